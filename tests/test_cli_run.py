"""`megalut run`: the whole pipeline from the command line."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from helpers import error_text
from pipeline_configs import write_pipeline

from megalut_cli.pipeline.config import default_pipeline_text

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def test_help(runner, cli) -> None:
    result = runner.invoke(cli, ["run", "--help"])
    assert result.exit_code == 0
    for text in (
        "PIPELINE.toml",
        "--workdir",
        "--skip-existing",
        "--scheduler",
        "-j",
        "megalut-run",
        "Example",
    ):
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
    assert result.exit_code == 0, result.output + error_text(result)
    out = result.stdout
    assert "unweighted" in out and "weighted" in out
    assert out.count("  g1 ") >= 2 and out.count("  g2 ") >= 2  # m and c rows of both schemes
    for step in ("simulate-tp", "train-point", "train-weight", "predict", "evaluate"):
        assert f"{step}: done in" in error_text(result)
    assert "pipeline finished in" in error_text(result)
    ev = json.loads((wd / "evaluation.json").read_text())
    png = (wd / "evaluation.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"

    # evaluation.json has the layout of `megalut evaluate --json`
    other = tmp_path / "other.json"
    assert (
        runner.invoke(cli, ["evaluate", str(wd / "vo-shears.fits"), "--json", str(other)]).exit_code
        == 0
    )
    direct = json.loads(other.read_text())
    assert ev.keys() == direct.keys()
    assert ev["weighted"] == direct["weighted"] and ev["unweighted"] == direct["unweighted"]

    # again without a flag: refused, one line, nothing touched
    mtime = (wd / "model.h5").stat().st_mtime_ns
    again = runner.invoke(cli, args)
    assert again.exit_code == 1
    assert (
        "exists; use --skip-existing" in error_text(again)
        and len(error_text(again).strip().splitlines()) == 1
    )
    assert (wd / "model.h5").stat().st_mtime_ns == mtime

    # --skip-existing: all up to date, the same table
    skipped = runner.invoke(cli, [*args, "--skip-existing", "-j", "2"])
    assert skipped.exit_code == 0, error_text(skipped)
    assert error_text(skipped).count("up to date, skipped") == 8
    assert skipped.stdout == out
    assert (wd / "model.h5").stat().st_mtime_ns == mtime

    # the product carries its own validation: predict reports a bias beyond Stage IV
    m = max(abs(ev["weighted"][g]["m"]) for g in ("g1", "g2"))
    pred = runner.invoke(
        cli, ["predict", str(wd / "vo.fits"), "--model", str(wd / "model.h5"), "-o", "-"]
    )
    assert pred.exit_code == 0
    said = "recorded bias on its simulated validation (weighted, vo-shears.fits)"
    assert (said in error_text(pred)) == (m > 2e-3), error_text(pred)


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
    err = error_text(result)
    assert message in err
    assert "Traceback" not in err
    assert not (tmp_path / "wd").exists()


def test_bad_pipeline_file(runner, cli, tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[sets.tp\n")
    result = runner.invoke(cli, ["run", str(bad), "--workdir", str(tmp_path / "wd")])
    assert result.exit_code == 2
    assert (
        "invalid TOML" in error_text(result) and len(error_text(result).strip().splitlines()) == 1
    )
    path = write_pipeline(tmp_path)
    (tmp_path / "file").write_text("")
    result = runner.invoke(cli, ["run", str(path), "--workdir", str(tmp_path / "file")])
    assert result.exit_code != 0


#: The Stage IV requirement and the default run's claim (README's results, docs/results.md):
#: weighted m, c within 2 sigma.
REQUIREMENT_M, REQUIREMENT_C = 2e-3, 2e-4
#: The usable rows of the default-run tables of docs/results.md, and the CPU they were recorded on
#: (:func:`cpu_signature`): numba's kernels are compiled for the host CPU and numpy's loops
#: dispatch to its widest vectors, so the last digits of stamps, features and float32
#: trainings depend on it.
RECORDED_ROWS, RECORDED_CPU = 386800, "family 26, model 2, AVX-512"


def cpu_signature() -> str | None:
    """``family F, model M, AVX-512`` (or ``no AVX-512``) from ``/proc/cpuinfo``; None where
    there is none."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return None
    fields: dict[str, str] = {}
    for line in text.splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    if "cpu family" not in fields or "model" not in fields:
        return None
    vectors = "AVX-512" if "avx512f" in fields.get("flags", "").split() else "no AVX-512"
    return f"family {fields['cpu family']}, model {fields['model']}, {vectors}"


def recorded_default_run_tables() -> dict[str, dict[str, dict[str, float]]]:
    """The m, c and errors of the two weighted tables docs/results.md records for the default
    run."""
    import re

    text = (Path(__file__).resolve().parents[1] / "docs" / "results.md").read_text()
    block = text[text.index("exactly `megalut run --workdir") :]
    block = block[block.index("```") :]
    block = block[: block.index("```", 3)]
    row = re.compile(r"^\s+(g[12])\s+([-+0-9.e]+) ± ([0-9.e-]+)\s+([-+0-9.e]+) ± ([0-9.e-]+)", re.M)
    tables = {}
    for name, part in zip(("run", "reference"), block.split("== the shipped model")):
        weighted = part[part.index("weighted (per-case weighted") :]
        tables[name] = {
            g: dict(zip(("m", "m_err", "c", "c_err"), map(float, v)))
            for g, *v in row.findall(weighted)
        }
    return tables


def test_results_page_records_the_default_run_tables() -> None:
    tables = recorded_default_run_tables()
    assert set(tables) == {"run", "reference"} and all(
        set(t) == {"g1", "g2"} for t in tables.values()
    )


@pytest.mark.slow
def test_default_run_meets_the_stage_iv_requirement_within_2_sigma(
    runner, cli, tmp_path: Path
) -> None:
    """The claim on exactly the default run (1.45e6 stamps, 3 minutes on 2 cores): the
    weighted m and c within 2 sigma of the Stage IV requirement, for the run's networks and
    for the shipped model on the same validation set; the weights reduce |m|; and the run
    reproduces the tables docs/results.md records (same seeds, results independent of -j)."""
    wd = tmp_path / "wd"
    result = runner.invoke(cli, ["run", "--workdir", str(wd), "-j", "2"])
    assert result.exit_code == 0, error_text(result)
    assert "the shipped model fiducial (models/fiducial.h5) on vo" in result.stdout
    recorded = recorded_default_run_tables()
    same_cpu = cpu_signature() == RECORDED_CPU
    for name, products in (("run", "evaluation.json"), ("reference", "evaluation-reference.json")):
        ev = json.loads((wd / products).read_text())
        for comp in ("g1", "g2"):
            unweighted, weighted = ev["unweighted"][comp], ev["weighted"][comp]
            print(name, comp, {k: weighted[k] for k in ("m", "m_err", "c", "c_err")})
            assert abs(weighted["m"]) < REQUIREMENT_M + 2 * weighted["m_err"], (
                name,
                comp,
                weighted,
            )
            assert abs(weighted["c"]) < REQUIREMENT_C + 2 * weighted["c_err"], (
                name,
                comp,
                weighted,
            )
            assert weighted["m_err"] < 2e-3, (name, comp, weighted)  # 1.4e-3 recorded
            # the unweighted estimates are biased (noise bias of faint galaxies, selection of
            # failures); the weights remove most of it
            assert unweighted["m"] < -0.02 and abs(weighted["m"]) < abs(unweighted["m"]) / 5, (
                name,
                comp,
            )
            # The recorded table is this run: within a quarter of its error on the CPU it
            # was recorded on (training is deterministic for given seeds). Elsewhere the
            # compiled kernels and numpy's loops choose other instructions: a few stamps change
            # flags and the float32 trainings drift apart (measured on AMD EPYC family 25 and
            # on another family-26 VM without the same vectors: the run's networks 0.1-0.5
            # sigma from the recorded table, the shipped model's within 0.04 sigma).
            rec = recorded[name][comp]
            tolerance = 0.25 if same_cpu or name == "reference" else 1.5
            for q in ("m", "c"):
                assert abs(weighted[q] - rec[q]) < tolerance * rec[f"{q}_err"], (
                    name,
                    comp,
                    q,
                    weighted[q],
                    rec,
                )
        rows = ev["weighted"]["g1"]["n_rows"]
        assert rows == RECORDED_ROWS if same_cpu else abs(rows - RECORDED_ROWS) <= 20, rows
