"""Common-random-number (CRN) sets, ``structure.common = true``: the same galaxies,
position angles, offsets and noise in every case; only the case-level draws differ."""

from __future__ import annotations

from pathlib import Path

import fitsio
import numpy as np
import pytest
from sim_configs import write

from megalut_cli.catalog import catalog_info, read_catalog
from megalut_cli.errors import ConfigError
from megalut_cli.measure.measure import measure_file
from megalut_cli.shear.predict import predict_catalog
from megalut_cli.sim.config import load_config
from megalut_cli.sim.simulate import simulate
from megalut_cli.sim.structure import draw_case

MODEL = Path(__file__).resolve().parents[1] / "models" / "fiducial.h5"
#: Truth of a realization (everything but the case-level shear, PSF and noise level).
PER_REALIZATION = (
    "tru_rad",
    "tru_flux",
    "tru_sb",
    "tru_sersicn",
    "tru_ell",
    "tru_theta",
    "tru_e1",
    "tru_e2",
    "tru_dx",
    "tru_dy",
)
CRN = ['structure.per_realization=["galaxy"]', "structure.snc=pairs", "structure.common=true"]


def _cfg(tmp_path, overrides=CRN, n_cases=4, n_rea=10, **replace):
    return load_config(
        write(tmp_path, replace=replace or None),
        list(overrides),
        n_cases=n_cases,
        n_realizations=n_rea,
    )


def test_same_galaxies_offsets_and_noise_in_every_case(tmp_path):
    cfg = _cfg(tmp_path)
    draws = [draw_case(cfg, 21, c) for c in range(4)]
    ref = draws[0]
    assert len(np.unique(ref.truth["tru_rad"])) == 5  # a new galaxy per pair
    for d in draws[1:]:
        for k in PER_REALIZATION:
            assert np.array_equal(d.truth[k], ref.truth[k]), k
        assert np.array_equal(d.noise_seeds, ref.noise_seeds)
        assert np.array_equal(d.offsets, ref.offsets)
        assert np.array_equal(d.galaxy_index, ref.galaxy_index)
    # the shear is drawn per case
    assert len({float(d.truth["tru_g1"][0]) for d in draws}) == 4
    # 90-degree pairs within every case
    e = ref.truth["tru_e1"] + 1j * ref.truth["tru_e2"]
    np.testing.assert_allclose(e[1::2], -e[0::2], atol=1e-15)


def test_independent_sets_differ_between_cases(tmp_path):
    """The control: without common = true every case has its own galaxies and noise."""
    cfg = _cfg(tmp_path, CRN[:2])
    a, b = draw_case(cfg, 21, 0), draw_case(cfg, 21, 1)
    assert not np.any(a.truth["tru_rad"] == b.truth["tru_rad"])
    assert not np.any(a.noise_seeds == b.noise_seeds)
    # and the case-level draws are the same with or without common random numbers
    c = draw_case(_cfg(tmp_path, CRN), 21, 1)
    assert (
        c.truth["tru_g1"][0] == b.truth["tru_g1"][0]
        and c.truth["tru_g2"][0] == b.truth["tru_g2"][0]
    )


def test_case_level_noise_and_psf_stay_per_case(tmp_path):
    cfg = _cfg(
        tmp_path,
        [
            *CRN,
            'noise.sigma={type="uniform", min=0.5, max=2.0}',
            'psf.sigma={type="uniform", min=1.2, max=2.0}',
        ],
    )
    draws = [draw_case(cfg, 3, c) for c in range(3)]
    assert len({d.noise.sigma for d in draws}) == 3
    assert len({d.psf_specs[0][0]["sigma"] for d in draws}) == 3
    for d in draws[1:]:
        assert np.array_equal(d.truth["tru_rad"], draws[0].truth["tru_rad"])
        assert np.array_equal(d.noise_seeds, draws[0].noise_seeds)


def test_knots_are_common_too(tmp_path):
    """Composite galaxies with star-forming knots: the knots of realization k are the same
    in every case (the knot seeds come from the common stream)."""
    text = (
        Path(__file__).resolve().parents[1] / "examples" / "realgal" / "tp-knots.toml"
    ).read_text()
    cfg = load_config(
        write(tmp_path, text, name="knots.toml"),
        [*CRN, "structure.offset=0.5"],
        n_cases=3,
        n_realizations=8,
    )
    a, b = draw_case(cfg, 4, 0), draw_case(cfg, 4, 2)
    assert len(np.unique(a.truth["tru_knot_seed"])) == 4
    for k in ("tru_knot_seed", "tru_knots", "tru_e1", "tru_rad"):
        assert np.array_equal(a.truth[k], b.truth[k]), k


def test_per_realization_psf_is_common_too(tmp_path):
    cfg = _cfg(
        tmp_path,
        [
            'structure.per_realization=["galaxy", "psf"]',
            "structure.snc=none",
            "structure.common=true",
            'psf.sigma={type="uniform", min=1.2, max=2.0}',
        ],
    )
    a, b = draw_case(cfg, 3, 0), draw_case(cfg, 3, 2)
    assert len(a.psf_specs) == 10
    assert [s[0]["sigma"] for s in a.psf_specs] == [s[0]["sigma"] for s in b.psf_specs]


@pytest.mark.parametrize(
    ("overrides", "words"),
    [
        (
            ['structure.per_realization=["angle"]', "structure.snc=none", "structure.common=true"],
            "include 'galaxy'",
        ),
        (
            [
                'structure.per_realization=["galaxy", "shear"]',
                "structure.snc=none",
                "structure.common=true",
            ],
            "shear must be drawn per case",
        ),
        (
            ['structure.per_realization=["galaxy"]', "structure.snc=ring", "structure.common=true"],
            "snc = 'ring'",
        ),
        (['structure.per_realization=["galaxy"]', "structure.common=1"], "expected true or false"),
    ],
)
def test_meaningless_combinations_refused(tmp_path, overrides, words):
    with pytest.raises(ConfigError, match="structure.common") as err:
        _cfg(tmp_path, overrides)
    assert words in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("sigma", [0.0, 1.0])
def test_stamps_identical_across_cases_at_equal_shear(tmp_path, sigma):
    """With the shear switched off, every case of a CRN set is the same image, noise-free or
    not: galaxies, offsets and noise all shared. Also independent of -j (work units split
    the cases)."""
    cfg = _cfg(
        tmp_path, [*CRN, "shear.g1=0.0", "shear.g2=0.0", f"noise.sigma={sigma}"], n_cases=3, n_rea=6
    )
    simulate(cfg, tmp_path / "c.fits", stamps=tmp_path / "s.fits", seed=5, measure=True)
    img = fitsio.read(str(tmp_path / "s.fits"))
    S = cfg.structure.stamp_size
    stamps = [
        img[r * S : (r + 1) * S, c * S : (c + 1) * S]
        for r in range(img.shape[0] // S)
        for c in range(img.shape[1] // S)
    ][:18]
    for case in (1, 2):
        for k in range(6):
            assert np.array_equal(stamps[case * 6 + k], stamps[k])
    t = read_catalog(tmp_path / "c.fits")
    assert t.meta["CRN"] is True
    for col in ("adamom_g1", "adamom_sigma", "tru_rad", "tru_e1", "tru_dx"):
        v = np.asarray(t[col]).reshape(3, 6)
        assert np.array_equal(v[1], v[0], equal_nan=True) and np.array_equal(
            v[2], v[0], equal_nan=True
        ), col
    simulate(cfg, tmp_path / "c2.fits", seed=5, measure=True, nproc=2)
    t2 = read_catalog(tmp_path / "c2.fits")
    for col in t.colnames:
        if col not in ("x", "y"):
            assert np.array_equal(np.asarray(t[col]), np.asarray(t2[col]), equal_nan=True), col


def test_noise_free_stamps_differ_only_by_the_shear(tmp_path):
    """Noise-free stamps of a CRN set: the same galaxy under two shears; its measured
    ellipticity moves with the shear, the same way for every galaxy (same sign)."""
    cfg = _cfg(
        tmp_path,
        [
            *CRN,
            "noise.sigma=0.0",
            "shear.g2=0.0",
            "structure.offset=0.0",
            'shear.g1={type="uniform", min=-0.1, max=0.1}',
        ],
        n_cases=2,
        n_rea=8,
    )
    simulate(cfg, tmp_path / "c.fits", seed=8, measure=True)
    t = read_catalog(tmp_path / "c.fits")
    g1 = np.asarray(t["tru_g1"]).reshape(2, 8)[:, 0]
    e = np.asarray(t["adamom_g1"]).reshape(2, 8)
    assert g1[0] != g1[1]
    assert np.all(np.sign(e[1] - e[0]) == np.sign(g1[1] - g1[0]))
    assert t.meta["CRN"] is True


def test_crn_card_survives_measure_and_predict(tmp_path):
    cfg = _cfg(tmp_path, CRN, n_cases=2, n_rea=4)
    simulate(cfg, tmp_path / "truth.fits", stamps=tmp_path / "s.fits", seed=2)
    measure_file(tmp_path / "s.fits", tmp_path / "truth.fits", tmp_path / "features.fits")
    predict_catalog(tmp_path / "features.fits", MODEL, tmp_path / "shears.fits")
    for name in ("truth.fits", "features.fits", "shears.fits"):
        header = catalog_info(tmp_path / name)[2]
        assert header["CRN"] is True and header["SNC"] == "pairs" and header["NREA"] == 4, name
    simulate(_cfg(tmp_path, CRN[:2], n_cases=2, n_rea=4), tmp_path / "ind.fits", seed=2)
    assert catalog_info(tmp_path / "ind.fits")[2]["CRN"] is False
