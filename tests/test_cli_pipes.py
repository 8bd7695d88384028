"""Shell pipelines: '-' is stdout for -o and --json, stdin for catalog inputs; logs stay on
stderr."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from helpers import make_model
from sim_configs import write

from megalut_cli.catalog import read_catalog

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """Stamps, their catalog (with truth) and a model using the measured features."""
    from megalut_cli.sim.config import load_config
    from megalut_cli.sim.simulate import simulate

    tmp = tmp_path_factory.mktemp("pipes")
    cfg = load_config(write(tmp), (), n_cases=4, n_realizations=6)
    simulate(cfg, tmp / "cat.fits", stamps=tmp / "stamps.fits", seed=3)
    make_model(tmp / "model.h5")
    return tmp


def _table(data: bytes):
    with fits.open(io.BytesIO(data)) as hdul:
        hdu = next(h for h in hdul if isinstance(h, fits.BinTableHDU))
        return {n: np.array(hdu.data[n]) for n in hdu.columns.names}, dict(hdu.header)


def test_measure_predict_evaluate_chain_through_stdin_and_stdout(runner, cli, sim):
    measured = runner.invoke(
        cli, ["measure", str(sim / "stamps.fits"), str(sim / "cat.fits"), "-o", "-"]
    )
    assert measured.exit_code == 0, measured.stderr
    assert "megalut:" in measured.stderr  # the logs went to stderr, not into the FITS stream
    cols, header = _table(measured.stdout_bytes)
    assert header["MLFORMAT"] == "megalut.features" and len(cols["x"]) == 24
    assert not (Path.cwd() / "-").exists()

    predicted = runner.invoke(
        cli,
        ["predict", "-", "--model", str(sim / "model.h5"), "-o", "-"],
        input=measured.stdout_bytes,
    )
    assert predicted.exit_code == 0, predicted.stderr
    cols2, header2 = _table(predicted.stdout_bytes)
    np.testing.assert_array_equal(cols2["adamom_g1"], cols["adamom_g1"])
    assert "pre_g1" in cols2 and "MODELSHA" in header2

    evaluated = runner.invoke(cli, ["evaluate", "-", "--json", "-"], input=predicted.stdout_bytes)
    assert evaluated.exit_code == 0, evaluated.stderr
    result = json.loads(evaluated.stdout)  # stdout holds the JSON only; the table went to stderr
    assert "unweighted" in evaluated.stderr and result
    plain = runner.invoke(cli, ["evaluate", "-"], input=predicted.stdout_bytes)
    assert plain.exit_code == 0 and "unweighted" in plain.stdout


def test_stdin_and_stdout_equal_the_files(runner, cli, sim, tmp_path):
    """The same bytes of catalog through a pipe or through files give the same predictions."""
    out = tmp_path / "shears.fits"
    model = str(sim / "model.h5")
    via_files = runner.invoke(
        cli, ["predict", str(sim / "cat.fits"), "--model", model, "-o", str(out)]
    )
    assert (
        via_files.exit_code != 0
    )  # the truth catalog has no features: refused the same way from stdin
    piped = runner.invoke(
        cli, ["predict", "-", "--model", model, "-o", "-"], input=(sim / "cat.fits").read_bytes()
    )
    assert piped.exit_code == 1 and piped.stdout_bytes == b""
    assert "Traceback" not in piped.stderr
    assert _one_line(piped).startswith("Error: stdin: missing column(s)")  # not the temporary file

    feats = tmp_path / "f.fits"
    assert (
        runner.invoke(
            cli, ["measure", str(sim / "stamps.fits"), str(sim / "cat.fits"), "-o", str(feats)]
        ).exit_code
        == 0
    )
    assert (
        runner.invoke(cli, ["predict", str(feats), "--model", model, "-o", str(out)]).exit_code == 0
    )
    piped = runner.invoke(
        cli, ["predict", "-", "--model", model, "-o", "-"], input=feats.read_bytes()
    )
    assert piped.exit_code == 0, piped.stderr
    cols, _ = _table(piped.stdout_bytes)
    t = read_catalog(out)
    np.testing.assert_array_equal(cols["pre_g1"], np.asarray(t["pre_g1"]))


def test_simulate_and_train_read_and_write_dash(runner, cli, tmp_path):
    sim = runner.invoke(
        cli,
        [
            "simulate",
            str(write(tmp_path)),
            "-o",
            "-",
            "--measure",
            "--n-cases",
            "6",
            "--n-realizations",
            "4",
        ],
    )
    assert sim.exit_code == 0, sim.stderr
    cols, header = _table(sim.stdout_bytes)
    assert header["MLFORMAT"] == "megalut.simulation" and len(cols["case"]) == 24
    model = tmp_path / "m.h5"
    trained = runner.invoke(
        cli,
        [
            "train-point",
            "-",
            "-o",
            str(model),
            "--iterations",
            "2",
            "--members",
            "2",
            "--valid-fraction",
            "0",
        ],
        input=sim.stdout_bytes,
    )
    assert trained.exit_code == 0, trained.stderr
    assert model.is_file() and trained.stdout == ""
    from megalut_cli.nn.model import ShearModel

    setup = ShearModel.load(model).provenance["setup"]  # recorded for predict's check
    assert setup["stamp_size"] == 24 and setup["psf"] == {"type": "gaussian", "sigma": 1.5}
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_empty_stdin_is_one_line_error(runner, cli, sim):
    result = runner.invoke(
        cli, ["predict", "-", "--model", str(sim / "model.h5"), "-o", "-"], input=b""
    )
    assert result.exit_code == 1 and result.stdout_bytes == b""
    assert len(result.stderr.strip().splitlines()) == 1 and "stdin" in result.stderr


def _one_line(result) -> str:
    lines = result.stderr.strip().splitlines()
    assert len(lines) >= 1 and "Traceback" not in result.stderr
    return lines[-1]


def _megalut(*args: str) -> list[str]:
    return [sys.executable, "-m", "megalut_cli", *args]


def test_real_shell_pipeline_and_closed_pipe(sim):
    """Through real pipes: stdout carries only FITS bytes, and `| head` ends quietly."""
    env = {**os.environ, "MEGALUT_NPROC": "1"}
    cmd = (
        f"{' '.join(_megalut('measure', str(sim / 'stamps.fits'), str(sim / 'cat.fits'), '-o', '-'))}"  # noqa: E501
        f" | {' '.join(_megalut('predict', '-', '--model', str(sim / 'model.h5'), '-o', '-'))}"
        f" | {' '.join(_megalut('evaluate', '-'))}"
    )
    done = subprocess.run(
        ["bash", "-o", "pipefail", "-c", cmd],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("shear biases of stdin") and "megalut:" not in done.stdout
    assert "unweighted" in done.stdout
    assert "Traceback" not in done.stderr

    cmd = (
        f"{' '.join(_megalut('measure', str(sim / 'stamps.fits'), '-o', '-'))}"
        " | head -c 100 > /dev/null"
    )
    done = subprocess.run(
        ["bash", "-o", "pipefail", "-c", cmd],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr and "Error" not in done.stderr


def test_model_output_refuses_dash(runner, cli, sim, tmp_path, monkeypatch):
    """HDF5 models cannot stream: '-o -' is a usage error, not a file named '-'."""
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(cli, ["train-point", str(sim / "cat.fits"), "-o", "-"])
    assert result.exit_code == 2 and "stdout" in result.stderr
    assert not (tmp_path / "-").exists()
