"""`megalut train-point`: help, outputs, exit codes and one-line errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from megalut_cli.catalog import write_catalog
from megalut_cli.nn.model import ShearModel
from megalut_cli.nn.toy import shear_like_columns

FAST = ["--members", "2", "--iterations", "6", "--hidden", "3"]


@pytest.fixture(scope="module")
def cats(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("tp")
    cols = shear_like_columns(24, 30, seed=1)
    paths = {"tp": d / "tp.fits", "vp": d / "vp.fits"}
    write_catalog(paths["tp"], cols, fmt="megalut.toy")
    write_catalog(paths["vp"], shear_like_columns(10, 30, seed=2), fmt="megalut.toy")
    nan_t = dict(cols, tru_g1=np.where(np.arange(len(cols["case"])) == 5, np.nan, cols["tru_g1"]))
    paths["nan"] = d / "nan.fits"
    write_catalog(paths["nan"], nan_t, fmt="megalut.toy")
    one = {k: v[cols["case"] == 0] for k, v in cols.items()}
    paths["one"] = d / "one.fits"
    write_catalog(paths["one"], one, fmt="megalut.toy")
    flagged = dict(cols, flags=np.where(cols["case"] == 3, 1, 0).astype(np.int32))
    paths["flagged"] = d / "flagged.fits"
    write_catalog(paths["flagged"], flagged, fmt="megalut.toy")
    paths["allbad"] = d / "allbad.fits"
    write_catalog(paths["allbad"], dict(cols, flags=np.ones_like(cols["flags"])), fmt="megalut.toy")
    paths["model"] = d / "model.h5"
    paths["notmodel"] = d / "notmodel.h5"
    paths["notmodel"].write_text("hello\n")
    return paths


def _run(runner, cli, *args: str):
    return runner.invoke(cli, ["train-point", *map(str, args)])


def test_help(runner, cli) -> None:
    res = runner.invoke(cli, ["train-point", "--help"])
    assert res.exit_code == 0
    for opt in (
        "--features",
        "--targets",
        "--valid",
        "--hidden",
        "--members",
        "--iterations",
        "--cost",
        "--select-cases",
        "--init-from",
        "--seed",
        "--nproc",
        "--scheduler",
        "--overwrite",
        "--batch-fraction",
        "--batch-iterations",
        "--valid-fraction",
    ):
        assert opt in res.output
    assert "megalut train-point tp.fits" in res.output


def test_train_defaults_and_progress(runner, cli, cats, tmp_path: Path) -> None:
    out = tmp_path / "m.h5"
    res = _run(runner, cli, cats["tp"], "-o", out, *FAST, "--select-cases", "mean(snr) > 10")
    assert res.exit_code == 0, res.output
    assert "done, 6 iterations" in res.stderr and "kept 1/2 members" in res.stderr
    m = ShearModel.load(out)
    assert list(m.point) == ["tru_g1", "tru_g2"] and not m.weight
    comm = m.point["tru_g1"]
    assert comm.features == ["adamom_g1", "adamom_g2", "adamom_sigma", "adamom_flux", "adamom_rho4"]
    assert comm.hidden == (3,) and len(comm.members) == 2 and comm.n_selected == 1
    t = comm.training
    assert t["select_cases"] == "mean(snr) > 10"
    assert t["n_train_cases"] + t["n_valid_cases"] < 24  # low-S/N cases removed
    assert m.provenance["inputs"]["train"]["sha256"]
    assert m.provenance["command"] == "train-point" and m.provenance["argv"]


def test_training_logs_per_member_not_per_mini_batch(runner, cli, cats, tmp_path: Path) -> None:
    """20 mini-batches per member: one line per member at info, the batches only with -v."""
    args = [
        cats["tp"],
        "-o",
        tmp_path / "m.h5",
        "--members",
        "2",
        "--iterations",
        "40",
        "--hidden",
        "3",
        "--batch-iterations",
        "2",
        "--targets",
        "tru_g1",
    ]
    res = _run(runner, cli, *args)
    assert res.exit_code == 0, res.output
    assert res.stderr.count(": done, ") == 2 and ": iteration " not in res.stderr
    verbose = _run(runner, cli, *args, "--overwrite", "-v")
    assert verbose.exit_code == 0, verbose.output
    assert verbose.stderr.count(": iteration ") >= 2 * 20


def test_valid_file_mse_and_options(runner, cli, cats, tmp_path: Path) -> None:
    out = tmp_path / "m.h5"
    res = _run(
        runner,
        cli,
        cats["tp"],
        "-o",
        out,
        *FAST,
        "--valid",
        cats["vp"],
        "--cost",
        "mse",
        "--targets",
        "tru_g2",
        "--features",
        "adamom_g2,adamom_sigma",
        "--optimizer",
        "lbfgs",
        "--normalization",
        "robust",
        "--init",
        "identity",
        "--precision",
        "float32",
        "--keep",
        "2",
    )
    assert res.exit_code == 0, res.output
    m = ShearModel.load(out)
    comm = m.point["tru_g2"]
    assert (
        comm.cost == "mse"
        and comm.features == ["adamom_g2", "adamom_sigma"]
        and comm.n_selected == 2
    )
    assert comm.training["n_valid_cases"] == 10 and comm.normalization == "robust"
    assert m.provenance["inputs"]["valid"]["path"].endswith("vp.fits")


def test_case_without_valid_rows_is_dropped(runner, cli, cats, tmp_path: Path) -> None:
    res = _run(
        runner, cli, cats["flagged"], "-o", tmp_path / "m.h5", *FAST, "--valid-fraction", "0"
    )
    assert res.exit_code == 0, res.output
    assert "1 case(s) dropped: every realization is flagged" in res.stderr
    assert ShearModel.load(tmp_path / "m.h5").point["tru_g1"].training["n_train_cases"] == 23


def test_cases_removed_by_a_selection_are_not_called_invalid(
    runner, cli, cats, tmp_path: Path
) -> None:
    """The log says a selection left cases out; only case 3 (all flagged) is reported as invalid."""
    res = _run(
        runner,
        cli,
        cats["flagged"],
        "-o",
        tmp_path / "m.h5",
        *FAST,
        "--valid-fraction",
        "0",
        "--select-cases",
        "mean(case) > 1",
    )
    assert res.exit_code == 0, res.output
    assert "2 case(s) left out by the selection" in res.stderr
    assert "1 case(s) dropped: every realization is flagged" in res.stderr
    assert ShearModel.load(tmp_path / "m.h5").point["tru_g1"].training["n_train_cases"] == 21


@pytest.mark.parametrize(
    "key,extra,code,message",
    [
        ("tp", ["--features", "adamom_g1,nope,nada"], 1, "missing column(s) nope, nada"),
        ("tp", ["--targets", "tru_g3"], 1, "missing column(s) tru_g3"),
        ("nan", [], 1, "target tru_g1 is not finite in 1 row"),
        ("one", [], 1, "fewer than 2 cases"),
        ("allbad", [], 1, "no valid realization in any case"),
        ("tp", ["--select-cases", "mean(snr) >"], 2, "cannot be read"),
        ("tp", ["--select-cases", "mean(snr) > 1e9"], 2, "selects no case"),
        ("tp", ["--select-cases", "mean(nope) > 1"], 2, "unknown column(s) nope"),
        ("tp", ["--select-cases", "__import__('os')"], 2, "unknown function"),
        ("tp", ["--init-from", "NOTMODEL"], 1, "not a readable HDF5 model"),
        ("tp", ["--hidden", "0"], 2, "positive integers"),
        ("tp", ["--hidden", "a,b"], 2, "comma-separated integers"),
        ("tp", ["--cost", "msx"], 2, "msx"),
        ("tp", ["-j", "2", "--scheduler", "tcp://localhost:1"], 2, "mutually exclusive"),
        ("tp", ["--features", "adamom_g1,tru_g1"], 2, "both a feature and a target"),
    ],
)
def test_errors_are_one_line_and_write_nothing(
    runner, cli, cats, tmp_path: Path, key, extra, code, message
) -> None:
    out = tmp_path / "m.h5"
    extra = [str(cats["notmodel"]) if e == "NOTMODEL" else e for e in extra]
    res = _run(runner, cli, cats[key], "-o", out, *FAST, *extra)
    assert res.exit_code == code, res.output
    assert message in res.stderr
    assert "Traceback" not in res.output
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


def test_refuses_overwrite_and_keeps_output(runner, cli, cats, tmp_path: Path) -> None:
    out = tmp_path / "m.h5"
    out.write_text("precious")
    res = _run(runner, cli, cats["tp"], "-o", out, *FAST)
    assert res.exit_code == 1 and "exists; use --overwrite" in res.stderr
    assert out.read_text() == "precious"
    res = _run(runner, cli, cats["tp"], "-o", out, *FAST, "--overwrite")
    assert res.exit_code == 0, res.output
    assert ShearModel.load(out).point


def test_init_from_mismatches(runner, cli, cats, tmp_path: Path) -> None:
    base = tmp_path / "base.h5"
    assert _run(runner, cli, cats["tp"], "-o", base, *FAST).exit_code == 0
    out = tmp_path / "m.h5"
    res = _run(
        runner,
        cli,
        cats["tp"],
        "-o",
        out,
        "--init-from",
        base,
        "--features",
        "adamom_g1,adamom_g2",
        "--iterations",
        "2",
    )
    assert res.exit_code == 1 and "do not match the features" in res.stderr
    res = _run(
        runner,
        cli,
        cats["tp"],
        "-o",
        out,
        "--init-from",
        base,
        "--hidden",
        "5,5",
        "--iterations",
        "2",
    )
    assert res.exit_code == 2 and "differs from the architecture" in res.stderr
    assert not out.exists()
    res = _run(
        runner,
        cli,
        cats["tp"],
        "-o",
        out,
        "--init-from",
        base,
        "--iterations",
        "2",
        "--members",
        "3",
    )
    assert res.exit_code == 0, res.output
    m = ShearModel.load(out)
    assert m.point["tru_g1"].hidden == (3,) and len(m.point["tru_g1"].members) == 3
