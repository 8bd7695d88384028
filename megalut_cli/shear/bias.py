"""The linear shear-bias model (Tewes et al. 2019, Eq. 2), the PSF frame and GREAT3's ``Q_c``.

Biases are measured on *cases* (sets of realizations sharing one true shear): the
estimates of each case are averaged (unweighted, or weighted by the predicted weights),
and a straight line is fitted to the residuals ``<g_est>_i - g_i`` against ``g_i``::

    <g_est>_i - g_i = m_i * g_i + c_i

Error model: ordinary least squares over cases, every case with the same weight (as in
the paper, Sect. 6: an *unweighted* regression on the weighted per-case averages, so that
cases are not weighted against each other); the 1-sigma errors of ``m`` and ``c`` come
from the scatter of the residuals about the line (``s^2 = sum(r^2) / (N - 2)``, the
usual OLS covariance ``s^2 (X^T X)^-1``, as ``scipy.stats.linregress`` gives them). The
quoted errors therefore reflect the scatter actually present in the data (shape noise,
pixel noise, anything else), with no assumption about per-galaxy errors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

#: Stage IV requirements on the multiplicative and additive biases (Massey et al. 2013).
STAGE_IV_M = 2e-3
STAGE_IV_C = 2e-4

#: GREAT3 constant-shear metric (Mandelbaum et al. 2015; constants of great3-public's evaluate.py):
#: normalisation, damping terms (ground and space branches), and target biases.
GREAT3_ETA = 1.232
GREAT3_SIGMA2_MIN_GROUND = 4.0
GREAT3_SIGMA2_MIN_SPACE = 1.0
GREAT3_M_TARGET = 2e-3
GREAT3_C_TARGET = 2e-4


def _json_float(x: float) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


@dataclass(frozen=True)
class BiasFit:
    """Result of one linear fit: ``m``, ``c`` with 1-sigma errors, and what went into it.

    Values that cannot be determined (too few cases, no spread in the true shear) are NaN.
    """

    m: float
    m_err: float
    c: float
    c_err: float
    n_cases: int
    n_rows: int
    #: With bootstrap errors: the parts of ``m_err`` and ``c_err`` (galaxies, drawn shears)
    #: as ``(m_galaxies, m_shears, c_galaxies, c_shears)``, added in quadrature.
    error_parts: tuple[float, float, float, float] | None = None

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready dict with keys ``m, m_err, c, c_err, n_cases, n_rows`` (NaN as None),
        plus ``m_err_galaxies, m_err_shears, c_err_galaxies, c_err_shears`` with bootstrap
        errors."""
        out = {
            "m": _json_float(self.m),
            "m_err": _json_float(self.m_err),
            "c": _json_float(self.c),
            "c_err": _json_float(self.c_err),
            "n_cases": int(self.n_cases),
            "n_rows": int(self.n_rows),
        }
        if self.error_parts is not None:
            names = ("m_err_galaxies", "m_err_shears", "c_err_galaxies", "c_err_shears")
            out.update({k: _json_float(v) for k, v in zip(names, self.error_parts)})
        return out

    def meets(self, m_tol: float = STAGE_IV_M, c_tol: float = STAGE_IV_C) -> bool:
        """Whether ``|m| < m_tol`` and ``|c| < c_tol`` (False when either is undetermined)."""
        return bool(abs(self.m) < m_tol and abs(self.c) < c_tol)


def stage_iv_requirement(
    fits: dict[str, tuple[float | None, float | None]], scheme: str, undetermined: str = "fails"
) -> dict[str, Any]:
    """Whether the m, c of each component (``{comp: (m, c)}``, of ``scheme``) meet the
    Stage IV requirement, with the failures as lines; a value that is None or not finite
    fails (``undetermined = "fails"``) or is not judged (``"skip"``: an m without lever arm)."""
    failures = []
    for comp, (m, c) in fits.items():
        known = {k: v for k, v in (("m", m), ("c", c)) if v is not None and math.isfinite(v)}
        if len(known) < 2 and undetermined == "fails":
            failures.append(f"{comp}: m, c undetermined")
            continue
        for key, limit in (("m", STAGE_IV_M), ("c", STAGE_IV_C)):
            if key in known and abs(known[key]) >= limit:
                failures.append(f"{comp}: |{key}| = {abs(known[key]):.2e}")
    return {
        "m": STAGE_IV_M,
        "c": STAGE_IV_C,
        "applies_to": scheme,
        "met": not failures,
        "failures": failures,
    }


def fit_bias(g_true: np.ndarray, g_est: np.ndarray, n_rows: int = 0) -> BiasFit:
    """Fit ``g_est - g_true = m g_true + c`` by ordinary least squares over cases.

    ``g_true`` and ``g_est`` hold one (average) value per case; non-finite pairs are
    ignored. Errors come from the residual scatter (``N - 2`` degrees of freedom), so
    they are NaN for exactly two cases; with fewer than two cases, or a true shear
    without spread, everything is NaN.
    """
    x = np.asarray(g_true, dtype=float)
    y = np.asarray(g_est, dtype=float) - x
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    n = int(x.size)
    nan = float("nan")
    if n < 2 or np.ptp(x) <= 1e-12 + 1e-9 * float(np.max(np.abs(x))):  # no lever arm
        return BiasFit(nan, nan, nan, nan, n, n_rows)
    if n == 2:
        m = (y[1] - y[0]) / (x[1] - x[0])
        return BiasFit(float(m), nan, float(y[0] - m * x[0]), nan, n, n_rows)
    # Centred OLS; the errors use the residuals themselves (not 1 - r^2), exact for tiny scatter.
    xm, ym = x.mean(), y.mean()
    dx = x - xm
    sxx = float(dx @ dx)
    m = float(dx @ (y - ym)) / sxx
    c = float(ym - m * xm)
    r = y - (m * x + c)
    s2 = float(r @ r) / (n - 2)
    return BiasFit(m, math.sqrt(s2 / sxx), c, math.sqrt(s2 * (1.0 / n + xm * xm / sxx)), n, n_rows)


def case_means(
    case: np.ndarray, values: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-case (weighted) means of ``values``.

    Rows with a non-finite value, or a weight that is zero or not finite, do not count.
    Returns ``(case_ids, means, sum_of_weights, n_rows)``, one entry per case id present;
    cases without any counted row have a NaN mean.
    """
    case = np.asarray(case)
    values = np.asarray(values, dtype=float)
    w = np.ones_like(values) if weights is None else np.asarray(weights, dtype=float)
    use = np.isfinite(values) & np.isfinite(w) & (w > 0)
    w = np.where(use, w, 0.0)
    ids, idx = np.unique(case, return_inverse=True)
    idx = idx.ravel()
    sw = np.bincount(idx, weights=w, minlength=ids.size)
    swv = np.bincount(idx, weights=np.where(use, w * values, 0.0), minlength=ids.size)
    nrows = np.bincount(idx, weights=use, minlength=ids.size).astype(np.int64)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.where(sw > 0, swv / sw, np.nan)
    return ids, means, sw, nrows


def psf_angle(psf_g1: np.ndarray, psf_g2: np.ndarray) -> np.ndarray:
    """Position angle ``theta = 0.5 atan2(g2, g1)`` of the PSF anisotropy (radians)."""
    return 0.5 * np.arctan2(np.asarray(psf_g2, dtype=float), np.asarray(psf_g1, dtype=float))


def rotate_to_psf_frame(
    g1: np.ndarray, g2: np.ndarray, psf_g1: np.ndarray, psf_g2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Components ``(g_plus, g_cross)`` of the spin-2 quantity ``(g1, g2)`` in the PSF frame.

    ``(g1, g2)`` is rotated by ``-2 theta`` with ``theta`` the PSF position angle (GREAT3,
    paper Sect. 2.2): ``g_plus`` is along the PSF anisotropy, ``g_cross`` at 45 degrees.
    """
    return rotate_spin2(g1, g2, psf_angle(psf_g1, psf_g2))


def calibrate_by_response(
    r11: Any, r12: Any, r21: Any, r22: Any, g1: np.ndarray, g2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``R^-1 (g1, g2)`` for the response matrix ``R = [[r11, r12], [r21, r22]]`` (metacal;
    entries broadcast against the estimates; NaN where R is singular)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        det = r11 * r22 - r12 * r21
        return (r22 * g1 - r12 * g2) / det, (r11 * g2 - r21 * g1) / det


def rotate_spin2(
    g1: np.ndarray, g2: np.ndarray, theta: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(g1, g2)`` in the frame turned by the angle ``theta`` (radians): rotated by
    ``-2 theta``."""
    cos2, sin2 = np.cos(2.0 * theta), np.sin(2.0 * theta)
    g1 = np.asarray(g1, dtype=float)
    g2 = np.asarray(g2, dtype=float)
    return g1 * cos2 + g2 * sin2, -g1 * sin2 + g2 * cos2


def q_c(
    m_plus: float,
    c_plus: float,
    m_cross: float,
    c_cross: float,
    *,
    sigma2_min: float = GREAT3_SIGMA2_MIN_GROUND,
    eta: float = GREAT3_ETA,
    m_target: float = GREAT3_M_TARGET,
    c_target: float = GREAT3_C_TARGET,
) -> float:
    """GREAT3 constant-shear quality factor (Mandelbaum et al. 2015)::

        Q_c = 2000 eta / sqrt(sigma2_min + sum_{i=+,x} [(m_i/m_target)^2 + (c_i/c_target)^2])

    with ``eta = 1.232``, ``m_target = 2e-3``, ``c_target = 2e-4`` and ``sigma2_min = 4``
    for ground branches (1 for space branches: :data:`GREAT3_SIGMA2_MIN_SPACE`). Higher is
    better; NaN if any bias is undetermined.
    """
    total = sigma2_min + (m_plus / m_target) ** 2 + (m_cross / m_target) ** 2
    total += (c_plus / c_target) ** 2 + (c_cross / c_target) ** 2
    return float(2000.0 * eta / math.sqrt(total)) if math.isfinite(total) else float("nan")
