"""A real galaxy's noise padding stays out of its stamp (issue 39).

Before the fix, the HST noise padded around a real galaxy folded back into the stamp: GalSim
drew it with the FFT period of the unpadded cutout, and for small cutouts the padding filled
the whole image that GalSim interpolates, whose periodic copies leaked in. The fold is the
same in every ring and seed, so it gave each galaxy its own response to g1 (galaxy 5:
A1/A2 - 1 = -10.5 % at 64 px, noiseless; ``examples/realgal/probe_padding.py``).
"""

from __future__ import annotations

from pathlib import Path

import galsim
import numpy as np
import pytest

from megalut_cli.sim.draw import draw_wide, real_pad_pixels, wide_draw_size
from megalut_cli.sim.galaxies import real_padded_side, real_profile, rotated

ROOT = Path(__file__).resolve().parents[1]
REAL = {
    "catalog": str(ROOT / "examples/data/cosmos/real_galaxy_catalog_26_extension_example.fits"),
    "dir": str(ROOT / "examples/data/cosmos"),
    "pixel_scale": 0.06,
}
PSF = galsim.Gaussian(sigma=2.0)
SHEAR = 0.02
#: Galaxies the old drawing biased most at 64 px (noiseless A1/A2 - 1: -10.5 %, -4.1 %,
#: +4.9 %; 0 has the smallest cutout, whose padding filled GalSim's interpolated image).
GALAXIES = (0, 5, 19, 37)


def simulator_stamp(index: int, stamp: int, theta: float, g1: float, g2: float, offset, pad):
    """Noiseless stamp of real galaxy ``index`` as the simulator draws it (before any noise
    processing), padded over ``pad`` pixels (0: unpadded)."""
    base = real_profile(REAL, index, 1000.0, pad_pixels=pad)
    obj = galsim.Convolve(rotated(base, theta, g1, g2), PSF)
    image = galsim.ImageF(stamp, stamp, scale=1.0)
    padded = real_padded_side(REAL, index, pad)
    size = wide_draw_size(stamp, padded, float(np.hypot(g1, g2)), PSF) if pad else stamp
    return draw_wide(obj, image, offset, "auto", size).array


def responses(index: int, stamp: int, pad: float, rings: int = 2) -> np.ndarray:
    """Adaptive-moment responses (A1, A2) to the shear, from common-random-number pairs over
    ``rings`` rings of 4 orientations."""
    rng = np.random.default_rng(index)
    d = np.zeros(2)
    for _ in range(rings):
        theta0 = rng.uniform(0.0, 45.0)
        for j in range(4):
            offset = tuple(rng.uniform(-0.5, 0.5, 2))
            for i, (g1, g2) in enumerate(((SHEAR, 0.0), (0.0, SHEAR))):
                e = []
                for sign in (1.0, -1.0):
                    arr = simulator_stamp(
                        index, stamp, theta0 + 45.0 * j, sign * g1, sign * g2, offset, pad
                    )
                    shape = galsim.hsm.FindAdaptiveMom(galsim.Image(arr)).observed_shape
                    e.append((shape.g1, shape.g2)[i])
                d[i] += (e[0] - e[1]) / (2 * SHEAR)
    return d / (4 * rings)


@pytest.mark.parametrize("stamp", [64, 96])
def test_padded_galaxy_responds_as_unpadded(stamp):
    # The padding's noise is sheared with the galaxy: it may change the response a little,
    # alike in both components (a noise effect), but not one component against the other.
    # Fixed, A1/A2 - 1 of the padded galaxy agrees with the unpadded one to 0.11 % rms over the
    # 100 galaxies (probe, 6 rings, 64 px); the old drawing was off by 9.9 % rms at 64 px.
    for index in GALAXIES:
        a_pad = responses(index, stamp, real_pad_pixels(stamp))
        a_ref = responses(index, stamp, 0.0)
        anisotropy = (a_pad[0] / a_pad[1]) / (a_ref[0] / a_ref[1]) - 1.0
        assert abs(anisotropy) < 3e-3, (index, stamp, a_pad, a_ref)
        assert np.all(np.abs(a_pad / a_ref - 1.0) < 0.02), (index, stamp, a_pad, a_ref)


@pytest.mark.parametrize("index", [0, 5])
def test_padded_stamp_is_the_unwrapped_image(index):
    # Pixel by pixel: the simulator's stamp is the same padded galaxy with far more zeros
    # around it, drawn into 1024 px (no periodic copy anywhere near), to 2 % of the padding
    # noise's rms (fixed: 0.41 % and 0.43 % at most, 0.07 % rms, for galaxies 0 and 5; the old
    # drawing: 47 % and 30 %).
    stamp = 64
    pad = real_pad_pixels(stamp)
    got = simulator_stamp(index, stamp, 30.0, 0.02, -0.01, (0.2, -0.3), pad)
    rgc = galsim.RealGalaxyCatalog(Path(REAL["catalog"]).name, dir=REAL["dir"])
    big_pad = galsim.RealGalaxy(
        rgc,
        index=index,
        noise_pad_size=pad * REAL["pixel_scale"],
        pad_factor=64.0,  # cutouts of 54 and 94 HST px in thousands of zeros
        rng=galsim.BaseDeviate(271828 + index),
    )
    unit = big_pad.withFlux(1.0).dilate(1.0 / REAL["pixel_scale"]).withFlux(1000.0)
    obj = galsim.Convolve(rotated(unit, 30.0, 0.02, -0.01), PSF)
    ref = obj.drawImage(nx=1024, ny=1024, scale=1.0, offset=(0.2, -0.3)).array
    a = (1024 - stamp) // 2
    ref = ref[a : a + stamp, a : a + stamp]
    clean = simulator_stamp(index, stamp, 30.0, 0.02, -0.01, (0.2, -0.3), 0.0)
    noise_rms = np.std((got - clean)[:8, :])  # a band of padding only
    assert noise_rms > 0
    assert np.max(np.abs(got - ref)) < 2e-2 * noise_rms


def test_wide_draw_matches_a_direct_draw():
    # A compact profile drawn through the wide image is the direct draw (same centre, offset
    # and pixel response), for even and odd stamps.
    obj = galsim.Convolve(galsim.Sersic(n=1.5, half_light_radius=3.0, flux=500.0), PSF)
    for n in (48, 49):
        direct = obj.drawImage(nx=n, ny=n, scale=1.0, offset=(0.3, -0.2)).array
        image = galsim.ImageF(n, n, scale=1.0)
        wide = draw_wide(obj, image, (0.3, -0.2), "auto", 256).array
        np.testing.assert_allclose(wide, direct, rtol=0, atol=1e-5 * direct.max())
