"""PSFs of the simulations: specs, validation, truth values, caching."""

from __future__ import annotations

import math

import galsim
import numpy as np
import pytest

from megalut_cli.catalog import write_image
from megalut_cli.errors import ConfigError, InputError
from megalut_cli.sim.psf import (
    blackbody_photons,
    make_psf,
    psf_includes_pixel,
    psf_varies,
    validate_psf_config,
)


def hsm(prof, scale=0.1, n=400):
    """(g1, g2, sigma in pixels) of a profile drawn finely without pixel response."""
    img = prof.drawImage(nx=n, ny=n, scale=scale, method="no_pixel")
    res = galsim.hsm.FindAdaptiveMom(img)
    return res.observed_shape.g1, res.observed_shape.g2, res.moments_sigma * scale


def test_gaussian_round_and_elliptical():
    prof, truth = make_psf({"type": "gaussian", "sigma": 2.0}, 0.3, 0.4)
    assert truth == {"tru_psf_g1": 0.0, "tru_psf_g2": 0.0, "tru_psf_sigma": 2.0}
    assert prof.flux == pytest.approx(1.0)
    prof, truth = make_psf({"type": "gaussian", "fwhm": 3.0, "g1": 0.1, "g2": -0.05}, 0, 0)
    g1, g2, sigma = hsm(prof)
    assert truth["tru_psf_sigma"] == pytest.approx(3.0 / (2 * math.sqrt(2 * math.log(2))))
    assert (g1, g2, sigma) == pytest.approx(
        (truth["tru_psf_g1"], truth["tru_psf_g2"], truth["tru_psf_sigma"]), abs=1e-5
    )
    assert (truth["tru_psf_g1"], truth["tru_psf_g2"]) == (0.1, -0.05)


def test_moffat_truth_matches_hsm():
    prof, truth = make_psf(
        {"type": "moffat", "beta": 3.0, "fwhm": 3.0, "g1": 0.05, "g2": 0.02}, 0, 0
    )
    assert prof.calculateFWHM() == pytest.approx(3.0, rel=0.1)
    g1, g2, sigma = hsm(prof)
    assert g1 == pytest.approx(0.05, abs=1e-5) and g2 == pytest.approx(0.02, abs=1e-5)
    assert sigma == pytest.approx(truth["tru_psf_sigma"], rel=1e-3)
    _, by_hlr = make_psf({"type": "moffat", "beta": 3.0, "half_light_radius": 1.5}, 0, 0)
    assert by_hlr["tru_psf_sigma"] != truth["tru_psf_sigma"] and by_hlr["tru_psf_g1"] == 0.0


@pytest.mark.parametrize(
    "x, y, e1, e2, sigma",
    [
        (0, 0, -0.25, 0.0, 1.75),
        (1, 0, 0.25, 0.0, 2.0),
        (0, 1, -0.25, 0.25, 2.0),
        (1, 1, 0.25, 0.25, 2.25),
        (0.5, 0.5, 0.0, 0.125, 2.0),
        (0.3, 0.9, -0.1, 0.225, 2.05),
    ],
)
def test_field_psf_follows_the_papers_toy_model(x, y, e1, e2, sigma):
    spec = {"type": "field"}
    prof, truth = make_psf(spec, x, y)
    assert truth["tru_psf_g1"] == pytest.approx(e1)
    assert truth["tru_psf_g2"] == pytest.approx(e2)
    assert truth["tru_psf_sigma"] == pytest.approx(sigma)
    g1, g2, s = hsm(prof)
    assert (g1, g2, s) == pytest.approx((e1, e2, sigma), abs=1e-5)  # GalSim g convention, area kept
    assert psf_varies(spec)


def test_field_psf_parameters_and_bad_positions():
    spec = {"type": "field", "sigma_mean": 3.0, "sigma_slope": 0.0, "e1_min": 0.0, "e1_max": 0.0}
    _, truth = make_psf(spec, 1.0, 1.0)
    assert truth == pytest.approx({"tru_psf_g1": 0.0, "tru_psf_g2": 0.25, "tru_psf_sigma": 3.0})
    with pytest.raises(ConfigError):
        make_psf({"type": "field", "sigma_slope": 1.0}, -5.0, -5.0)  # sigma < 0 there


def test_psf_varies_only_for_field():
    assert not psf_varies({"type": "gaussian", "sigma": 2.0})
    assert not psf_varies({"type": "euclid"})


def test_blackbody_photon_weights():
    lam = np.array([550.0, 900.0])
    w = blackbody_photons(lam, 5800.0)
    # photon counts: lam^-4 / (exp(hc/lam k T) - 1)
    hc_k = 6.62607015e-34 * 2.99792458e8 / 1.380649e-23
    expected = (lam * 1e-9) ** -4 / np.expm1(hc_k / (lam * 1e-9 * 5800.0))
    np.testing.assert_allclose(w, expected)
    # peak of B_lambda in photons for 5800 K lies near 630 nm (Wien for photons: 3670 um K / T)
    grid = np.linspace(300, 1500, 2401)
    assert grid[np.argmax(blackbody_photons(grid, 5800.0))] == pytest.approx(
        3.6697e6 / 5800.0, abs=2
    )


def test_euclid_psf_is_cached_and_plausible():
    spec = {"type": "euclid", "size": 32}  # smaller stamp keeps the test fast
    prof, truth = make_psf(spec, 0.0, 0.0)
    prof2, truth2 = make_psf(dict(spec), 0.7, 0.2)
    assert prof2 is prof and truth2 == truth  # cached: the same object, not rebuilt (no timing)
    assert prof.flux == pytest.approx(1.0)
    # Round (six struts, no aberrations); paper: FWHM ~ 0.1" = 1 VIS pixel when oversampled.
    assert abs(truth["tru_psf_g1"]) < 1e-3 and abs(truth["tru_psf_g2"]) < 1e-3
    assert 0.4 < truth["tru_psf_sigma"] < 0.55
    assert 0.9 < prof.calculateFWHM() < 1.3
    # At the native pixel scale the PSF is wider (the paper measures ~0.15").
    img = prof.drawImage(nx=32, ny=32, scale=1.0)
    assert 0.65 < galsim.hsm.FindAdaptiveMom(img).moments_sigma < 0.85
    assert not psf_includes_pixel(spec)


def test_euclid_psf_sensitivity_to_the_spectrum_is_small():
    _, hot = make_psf({"type": "euclid", "size": 32, "temperature": 6500.0}, 0, 0)
    _, ref = make_psf({"type": "euclid", "size": 32}, 0, 0)
    # bluer light, sharper diffraction pattern; but only by a couple of per cent
    assert 0.97 < hot["tru_psf_sigma"] / ref["tru_psf_sigma"] < 1.0


def _starfield(path, size=24):
    field = galsim.ImageF(3 * size, 3 * size, scale=1.0)
    for k in range(9):
        i, j = k % 3, k // 3
        b = galsim.BoundsI(i * size + 1, (i + 1) * size, j * size + 1, (j + 1) * size)
        galsim.Gaussian(sigma=1.5 + 0.25 * k, flux=50.0).shear(g1=0.02 * k, g2=0.0).drawImage(
            field[b], method="no_pixel"
        )
    write_image(path, field.array, fmt="test")
    return path


@pytest.mark.parametrize("index", [0, 4, 8])
def test_stamp_psf_picks_the_right_star(tmp_path, index):
    path = _starfield(tmp_path / "stars.fits")
    spec = {"type": "stamp", "path": str(path), "stamp_size": 24, "index": index}
    prof, truth = make_psf(spec, 0, 0)
    assert truth["tru_psf_sigma"] == pytest.approx(1.5 + 0.25 * index, rel=2e-3)
    assert truth["tru_psf_g1"] == pytest.approx(0.02 * index, abs=2e-3)
    assert prof.flux == pytest.approx(1.0)
    # the interpolated star reproduces the star's moments
    g1, _, sigma = hsm(prof, scale=0.25, n=200)
    assert sigma == pytest.approx(truth["tru_psf_sigma"], rel=1e-2)
    assert g1 == pytest.approx(truth["tru_psf_g1"], abs=5e-3)
    assert psf_includes_pixel(spec)
    assert not psf_includes_pixel({**spec, "pixel_scale": 0.2})
    assert not psf_includes_pixel({**spec, "includes_pixel": False})


def test_stamp_psf_single_star_and_pixel_scale(tmp_path):
    star = galsim.Gaussian(sigma=5.0).drawImage(nx=64, ny=64, scale=1.0, method="no_pixel")
    write_image(tmp_path / "star.fits", star.array, fmt="test")
    # a star image sampled 5x finer than the simulation pixels
    _, truth = make_psf(
        {"type": "stamp", "path": str(tmp_path / "star.fits"), "pixel_scale": 0.2}, 0, 0
    )
    assert truth["tru_psf_sigma"] == pytest.approx(1.0, rel=1e-3)


def test_stamp_psf_errors(tmp_path):
    path = _starfield(tmp_path / "stars.fits")
    with pytest.raises(ConfigError, match="psf.index"):
        make_psf({"type": "stamp", "path": str(path), "stamp_size": 24, "index": 9}, 0, 0)
    with pytest.raises(InputError, match="does not divide"):
        make_psf({"type": "stamp", "path": str(path), "stamp_size": 25}, 0, 0)
    with pytest.raises(InputError, match="no such file"):
        validate_psf_config({"type": "stamp", "path": str(tmp_path / "nope.fits")})
    (tmp_path / "bad.fits").write_text("nonsense")
    with pytest.raises(InputError, match="bad.fits"):
        make_psf({"type": "stamp", "path": str(tmp_path / "bad.fits")}, 0, 0)
    write_image(tmp_path / "nan.fits", np.full((10, 10), np.nan), fmt="test")
    with pytest.raises(InputError, match="NaN"):
        make_psf({"type": "stamp", "path": str(tmp_path / "nan.fits")}, 0, 0)


@pytest.mark.parametrize(
    "spec, key",
    [
        ({"sigma": 2.0}, "psf.type"),
        ({"type": "airy", "sigma": 2.0}, "psf.type"),
        ({"type": "gaussian", "sigma": float("nan")}, "psf.sigma"),
        ({"type": "gaussian", "sigma": -1.0}, "psf.sigma"),
        ({"type": "gaussian", "sigma": 0.0}, "psf.sigma"),
        ({"type": "gaussian", "sigma": "2"}, "psf.sigma"),
        ({"type": "gaussian"}, "psf.sigma"),
        ({"type": "gaussian", "sigma": 2.0, "fwhm": 3.0}, "psf.sigma"),
        ({"type": "gaussian", "sigma": 2.0, "sigam": 3.0}, "psf.sigam"),
        ({"type": "gaussian", "sigma": 2.0, "g1": 0.8, "g2": 0.8}, "psf"),
        ({"type": "gaussian", "sigma": 2.0, "g1": float("inf")}, "psf.g1"),
        ({"type": "moffat", "fwhm": 3.0}, "psf.beta"),
        ({"type": "moffat", "beta": 3.0}, "psf.fwhm"),
        ({"type": "moffat", "beta": 1.0, "fwhm": 3.0}, "psf.beta"),
        ({"type": "moffat", "beta": 3.0, "fwhm": 3.0, "trunc": -1.0}, "psf.trunc"),
        ({"type": "field", "sigma_mean": 0.1}, "psf.sigma_mean"),
        ({"type": "field", "e1_max": 1.5}, "psf"),
        ({"type": "euclid", "obscuration": 1.2}, "psf.obscuration"),
        ({"type": "euclid", "oversampling": 2.5}, "psf.oversampling"),
        ({"type": "euclid", "lam_step": float("nan")}, "psf.lam_step"),
        ({"type": "stamp"}, "psf.path"),
        ({"type": "stamp", "path": 3}, "psf.path"),
    ],
)
def test_validation_names_the_bad_key(spec, key):
    with pytest.raises(ConfigError) as err:
        validate_psf_config(spec)
    assert str(err.value).startswith(key)


def test_valid_specs_pass():
    for spec in (
        {"type": "gaussian", "sigma": 2.0},
        {"type": "gaussian", "fwhm": 2.0, "g1": -0.1, "g2": 0.1},
        {"type": "moffat", "beta": 2.5, "half_light_radius": 1.2, "trunc": 10.0},
        {"type": "moffat", "beta": 1.05, "fwhm": 3.0, "trunc": 10.0},
        {"type": "field"},
        {"type": "euclid"},
    ):
        validate_psf_config(spec)
