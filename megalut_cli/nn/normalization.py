"""Input normalisation fitted on the training data and stored with the model.

``minmax`` (the paper, Sect. 3.4): each feature is shifted and scaled so that the training
data cover exactly [-1, 1]. ``robust``: the central 98 % (1st to 99th percentile) is mapped
to [-1, 1], so that a few outliers (a wild ``adamom_flux``) do not squeeze all other values
into a tiny interval; rare values beyond simply land a little outside [-1, 1].
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

log = logging.getLogger(__name__)

METHODS = ("minmax", "robust")


def fit(
    x: np.ndarray, method: str = "minmax", names: Sequence[str] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``(loc, scale)`` per column of ``x`` (rows x features, finite values only)."""
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] == 0:
        raise ValueError("normalisation needs a non-empty (rows x features) array")
    if method == "minmax":
        lo, hi = column_extremes(x)
    elif method == "robust":
        lo, hi = np.percentile(x, [1.0, 99.0], axis=0)
    else:
        raise ValueError(f"unknown normalisation {method!r} (choose from {', '.join(METHODS)})")
    loc = 0.5 * (lo + hi)
    scale = 0.5 * (hi - lo)
    flat = ~(scale > 0)
    if np.any(flat):
        names = list(names) if names is not None else [str(i) for i in range(x.shape[1])]
        log.warning(
            "feature(s) %s constant in the training data: scale set to 1",
            ", ".join(n for n, f in zip(names, flat) if f),
        )
        scale = np.where(flat, 1.0, scale)
    return loc, scale


def column_extremes(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(x.min(axis=0), x.max(axis=0))`` of a rows x features array, column by column (on
    C-ordered rows numpy's axis-0 reduction is 10 times slower). The numbers are the same
    element either way, except that of a zero or a NaN, whose sign or payload may depend on
    the order of the comparisons: numpy's axis-0 reduction then."""
    lo = np.array([x[:, k].min() for k in range(x.shape[1])], dtype=x.dtype)
    hi = np.array([x[:, k].max() for k in range(x.shape[1])], dtype=x.dtype)
    if not (
        np.all(lo != 0) and np.all(hi != 0) and np.isfinite(lo).all() and np.isfinite(hi).all()
    ):
        return x.min(axis=0), x.max(axis=0)
    return lo, hi


def apply(x: np.ndarray, loc: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Normalised copy of ``x`` (rows x features)."""
    return (np.asarray(x, dtype=np.float64) - loc) / scale
