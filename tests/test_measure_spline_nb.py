"""The periodic quintic spline kernel against SciPy's ``map_coordinates``."""

import numpy as np
import scipy.ndimage

from megalut_cli.measure.spline_nb import quintic_wrap


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
    out = np.empty(len(rows), dtype=np.complex128)
    quintic_wrap(coefficients, rows, cols, out)
    ref = scipy_spline(coefficients, rows, cols)
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
    out = np.empty(n * n, dtype=np.complex128)
    quintic_wrap(coefficients, y.ravel().astype(float), x.ravel().astype(float), out)
    assert np.abs(out - values.ravel()).max() < 1e-12
    rows, cols = np.array([10.3, 40.71]), np.array([5.5, 63.2])
    between = np.empty(2, dtype=np.complex128)
    quintic_wrap(coefficients, rows, cols, between)
    exact = np.exp(2j * np.pi * (3 * cols + 2 * rows) / n)
    assert np.abs(between - exact).max() < 1e-5
