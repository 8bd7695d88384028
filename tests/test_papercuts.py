"""The first-contact papercuts of issue 24: what a new user meets in the first minutes
(README's install line and tables, messages naming files and keys as written, refusals
before any work, `info` on every file a run leaves behind)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import click
import pytest
from helpers import error_text, make_model, one_line, synthetic
from pipeline_configs import TINY_PIPELINE, write_pipeline
from sim_configs import write as write_sim_config

from megalut_cli.catalog import write_catalog
from megalut_cli.shear.options import JSON_FORMAT_VERSION

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def _setup_section() -> str:
    text = README.read_text()
    return text[text.index("## Set up") : text.index("## A tour of the subcommands")]


# --------------------------------------------------------------------------- 1. the plot extra
def test_readme_install_line_has_the_plot_extra_that_pyproject_declares() -> None:
    """README's quick start promises evaluation.png: it installs the extra that draws it,
    spelled as pyproject.toml declares it, in a form pip understands from a clone."""
    from megalut_cli.configfile import tomllib

    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]
    assert any(dep.startswith("matplotlib") for dep in extras["plot"])
    setup = _setup_section()
    first = re.search(r"```sh\n(.*?)```", setup, re.S).group(1)
    installs = re.findall(r"pip install (\S+)", first)
    assert installs == ['".[plot]"'], installs
    assert "evaluation.png" in setup


def test_matplotlib_hint_is_a_command_that_works(runner, cli, tmp_path, monkeypatch) -> None:
    """Without matplotlib, `evaluate --plot` says how to install it with a command that
    works from a clone (the package is not on the index, so `megalut-cli[plot]` is not)."""
    from megalut_cli.shear import plots

    assert plots.MATPLOTLIB_HINT == "pip install matplotlib"
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)  # an import of it fails
    path = tmp_path / "s.fits"
    write_catalog(path, synthetic(seed=1, n_cases=10, n_rea=5), fmt="megalut.predictions")
    result = runner.invoke(cli, ["evaluate", str(path), "--plot", str(tmp_path / "e.png")])
    assert result.exit_code == 1
    assert one_line(result).endswith("figures need matplotlib: pip install matplotlib")
    for doc in [README, *sorted((ROOT / "docs").glob("*.md"))]:
        assert "megalut-cli[plot]" not in doc.read_text(), doc


# --------------------------------------------------------------------------- 2. the tour's table
def _tour_tool():
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        import readme_tour
    finally:
        sys.path.remove(str(ROOT / "tools"))
    return readme_tour


def test_readme_tour_tool_reads_the_commands_and_the_table() -> None:
    tour = _tour_tool()
    text = README.read_text()
    commands = tour.tour_commands(text)
    assert "megalut evaluate shears.fits" in commands and commands.startswith("E=examples/fiducial")
    table, _ = tour.readme_table(text)
    rows = tour.rows(table)
    assert set(rows) == {"g1", "g2"}
    assert rows["g1"][4:] == (20, 3871)  # 20 cases x 200 realizations, less the failed measurements


@pytest.mark.slow
def test_readme_tour_reproduces_its_table() -> None:
    """README's tour, rerun as it stands (about a minute on 2 cores), prints README's table."""
    res = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "readme_tour.py")], capture_output=True, text=True
    )
    assert res.returncode == 0, res.stderr[-3000:]


# --------------------------------------------------------------------------- 3. a quick first run
def test_readme_setup_shows_a_quick_first_run_with_its_time() -> None:
    setup = _setup_section()
    m = re.search(r"megalut run scale=0\.02[^\n]*\n```\n\n[^`]*?(\d+) s ", setup)
    assert m, "README's set-up section shows `megalut run scale=0.02` and its measured time"
    assert "2-core machine, shared" in setup[m.start() : m.end() + 200]


# --------------------------------------------------------------------------- 4. keys as written
@pytest.mark.parametrize(
    ("edit", "overrides", "expected"),
    [
        (("sigma = 1.0", "sigam = 1.0"), [], "{file}: [simulation.noise] sigam: unknown key"),
        (
            ("sigma = 1.0", "sigma = -1.0"),
            [],
            "{file}: [simulation.noise] sigma: the noise sigma must be >= 0",
        ),
        (("n_cases = 24", "n_cases = -3"), [], "{file}: [sets.tp] n_cases: must be >= 1"),
        (
            ('snc = "ring"', 'snc = "rong"'),
            [],
            "{file}: [sets.tp] simulation.structure.snc: unknown value 'rong'",
        ),
        (("iterations = 15", "iteration = 15"), [], "{file}: [train_point] iteration: unknown key"),
        (None, ["simulation.noise.sigam=1"], "simulation.noise.sigam: unknown key"),
        (
            None,
            ["sets.tp.simulation.structure.snc=x"],
            "sets.tp.simulation.structure.snc: unknown value 'x'",
        ),
    ],
)
def test_pipeline_errors_name_the_file_and_table_as_written(
    runner, cli, tmp_path, edit, overrides, expected
) -> None:
    text = TINY_PIPELINE if edit is None else TINY_PIPELINE.replace(*edit, 1)
    path = write_pipeline(tmp_path, text)
    result = runner.invoke(
        cli, ["run", str(path), *overrides, "--workdir", str(tmp_path / "wd"), "--dry-run"]
    )
    assert result.exit_code == 2
    assert one_line(result).startswith("Error: " + expected.format(file=path)), error_text(result)
    assert not (tmp_path / "wd").exists()


def test_pipeline_errors_in_a_set_config_file_name_that_file(
    runner, cli, tmp_path, monkeypatch
) -> None:
    cfg = write_sim_config(tmp_path, name="tp-sim.toml")
    text = cfg.read_text()
    assert "\n[noise]" in text and "sigma" in text
    cfg.write_text(re.sub(r"(\[noise\][^\[]*?)\bsigma\b", r"\1sigam", text, count=1))
    pipe = TINY_PIPELINE.replace("[sets.tp]\n", '[sets.tp]\nconfig = "tp-sim.toml"\n', 1)
    pipe = pipe.replace(
        'simulation = {structure = {per_realization = ["angle"], snc = "ring"}}\n', "", 1
    )
    path = write_pipeline(tmp_path, pipe)
    monkeypatch.chdir(tmp_path)  # the config file is named relative to the current folder
    result = runner.invoke(cli, ["run", str(path), "--workdir", str(tmp_path / "wd"), "--dry-run"])
    assert result.exit_code == 2
    assert one_line(result).startswith("Error: tp-sim.toml: [noise] sigam: unknown key"), (
        error_text(result)
    )


def test_where_written_keeps_other_messages() -> None:
    from megalut_cli.pipeline.config import table_key, where_written

    assert table_key("[a.b]\nx = 1\n[a]\n", ["a", "b", "c", "d"]) == "[a.b] c.d"
    assert table_key("x = 1\n", ["x"]) == "x"
    assert table_key("[pretrain]\n", ["pretrain"]) == "[pretrain]"
    assert where_written("override 'x': bad key", None) == "override 'x': bad key"
    assert (
        where_written("/abs/file.toml: invalid TOML (...)", None)
        == "/abs/file.toml: invalid TOML (...)"
    )


# --------------------------------------------------------------------------- 5. errors n/a
def test_evaluate_says_why_errors_are_na(runner, cli, tmp_path) -> None:
    from megalut_cli.shear.evaluate import errors_na_note

    path = tmp_path / "two.fits"
    write_catalog(path, synthetic(seed=1, n_cases=2, n_rea=20), fmt="megalut.predictions")
    result = runner.invoke(cli, ["evaluate", str(path)])
    assert result.exit_code == 0
    assert "±   n/a" in result.stdout
    assert (
        "megalut: errors n/a: errors from the fit need at least 3 cases (the residual scatter "
        "about the line has N - 2 degrees of freedom); the catalog has 2 usable cases"
    ) in error_text(result)
    many = tmp_path / "many.fits"
    write_catalog(many, synthetic(seed=1, n_cases=10, n_rea=5), fmt="megalut.predictions")
    result = runner.invoke(cli, ["evaluate", str(many)])
    assert result.exit_code == 0 and "errors n/a" not in error_text(result)
    result = runner.invoke(
        cli, ["evaluate", str(many), "--by", "tru_rad", "--bins", "5", "--json", "-"]
    )
    assert errors_na_note(json.loads(result.stdout)).startswith(
        "errors n/a (conditional bins): errors from the fit need at least 3 cases"
    )


# --------------------------------------------------------------------------- 6. --plot e.jpg
def test_plot_with_an_unsupported_extension_is_a_usage_error_before_any_work(
    runner, cli, tmp_path, monkeypatch
) -> None:
    import megalut_cli.shear.evaluate as ev

    def no_work(*args, **kwargs):
        raise AssertionError("evaluated before refusing --plot")

    monkeypatch.setattr(ev, "evaluate_catalog", no_work)
    path = tmp_path / "s.fits"
    write_catalog(path, synthetic(seed=1, n_cases=10, n_rea=5), fmt="megalut.predictions")
    result = runner.invoke(
        cli,
        [
            "evaluate",
            str(path),
            "--json",
            str(tmp_path / "e.json"),
            "--plot",
            str(tmp_path / "e.jpg"),
        ],
    )
    assert result.exit_code == 2
    err = error_text(result)
    assert "Invalid value for '--plot'" in err and ".png, .pdf, .svg" in err and "e.jpg" in err
    assert not (tmp_path / "e.json").exists()


def test_check_plot_output_refuses_the_extension_first() -> None:
    from megalut_cli.errors import ConfigError
    from megalut_cli.shear.plots import check_plot_output

    with pytest.raises(
        ConfigError, match=r"e\.jpg: unsupported figure type \(use a name ending in \.png"
    ):
        check_plot_output("e.jpg")


# --------------------------------------------------------------------------- 7. -o - to a terminal
class _Terminal:
    def isatty(self) -> bool:
        return True


def test_stdout_path_refuses_a_terminal(monkeypatch) -> None:
    from megalut_cli.cli.console import stdout_path

    monkeypatch.setattr(sys, "stdout", _Terminal())
    with pytest.raises(click.UsageError, match="stdout is a terminal") as err, stdout_path("-"):
        pass
    assert err.value.exit_code == 2
    with stdout_path("out.fits") as p:  # a file is fine
        assert p == "out.fits"


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs a pseudo-terminal")
def test_dash_o_to_a_terminal_is_refused_before_any_work(tmp_path) -> None:
    cfg = write_sim_config(tmp_path)
    leader, follower = os.openpty()
    try:
        res = subprocess.run(
            [sys.executable, "-m", "megalut_cli", "simulate", str(cfg), "-o", "-", "--measure"],
            stdout=follower,
            stderr=subprocess.PIPE,
            stdin=subprocess.DEVNULL,
            text=True,
            cwd=tmp_path,
            timeout=120,
        )
    finally:
        os.close(follower)
        os.close(leader)
    assert res.returncode == 2, res.stderr
    assert "'-o -' writes a FITS file to stdout, but stdout is a terminal" in res.stderr
    assert "about to simulate" not in res.stderr


# ------------------------------------------------------------------- 8. simulate says what it wrote
def test_simulate_logs_what_it_wrote(runner, cli, tmp_path) -> None:
    out, stamps = tmp_path / "cat.fits", tmp_path / "stamps.fits"
    result = runner.invoke(
        cli,
        [
            "simulate",
            str(write_sim_config(tmp_path)),
            "-o",
            str(out),
            "--stamps",
            str(stamps),
            "--n-cases",
            "2",
            "--n-realizations",
            "4",
        ],
    )
    assert result.exit_code == 0, error_text(result)
    assert f"megalut: wrote {out} (8 rows) and {stamps}" in error_text(result)


# ------------------------------------------------------------------- 9. info on JSON and text files
def test_info_reads_an_evaluation(runner, cli, tmp_path) -> None:
    shears, ev = tmp_path / "s.fits", tmp_path / "evaluation.json"
    write_catalog(
        shears, synthetic(seed=1, n_cases=10, n_rea=5, weights=True), fmt="megalut.predictions"
    )
    assert runner.invoke(cli, ["evaluate", str(shears), "--json", str(ev)]).exit_code == 0
    result = runner.invoke(cli, ["info", str(ev)])
    assert result.exit_code == 0, error_text(result)
    lines = result.stdout.splitlines()
    assert (
        lines[0] == f"{ev}: megalut.evaluation {JSON_FORMAT_VERSION}, the biases of {shears} "
        "(50 of 50 rows usable)"
    )
    assert any(
        re.match(r"  weighted   g2    m = [-+]\d\.\d\de[-+]\d\d ± \d\.\de[-+]\d\d .* 10 cases$", x)
        for x in lines
    )
    assert lines[-1].startswith("command: megalut evaluate")
    as_json = json.loads(runner.invoke(cli, ["info", str(ev), "--json"]).stdout)
    assert as_json["kind"] == "evaluation" and as_json["fits"]["unweighted"]["g1"]["n_cases"] == 10


def test_info_reads_a_run_manifest(runner, cli, tmp_path) -> None:
    from megalut_cli.pipeline.steps import Manifest, RunRecord, Step

    path = tmp_path / "manifest.json"
    manifest = Manifest(path, RunRecord("", "pipeline.toml", "ab" * 32, ("scale=0.02",), {}))
    step = Step("simulate-tp", ["tp.fits"], [], {}, lambda workdir, overwrite: None)
    manifest.record(
        step, "k", {}, {"tp.fits": {"sha256": "cd" * 32, "size": 1, "mtime_ns": 0}}, 6.25
    )
    result = runner.invoke(cli, ["info", str(path)])
    assert result.exit_code == 0, error_text(result)
    lines = result.stdout.splitlines()
    assert lines[0].startswith(f"{path}: megalut.run-manifest")
    assert lines[1] == "pipeline: pipeline.toml (sha256 abababababab), overrides: scale=0.02"
    assert lines[2] == "steps: 1 finished"
    assert re.match(r"  simulate-tp\s+6\.2 s  \S+  tp\.fits$", lines[3]), lines[3]


def test_info_reads_a_great3_text_catalog(runner, cli, tmp_path) -> None:
    from megalut_cli.catalog import write_text_catalog
    from megalut_cli.great3.layout import galaxy_catalog

    path = tmp_path / "galaxy_catalog-003.txt"
    write_text_catalog(path, galaxy_catalog(3, 4, 4, 48))
    result = runner.invoke(cli, ["info", str(path)])
    assert result.exit_code == 0, error_text(result)
    assert result.stdout.splitlines() == [
        f"{path}: GREAT3 galaxy catalog (text), 16 rows, 3 columns: x, y, ID",
        "subfields (ID // 10^6): 3",
        "x: 23 to 167",
        "y: 23 to 167",
    ]


def test_info_refuses_other_json_and_text_in_one_line(runner, cli, tmp_path) -> None:
    (tmp_path / "x.json").write_text('{"a": 1}')
    (tmp_path / "x.txt").write_text("hello\n")
    for name in ("x.json", "x.txt"):
        result = runner.invoke(cli, ["info", str(tmp_path / name)])
        assert result.exit_code == 1
        one_line(result)


# --------------------------------------------------------------------------- 10. no absolute paths
def test_recorded_path_is_never_absolute(tmp_path, monkeypatch) -> None:
    from megalut_cli.provenance import recorded_path

    monkeypatch.chdir(tmp_path)
    work = tmp_path / "work"
    assert recorded_path(work / "tp.fits", work) == "tp.fits"
    assert recorded_path(work / "sub" / "tp.fits") == "work/sub/tp.fits"
    assert recorded_path("/elsewhere/data/tp.fits", work) == "tp.fits"


def test_info_shows_no_absolute_path_of_the_machine_a_model_was_made_on(
    runner, cli, tmp_path
) -> None:
    from megalut_cli.nn.model import ShearModel

    path = tmp_path / "m.h5"
    model = make_model(path)
    model.provenance = {
        "command": "train-point",
        "argv": "megalut train-point tp.fits -o m.h5",
        "inputs": {"train": {"path": "/work/exp12/fiducial-model/tp.fits", "sha256": "ab" * 32}},
    }
    model.save(path, overwrite=True)
    assert (
        ShearModel.load(path).provenance["inputs"]["train"]["path"].startswith("/work/exp12")
    )  # as recorded
    result = runner.invoke(cli, ["info", str(path)])
    assert result.exit_code == 0, error_text(result)
    assert "inputs: train tp.fits (sha256 abababababab)" in result.stdout
    assert "/work/exp12" not in result.stdout
    shipped = runner.invoke(cli, ["info", str(ROOT / "models" / "fiducial.h5")])
    assert shipped.exit_code == 0
    inputs = [x for x in shipped.stdout.splitlines() if x.strip().startswith("inputs:")]
    assert inputs and not any("/work/" in x for x in inputs)
