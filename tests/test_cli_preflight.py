"""Pre-flight checks, --dry-run, verbosity, progress and Ctrl-C, through the CLI."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from helpers import one_line
from pipeline_configs import write_pipeline
from sim_configs import write

from megalut_cli.catalog import write_catalog


@pytest.fixture
def inputs(tmp_path):
    """A config, a features catalog with truth and predictions, and a point model."""
    from helpers import features_catalog, make_model

    feats = features_catalog(200)
    feats["case"] = np.repeat(np.arange(20), 10)
    feats["tru_g1"] = np.repeat(np.linspace(-0.05, 0.05, 20), 10)
    feats["tru_g2"] = -feats["tru_g1"]
    feats["pre_g1"], feats["pre_g2"] = feats["tru_g1"] * 1.01, feats["tru_g2"]
    write_catalog(tmp_path / "f.fits", feats, fmt="megalut.features")
    make_model(tmp_path / "m.h5")
    return {"config": write(tmp_path), "features": tmp_path / "f.fits", "model": tmp_path / "m.h5"}


def _commands(inputs, out: str) -> dict[str, list[str]]:
    return {
        "simulate": ["simulate", str(inputs["config"]), "-o", out, "--measure"],
        "simulate --stamps": [
            "simulate",
            str(inputs["config"]),
            "-o",
            str(inputs["config"].parent / "c.fits"),
            "--stamps",
            out,
        ],
        "train-point": ["train-point", str(inputs["features"]), "-o", out, "--iterations", "2"],
        "predict": ["predict", str(inputs["features"]), "--model", str(inputs["model"]), "-o", out],
        "evaluate --json": ["evaluate", str(inputs["features"]), "--json", out],
    }


@pytest.mark.parametrize(
    "command", ["simulate", "simulate --stamps", "train-point", "predict", "evaluate --json"]
)
def test_missing_output_folder_fails_before_any_work(runner, cli, inputs, tmp_path, command):
    out = str(tmp_path / "nowhere" / "out.fits")
    result = runner.invoke(cli, _commands(inputs, out)[command])
    assert result.exit_code == 1
    text = one_line(result)
    assert out in text and "does not exist" in text
    assert not (tmp_path / "c.fits").exists()


@pytest.mark.parametrize("command", ["simulate", "train-point", "predict", "evaluate --json"])
def test_unwritable_output_folder_is_named_before_any_work(
    runner, cli, inputs, tmp_path, command, monkeypatch
):
    """The folder's write permission is checked first (simulated here: tests may run as root)."""
    import megalut_cli.atomic as atomic

    ro = tmp_path / "ro"
    ro.mkdir()
    real_access = atomic.os.access
    monkeypatch.setattr(
        atomic.os, "access", lambda p, mode: False if Path(p) == ro else real_access(p, mode)
    )
    out = str(ro / "out.fits")
    result = runner.invoke(cli, _commands(inputs, out)[command])
    assert result.exit_code == 1
    text = one_line(result)
    assert out in text and "not writable" in text and ".tmp" not in text
    assert list(ro.iterdir()) == []


@pytest.mark.parametrize("command", ["simulate", "train-point"])
def test_folder_that_takes_no_file_is_named_before_any_work(
    runner, cli, inputs, tmp_path, command, monkeypatch
):
    """Permission bits that allow writing are not enough (root, read-only mounts): the
    pre-flight creates the temporary file the writer would (issue 24: `-o /sys/x.h5` as root
    trained every network before failing)."""
    import megalut_cli.atomic as atomic

    ro = tmp_path / "ro"
    ro.mkdir()
    real_mkstemp = atomic.tempfile.mkstemp

    def refuse(*args, **kwargs):
        if Path(kwargs.get("dir", "")) == ro:
            raise OSError(30, "Read-only file system")
        return real_mkstemp(*args, **kwargs)

    monkeypatch.setattr(atomic.tempfile, "mkstemp", refuse)
    out = str(ro / "out.fits")
    result = runner.invoke(cli, _commands(inputs, out)[command])
    assert result.exit_code == 1
    text = one_line(result)
    assert out in text and "Read-only file system" in text
    assert list(ro.iterdir()) == []


def test_virtual_file_system_is_refused_before_any_work(runner, cli, inputs):
    """The case of issue 24 itself: /sys takes no new file, for root either."""
    result = runner.invoke(cli, _commands(inputs, "/sys/megalut-test.h5")["train-point"])
    assert result.exit_code == 1
    assert "/sys/megalut-test.h5" in one_line(result)


def test_simulate_dry_run_says_what_and_how_long_and_writes_nothing(runner, cli, inputs, tmp_path):
    out = tmp_path / "cat.fits"
    result = runner.invoke(
        cli,
        [
            "simulate",
            str(inputs["config"]),
            "-o",
            str(out),
            "--measure",
            "--dry-run",
            "--n-cases",
            "5",
        ],
    )
    assert result.exit_code == 0, result.stderr
    assert "5 cases x 4 realizations = 20 stamps of 24x24 px, measured" in result.stderr
    assert "stamps/s per worker in a calibration draw" in result.stderr and "about" in result.stderr
    assert not out.exists() and result.stdout == ""
    # the dry run still does the pre-flight
    (tmp_path / "cat.fits").write_text("x")
    again = runner.invoke(cli, ["simulate", str(inputs["config"]), "-o", str(out), "--dry-run"])
    assert again.exit_code == 1 and "--overwrite" in again.stderr


def test_small_simulation_makes_no_calibration_draw(runner, cli, inputs, tmp_path, monkeypatch):
    """A run far below ESTIMATE_MIN_STAMPS says what it does but draws nothing to time it
    (the calibration would cost more than the run); --dry-run still estimates."""
    from megalut_cli.sim import simulate as sim_module

    calls = []
    real = sim_module.stamps_per_second
    monkeypatch.setattr(
        sim_module, "stamps_per_second", lambda *a, **k: calls.append(1) or real(*a, **k)
    )
    out = tmp_path / "cat.fits"
    result = runner.invoke(
        cli,
        [
            "simulate",
            str(inputs["config"]),
            "-o",
            str(out),
            "--measure",
            "--n-cases",
            "3",
            "-j",
            "1",
        ],
    )
    assert result.exit_code == 0, result.stderr
    assert (
        "3 cases x 4 realizations = 12 stamps of 24x24 px, measured, on 1 worker(s)"
        in result.stderr
    )
    assert "calibration draw" not in result.stderr and calls == [] and out.exists()
    assert sim_module.ESTIMATE_MIN_STAMPS >= 100 * sim_module.CALIBRATION_STAMPS
    dry = runner.invoke(
        cli,
        [
            "simulate",
            str(inputs["config"]),
            "-o",
            str(out),
            "--measure",
            "--n-cases",
            "3",
            "--dry-run",
            "--overwrite",
        ],
    )
    assert dry.exit_code == 0 and "calibration draw" in dry.stderr and calls == [1]


def test_run_dry_run_lists_steps_and_creates_nothing(runner, cli, tmp_path):
    wd = tmp_path / "wd"
    result = runner.invoke(
        cli, ["run", str(write_pipeline(tmp_path)), "--workdir", str(wd), "--dry-run"]
    )
    assert result.exit_code == 0, result.stderr
    for line in (
        "[1/8] simulate-tp: 24 cases x 8 realizations = 192 stamps",
        "[4/8] train-point",
        "[7/8] evaluate",
        "[8/8] model",
    ):
        assert line in result.stderr
    assert "calibration draw" in result.stderr
    assert not wd.exists() and result.stdout == ""


def test_run_dry_run_with_skip_existing_names_the_up_to_date_simulations(runner, cli, tmp_path):
    """No calibration draw, and no time, for a simulation that --skip-existing will skip."""
    wd = tmp_path / "wd"
    pipeline = str(write_pipeline(tmp_path))
    assert runner.invoke(cli, ["run", pipeline, "--workdir", str(wd), "-q"]).exit_code == 0
    result = runner.invoke(
        cli,
        ["run", pipeline, "sets.tw.seed=77", "--workdir", str(wd), "--dry-run", "--skip-existing"],
    )
    assert result.exit_code == 0, result.stderr
    lines = result.stderr.splitlines()
    assert any(line.endswith("simulate-tp: up to date, will be skipped") for line in lines), lines
    assert any(line.endswith("simulate-vo: up to date, will be skipped") for line in lines), lines
    assert any("simulate-tw:" in line and "calibration draw" in line for line in lines), lines


def test_run_unwritable_workdir_fails_first(runner, cli, tmp_path):
    (tmp_path / "afile").write_text("x")
    wd = tmp_path / "afile" / "wd"
    result = runner.invoke(cli, ["run", str(write_pipeline(tmp_path)), "--workdir", str(wd)])
    assert result.exit_code == 1
    assert str(wd) in one_line(result)


def test_verbosity_before_and_after_the_subcommand(runner, cli, inputs, tmp_path):
    args = [
        "simulate",
        str(inputs["config"]),
        "--measure",
        "--overwrite",
        "-o",
        str(tmp_path / "c.fits"),
    ]
    normal = runner.invoke(cli, args)
    assert normal.exit_code == 0 and "about to simulate" in normal.stderr
    assert "simulate: 3/3" not in normal.stderr  # progress lines are silent off a terminal
    for quiet in (["-q", *args], [*args, "-q"]):
        result = runner.invoke(cli, quiet)
        assert result.exit_code == 0 and result.stderr == "", result.stderr
    verbose = runner.invoke(cli, [*args, "-v"])
    assert verbose.exit_code == 0 and "simulate: 3/3" in verbose.stderr
    assert logging.getLogger("h5py").getEffectiveLevel() == logging.WARNING
    assert logging.getLogger("megalut_cli").getEffectiveLevel() == logging.DEBUG
    both = runner.invoke(cli, ["-v", *args, "-v"])  # they add up: -vv
    assert both.exit_code == 0
    assert logging.getLogger("h5py").getEffectiveLevel() == logging.DEBUG
    undone = runner.invoke(cli, ["-v", *args, "-q"])
    assert (
        undone.exit_code == 0
        and "simulate: 3/3" not in undone.stderr
        and "about to" in undone.stderr
    )


def test_ctrl_c_exits_130_with_one_line_and_no_file(runner, cli, inputs, tmp_path, monkeypatch):
    import megalut_cli.sim.simulate as sim

    real = sim.write_image

    def interrupted(path, *args, **kwargs):
        real(path, *args, **kwargs)  # the temporary files are written, then Ctrl-C
        assert Path(path).exists()
        raise KeyboardInterrupt

    monkeypatch.setattr(sim, "write_image", interrupted)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    result = runner.invoke(
        cli,
        [
            "simulate",
            str(inputs["config"]),
            "-o",
            str(out_dir / "c.fits"),
            "--measure",
            "--stamps",
            str(out_dir / "s.fits"),
        ],
    )
    assert result.exit_code == 130
    assert result.stderr.splitlines()[-1] == "megalut: interrupted"
    assert "Traceback" not in result.stderr and "Aborted" not in result.stderr
    assert list(out_dir.iterdir()) == []  # neither output nor temporary files


def test_ctrl_c_while_workers_start_is_one_line(inputs, tmp_path):
    """A real SIGINT to the whole process group (as a terminal sends it) just as `-j 2`
    starts its workers: one line, exit 130, no worker traceback, no file (issue 24)."""
    import os
    import signal
    import subprocess
    import sys

    out_dir = tmp_path / "out"
    out_dir.mkdir()
    env = {**os.environ, "MEGALUT_NPROC": "2"}
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "megalut_cli",
            "simulate",
            str(inputs["config"]),
            "--measure",
            "-v",
            "--n-cases",
            "4000",
            "-o",
            str(out_dir / "c.fits"),
        ],
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
        env=env,
        start_new_session=True,
    )
    lines = []
    try:
        for line in proc.stderr:
            lines.append(line)
            if "local worker processes" in line:
                os.killpg(proc.pid, signal.SIGINT)
                break
        rest = proc.stderr.read()
        assert proc.wait(timeout=60) == 130, "".join(lines) + rest
    finally:
        if proc.poll() is None:
            proc.kill()
    assert "Traceback" not in rest and rest.strip().splitlines() == ["megalut: interrupted"], rest
    assert list(out_dir.iterdir()) == []


def test_progress_bar_gets_its_own_line(monkeypatch, capsys):
    """On a terminal, a log line first clears the bar's line; with CI set, there is no bar."""
    from megalut_cli.cli import console

    console.setup_logging(0)
    monkeypatch.setattr(console, "interactive", lambda: True)
    with console.progress("work", 4) as update:
        update(1)
        logging.getLogger("megalut_cli").info("hello")
        update(3)
    err = capsys.readouterr().err
    assert "\r\x1b[Kmegalut: hello\n" in err and "work" in err

    monkeypatch.undo()
    monkeypatch.setenv("CI", "true")
    monkeypatch.setattr("sys.stderr.isatty", lambda: True, raising=False)
    assert not console.interactive()


def test_progress_off_a_terminal_estimates_the_time_left(monkeypatch, caplog):
    """Silent per step; an info line from the measured pace once a tenth is done, on long jobs,
    and again from the pace since then a quarter further on (not sooner than 20 s later)."""
    from megalut_cli.cli import console

    clock = iter([0.0, 5.0, 30.0, 31.0, 32.0, 60.0])
    monkeypatch.setattr(console.time, "perf_counter", lambda: next(clock))
    monkeypatch.setattr(console, "interactive", lambda: False)
    with (
        caplog.at_level(logging.INFO, logger="megalut_cli"),
        console.progress("units", 10) as update,
    ):
        for _ in range(5):
            update(1)
    infos = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
    assert infos == [
        "units: 2/10 in 30 s, about 2.0 min left",
        "units: 5/10 in 60 s, about 50 s left",
    ]


def test_progress_estimate_waits_for_every_unit_running_at_once(monkeypatch, caplog):
    """Units that ran at once finish together: the estimate waits for all of them, else the
    first alone (8 units on 2 workers, the second done 4 s later) gives twice the time left."""
    from megalut_cli.cli import console

    clock = iter([0.0, 84.0, 88.0, 168.0])
    monkeypatch.setattr(console.time, "perf_counter", lambda: next(clock))
    monkeypatch.setattr(console, "interactive", lambda: False)
    with (
        caplog.at_level(logging.INFO, logger="megalut_cli"),
        console.progress("simulate", 8, parallel=2) as update,
    ):
        for _ in range(3):
            update(1)
    infos = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
    assert infos == ["simulate: 2/8 in 88 s, about 4.4 min left"]


def test_progress_later_estimates_take_the_pace_since_the_last(monkeypatch, caplog):
    """A first round slowed by warm-up: set 4408's units (8 on 2 processes, measured on
    completion) finished at 9.3, 13.9, 18.5 and 23.0 min, two at a time. The first line says
    27.9 min left (13.7 true); the later ones take the pace since the line before."""
    from megalut_cli.cli import console

    minutes = [9.3, 9.3, 13.9, 13.9, 18.5, 18.5, 23.0, 23.0]
    clock = iter([0.0] + [60.0 * t for t in minutes])
    monkeypatch.setattr(console.time, "perf_counter", lambda: next(clock))
    monkeypatch.setattr(console, "interactive", lambda: False)
    with (
        caplog.at_level(logging.INFO, logger="megalut_cli"),
        console.progress("simulate", 8, parallel=2) as update,
    ):
        for _ in minutes:
            update(1)
    infos = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
    assert infos == [
        "simulate: 2/8 in 9.3 min, about 27.9 min left",
        "simulate: 4/8 in 13.9 min, about 9.2 min left",
        "simulate: 6/8 in 18.5 min, about 4.6 min left",
    ]
