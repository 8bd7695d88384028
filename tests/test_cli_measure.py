"""`megalut measure`: help, outputs, exit codes on bad input, engines."""

from __future__ import annotations

import galsim
import numpy as np
import pytest
from helpers import invoke_fails

from megalut_cli.catalog import read_catalog, write_catalog, write_image
from megalut_cli.measure.features import FEATURE_COLUMNS

S = 32
NX, NY = 3, 2


@pytest.fixture
def data(tmp_path):
    """A 3x2 grid of noisy galaxies, its catalog (with a truth column) and a PSF image."""
    big = galsim.ImageF(NX * S, NY * S, scale=1.0)
    xs, ys = [], []
    for k in range(NX * NY):
        i, j = k % NX, k // NX
        b = galsim.BoundsI(i * S + 1, (i + 1) * S, j * S + 1, (j + 1) * S)
        galsim.Gaussian(sigma=1.5 + 0.2 * k, flux=800.0).drawImage(big[b])
        xs.append(b.true_center.x)
        ys.append(b.true_center.y)
    arr = big.array + np.random.default_rng(5).normal(0.0, 1.0, big.array.shape)
    write_image(tmp_path / "stamps.fits", arr, fmt="megalut.stamps", cards={"STAMPSZ": S})
    write_image(tmp_path / "nocard.fits", arr, fmt="megalut.stamps")
    write_catalog(
        tmp_path / "cat.fits",
        {"x": np.array(xs), "y": np.array(ys), "tru_rad": np.arange(NX * NY, dtype=float)},
        fmt="megalut.catalog",
        cards={"SEED": 12},
        history=["megalut simulate tp.toml -o cat.fits"],
    )
    psf = galsim.Gaussian(sigma=2.0).drawImage(nx=S, ny=S, scale=1.0)
    write_image(tmp_path / "psf.fits", psf.array, fmt="test")
    return tmp_path


def test_help(runner, cli):
    result = runner.invoke(cli, ["measure", "--help"])
    assert result.exit_code == 0
    for opt in (
        "--stamp-size",
        "--origin",
        "--gain",
        "--psf",
        "--nproc",
        "--scheduler",
        "--overwrite",
    ):
        assert opt in result.output
    assert "Example" in result.output


def test_measure_with_catalog(runner, cli, data):
    out = data / "f.fits"
    result = runner.invoke(
        cli,
        [
            "measure",
            str(data / "stamps.fits"),
            str(data / "cat.fits"),
            "-o",
            str(out),
            "--gain",
            "3.1",
            "--psf",
            str(data / "psf.fits"),
        ],
    )
    assert result.exit_code == 0, result.output
    t = read_catalog(out)
    assert t.colnames[:3] == ["x", "y", "tru_rad"]
    for c in FEATURE_COLUMNS + (
        "psf_adamom_g1",
        "psf_adamom_g2",
        "psf_adamom_sigma",
        "psf_adamom_rho4",
    ):
        assert c in t.colnames
    assert (t["flags"] == 0).all()
    assert np.all(np.diff(t["adamom_sigma"]) > 0)  # sizes grow with k
    assert t.meta["MLFORMAT"] == "megalut.features"
    assert t.meta["SEED"] == 12 and t.meta["GAIN"] == 3.1
    assert t.meta["HISTORY"][0] == "megalut simulate tp.toml -o cat.fits"
    assert any("measure" in h for h in t.meta["HISTORY"][1:])


def test_grid_order_and_stamp_size_option(runner, cli, data):
    result = runner.invoke(
        cli,
        ["measure", str(data / "nocard.fits"), "-o", str(data / "f.fits"), "--stamp-size", str(S)],
    )
    assert result.exit_code == 0, result.output
    t = read_catalog(data / "f.fits")
    assert len(t) == NX * NY and np.all(np.diff(t["adamom_sigma"]) > 0)


def test_parallel_engines_give_identical_results(runner, cli, data):
    args = ["measure", str(data / "stamps.fits"), str(data / "cat.fits")]
    assert runner.invoke(cli, [*args, "-o", str(data / "a.fits")]).exit_code == 0
    result = runner.invoke(cli, [*args, "-o", str(data / "b.fits"), "-j", "2"])
    assert result.exit_code == 0, result.output
    a, b = read_catalog(data / "a.fits"), read_catalog(data / "b.fits")
    for c in a.colnames:
        np.testing.assert_array_equal(np.asarray(a[c]), np.asarray(b[c]))


def test_bad_inputs(runner, cli, data):
    out = str(data / "out.fits")
    raw = (data / "stamps.fits").read_bytes()
    (data / "trunc.fits").write_bytes(raw[: len(raw) - 3000])
    invoke_fails(
        runner, cli, ["measure", str(data / "trunc.fits"), "-o", out], 1, "trunc.fits", "truncated"
    )
    (data / "junk.fits").write_text("SIMPLE = garbage\n" * 300)
    invoke_fails(
        runner, cli, ["measure", str(data / "junk.fits"), "-o", out], 1, "junk.fits", "FITS"
    )
    write_catalog(data / "noxy.fits", {"ra": np.zeros(3), "dec": np.zeros(3)}, fmt="test")
    invoke_fails(
        runner,
        cli,
        ["measure", str(data / "stamps.fits"), str(data / "noxy.fits"), "-o", out],
        1,
        "noxy.fits",
        "x, y",
    )
    invoke_fails(
        runner,
        cli,
        ["measure", str(data / "nocard.fits"), "-o", out, "--stamp-size", "40"],
        1,
        "does not divide",
    )
    invoke_fails(
        runner, cli, ["measure", str(data / "nocard.fits"), "-o", out], 2, "STAMPSZ", "--stamp-size"
    )
    invoke_fails(
        runner,
        cli,
        ["measure", str(data / "stamps.fits"), str(data / "stamps.fits"), "-o", out],
        1,
        "no table",
    )
    invoke_fails(runner, cli, ["measure", str(data / "stamps.fits"), "-o", out, "--gain", "-1"], 2)
    invoke_fails(runner, cli, ["measure", str(data / "stamps.fits"), "-o", out, "--origin", "2"], 2)
    invoke_fails(runner, cli, ["measure", str(data / "missing.fits"), "-o", out], 2)
    invoke_fails(
        runner,
        cli,
        [
            "measure",
            str(data / "stamps.fits"),
            "-o",
            out,
            "-j",
            "2",
            "--scheduler",
            "tcp://localhost:1",
        ],
        2,
    )
    assert not (data / "out.fits").exists()
    assert [p.name for p in data.iterdir() if p.name.startswith(".")] == []  # no temp files left


def test_refuses_to_overwrite(runner, cli, data):
    out = data / "f.fits"
    out.write_text("precious")
    invoke_fails(
        runner, cli, ["measure", str(data / "stamps.fits"), "-o", str(out)], 1, "--overwrite"
    )
    assert out.read_text() == "precious"
    result = runner.invoke(
        cli, ["measure", str(data / "stamps.fits"), "-o", str(out), "--overwrite"]
    )
    assert result.exit_code == 0, result.output
    assert len(read_catalog(out)) == NX * NY


def test_stamp_size_contradicting_the_card_is_refused(runner, cli, data):
    out = data / "out.fits"
    text = invoke_fails(
        runner,
        cli,
        ["measure", str(data / "stamps.fits"), "-o", str(out), "--stamp-size", "16"],
        1,
        str(data / "stamps.fits"),
        "stamp size 16 (--stamp-size)",
        "STAMPSZ = 32",
    )
    assert len(text.strip().splitlines()) == 2  # the one line, in output (stdout+stderr) and stderr
    assert not out.exists()


def test_catalog_of_another_simulation_is_refused(runner, cli, data):
    """Seed, config hash and grid shape of the catalog must match the stamp image's."""
    arr = np.zeros((NY * S, NX * S), dtype=np.float32)
    prov = {"STAMPSZ": S, "SEED": 12, "CFGSHA": "abc", "NSTAMPX": NX}
    write_image(data / "sim.fits", arr, fmt="megalut.stamps", cards=prov)
    xy = {"x": np.array([S / 2 + 0.5]), "y": np.array([S / 2 + 0.5])}
    write_catalog(
        data / "other.fits", xy, fmt="megalut.simulation", cards={**prov, "SEED": 13, "NSTAMPX": 4}
    )
    out = data / "out.fits"
    text = invoke_fails(
        runner,
        cli,
        ["measure", str(data / "sim.fits"), str(data / "other.fits"), "-o", str(out)],
        1,
        str(data / "other.fits"),
        "does not belong to",
        "SEED = 13 vs 12",
        "NSTAMPX = 4 vs 3",
    )
    assert "CFGSHA" not in text  # equal cards are not reported
    assert len(text.strip().splitlines()) == 2 and not out.exists()
    write_catalog(data / "same.fits", xy, fmt="megalut.simulation", cards=prov)
    result = runner.invoke(
        cli, ["measure", str(data / "sim.fits"), str(data / "same.fits"), "-o", str(out)]
    )
    assert result.exit_code == 0, result.output


def test_warns_when_most_stamps_are_flagged(runner, cli, data):
    """An empty image: every stamp fails; the warning gives the count and the reasons."""
    write_image(
        data / "empty.fits",
        np.zeros((NY * S, NX * S), dtype=np.float32),
        fmt="megalut.stamps",
        cards={"STAMPSZ": S},
    )
    result = runner.invoke(cli, ["measure", str(data / "empty.fits"), "-o", str(data / "f.fits")])
    assert result.exit_code == 0, result.output
    assert f"{NX * NY} of {NX * NY} stamps flagged" in result.stderr
    assert "HSM_FAILED" in result.stderr or "NEGATIVE_FLUX" in result.stderr
    ok = runner.invoke(cli, ["measure", str(data / "stamps.fits"), "-o", str(data / "g.fits")])
    assert ok.exit_code == 0 and "wrong --stamp-size" not in ok.stderr


def test_library_messages_name_arguments_the_command_line_its_flags(data, runner, cli):
    """The library names its own arguments; the subcommand maps them to its flags."""
    from megalut_cli.cli.console import flag_names
    from megalut_cli.cli.measure import command
    from megalut_cli.errors import ConfigError
    from megalut_cli.measure.measure import measure_file

    out = str(data / "out.fits")
    with pytest.raises(ConfigError, match=r"^gain must be a positive number"):
        measure_file(data / "stamps.fits", None, out, gain=-1.0)
    with pytest.raises(ConfigError, match="give stamp_size or a STAMPSZ"):
        measure_file(data / "nocard.fits", None, out)
    with pytest.raises(ConfigError, match=r"^psf_path does not apply to a star field"):
        measure_file(data / "stamps.fits", None, out, psf_path=data / "stamps.fits", stars=True)
    names = flag_names(command, psf_path="--psf")
    assert (
        names["stamp_size"] == "--stamp-size"
        and names["psf_path"] == "--psf"
        and names["output"] == "-o"
    )
    invoke_fails(
        runner,
        cli,
        ["measure", str(data / "nocard.fits"), "-o", out],
        2,
        "give --stamp-size or a STAMPSZ",
    )
    assert not (data / "out.fits").exists()


def test_moments_retry(runner, cli, tmp_path):
    """``--moments-retry``: fewer HSM failures, every other row as without it, the card."""
    from test_measure_adamom import fiducial_stamps

    from megalut_cli import flags as fl

    stamps = fiducial_stamps(400, size=S, seed=21).astype(np.float32)
    image = stamps.reshape(20, 20, S, S).transpose(0, 2, 1, 3).reshape(20 * S, 20 * S)
    write_image(tmp_path / "s.fits", image, fmt="megalut.stamps", cards={"STAMPSZ": S})
    out = {}
    for name, extra in (("plain", []), ("retry", ["--moments-retry", "0.5"])):
        args = ["measure", str(tmp_path / "s.fits"), "-o", str(tmp_path / f"{name}.fits")]
        result = runner.invoke(cli, args + extra)
        assert result.exit_code == 0, result.output
        out[name] = read_catalog(tmp_path / f"{name}.fits")
    plain, retry = out["plain"], out["retry"]
    failed = (plain["flags"] & fl.HSM_FAILED) != 0
    assert failed.sum() >= 4
    assert ((retry["flags"] & fl.HSM_FAILED) != 0).sum() < failed.sum()
    assert (retry["flags"][~failed] == plain["flags"][~failed]).all()
    np.testing.assert_array_equal(retry["adamom_g1"][~failed], plain["adamom_g1"][~failed])
    assert retry.meta["HSMRETRY"] == 0.5 and "HSMRETRY" not in plain.meta
    invoke_fails(
        runner,
        cli,
        [
            "measure",
            str(tmp_path / "s.fits"),
            "-o",
            str(tmp_path / "x.fits"),
            "--moments-retry",
            "1",
        ],
        2,
        "--moments-retry",
    )
    assert not (tmp_path / "x.fits").exists()
