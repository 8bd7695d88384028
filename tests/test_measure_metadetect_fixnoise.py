"""The fixnoise of metadetection on whole cells (``measure/cell_fixnoise.py``, and the cell
engine's, ``measure/cell_metacal.py``): it moves with
the image (a pixel of the noise field lands where the version's shear about the cell's
centre takes it), has the response of metacal's rotated field (its power spectrum), and so
leaves the response of an object far from the centre nearly independent of its seed."""

from __future__ import annotations

import galsim
import numpy as np
import pytest

from megalut_cli.measure.cell_detect import CellNoise, metadetect_cell
from megalut_cli.measure.cell_fixnoise import kernel_size, moving_fixnoise
from megalut_cli.measure.cell_metacal import cell_versions
from megalut_cli.measure.measurer import MeasureSettings, MetacalSettings
from megalut_cli.measure.metacal import metacal_versions
from megalut_cli.measure.metacal_defaults import SHEARS, TYPES
from megalut_cli.measure.source_registry import DetectSettings


def centroid(image: np.ndarray, x0: float, y0: float, half: int = 10) -> np.ndarray:
    """The (x, y) barycentre (0-based) of ``image`` in a box around ``(x0, y0)``."""
    ix, iy = round(x0), round(y0)
    box = image[iy - half : iy + half + 1, ix - half : ix + half + 1]
    yy, xx = np.mgrid[iy - half : iy + half + 1, ix - half : ix + half + 1]
    return np.array([(box * xx).sum(), (box * yy).sum()]) / box.sum()


@pytest.mark.parametrize("engine", ["fast", "galsim"])
@pytest.mark.parametrize("psf_shear", [(0.0, 0.0), (0.03, -0.02)], ids=["round", "elliptical"])
def test_a_pixel_of_noise_moves_with_the_image(psf_shear, engine):
    """One pixel of noise about 30 px from the cell's centre along each axis: in every version
    it lands at the image's sheared position (metacal's rotated field: the other way), and
    the amplitude of its Fourier transform (the field's power spectrum) is the rotated
    field's."""
    size, step, target = 96, 0.05, "gauss"
    psf = galsim.Gaussian(fwhm=3.6).shear(g1=psf_shear[0], g2=psf_shear[1])
    psf_image = psf.drawImage(nx=32, ny=32, scale=1.0).array  # even: as a 96-px cell's
    field = np.zeros((size, size))
    px, py = 80, 20
    field[py, px] = 1.0
    if engine == "galsim":
        moving = moving_fixnoise(field, psf_image, step, target)
    else:  # the cell engine: the field's part of the versions of an empty cell
        moving, _ = cell_versions(np.zeros_like(field), psf_image, step, target, moving_field=field)
    rotated, _ = metacal_versions(np.rot90(field, 1)[None].copy(), psf_image, step, target=target)
    standard = {kind: np.rot90(rotated[kind][0], -1) for kind in TYPES}
    centre = (size - 1) / 2.0
    offset = np.array([px - centre, py - centre])
    for kind in TYPES:
        s1, s2 = SHEARS[kind]
        shear = galsim.Shear(g1=s1 * step, g2=s2 * step).getMatrix()
        there = centre + shear @ offset
        np.testing.assert_allclose(centroid(moving[kind], *there), there, atol=0.25)
        away = centre + np.linalg.inv(shear) @ offset
        np.testing.assert_allclose(centroid(standard[kind], *away), away, atol=0.25)
    # |FT|: the moving pixel's is the rotated field's, to a tenth of what the shear changes
    k = 2 * np.pi * np.fft.fftfreq(size)
    band = np.hypot(*np.meshgrid(k, k)) < 1.5
    amp = {kind: np.abs(np.fft.fft2(moving[kind]))[band] for kind in TYPES}
    amp_std = {kind: np.abs(np.fft.fft2(standard[kind]))[band] for kind in TYPES}
    assert np.abs(amp["noshear"] - amp_std["noshear"]).max() < 0.01 * amp_std["noshear"].max()
    for kind, other in (("1p", "1m"), ("1m", "1p"), ("2p", "2m"), ("2m", "2p")):
        change = np.abs(amp_std[kind] - amp_std[other]).max()
        assert change > 0.2 * amp_std[kind].max()
        assert np.abs(amp[kind] - amp_std[kind]).max() < 0.1 * change, kind


def test_kernel_size_fits_the_cell():
    assert kernel_size(250) == 129
    assert kernel_size(96) == 95 and kernel_size(97) == 97


def test_an_object_far_from_the_centre_keeps_its_response():
    """A galaxy 64 px from the centre of a noisy cell (S/N about 30): its response
    R11 = (g1_1p - g1_1m) / (2 step) hardly depends on the fixnoise field (metacal's rotated
    field, sheared the other way, put two independent realizations under it: a scatter of
    about 1.3 over seeds)."""
    size, step = 160, 0.01
    gal = galsim.Convolve(
        galsim.Exponential(half_light_radius=2.0, flux=400.0), galsim.Gaussian(fwhm=3.6)
    )
    where = np.array([130.0, 40.0])  # 0-based pixel (x, y); the centre is (79.5, 79.5)
    image = gal.drawImage(nx=size, ny=size, scale=1.0, offset=where - (size - 1) / 2.0).array
    image = image + np.random.default_rng(3).normal(0.0, 1.0, image.shape)
    psf = galsim.Gaussian(fwhm=3.6).drawImage(nx=33, ny=33, scale=1.0).array
    detection = DetectSettings(5.0, 4, 32, 0.005)
    responses = []
    for seed in range(6):
        settings = MeasureSettings(metacal=MetacalSettings(step, seed))
        out = metadetect_cell(image, psf, CellNoise(1.0, seed), settings, detection)
        g1 = {}
        for kind in ("1p", "1m"):
            rows = np.flatnonzero(out["mdet_step"] == kind)
            near = rows[np.hypot(out["x"][rows] - 1 - where[0], out["y"][rows] - 1 - where[1]) < 3]
            assert len(near) == 1 and out["flags"][near[0]] == 0
            g1[kind] = out["adamom_g1"][near[0]]
        responses.append((g1["1p"] - g1["1m"]) / (2 * step))
    assert 0.2 < np.mean(responses) < 0.8
    assert np.std(responses) < 0.2, responses
