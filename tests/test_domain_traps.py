"""The traps of issue 41 that predict's domain check missed: an elliptical PSF given to a
model trained on a round one, joint (size, flux) coverage, a catalog without PSF
measurements, a catalog without usable row, a model whose own recorded m is outside the
Stage IV requirement, mixed stamp sizes (MEDS box_size), and metacal models (judged on S/N
and resolution only, so that --strict passes on a catalog like their training set).

Each: a finding when it should, none on a matching catalog; --strict exits 1 with one line and
writes nothing."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import fitsio
import numpy as np
import pytest

from megalut_cli.catalog import write_catalog
from megalut_cli.nn.domain import (
    JOINT_KEY,
    RESOLUTION,
    domain_findings,
    domain_record,
    mode_domain,
    model_domain,
    with_constant_column,
)
from megalut_cli.nn.model import ShearModel
from megalut_cli.nn.shipped import shipped_model
from megalut_cli.shear.predict import applied_domain, validation_findings

ROOT = Path(__file__).resolve().parents[1]
VO = ROOT / "examples" / "fiducial" / "vo.toml"


@pytest.fixture(scope="module")
def own(tmp_path_factory) -> dict[str, np.ndarray]:
    """A small catalog of the fiducial population (plain columns), without setup cards."""
    from megalut_cli.sim.config import load_config
    from megalut_cli.sim.simulate import simulate

    d = tmp_path_factory.mktemp("traps")
    path = d / "own.fits"
    simulate(load_config(VO, (), n_cases=2, n_realizations=150), path, measure=True, seed=8)
    t = fitsio.read(str(path))
    return {k: t[k] for k in t.dtype.names if not k.startswith("tru_")}


def _survey(path: Path, columns: dict[str, np.ndarray], **cards) -> Path:
    write_catalog(path, columns, fmt="survey", cards=cards or None)
    return path


def _strict(runner, cli, path: Path, model: str = "fiducial") -> tuple[int, list[str], Path]:
    out = path.with_name(path.stem + "-shears.fits")
    r = runner.invoke(cli, ["predict", str(path), "--model", model, "-o", str(out), "--strict"])
    return r.exit_code, r.stderr.strip().splitlines(), out


def _round_psf(n: int, g2: float = 0.0) -> dict[str, np.ndarray]:
    return {
        "psf_adamom_sigma": np.full(n, 2.0208539962768555),
        "psf_adamom_g1": np.zeros(n),
        "psf_adamom_g2": np.full(n, g2),
    }


# --------------------------------------------------------------------------- PSF ellipticity


def test_an_elliptical_psf_given_to_the_round_psf_model_is_a_finding(tmp_path, own, runner, cli):
    n = len(own["flags"])
    dom, dropped = applied_domain(ShearModel.load(shipped_model("fiducial")))
    assert dropped == [] and dom["columns"]["psf_adamom_g2"]["atol"] == 2e-4
    assert abs(dom["columns"]["psf_adamom_g2"]["q"][3]) < 1e-6  # a round PSF, drawn and measured
    assert [f.item for f in domain_findings(dom, {**own, **_round_psf(n)})] == []
    (f,) = domain_findings(dom, {**own, **_round_psf(n, 0.02)})
    assert f.item == "psf_adamom_g2" and f.message == (
        "psf_adamom_g2 median 0.02 (5–95 %: 0.02–0.02), model trained at 0 (±0.0002)"
    )
    # a PSF that varies over the field: the median is round, 30 % of the rows are not
    varying = _round_psf(n)
    varying["psf_adamom_g1"] = np.where(np.arange(n) % 10 < 3, 0.01, 0.0)
    (f,) = domain_findings(dom, {**own, **varying})
    assert (
        f.item == "psf_adamom_g1"
        and "% of the rows outside the model trained at 0 (±0.0002)" in str(f)
    )
    good = _survey(tmp_path / "round.fits", {**own, **_round_psf(n)})
    code, lines, out = _strict(runner, cli, good)
    assert code == 0 and out.exists(), lines
    bad = _survey(tmp_path / "ell.fits", {**own, **_round_psf(n, 0.02)})
    code, lines, out = _strict(runner, cli, bad)
    assert code == 1 and not out.exists() and len(lines) == 1
    assert "--strict" in lines[0] and "psf_adamom_g2 median 0.02" in lines[0]


def test_a_simulated_catalogs_recorded_psf_is_compared_as_measured(tmp_path, runner, cli):
    """A simulated catalog records its PSF in its setup, not as columns: its g2 is drawn and
    measured, so a sheared PSF is a finding where the setup comparison saw none."""
    from megalut_cli.sim.config import load_config
    from megalut_cli.sim.simulate import simulate

    cat = tmp_path / "ell.fits"
    simulate(
        load_config(VO, ("psf.g2=0.02",), n_cases=1, n_realizations=100),
        cat,
        measure=True,
        seed=9,
    )
    code, lines, out = _strict(runner, cli, cat)
    assert code == 1 and not out.exists() and len(lines) == 1
    assert "psf_adamom_g2 median 0.0196" in lines[0] and "model trained at 0 (±0.0002)" in lines[0]


# --------------------------------------------------------------------------- joint coverage


def _joint_domain(rng: np.random.Generator) -> dict:
    size = rng.uniform(2.0, 6.0, 20000)
    flux = 50.0 * size**2 * rng.lognormal(0.0, 0.1, 20000)  # flux follows size
    return domain_record({"adamom_sigma": size, "adamom_flux": flux}, stamp_size=64)


def test_joint_size_flux_coverage():
    rng = np.random.default_rng(4)
    dom = _joint_domain(rng)
    joint = dom[JOINT_KEY]
    assert joint["columns"] == ["adamom_sigma", "adamom_flux"] and joint["n"] == 20000
    assert np.asarray(joint["counts"]).shape == (8, 8)
    size = rng.uniform(2.0, 6.0, 1000)
    same = {"adamom_sigma": size, "adamom_flux": 50.0 * size**2 * rng.lognormal(0, 0.1, 1000)}
    assert domain_findings(dom, same) == []
    # each column alone inside, the pairs not: small and bright, large and faint
    swapped = {"adamom_sigma": size, "adamom_flux": 50.0 * (8.0 - size) ** 2}
    found = domain_findings(dom, swapped)
    assert [f.item for f in found] == [JOINT_KEY], found
    assert "adamom_sigma × adamom_flux:" in found[0].message
    assert "although each column alone may lie inside" in found[0].message
    # a model recorded before the joint occupancy: nothing to judge
    old = {k: v for k, v in dom.items() if k != JOINT_KEY}
    assert domain_findings(old, swapped) == []


def test_training_records_the_joint_occupancy(tmp_path):
    from sim_configs import write

    from megalut_cli.nn.fit import train_point
    from megalut_cli.nn.options import PointSpec
    from megalut_cli.sim.config import load_config
    from megalut_cli.sim.simulate import simulate

    cfg = write(tmp_path, replace={"n_cases = 3": "n_cases = 8"})
    tp = tmp_path / "tp.fits"
    simulate(load_config(cfg), tp, measure=True, seed=3)
    model = train_point(tp, tmp_path / "m.h5", PointSpec(hidden=[3], members=1, iterations=3))
    dom = model.provenance["domain"]
    joint = dom[JOINT_KEY]
    assert sum(map(sum, joint["counts"])) <= joint["n"] == dom["columns"]["adamom_sigma"]["n"]
    for c in ("psf_adamom_g1", "psf_adamom_g2"):  # the round config PSF, drawn and measured
        assert abs(dom["columns"][c]["q"][0]) < 1e-6 and dom["columns"][c]["atol"] == 2e-4


# --------------------------------------------------------------------------- PSF missing


def test_a_catalog_without_psf_measurements(tmp_path, own, runner, cli):
    code, lines, out = _strict(runner, cli, _survey(tmp_path / "nopsf.fits", own))
    assert code == 1 and not out.exists() and len(lines) == 1
    assert (
        "no PSF measurement (psf_adamom_sigma, psf_adamom_g1, psf_adamom_g2 missing or NaN)"
        in (lines[0])
    )
    assert "trained at psf_adamom_sigma 2.02 px, psf_adamom_g1 0, psf_adamom_g2 0" in lines[0]
    nan = {k: np.full(len(own["flags"]), np.nan) for k in _round_psf(1)}
    code, lines, _ = _strict(runner, cli, _survey(tmp_path / "nanpsf.fits", {**own, **nan}))
    assert code == 1 and "no PSF measurement" in lines[0]


def test_a_model_whose_features_need_the_psf_and_a_catalog_without_it(tmp_path, own, runner, cli):
    from sim_configs import write

    from megalut_cli.nn.fit import train_point
    from megalut_cli.nn.options import PointSpec
    from megalut_cli.sim.config import load_config
    from megalut_cli.sim.simulate import simulate

    tp = tmp_path / "tp.fits"
    simulate(
        load_config(write(tmp_path, replace={"n_cases = 3": "n_cases = 8"})),
        tp,
        measure=True,
        seed=3,
    )
    t = fitsio.read(str(tp))
    cols = {k: t[k] for k in t.dtype.names}
    n = len(t)
    train = _survey(tmp_path / "train.fits", {**cols, **_round_psf(n)}, STAMPSZ=24)
    feats = ["adamom_g1", "adamom_g2", "adamom_sigma", "psf_adamom_sigma"]
    train_point(
        train, tmp_path / "m.h5", PointSpec(hidden=[3], members=1, iterations=3, features=feats)
    )
    nan = {k: np.full(n, np.nan) for k in _round_psf(1)}
    cat = _survey(
        tmp_path / "nan.fits", {k: v for k, v in {**cols, **nan}.items() if "tru" not in k}
    )
    code, lines, out = _strict(runner, cli, cat, str(tmp_path / "m.h5"))
    assert code == 1 and not out.exists() and len(lines) == 1
    assert (
        "no usable row" in lines[0]
        and "psf_adamom_sigma not finite in any unflagged row" in (lines[0])
    )
    assert "measure with a PSF" in lines[0]


# --------------------------------------------------------------------------- no usable row


def test_a_catalog_with_no_usable_row(tmp_path, own, runner, cli):
    n = len(own["flags"])
    cols = {**own, **_round_psf(n), "flags": np.ones(n, dtype=np.int32)}
    code, lines, out = _strict(runner, cli, _survey(tmp_path / "flagged.fits", cols))
    assert code == 1 and not out.exists() and len(lines) == 1
    assert (
        f"no usable row: of all {n} rows, {n} flagged (flags != 0); nothing to estimate"
        in (lines[0])
    )
    # without --strict: a warning, and the NaN estimates are written
    r = runner.invoke(
        cli, ["predict", str(tmp_path / "flagged.fits"), "--model", "fiducial", "-o", str(out)]
    )
    assert r.exit_code == 0 and "no usable row" in r.stderr and out.exists()


# --------------------------------------------------------------------------- recorded validation


def test_a_model_whose_recorded_m_is_outside_stage_iv(tmp_path, own, runner, cli):
    from megalut_cli.nn.population import SIMULATED_BIAS_ATTR, record_simulated_bias

    fits = {
        "g1": {"m": -0.021, "m_err": 0.003, "c": 1e-4, "c_err": 1e-4},
        "g2": {"m": -0.019, "m_err": 0.003, "c": 0.0, "c_err": 1e-4},
    }
    evaluation = {"input": "/somewhere/vo-shears.fits", "n_valid": 4000, "weighted": fits}
    model = tmp_path / "model.h5"
    shutil.copy(shipped_model("fiducial"), model)
    record_simulated_bias(model, evaluation)
    rec = ShearModel.load(model).validation[SIMULATED_BIAS_ATTR]
    assert (
        rec["m_g1"] == -0.021 and rec["input"] == "vo-shears.fits" and rec["scheme"] == "weighted"
    )
    (f,) = validation_findings(ShearModel.load(model).validation)
    assert f.item == "validation" and f.message == (
        "the model's recorded bias on its simulated validation (weighted, vo-shears.fits): "
        "m1 = -2.10e-02 ± 3.0e-03, m2 = -1.90e-02 ± 3.0e-03, outside the Stage IV requirement "
        "|m| < 2e-03"
    )
    n = len(own["flags"])
    code, lines, out = _strict(
        runner, cli, _survey(tmp_path / "c.fits", {**own, **_round_psf(n)}), str(model)
    )
    assert code == 1 and not out.exists() and len(lines) == 1 and "m1 = -2.10e-02" in lines[0]
    good = {g: {**v, "m": 1e-3} for g, v in fits.items()}
    record_simulated_bias(model, {**evaluation, "weighted": good})
    assert validation_findings(ShearModel.load(model).validation) == []
    # the shipped models: metacal's m_real is inside; fiducial's m_real - m_twin is a difference
    for name in ("fiducial", "fiducial-metacal"):
        assert validation_findings(ShearModel.load(shipped_model(name)).validation) == []


# --------------------------------------------------------------------------- mixed stamp sizes


def test_mixed_stamp_sizes_are_compared_row_by_row(tmp_path, own, runner, cli):
    n = len(own["flags"])
    base = {**own, **_round_psf(n)}
    same = _survey(tmp_path / "box64.fits", {**base, "box_size": np.full(n, 64)})
    code, lines, _ = _strict(runner, cli, same)
    assert code == 0, lines
    mixed = np.where(np.arange(n) % 4 == 0, 48, 64)
    code, lines, out = _strict(
        runner, cli, _survey(tmp_path / "mixed.fits", {**base, "box_size": mixed})
    )
    assert code == 1 and not out.exists() and len(lines) == 1
    assert re.search(
        r"stamp sizes \(box_size\) 64 px \(7\d %\), 48 px \(2\d %\), model trained at 64 px",
        lines[0],
    )


# --------------------------------------------------------------------------- metacal


def test_metacal_models_are_judged_on_snr_and_resolution_only(tmp_path, runner, cli):
    from megalut_cli.sim.config import load_config
    from megalut_cli.sim.simulate import simulate

    dom, dropped = applied_domain(ShearModel.load(shipped_model("fiducial-metacal")))
    assert sorted(dom["columns"]) == sorted(["snr", RESOLUTION])
    assert "stamp_size" not in dom and {"skymad", "psf_adamom_sigma", "stamp_size"} <= set(dropped)
    full = model_domain(ShearModel.load(shipped_model("fiducial-metacal")).provenance)
    np.testing.assert_allclose(
        dom["columns"][RESOLUTION]["q"],
        np.asarray(full["columns"]["adamom_sigma"]["q"])
        / full["columns"]["psf_adamom_sigma"]["q"][0],
    )
    assert mode_domain(full, "simulation")[0] == full
    # the trap of issue 41: twice the noise, a wider elliptical PSF, 48-px stamps, which the
    # response absorbs: no finding
    cat = tmp_path / "mc.fits"
    overrides = ("noise.sigma=2.0", "psf.sigma=2.4", "psf.g2=0.02", "structure.stamp_size=48")
    simulate(
        load_config(VO, overrides, n_cases=1, n_realizations=60),
        cat,
        measure=True,
        seed=5,
        metacal=True,
    )
    code, lines, out = _strict(runner, cli, cat, "fiducial-metacal")
    assert code == 0 and out.exists(), lines
    # galaxies far smaller than the PSF: the resolution stays a finding
    t = fitsio.read(str(cat))
    small = {k: t[k] for k in t.dtype.names}
    small["adamom_sigma_noshear"] = 0.5 * small["psf_adamom_sigma_noshear"]
    hdr = fitsio.read_header(str(cat), 1)
    small_cat = _survey(tmp_path / "small.fits", small, MCALSTEP=hdr["MCALSTEP"])
    code, lines, out = _strict(runner, cli, small_cat, "fiducial-metacal")
    assert code == 1 and not out.exists() and len(lines) == 1
    assert "resolution median 0.5" in lines[0] and "skymad" not in lines[0]


def test_with_constant_column_absolute_margin():
    dom = with_constant_column(
        {"columns": {}, "n_rows": 2000}, "psf_adamom_g1", 0.0, 1e-3, "x", True
    )
    entry = dom["columns"]["psf_adamom_g1"]
    assert entry["atol"] == 1e-3 and "tolerance" not in entry
    inside = {"psf_adamom_g1": np.full(200, 9e-4)}
    assert domain_findings(dom, inside) == []
    (f,) = domain_findings(dom, {"psf_adamom_g1": np.full(200, 2e-3)})
    assert f.message.endswith("model trained at 0 (±0.001)")
