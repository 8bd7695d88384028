"""`megalut draft` (issue 24): a pipeline file whose stamp size, PSF and noise come from the
user's own measured stamps, accepted by `megalut run --dry-run`."""

from __future__ import annotations

import math
from pathlib import Path

import fitsio
import galsim
import numpy as np
import pytest
from click.testing import CliRunner
from helpers import error_text, one_line
from sim_configs import write as write_sim_config

from megalut_cli.configfile import tomllib
from megalut_cli.errors import InputError

#: A non-fiducial setup, as a survey would have it: 48-px stamps, Gaussian PSF sigma 3, noise
#: sigma 3.
STAMP, PSF_SIGMA, NOISE_SIGMA = 48, 3.0, 3.0
SETUP = f"""
[structure]
n_cases = 6
n_realizations = 40
per_realization = ["galaxy"]
stamp_size = {STAMP}

[shear]
g1 = {{type = "uniform", min = -0.05, max = 0.05}}
g2 = {{type = "uniform", min = -0.05, max = 0.05}}

[galaxy]
profile = "sersic"
sersicn = {{type = "grid", min = 1.0, max = 4.0, step = 0.5}}
rad = {{type = "uniform", min = 2.0, max = 8.0}}
sb = {{type = "uniform", min = 3.0, max = 45.0}}
ellipticity = {{type = "rayleigh", mode = 0.2, min = 0.0, max = 0.6}}
angle = {{type = "uniform", min = 0.0, max = 180.0}}

[psf]
type = "gaussian"
sigma = {PSF_SIGMA}

[noise]
type = "gaussian"
sigma = {NOISE_SIGMA}
"""


def _star_field(path: Path, psf: galsim.GSObject, n: int = 4, size: int = STAMP) -> None:
    """An n x n grid of bright stars of ``psf`` (drawn with the pixel), with a little noise."""
    rng = np.random.default_rng(5)
    image = np.zeros((n * size, n * size))
    star = psf.withFlux(1e4).drawImage(nx=size, ny=size, scale=1.0).array
    for i in range(n):
        for j in range(n):
            image[i * size : (i + 1) * size, j * size : (j + 1) * size] = star + rng.normal(
                0.0, 0.05, star.shape
            )
    fitsio.write(str(path), image, clobber=True)


@pytest.fixture(scope="module")
def measured(tmp_path_factory) -> dict[str, Path]:
    """The setup simulated and measured as a user would measure their own stamps: with a PSF
    image (psf_adamom_* on every row), without one, and a star field of an elliptical Moffat."""
    from megalut_cli.cli import main

    d = tmp_path_factory.mktemp("draft")
    runner = CliRunner()
    cfg = write_sim_config(d, SETUP)
    psf = d / "psf.fits"
    fitsio.write(
        str(psf), galsim.Gaussian(sigma=PSF_SIGMA).drawImage(nx=STAMP, ny=STAMP, scale=1.0).array
    )
    _star_field(d / "moffat.fits", galsim.Moffat(beta=3.0, fwhm=6.0).shear(g1=0.04, g2=-0.02))
    for args in (
        ["simulate", str(cfg), "-o", str(d / "truth.fits"), "--stamps", str(d / "stamps.fits")],
        [
            "measure",
            str(d / "stamps.fits"),
            str(d / "truth.fits"),
            "--psf",
            str(psf),
            "-o",
            str(d / "feats.fits"),
        ],
        ["measure", str(d / "stamps.fits"), str(d / "truth.fits"), "-o", str(d / "nopsf.fits")],
        [
            "measure",
            str(d / "moffat.fits"),
            "-o",
            str(d / "stars.fits"),
            "--stars",
            "--stamp-size",
            str(STAMP),
        ],
    ):
        result = runner.invoke(main, args)
        assert result.exit_code == 0, error_text(result)
    return {name: d / f"{name}.fits" for name in ("feats", "nopsf", "stars")}


def test_draft_recovers_the_setup_and_megalut_run_accepts_it(
    runner, cli, measured, tmp_path
) -> None:
    out = tmp_path / "draft.toml"
    result = runner.invoke(cli, ["draft", str(measured["feats"]), "-o", str(out)])
    assert result.exit_code == 0, error_text(result)
    text = out.read_text()
    sim = tomllib.loads(text)["simulation"]
    assert sim["structure"]["stamp_size"] == STAMP
    assert sim["psf"] == {"type": "gaussian", "sigma": pytest.approx(PSF_SIGMA, rel=0.02)}
    assert sim["noise"]["sigma"] == pytest.approx(NOISE_SIGMA, rel=0.02)
    # every drafted value says where it comes from; the default's sets and comments are kept
    assert "stamp_size = 48  # drafted: the STAMPSZ card of" in text
    assert "median skymad of 240 rows" in text and "sqrt(s^2 - 1/12)" in text
    assert (
        "[sets.tp]" in text
        and "# TP: point-estimator training" in text
        and text.count("\nsigma = ") == 2
    )
    assert (
        "adamom_sigma" in text and "snr" in text and "adamom_flux" in text
    )  # the data's quantiles reported
    assert "wrote" in error_text(result)
    dry = runner.invoke(cli, ["run", str(out), "--dry-run", "--workdir", str(tmp_path / "wd")])
    assert dry.exit_code == 0, error_text(dry)
    assert "48x48 px" in error_text(dry)
    again = runner.invoke(
        cli, ["draft", str(measured["feats"]), "-o", "-"]
    )  # -o -: the same file on stdout
    assert again.exit_code == 0 and again.stdout == text


def test_draft_from_stars_fits_their_moffat_profile_and_ellipticity(measured) -> None:
    """Stars of a Moffat (beta 3, FWHM 6 px, g = (0.04, -0.02)): their rho4 says wings, and the
    drafted Moffat, drawn with the pixel, has their measured size and rho4."""
    from megalut_cli.catalog import read_catalog_columns
    from megalut_cli.draft import PSF, draft_setup

    features, header = read_catalog_columns(measured["nopsf"])
    stars = read_catalog_columns(measured["stars"])[0]
    draft = draft_setup(
        features, header, stars, features_name="nopsf.fits", stars_name="stars.fits"
    )
    assert draft.value(PSF, "type") == "moffat" and ("simulation.psf", "sigma") in draft.removed
    assert draft.value(PSF, "beta") == pytest.approx(3.0, rel=0.03)
    assert draft.value(PSF, "fwhm") == pytest.approx(6.0, rel=0.01)
    assert draft.value(PSF, "g1") == pytest.approx(0.04, abs=0.001)
    assert draft.value(PSF, "g2") == pytest.approx(-0.02, abs=0.001)
    assert any("wings" in n.text and n.warning for n in draft.notes)
    assert not any(
        "varies across the field" in n.text for n in draft.notes
    )  # one PSF for all stars


def _psf_columns(sigmas: np.ndarray, rho4: float = 2.0) -> dict[str, np.ndarray]:
    n = len(sigmas)
    return {
        "psf_adamom_sigma": sigmas,
        "psf_adamom_rho4": np.full(n, rho4),
        "psf_adamom_g1": np.zeros(n),
        "psf_adamom_g2": np.zeros(n),
        "skymad": np.full(n, 1.0),
        "flags": np.zeros(n, dtype=np.int32),
    }


def test_a_psf_varying_across_the_field_is_a_warning_pointing_to_varpsf() -> None:
    from megalut_cli.draft import PSF, draft_setup, render_pipeline

    rng = np.random.default_rng(2)
    varying = _psf_columns(rng.uniform(2.4, 3.6, 500))
    draft = draft_setup(varying, {"STAMPSZ": 48}, features_name="f.fits")
    warned = [n for n in draft.notes if "varies across the field" in n.text]
    assert len(warned) == 1 and warned[0].warning and "examples/varpsf" in warned[0].text
    assert draft.value(PSF, "sigma") == pytest.approx(
        math.sqrt(np.median(varying["psf_adamom_sigma"]) ** 2 - 1 / 12), rel=1e-3
    )
    assert "# WARNING: the PSF varies across the field" in render_pipeline(draft)
    steady = _psf_columns(rng.normal(3.0, 0.02, 500))  # 5-95 % spread of 2 %
    assert not any("varies" in n.text for n in draft_setup(steady, {"STAMPSZ": 48}).notes)
    flagged = _psf_columns(np.full(10, 3.0))
    flagged["flags"][:] = 64  # PSF_FAILED everywhere
    with pytest.raises(InputError, match="no usable PSF measurement"):
        draft_setup(flagged, {"STAMPSZ": 48})


def test_a_metacal_catalog_drafts_a_metacal_pipeline() -> None:
    """A catalog measured with --metacal drafts a metacal pipeline: `metacal = true` at the
    top (before any table), the metacal reference model, a note saying why; a plain one
    does not."""
    import tomllib

    from megalut_cli.draft import draft_setup, render_pipeline

    rng = np.random.default_rng(3)
    cols = _psf_columns(rng.normal(3.0, 0.02, 200))
    plain = draft_setup(cols, {"STAMPSZ": 48}, features_name="f.fits")
    assert not any("metacal" in n.text for n in plain.notes)
    assert "metacal" not in tomllib.loads(render_pipeline(plain))
    mcal = draft_setup(cols, {"STAMPSZ": 48, "MCALSTEP": 0.01}, features_name="f.fits")
    noted = [n for n in mcal.notes if "metacal mode" in n.text]
    assert len(noted) == 1 and "metacal = true" in noted[0].text
    parsed = tomllib.loads(render_pipeline(mcal))
    assert parsed["metacal"] is True and parsed["reference"]["model"] == "fiducial-metacal"


def test_the_rad_range_is_widened_to_cover_the_data_and_never_narrowed() -> None:
    """Galaxies larger than the fiducial range makes with this PSF: rad max grows until a
    Sersic n = 1 galaxy of that radius has the data's 95 % size; the lower end stays."""
    from megalut_cli.draft import GALAXY, draft_setup, galaxy_moments

    rng = np.random.default_rng(3)
    n = 400
    columns = _psf_columns(np.full(n, 2.0))
    columns.update(
        adamom_sigma=rng.uniform(4.0, 11.0, n),
        snr=rng.uniform(12.0, 30.0, n),
        adamom_flux=rng.uniform(100.0, 1000.0, n),
    )
    draft = draft_setup(columns, {"STAMPSZ": 64})
    rad = draft.value(GALAXY, "rad")
    q95 = np.percentile(columns["adamom_sigma"], 95)
    psf = {"type": "gaussian", "sigma": math.sqrt(4 - 1 / 12)}
    assert rad["min"] == 2.0 and rad["max"] > 8.0
    assert (
        galaxy_moments(rad["max"], 1.0, psf, 64)[1]
        >= q95
        > galaxy_moments(rad["max"] - 0.2, 1.0, psf, 64)[1]
    )
    with pytest.raises(KeyError):  # the data's snr lies within the simulated one: sb stays
        draft.value(GALAXY, "sb")
    small = _psf_columns(np.full(n, 2.0))
    small.update(adamom_sigma=rng.uniform(3.5, 5.0, n), snr=rng.uniform(12.0, 30.0, n))
    with pytest.raises(KeyError):  # covered already: not narrowed
        draft_setup(small, {"STAMPSZ": 64}).value(GALAXY, "rad")


@pytest.mark.parametrize(
    ("which", "extra", "expected"),
    [
        (
            "nopsf",
            [],
            "{nopsf}: no psf_adamom_sigma: measure with --psf or --psf-model, or give --stars",
        ),
        (
            "nopsf",
            ["--stars", "{nopsf}"],
            "{nopsf}: no psf_adamom_sigma: not a star catalog: measure the star field "
            "with `megalut measure STARFIELD -o STARS --stars`",
        ),
    ],
)
def test_errors_say_what_is_missing_and_how_to_get_it(
    runner, cli, measured, tmp_path, which, extra, expected
) -> None:
    names = {k: str(v) for k, v in measured.items()}
    out = tmp_path / "draft.toml"
    result = runner.invoke(
        cli, ["draft", names[which], *(a.format(**names) for a in extra), "-o", str(out)]
    )
    assert result.exit_code == 1
    assert one_line(result) == "Error: " + expected.format(**names)
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_every_missing_column_at_once_and_no_overwrite(runner, cli, measured, tmp_path) -> None:
    bare = tmp_path / "bare.fits"
    fitsio.write(str(bare), np.zeros(3, dtype=[("adamom_sigma", "f8")]))
    result = runner.invoke(cli, ["draft", str(bare), "-o", str(tmp_path / "d.toml")])
    assert result.exit_code == 1
    line = one_line(result)
    assert all(
        f"no {what}" in line
        for what in (
            "STAMPSZ card or box_size column",
            "skymad or noise_weight",
            "psf_adamom_sigma",
        )
    )
    out = tmp_path / "d.toml"
    out.write_text("mine\n")
    result = runner.invoke(cli, ["draft", str(measured["feats"]), "-o", str(out)])
    assert result.exit_code == 1 and "use --overwrite" in one_line(result)
    assert out.read_text() == "mine\n"
    result = runner.invoke(cli, ["draft", str(measured["feats"]), "-o", str(out), "--overwrite"])
    assert result.exit_code == 0 and out.read_text().startswith("# Drafted by `megalut draft`")
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "bare.fits",
        "d.toml",
    ]  # no temporary file left
