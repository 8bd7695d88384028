"""`megalut evaluate`: help, outputs, exit codes 0/1/2/3."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import png_size, synthetic

from megalut_cli.catalog import write_catalog


@pytest.fixture
def shears(tmp_path):
    """A prediction catalog with weights and PSF columns and a clear multiplicative bias."""
    path = tmp_path / "shears.fits"
    write_catalog(
        path,
        synthetic(seed=7, m=(0.02, 0.0), sigma=0.05, weights=True, psf=True),
        fmt="megalut.predictions",
    )
    return path


@pytest.fixture
def perfect(tmp_path):
    path = tmp_path / "perfect.fits"
    write_catalog(
        path, synthetic(seed=7, sigma=0.0, n_cases=20, n_rea=5), fmt="megalut.predictions"
    )
    return path


def test_help(runner, cli):
    result = runner.invoke(cli, ["evaluate", "--help"])
    assert result.exit_code == 0
    for word in (
        "--by",
        "--bins",
        "--select",
        "--json",
        "--plot",
        "--fail-above",
        "Example",
        "status",
    ):
        assert word in result.output


def test_table_json_and_plot(runner, cli, shears, tmp_path):
    js, png = tmp_path / "out.json", tmp_path / "out.png"
    result = runner.invoke(
        cli,
        [
            "evaluate",
            str(shears),
            "--by",
            "tru_rad,snr",
            "--bins",
            "3",
            "--json",
            str(js),
            "--plot",
            str(png),
        ],
    )
    assert result.exit_code == 0, result.output
    assert (
        "unweighted" in result.stdout
        and "plus" in result.stdout
        and "conditional biases by snr" in result.stdout
    )
    data = json.loads(js.read_text())
    for scheme in ("unweighted", "weighted"):
        assert set(data[scheme]) == {"g1", "g2", "plus", "cross"}
        for fit in data[scheme].values():
            assert set(fit) == {"m", "m_err", "c", "c_err", "n_cases", "n_rows"}
    assert abs(data["weighted"]["g1"]["m"] - 0.02) < 3 * data["weighted"]["g1"]["m_err"]
    assert len(data["conditional"]["tru_rad"]["bins"]) == 3
    assert set(data["conditional"]["snr"]["bins"][0]["weighted"]) == {"g1", "g2", "plus", "cross"}
    assert len(data["per_case"]["case"]) == 100
    w, h = png_size(png)
    assert w > 800 and h > 800


def test_by_case_average_and_expression(runner, cli, shears, tmp_path):
    js, png = tmp_path / "q.json", tmp_path / "q.png"
    result = runner.invoke(
        cli,
        [
            "evaluate",
            str(shears),
            "--by",
            "mean(snr),snr*2",
            "--bins",
            "2",
            "--select-cases",
            "mean(snr) > 0",
            "--json",
            str(js),
            "--plot",
            str(png),
        ],
    )
    assert result.exit_code == 0, result.output
    assert "conditional biases by mean(snr)" in result.stdout
    cond = json.loads(js.read_text())["conditional"]
    assert set(cond) == {"mean(snr)", "snr*2"} and len(cond["mean(snr)"]["bins"]) == 2
    assert png.stat().st_size > 0
    result = runner.invoke(cli, ["evaluate", str(shears), "--by", "mean(snr) > 3"])
    assert result.exit_code == 2 and "is a condition" in _errline(result)


def test_fail_above_exit_codes(runner, cli, shears, perfect):
    result = runner.invoke(cli, ["evaluate", str(shears), "--fail-above"])
    assert result.exit_code == 3
    assert "bias out of tolerance" in result.stderr
    assert (
        runner.invoke(cli, ["evaluate", str(shears)]).exit_code == 0
    )  # only reported without the flag
    assert runner.invoke(cli, ["evaluate", str(perfect), "--fail-above"]).exit_code == 0


def test_select_changes_rows(runner, cli, shears, tmp_path):
    js = tmp_path / "sel.json"
    result = runner.invoke(
        cli, ["evaluate", str(shears), "--select", "snr > 10 & tru_rad > 1.5", "--json", str(js)]
    )
    assert result.exit_code == 0, result.output
    data = json.loads(js.read_text())
    assert 0 < data["n_selected"] < data["n_rows"]


def test_refuses_to_overwrite(runner, cli, shears, tmp_path):
    js = tmp_path / "out.json"
    js.write_text("keep")
    result = runner.invoke(cli, ["evaluate", str(shears), "--json", str(js)])
    assert result.exit_code == 1 and "--overwrite" in result.output + result.stderr
    assert js.read_text() == "keep"
    assert (
        runner.invoke(cli, ["evaluate", str(shears), "--json", str(js), "--overwrite"]).exit_code
        == 0
    )
    assert json.loads(js.read_text())["format"] == "megalut.evaluation"


def _errline(result) -> str:
    text = (result.stderr or result.output).strip()
    assert "Traceback" not in text
    return text


@pytest.mark.parametrize(
    "mutate, code, message",
    [
        (lambda d: (d.pop("tru_g1"), d.pop("tru_g2")), 1, "evaluate needs the true shear"),
        (lambda d: d["flags"].fill(4), 1, "rows failed"),
        (lambda d: d["case"].fill(3), 1, "only one case"),
        (lambda d: (d["tru_g1"].fill(0.01), d["tru_g2"].fill(0.0)), 1, "no lever arm"),
    ],
)
def test_bad_catalogs(runner, cli, tmp_path, mutate, code, message):
    d = synthetic(seed=1, n_cases=10, n_rea=5)
    mutate(d)
    path = tmp_path / "bad.fits"
    write_catalog(path, d, fmt="megalut.predictions")
    js = tmp_path / "never.json"
    result = runner.invoke(cli, ["evaluate", str(path), "--json", str(js)])
    assert result.exit_code == code
    err = _errline(result)
    assert message in err and len(err.splitlines()) == 1
    assert not js.exists()


def test_unreadable_and_bad_options(runner, cli, shears, tmp_path):
    junk = tmp_path / "junk.fits"
    junk.write_bytes(b"not a fits file" * 10)
    result = runner.invoke(cli, ["evaluate", str(junk)])
    assert result.exit_code == 1 and "not a readable FITS file" in _errline(result)
    assert runner.invoke(cli, ["evaluate", str(tmp_path / "missing.fits")]).exit_code == 2
    result = runner.invoke(cli, ["evaluate", str(shears), "--by", "nope"])
    assert result.exit_code == 2 and "nope" in _errline(result)
    assert runner.invoke(cli, ["evaluate", str(shears), "--bins", "0"]).exit_code == 2
    result = runner.invoke(cli, ["evaluate", str(shears), "--select", "snr >"])
    assert result.exit_code == 2
    result = runner.invoke(cli, ["evaluate", str(shears), "--plot", str(tmp_path / "x.jpg")])
    assert result.exit_code == 2 and ".png" in _errline(result)  # a usage error (issue 24)


def test_nan_in_json_is_null(runner, cli, tmp_path):
    """A component without spread in its true shear is reported as null, not NaN (valid JSON)."""
    d = synthetic(seed=2, n_cases=10, n_rea=5)
    d["tru_g2"] = np.zeros_like(d["tru_g2"])
    path = tmp_path / "g1only.fits"
    write_catalog(path, d, fmt="megalut.predictions")
    js = tmp_path / "g1only.json"
    result = runner.invoke(cli, ["evaluate", str(path), "--json", str(js)])
    assert result.exit_code == 0, result.output
    data = json.loads(js.read_text())
    assert data["unweighted"]["g2"]["m"] is None and data["unweighted"]["g1"]["m"] is not None
    assert "undetermined" in result.stdout


def test_crn_catalog_gets_bootstrap_errors(runner, cli, tmp_path):
    """A common-random-number catalog (header CRN = T): bootstrap over galaxies, said in the
    table and the JSON; --errors fit overrides; the seed makes it reproducible."""
    from helpers import crn_synthetic

    path = tmp_path / "crn.fits"
    write_catalog(
        path,
        crn_synthetic(3, True, n_cases=6, n_groups=50),
        fmt="megalut.predictions",
        cards={"CRN": True, "SNC": "pairs", "NREA": 100},
    )
    js = tmp_path / "e.json"
    result = runner.invoke(
        cli, ["evaluate", str(path), "--bootstrap", "50", "--seed", "4", "--json", str(js)]
    )
    assert result.exit_code == 0, result.output
    assert "errors: bootstrap over galaxies (common-random-number set" in result.stdout
    assert "50 groups of 2 realization(s)" in result.stdout
    data = json.loads(js.read_text())
    assert data["error"] == "bootstrap-galaxies" and data["bootstrap"]["seed"] == 4
    again = runner.invoke(cli, ["evaluate", str(path), "--bootstrap", "50", "--seed", "4"])
    assert again.stdout == result.stdout
    fit = runner.invoke(cli, ["evaluate", str(path), "--errors", "fit"])
    assert fit.exit_code == 0 and "errors: from the fit" in fit.stdout


def test_bootstrap_bad_input(runner, cli, shears, tmp_path):
    # without the 'rea' column galaxies cannot be resampled: one line, exit 1
    d = synthetic(seed=1, n_cases=10, n_rea=5)
    d.pop("rea")
    path = tmp_path / "norea.fits"
    write_catalog(path, d, fmt="megalut.predictions")
    result = runner.invoke(cli, ["evaluate", str(path), "--errors", "bootstrap"])
    assert result.exit_code == 1
    text = (result.stderr or result.output).strip()
    assert "Traceback" not in text and len(text.splitlines()) == 1 and "'rea'" in text
    assert runner.invoke(cli, ["evaluate", str(shears), "--bootstrap", "3"]).exit_code == 2
    assert runner.invoke(cli, ["evaluate", str(shears), "--errors", "jackknife"]).exit_code == 2
    assert (
        runner.invoke(
            cli, ["evaluate", str(shears), "--errors", "bootstrap", "--great3-truth", str(tmp_path)]
        ).exit_code
        == 2
    )
