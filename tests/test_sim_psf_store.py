"""Fixed PSFs in the disk cache: the renderer draws the same stamps from them without GalSim."""

from __future__ import annotations

import numpy as np
import pytest

from megalut_cli import cache
from megalut_cli.sim import psf_store
from megalut_cli.sim.distributions import parse_distribution
from megalut_cli.sim.draw import get_psf, psf_cache_key
from megalut_cli.sim.render import StampRenderer


@pytest.fixture
def folder(tmp_path, monkeypatch):
    monkeypatch.setenv(cache.CACHE_ENV, str(tmp_path / "cache"))
    return tmp_path / "cache"


def test_which_psfs_are_stored():
    assert psf_store.stores_psf({"type": "gaussian", "sigma": 2.0}, False)
    assert psf_store.stores_psf({"type": "moffat", "beta": 3.0, "fwhm": 2.0}, False)
    assert not psf_store.stores_psf({"type": "field"}, True)  # an entry per field position
    assert not psf_store.stores_psf({"type": "stamp", "path": "star.fits"}, False)  # a file
    drawn = parse_distribution({"type": "uniform", "min": 1.5, "max": 2.5}, "psf.sigma")
    assert not psf_store.stores_psf({"type": "gaussian", "sigma": drawn}, False)


def _galaxies(m: int = 40) -> dict:
    rng = np.random.default_rng(5)
    return {
        "profile": "sersic",
        "rad": rng.uniform(1.0, 6.0, m),
        "flux": rng.uniform(50.0, 500.0, m),
        "sersicn": rng.choice([1.0, 2.5, 4.0], m),
        "e1": rng.uniform(-0.4, 0.4, m),
        "e2": rng.uniform(-0.4, 0.4, m),
        "g1": np.full(m, 0.03),
        "g2": np.full(m, -0.02),
        "dx": rng.uniform(-0.5, 0.5, m),
        "dy": rng.uniform(-0.5, 0.5, m),
    }


@pytest.mark.parametrize(
    "spec, gsparams",
    [
        ({"type": "gaussian", "sigma": 2.0, "g1": 0.05}, {}),
        ({"type": "moffat", "beta": 3.0, "fwhm": 2.5}, {"folding_threshold": 1e-2}),
    ],
)
def test_stored_psf_draws_galsims_stamps_and_loads_without_building(folder, spec, gsparams):
    key = psf_cache_key(spec, 0.0, 0.0, False, gsparams)
    profile, truth = get_psf(spec, 0.0, 0.0, False, gsparams)
    gals = _galaxies()
    reference = StampRenderer(32, gsparams).draw(profile, key, "auto", **gals)

    built = []

    def build():
        built.append(1)
        return get_psf(spec, 0.0, 0.0, False, gsparams)

    first = psf_store.StoredPsf(key, build)
    assert first.truth() == truth
    np.testing.assert_array_equal(
        StampRenderer(32, gsparams).draw(first, key, "auto", **gals), reference
    )
    assert built and any(folder.glob("psf-*.npz"))

    def no_build():
        raise AssertionError("built again: its entries were not loaded")

    later = psf_store.StoredPsf(key, no_build)  # another process: everything from disk
    assert later.truth() == truth
    again = StampRenderer(32, gsparams).draw(later, key, "auto", **gals)
    np.testing.assert_array_equal(again, reference)
    assert again.dtype == reference.dtype


def test_the_key_names_galsim_numpy_and_the_code(folder, monkeypatch):
    key = psf_store.stored_psf_key("gaussian 2")
    assert "galsim=" in key and f"numpy={np.__version__}" in key and "code=" in key
    monkeypatch.setattr(psf_store, "galsim_version", lambda: "0.0")
    assert psf_store.stored_psf_key("gaussian 2") != key


def test_a_cache_turned_off_builds_every_time(monkeypatch):
    monkeypatch.setenv(cache.CACHE_ENV, "none")
    spec = {"type": "gaussian", "sigma": 1.5}
    key = psf_cache_key(spec, 0.0, 0.0, False, {})
    stored = psf_store.StoredPsf(key, lambda: get_psf(spec, 0.0, 0.0, False, {}))
    assert stored.truth()["tru_psf_sigma"] == 1.5
    profile, _ = get_psf(spec, 0.0, 0.0, False, {})
    gals = _galaxies(5)
    np.testing.assert_array_equal(
        StampRenderer(24).draw(stored, key, "auto", **gals),
        StampRenderer(24).draw(profile, key, "auto", **gals),
    )
