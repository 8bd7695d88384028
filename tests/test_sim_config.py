"""Config loading, overrides, validation errors, catalog (GEMS-like) sampling."""

from __future__ import annotations

import fitsio
import numpy as np
import pytest
from sim_configs import COSMOS, TINY, write

from megalut_cli.configfile import apply_overrides, parse_override
from megalut_cli.errors import ConfigError, InputError
from megalut_cli.sim.config import load_config
from megalut_cli.sim.structure import draw_case


def test_load_tiny(tmp_path):
    cfg = load_config(write(tmp_path))
    s = cfg.structure
    assert (s.n_cases, s.n_realizations, s.stamp_size, s.snc) == (3, 4, 24, "ring")
    assert s.grid_nx == 4  # ceil(sqrt(12))
    assert len(cfg.sha256) == 64
    assert cfg.galaxy.flux_mode == "sb"
    assert not cfg.psf_varies


def test_structure_overrides(tmp_path):
    cfg = load_config(write(tmp_path), n_cases=7, n_realizations=10)
    assert cfg.structure.n_cases == 7 and cfg.structure.n_realizations == 10
    assert '"n_cases": 7' in cfg.to_json()


def test_dotted_overrides(tmp_path):
    cfg = load_config(
        write(tmp_path), ["noise.sigma=0.25", 'galaxy.rad={type="uniform", min=2, max=2.5}']
    )
    assert cfg.noise.params["sigma"].bounds() == (0.25, 0.25)
    assert cfg.galaxy.params["rad"].bounds() == (2.0, 2.5)
    assert parse_override("psf.type=moffat") == (["psf", "type"], "moffat")
    assert parse_override("a.b=[1, 2]") == (["a", "b"], [1, 2])
    assert apply_overrides({"a": {"b": 1}}, ["a.c=2"]) == {"a": {"b": 1, "c": 2}}
    with pytest.raises(ConfigError, match="expected KEY=VALUE"):
        parse_override("noise.sigma")
    with pytest.raises(ConfigError, match="noise.sigma is not a table"):
        apply_overrides({"noise": {"sigma": 1}}, ["noise.sigma.x=1"])


@pytest.mark.parametrize(
    "replace, overrides, message",
    [
        ({"n_cases = 3\n": ""}, [], "structure.n_cases: missing"),
        ({"n_cases = 3": "n_cases = 0"}, [], "structure.n_cases: must be >= 1"),
        ({"n_cases = 3": "n_cases = 2.5"}, [], "structure.n_cases: expected an integer"),
        ({'snc = "ring"': 'snc = "circle"'}, [], "structure.snc: unknown value 'circle'"),
        (
            {'snc = "ring"': 'snc = "pairs"', "n_realizations = 4": "n_realizations = 3"},
            [],
            "structure.n_realizations: snc = 'pairs'",
        ),
        (
            {'per_realization = ["angle"]': 'per_realization = ["colour"]'},
            [],
            "structure.per_realization",
        ),
        ({"stamp_size = 24": "stamp_size = 4"}, [], "structure.stamp_size"),
        (
            {'rad = {type = "uniform", min = 1.5, max = 3.0}': "rad = nan"},
            [],
            "galaxy.rad: must be a finite number",
        ),
        (
            {'rad = {type = "uniform", min = 1.5, max = 3.0}': "rad = -2.0"},
            [],
            "galaxy.rad: the half-light radius must be > 0",
        ),
        (
            {
                'rad = {type = "uniform", min = 1.5, max = 3.0}': (
                    'rad = {type = "uniform", min = 0.0, max = 3.0}'
                )
            },
            [],
            "galaxy.rad",
        ),
        ({'rad = {type = "uniform", min = 1.5, max = 3.0}\n': ""}, [], "galaxy.rad: missing"),
        (
            {'rad = {type = "uniform", min = 1.5, max = 3.0}': 'rad = {type = "gamma", k = 2}'},
            [],
            "galaxy.rad.type: unknown distribution 'gamma'",
        ),
        ({"sb = {": "flux = 100.0\nsb = {"}, [], "give exactly one of galaxy.flux"),
        ({"sb = {": "mag = 22.0\n#"}, [], "instrument.zeropoint: missing (needed by galaxy.mag)"),
        ({"max = 0.6}": "max = 1.2}"}, [], "galaxy.ellipticity: the modulus must be < 1"),
        (
            {"step = 0.5}": "step = 0.5}\nsersicn_step = 0"},
            ["galaxy.sersicn={type='uniform', min=0.1, max=2}"],
            "galaxy.sersicn: GalSim supports",
        ),
        (
            {'type = "gaussian"\nsigma = 1.5': 'type = "hexagon"'},
            [],
            "psf.type: unknown PSF type 'hexagon'",
        ),
        ({'type = "gaussian"\nsigma = 1.5': 'type = "gaussian"\nsigma = -1.5'}, [], "psf.sigma"),
        ({"[psf]\ntype": "[psf]\nkind"}, [], "psf.type: missing"),
        (
            {'type = "gaussian"\nsigma = 1.0': 'type = "poisson"'},
            [],
            "noise.type: unknown value 'poisson'",
        ),
        ({'type = "gaussian"\nsigma = 1.0': 'type = "gaussian"'}, [], "noise.sigma: missing"),
        (
            {'type = "gaussian"\nsigma = 1.0': 'type = "ccd"\nsky_mag = 22.0'},
            [],
            "instrument.pixel_scale: missing",
        ),
        ({"[noise]": "[noise]\ncolour = 1"}, [], "noise.colour: unknown key"),
        ({"[shear]": "[shaer]"}, [], "shaer: unknown table"),
        ({"offset = 0.5": "offset = 0.5\nofset = 1"}, [], "structure.ofset: unknown key"),
        (
            {"[psf]": "[gsparams]\nfolding_threshold = 2.0\n\n[psf]"},
            [],
            "gsparams.folding_threshold: must be in (0, 1)",
        ),
        ({"[psf]": "[gsparams]\nfolding = 0.1\n\n[psf]"}, [], "gsparams.folding: unknown key"),
        (
            {"[psf]": "[gsparams]\nmaximum_fft_size = 1.5\n\n[psf]"},
            [],
            "gsparams.maximum_fft_size: expected an integer",
        ),
        (
            {"[shear]\ng1": '[shear]\ng1 = {type = "uniform", min = -0.9, max = 0.9}\n#'},
            ["shear.g2=0.9"],
            "shear: the reduced shear",
        ),
    ],
)
def test_config_errors_name_the_key(tmp_path, replace, overrides, message):
    with pytest.raises(ConfigError) as err:
        load_config(write(tmp_path, replace=replace), overrides)
    assert message in str(err.value), str(err.value)
    assert "\n" not in str(err.value)


def test_invalid_toml_and_missing_file(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[structure\nn_cases = 3")
    with pytest.raises(ConfigError, match="invalid TOML"):
        load_config(bad)
    with pytest.raises(InputError, match="no such file"):
        load_config(tmp_path / "missing.toml")


GEMS = """
[catalog]
path = "{path}"
select = "mag_auto > 20.5 & mag_auto < 25.0 & sersicfit_2 > 0.3 & sersicfit_2 < 6.0 & hlr_0 < 1.2"

[galaxy]
profile = "sersic"
mag = {{type = "catalog", column = "mag_auto"}}
sersicn = {{type = "catalog", column = "sersicfit", element = 2}}
sersicn_step = 0
rad = {{type = "catalog", column = "hlr", element = 0, scale = 10.0}}
ellipticity = {{type = "rayleigh", mode = 0.25, min = 0.0, max = 0.7}}

[instrument]
pixel_scale = 0.1
exptime = 1695.0
gain = 3.1
zeropoint = 24.6
"""


def _gems_config(tmp_path, path=COSMOS, extra=""):
    text = (
        TINY.split("[galaxy]")[0]
        + GEMS.format(path=path)
        + "\n[psf]"
        + TINY.split("[psf]")[1]
        + extra
    )
    text = text.replace('per_realization = ["angle"]', 'per_realization = ["galaxy"]').replace(
        'snc = "ring"', 'snc = "none"'
    )
    return write(tmp_path, text)


def test_joint_catalog_sampling(tmp_path):
    cfg = load_config(_gems_config(tmp_path), n_cases=20, n_realizations=50)
    data = fitsio.read(str(COSMOS), ext=1)
    sel = (
        (data["mag_auto"] > 20.5)
        & (data["mag_auto"] < 25)
        & (data["sersicfit"][:, 2] > 0.3)
        & (data["sersicfit"][:, 2] < 6)
        & (data["hlr"][:, 0] < 1.2)
    )
    assert cfg.catalog_rows == int(sel.sum())
    rows = {
        (round(m, 9), round(n, 9), round(r * 10, 9))
        for m, n, r in zip(data["mag_auto"][sel], data["sersicfit"][sel, 2], data["hlr"][sel, 0])
    }
    seen = set()
    for case in range(20):
        t = draw_case(cfg, 3, case).truth
        assert len(np.unique(t["tru_mag"])) > 1  # galaxies vary per realization
        for m, n, r in zip(t["tru_mag"], t["tru_sersicn"], t["tru_rad"]):
            key = (round(m, 9), round(n, 9), round(r, 9))
            assert key in rows  # mag, n and radius come from the same catalog row
            seen.add(key)
        flux = 1695.0 / 3.1 * 10 ** (-0.4 * (t["tru_mag"] - 24.6))
        np.testing.assert_allclose(t["tru_flux"], flux, rtol=1e-12)
    assert len(seen) > 0.9 * len(rows)


def test_catalog_errors(tmp_path):
    with pytest.raises(ConfigError, match="galaxy.rad.element: 'hlr' is an array column"):
        load_config(_gems_config(tmp_path), ['galaxy.rad={type="catalog", column="hlr"}'])
    with pytest.raises(ConfigError, match="galaxy.mag.column: no column 'MAG'"):
        load_config(_gems_config(tmp_path), ['galaxy.mag={type="catalog", column="MAG"}'])
    with pytest.raises(ConfigError, match="catalog.select: no usable row"):
        load_config(_gems_config(tmp_path), ["catalog.select='mag_auto > 99'"])
    with pytest.raises(InputError, match="catalog.path: no such file"):
        load_config(_gems_config(tmp_path, path="nowhere.fits"))
    with pytest.raises(ConfigError, match="needs a \\[catalog\\] table"):
        load_config(
            write(
                tmp_path,
                replace={
                    'sb = {type = "uniform", min = 5.0, max = 15.0}': (
                        'flux = {type = "catalog", column = "flux"}'
                    )
                },
            )
        )


def test_catalog_path_relative_to_config(tmp_path, monkeypatch):
    import shutil

    shutil.copy(COSMOS, tmp_path / "cat.fits")
    cfg_path = _gems_config(tmp_path, path="cat.fits")
    monkeypatch.chdir(tmp_path.parent)
    cfg = load_config(cfg_path)
    assert cfg.catalog_path == str((tmp_path / "cat.fits").resolve())
