"""Tiny GREAT3-layout branches (4x4 stamps, 2 subfields) written by `simulate --great3`,
read back by `measure`, down to a valid submission evaluated against the truth."""

from __future__ import annotations

import json
from pathlib import Path

import fitsio
import galsim
import numpy as np
import pytest
from helpers import GREAT3_BRANCH as BRANCH
from helpers import assert_ok, error_line
from sim_configs import write

from megalut_cli import catalog
from megalut_cli.catalog import read_catalog, read_image, write_catalog, write_image
from megalut_cli.great3 import layout as L

S = 32


@pytest.fixture(scope="module")
def branch(tmp_path_factory):
    """A 2-subfield, 4x4 branch with its -o catalog (features measured while drawing)."""
    from click.testing import CliRunner

    from megalut_cli.cli import main

    d = tmp_path_factory.mktemp("branch")
    cfg = write(d, BRANCH, "branch.toml")
    r = CliRunner().invoke(
        main,
        [
            "simulate",
            str(cfg),
            "-o",
            str(d / "cat.fits"),
            "--great3",
            str(d / "b"),
            "--measure",
            "--seed",
            "11",
        ],
    )
    assert_ok(r)
    return d


def test_branch_files_and_truth(branch):
    b = branch / "b"
    for s in (0, 1):
        for name in (
            L.image_name(s),
            L.galaxy_catalog_name(s, "txt"),
            L.galaxy_catalog_name(s, "fits"),
            L.starfield_name(s),
            L.star_catalog_name(s, "txt"),
            "truth/" + L.shear_params_name(s),
            "truth/" + L.starshape_name(s, 0, "yaml"),
        ):
            assert (b / name).is_file(), name
    assert not list(branch.glob(".b.*"))  # no temporary folder left
    img, hdr = read_image(b / L.image_name(1))
    assert img.shape == (4 * S, 4 * S) and hdr["STAMPSZ"] == S and hdr["SUBFIELD"] == 1
    cat = L.read_galaxy_catalog(b / L.galaxy_catalog_name(1, "txt"))
    np.testing.assert_array_equal(cat["x"][:5], [15, 47, 79, 111, 15])  # (xmin + xmax) // 2
    np.testing.assert_array_equal(
        cat["ID"][:5], [1_000_000, 1_001_000, 1_002_000, 1_003_000, 1_000_001]
    )
    t = read_catalog(branch / "cat.fits")
    assert t.colnames[:6] == ["case", "rea", "subfield", "ID", "x", "y"]
    assert t.meta["LAYOUT"] == "great3"
    np.testing.assert_array_equal(t["ID"][16:], cat["ID"])
    np.testing.assert_allclose(t["x"][16:], cat["x"] + 1.5)  # 1-based true centres
    truth = L.read_truth(b / "truth")
    for s in (0, 1):
        rows = t[t["subfield"] == s]
        assert np.all(rows["tru_g1"] == truth["g1"][s]) and np.all(rows["tru_g2"] == truth["g2"][s])
        # 90-degree pairs: intrinsic ellipticities cancel pair by pair
        np.testing.assert_allclose(rows["tru_e1"][0::2], -rows["tru_e1"][1::2], atol=1e-12)
        # the PSF frame of the truth follows the subfield's PSF
        ang = np.arctan2(truth["psf_g2"][s], truth["psf_g1"][s])
        assert ang == pytest.approx(
            np.arctan2(rows["tru_psf_g2"][0], rows["tru_psf_g1"][0]), abs=0.05
        )


def test_stamp_pixels_are_the_subfield_images(branch):
    """Stamp k of subfield s: grid column k mod 4, row k div 4 of image-SSS-0.fits; the
    features of the -o catalog are those of the stamps cut at the catalog centres."""
    from megalut_cli.measure.features import measure_stamps

    img, _ = read_image(branch / "b" / L.image_name(0))
    stamps = img.reshape(4, S, 4, S).transpose(0, 2, 1, 3).reshape(16, S, S)
    t = read_catalog(branch / "cat.fits")[:16]
    f = measure_stamps(stamps.astype(np.float64))
    np.testing.assert_allclose(t["adamom_g1"], f["adamom_g1"], rtol=1e-12)
    np.testing.assert_allclose(t["adamom_x"] - t["x"], f["adamom_x"] - (S + 1) / 2, atol=1e-9)


def test_starfield_lower_left_star_is_centred(branch):
    stars = L.read_starfield(branch / "b" / L.starfield_name(0), S)
    assert stars.shape == (9, S, S)
    np.testing.assert_allclose(stars.sum(axis=(1, 2)), 1.0, atol=2e-3)  # flux-1 PSF
    res = galsim.hsm.FindAdaptiveMom(galsim.ImageD(stars[0]))
    assert res.moments_centroid.x == pytest.approx((S + 1) / 2, abs=1e-4)
    assert res.moments_centroid.y == pytest.approx((S + 1) / 2, abs=1e-4)
    truth = L.read_truth(branch / "b" / "truth")
    assert truth["psf_g1"][0] == pytest.approx(res.observed_shape.g1, abs=1e-6)
    offs = [galsim.hsm.FindAdaptiveMom(galsim.ImageD(s)).moments_centroid for s in stars[1:]]
    assert max(abs(o.x - (S + 1) / 2) for o in offs) > 0.05  # the others are offset
    assert max(max(abs(o.x - (S + 1) / 2), abs(o.y - (S + 1) / 2)) for o in offs) <= 1.05


@pytest.mark.parametrize("catalog", ["txt", "fits"])
def test_measure_reads_subfields(runner, cli, branch, tmp_path, catalog):
    b = branch / "b"
    out = tmp_path / "f.fits"
    assert_ok(
        runner.invoke(
            cli,
            [
                "measure",
                str(b / L.image_name(1)),
                str(b / L.galaxy_catalog_name(1, catalog)),
                "-o",
                str(out),
                "--origin",
                "0",
                "--stamp-size",
                str(S),
                "--psf",
                str(b / L.starfield_name(1)),
            ],
        )
    )
    f = read_catalog(out)
    ref = read_catalog(branch / "cat.fits")[16:]
    np.testing.assert_array_equal(f["ID"], ref["ID"])
    for c in ("adamom_g1", "adamom_g2", "adamom_sigma", "adamom_flux", "adamom_x", "skymad", "snr"):
        np.testing.assert_allclose(f[c], ref[c], rtol=1e-12, err_msg=c)
    assert f.meta["XYORIGIN"] == 0
    # the PSF features are those of the lower-left star, measured on its own
    stars = tmp_path / "stars.fits"
    assert_ok(
        runner.invoke(
            cli, ["measure", str(b / L.starfield_name(1)), "-o", str(stars), "--stamp-size", str(S)]
        )
    )
    st = read_catalog(stars)
    assert len(st) == 9 and st.meta["MLFORMAT"] == "megalut.stars" and (st["flags"] == 0).all()
    for c in ("psf_adamom_g1", "psf_adamom_g2", "psf_adamom_sigma", "psf_adamom_rho4"):
        assert np.all(f[c] == st[c][0]), c
    np.testing.assert_allclose(
        [st["psf_adamom_x"][0], st["psf_adamom_y"][0]], (S + 1) / 2, atol=1e-4
    )
    # a square star field without any stamp size is GREAT3's 3x3 grid
    assert_ok(
        runner.invoke(
            cli, ["measure", str(b / L.starfield_name(1)), "-o", str(tmp_path / "s2.fits")]
        )
    )
    np.testing.assert_array_equal(
        read_catalog(tmp_path / "s2.fits")["psf_adamom_sigma"], st["psf_adamom_sigma"]
    )


def test_measure_bad_subfields(runner, cli, branch, tmp_path):
    b = branch / "b"
    img = str(b / L.image_name(0))
    out = str(tmp_path / "f.fits")
    # a --stamp-size that contradicts the image's STAMPSZ card
    error_line(
        runner.invoke(
            cli,
            [
                "measure",
                img,
                str(b / L.galaxy_catalog_name(0)),
                "-o",
                out,
                "--origin",
                "0",
                "--stamp-size",
                "64",
            ],
        ),
        1,
        "image-000-0.fits",
        "STAMPSZ = 32",
    )
    # stamp size not matching the catalog grid, on an image without the card (64 divides the
    # 128-pixel image)
    pixels, _ = read_image(img)
    nocard = tmp_path / "image-nocard.fits"
    write_image(nocard, pixels, fmt="test")
    error_line(
        runner.invoke(
            cli,
            [
                "measure",
                str(nocard),
                str(b / L.galaxy_catalog_name(0)),
                "-o",
                out,
                "--origin",
                "0",
                "--stamp-size",
                "64",
            ],
        ),
        1,
        "galaxy_catalog-000.txt",
        "stamp size 64",
    )
    # centres off the image: all of them
    far = tmp_path / "far.txt"
    catalog.write_text_catalog(
        far, {"x": np.array([1000.0, 2000.0]), "y": np.array([15.0, 15.0]), "ID": np.array([0, 1])}
    )
    error_line(
        runner.invoke(
            cli, ["measure", img, str(far), "-o", out, "--origin", "0", "--stamp-size", str(S)]
        ),
        1,
        "far.txt",
        "no stamp centre falls on",
    )
    # a broken text catalog
    bad = tmp_path / "bad.txt"
    bad.write_text("# x\n# y\n15 15\n47\n")
    error_line(
        runner.invoke(
            cli, ["measure", img, str(bad), "-o", out, "--origin", "0", "--stamp-size", str(S)]
        ),
        1,
        "bad.txt",
        "line 4",
    )
    # a star field without stars, and one with NaN pixels
    empty = tmp_path / "starfield_image-009-0.fits"
    write_image(empty, np.zeros((3 * S, 3 * S)), fmt="test")
    error_line(
        runner.invoke(cli, ["measure", str(empty), "-o", out, "--stamp-size", str(S)]),
        1,
        "starfield_image-009-0.fits",
        "no star",
    )
    error_line(
        runner.invoke(
            cli,
            [
                "measure",
                img,
                str(b / L.galaxy_catalog_name(0)),
                "-o",
                out,
                "--origin",
                "0",
                "--psf",
                str(empty),
            ],
        ),
        1,
        "starfield_image-009-0.fits",
        "empty",
    )
    stars, _ = read_image(b / L.starfield_name(0))
    stars[3, 3] = np.nan
    nan = tmp_path / "nanstars.fits"
    write_image(nan, stars, fmt="test")
    error_line(
        runner.invoke(
            cli,
            [
                "measure",
                img,
                str(b / L.galaxy_catalog_name(0)),
                "-o",
                out,
                "--origin",
                "0",
                "--psf",
                str(nan),
            ],
        ),
        1,
        "nanstars.fits",
        "NaN",
    )
    assert not Path(out).exists()
    # NaN pixels in a galaxy stamp: that stamp is flagged, the others measured
    gal, _ = read_image(b / L.image_name(0))
    gal[S + 3, 3] = np.nan  # stamp (column 0, row 1) = galaxy 4
    nanimg = tmp_path / "image-000-0.fits"
    write_image(nanimg, gal, fmt="test")
    assert_ok(
        runner.invoke(
            cli,
            [
                "measure",
                str(nanimg),
                str(b / L.galaxy_catalog_name(0)),
                "-o",
                out,
                "--origin",
                "0",
                "--stamp-size",
                str(S),
            ],
        )
    )
    f = read_catalog(out)
    assert (
        f["flags"][4] != 0 and np.isnan(f["adamom_g1"][4]) and (np.delete(f["flags"], 4) == 0).all()
    )


def test_simulate_great3_errors(runner, cli, branch, tmp_path):
    cfg = str(write(tmp_path, BRANCH, "b.toml"))
    out = str(tmp_path / "c.fits")
    error_line(
        runner.invoke(cli, ["simulate", cfg, "-o", out, "--great3", str(branch / "b")]),
        1,
        "not empty",
        "--overwrite",
    )
    error_line(
        runner.invoke(
            cli,
            [
                "simulate",
                cfg,
                "-o",
                out,
                "--great3",
                str(tmp_path / "x"),
                "--stamps",
                str(tmp_path / "s.fits"),
            ],
        ),
        2,
        "--stamps",
    )
    error_line(
        runner.invoke(
            cli,
            ["simulate", cfg, "-o", out, "--great3", str(tmp_path / "x"), "--n-realizations", "12"],
        ),
        2,
        "structure.n_x",
    )
    error_line(
        runner.invoke(
            cli,
            [
                "simulate",
                cfg,
                "-o",
                out,
                "--great3",
                str(tmp_path / "x"),
                "structure.per_realization=['galaxy', 'shear']",
            ],
        ),
        2,
        "one shear per subfield",
    )
    error_line(
        runner.invoke(
            cli, ["simulate", cfg, "-o", out, "--great3", str(tmp_path / "x"), "structure.n_x=5"]
        ),
        2,
        "does not divide",
    )
    assert not (tmp_path / "x").exists() and not Path(out).exists()


def test_simulate_great3_is_reproducible_with_workers(runner, cli, branch, tmp_path):
    cfg = str(write(tmp_path, BRANCH, "b.toml"))
    assert_ok(
        runner.invoke(
            cli,
            [
                "simulate",
                cfg,
                "-o",
                str(tmp_path / "c.fits"),
                "--great3",
                str(tmp_path / "b"),
                "--seed",
                "11",
                "-j",
                "2",
                "structure.n_x=8",
            ],
        )
    )
    a, _ = read_image(branch / "b" / L.image_name(1))
    b, hdr = read_image(tmp_path / "b" / L.image_name(1))
    assert b.shape == (2 * S, 8 * S) and hdr["NSTAMPX"] == 8
    # the same stamps (same seed), laid out on an 8x2 grid instead of 4x4
    sa = a.reshape(4, S, 4, S).transpose(0, 2, 1, 3).reshape(16, S, S)
    sb = b.reshape(2, S, 8, S).transpose(0, 2, 1, 3).reshape(16, S, S)
    np.testing.assert_array_equal(sa, sb)
    np.testing.assert_array_equal(
        read_image(branch / "b" / L.starfield_name(0))[0],
        read_image(tmp_path / "b" / L.starfield_name(0))[0],
    )
    with fitsio.FITS(str(tmp_path / "c.fits")) as f:
        assert json.loads(f["CONFIG"].read()["config_json"][0])["structure"]["n_x"] == 8


def test_measure_predict_submit_evaluate(runner, cli, branch, tmp_path):
    """End to end: measure both subfields, train a tiny model on Sersic simulations drawn
    with a star of the branch, predict, average per subfield, write and evaluate the submission."""
    b = branch / "b"
    feats = []
    for s in (0, 1):
        f = tmp_path / f"f{s}.fits"
        assert_ok(
            runner.invoke(
                cli,
                [
                    "measure",
                    str(b / L.image_name(s)),
                    str(b / L.galaxy_catalog_name(s)),
                    "-o",
                    str(f),
                    "--origin",
                    "0",
                    "--stamp-size",
                    str(S),
                ],
            )
        )
        feats.append(read_catalog(f))
    tp = write(
        tmp_path,
        BRANCH.replace("stamp_size = 32", "stamp_size = 32\noffset = 0.5")
        .replace('per_realization = ["galaxy"]', 'per_realization = ["angle"]')
        .replace('snc = "pairs"', 'snc = "ring"')
        .replace(
            '[psf]\ntype = "moffat"\nbeta = 3.0\nfwhm = {type = "uniform", min = 2.5, max = 3.5}\n'
            'g1 = {type = "uniform", min = -0.05, max = 0.05}\n'
            'g2 = {type = "uniform", min = -0.05, max = 0.05}',
            f'[psf]\ntype = "stamp"\npath = "{b / L.starfield_name(0)}"\nstamp_size = {S}\n'
            'index = "random"',
        ),
        "tp.toml",
    )
    assert_ok(
        runner.invoke(
            cli,
            [
                "simulate",
                str(tp),
                "-o",
                str(tmp_path / "tp.fits"),
                "--measure",
                "--n-cases",
                "24",
                "--n-realizations",
                "8",
                "--seed",
                "5",
            ],
        )
    )
    tpc = read_catalog(tmp_path / "tp.fits")
    assert len(np.unique(tpc["tru_psf_g1"])) > 1  # a random star of the field per case
    assert_ok(
        runner.invoke(
            cli,
            [
                "train-point",
                str(tmp_path / "tp.fits"),
                "-o",
                str(tmp_path / "m.h5"),
                "--members",
                "2",
                "--iterations",
                "5",
                "--hidden",
                "3",
                "--features",
                "adamom_g1,adamom_g2,adamom_sigma,adamom_flux",
            ],
        )
    )
    write_catalog(
        tmp_path / "all.fits",
        {c: np.concatenate([np.asarray(f[c]) for f in feats]) for c in feats[0].colnames},
        fmt="megalut.features",
    )
    assert_ok(
        runner.invoke(
            cli,
            [
                "predict",
                str(tmp_path / "all.fits"),
                "--model",
                str(tmp_path / "m.h5"),
                "-o",
                str(tmp_path / "shears.fits"),
            ],
        )
    )
    shears = read_catalog(tmp_path / "shears.fits")
    s, g1, g2, n = L.submission_from_catalog(shears)
    np.testing.assert_array_equal(s, [0, 1])
    assert (n >= 14).all()
    sub = tmp_path / "submission.txt"
    L.write_submission(sub, s, g1, g2)
    data = np.loadtxt(sub)
    assert data.shape == (2, 3) and list(data[:, 0]) == [0, 1]
    np.testing.assert_allclose(data[:, 1], g1, rtol=1e-15)
    out = runner.invoke(
        cli,
        [
            "evaluate",
            str(sub),
            "--great3-truth",
            str(b / "truth"),
            "--json",
            str(tmp_path / "e.json"),
        ],
    )
    assert_ok(out)
    assert "plus" in out.output and "Q_c" in out.output
    res = json.loads((tmp_path / "e.json").read_text())
    assert res["great3"]["n_subfields"] == 2 and res["unweighted"]["g1"]["n_cases"] == 2
    truth = L.read_truth(b / "truth")
    # with two subfields the line goes through both points: m, c reproduce the submission exactly
    m, c = res["unweighted"]["g1"]["m"], res["unweighted"]["g1"]["c"]
    np.testing.assert_allclose((1 + m) * truth["g1"] + c, g1, atol=1e-12)
    # the per-galaxy catalog gives the same per-subfield averages
    res2 = json.loads(
        _json_of(runner, cli, tmp_path / "shears.fits", b / "truth", tmp_path / "e2.json")
    )
    assert res2["unweighted"]["g1"]["m"] == pytest.approx(m, abs=1e-12)


def _json_of(runner, cli, shears, truth, path):
    assert_ok(
        runner.invoke(
            cli, ["evaluate", str(shears), "--great3-truth", str(truth), "--json", str(path)]
        )
    )
    return Path(path).read_text()
