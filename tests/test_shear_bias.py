"""The bias library: linear fit and its errors, case means, PSF-frame rotation, Q_c, bins."""

from __future__ import annotations

import math

import numpy as np
import pytest

from megalut_cli.shear.bias import (
    GREAT3_ETA,
    case_means,
    fit_bias,
    psf_angle,
    q_c,
    rotate_to_psf_frame,
)
from megalut_cli.shear.conditional import assign_bins, equal_population_edges


def test_fit_exact_line():
    g = np.linspace(-0.1, 0.1, 11)
    fit = fit_bias(g, (1 + 0.02) * g - 3e-4)
    assert fit.m == pytest.approx(0.02, abs=1e-12)
    assert fit.c == pytest.approx(-3e-4, abs=1e-14)
    assert fit.m_err < 1e-12 and fit.c_err < 1e-12
    assert fit.n_cases == 11


def test_fit_errors_follow_ols_formula():
    """Errors are the OLS ones from the residual scatter with N - 2 degrees of freedom."""
    rng = np.random.default_rng(3)
    g = rng.uniform(-0.1, 0.1, 40)
    y = 0.01 * g + 1e-3 + rng.normal(0, 1e-3, g.size)
    fit = fit_bias(g, g + y)
    X = np.column_stack([g, np.ones_like(g)])
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    s2 = np.sum((y - X @ coef) ** 2) / (g.size - 2)
    cov = s2 * np.linalg.inv(X.T @ X)
    assert fit.m == pytest.approx(coef[0], rel=1e-10)
    assert fit.c == pytest.approx(coef[1], rel=1e-10)
    assert fit.m_err == pytest.approx(math.sqrt(cov[0, 0]), rel=1e-8)
    assert fit.c_err == pytest.approx(math.sqrt(cov[1, 1]), rel=1e-8)


def test_fit_degenerate_inputs_are_nan():
    assert math.isnan(fit_bias([0.01], [0.02]).m)
    const = fit_bias([0.05, 0.05, 0.05], [0.04, 0.06, 0.05])
    assert math.isnan(const.m) and math.isnan(const.c)
    two = fit_bias([0.0, 0.1], [0.001, 0.102])
    assert two.m == pytest.approx(0.01) and math.isnan(two.m_err)
    assert fit_bias([0.0, 0.1], [0.001, 0.102]).as_dict()["m_err"] is None


def test_case_means_weights_and_nan():
    case = np.array([5, 5, 5, 7, 7, 9])
    vals = np.array([1.0, 3.0, np.nan, 2.0, 100.0, 4.0])
    w = np.array([1.0, 3.0, 1.0, 1.0, 0.0, 0.0])
    ids, means, sw, n = case_means(case, vals, w)
    assert ids.tolist() == [5, 7, 9]
    assert means[0] == pytest.approx(2.5) and means[1] == 2.0 and np.isnan(means[2])
    assert n.tolist() == [2, 1, 0]
    assert sw.tolist() == [4.0, 1.0, 0.0]


def test_rotation_puts_psf_ellipticity_on_plus_axis():
    rng = np.random.default_rng(1)
    e1, e2 = rng.uniform(-0.2, 0.2, (2, 100))
    plus, cross = rotate_to_psf_frame(e1, e2, e1, e2)
    np.testing.assert_allclose(plus, np.hypot(e1, e2), atol=1e-15)
    np.testing.assert_allclose(cross, 0.0, atol=1e-15)
    # A PSF along the pixel x axis leaves components unchanged; along the diagonal swaps them.
    assert rotate_to_psf_frame(0.03, -0.01, 0.1, 0.0) == pytest.approx((0.03, -0.01))
    assert rotate_to_psf_frame(0.03, -0.01, 0.0, 0.1) == pytest.approx((-0.01, -0.03))
    assert psf_angle(0.0, 0.1) == pytest.approx(np.pi / 4)


def test_q_c_great3_values():
    assert q_c(0, 0, 0, 0) == pytest.approx(2000 * GREAT3_ETA / 2)  # sigma2_min = 4
    assert q_c(2e-3, 0, 0, 0) == pytest.approx(2000 * 1.232 / math.sqrt(5))
    assert q_c(0, 2e-4, 0, 2e-4, sigma2_min=1.0) == pytest.approx(2000 * 1.232 / math.sqrt(3))
    assert math.isnan(q_c(float("nan"), 0, 0, 0))


def test_equal_population_bins():
    rng = np.random.default_rng(0)
    v = rng.lognormal(size=10_000)
    edges = equal_population_edges(v, 5)
    counts = np.bincount(assign_bins(v, edges), minlength=5)
    assert counts.sum() == v.size and counts.min() >= 1999 and counts.max() <= 2001
    idx = assign_bins(np.array([np.nan, -1.0, edges[-1]]), edges)
    assert idx.tolist() == [-1, -1, 4]
    # Tied values (a per-case parameter with 3 values) merge into fewer bins.
    tied = np.repeat([1.0, 2.0, 4.0], 100)
    assert equal_population_edges(tied, 5).size - 1 <= 3
