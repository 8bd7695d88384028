"""The metacal operation on whole cells on the cell's own FFT grid (``measure/cell_metacal.py``):
its shifts make the version's shear exactly, its versions of analytic galaxies are as close
to the analytic truth as GalSim's reference, and its two fixnoise fields agree with the
reference's in power."""

from __future__ import annotations

import galsim
import numpy as np
import pytest

from megalut_cli.measure.cell_detect import cell_operation
from megalut_cli.measure.cell_metacal import (
    ROTATION,
    cell_filters,
    cell_geometry,
    cell_versions,
    shear_passes,
)
from megalut_cli.measure.metacal_defaults import SHEARS, TYPES
from megalut_cli.measure.metacal_fft import psf_params, shear_matrix
from megalut_cli.measure.metacal_targets import metacal_target

SIZE, STEP = 160, 0.01
PSF = galsim.Convolve(galsim.Gaussian(fwhm=3.6), galsim.Pixel(1.0))
PSF_IMAGE = PSF.drawImage(nx=32, ny=32, scale=1.0, method="no_pixel").array
#: Galaxies and their offsets (pixels) from the cell's centre.
GALAXIES = [
    (galsim.Exponential(half_light_radius=2.0, flux=400.0).shear(g1=0.2, g2=-0.1), (40.3, -25.7)),
    (galsim.Sersic(n=2.5, half_light_radius=3.0, flux=900.0).shear(g1=-0.1, g2=0.3), (-50.2, 44.9)),
    (galsim.Gaussian(sigma=2.0, flux=300.0), (0.0, 0.0)),
]


def shear_product(passes: list[tuple[int, float]]) -> np.ndarray:
    """The matrix ``M`` with ``H(M (x, y))`` after the passes, in order."""
    out = np.eye(2)
    for axis, s in passes:
        out = out @ (np.array([[1.0, s], [0.0, 1.0]]) if axis == 1 else [[1.0, 0.0], [s, 1.0]])
    return out


@pytest.mark.parametrize("step", [0.001, 0.01, 0.1])
def test_the_passes_compose_to_each_version_s_inverse_shear(step):
    for kind in TYPES:
        s1, s2 = SHEARS[kind]
        inverse = np.linalg.inv(shear_matrix(s1 * step, s2 * step))
        passes = shear_passes(inverse)
        assert len(passes) == (0 if kind == "noshear" else 4 if s1 else 3)
        assert not passes or passes[0][0] == 1  # merged with the inverse FFT
        np.testing.assert_allclose(shear_product(passes), inverse, atol=1e-13)
        assert max((abs(s) for _, s in passes), default=0.0) <= 1.2 * np.sqrt(step)


def cell(profile_of) -> np.ndarray:
    image = galsim.ImageD(SIZE, SIZE, scale=1.0)
    for gal, offset in GALAXIES:
        profile_of(gal).drawImage(image=image, offset=offset, add_to_image=True, method="no_pixel")
    return image.array


@pytest.mark.parametrize("engine", ["fast", "galsim"])
def test_versions_of_analytic_galaxies_are_the_analytic_truth(engine):
    """Galaxies convolved with the PSF and its pixel, anywhere in the cell: every version is
    each galaxy sheared about the cell's centre (its position too) and convolved with the
    target, drawn analytically, to 2e-4 of the peak away from the edges (measured: 1.2e-4
    for the cell engine, 1.4e-4 for GalSim's)."""
    image = cell(lambda gal: galsim.Convolve(gal, PSF))
    versions, sigma = cell_operation(image, PSF_IMAGE, STEP, "gauss", engine)
    target = galsim.Gaussian(sigma=sigma)
    for kind in TYPES:
        s1, s2 = SHEARS[kind]
        matrix = galsim.Shear(g1=s1 * STEP, g2=s2 * STEP).getMatrix()
        truth = galsim.ImageD(SIZE, SIZE, scale=1.0)
        for gal, offset in GALAXIES:
            sheared = gal.shear(g1=s1 * STEP, g2=s2 * STEP) if kind != "noshear" else gal
            galsim.Convolve(sheared, target).drawImage(
                image=truth, offset=matrix @ np.array(offset), add_to_image=True, method="no_pixel"
            )
        diff = (versions[kind] - truth.array)[16:-16, 16:-16]
        assert np.abs(diff).max() < 2e-4 * truth.array.max(), kind


def amplitude(image: np.ndarray) -> np.ndarray:
    k = 2 * np.pi * np.fft.fftfreq(image.shape[0])
    band = np.hypot(*np.meshgrid(k, k)) < 2.0
    return np.abs(np.fft.fft2(image))[band]


def test_the_fixnoise_fields_have_the_reference_s_power():
    """White noise through the moving fixnoise, and a noise image through the rotated one:
    the amplitude of each version's transform, averaged over rings, is GalSim's to 2 %
    (their grids differ: GalSim wraps at its own FFT size), and each version is the
    reference's image of the same field (correlation > 0.99)."""
    rng = np.random.default_rng(5)
    image = cell(lambda gal: galsim.Convolve(gal, PSF))  # GalSim needs flux
    plain = {e: cell_operation(image, PSF_IMAGE, STEP, "gauss", e)[0] for e in ("fast", "galsim")}
    for which in ("moving_field", "rotated_field"):
        field = rng.normal(0.0, 1.0, (SIZE, SIZE))
        new, _ = cell_operation(image, PSF_IMAGE, STEP, "gauss", "fast", **{which: field})
        ref, _ = cell_operation(image, PSF_IMAGE, STEP, "gauss", "galsim", **{which: field})
        for kind in TYPES:
            new[kind] -= plain["fast"][kind]
            ref[kind] -= plain["galsim"][kind]
            a, b = new[kind][20:-20, 20:-20], ref[kind][20:-20, 20:-20]
            assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.99, (which, kind)
            assert a.std() == pytest.approx(b.std(), rel=0.02), (which, kind)
            assert amplitude(new[kind]).mean() == pytest.approx(
                amplitude(ref[kind]).mean(), rel=0.02
            )


def test_the_cell_must_be_square():
    with pytest.raises(ValueError, match="square"):
        cell_versions(np.zeros((40, 50)), PSF_IMAGE, STEP, "gauss")


def test_the_response_on_noise_is_that_of_an_accurate_galsim():
    """Round galaxies at S/N about 40 on a noisy cell: each galaxy's response
    R = (g_1p - g_1m) / (2 step) (and R22) from the cell engine equals GalSim's operation
    drawn with its transform interpolated from a 16-fold padding, within 2e-5 on average
    (measured: 1e-7 on 1 212 galaxies of examples/scenes/isolated.toml). GalSim's default
    4-fold padding moves R11 by +1.8e-4 and R22 by -0.7e-4 there: the reference's own
    interpolation error, which the engine does not have (docs/metadetect.md)."""
    size = 128
    rng = np.random.default_rng(11)
    places = [(-30.3, -28.6), (29.1, -31.8), (-27.7, 30.4), (31.6, 28.2), (0.4, -0.3)]
    image = galsim.ImageD(size, size, scale=1.0)
    gal = galsim.Convolve(galsim.Exponential(half_light_radius=2.0, flux=400.0), PSF)
    for offset in places:
        gal.drawImage(image=image, offset=offset, add_to_image=True, method="no_pixel")
    cell = image.array + rng.normal(0.0, 1.0, (size, size))
    new, sigma = cell_versions(cell, PSF_IMAGE, STEP, "gauss")
    obj = galsim.InterpolatedImage(
        galsim.ImageD(cell, scale=1.0), x_interpolant="lanczos15", pad_factor=16
    )
    psf = galsim.InterpolatedImage(galsim.ImageD(PSF_IMAGE, scale=1.0), x_interpolant="lanczos15")
    deconvolved = galsim.Convolve(obj, galsim.Deconvolve(psf))
    centre = (size - 1) / 2.0
    response = {"cell": [], "galsim": []}
    for which, versions in (("cell", new), ("galsim", None)):
        g = {}
        for kind in ("1p", "1m", "2p", "2m"):
            s1, s2 = SHEARS[kind]
            if versions is None:
                sheared = galsim.Convolve(
                    deconvolved.shear(g1=s1 * STEP, g2=s2 * STEP), galsim.Gaussian(sigma=sigma)
                )
                version = sheared.drawImage(nx=size, ny=size, scale=1.0, method="no_pixel").array
            else:
                version = versions[kind]
            matrix = galsim.Shear(g1=s1 * STEP, g2=s2 * STEP).getMatrix()
            stamps = []
            for offset in places:
                x, y = centre + matrix @ np.array(offset)
                i, j = round(y), round(x)
                stamps.append(version[i - 16 : i + 16, j - 16 : j + 16])
            res = [galsim.hsm.FindAdaptiveMom(galsim.ImageD(s, scale=1.0)) for s in stamps]
            g[kind] = np.array([[r.observed_shape.g1, r.observed_shape.g2] for r in res])
        response[which] = np.stack(
            [
                (g["1p"][:, 0] - g["1m"][:, 0]) / (2 * STEP),
                (g["2p"][:, 1] - g["2m"][:, 1]) / (2 * STEP),
            ]
        )
    diff = response["cell"] - response["galsim"]
    assert np.all(np.abs(diff.mean(axis=1)) < 2e-5), diff
    assert np.all(np.abs(response["cell"].mean(axis=1) - 0.5) < 0.15)


@pytest.mark.parametrize("engine", ["fast", "galsim"])
def test_asking_for_some_versions_gives_those_versions_bit_for_bit(engine):
    """``kinds`` (what the detection noise's gain asks: the noshear version alone) returns
    those versions, the same bits as in the whole operation, with and without fixnoise."""
    rng = np.random.default_rng(8)
    image = rng.normal(size=(64, 64))
    field = rng.normal(size=(64, 64))
    for extra in ({}, {"moving_field": field}):
        whole, sigma = cell_operation(image, PSF_IMAGE, STEP, "gauss", engine, **extra)
        some, some_sigma = cell_operation(
            image, PSF_IMAGE, STEP, "gauss", engine, kinds=("noshear", "2m"), **extra
        )
        assert sorted(some) == ["2m", "noshear"] and some_sigma == sigma
        for kind, version in some.items():
            assert np.array_equal(version, whole[kind]), kind


def exact_dft(psf: np.ndarray, ux: np.ndarray, uy: np.ndarray) -> np.ndarray:
    """The PSF image's DFT about its true centre at the frequencies ``(ux, uy)``: the sum
    over its pixels."""
    x = np.arange(psf.shape[0]) - 0.5 * (psf.shape[0] - 1)
    return np.einsum(
        "yx,ky,kx->k", psf, np.exp(-1j * np.outer(uy, x)), np.exp(-1j * np.outer(ux, x))
    )


def exact_filters(psf: np.ndarray, step: float, size: int) -> tuple[list, list]:
    """The filters of :func:`cell_filters` from the exact DFT of the PSF image: per version,
    where each is kept and its values there."""
    target = metacal_target("gauss", psf, step)
    _, maxk, _ = psf_params(psf.tobytes(), psf.shape[0])
    grid = cell_geometry(size, step).grid
    q = 2.0 * np.pi * np.fft.fftfreq(grid)
    qx, qy = np.meshgrid(2.0 * np.pi * np.fft.rfftfreq(grid), q)
    image, noise = [], []
    for kind in TYPES:
        inv = np.linalg.inv(shear_matrix(*(s * step for s in SHEARS[kind])))
        inside = qx**2 + qy**2 <= maxk**2
        tx, ty = inv @ np.array([qx[inside], qy[inside]])
        image.append((inside, target.kvalue(tx, ty) / exact_dft(psf, qx[inside], qy[inside])))
        ux, uy = ROTATION @ inv @ inv @ np.array([qx.ravel(), qy.ravel()])
        keep = (ux**2 + uy**2 <= maxk**2).reshape(qx.shape)
        rx, ry = ROTATION @ inv @ np.array([qx[keep], qy[keep]])
        psf_at = exact_dft(psf, ux[keep.ravel()], uy[keep.ravel()])
        noise.append((keep, target.kvalue(rx, ry) / psf_at))
    return image, noise


@pytest.mark.parametrize("psf_size", [31, 32])
def test_the_filters_are_those_of_the_exact_psf_transform(psf_size):
    """Every version's image and fixnoise filters, for an elliptical PSF image of odd and of
    even size, equal those made from the PSF image's exact DFT (the sum over its pixels) at
    the rotated, sheared frequencies: the same frequencies kept, the values to 1e-6 of each
    (float32 filters and the spline's error; measured 2.5e-7), zero elsewhere."""
    moffat = galsim.Moffat(beta=3.0, fwhm=3.5).shear(g1=0.06, g2=-0.04)
    profile = galsim.Convolve(moffat, galsim.Pixel(1.0))
    psf = profile.drawImage(nx=psf_size, ny=psf_size, scale=1.0, method="no_pixel").array
    psf = np.ascontiguousarray(psf / psf.sum(), dtype=np.float64)
    step, size = 0.01, 120
    filters = cell_filters(
        psf.tobytes(), psf_size, metacal_target("gauss", psf, step), cell_geometry(size, step)
    )
    image, noise = exact_filters(psf, step, size)
    for made, (where, ref) in zip(filters.image + filters.noise, image + noise):
        assert made is not None
        np.testing.assert_array_equal(made != 0, where)
        np.testing.assert_allclose(made[where], ref, rtol=1e-6, atol=0)
