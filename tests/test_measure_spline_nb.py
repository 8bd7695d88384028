"""The periodic quintic spline kernels against SciPy's ``map_coordinates``."""

import numpy as np
import scipy.ndimage

from megalut_cli.measure.spline_nb import PeriodicQuintic


def scipy_spline(coefficients: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """SciPy's evaluation of the same spline, one part at a time."""
    where = np.array([rows, cols])
    return sum(
        unit
        * scipy.ndimage.map_coordinates(part, where, order=5, mode="grid-wrap", prefilter=False)
        for unit, part in ((1.0, coefficients.real), (1j, coefficients.imag))
    )


def test_the_spline_is_scipys_at_any_point_wrapped_or_not():
    """Points inside the grid, across its edges and several periods away, a grid that is
    not square: the values agree to 1e-13 of their scale."""
    rng = np.random.default_rng(4)
    coefficients = rng.normal(size=(40, 52)) + 1j * rng.normal(size=(40, 52))
    rows = np.concatenate([rng.uniform(0, 40, 500), rng.uniform(-90, 130, 500), [0, 39.999, -2.5]])
    cols = np.concatenate([rng.uniform(0, 52, 500), rng.uniform(-110, 160, 500), [51.5, 0, -0.25]])
    out = PeriodicQuintic.from_coefficients(coefficients).at(rows, cols)
    ref = scipy_spline(coefficients, rows, cols)
    assert np.abs(out - ref).max() < 1e-13 * np.abs(ref).max()


def test_the_outer_form_is_the_spline_at_every_pair():
    """``outer`` on a set of rows and a set of columns (across the edges, not square) is the
    spline at each pair, as SciPy evaluates it, to 1e-13 of its scale."""
    rng = np.random.default_rng(5)
    coefficients = rng.normal(size=(36, 30)) + 1j * rng.normal(size=(36, 30))
    rows = np.concatenate([rng.uniform(-50, 80, 23), [0.0, 35.5]])
    cols = np.concatenate([rng.uniform(-40, 70, 17), [29.999, -0.5]])
    out = PeriodicQuintic.from_coefficients(coefficients).outer(rows, cols)
    r, c = np.meshgrid(rows, cols, indexing="ij")
    ref = scipy_spline(coefficients, r.ravel(), c.ravel()).reshape(r.shape)
    assert out.shape == (25, 19)
    assert np.abs(out - ref).max() < 1e-13 * np.abs(ref).max()


def test_the_spline_interpolates_its_samples():
    """Coefficients prefiltered from samples give the samples back at the nodes, and a
    band-limited function between them."""
    n = 64
    y, x = np.mgrid[0:n, 0:n]
    values = np.exp(2j * np.pi * (3 * x + 2 * y) / n)
    coefficients = scipy.ndimage.spline_filter(
        values.real, order=5, mode="grid-wrap"
    ) + 1j * scipy.ndimage.spline_filter(values.imag, order=5, mode="grid-wrap")
    spline = PeriodicQuintic.from_coefficients(coefficients)
    out = spline.at(y.ravel().astype(float), x.ravel().astype(float))
    assert np.abs(out - values.ravel()).max() < 1e-12
    rows, cols = np.array([10.3, 40.71]), np.array([5.5, 63.2])
    exact = np.exp(2j * np.pi * (3 * cols + 2 * rows) / n)
    assert np.abs(spline.at(rows, cols) - exact).max() < 1e-5
