"""`megalut train-weight`: help, outputs, exit codes and one-line errors."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from megalut_cli.catalog import write_catalog
from megalut_cli.nn.fit import train_point
from megalut_cli.nn.model import ShearModel
from megalut_cli.nn.options import PointSpec
from megalut_cli.nn.toy import shear_like_columns

FAST = ["--members", "2", "--iterations", "6"]


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("tw")
    paths = {k: d / f"{k}.fits" for k in ("tp", "tw", "vw", "nofeat")}
    write_catalog(paths["tp"], shear_like_columns(20, 30, seed=1), fmt="megalut.toy")
    tw = shear_like_columns(12, 60, seed=3)
    write_catalog(paths["tw"], tw, fmt="megalut.toy")
    write_catalog(paths["vw"], shear_like_columns(6, 60, seed=4), fmt="megalut.toy")
    write_catalog(
        paths["nofeat"], {k: v for k, v in tw.items() if k != "adamom_rho4"}, fmt="megalut.toy"
    )
    paths["model"] = d / "model.h5"
    train_point(paths["tp"], paths["model"], PointSpec(hidden=[3], members=2, iterations=5))
    data = paths["model"].read_bytes()
    paths["trunc"] = d / "trunc.h5"
    paths["trunc"].write_bytes(data[:2000])
    paths["v9"] = d / "v9.h5"
    paths["v9"].write_bytes(data)
    with h5py.File(paths["v9"], "r+") as f:
        f.attrs["format_version"] = "9.0"
    return paths


def _run(runner, cli, *args: str):
    return runner.invoke(cli, ["train-weight", *map(str, args)])


def test_help(runner, cli) -> None:
    res = runner.invoke(cli, ["train-weight", "--help"])
    assert res.exit_code == 0
    for opt in (
        "--model",
        "--features",
        "--hidden",
        "--members",
        "--iterations",
        "--select",
        "--valid",
        "--seed",
        "--nproc",
        "--scheduler",
        "--overwrite",
    ):
        assert opt in res.output
    assert "megalut train-weight tw.fits --model model.h5" in res.output


def test_train_weight_writes_point_and_weight(runner, cli, setup, tmp_path: Path) -> None:
    out = tmp_path / "mw.h5"
    res = _run(
        runner,
        cli,
        setup["tw"],
        "--model",
        setup["model"],
        "-o",
        out,
        *FAST,
        "--select",
        "snr > 10",
    )
    assert res.exit_code == 0, res.output
    assert "done, 6 iterations" in res.stderr
    m = ShearModel.load(out)
    point = ShearModel.load(setup["model"])
    assert list(m.point) == list(m.weight) == ["tru_g1", "tru_g2"]
    for t in m.point:
        assert np.array_equal(m.point[t].member_params(0), point.point[t].member_params(0))
        w = m.weight[t]
        assert w.kind == "weight" and w.cost == "mswb" and w.hidden == (5,)
        assert w.features == point.features  # default: all features of the point model
        assert w.training["select"] == "snr > 10"
        assert w.training["point_model_sha256"] == point.sha256
        x = np.random.default_rng(0).normal(size=(100, 5)) * [0.2, 0.2, 0.5, 300, 0.1] + [
            0,
            0,
            3,
            800,
            2.5,
        ]
        pred = w.predict(x)
        assert np.all((pred > 0) & (pred < 1))
    assert m.provenance["parent"]["command"] == "train-point"
    assert m.provenance["inputs"]["model"]["sha256"] == point.sha256


def test_features_hidden_and_valid(runner, cli, setup, tmp_path: Path) -> None:
    out = tmp_path / "mw.h5"
    res = _run(
        runner,
        cli,
        setup["tw"],
        "--model",
        setup["model"],
        "-o",
        out,
        *FAST,
        "--features",
        "adamom_flux,adamom_sigma,snr",
        "--hidden",
        "4,2",
        "--valid",
        setup["vw"],
    )
    assert res.exit_code == 0, res.output
    w = ShearModel.load(out).weight["tru_g2"]
    assert w.features == ["adamom_flux", "adamom_sigma", "snr"] and w.hidden == (4, 2)
    assert w.training["n_valid_cases"] == 6


@pytest.mark.parametrize(
    "cat,model,extra,code,message",
    [
        ("tw", "tp", [], 1, "not a readable HDF5 model"),
        ("tw", "trunc", [], 1, "truncated"),
        ("tw", "v9", [], 1, "version 9.0 is not supported"),
        ("nofeat", "model", [], 1, "missing column(s) adamom_rho4"),
        ("tw", "model", ["--features", "adamom_flux,nope"], 1, "missing column(s) nope"),
        ("tw", "model", ["--select", "snr >"], 2, "cannot be read"),
        ("tw", "model", ["--select", "snr > 1e9"], 2, "selects no row"),
        ("tw", "model", ["--select", "mean(snr) > 3"], 2, "unknown function 'mean'"),
        ("tw", "model", ["--hidden", "-1"], 2, "positive integers"),
    ],
)
def test_errors(runner, cli, setup, tmp_path: Path, cat, model, extra, code, message) -> None:
    out = tmp_path / "mw.h5"
    res = _run(runner, cli, setup[cat], "--model", setup[model], "-o", out, *FAST, *extra)
    assert res.exit_code == code, res.output
    assert message in res.stderr
    assert "Traceback" not in res.output
    assert list(tmp_path.iterdir()) == []


def test_output_safety(runner, cli, setup, tmp_path: Path) -> None:
    out = tmp_path / "mw.h5"
    out.write_text("precious")
    res = _run(runner, cli, setup["tw"], "--model", setup["model"], "-o", out, *FAST)
    assert res.exit_code == 1 and "--overwrite" in res.stderr and out.read_text() == "precious"
    res = _run(
        runner,
        cli,
        setup["tw"],
        "--model",
        setup["model"],
        "-o",
        setup["model"],
        *FAST,
        "--overwrite",
    )
    assert res.exit_code == 2 and "would replace the input model" in res.stderr
    res = runner.invoke(cli, ["train-weight", str(setup["tw"]), "-o", str(out)])
    assert res.exit_code == 2 and "--model" in res.stderr


def test_weights_of_a_d4_model_are_trained_for_its_symmetrized_estimates(
    runner, cli, setup, tmp_path: Path
) -> None:
    """A point model with symmetry d4 keeps it through train-weight, and the weights learn
    from its symmetrized point estimates (so they differ from those of the same networks
    as trained)."""
    d4 = tmp_path / "d4.h5"
    ShearModel.load(setup["model"]).with_symmetry("d4", "test").save(d4)
    outs = {}
    for name, model in (("plain", setup["model"]), ("d4", d4)):
        outs[name] = tmp_path / f"w-{name}.h5"
        res = _run(runner, cli, setup["tw"], "--model", model, "-o", outs[name], *FAST)
        assert res.exit_code == 0, res.output
    plain, sym = ShearModel.load(outs["plain"]), ShearModel.load(outs["d4"])
    assert sym.symmetry == "d4" and plain.symmetry == "none"
    assert not np.array_equal(
        sym.weight["tru_g1"].member_params(0), plain.weight["tru_g1"].member_params(0)
    )
