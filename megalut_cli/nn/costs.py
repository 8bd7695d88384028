"""Cost functions of the paper with their analytic derivatives, on cases x realizations.

Data are handled in a compact form: only the valid (unmasked) realizations are kept, one row
each, with ``case`` giving the index (0..n_cases-1) of the case of every row (an array, or a
prepared :class:`Groups`) and ``n`` the number of valid rows of each case. Masked
realizations (failed measurements, padding of unequal case sizes, rows outside a selection)
simply are not there. Each function returns
``(cost, d cost / d output)`` with the derivative per row, so that a network's backward pass
turns it into the parameter gradient.

- MSE (Eq. 4): mean over cases of the mean over realizations of (o - t)^2;
- MSB (Eq. 3): mean over cases of (mean over realizations of o - t)^2;
- MSWB (Eq. 5): mean over cases of (sum w o / sum w - t)^2, derivative w.r.t. the weights w.

:func:`padded_cost` evaluates the same equations literally on padded
``(n_cases, n_rea)`` arrays with a boolean mask, as a reference.
"""

from __future__ import annotations

import numpy as np

COSTS = ("mse", "msb", "mswb")


class Groups:
    """Rows grouped into cases: sums over the rows of each case and per-case values per row.

    When the rows of each case are contiguous and in case order (as :class:`CaseData`
    stores them) the fast ``reduceat``/``repeat`` path is used; otherwise ``bincount``.
    """

    def __init__(self, case: np.ndarray, n_cases: int | None = None) -> None:
        self.case = np.asarray(case, dtype=np.intp)
        self.n_cases = int(
            n_cases if n_cases is not None else (self.case.max() + 1 if len(self.case) else 0)
        )
        self.counts = np.bincount(self.case, minlength=self.n_cases)
        self.n = self.counts.astype(np.float64)
        self.contiguous = bool(np.all(self.counts > 0)) and bool(np.all(np.diff(self.case) >= 0))
        self.starts = np.concatenate([[0], np.cumsum(self.counts)[:-1]]).astype(np.intp)

    def sum(self, values: np.ndarray) -> np.ndarray:
        """Sum of ``values`` (one per row) over the rows of each case, in float64."""
        if self.contiguous:
            return np.add.reduceat(np.asarray(values, dtype=np.float64), self.starts)
        return np.bincount(self.case, weights=values, minlength=self.n_cases)

    def expand(self, per_case: np.ndarray) -> np.ndarray:
        """The value of its case for every row."""
        if self.contiguous:
            return np.repeat(per_case, self.counts)
        return per_case[self.case]


def _groups(case: np.ndarray | Groups, n: np.ndarray) -> Groups:
    return case if isinstance(case, Groups) else Groups(case, len(n))


def mse(
    o: np.ndarray, case: np.ndarray | Groups, n: np.ndarray, t_row: np.ndarray
) -> tuple[float, np.ndarray]:
    """Mean square error (Eq. 4); ``t_row`` is the target of each row."""
    grp = _groups(case, n)
    c = len(n)
    d = o - t_row
    inv = 1.0 / (c * n)
    cost = float(grp.sum(d * d) @ inv)
    return cost, 2.0 * d * grp.expand(inv)


def msb(
    o: np.ndarray, case: np.ndarray | Groups, n: np.ndarray, t: np.ndarray
) -> tuple[float, np.ndarray]:
    """Mean square bias (Eq. 3); ``t`` is the target of each case."""
    grp = _groups(case, n)
    c = len(n)
    r = grp.sum(o) / n - t
    cost = float(r @ r) / c
    return cost, grp.expand(2.0 * r / (c * n))


def msb_value(o: np.ndarray, case: np.ndarray | Groups, n: np.ndarray, t: np.ndarray) -> float:
    """:func:`msb` without the derivative (the same number)."""
    r = _groups(case, n).sum(o) / n - t
    return float(r @ r) / len(n)


def mswb(
    w: np.ndarray, o: np.ndarray, case: np.ndarray | Groups, n: np.ndarray, t: np.ndarray
) -> tuple[float, np.ndarray]:
    """Mean square weighted bias (Eq. 5) of point estimates ``o`` weighted by ``w``.

    The derivative is with respect to the weights ``w`` (the point estimates are fixed).
    """
    grp = _groups(case, n)
    c = len(n)
    wsum = np.maximum(grp.sum(w), np.finfo(float).tiny)  # sigmoid weights are > 0; guard underflow
    m = grp.sum(w * o) / wsum
    r = m - t
    cost = float(r @ r) / c
    return cost, grp.expand(2.0 * r / (c * wsum)) * (o - grp.expand(m))


def padded_cost(
    name: str,
    out: np.ndarray,
    mask: np.ndarray,
    t: np.ndarray,
    point: np.ndarray | None = None,
) -> float:
    """Reference: a cost evaluated literally on padded ``(n_cases, n_rea)`` arrays.

    ``mask`` is True for valid realizations; ``t`` holds one target per case (or one per
    realization for MSE). For MSWB ``out`` are the weights and ``point`` the point estimates.
    """
    mask = np.asarray(mask, bool)
    out = np.where(mask, out, 0.0)
    n = mask.sum(axis=1)
    if name == "mse":
        tt = np.broadcast_to(t[:, None] if np.ndim(t) == 1 else t, out.shape)
        return float(np.mean(np.sum(np.where(mask, (out - tt) ** 2, 0.0), axis=1) / n))
    if name == "msb":
        return float(np.mean((out.sum(axis=1) / n - t) ** 2))
    if name == "mswb":
        if point is None:
            raise ValueError("MSWB needs the point estimates")
        p = np.where(mask, point, 0.0)
        return float(np.mean(((out * p).sum(axis=1) / out.sum(axis=1) - t) ** 2))
    raise ValueError(f"unknown cost {name!r}")
