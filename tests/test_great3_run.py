"""`megalut run` on a GREAT3-layout branch (a pipeline file with a [branch] table): a tiny
branch (4x4 stamps of 48 pixels, 2 subfields) written by `simulate --great3`, read back,
trained per subfield with tiny sizes, down to the per-galaxy catalog and the submission."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import fitsio
import numpy as np
import pytest
from helpers import GREAT3_BRANCH as G3BRANCH
from helpers import assert_ok, error_line

from megalut_cli import catalog
from megalut_cli.catalog import read_catalog
from megalut_cli.errors import ConfigError
from megalut_cli.great3 import layout as L
from megalut_cli.nn.model import ShearModel
from megalut_cli.pipeline import great3_file as P

#: The 2-subfield, 4x4 branch of test_great3_branch, with GREAT3's ground stamps.
BRANCH = G3BRANCH.replace("stamp_size = 32", "stamp_size = 48\noffset = 0.5")
assert "stamp_size = 48" in BRANCH

#: Tiny training sizes: a few seconds per subfield.
PIPELINE = """
description = "tiny test branch"

[branch]
path = "{path}"
kind = "ground"

[tp]
n_cases = 20
n_realizations = 4

[tw]
n_cases = 4
n_realizations = 16

[train_point]
members = 2
iterations = 5
hidden = [3]

[train_weight]
members = 2
iterations = 5
hidden = [3]
"""


@pytest.fixture(scope="module")
def branch(tmp_path_factory) -> Path:
    """A 2-subfield branch of 4x4 stamps of 48 pixels in the GREAT3 layout, with its truth."""
    from click.testing import CliRunner

    from megalut_cli.cli import main

    d = tmp_path_factory.mktemp("g3run")
    (d / "branch.toml").write_text(BRANCH)
    r = CliRunner().invoke(
        main,
        [
            "simulate",
            str(d / "branch.toml"),
            "-o",
            str(d / "cat.fits"),
            "--great3",
            str(d / "b"),
            "--seed",
            "11",
        ],
    )
    assert_ok(r)
    return d / "b"


@pytest.fixture(scope="module")
def first_run(branch, tmp_path_factory):
    """The tiny pipeline run once, serially: (pipeline file, work folder, stdout)."""
    from click.testing import CliRunner

    from megalut_cli.cli import main

    d = tmp_path_factory.mktemp("run")
    pipe = _pipeline(d, branch)
    r = CliRunner().invoke(main, ["run", str(pipe), "--workdir", str(d / "w")])
    assert_ok(r)
    return pipe, d / "w", r.output


def _pipeline(d: Path, branch: Path, extra: str = "") -> Path:
    p = d / "pipe.toml"
    p.write_text(PIPELINE.format(path=branch) + extra)
    return p


def _copy(branch: Path, dest: Path) -> Path:
    shutil.copytree(branch, dest)
    return dest


def test_run_writes_submission_and_catalog(first_run, branch):
    _, w, out = first_run
    sub = np.loadtxt(w / P.SUBMISSION)  # what GREAT3's evaluate.py does
    assert sub.shape == (2, 3) and list(sub[:, 0]) == [0, 1]
    assert np.all(np.isfinite(sub[:, 1:])) and np.all(np.abs(sub[:, 1:]) < 1)
    shears = read_catalog(w / P.SHEARS_FILE)
    assert len(shears) == 32
    for c in (
        "subfield",
        "ID",
        "x",
        "y",
        "adamom_g1",
        "skymad",
        "flags",
        "pre_g1",
        "pre_g2",
        "pre_g1_w",
        "pre_g2_w",
    ):
        assert c in shears.colnames, c
    np.testing.assert_array_equal(shears["subfield"], L.split_ids(shears["ID"])[0])
    # the submission is the per-subfield weighted mean of the per-galaxy catalog
    s, g1, g2, _ = L.submission_from_catalog(shears, weighted=True)
    np.testing.assert_array_equal(s, sub[:, 0])
    np.testing.assert_allclose(g1, sub[:, 1], rtol=1e-12)
    np.testing.assert_allclose(g2, sub[:, 2], rtol=1e-12)
    # evaluation against the branch's truth/, printed and written
    ev = json.loads((w / P.EVALUATION).read_text())
    assert ev["great3"]["n_subfields"] == 2 and "q_c" in ev
    assert "Q_c" in out and "submission.txt" in out
    man = json.loads((w / P.MANIFEST).read_text())  # the step engine's manifest
    assert man["format"] == "megalut.run-manifest" and man["failed"] == {}
    assert set(man["steps"]) == {
        "subfield-000",
        "subfield-001",
        "shears",
        "submission",
        "evaluation",
    }
    assert man["steps"]["subfield-001"]["result"]["n_galaxies"] == 16
    assert man["steps"]["submission"]["params"] == {"subfields": [0, 1], "weighted": True}


def test_per_subfield_products(first_run, branch):
    _, w, _ = first_run
    d = w / P.SUBFIELDS_DIR / "001"
    assert sorted(p.name for p in d.iterdir()) == sorted(
        [*P.UNIT_PRODUCTS, P.UNIT_RECORD]
    )  # no tp/tw by default
    model = ShearModel.load(d / "model.h5")
    # the ellipticity shortcut: point committees trained on tru_e1/e2 estimate g1/g2, and
    # every component has the paper's four features with its own adamom_g
    assert sorted(model.point) == sorted(model.weight) == ["tru_g1", "tru_g2"]
    assert model.point["tru_g1"].training["trained_on"] == "tru_e1"
    assert model.point["tru_g1"].features == [
        "adamom_g1",
        "adamom_sigma",
        "adamom_flux",
        "adamom_rho4",
    ]
    assert model.weight["tru_g2"].features == [
        "adamom_g2",
        "adamom_sigma",
        "adamom_flux",
        "adamom_rho4",
    ]
    rec = json.loads((d / P.UNIT_RECORD).read_text())
    # the weight-training noise is the subfield's measured skymad (the branch has sigma 0.5)
    assert rec["summary"]["noise_sigma"] == pytest.approx(0.5, rel=0.1)
    stars = read_catalog(d / "stars.fits")
    assert len(stars) == 9 and (np.asarray(stars["flags"]) == 0).all()
    # distinct seeds per subfield: the two subfields' training sets differ
    assert (
        rec["params"]["sets"]["tp"]["seed"]
        != json.loads((w / P.SUBFIELDS_DIR / "000" / P.UNIT_RECORD).read_text())["params"]["sets"][
            "tp"
        ]["seed"]
    )


def test_moments_retry_branch(runner, cli, first_run, branch, tmp_path):
    """`moments_retry = 0.5`: every measurement of a subfield has the damped retry (the
    galaxies', the stars' and the kept training sets' headers say so), the subfields' keys
    hold it (absent without it), and every galaxy that GalSim's iteration settles is measured
    as without it: the retry only touches the failures."""
    _, first, _ = first_run
    pipe = tmp_path / "pipe.toml"
    pipe.write_text(
        "moments_retry = 0.5\n" + PIPELINE.format(path=branch) + "\n[output]\nkeep_sets = true\n"
    )
    assert P.load_branch_pipeline(pipe).moments_retry == 0.5
    w = tmp_path / "w"
    assert_ok(runner.invoke(cli, ["run", str(pipe), "--workdir", str(w)]))
    d = w / P.SUBFIELDS_DIR / "000"
    for name in ("features.fits", "stars.fits", "tp.fits", "tw.fits"):
        assert fitsio.read_header(str(d / name), 1)["HSMRETRY"] == 0.5, name
    record = json.loads((d / P.UNIT_RECORD).read_text())
    assert record["params"]["moments_retry"] == 0.5
    plain = json.loads((first / P.SUBFIELDS_DIR / "000" / P.UNIT_RECORD).read_text())
    assert "moments_retry" not in plain["params"]
    before = fitsio.read(str(first / P.SUBFIELDS_DIR / "000" / "features.fits"))
    after = fitsio.read(str(d / "features.fits"))
    settled = before["flags"] == 0
    assert settled.sum() >= 8
    for column in ("adamom_g1", "adamom_g2", "adamom_sigma", "adamom_flux", "adamom_rho4"):
        assert np.array_equal(before[column][settled], after[column][settled]), column


@pytest.mark.slow
def test_subfields_do_not_depend_on_workers(runner, cli, first_run, tmp_path):
    """Subfields as work units on 2 processes: the same products as in one."""
    pipe, w, _ = first_run
    assert_ok(runner.invoke(cli, ["run", str(pipe), "--workdir", str(tmp_path / "j2"), "-j", "2"]))
    assert (tmp_path / "j2" / P.SUBMISSION).read_text() == (w / P.SUBMISSION).read_text()
    a, b = read_catalog(tmp_path / "j2" / P.SHEARS_FILE), read_catalog(w / P.SHEARS_FILE)
    for c in ("pre_g1", "pre_g2", "pre_g1_w", "pre_g2_w"):
        np.testing.assert_array_equal(a[c], b[c])


def test_subfields_do_not_depend_on_the_selection(runner, cli, first_run, tmp_path):
    """A subfield's result depends on its index and the seeds only: the same run alone."""
    pipe, w, _ = first_run
    assert_ok(
        runner.invoke(
            cli, ["run", str(pipe), "--workdir", str(tmp_path / "one"), "branch.subfields=[1]"]
        )
    )
    one = np.loadtxt(tmp_path / "one" / P.SUBMISSION)
    np.testing.assert_array_equal(one, np.loadtxt(w / P.SUBMISSION)[1])
    assert not (tmp_path / "one" / P.EVALUATION).exists()  # one subfield: no fit


def _ran_at(w: Path, step: str = "subfield-000") -> tuple:
    """When ``step`` last ran (its record changes only when it runs)."""
    rec = json.loads((w / P.MANIFEST).read_text())["steps"][step]
    return rec["finished"], rec["seconds"], rec["outputs"]


def test_skip_existing_and_refusal(runner, cli, branch, tmp_path):
    pipe = _pipeline(tmp_path, branch)
    w = tmp_path / "w"
    assert_ok(runner.invoke(cli, ["run", str(pipe), "--workdir", str(w), "branch.subfields=[0]"]))
    first, ran = (w / P.SUBMISSION).read_text(), _ran_at(w)
    error_line(
        runner.invoke(cli, ["run", str(pipe), "--workdir", str(w), "branch.subfields=[0]"]),
        1,
        "exists",
        "--skip-existing",
    )
    r = runner.invoke(
        cli, ["run", str(pipe), "--workdir", str(w), "branch.subfields=[0]", "--skip-existing"]
    )
    assert_ok(r)
    assert _ran_at(w) == ran and _ran_at(w, "shears") is not None
    assert (w / P.SUBMISSION).read_text() == first
    # a product touched but unchanged is still up to date (content hashes, the step engine's rule)
    os.utime(w / P.SUBFIELDS_DIR / "000" / "shears.fits", ns=(0, 0))
    assert_ok(
        runner.invoke(
            cli, ["run", str(pipe), "--workdir", str(w), "branch.subfields=[0]", "--skip-existing"]
        )
    )
    assert _ran_at(w) == ran
    # a product changed: the subfield is redone, the same
    model = w / P.SUBFIELDS_DIR / "000" / "model.h5"
    model.write_bytes(model.read_bytes() + b"x")
    assert_ok(
        runner.invoke(
            cli, ["run", str(pipe), "--workdir", str(w), "branch.subfields=[0]", "--skip-existing"]
        )
    )
    assert _ran_at(w) != ran
    assert (w / P.SUBMISSION).read_text() == first
    # a changed training setting re-runs the subfield
    ran = _ran_at(w)
    assert_ok(
        runner.invoke(
            cli,
            [
                "run",
                str(pipe),
                "--workdir",
                str(w),
                "branch.subfields=[0]",
                "--skip-existing",
                "train_weight.iterations=6",
            ],
        )
    )
    assert _ran_at(w) != ran
    # a work folder of the previous megalut (its own manifest format): refused, one line naming
    # --overwrite
    man = w / P.MANIFEST
    man.write_text(
        json.dumps({"format": "megalut.great3-run", "format_version": "1.0", "subfields": {}})
    )
    error_line(
        runner.invoke(
            cli, ["run", str(pipe), "--workdir", str(w), "branch.subfields=[0]", "--skip-existing"]
        ),
        1,
        str(man),
        "older megalut",
        "--overwrite",
    )
    assert_ok(
        runner.invoke(
            cli, ["run", str(pipe), "--workdir", str(w), "branch.subfields=[0]", "--overwrite"]
        )
    )
    assert json.loads(man.read_text())["format"] == "megalut.run-manifest"
    assert (w / P.SUBMISSION).read_text() == first


def test_keep_going_with_a_corrupted_subfield(runner, cli, branch, tmp_path):
    b = _copy(branch, tmp_path / "bad")
    image = b / L.image_name(1)
    data, header = fitsio.read(str(image), header=True)
    data[60, 70] = np.nan
    fitsio.write(str(image), data, header=header, clobber=True)
    pipe = _pipeline(tmp_path, b)
    w = tmp_path / "w"
    r = runner.invoke(cli, ["run", str(pipe), "--workdir", str(w)])
    error_line(r, 1, "subfield 1", str(image), "NaN")
    for name in (P.SHEARS_FILE, P.SUBMISSION, P.EVALUATION):
        assert not (w / name).exists(), name
    # the engine's manifest records the subfield finished before the failure (--skip-existing
    # resumes)
    assert {"subfield-000"} == set(json.loads((w / P.MANIFEST).read_text())["steps"])
    assert not (w / P.SUBFIELDS_DIR / "001").exists()
    assert not [
        p for p in (w / P.SUBFIELDS_DIR).iterdir() if p.name.startswith(".")
    ]  # no temporary left
    w2 = tmp_path / "w2"
    r = runner.invoke(cli, ["run", str(pipe), "--workdir", str(w2), "--keep-going"])
    error_line(r, 1, "1 of 2 subfield(s) failed", "image-001-0.fits")
    sub = np.loadtxt(w2 / P.SUBMISSION, ndmin=2)
    assert sub.shape == (1, 3) and sub[0, 0] == 0
    assert len(read_catalog(w2 / P.SHEARS_FILE)) == 16
    man = json.loads((w2 / P.MANIFEST).read_text())
    assert list(man["failed"]) == ["subfield-001"] and "NaN" in man["failed"]["subfield-001"]
    # the non-strict mode flags the bad stamp and completes the subfield
    assert_ok(
        runner.invoke(
            cli, ["run", str(pipe), "--workdir", str(tmp_path / "w3"), "branch.strict=false"]
        )
    )
    shears = read_catalog(tmp_path / "w3" / P.SHEARS_FILE)
    assert np.count_nonzero(np.asarray(shears["flags"])[np.asarray(shears["subfield"]) == 1]) == 1


def _corrupt_missing(b: Path) -> str:
    (b / L.starfield_name(1)).unlink()
    return L.starfield_name(1)


def _corrupt_off_image(b: Path) -> str:
    p = b / L.galaxy_catalog_name(1)
    t = catalog.read_text_catalog(p)
    catalog.write_text_catalog(
        p,
        {"x": np.asarray(t["x"]) + 100.0, "y": np.asarray(t["y"]), "ID": np.asarray(t["ID"])},
        overwrite=True,
    )
    return p.name


def _corrupt_empty_stars(b: Path) -> str:
    p = b / L.starfield_name(1)
    data, header = fitsio.read(str(p), header=True)
    fitsio.write(str(p), np.zeros_like(data), header=header, clobber=True)
    return p.name


def _corrupt_nan_stars(b: Path) -> str:
    p = b / L.starfield_name(1)
    data, header = fitsio.read(str(p), header=True)
    data[5, 5] = np.nan
    fitsio.write(str(p), data, header=header, clobber=True)
    return p.name


def _image_with_stampsz_card(b: Path) -> str:
    """Nothing corrupted: megalut's simulated branch images carry a STAMPSZ card (48)."""
    return L.image_name(0)


def _corrupt_empty_subfield(b: Path) -> str:
    p = b / L.galaxy_catalog_name(1)
    p.write_text("# x\n# y\n# ID\n")
    return p.name


@pytest.mark.parametrize(
    "corrupt, extra, words",
    [
        (_corrupt_missing, [], ["missing"]),
        (_corrupt_off_image, [], ["fall off"]),
        (_corrupt_empty_stars, [], ["empty"]),
        (_corrupt_nan_stars, [], ["NaN"]),
        (_corrupt_empty_subfield, [], ["no rows"]),
        (_image_with_stampsz_card, ["branch.stamp_size=32"], ["stamp size 32", "STAMPSZ = 48"]),
        (_image_with_stampsz_card, ["branch.kind=space"], ["stamp size 96", "STAMPSZ = 48"]),
    ],
)
def test_bad_branch_input(runner, cli, branch, tmp_path, corrupt, extra, words):
    b = _copy(branch, tmp_path / "b")
    name = corrupt(b) if corrupt else L.galaxy_catalog_name(0)
    w = tmp_path / "w"
    r = runner.invoke(cli, ["run", str(_pipeline(tmp_path, b)), "--workdir", str(w), *extra])
    error_line(r, 1, name, *words)
    assert not (w / P.SUBMISSION).exists() and not (w / P.SHEARS_FILE).exists()


@pytest.mark.parametrize(
    "override, words",
    [
        ("branch.colour=1", ["branch.colour", "unknown key"]),
        ("branch.kind=balloon", ["branch.kind"]),
        ('branch.subfields="3-1"', ["branch.subfields"]),
        ('train_point.features=["adamom_g{i}","tru_rad"]', ["train_point.features", "tru_rad"]),
        ('train_point.targets=["tru_e1"]', ["train_point.targets"]),
        ("tw.seed=1", ["tw.seed"]),
        ("tp.simulation.galaxy.rad.max=-1", ["tp", "galaxy.rad"]),
        ("tp.n_cases=1", ["tp.n_cases"]),
        ("branch.sigma2_min=0", ["branch.sigma2_min: must be > 0"]),
        ("branch.stamp_size=2", ["branch.stamp_size: must be >= 3"]),
        ("branch.epoch=-1", ["branch.epoch: must be >= 0"]),
        ("moments_retry=1.5", ["moments_retry"]),
    ],
)
def test_bad_pipeline_settings(runner, cli, branch, tmp_path, override, words):
    r = runner.invoke(
        cli, ["run", str(_pipeline(tmp_path, branch)), "--workdir", str(tmp_path / "w"), override]
    )
    error_line(r, 2, *words)
    assert not (tmp_path / "w").exists()


def test_missing_branch_folder(runner, cli, tmp_path):
    r = runner.invoke(
        cli,
        ["run", str(_pipeline(tmp_path, tmp_path / "nowhere")), "--workdir", str(tmp_path / "w")],
    )
    error_line(
        r, 1, "pipe.toml: [branch] path", "nowhere"
    )  # the file and table as written (issue 24)


def test_branch_defaults_come_from_the_declarations(branch, tmp_path):
    """Defaults by kind (stamp size, sigma2_min) and the others are those of BRANCH_OPTIONS."""
    from megalut_cli.shear.bias import GREAT3_SIGMA2_MIN_SPACE

    pipe = P.load_branch_pipeline(_pipeline(tmp_path, branch))
    assert (pipe.kind, pipe.stamp_size, pipe.sigma2_min) == (
        "ground",
        L.STAMP_SIZES["ground"],
        P.SIGMA2_MIN["ground"],
    )
    assert pipe.epoch == P.BRANCH["epoch"].default and pipe.strict is P.BRANCH["strict"].default
    space = P.parse_branch_pipeline(
        {"branch": {"path": str(branch), "kind": "space"}}, overrides=()
    )
    assert (
        space.sigma2_min == GREAT3_SIGMA2_MIN_SPACE and space.stamp_size == L.STAMP_SIZES["space"]
    )


def test_parse_helpers(branch):
    assert P.parse_subfields("all") is None
    assert P.parse_subfields("0-3,7") == [0, 1, 2, 3, 7]
    assert P.parse_subfields([5, 2, 5]) == [2, 5]
    with pytest.raises(ConfigError):
        P.parse_subfields("a-b")
    assert P.component_features(P.FEATURE_TEMPLATES, 2) == [
        "adamom_g2",
        "adamom_sigma",
        "adamom_flux",
        "adamom_rho4",
    ]
    star = branch / L.starfield_name(0)
    for kind, size in (("ground", 48), ("space", 96)):
        for name in P.SET_NAMES:
            tpl = P.SetTemplate(name, P.default_set(name, kind, size), 1, "<test>", "default")
            if size == 48:
                cfg = P.set_config(tpl, star, None)
                assert cfg.structure.stamp_size == 48 and cfg.psf["type"] == "stamp"
            else:  # Table 3 space distributions
                assert tpl.raw["galaxy"]["rad"]["max"] == 10.0
    tp = P.default_set("tp", "ground", 48)
    assert (
        tp["noise"] == {"type": "none"}
        and "shear" not in tp
        and tp["structure"]["n_realizations"] == 10
    )
    tw = P.default_set("tw", "ground", 48)
    assert tw["structure"]["snc"] == "pairs" and tw["noise"]["sigma"]["type"] == "measured"


#: 6 subfields of 8x8 stamps, bright galaxies (within the tp fluxes) and low noise.
BRIGHT = BRANCH
for _old, _new in (
    ("n_cases = 2", "n_cases = 6"),
    ("n_realizations = 16", "n_realizations = 64"),
    ("min = 100.0, max = 200.0", "min = 60.0, max = 100.0"),
    ("sigma = 0.5", "sigma = 0.05"),
):
    assert _old in BRIGHT
    BRIGHT = BRIGHT.replace(_old, _new)


@pytest.mark.slow
def test_branch_shear_recovered(runner, cli, tmp_path):
    """A bright Sersic branch (6 subfields of 8x8 stamps in pairs, shears up to 0.05): the
    point estimates of the per-subfield training (ellipticity shortcut, star PSFs) recover
    the shears, |m| < 0.1 with an error below 0.08, |c| < 0.005, in both components.
    (Unweighted: weights from a tiny tw break the pairs' shape-noise cancellation; the
    scatter of the weighted means is 4x larger at this size.)"""
    (tmp_path / "branch.toml").write_text(BRIGHT)
    assert_ok(
        runner.invoke(
            cli,
            [
                "simulate",
                str(tmp_path / "branch.toml"),
                "-o",
                str(tmp_path / "cat.fits"),
                "--great3",
                str(tmp_path / "b"),
                "--seed",
                "2024",
            ],
        )
    )
    pipe = tmp_path / "pipe.toml"
    pipe.write_text(
        PIPELINE.format(path=tmp_path / "b")
        .replace("n_cases = 20\nn_realizations = 4", "n_cases = 300\nn_realizations = 10")
        .replace("n_cases = 4\nn_realizations = 16", "n_cases = 20\nn_realizations = 100")
        .replace(
            "members = 2\niterations = 5\nhidden = [3]",
            "members = 4\niterations = 300\nhidden = [5, 5]",
            1,
        )
        .replace(
            "members = 2\niterations = 5\nhidden = [3]",
            "members = 4\niterations = 100\nhidden = [5, 5]",
            1,
        )
    )
    assert_ok(runner.invoke(cli, ["run", str(pipe), "--workdir", str(tmp_path / "w")]))
    ev = json.loads((tmp_path / "w" / P.EVALUATION).read_text())
    for comp in ("g1", "g2"):
        f = ev["unweighted"][comp]
        assert abs(f["m"]) < 0.1 and abs(f["c"]) < 0.005 and f["m_err"] < 0.08, (comp, f)


@pytest.mark.slow
def test_metacal_branch(runner, cli, branch, tmp_path):
    """`metacal = true`: the subfield's galaxies measured with --metacal on the star field's PSF,
    the networks trained on metacal sets (a metacal model), and each subfield's submitted shear
    its response-calibrated mean: R^-1 times the mean noshear estimate of the same rows."""
    pipe = tmp_path / "pipe.toml"
    pipe.write_text(
        "metacal = true\n"
        + PIPELINE.format(path=branch).replace(
            "n_cases = 20\nn_realizations = 4", "n_cases = 8\nn_realizations = 4"
        )
    )
    w = tmp_path / "w"
    assert_ok(runner.invoke(cli, ["run", str(pipe), "--workdir", str(w)]))
    shears = read_catalog(w / P.SHEARS_FILE)
    for c in ("adamom_g1_noshear", "adamom_g1_1p", "pre_g1_noshear", "mcal_r11", "mcal_r22"):
        assert c in shears.colnames, c
    assert ShearModel.load(w / "subfields" / "000" / "model.h5").shear_mode == "metacal"
    sub = np.loadtxt(w / P.SUBMISSION)
    rows = np.asarray(shears["subfield"]) == 0
    ok = rows & (np.asarray(shears["flags_noshear"]) == 0)
    for c in ("mcal_r11", "mcal_r12", "mcal_r21", "mcal_r22", "pre_g1_noshear", "pre_g2_noshear"):
        ok &= np.isfinite(np.asarray(shears[c], dtype=float))
    w1, w2 = (np.asarray(shears[f"pre_g{i}_w_noshear"], dtype=float)[ok] for i in (1, 2))
    g = np.array(
        [
            np.average(np.asarray(shears["pre_g1_noshear"])[ok], weights=w1),
            np.average(np.asarray(shears["pre_g2_noshear"])[ok], weights=w2),
        ]
    )
    r = np.array(
        [
            [
                np.average(np.asarray(shears[f"mcal_r{i}{j}"])[ok], weights=(w1, w2)[i - 1])
                for j in (1, 2)
            ]
            for i in (1, 2)
        ]
    )
    np.testing.assert_allclose(sub[0, 1:], np.linalg.solve(r, g), rtol=1e-10)
