"""A model records its training population; predict tells it, with the recorded real-galaxy bias."""

from __future__ import annotations

import pytest
from sim_configs import write

from megalut_cli.errors import InputError
from megalut_cli.nn.model import ShearModel
from megalut_cli.nn.population import (
    REAL_BIAS_ATTR,
    describe_value,
    model_report,
    population_summary,
    record_real_bias,
    training_population,
)

RECORD = {
    "dm_g1": -0.022,
    "dm_g1_err": 0.004,
    "dm_g2": -0.023,
    "dm_g2_err": 0.005,
    "scheme": "weighted",
    "setup": "fiducial resolution",
    "command": "megalut evaluate real.fits --twin twin.fits",
}


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    from click.testing import CliRunner

    from megalut_cli.cli import main

    d = tmp_path_factory.mktemp("pop")
    cfg = write(d, replace={"n_cases = 3": "n_cases = 8"})
    runner = CliRunner()
    res = runner.invoke(
        main, ["simulate", str(cfg), "-o", str(d / "tp.fits"), "--measure", "--seed", "3"]
    )
    assert res.exit_code == 0, res.output
    res = runner.invoke(
        main,
        [
            "train-point",
            str(d / "tp.fits"),
            "-o",
            str(d / "m.h5"),
            "--members",
            "1",
            "--iterations",
            "3",
            "--hidden",
            "3",
        ],
    )
    assert res.exit_code == 0, res.output
    return d


def test_training_catalog_population(trained):
    pop = training_population(trained / "tp.fits")
    assert pop["galaxy"]["profile"] == "sersic" and pop["psf"]["sigma"] == 1.5
    assert pop["summary"] == (
        "Sersic galaxies (n grid, rad U(1.5, 3.0) px); gaussian PSF sigma 1.5; "
        "gaussian noise sigma 1.0"
    )
    prov = ShearModel.load(trained / "m.h5").provenance
    assert prov["population"]["summary"] == pop["summary"]


def test_population_summary_real_and_twin():
    gal = {"profile": "real", "real_catalog": "../x/real.fits", "twin": "sersic"}
    s = population_summary(
        {
            "galaxy": gal,
            "psf": {"type": "moffat", "fwhm": 3.0, "beta": 3.0},
            "noise": {"type": "gaussian", "sigma": 0.1},
        }
    )
    assert (
        s == "Sersic twins of real galaxies of real.fits; moffat PSF fwhm 3.0 beta 3.0; "
        "gaussian noise sigma 0.1"
    )


def test_predict_logs_population_and_recorded_bias(trained):
    from click.testing import CliRunner

    from megalut_cli.cli import main

    model = trained / "m.h5"
    lines = model_report(ShearModel.load(model))
    assert (
        lines[0].startswith("model point estimates trained on: Sersic galaxies")
        and "tp.fits" in lines[0]
    )
    assert lines[-1].startswith("no model bias on real galaxies recorded")
    record_real_bias(model, RECORD)
    loaded = ShearModel.load(model)
    assert loaded.validation[REAL_BIAS_ATTR] == RECORD
    res = CliRunner().invoke(
        main,
        [
            "predict",
            str(trained / "tp.fits"),
            "--model",
            str(model),
            "-o",
            str(trained / "s.fits"),
            "--overwrite",
        ],
    )
    assert res.exit_code == 0, res.output
    text = res.output  # the log lines (stderr; click mixes them into output)
    assert "trained on: Sersic galaxies" in text
    assert "m_real - m_twin = -2.20e-02 ± 4.0e-03 (g1), -2.30e-02 ± 5.0e-03 (g2)" in text
    with pytest.raises(InputError, match="missing dm_g2"):
        record_real_bias(model, {k: v for k, v in RECORD.items() if k != "dm_g2"})
    # a metacal model records m_real itself (no twins), and says so
    record_real_bias(model, {**RECORD, "quantity": "m_real", "dm_g1": 5e-5})
    (line,) = [x for x in model_report(ShearModel.load(model)) if "real galaxies" in x]
    assert "m_real = +5.00e-05 ± 4.0e-03 (g1)" in line and "m_twin" not in line


def test_old_model_without_population(tmp_path):
    from helpers import make_model

    make_model(tmp_path / "old.h5")
    lines = model_report(ShearModel.load(tmp_path / "old.h5"))
    assert lines[-1].startswith("no model bias on real galaxies recorded")
    assert all("trained on" not in line for line in lines)


def test_population_recorded_afterwards_from_a_config(tmp_path):
    from pathlib import Path

    from helpers import make_model

    from megalut_cli.nn.population import population_from_config, record_population

    tp = Path(__file__).resolve().parents[1] / "examples" / "fiducial" / "tp.toml"
    make_model(tmp_path / "old.h5")
    record_population(tmp_path / "old.h5", population_from_config(tp))
    lines = model_report(ShearModel.load(tmp_path / "old.h5"))
    assert any(
        line.endswith(
            "trained on: Sersic galaxies (n grid, rad U(2.0, 8.0) px); gaussian PSF sigma 2.0; "
            "gaussian noise sigma 1.0 (tp.toml)"
        )
        for line in lines
    ), lines


def test_population_of_a_weight_trained_model_and_its_parent(tmp_path):
    import shutil
    from pathlib import Path

    from megalut_cli.nn.population import population_from_config, record_population

    root = Path(__file__).resolve().parents[1]
    shutil.copyfile(root / "models" / "fiducial.h5", tmp_path / "m.h5")
    record_population(
        tmp_path / "m.h5", population_from_config(root / "models" / "fiducial-pipeline.toml")
    )
    model = ShearModel.load(tmp_path / "m.h5")
    assert model.provenance["parent"]["population"] == model.provenance["population"]
    lines = model_report(model)
    assert lines[0].startswith(
        "model weights trained on: Sersic galaxies (n grid, rad U(2.0, 8.0) px)"
    )
    assert lines[1].startswith("model point estimates trained on: Sersic galaxies")


def test_distributions_in_plain_words():
    assert describe_value({"type": "uniform", "min": 2, "max": 8}, "px") == "uniform 2 to 8 px"
    assert describe_value({"type": "grid", "values": [1, 2]}) == "one of 1, 2"
    assert describe_value({"type": "sequence", "values": [0.05, -0.05]}) == "in turn 0.05, -0.05"
