"""Sérsic twins of real galaxies: the fit, the config keys, and common random numbers."""

from __future__ import annotations

from pathlib import Path

import galsim
import numpy as np
import pytest
from sim_configs import write

from megalut_cli.catalog import read_catalog
from megalut_cli.errors import ConfigError, InputError
from megalut_cli.sim.config import load_config
from megalut_cli.sim.twins import fit_sersic, load_twins

COSMOS_DIR = Path(__file__).resolve().parents[1] / "examples" / "data" / "cosmos"
RGC = COSMOS_DIR / "real_galaxy_catalog_26_extension_example.fits"
TWINS = COSMOS_DIR / "real_galaxy_catalog_26_extension_sersic_twins.fits"

CONFIG = f"""
[structure]
n_cases = 2
n_realizations = 6
per_realization = ["galaxy"]
snc = "pairs"
stamp_size = 48
offset = 0.5

[shear]
g1 = {{type = "uniform", min = -0.1, max = 0.1}}
g2 = {{type = "uniform", min = -0.1, max = 0.1}}

[galaxy]
profile = "real"
real_catalog = "{RGC}"
pixel_scale = 0.06
index = {{type = "grid", values = [4, 5, 9]}}
real_order = "each"
hst_noise = "symmetrize"
twin = "none"
twin_catalog = "{TWINS}"
flux = {{type = "uniform", min = 300.0, max = 1500.0}}

[psf]
type = "gaussian"
sigma = 2.0

[noise]
type = "gaussian"
sigma = 1.0
"""


def test_fit_recovers_a_sersic_through_the_hst_psf():
    """A Sérsic drawn with a COSMOS galaxy's HST PSF and noise is fitted back: n, size,
    shape, centroid and flux within a few per cent at S/N ~ 300."""
    rgc = galsim.RealGalaxyCatalog(str(RGC), dir=str(COSMOS_DIR))
    psf, image, var = rgc.getPSF(5), rgc.getGalImage(5).copy(), float(rgc.variance[5])
    truth = (
        galsim.Sersic(n=2.5, half_light_radius=0.25, flux=100.0)
        .shear(g1=0.3, g2=-0.2)
        .shift(0.02, -0.03)
    )
    galsim.Convolve(truth, psf).drawImage(image=image, method="no_pixel")
    image.array[:] += np.random.default_rng(1).normal(0.0, np.sqrt(var), image.array.shape)
    fit = fit_sersic(image, psf, var)
    assert fit["sersicn"] == pytest.approx(2.5, abs=0.15)
    assert fit["hlr"] == pytest.approx(0.25, rel=0.03)
    assert fit["g1"] == pytest.approx(0.3, abs=0.015) and fit["g2"] == pytest.approx(
        -0.2, abs=0.015
    )
    assert fit["dx"] == pytest.approx(0.02, abs=0.005) and fit["dy"] == pytest.approx(
        -0.03, abs=0.005
    )
    assert fit["flux"] == pytest.approx(100.0, rel=0.02)
    assert fit["chi2_dof"] == pytest.approx(1.0, abs=0.03)  # fixed seed: achieved 0.992


def test_shipped_twin_catalog_covers_the_bright_galaxies():
    twins = load_twins(str(TWINS))
    mag = read_catalog(RGC)["MAG"]
    bright = np.flatnonzero(mag < 24.5)
    assert set(bright.tolist()) <= set(twins)
    n = np.array([twins[i][0] for i in bright])
    assert np.all((n >= 0.3) & (n <= 6.0)) and np.ptp(n) > 2  # a range of profiles


def test_config_keys(tmp_path):
    cfg = load_config(write(tmp_path, CONFIG, "t.toml"), ["galaxy.twin='sersic'"])
    assert cfg.galaxy.real["twin"] == "sersic" and cfg.galaxy.real["rows"] == (4, 5, 9)
    with pytest.raises(ConfigError, match="galaxy.twin: unknown value 'bulge'"):
        load_config(write(tmp_path, CONFIG, "t.toml"), ["galaxy.twin='bulge'"])
    no_cat = CONFIG.replace(f'twin_catalog = "{TWINS}"\n', "")
    with pytest.raises(ConfigError, match="galaxy.twin_catalog: missing"):
        load_config(write(tmp_path, no_cat, "t.toml"), ["galaxy.twin='sersic'"])
    with pytest.raises(InputError, match="not a Sérsic-twin catalog"):
        load_config(
            write(tmp_path, CONFIG.replace(str(TWINS), str(RGC)), "t.toml"),
            ["galaxy.twin='sersic'"],
        )
    with pytest.raises(ConfigError, match="galaxy.real_order: 'each' needs"):
        load_config(
            write(
                tmp_path,
                CONFIG.replace('index = {type = "grid", values = [4, 5, 9]}', "index = 4"),
                "t.toml",
            )
        )


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """A real set and its twin set from one config and seed (measured)."""
    from click.testing import CliRunner

    from megalut_cli.cli import main

    d = tmp_path_factory.mktemp("twins")
    cfg = write(d, CONFIG, "t.toml")
    out = {}
    for name, extra in (("real", []), ("twin", ["galaxy.twin=sersic"])):
        res = CliRunner().invoke(
            main,
            [
                "simulate",
                str(cfg),
                *extra,
                "-o",
                str(d / f"{name}.fits"),
                "--measure",
                "--seed",
                "7",
                "--n-cases",
                "4",
            ],
        )
        assert res.exit_code == 0, res.output
        out[name] = read_catalog(d / f"{name}.fits")
    return out


def test_common_random_numbers(pair):
    """Same shears, galaxies (each under every shear), rotations, offsets, fluxes and HST
    noise variance; only tru_twin differs."""
    real, twin = pair["real"], pair["twin"]
    truth = [c for c in real.colnames if c.startswith("tru_") and c != "tru_twin"]
    assert {"tru_twin_rad", "tru_twin_sersicn", "tru_hst_noise_var", "tru_theta", "tru_dx"} <= set(
        truth
    )
    for c in truth + ["case", "rea"]:
        np.testing.assert_array_equal(real[c], twin[c], err_msg=c)
    assert np.all(real["tru_twin"] == 0) and np.all(twin["tru_twin"] == 1)
    idx = np.asarray(real["tru_real_index"]).reshape(4, 6)
    assert np.all(idx == [4, 4, 5, 5, 9, 9])


def test_twins_look_like_their_galaxies_with_the_same_noise(pair):
    """The twin's measured size and shape follow its real galaxy's, and the noise on the
    stamp edges is statistically the same (the HST-noise model and Gaussian rest are shared)."""
    real, twin = pair["real"], pair["twin"]
    ok = (real["flags"] == 0) & (twin["flags"] == 0)
    assert ok.mean() > 0.9
    ratio = np.asarray(twin["adamom_sigma"][ok] / real["adamom_sigma"][ok])
    assert np.median(ratio) == pytest.approx(1.0, abs=0.1)
    dg = np.hypot(
        twin["adamom_g1"][ok] - real["adamom_g1"][ok], twin["adamom_g2"][ok] - real["adamom_g2"][ok]
    )
    assert np.median(dg) < 0.1
    sky = np.asarray(twin["skymad"] / real["skymad"])
    assert np.mean(sky) == pytest.approx(1.0, abs=0.05)


def test_surface_brightness_of_real_galaxies_uses_the_twin_radius(tmp_path):
    """``sb`` for real galaxies: F = S·π·R² with R the fitted half-light radius, so that the
    fluxes follow the training population's size-flux coupling (Sect. 5.1)."""
    from megalut_cli.sim.structure import draw_case

    cfg_text = CONFIG.replace(
        'flux = {type = "uniform", min = 300.0, max = 1500.0}',
        'sb = {type = "uniform", min = 5.0, max = 15.0}',
    )
    cfg = load_config(write(tmp_path, cfg_text, "t.toml"))
    truth = draw_case(cfg, 2, 3).truth
    twins = load_twins(str(TWINS))
    rad = np.array([twins[int(i)][1] / 0.06 for i in truth["tru_real_index"]])
    sb = np.asarray(truth["tru_flux"]) / (np.pi * rad**2)
    assert np.all((sb >= 5.0) & (sb <= 15.0)) and np.ptp(sb) > 1.0
    np.testing.assert_allclose(truth["tru_sb"], sb, rtol=1e-12)
    with pytest.raises(
        ConfigError, match="galaxy.sb: profile 'real' takes its size from galaxy.twin_catalog"
    ):
        load_config(write(tmp_path, cfg_text.replace(f'twin_catalog = "{TWINS}"\n', ""), "t.toml"))
