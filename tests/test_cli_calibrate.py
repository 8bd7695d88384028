"""`megalut calibrate`: help, table, JSON, the per-object catalog, exit codes 0/1/2 and
nothing written on failure."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from helpers import assert_ok, error_line, metacal_predictions

from megalut_cli.catalog import catalog_info, read_catalog, write_catalog
from megalut_cli.provenance import sha256_file


@pytest.fixture
def metacal(tmp_path):
    """A metacal prediction catalog with weights, positions and PSF ellipticities."""
    cat = metacal_predictions(n=3000, weights=True, seed=11, ring=1)
    rng = np.random.default_rng(3)
    cat["psf_adamom_g1"], cat["psf_adamom_g2"] = rng.uniform(-0.05, 0.05, (2, 3000))
    cat["tomo"] = (np.arange(3000) % 3).astype(np.int32)
    path = tmp_path / "pred.fits"
    write_catalog(path, cat, fmt="megalut.predictions", cards={"MCALSTEP": 0.01})
    return path


def test_help(runner, cli):
    result = runner.invoke(cli, ["calibrate", "--help"])
    assert_ok(result)
    for word in (
        "--select",
        "--by",
        "--bins",
        "--unweighted",
        "--errors",
        "--patches",
        "--bootstrap",
        "--seed",
        "--json",
        "-o",
        "--overwrite",
        "Example",
    ):
        assert word in result.output


def test_table_json_and_catalog(runner, cli, metacal, tmp_path):
    """``--failures exclude``: the mean response plus the selection response, each in the
    JSON, their sum in the per-object catalog's header."""
    js, out = tmp_path / "cal.json", tmp_path / "cal.fits"
    args = ["calibrate", str(metacal), "--by", "tomo", "--select", "size > 0.5"]
    args += ["--failures", "exclude"]
    result = runner.invoke(cli, [*args, "--json", str(js), "-o", str(out)])
    assert_ok(result)
    lines = result.output.splitlines()
    assert "metacal route" in lines[0] and lines[1].split()[:2] == ["bin", "n_objects"]
    assert lines[2].startswith("all") and lines[3].startswith("tomo = 0")
    assert "alpha1" in lines[1] and "jackknife" in result.output
    res = json.loads(js.read_text())
    assert res["format"] == "megalut.calibration" and res["calibration"] == "metacal"
    for entry in (res["all"], *res["bins"]):
        for key in (
            "g1",
            "g2",
            "g1_err",
            "g2_err",
            "n_objects",
            "response",
            "selection_response",
            "scheme",
            "alpha",
            "alpha_err",
        ):
            assert key in entry
        assert np.shape(entry["response"]) == (2, 2) == np.shape(entry["selection_response"])
        assert entry["scheme"] == "weighted"
    assert [b["value"] for b in res["bins"]] == [0, 1, 2]
    assert res["provenance"]["input"]["sha256"] == sha256_file(metacal)
    assert "megalut" in res["provenance"]["versions"]
    cat = read_catalog(out)
    assert {"id", "ra", "dec", "tomo", "g1", "g2", "weight", "bin", "R11", "R22"} <= set(
        cat.colnames
    )
    assert cat.meta["CALROUTE"].strip() == "metacal" and cat.meta["CALNOTE"].strip() == "averages"
    assert cat.meta["R11B2"] == pytest.approx(
        res["bins"][2]["response"][0][0] + res["bins"][2]["selection_response"][0][0]
    )
    assert "megalut calibrate" in " ".join(cat.meta["HISTORY"])
    assert int(np.sum(cat["bin"] == 1)) == res["bins"][1]["n_objects"]


def test_failures_as_a_selection(runner, cli, metacal, tmp_path):
    """``--failures selection``, the default: the response of the versions' means, with --by
    bins and --select per version, the same per-object catalog columns; the JSON records the
    choice, the same whether asked or by default; a catalog without metacal versions is
    calibrated without it by default and refused when it is asked (exit 1, nothing
    written)."""
    js, out = tmp_path / "cal.json", tmp_path / "cal.fits"
    args = ["calibrate", str(metacal), "--by", "tomo", "--select", "size > 0.5"]
    result = runner.invoke(cli, [*args, "--json", str(js), "-o", str(out)])
    assert_ok(result)
    assert "each version's mean over its own measured objects" in result.output
    res = json.loads(js.read_text())
    assert res["failures"] == "selection" and res["all"]["selection_response"] is None
    assert len(res["bins"]) == 3 and read_catalog(out)["R11"].size == res["all"]["n_objects"]
    asked = tmp_path / "asked.json"
    result = runner.invoke(cli, [*args, "--failures", "selection", "--json", str(asked)])
    assert_ok(result)
    assert json.loads(asked.read_text())["all"] == res["all"]
    plain = tmp_path / "sim.fits"
    write_catalog(plain, {"pre_g1": np.zeros(9), "pre_g2": np.zeros(9)}, fmt="megalut.predictions")
    result = runner.invoke(cli, ["calibrate", str(plain), "-q"])
    assert_ok(result)
    bad = tmp_path / "bad.json"
    result = runner.invoke(
        cli, ["calibrate", str(plain), "--failures", "selection", "--json", str(bad)]
    )
    error_line(result, 1, "metacal catalog of stamps")
    assert not bad.exists()


def test_json_to_stdout_and_simulation_route(runner, cli, tmp_path):
    rng = np.random.default_rng(0)
    path = tmp_path / "sim.fits"
    write_catalog(
        path,
        {"pre_g1": rng.normal(0.01, 0.2, 500), "pre_g2": rng.normal(0.0, 0.2, 500)},
        fmt="megalut.predictions",
    )
    result = runner.invoke(cli, ["calibrate", str(path), "--json", "-", "--seed", "4"])
    assert_ok(result)
    res = json.loads(result.stdout)
    assert res["calibration"] == "simulation" and res["scheme"] == "unweighted"
    assert res["errors"] == {"method": "bootstrap", "resamples": 200, "seed": 4}
    assert res["all"]["g1"] == pytest.approx(np.mean(read_catalog(path)["pre_g1"]))
    assert "simulation route" in result.stderr


def test_reproducible_bootstrap(runner, cli, metacal):
    args = ["calibrate", str(metacal), "--errors", "bootstrap", "--bootstrap", "20"]
    a, b = runner.invoke(cli, [*args, "--seed", "3"]), runner.invoke(cli, [*args, "--seed", "3"])
    c = runner.invoke(cli, [*args, "--seed", "4"])
    assert a.output == b.output != c.output


def test_bad_inputs_one_line_nothing_written(runner, cli, metacal, tmp_path):
    js, out = tmp_path / "x.json", tmp_path / "x.fits"
    outputs = ["--json", str(js), "-o", str(out)]
    plain = tmp_path / "features.fits"
    write_catalog(plain, {"snr": np.ones(10), "ra": np.ones(10)}, fmt="megalut.features")
    cases = [
        ([str(plain)], 1, "missing: pre_g1, pre_g2"),
        ([str(metacal), "--select", "size > 100"], 1, "no row passes --select"),
        ([str(metacal), "--by", "nosuch"], 2, "--by: no column nosuch"),
        ([str(metacal), "--select", "size >"], 2, "cannot be read"),
        ([str(metacal), "--patches", "1"], 2, "--patches"),
    ]
    for args, code, words in cases:
        error_line(runner.invoke(cli, ["calibrate", *args, *outputs]), code, words)
        assert not js.exists() and not out.exists()
    # a metacal catalog missing one version's estimate
    cat = read_catalog(metacal)
    del cat["pre_g2_1m"]
    broken = tmp_path / "broken.fits"
    write_catalog(broken, cat, fmt="megalut.predictions")
    error_line(runner.invoke(cli, ["calibrate", str(broken), *outputs]), 1, "lacks pre_g2_1m")
    assert not js.exists() and not out.exists()


def test_existing_output_needs_overwrite(runner, cli, metacal, tmp_path):
    out = tmp_path / "cal.fits"
    out.write_text("keep")
    error_line(runner.invoke(cli, ["calibrate", str(metacal), "-o", str(out)]), 1, "--overwrite")
    assert out.read_text() == "keep"
    js = tmp_path / "cal.json"
    js.write_text("keep")
    result = runner.invoke(cli, ["calibrate", str(metacal), "--json", str(js)])
    error_line(result, 1, "--overwrite")
    assert js.read_text() == "keep" and result.stdout == ""
    assert_ok(runner.invoke(cli, ["calibrate", str(metacal), "-o", str(out), "--overwrite"]))
    assert catalog_info(out)[0] > 0


def test_a_real_process_reports_one_line(metacal, tmp_path):
    """As a user runs it: one 'Error:' line on stderr and exit status 1, no traceback."""
    proc = subprocess.run(
        [sys.executable, "-m", "megalut_cli", "calibrate", str(metacal), "--select", "size > 9"],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 1 and proc.stderr.strip().count("\n") == 0, proc.stderr
    assert proc.stderr.startswith("Error:") and proc.stdout == ""


def test_plot(runner, cli, metacal, tmp_path):
    """--plot draws the leakage and per-bin panels (a PNG of the expected size); a bad suffix
    is a usage error before any work, and names clashing with --json are refused."""
    from helpers import png_size

    pytest.importorskip("matplotlib")
    png = tmp_path / "cal.png"
    result = runner.invoke(cli, ["calibrate", str(metacal), "--by", "tomo", "--plot", str(png)])
    assert_ok(result)
    assert png_size(png) == (1200, 360)
    bad = runner.invoke(cli, ["calibrate", str(metacal), "--plot", str(tmp_path / "x.gif")])
    assert bad.exit_code == 2 and "unsupported figure type" in bad.output
    same = tmp_path / "same.png"
    clash = runner.invoke(
        cli, ["calibrate", str(metacal), "--json", str(same), "--plot", str(same)]
    )
    assert clash.exit_code == 2 and not same.exists()
