"""The batched metacal operation (measure/metacal_fft.py) against the GalSim reference."""

from __future__ import annotations

import galsim
import numpy as np
import pytest

from megalut_cli.measure.metacal import SHEARS, TYPES, metacal_versions, target_psf_sigma
from megalut_cli.measure.metacal_fft import fft_versions

STEP = 0.01


def _stack(
    size: int, psf: galsim.GSObject, seed: int, n_gal: int = 2, n_noise: int = 1
) -> np.ndarray:
    """Sersic galaxies (n 1..4, hlr 1.5..6 px, |g| < 0.5, off-centre) seen through ``psf``,
    then unit-noise stamps."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n_gal):
        gal = galsim.Sersic(rng.uniform(1, 4), half_light_radius=rng.uniform(1.5, 6))
        gal = gal.shear(g=rng.uniform(0, 0.5), beta=rng.uniform(0, np.pi) * galsim.radians)
        gal = gal.shift(*rng.uniform(-1, 1, 2))
        out.append(galsim.Convolve(gal, psf).drawImage(nx=size, ny=size, scale=1.0).array)
    out += [rng.normal(0.0, 1.0, (size, size)) for _ in range(n_noise)]
    return np.array(out, dtype=np.float64)


def _errors(fast: dict, ref: dict, n_gal: int) -> np.ndarray:
    """Max |fast - ref| over the five versions of each stamp, relative to the reference's
    noshear peak (galaxies) or rms (noise)."""
    out = []
    for i in range(len(ref["noshear"])):
        scale = ref["noshear"][i].max() if i < n_gal else ref["noshear"][i].std()
        out.append(max(np.abs(fast[k][i] - ref[k][i]).max() for k in TYPES) / scale)
    return np.array(out)


CASES = {
    # stamp size, PSF stamp size, PSF
    "64/64 gaussian": (64, 64, galsim.Gaussian(sigma=2.0)),
    "48/33 elliptical moffat fwhm 3": (
        48,
        33,
        galsim.Moffat(beta=3.0, fwhm=3.0).shear(g1=0.1, g2=-0.11),
    ),
    "65/48 moffat fwhm 5": (65, 48, galsim.Moffat(beta=2.5, fwhm=5.0)),
    # the PSF's maxk falls exactly on grid points of the noshear k image (cut or not by GalSim)
    "49/32 moffat fwhm 3": (49, 32, galsim.Moffat(beta=3.0, fwhm=3.0)),
}


@pytest.mark.parametrize("case", list(CASES))
def test_versions_match_galsim(case):
    """Noiseless Sersic galaxies and a unit-noise stamp, even and odd stamp and PSF sizes,
    PSF stamps of another size: ``engine="fast"`` (float32 arithmetic) against GalSim, max
    over the five versions. Achieved over a 30-configuration grid (Gaussian and Moffat PSFs,
    FWHM 3-5, elliptical, S 48/49/64/65, P 32-64): 5.8e-7 of the peak on galaxies, 1.4e-6 of
    the rms on noise; float64 arithmetic: 7.6e-8 and 3.2e-7 (here: 6.0e-7, 1.2e-6; 6.1e-8,
    2.6e-7)."""
    size, psf_size, psf = CASES[case]
    psf_image = psf.drawImage(nx=psf_size, ny=psf_size, scale=1.0).array
    stamps = _stack(size, psf, seed=len(case))
    ref, target = metacal_versions(stamps, psf_image, step=STEP, engine="galsim")
    fast, target_fast = metacal_versions(stamps, psf_image, step=STEP, engine="fast")
    np.testing.assert_array_equal(target, target_fast)
    assert all(fast[k].dtype == np.float64 and fast[k].shape == stamps.shape for k in TYPES)
    assert np.all(_errors(fast, ref, 2) < 1e-5), _errors(fast, ref, 2)
    exact = fft_versions(stamps, psf_image, STEP, target[0], dtype="float64")
    assert np.all(_errors(exact, ref, 2) < 1e-6), _errors(exact, ref, 2)


def test_mixed_fft_sizes_and_fixnoise():
    """128-px stamps: GalSim draws the compact galaxies on a 128 k grid and the noise on a
    192 one (from each stamp's flux radius); the fast engine follows it stamp by stamp. With
    fixnoise (metacal.py adds the operation's image of a rotated noise field). Achieved:
    4.4e-7 of the peak, 1.4e-6 of the rms (with fixnoise: 4.2e-7, 1.3e-6)."""
    psf = galsim.Gaussian(sigma=2.0)
    psf_image = psf.drawImage(nx=32, ny=32, scale=1.0).array
    stamps = _stack(128, psf, seed=3)[[0, 2, 1]]  # galaxy, noise, galaxy
    ref, _ = metacal_versions(stamps, psf_image, step=STEP, engine="galsim")
    fast, _ = metacal_versions(stamps, psf_image, step=STEP, engine="fast")
    errors = _errors(
        {k: v[[0, 2, 1]] for k, v in fast.items()}, {k: v[[0, 2, 1]] for k, v in ref.items()}, 2
    )
    assert np.all(errors < 1e-5), errors
    sigmas = np.array([0.1, 1.0, 0.0])
    ref, _ = metacal_versions(stamps, psf_image, step=STEP, noise_sigma=sigmas, engine="galsim")
    fast, _ = metacal_versions(stamps, psf_image, step=STEP, noise_sigma=sigmas, engine="fast")
    errors = _errors(
        {k: v[[0, 2, 1]] for k, v in fast.items()}, {k: v[[0, 2, 1]] for k, v in ref.items()}, 2
    )
    assert np.all(errors < 1e-5), errors


def test_noshear_and_sheared_versions_on_different_fft_sizes(monkeypatch):
    """Where GalSim's FFT size differs between the noshear and the sheared versions of a
    stamp (the shear widens the profile: N can cross a size step), each comes from its own
    k grid."""
    from megalut_cli.measure import metacal_fft

    psf = galsim.Gaussian(sigma=2.0)
    psf_image = psf.drawImage(nx=32, ny=32, scale=1.0).array
    sigma = target_psf_sigma(psf_image, STEP)
    stamps = _stack(32, psf, seed=9)

    def forced(pair):
        monkeypatch.setattr(
            metacal_fft, "grid_sizes", lambda images, *a: np.tile(pair, (len(images), 1))
        )
        return fft_versions(stamps, psf_image, STEP, sigma)

    mixed, small, large = forced([128, 192]), forced([128, 128]), forced([192, 192])
    assert np.array_equal(mixed["noshear"], small["noshear"]) and not np.allclose(
        small["noshear"], large["noshear"]
    )
    assert all(np.array_equal(mixed[k], large[k]) for k in TYPES[1:])


def test_batch_equals_one_by_one():
    """A stack of 37 stamps (more than a block; galaxies and noise; float32 input) gives each
    stamp's versions as computed alone, up to float32 rounding (the matrix products sum in
    another order for another block size): achieved 9.6e-8 of the version's peak."""
    psf = galsim.Moffat(beta=3.0, fwhm=4.0)
    psf_image = psf.drawImage(nx=48, ny=48, scale=1.0).array
    sigma = target_psf_sigma(psf_image, STEP)
    stamps = _stack(48, psf, seed=7, n_gal=25, n_noise=12).astype(np.float32)
    batch = fft_versions(stamps, psf_image, STEP, sigma)
    for i in (0, 16, 24, 25, 36):
        one = fft_versions(stamps[i : i + 1], psf_image, STEP, sigma)
        for k in TYPES:
            scale = np.abs(one[k][0]).max()
            assert np.abs(batch[k][i] - one[k][0]).max() <= 1e-6 * scale, (i, k)


def test_response_calibrates_a_sheared_sersic_ring():
    """As tests/test_measure_metacal.py's ring test, with the fast engine: a noiseless Sersic
    ring (4 orientations) under a known shear, adaptive-moment shapes of the noshear
    versions calibrated by the mean metacal response give back the shear. Achieved:
    m = 2.2e-4, 2.1e-4 (GalSim's engine: the same to 1e-6)."""
    size, psf_sigma = 48, 2.0
    psf = galsim.Gaussian(sigma=psf_sigma)
    psf_image = psf.drawImage(nx=size, ny=size, scale=1.0).array
    g_true = np.array([0.02, -0.01])
    stamps = []
    for angle in (0, 45, 90, 135):
        galaxy = galsim.Sersic(2.0, half_light_radius=3.0).shear(g=0.3, beta=angle * galsim.degrees)
        galaxy = galaxy.shear(g1=g_true[0], g2=g_true[1])
        stamps.append(galsim.Convolve(galaxy, psf).drawImage(nx=size, ny=size, scale=1.0).array)
    versions, _ = metacal_versions(np.array(stamps), psf_image, step=STEP, engine="fast")

    def shape(image: np.ndarray) -> np.ndarray:
        res = galsim.hsm.FindAdaptiveMom(galsim.ImageD(image, scale=1.0))
        return np.array([res.observed_shape.g1, res.observed_shape.g2])

    e, response = np.zeros(2), np.zeros((2, 2))
    for i in range(4):
        shapes = {kind: shape(versions[kind][i]) for kind in TYPES}
        e += shapes["noshear"] / 4
        response += (
            np.column_stack([shapes["1p"] - shapes["1m"], shapes["2p"] - shapes["2m"]])
            / (2 * STEP)
            / 4
        )
    m = np.linalg.solve(response, e) / g_true - 1
    assert np.all(np.abs(m) < 1e-3), m
    assert np.all(np.diag(response) > 0.3) and np.all(
        np.abs(response - np.diag(np.diag(response))) < 1e-3
    )


def test_versions_are_the_sheared_galaxy_through_the_target_psf():
    """The physics, without GalSim's operation: each version of a Gaussian galaxy is the
    galaxy sheared by the version's shear, through the round target (achieved: 3.2e-7;
    GalSim's engine: 2.4e-7)."""
    size, psf = 48, galsim.Gaussian(sigma=2.0)
    galaxy = galsim.Gaussian(sigma=3.0).shear(g1=0.2, g2=-0.1)
    psf_image = psf.drawImage(nx=size, ny=size, scale=1.0).array
    stamp = galsim.Convolve(galaxy, psf).drawImage(nx=size, ny=size, scale=1.0).array
    sigma = target_psf_sigma(psf_image, STEP)
    versions = fft_versions(stamp[None], psf_image, STEP, sigma)
    for kind in TYPES:
        s1, s2 = SHEARS[kind]
        expected = galsim.Convolve(
            galaxy.shear(g1=s1 * STEP, g2=s2 * STEP), galsim.Gaussian(sigma=sigma)
        )
        ref = expected.drawImage(nx=size, ny=size, scale=1.0, method="no_pixel").array
        assert np.abs(versions[kind][0] - ref).max() < 1e-6 * ref.max(), kind


def test_shapes_are_checked():
    psf_image = np.ones((5, 5))
    with pytest.raises(ValueError, match="square stamps"):
        fft_versions(np.zeros((2, 8, 9)), psf_image, STEP, 2.0)
    with pytest.raises(ValueError, match="square PSF"):
        fft_versions(np.zeros((2, 8, 8)), np.ones((5, 6)), STEP, 2.0)
    empty = fft_versions(np.zeros((0, 8, 8)), psf_image, STEP, 2.0)
    assert all(v.shape == (0, 8, 8) for v in empty.values())
    with pytest.raises(ValueError, match="out must be"):
        fft_versions(
            np.zeros((2, 8, 8)), psf_image, STEP, 2.0, out=np.empty((5, 2, 8, 8), np.float32)
        )


def test_out_receives_the_versions():
    """``out=`` (e.g. a buffer reused from call to call): the same numbers, written in place."""
    psf = galsim.Gaussian(sigma=1.5)
    psf_image = psf.drawImage(nx=24, ny=24, scale=1.0).array
    stamps = _stack(24, psf, seed=5)
    sigma = target_psf_sigma(psf_image, STEP)
    fresh = fft_versions(stamps, psf_image, STEP, sigma)
    out = np.full((5, 3, 24, 24), np.nan)
    into = fft_versions(stamps, psf_image, STEP, sigma, out=out)
    for v, kind in enumerate(TYPES):
        assert np.shares_memory(into[kind], out) and np.array_equal(out[v], fresh[kind])
