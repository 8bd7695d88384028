"""Bootstrap over galaxies: resample realization groups, recompute per-case sums.

In a common-random-number set (``structure.common``) realization group ``g`` (a galaxy:
one realization, or a 90-degree pair) is the same galaxy in every case, so cases are not
independent and the OLS errors of a fit over cases are wrong. The bootstrap draws groups
with replacement (each group with all its rows, in all cases together) and recomputes the
per-case sums; the spread of the refitted ``m`` and ``c`` is their error.

The sums of each (key, group) entry are held in one sparse matrix ``(names x keys, groups)``
so that a block of resamples is one sparse-dense product with the count matrix.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import scipy.sparse

from megalut_cli.seeding import STREAM_BOOTSTRAP, rng_for

#: Name of the error model in ``megalut evaluate`` results.
ERROR_BOOTSTRAP = "bootstrap-galaxies"
ERROR_FIT = "fit"
#: How the bootstrap's errors get the part of the drawn shears (:func:`shear_draw_variance`).
SHEAR_TERM = "excess-residuals"
#: Largest count matrix of one block of resamples (groups x resamples entries).
BLOCK_ENTRIES = 2**24


def group_size_for(snc: str | None, n_realizations: int | None, antithetic: bool = False) -> int:
    """Realizations per galaxy group of a simulated set: 2 for ``pairs``, all of a case for
    ``ring``, else 1; twice that with ``antithetic`` twins (but for ``ring``)."""
    if snc == "ring" and n_realizations:
        return int(n_realizations)
    return (2 if snc == "pairs" else 1) * (2 if antithetic else 1)


def resample_counts(
    seed: int, n_groups: int, n_resamples: int, stream: int = STREAM_BOOTSTRAP
) -> list[np.ndarray]:
    """Multiplicities of the groups in each resample, as ``(n_groups, b)`` blocks.

    Resample ``r`` draws ``n_groups`` groups uniformly with replacement from the generator
    of ``seed`` and ``stream`` (the same sequence whatever the block size)."""
    rng = rng_for(seed, stream)
    per_block = max(1, min(n_resamples, BLOCK_ENTRIES // max(n_groups, 1)))
    blocks = []
    for start in range(0, n_resamples, per_block):
        b = min(per_block, n_resamples - start)
        counts = np.empty((n_groups, b))
        for j in range(b):
            counts[:, j] = np.bincount(rng.integers(0, n_groups, n_groups), minlength=n_groups)
        blocks.append(counts)
    return blocks


class GroupResampler:
    """Per-key sums of entry values under resampled group multiplicities.

    ``key_index[e]`` (``0..n_keys-1``) and ``group[e]`` (``0..n_groups-1``) place entry
    ``e``; ``values[name][e]`` is its sum of ``name`` (e.g. the weighted estimates of one
    galaxy group in one case).
    """

    def __init__(
        self,
        key_index: np.ndarray,
        group: np.ndarray,
        values: Mapping[str, np.ndarray],
        n_keys: int,
        n_groups: int,
    ):
        self.names = list(values)
        self.n_keys = int(n_keys)
        key_index = np.asarray(key_index, dtype=np.int64)
        group = np.asarray(group, dtype=np.int64)
        rows = np.concatenate([i * self.n_keys + key_index for i in range(len(self.names))])
        cols = np.tile(group, len(self.names))
        data = np.concatenate([np.asarray(values[k], dtype=float) for k in self.names])
        self.matrix = scipy.sparse.csr_matrix(
            (data, (rows, cols)), shape=(len(self.names) * self.n_keys, int(n_groups))
        )

    def sums(self, counts: np.ndarray) -> dict[str, np.ndarray]:
        """Per-key sums ``{name: (n_keys, b)}`` for the ``b`` resamples of
        ``counts`` (n_groups, b)."""
        total = np.asarray(self.matrix @ counts)
        return {k: total[i * self.n_keys : (i + 1) * self.n_keys] for i, k in enumerate(self.names)}


def fit_columns(g_true: np.ndarray, g_est: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``m, c`` of :func:`megalut_cli.shear.bias.fit_bias` for every column of ``(cases, b)``
    arrays at once (non-finite pairs left out; NaN without two cases or a lever arm)."""
    x = np.asarray(g_true, dtype=float)
    y = np.asarray(g_est, dtype=float) - x
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = np.where(ok, x, 0.0), np.where(ok, y, 0.0)
    n = ok.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        xm, ym = x.sum(axis=0) / n, y.sum(axis=0) / n
        dx = np.where(ok, x - xm, 0.0)
        sxx = (dx * dx).sum(axis=0)
        m = (dx * (y - ym)).sum(axis=0) / sxx
        c = ym - m * xm
        span = np.where(ok, x, -np.inf).max(axis=0) - np.where(ok, x, np.inf).min(axis=0)
        scale = np.where(ok, np.abs(x), 0.0).max(axis=0)
    bad = (n < 2) | ~(span > 1e-12 + 1e-9 * scale)
    return np.where(bad, np.nan, m), np.where(bad, np.nan, c)


def residuals(g_true: np.ndarray, g_est: np.ndarray, m: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Residuals ``(g_est - g_true) - (m g_true + c)`` of per-case averages ``(cases, b)``
    about the fitted lines of ``m, c`` (one per column)."""
    return (np.asarray(g_est, float) - np.asarray(g_true, float)) - (
        np.asarray(m, float) * np.asarray(g_true, float) + np.asarray(c, float)
    )


class ResidualMoments:
    """Running mean and variance, per case, of the residuals of the resampled fits: how much
    of each case's residual the galaxies alone explain."""

    def __init__(self) -> None:
        self.n: np.ndarray | None = None
        self.s1: np.ndarray | None = None
        self.s2: np.ndarray | None = None

    def add(self, r: np.ndarray) -> None:
        """Add the residuals ``(cases, b)`` of ``b`` resamples (NaN: a case left out)."""
        ok = np.isfinite(r)
        v = np.where(ok, r, 0.0)
        n, s1, s2 = ok.sum(axis=1), v.sum(axis=1), (v * v).sum(axis=1)
        if self.n is None:
            self.n, self.s1, self.s2 = n, s1, s2
        else:
            self.n, self.s1, self.s2 = self.n + n, self.s1 + s1, self.s2 + s2

    def variance(self) -> np.ndarray:
        """Per-case variance (ddof = 1) of the residuals over the resamples."""
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = self.s1 / self.n
            return (self.s2 - self.n * mean * mean) / (self.n - 1)


def shear_draw_variance(
    g_true: np.ndarray, g_est: np.ndarray, m: float, c: float, galaxy_variance: np.ndarray
) -> tuple[float, float]:
    """Variances of ``m`` and ``c`` from a response that varies from one drawn shear to
    another, which a bootstrap over galaxies holding the cases fixed does not see.

    Model: each case adds ``mu_k g_k`` to its average, ``mu_k`` independent with variance
    ``tau^2``. The OLS residuals then have ``E[sum r_k^2] = tau^2 sum (1 - h_k) g_k^2`` plus
    their galaxy part, whose variance ``galaxy_variance`` the bootstrap gives (``h_k``: the
    case's leverage), so ``tau^2 = sum(r_k^2 - galaxy_variance_k) / sum((1 - h_k) g_k^2)``,
    clipped at 0, and propagated through the OLS weights of ``m`` and ``c``. NaN with fewer
    than three usable cases (an exact fit has no residual)."""
    x = np.asarray(g_true, float)
    y = np.asarray(g_est, float) - x
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(galaxy_variance)
    k = int(ok.sum())
    if k < 3 or not (math.isfinite(m) and math.isfinite(c)):
        return float("nan"), float("nan")
    x, y, gv = x[ok], y[ok], np.asarray(galaxy_variance, float)[ok]
    dx = x - x.mean()
    sxx = float(dx @ dx)
    w_m = dx / sxx
    w_c = 1.0 / k - x.mean() * w_m
    h = 1.0 / k + dx * dx / sxx
    r = y - (m * x + c)
    tau2 = max(0.0, float((r * r - gv).sum()) / float(((1.0 - h) * x * x).sum()))
    return tau2 * float(w_m * w_m @ (x * x)), tau2 * float(w_c * w_c @ (x * x))


def spread(values: Sequence[float]) -> float:
    """Standard deviation (ddof = 1) of the finite resampled values; NaN when fewer than
    half of them are finite (the statistic is too often undefined to trust its spread)."""
    v = np.asarray(values, dtype=float)
    ok = np.isfinite(v)
    if ok.sum() < max(2, v.size // 2):
        return float("nan")
    return float(np.std(v[ok], ddof=1))
