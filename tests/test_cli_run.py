"""`megalut run`: the whole pipeline from the command line."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from pipeline_configs import write_pipeline

from megalut_cli.pipeline import default_pipeline_text

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def _err(result) -> str:
    try:
        return result.stderr
    except ValueError:  # older click: stderr mixed in
        return result.output


def test_help(runner, cli) -> None:
    result = runner.invoke(cli, ["run", "--help"])
    assert result.exit_code == 0
    for text in ("PIPELINE.toml", "--workdir", "--skip-existing", "--scheduler", "-j", "megalut-run", "Example"):
        assert text in result.output
    assert "run" in runner.invoke(cli, ["--help"]).output


def test_print_default(runner, cli) -> None:
    result = runner.invoke(cli, ["run", "--print-default"])
    assert result.exit_code == 0
    assert result.stdout == default_pipeline_text()
    raw = tomllib.loads(result.stdout)
    assert set(raw["sets"]) == {"tp", "tw", "vo"}
    assert raw["reference"] == {"model": "fiducial"}  # the second table: the shipped model on vo


def test_run_prints_table_and_writes_products(runner, cli, tmp_path: Path) -> None:
    path = write_pipeline(tmp_path)
    wd = tmp_path / "wd"
    args = ["run", str(path), "evaluate.plot=true", "--workdir", str(wd)]
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output + _err(result)
    out = result.stdout
    assert "unweighted" in out and "weighted" in out
    assert out.count("  g1 ") >= 2 and out.count("  g2 ") >= 2  # m and c rows of both schemes
    for step in ("simulate-tp", "train-point", "train-weight", "predict", "evaluate"):
        assert f"{step}: done in" in _err(result)
    assert "pipeline finished in" in _err(result)
    ev = json.loads((wd / "evaluation.json").read_text())
    png = (wd / "evaluation.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"

    # evaluation.json has the layout of `megalut evaluate --json`
    other = tmp_path / "other.json"
    assert runner.invoke(cli, ["evaluate", str(wd / "vo-shears.fits"), "--json", str(other)]).exit_code == 0
    direct = json.loads(other.read_text())
    assert ev.keys() == direct.keys()
    assert ev["weighted"] == direct["weighted"] and ev["unweighted"] == direct["unweighted"]

    # again without a flag: refused, one line, nothing touched
    mtime = (wd / "model.h5").stat().st_mtime_ns
    again = runner.invoke(cli, args)
    assert again.exit_code == 1
    assert "exists; use --skip-existing" in _err(again) and len(_err(again).strip().splitlines()) == 1
    assert (wd / "model.h5").stat().st_mtime_ns == mtime

    # --skip-existing: all up to date, the same table
    skipped = runner.invoke(cli, [*args, "--skip-existing", "-j", "2"])
    assert skipped.exit_code == 0, _err(skipped)
    assert _err(skipped).count("up to date, skipped") == 7
    assert skipped.stdout == out
    assert (wd / "model.h5").stat().st_mtime_ns == mtime


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["missing.toml"], 2, "no such file"),
        (["bogus=1"], 2, "bogus: unknown key"),
        (["scale=-1"], 2, "scale: must be > 0"),
        (["sets.vo.seed=1"], 2, "sets.vo.seed: 1 is also the seed of sets.tp"),
        (["-j", "2", "--scheduler", "tcp://localhost:1"], 2, "mutually exclusive"),
    ],
)
def test_bad_input(runner, cli, tmp_path: Path, args: list[str], code: int, message: str) -> None:
    result = runner.invoke(cli, ["run", *args, "--workdir", str(tmp_path / "wd")])
    assert result.exit_code == code
    err = _err(result)
    assert message in err
    assert "Traceback" not in err
    assert not (tmp_path / "wd").exists()


def test_bad_pipeline_file(runner, cli, tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[sets.tp\n")
    result = runner.invoke(cli, ["run", str(bad), "--workdir", str(tmp_path / "wd")])
    assert result.exit_code == 2
    assert "invalid TOML" in _err(result) and len(_err(result).strip().splitlines()) == 1
    path = write_pipeline(tmp_path)
    (tmp_path / "file").write_text("")
    result = runner.invoke(cli, ["run", str(path), "--workdir", str(tmp_path / "file")])
    assert result.exit_code != 0


@pytest.mark.slow
def test_default_pipeline_weights_reduce_multiplicative_bias(runner, cli, tmp_path: Path) -> None:
    """The issue's check at a quarter of the default size (about 75 000 stamps, minutes)."""
    wd = tmp_path / "wd"
    result = runner.invoke(cli, ["run", "scale=0.25", "--workdir", str(wd), "-j", "2"])
    assert result.exit_code == 0, _err(result)
    assert "unweighted" in result.stdout and "weighted" in result.stdout
    ev = json.loads((wd / "evaluation.json").read_text())
    for comp in ("g1", "g2"):
        unweighted, weighted = ev["unweighted"][comp], ev["weighted"][comp]
        assert abs(weighted["m"]) < abs(unweighted["m"]), comp
        # the unweighted estimates are biased (noise bias of faint galaxies, selection of failures)
        assert unweighted["m"] < 0
    # the second table: the shipped model, trained on far more stamps, on the same rows
    assert "the shipped model fiducial (models/fiducial.h5) on vo" in result.stdout
    ref = json.loads((wd / "evaluation-reference.json").read_text())
    assert ref["weighted"]["g1"]["n_rows"] == ev["weighted"]["g1"]["n_rows"]
