"""A noise image's correlation and spectrum (``measure/noise_correlation.py``), and the moving
fixnoise it colours: in every metacal version, the power of metacal's own fixnoise (the
noise image rotated, through the operation, rotated back), shear direction included."""

from __future__ import annotations

import galsim
import numpy as np
import pytest
import scipy.signal

from megalut_cli.measure.cell_detect import cell_operation
from megalut_cli.measure.cell_metacal import cell_versions
from megalut_cli.measure.metacal_defaults import TYPES
from megalut_cli.measure.noise_correlation import (
    MAX_LAG,
    noise_correlation,
    spectrum_at,
    spectrum_on_grid,
)

#: An anisotropic colouring kernel: noise correlated along x more than along y.
KERNEL = np.array([[0.0, 0.3, 0.0], [0.6, 1.0, 0.6], [0.0, 0.3, 0.0]])
PSF_IMAGE = (
    galsim.Convolve(galsim.Gaussian(fwhm=3.6), galsim.Pixel(1.0))
    .drawImage(nx=32, ny=32, scale=1.0, method="no_pixel")
    .array
)
STEP = 0.01


def coloured_noise(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    white = rng.normal(0.0, 1.0, (shape[0] + 2, shape[1] + 2))
    return scipy.signal.convolve2d(white, KERNEL, mode="valid")


def true_correlation() -> np.ndarray:
    """The correlation of :func:`coloured_noise` at the lags -MAX_LAG..MAX_LAG."""
    full = scipy.signal.convolve2d(KERNEL, KERNEL[::-1, ::-1])  # 5 x 5, lag 0 at [2, 2]
    out = np.zeros((2 * MAX_LAG + 1, 2 * MAX_LAG + 1))
    out[MAX_LAG - 2 : MAX_LAG + 3, MAX_LAG - 2 : MAX_LAG + 3] = full
    return out


def test_the_correlation_of_a_noise_image_with_masked_pixels():
    """Lags within 0.02 of the truth (|lag 0| = 2.62) on a 400-px image with a fifth of its
    pixels masked (set to 0), none beyond the kernel's reach."""
    rng = np.random.default_rng(1)
    field = coloured_noise(rng, (400, 400))
    bad = rng.random(field.shape) < 0.2
    estimate = noise_correlation(np.where(bad, 0.0, field), bad)
    np.testing.assert_allclose(estimate, true_correlation(), atol=0.03)
    assert estimate[MAX_LAG, MAX_LAG] == pytest.approx(true_correlation()[MAX_LAG, MAX_LAG], 0.02)


def test_the_spectrum_on_a_grid_and_at_any_frequency_agree():
    correlation = true_correlation()
    grid = 48
    k = 2 * np.pi * np.fft.fftfreq(grid)
    kx, ky = np.meshgrid(k, k)
    np.testing.assert_allclose(
        spectrum_on_grid(correlation, grid), spectrum_at(correlation, kx, ky), atol=1e-12
    )
    # the kernel's transform squared
    kt = np.fft.fft2(KERNEL, s=(grid, grid))
    np.testing.assert_allclose(spectrum_at(correlation, kx, ky), np.abs(kt) ** 2, atol=1e-12)


def quadrupoles(fields: list[np.ndarray]) -> tuple[float, float]:
    """The power-weighted ``<cos 2 phi>`` and ``<sin 2 phi>`` of the fields' mean periodogram
    (frequencies below 2 radians per pixel)."""
    power = np.mean([np.abs(np.fft.fft2(f)) ** 2 for f in fields], axis=0)
    k = 2 * np.pi * np.fft.fftfreq(fields[0].shape[0])
    kx, ky = np.meshgrid(k, k)
    k2 = kx * kx + ky * ky
    band = (k2 < 4.0) & (k2 > 0)
    p = power[band]
    return (
        float((p * (kx * kx - ky * ky)[band] / k2[band]).sum() / p.sum()),
        float((p * (2 * kx * ky)[band] / k2[band]).sum() / p.sum()),
    )


def test_the_coloured_moving_fixnoise_has_metacal_s_power_in_every_version():
    """30 noise cells of 128 px: each version's coloured moving fixnoise (unit white noise)
    has the mean power of metacal's rotated fixnoise of the noise images (the total within
    3 %), and the same quadrupole: their version-to-version changes, which are the noise's
    shear the fixnoise must undo (-0.031 from noshear to 1p here), agree within 0.002
    (measured: 0.001); the colour left unsheared is 0.008 off, sheared the wrong way 0.017."""
    rng = np.random.default_rng(3)
    size, n = 128, 30
    correlation = noise_correlation(coloured_noise(rng, (512, 512)))
    zeros = np.zeros((size, size))
    moving: dict[str, list[np.ndarray]] = {k: [] for k in TYPES}
    rotated: dict[str, list[np.ndarray]] = {k: [] for k in TYPES}
    for _ in range(n):
        white = rng.normal(0.0, 1.0, (size, size))
        new, _ = cell_versions(
            zeros, PSF_IMAGE, STEP, "gauss", moving_field=white, moving_correlation=correlation
        )
        ref, _ = cell_versions(
            zeros, PSF_IMAGE, STEP, "gauss", rotated_field=coloured_noise(rng, (size, size))
        )
        for kind in TYPES:
            moving[kind].append(new[kind][16:-16, 16:-16])
            rotated[kind].append(ref[kind][16:-16, 16:-16])
    q = {k: (quadrupoles(moving[k]), quadrupoles(rotated[k])) for k in TYPES}
    for kind in TYPES:
        assert np.mean(np.square(moving[kind])) == pytest.approx(
            np.mean(np.square(rotated[kind])), rel=0.03
        ), kind
        for c in (0, 1):
            change_moving = q[kind][0][c] - q["noshear"][0][c]
            change_rotated = q[kind][1][c] - q["noshear"][1][c]
            assert change_moving == pytest.approx(change_rotated, abs=0.002), (kind, c)
    assert abs(q["1p"][1][0] - q["noshear"][1][0]) > 0.005  # the test can see a shear


def test_the_coloured_moving_fixnoise_of_both_engines_is_one_field():
    """The same unit white field and correlation through the cell engine and GalSim's
    reference: each version correlates above 0.99 with the reference's, its rms within 2 %."""
    rng = np.random.default_rng(4)
    size = 120
    correlation = noise_correlation(coloured_noise(rng, (400, 400)))
    image = np.zeros((size, size))
    image[60, 60] = 1.0  # GalSim needs flux
    white = rng.normal(0.0, 1.0, (size, size))
    out = {}
    for engine in ("fast", "galsim"):
        plain, _ = cell_operation(image, PSF_IMAGE, STEP, "gauss", engine)
        noisy, _ = cell_operation(
            image, PSF_IMAGE, STEP, "gauss", engine, white, moving_correlation=correlation
        )
        out[engine] = {k: (noisy[k] - plain[k])[20:-20, 20:-20] for k in TYPES}
    for kind in TYPES:
        a, b = out["fast"][kind], out["galsim"][kind]
        assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.99, kind
        assert a.std() == pytest.approx(b.std(), rel=0.02), kind
