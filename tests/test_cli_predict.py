"""`megalut predict`: help, outputs, --col, -j, exit codes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import FEATURES, features_catalog, make_model, manual_predict, one_line

from megalut_cli.catalog import read_catalog, write_catalog
from megalut_cli.nn.model import ShearModel


@pytest.fixture
def setup(tmp_path):
    model = tmp_path / "model.h5"
    make_model(model)
    src = tmp_path / "features.fits"
    d = features_catalog(500)
    write_catalog(src, d, fmt="megalut.features")
    return tmp_path, model, src, d


def test_help(runner, cli):
    result = runner.invoke(cli, ["predict", "--help"])
    assert result.exit_code == 0
    for word in ("--model", "-o", "--col", "-j", "--scheduler", "--overwrite", "Example"):
        assert word in result.output


def test_predict_writes_predictions(runner, cli, setup):
    tmp, model, src, d = setup
    out = tmp / "shears.fits"
    result = runner.invoke(cli, ["predict", str(src), "--model", str(model), "-o", str(out)])
    assert result.exit_code == 0, result.output
    t = read_catalog(out)
    m = ShearModel.load(model)
    x = np.column_stack([d[f] for f in FEATURES])
    np.testing.assert_allclose(t["pre_g1"], manual_predict(m.point["tru_g1"], x), rtol=1e-12)
    assert t.meta["MODELSHA"] == m.sha256
    assert any("predict" in h for h in t.meta["HISTORY"])


def test_col_mapping_and_parallel(runner, cli, setup):
    tmp, model, _, d = setup
    d = dict(d)
    d["E1"], d["E2"] = d.pop("adamom_g1"), d.pop("adamom_g2")
    src = tmp / "renamed.fits"
    write_catalog(src, d, fmt="megalut.features")
    out = tmp / "shears.fits"
    result = runner.invoke(
        cli,
        [
            "predict",
            str(src),
            "--model",
            str(model),
            "-o",
            str(out),
            "--col",
            "adamom_g1=E1",
            "--col",
            "adamom_g2=E2",
            "-j",
            "2",
            "--chunk-rows",
            "1000",
        ],
    )
    assert result.exit_code == 0, result.output
    m = ShearModel.load(model)
    x = np.column_stack([d["E1"], d["E2"], *(d[f] for f in FEATURES[2:])])
    np.testing.assert_allclose(
        read_catalog(out)["pre_g2"], manual_predict(m.point["tru_g2"], x), rtol=1e-12
    )


def test_missing_feature_suggests_col(runner, cli, setup):
    tmp, model, _, d = setup
    d = {k: v for k, v in d.items() if k not in ("adamom_g1", "adamom_flux")}
    src = tmp / "missing.fits"
    write_catalog(src, d, fmt="megalut.features")
    out = tmp / "shears.fits"
    result = runner.invoke(cli, ["predict", str(src), "--model", str(model), "-o", str(out)])
    assert result.exit_code == 1
    msg = one_line(result)
    assert "adamom_g1" in msg and "adamom_flux" in msg and "--col" in msg
    assert not out.exists()


def test_bad_usage_and_files(runner, cli, setup):
    tmp, model, src, _ = setup
    out = tmp / "shears.fits"
    base = ["predict", str(src), "--model", str(model), "-o", str(out)]
    result = runner.invoke(cli, [*base, "--col", "adamom_g1"])
    assert result.exit_code == 2 and "FEATURE=COLUMN" in one_line(result)
    result = runner.invoke(cli, [*base, "--col", "size=adamom_sigma"])
    assert result.exit_code == 2 and "not a feature" in one_line(result)
    assert runner.invoke(cli, [*base, "-j", "2", "--scheduler", "tcp://x:1"]).exit_code == 2
    assert (
        runner.invoke(cli, ["predict", str(src), "-o", str(out)]).exit_code == 2
    )  # --model required
    junk = tmp / "junk.h5"
    junk.write_bytes(b"x" * 64)
    result = runner.invoke(cli, ["predict", str(src), "--model", str(junk), "-o", str(out)])
    assert result.exit_code == 1 and "junk.h5" in one_line(result)
    bad_cat = tmp / "junk.fits"
    bad_cat.write_bytes(b"y" * 64)
    result = runner.invoke(cli, ["predict", str(bad_cat), "--model", str(model), "-o", str(out)])
    assert result.exit_code == 1 and "junk.fits" in one_line(result)
    assert not out.exists()


def test_refuses_to_overwrite(runner, cli, setup):
    tmp, model, src, _ = setup
    out = tmp / "shears.fits"
    out.write_text("keep")
    args = ["predict", str(src), "--model", str(model), "-o", str(out)]
    result = runner.invoke(cli, args)
    assert result.exit_code == 1 and "--overwrite" in one_line(result)
    assert out.read_text() == "keep"
    assert runner.invoke(cli, [*args, "--overwrite"]).exit_code == 0
    assert len(read_catalog(out)) == 500
    result = runner.invoke(
        cli, ["predict", str(src), "--model", str(model), "-o", str(src), "--overwrite"]
    )
    assert result.exit_code == 2


def test_dask_scheduler(runner, cli, setup):
    from distributed import LocalCluster

    tmp, model, src, _ = setup
    with LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        out = tmp / "dask.fits"
        result = runner.invoke(
            cli,
            [
                "predict",
                str(src),
                "--model",
                str(model),
                "-o",
                str(out),
                "--scheduler",
                cluster.scheduler_address,
                "--chunk-rows",
                "1000",
            ],
        )
    assert result.exit_code == 0, result.output
    ref = tmp / "ref.fits"
    assert (
        runner.invoke(
            cli,
            ["predict", str(src), "--model", str(model), "-o", str(ref), "--chunk-rows", "1000"],
        ).exit_code
        == 0
    )
    np.testing.assert_array_equal(read_catalog(out)["pre_g1_w"], read_catalog(ref)["pre_g1_w"])


def test_identity_model_then_evaluate(runner, cli, tmp_path):
    """A linear committee returning adamom_g1/adamom_g2 on unbiased features: evaluate finds
    m, c ~ 0."""
    from megalut_cli.nn.model import Committee, Member

    def identity(target: str, k: int) -> Committee:
        w = np.zeros((2, 1))
        w[k, 0] = 1.0
        return Committee(
            "point",
            target,
            ["adamom_g1", "adamom_g2"],
            (),
            np.zeros(2),
            np.ones(2),
            [Member(layers=[(w, np.zeros(1))])],
        )

    model = tmp_path / "identity.h5"
    ShearModel({"tru_g1": identity("tru_g1", 0), "tru_g2": identity("tru_g2", 1)}).save(model)
    rng = np.random.default_rng(5)
    n_cases, n_rea = 60, 50
    case = np.repeat(np.arange(n_cases), n_rea)
    g = rng.uniform(-0.05, 0.05, (2, n_cases))[:, case]
    cat = {
        "case": case,
        "tru_g1": g[0],
        "tru_g2": g[1],
        "adamom_g1": g[0] + rng.normal(0, 0.01, case.size),
        "adamom_g2": g[1] + rng.normal(0, 0.01, case.size),
    }
    cat["adamom_g2"][7] = np.nan
    src, out = tmp_path / "f.fits", tmp_path / "s.fits"
    write_catalog(src, cat, fmt="megalut.features")
    assert (
        runner.invoke(cli, ["predict", str(src), "--model", str(model), "-o", str(out)]).exit_code
        == 0
    )
    js = tmp_path / "e.json"
    result = runner.invoke(cli, ["evaluate", str(out), "--json", str(js)])
    assert result.exit_code == 0, result.output
    r = json.loads(js.read_text())
    assert r["n_valid"] == case.size - 1
    for comp in ("g1", "g2"):
        f = r["unweighted"][comp]
        assert abs(f["m"]) < 3 * f["m_err"] and abs(f["c"]) < 3 * f["c_err"] and f["m_err"] < 0.01


def test_warns_when_catalog_setup_differs_from_training(runner, cli, tmp_path):
    """The model records its training set's setup; predict names each difference."""
    from helpers import make_committee

    from megalut_cli.nn.model import ShearModel as Model

    point = {
        t: make_committee("point", t, FEATURES, seed=i) for i, t in enumerate(("tru_g1", "tru_g2"))
    }
    setup = {
        "stamp_size": 64,
        "noise": {"type": "gaussian", "sigma": 1.0},
        "psf": {"type": "gaussian", "sigma": 2.0},
    }
    Model(point, provenance={"setup": setup}).save(tmp_path / "m.h5")
    d = features_catalog(100)
    write_catalog(tmp_path / "same.fits", d, fmt="megalut.features", cards={"STAMPSZ": 64})
    write_catalog(tmp_path / "other.fits", d, fmt="megalut.features", cards={"STAMPSZ": 48})
    same = runner.invoke(
        cli,
        [
            "predict",
            str(tmp_path / "same.fits"),
            "--model",
            str(tmp_path / "m.h5"),
            "-o",
            str(tmp_path / "a.fits"),
        ],
    )
    assert same.exit_code == 0 and "setup differs" not in same.stderr
    other = runner.invoke(
        cli,
        [
            "predict",
            str(tmp_path / "other.fits"),
            "--model",
            str(tmp_path / "m.h5"),
            "-o",
            str(tmp_path / "b.fits"),
        ],
    )
    assert other.exit_code == 0, other.stderr
    assert "recorded setup differs" in other.stderr and "stamp_size 64 vs 48" in other.stderr
    assert "psf" not in other.stderr  # not recorded by this catalog: nothing to compare


def test_training_records_the_setup_of_simulated_catalogs(tmp_path):
    """read_setup takes stamp size, noise and gain cards and the CONFIG HDU's psf and noise."""
    from sim_configs import write

    from megalut_cli.catalog import read_setup, setup_differences
    from megalut_cli.sim.config import load_config
    from megalut_cli.sim.simulate import simulate

    simulate(load_config(write(tmp_path), ()), tmp_path / "a.fits", measure=True)
    simulate(
        load_config(write(tmp_path, name="b.toml"), ("psf.sigma=2.0",)),
        tmp_path / "b.fits",
        measure=True,
    )
    a, b = read_setup(tmp_path / "a.fits"), read_setup(tmp_path / "b.fits")
    assert a["stamp_size"] == 24 and a["psf"] == {"type": "gaussian", "sigma": 1.5}
    assert a["noise"] == {"type": "gaussian", "sigma": 1.0} and a["noise_type"] == "gaussian"
    assert setup_differences(a, b) == [f"psf {a['psf']} vs {b['psf']}"]


def test_setup_written_another_way_is_no_difference():
    """A path from another folder to the same file, or a key left to its default, is not a
    different setup; another value is."""
    from megalut_cli.catalog import setup_differences

    trained = {
        "noise": {
            "type": "correlated",
            "correlation": "../data/cosmos/cf.fits",
            "pixel_scale": 1.0,
            "sigma": 1.0,
        }
    }
    same = {
        "noise": {
            "type": "correlated",
            "correlation": "/abs/examples/data/cosmos/cf.fits",
            "sigma": 1.0,
        }
    }
    assert setup_differences(trained, same) == []
    other = {"noise": {"type": "correlated", "correlation": "/abs/other_cf.fits", "sigma": 1.0}}
    assert setup_differences(trained, other) == [f"noise {trained['noise']} vs {other['noise']}"]
    assert setup_differences(trained, {"noise": {**same["noise"], "sigma": 2.0}}) != []
