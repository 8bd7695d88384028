"""The periodic quintic spline kernels against SciPy's ``map_coordinates``."""

import numpy as np
import pytest
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
    with pytest.raises(ValueError, match="one length"):
        PeriodicQuintic.from_coefficients(coefficients).at(rows, cols[:-1])


@pytest.mark.parametrize(
    "matrix",
    [
        [[1.3, 0.0], [0.0, -0.7]],  # diagonal: lines contracted, columns' weights once
        [[0.0, -1.02], [0.98, 0.0]],  # anti-diagonal: columns contracted per row
        [[1.1, 0.4], [0.0, 0.9]],  # u_y fixed along a row, u_x not a column's alone
        [[0.02, -1.0], [1.0, -0.02]],  # general: point by point
    ],
)
def test_on_grid_is_the_spline_at_the_mapped_frequencies(matrix):
    """``on_grid`` at ``matrix @ (kx, ky)`` where a mask keeps the point, in the mask's order,
    times the axes' phases: the spline of :meth:`at` at those points (and SciPy's), to 1e-13
    of its scale, whichever of its paths the matrix takes; a grid that is not the spline's
    nodes, points across the edges."""
    rng = np.random.default_rng(6)
    coefficients = rng.normal(size=(36, 30)) + 1j * rng.normal(size=(36, 30))
    spline = PeriodicQuintic.from_coefficients(coefficients)
    kx, ky = rng.uniform(-45, 60, 19), rng.uniform(-50, 70, 25)
    keep = rng.uniform(size=(25, 19)) < 0.6
    phase_x = np.exp(1j * rng.uniform(0, 6, 19))
    phase_y = np.exp(1j * rng.uniform(0, 6, 25))
    matrix = np.array(matrix)
    fx, fy = np.meshgrid(kx, ky)
    ux, uy = matrix @ np.array([fx[keep], fy[keep]])
    ref = scipy_spline(coefficients, uy, ux)
    assert np.abs(spline.at(uy, ux) - ref).max() < 1e-13 * np.abs(ref).max()
    out = spline.on_grid(matrix, kx, ky, keep)
    assert out.shape == (keep.sum(),)
    assert np.abs(out - ref).max() < 1e-13 * np.abs(ref).max()
    phased = spline.on_grid(matrix, kx, ky, keep, phase_x, phase_y)
    expected = ref * np.multiply.outer(phase_y, phase_x)[keep]
    assert np.abs(phased - expected).max() < 1e-13 * np.abs(ref).max()
    # the kernel reads without bounds checks: mismatched axes are refused before it
    for bad in ((matrix, kx[:-1], ky), (matrix, kx, ky[1:]), (matrix[:1], kx, ky)):
        with pytest.raises(ValueError, match="on_grid"):
            spline.on_grid(*bad, keep)
    with pytest.raises(ValueError, match="on_grid"):
        spline.on_grid(matrix, kx, ky, keep, phase_x[:-1], phase_y)


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


@pytest.mark.parametrize("shape", [(16, 9), (9, 16), (15, 11), (12, 12)])
def test_the_half_spectrum_gives_the_whole_transforms_spline(shape):
    """A real image's ``rfft2`` completed by Hermitian symmetry is its whole ``fft2``: the
    same spline to 1e-15 of its scale, odd and even sides."""
    image = np.random.default_rng(7).normal(size=shape)
    half = PeriodicQuintic.from_half_spectrum(np.fft.rfft2(image), shape[1])
    whole = PeriodicQuintic.from_coefficients(np.fft.fft2(image))
    assert half.shape == whole.shape == shape
    assert np.abs(half.block - whole.block).max() < 1e-15 * np.abs(whole.block).max()
