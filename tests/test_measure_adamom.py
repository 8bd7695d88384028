"""The compiled HSM adaptive moments (measure/adamom.py) against galsim.hsm.FindAdaptiveMom."""

from __future__ import annotations

import galsim
import numpy as np
import pytest

from megalut_cli import flags as fl
from megalut_cli.measure.adamom import (
    ALL_ZERO,
    GALSIM_MESSAGES,
    STATUS_NAMES,
    SUCCESS,
    HSMParams,
    adaptive_moments,
)
from megalut_cli.measure.features import FEATURE_COLUMNS, MEASURE_ENGINES, measure_stamps

FIELDS = ("amp", "g1", "g2", "sigma", "rho4", "x", "y")
#: Tolerances of the checks: relative for amp and sigma, absolute for the others.
RELATIVE = ("amp", "sigma")
TOLERANCE = 1e-6


def fiducial_stamps(n: int, size: int = 64, seed: int = 0) -> np.ndarray:
    """Noisy galaxies at the paper's fiducial S/N: elliptical Gaussian or exponential
    profiles (half each), hlr U(2, 8) px, surface brightness U(1, 15), |e| < 0.6, offsets
    +-0.5 px, convolved with a Gaussian PSF of sigma 2 px (FFT), unit Gaussian noise."""
    rng = np.random.default_rng(seed)
    hlr = rng.uniform(2.0, 8.0, n)
    flux = rng.uniform(1.0, 15.0, n) * np.pi * hlr**2
    e = rng.uniform(0.0, 0.6, n)
    angle = rng.uniform(0.0, np.pi, n)
    offset = rng.uniform(-0.5, 0.5, (n, 2))
    exponential = rng.random(n) < 0.5
    coords = np.arange(1, size + 1) - (size + 1) / 2.0
    dx = coords[None, None, :] - offset[:, 0, None, None]
    dy = coords[None, :, None] - offset[:, 1, None, None]
    cos, sin = np.cos(angle)[:, None, None], np.sin(angle)[:, None, None]
    q = ((1.0 - e) / (1.0 + e))[:, None, None]
    u, v = cos * dx + sin * dy, -sin * dx + cos * dy
    r = np.sqrt(u**2 * q + v**2 / q)
    h = hlr[:, None, None]
    scale = h / 1.6783469900166612  # exponential scale radius
    sigma = h / np.sqrt(2.0 * np.log(2.0))
    profile = np.where(
        exponential[:, None, None],
        np.exp(-r / scale) / (2.0 * np.pi * scale**2),
        np.exp(-0.5 * (r / sigma) ** 2) / (2.0 * np.pi * sigma**2),
    )
    k = 2.0 * np.pi * np.fft.fftfreq(size)
    psf = np.exp(-0.5 * 2.0**2 * (k[:, None] ** 2 + k[None, :] ** 2))
    images = np.fft.ifft2(np.fft.fft2(profile) * psf).real * flux[:, None, None]
    return images + rng.normal(size=images.shape)


def galsim_reference(stamps: np.ndarray, guess_sigma: float) -> tuple[np.ndarray, dict]:
    """GalSim's status codes (ours, from its error messages) and outputs, per stamp."""
    n, ny, nx = stamps.shape
    image = galsim.ImageD(nx, ny)
    weight = galsim.ImageI(nx, ny, init_value=1)
    status = np.full(n, -1)
    out = {f: np.full(n, np.nan) for f in FIELDS}
    for i, stamp in enumerate(stamps):
        image.array[:, :] = stamp
        res = galsim.hsm.FindAdaptiveMom(
            image, weight=weight, guess_sig=guess_sigma, strict=False, check=False
        )
        if res.moments_status == 0:
            status[i] = SUCCESS
            shape, cen = res.observed_shape, res.moments_centroid
            values = (res.moments_amp, shape.g1, shape.g2, res.moments_sigma, res.moments_rho4, cen.x, cen.y)
            for f, v in zip(FIELDS, values):
                out[f][i] = v
        else:
            codes = [c for c, m in GALSIM_MESSAGES.items() if res.error_message.startswith(m)]
            assert len(codes) == 1, res.error_message
            status[i] = codes[0]
    return status, out


def assert_matches_galsim(stamps, guess_sigma=5.0, min_agreement=1.0, tol=TOLERANCE, **kw):
    """Same failures (kinds included) on ``min_agreement`` of the stamps, same numbers."""
    ours = adaptive_moments(stamps, guess_sigma, **kw)
    status, ref = galsim_reference(stamps, guess_sigma)
    agree = ours.status == status
    assert agree.mean() >= min_agreement, [
        (STATUS_NAMES[a], STATUS_NAMES[b]) for a, b in zip(ours.status[~agree], status[~agree])
    ]
    # Whether a stamp failed at all agrees even more often.
    assert ((ours.status == 0) == (status == 0)).mean() >= min_agreement
    both = (ours.status == 0) & (status == 0)
    for f in FIELDS:
        mine, theirs = getattr(ours, f)[both], ref[f][both]
        if f in RELATIVE:
            np.testing.assert_allclose(mine, theirs, rtol=tol, atol=0, err_msg=f)
        else:
            np.testing.assert_allclose(mine, theirs, rtol=0, atol=tol, err_msg=f)
        assert np.isnan(getattr(ours, f)[ours.status != 0]).all()
    return ours, status


def test_status_names_cover_galsim_messages():
    assert set(GALSIM_MESSAGES) | {SUCCESS} == set(STATUS_NAMES)
    assert STATUS_NAMES[SUCCESS] == "SUCCESS"


def test_fiducial_stamps_match_galsim():
    stamps = fiducial_stamps(2000, seed=11)
    ours, status = assert_matches_galsim(stamps, min_agreement=0.995)
    # Faint galaxies make HSM fail, so that failures are tested too.
    assert 0.01 < (status != 0).mean() < 0.2
    assert ours.n_iter[ours.status == 0].min() >= 1
    assert np.median(ours.n_iter[ours.status == 0]) < 50


@pytest.mark.slow
def test_fiducial_stamps_match_galsim_1e4():
    stamps = fiducial_stamps(10_000, seed=12)
    assert_matches_galsim(stamps, min_agreement=0.995)


def test_exact_exp_reproduces_galsim_numbers():
    """With an exp per pixel, the sums are GalSim's, summed in GalSim's order."""
    stamps = fiducial_stamps(300, seed=13)
    assert_matches_galsim(stamps, min_agreement=1.0, tol=1e-12, exact_exp=True)


@pytest.mark.parametrize("size", [32, 33, 64, 128])
def test_stamp_sizes_match_galsim(size):
    stamps = fiducial_stamps(150, size=size, seed=size)
    guess = min(5.0, size / 8.0)
    ours, status = assert_matches_galsim(stamps, guess, min_agreement=0.98)
    assert (status == 0).mean() > 0.5


def _gaussian(sigma, size=64, g1=0.1, g2=-0.05, flux=1000.0, offset=(0.2, -0.3), method="auto"):
    prof = galsim.Gaussian(sigma=sigma, flux=flux).shear(g1=g1, g2=g2)
    return prof.drawImage(nx=size, ny=size, scale=1.0, offset=offset, method=method).array


def test_corner_cases_match_galsim():
    rng = np.random.default_rng(5)
    delta = np.zeros((64, 64))
    delta[30, 40] = 1.0
    corner = np.zeros((64, 64))  # nonzero pixels only in a corner: GalSim's bounds shrink
    corner[:20, :24] = _gaussian(2.0, size=64)[22:42, 20:44]
    stamps = np.stack(
        [
            np.zeros((64, 64)),  # all zero
            delta,  # a single pixel
            _gaussian(0.3),  # tiny, undersampled
            _gaussian(0.7),
            _gaussian(12.0),  # large
            _gaussian(40.0),  # larger than the stamp
            _gaussian(3.0, g1=0.7, g2=0.0),  # very elongated
            _gaussian(3.0, g1=0.0, g2=-0.7),
            _gaussian(3.0, offset=(14.0, 9.0)),  # far from the centre
            -_gaussian(3.0),  # negative
            corner,
            rng.normal(size=(64, 64)),  # pure noise
            rng.normal(size=(64, 64)) + _gaussian(2.5, flux=50.0),
            np.full((64, 64), 3.0),  # constant
        ]
    )
    ours, status = assert_matches_galsim(stamps, min_agreement=1.0)
    assert ours.status[0] == ALL_ZERO
    # GalSim's outcomes, which cover most failure kinds
    names = [STATUS_NAMES[s] for s in ours.status]
    assert names[:4] == ["ALL_ZERO", "SINGULAR", "SINGULAR", "SINGULAR"]
    assert names[10:12] == ["OUT_OF_RANGE", "TOO_MANY_ITERATIONS"]
    assert ours.sigma[4] == pytest.approx(12.0, rel=0.01)  # the stamp truncates the window
    assert ours.amp[9] < 0  # a negative source converges, with a negative amplitude


def test_rectangular_stamps_and_guesses_match_galsim():
    stamps = fiducial_stamps(60, size=48, seed=2)[:, 4:44, :]  # 40 x 48
    for guess in (1.5, 5.0, 9.0):
        assert_matches_galsim(stamps, guess, min_agreement=0.95)


def test_noiseless_gaussian_is_recovered():
    stamp = _gaussian(3.0, g1=0.2, g2=-0.1, flux=500.0, offset=(0.3, -0.2), method="no_pixel")
    res = adaptive_moments(stamp[None])
    assert res.status[0] == SUCCESS
    assert res.sigma[0] == pytest.approx(3.0, rel=1e-5)
    assert res.g1[0] == pytest.approx(0.2, abs=1e-5)
    assert res.g2[0] == pytest.approx(-0.1, abs=1e-5)
    assert res.amp[0] == pytest.approx(500.0, rel=1e-4)
    assert res.rho4[0] == pytest.approx(2.0, rel=1e-4)
    assert res.x[0] == pytest.approx(32.8, abs=1e-6)
    assert res.y[0] == pytest.approx(32.3, abs=1e-6)


def test_independent_of_batch_size():
    stamps = fiducial_stamps(120, seed=21)
    whole = adaptive_moments(stamps)
    parts = [adaptive_moments(stamps[i : i + 7]) for i in range(0, len(stamps), 7)]
    for f in ("status", "n_iter", *FIELDS):
        joined = np.concatenate([getattr(p, f) for p in parts])
        np.testing.assert_array_equal(getattr(whole, f), joined, err_msg=f)
    for i in (0, 57, 119):
        one = adaptive_moments(stamps[i : i + 1])
        np.testing.assert_array_equal(
            [getattr(one, f)[0] for f in FIELDS], [getattr(whole, f)[i] for f in FIELDS]
        )


def test_hsm_params_are_applied():
    stamps = fiducial_stamps(40, seed=4)
    few = adaptive_moments(stamps, params=HSMParams(max_mom2_iter=14))
    assert (few.status == SUCCESS).any() and (few.status != SUCCESS).any()
    assert (few.n_iter[few.status == SUCCESS] <= 14).all()
    hsm = galsim.hsm.HSMParams(max_mom2_iter=14)
    image = galsim.ImageD(stamps[0])
    for i in range(len(stamps)):
        image.array[:, :] = stamps[i]
        res = galsim.hsm.FindAdaptiveMom(image, hsmparams=hsm, strict=False)
        assert (res.moments_status == 0) == (few.status[i] == SUCCESS)
        if res.moments_status == 0:
            assert res.moments_sigma == few.sigma[i]


def test_guess_sigma_per_stamp():
    stamps = fiducial_stamps(12, seed=8)
    guesses = np.linspace(1.5, 7.0, 12)
    together = adaptive_moments(stamps, guesses)
    for i, guess in enumerate(guesses):
        alone = adaptive_moments(stamps[i : i + 1], guess)
        assert alone.status[0] == together.status[i] and alone.n_iter[0] == together.n_iter[i]
        np.testing.assert_array_equal(alone.g1[0], together.g1[i])


def test_bad_arguments_rejected():
    with pytest.raises(ValueError):
        adaptive_moments(np.zeros((64, 64)))
    with pytest.raises(ValueError):
        adaptive_moments(np.zeros((1, 64, 64)), guess_sigma=0.0)
    with pytest.raises(ValueError):
        adaptive_moments(np.zeros((1, 64, 64)), guess_sigma=np.nan)
    with pytest.raises(ValueError):
        adaptive_moments(np.zeros((1, 64, 64)), precision=0.0)
    empty = adaptive_moments(np.zeros((0, 64, 64)))
    assert empty.status.shape == (0,) and empty.g1.shape == (0,)


def _assert_same_features(a, b, min_agreement):
    """Same flags on ``min_agreement`` of the rows (HSM runs that have not converged after
    hundreds of iterations amplify rounding differences), same features where both are 0."""
    same = a["flags"] == b["flags"]
    assert same.mean() >= min_agreement
    for c in FEATURE_COLUMNS:
        np.testing.assert_allclose(a[c][same], b[c][same], rtol=TOLERANCE, atol=TOLERANCE, err_msg=c)


@pytest.mark.parametrize("size", [32, 33, 64])
def test_measure_stamps_engines_agree(size):
    assert MEASURE_ENGINES == ("fast", "galsim")
    stamps = fiducial_stamps(100, size=size, seed=40 + size)
    stamps[3] = 0.0  # HSM fails
    stamps[4, 2, 5] = np.nan  # flagged before HSM
    stamps[5] = -stamps[5]  # negative flux
    stamps[6, :, :] = np.roll(stamps[6], size // 3, axis=1)  # off centre
    origins = np.random.default_rng(1).integers(1, 500, size=(100, 2))
    fast = measure_stamps(stamps, origins, engine="fast")
    ref = measure_stamps(stamps, origins, engine="galsim")
    _assert_same_features(fast, ref, min_agreement=0.98)
    np.testing.assert_array_equal(fast["flags"][3:7], ref["flags"][3:7])
    assert fast["flags"][3] == fl.HSM_FAILED
    assert fast["flags"][4] & fl.BAD_PIXELS
    assert fast["flags"][5] != 0
    assert (fast["flags"] == 0).mean() > 0.7


def test_measure_engines_are_the_cli_engines():
    from megalut_cli.engine import ENGINES

    assert MEASURE_ENGINES == tuple(ENGINES)


def test_measure_stamps_rejects_unknown_engine():
    with pytest.raises(ValueError, match="engine"):
        measure_stamps(fiducial_stamps(2), engine="ngmix")
