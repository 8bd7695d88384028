"""``megalut measure CELLS --metadetect`` (``measure/cells.py``): detection on each metacal
version of whole cells, the detection count against the truth, independent detections per
version, the shear response of the detections against metacal on stamps, the output
contract, determinism and bad input."""

from __future__ import annotations

import fitsio
import galsim
import numpy as np
import pytest
from helpers import invoke_fails
from sim_configs import write

from megalut_cli.catalog import read_catalog
from megalut_cli.measure.cell_detect import CellNoise, cut_around, detect, metadetect_cell
from megalut_cli.measure.cells import read_cell
from megalut_cli.measure.features import effective_area
from megalut_cli.measure.measurer import MeasureSettings, MetacalSettings
from megalut_cli.measure.meds import write_meds
from megalut_cli.measure.metacal import metacal_features
from megalut_cli.measure.metacal_defaults import TYPES
from megalut_cli.measure.source_registry import DetectSettings

#: Round exponential galaxies (half-light radius 2 px), a round Gaussian PSF (FWHM 3.6 px),
#: sparse enough that none overlap, almost no noise; paired at g1 = +-0.02.
CELLS = """
[structure]
stamp_size = 48

[shear]
g1 = 0.02
g2 = 0.0

[galaxy]
profile = "sersic"
sersicn = 1.0
rad = 2.0
flux = 400.0
ellipticity = 0.0

[psf]
type = "gaussian"
fwhm = 3.6

[noise]
type = "gaussian"
sigma = {sigma}

[instrument]
pixel_scale = 0.25

[scene]
density = 14
size = 160
n_fields = 6
pairs = true
border = 24
"""

STEP = 0.01


def scenes(runner, cli, tmp_path, sigma: float = 0.01, name: str = "scenes") -> tuple:
    """A cells file and its truth (``simulate --scene --pairs``)."""
    config = write(tmp_path, CELLS, replace={"{sigma}": str(sigma)})
    cells, truth = tmp_path / f"{name}.fits", tmp_path / f"{name}_truth.fits"
    args = ["simulate", str(config), "-o", str(truth), "--scene", str(cells), "--pairs"]
    result = runner.invoke(cli, [*args, "--seed", "3", "-j", "1"])
    assert result.exit_code == 0, result.output
    return cells, read_catalog(truth)


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    """A nearly noiseless cells file, its truth and its metadetect catalog."""
    from click.testing import CliRunner

    from megalut_cli.cli import main

    tmp_path = tmp_path_factory.mktemp("mdet")
    runner = CliRunner()
    cells, truth = scenes(runner, main, tmp_path)
    out = tmp_path / "det.fits"
    result = runner.invoke(main, ["measure", str(cells), "--metadetect", "-o", str(out), "-j", "1"])
    assert result.exit_code == 0, result.output
    return cells, truth, read_catalog(out), fitsio.read_header(str(out), 1)


def min_separation(truth, image: int) -> float:
    x = np.asarray(truth["x"][truth["image"] == image])
    y = np.asarray(truth["y"][truth["image"] == image])
    d = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :]) + np.eye(len(x)) * 1e9
    return float(d.min()) if len(x) > 1 else np.inf


def test_the_detections_of_isolated_galaxies_are_the_truth(measured):
    from megalut_cli import flags as fl

    _, truth, det, _ = measured
    ns = det[det["mdet_step"] == "noshear"]
    isolated = [i for i in np.unique(truth["image"]) if min_separation(truth, i) > 20]
    assert len(isolated) >= 4 and len(truth[np.isin(truth["image"], isolated)]) >= 12
    for image in isolated:
        t = truth[truth["image"] == image]
        d = ns[ns["image"] == image]
        assert len(d) == len(t) > 0
        dist = np.hypot(
            np.asarray(d["x"])[:, None] - np.asarray(t["x"])[None, :],
            np.asarray(d["y"])[:, None] - np.asarray(t["y"])[None, :],
        )
        assert dist.min(axis=1).max() < 0.5  # each detection is a galaxy, within half a pixel
        assert dist.min(axis=0).max() < 0.5  # each galaxy is found
    alone = np.isin(ns["image"], isolated)
    assert (ns["flags"][alone] == 0).all() and ns["inner"].all()
    # a closer pair (7.6 px) is detected twice, but both moments take in the pair's light:
    # one row keeps it, the other is flagged DUPLICATE
    assert np.all((ns["flags"][~alone] & ~fl.DUPLICATE) == 0)
    assert len(ns) <= len(truth)  # blended neighbours may be one detection, never more


def test_each_version_is_detected_on_its_own(measured):
    _, truth, det, _ = measured
    counts = [int((det["mdet_step"] == kind).sum()) for kind in TYPES]
    assert min(counts) > 0 and len(set(counts)) == 1  # the same galaxies, found in each
    ns, p1 = det[det["mdet_step"] == "noshear"], det[det["mdet_step"] == "1p"]
    # the 1p image is sheared about the cell's centre: its objects move there (not forced
    # photometry: each version's centroid is its own) ...
    dx = np.asarray(p1["adamom_x"]) - np.asarray(ns["adamom_x"])
    centre = (160 + 1) / 2.0
    expected = STEP * (np.asarray(ns["x"]) - centre)  # x' = (1 + g1) x about the centre, roughly
    measured = (np.asarray(ns["flags"]) == 0) & (np.asarray(p1["flags"]) == 0)
    assert np.abs(dx[measured]).max() > 0.3
    assert np.corrcoef(dx[measured], expected[measured])[0, 1] > 0.95
    # ... and x, y are its detections taken back to the unsheared cell: the same place
    back = np.hypot(np.asarray(p1["x"]) - ns["x"], np.asarray(p1["y"]) - ns["y"])
    assert np.median(back) < 0.02 and back.max() < 0.5  # blends: a barycentre moves a little


def test_the_response_of_the_detections_is_metacal_s(measured):
    cells, truth, all_rows, header = measured
    isolated = [i for i in np.unique(truth["image"]) if min_separation(truth, i) > 20]
    det = all_rows[np.isin(all_rows["image"], isolated)]
    g1 = {k: np.mean(det["adamom_g1"][det["mdet_step"] == k]) for k in TYPES}
    g2 = {k: np.mean(det["adamom_g2"][det["mdet_step"] == k]) for k in TYPES}
    assert g1["1p"] > g1["noshear"] > g1["1m"]
    assert g2["2p"] > g2["noshear"] > g2["2m"]
    r11 = (g1["1p"] - g1["1m"]) / (2 * STEP)
    r22 = (g2["2p"] - g2["2m"]) / (2 * STEP)
    # metacal on stamps cut at the true positions of the same galaxies, without fixnoise
    stamps, psfs = [], []
    for image in isolated:
        cell = read_cell(str(cells), int(image))
        t = truth[truth["image"] == image]
        cut, _, _, _ = cut_around(
            cell["image"], cell["bad"], np.asarray(t["x"]) - 1, np.asarray(t["y"]) - 1, 48
        )
        stamps.append(cut)
        psfs += [cell["psf"]] * len(t)
    stack = np.concatenate(stamps)
    feats = metacal_features(stack, np.array(psfs)[:1], STEP, psf_index=np.zeros(len(stack), int))
    r11_stamps = np.mean(feats["adamom_g1_1p"] - feats["adamom_g1_1m"]) / (2 * STEP)
    assert r11 > 0.2 and r22 > 0.2
    assert r11 == pytest.approx(r11_stamps, rel=0.05)
    assert r22 == pytest.approx(r11_stamps, rel=0.05)
    # the shear of the scenes is seen: +g and -g images differ by about 2 g R
    both = [f for f in np.unique(det["field"]) if (det["field"] == f).sum() and 2 * f in isolated]
    both = [f for f in both if 2 * f + 1 in isolated]
    noshear = (det["mdet_step"] == "noshear") & np.isin(det["field"], both)
    plus, minus = noshear & (det["pair_sign"] == 1), noshear & (det["pair_sign"] == -1)
    assert plus.sum() == minus.sum() > 4
    g = (np.mean(det["adamom_g1"][plus]) - np.mean(det["adamom_g1"][minus])) / 2 / r11
    assert g == pytest.approx(0.02, rel=0.05)
    assert header["MDETSTEP"] == STEP and "MCALSTEP" not in header


def test_the_catalog_contract(measured):
    _, _, det, header = measured
    names = list(det.colnames)
    head = ["mdet_step", "image", "field", "pair_sign", "tru_g1", "tru_g2", "x", "y", "inner"]
    assert names[:9] == head
    for c in (
        "adamom_flux",
        "adamom_g1",
        "adamom_g2",
        "adamom_sigma",
        "adamom_rho4",
        "skymad",
        "snr",
        "psf_adamom_g1",
        "psf_adamom_g2",
        "psf_adamom_sigma",
        "psf_adamom_rho4",
        "flags",
    ):
        assert c in names
    assert set(np.unique(det["mdet_step"])) == set(TYPES)
    assert header["MLFORMAT"] == "megalut.metadetect"
    for card in ("DETTHRSH", "DETMINAR", "DBNTHRSH", "DBCONT", "MCALSEED", "STAMPSZ"):
        assert card in header
    assert header["DBCLEAN"] is True  # sep's cleaning, its default
    # the target PSF: round, one size for every row
    assert np.abs(det["psf_adamom_g1"]).max() < 1e-6
    assert np.ptp(det["psf_adamom_sigma"]) == 0
    assert set(np.unique(det["field"])) == set(range(6))


def test_noise_detection_threshold_and_library_call(tmp_path):
    """A cell of pure noise: no detection at 5 sigma, many at 1 sigma (the noise of the
    versions is propagated from the weight map's); the library call takes arrays."""
    rng = np.random.default_rng(1)
    image = rng.normal(0.0, 1.0, (128, 128))
    import galsim

    psf = galsim.Gaussian(fwhm=3.6).drawImage(nx=33, ny=33, scale=1.0).array
    settings = MeasureSettings(metacal=MetacalSettings(STEP, 4))
    counts = []
    for thresh in (5.0, 1.0):
        out = metadetect_cell(
            image, psf, CellNoise(1.0, 7), settings, DetectSettings(thresh, 4, 32, 0.005)
        )
        counts.append(len(out["x"]))
    assert counts[0] == 0 and counts[1] > 100  # five versions
    found = detect(np.zeros((32, 32)), 1.0, DetectSettings(5.0, 4, 32, 0.005))
    assert len(found.x) == len(found.y) == 0


def test_no_clean_reaches_sep(monkeypatch, runner, cli, tmp_path):
    """``--no-clean``: sep.extract is called with clean=False (True by default), and the
    catalog says so (DBCLEAN)."""
    import sep

    calls = []
    extract = sep.extract

    def spy(*args, **kwargs):
        calls.append(kwargs["clean"])
        return extract(*args, **kwargs)

    monkeypatch.setattr(sep, "extract", spy)
    image = np.zeros((32, 32))
    detect(image, 1.0, DetectSettings(5.0, 4, 32, 0.005))
    detect(image, 1.0, DetectSettings(5.0, 4, 32, 0.005, clean=False))
    assert calls == [True, False]
    cells, _ = scenes(runner, cli, tmp_path, sigma=1.0)
    out = tmp_path / "noclean.fits"
    result = runner.invoke(
        cli, ["measure", str(cells), "--metadetect", "--no-clean", "-j", "1", "-o", str(out)]
    )
    assert result.exit_code == 0, result.output
    assert fitsio.read_header(str(out), 1)["DBCLEAN"] is False
    assert calls[2:] and not any(calls[2:])


def test_the_same_seed_the_same_rows_and_workers_agree(runner, cli, tmp_path):
    cells, _ = scenes(runner, cli, tmp_path, sigma=1.0)
    outs = []
    for name, extra in (("a", ["-j", "1"]), ("b", ["-j", "2"]), ("c", ["--seed", "5"])):
        out = tmp_path / f"{name}.fits"
        result = runner.invoke(cli, ["measure", str(cells), "--metadetect", "-o", str(out), *extra])
        assert result.exit_code == 0, result.output
        outs.append(fitsio.read(str(out)))
    assert outs[0].dtype == outs[1].dtype
    for c in outs[0].dtype.names:  # flagged rows hold NaN features in both
        assert np.array_equal(outs[0][c], outs[1][c], equal_nan=outs[0][c].dtype.kind == "f"), c
    assert len(outs[2]) != len(outs[0]) or not np.array_equal(
        outs[2]["adamom_g1"], outs[0]["adamom_g1"], equal_nan=True
    )


def test_a_scene_inner_border_marks_the_edge_rows(runner, cli, tmp_path):
    """``scene.inner_border`` writes ``INNERBRD`` into the cells file: the detections whose
    (unsheared) position lies that close to an edge are ``inner = 0``, the others 1."""
    config = write(tmp_path, CELLS, replace={"{sigma}": "0.01", "border = 24": "border = 4"})
    config.write_text(config.read_text() + "inner_border = 30\n")
    cells, truth = tmp_path / "s.fits", tmp_path / "t.fits"
    args = ["simulate", str(config), "-o", str(truth), "--scene", str(cells), "--seed", "3"]
    assert runner.invoke(cli, [*args, "-j", "1"]).exit_code == 0
    assert fitsio.read_header(str(cells), 0)["INNERBRD"] == 30
    out = tmp_path / "det.fits"
    result = runner.invoke(cli, ["measure", str(cells), "--metadetect", "-o", str(out), "-j", "1"])
    assert result.exit_code == 0, result.output
    det = read_catalog(out)
    x, y = np.asarray(det["x"]), np.asarray(det["y"])
    inside = (x > 30.5) & (x <= 130.5) & (y > 30.5) & (y <= 130.5)
    assert inside.any() and (~inside).any()
    np.testing.assert_array_equal(np.asarray(det["inner"]) != 0, inside)
    assert fitsio.read_header(str(out), 1)["INNERBRD"] == 30


def test_bad_input_is_one_line(runner, cli, tmp_path):
    cells, _ = scenes(runner, cli, tmp_path)
    out = tmp_path / "out.fits"
    # a grid image of stamps, a MEDS file: not cells
    grid = tmp_path / "grid.fits"
    fitsio.write(str(grid), np.zeros((64, 64), np.float32))
    invoke_fails(runner, cli, ["measure", str(grid), "--metadetect", "-o", str(out)], 2, "cells")
    meds = tmp_path / "o.meds.fits"
    write_meds(meds, np.zeros((2, 16, 16)))
    invoke_fails(runner, cli, ["measure", str(meds), "--metadetect", "-o", str(out)], 2, "cells")
    # a cells file without PSF
    nopsf = tmp_path / "nopsf.fits"
    with fitsio.FITS(str(cells)) as f:
        sci, wgt = f["SCI"].read(), f["WGT"].read()
    with fitsio.FITS(str(nopsf), "rw", clobber=True) as f:
        f.write(sci, extname="SCI")
        f.write(wgt, extname="WGT")
    invoke_fails(runner, cli, ["measure", str(nopsf), "--metadetect", "-o", str(out)], 1, "PSF")
    # a cells file without --metadetect; with --metacal too; a catalog
    invoke_fails(runner, cli, ["measure", str(cells), "-o", str(out)], 2, "--metadetect")
    args = ["measure", str(cells), "--metadetect", "--metacal", "-o", str(out)]
    invoke_fails(runner, cli, args, 2, "--metacal")
    args = ["measure", str(cells), "--metadetect", "--stamp-size", "400", "-o", str(out)]
    invoke_fails(runner, cli, args, 2, "--stamp-size")
    # NaN pixels that are not masked
    nan = tmp_path / "nan.fits"
    with fitsio.FITS(str(cells)) as f:
        hdus = {n: f[n].read() for n in ("SCI", "WGT", "PSF")}
    hdus["SCI"][1, 50, 50] = np.nan
    with fitsio.FITS(str(nan), "rw", clobber=True) as f:
        for n, arr in hdus.items():
            f.write(arr, extname=n)
    invoke_fails(runner, cli, ["measure", str(nan), "--metadetect", "-o", str(out)], 1, "cell 1")
    # a cell whose every pixel is masked; a PSF cube of another pixel scale
    masked = tmp_path / "masked.fits"
    hdus["SCI"][1, 50, 50] = 0.0
    weights = hdus["WGT"].copy()
    weights[2] = 0.0
    with fitsio.FITS(str(masked), "rw", clobber=True) as f:
        f.write(hdus["SCI"], extname="SCI", header={"PIXSCALE": 0.25})
        f.write(weights, extname="WGT")
        f.write(hdus["PSF"], extname="PSF")
    args = ["measure", str(masked), "--metadetect", "-o", str(out)]
    invoke_fails(runner, cli, args, 1, "cell 2", "every pixel is masked")
    scale = tmp_path / "scale.fits"
    with fitsio.FITS(str(scale), "rw", clobber=True) as f:
        f.write(hdus["SCI"], extname="SCI", header={"PIXSCALE": 0.25})
        f.write(hdus["PSF"], extname="PSF", header={"PIXSCALE": 0.2})
    invoke_fails(runner, cli, ["measure", str(scale), "--metadetect", "-o", str(out)], 1, "0.2")
    # a coadd image's options on a cells file
    args = ["measure", str(cells), "--metadetect", "--weight", str(cells), "-o", str(out)]
    invoke_fails(runner, cli, args, 2, "--weight")
    assert not out.exists()


def test_correlated_noise_scenes_carry_a_noise_cube_for_fixnoise(runner, cli, tmp_path):
    """Scenes with correlated noise write NOISE: another realization, independent of the
    images' noise, with its correlations; metadetection takes it as the fixnoise field."""
    from pathlib import Path

    cf = Path(__file__).parents[1] / "examples" / "data" / "cosmos" / "acs_I_unrot_sci_20_cf.fits"
    config = write(tmp_path, CELLS, replace={"{sigma}": "1.0"})
    noise = f'[noise]\ntype = "correlated"\nsigma = 1.0\ncorrelation = "{cf}"\npixel_scale = 1.0\n'
    text = config.read_text().replace('[noise]\ntype = "gaussian"\nsigma = 1.0\n', noise)
    config.write_text(text)
    cells, truth = tmp_path / "c.fits", tmp_path / "t.fits"
    args = ["simulate", str(config), "-o", str(truth), "--scene", str(cells), "--pairs"]
    result = runner.invoke(cli, [*args, "scene.n_fields=2", "scene.size=128"])
    assert result.exit_code == 0, result.output
    with fitsio.FITS(str(cells)) as f:
        sci, twin = f["SCI"].read(), f["NOISE"].read()
    assert twin.shape == sci.shape
    np.testing.assert_array_equal(twin[0], twin[1])  # a pair shares it, as its noise
    blank = np.abs(sci[0] - sci[1]) < 1e-6  # no galaxy there: the images' noise alone
    assert blank.mean() > 0.5
    assert abs(np.corrcoef(sci[0][blank], twin[0][blank])[0, 1]) < 0.05  # independent

    def neighbour_corr(a: np.ndarray) -> float:
        return float(np.corrcoef(a[:, :-1].ravel(), a[:, 1:].ravel())[0, 1])

    assert neighbour_corr(twin[0]) > 0.1  # correlated, as the images' noise
    out = tmp_path / "det.fits"
    result = runner.invoke(cli, ["measure", str(cells), "--metadetect", "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert fitsio.read_header(str(out), 1)["MDETFIX"].strip() == "NOISE"


def test_detect_is_the_stamp_route_on_the_same_cells(measured, runner, cli, tmp_path):
    """--detect: one row per detection on the cells themselves (no versions); with
    --metacal, each stamp's metacal versions: a metacal catalog, whose per-object response
    on these noiseless isolated galaxies is the metadetection response."""
    cells, truth, det, _ = measured
    out = tmp_path / "stamps.fits"
    args = ["measure", str(cells), "--detect", "--metacal", "-o", str(out), "-j", "1"]
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    rows, header = read_catalog(out), fitsio.read_header(str(out), 1)
    assert header["MLFORMAT"] == "megalut.features" and header["MCALSTEP"] == STEP
    assert "mdet_step" not in rows.colnames and "adamom_g1_1p" in rows.colnames
    ns = det[det["mdet_step"] == "noshear"]
    assert len(rows) == len(ns)
    near = np.hypot(
        np.asarray(rows["x"])[:, None] - np.asarray(ns["x"])[None, :],
        np.asarray(rows["y"])[:, None] - np.asarray(ns["y"])[None, :],
    )
    assert near.min(axis=1).max() < 0.5
    ok = (rows["flags"] == 0) & (rows["flags_1p"] == 0) & (rows["flags_1m"] == 0)
    r11 = (np.asarray(rows["adamom_g1_1p"]) - rows["adamom_g1_1m"])[ok].mean() / (2 * STEP)
    p1, m1 = det[det["mdet_step"] == "1p"], det[det["mdet_step"] == "1m"]
    p1, m1 = p1[p1["flags"] == 0], m1[m1["flags"] == 0]
    r11_mdet = (p1["adamom_g1"].mean() - m1["adamom_g1"].mean()) / (2 * STEP)
    assert r11 == pytest.approx(r11_mdet, rel=0.05)
    # without --metacal: the features only; --detect and --metadetect exclude each other
    result = runner.invoke(cli, ["measure", str(cells), "--detect", "-o", str(tmp_path / "d.fits")])
    assert result.exit_code == 0, result.output
    assert "adamom_g1_1p" not in read_catalog(tmp_path / "d.fits").colnames
    args = ["measure", str(cells), "--detect", "--metadetect", "-o", str(tmp_path / "x.fits")]
    invoke_fails(runner, cli, args, 2, "--detect", "--metadetect")


def test_mask_neighbours_keeps_a_neighbour_out_of_the_moments(runner, cli, tmp_path):
    """``--mask-neighbours``: a round galaxy 12 px from one twice as bright (noise 1, S/N
    of hundreds); with the neighbour left in, its moments fail or take in the pair
    (|g1| about 0.5); with the neighbour's segment masked (sep's segmentation of each
    version) its ellipticity is that of the galaxy alone within 0.02 in every version, and
    the catalog says so (MASKNBR)."""
    size = 96
    psf = galsim.Gaussian(fwhm=3.6)
    gal = galsim.Convolve(galsim.Exponential(half_light_radius=1.5, flux=6000.0), psf)
    bright = galsim.Convolve(galsim.Exponential(half_light_radius=1.5, flux=12000.0), psf)
    image = galsim.ImageD(size, size, scale=1.0)
    gal.drawImage(image=image, offset=(-6.0, 0.0), add_to_image=True)
    bright.drawImage(image=image, offset=(6.0, 0.0), add_to_image=True)
    alone = galsim.ImageD(size, size, scale=1.0)
    gal.drawImage(image=alone, offset=(-6.0, 0.0))
    psf_image = psf.drawImage(nx=32, ny=32, scale=1.0).array
    settings = MeasureSettings(metacal=MetacalSettings(STEP, 4))
    near = {}
    for mask, cell in ((False, image.array), (True, image.array), (None, alone.array)):
        detection = DetectSettings(3.0, 4, 32, 0.005, mask_neighbours=bool(mask))
        out = metadetect_cell(cell, psf_image, CellNoise(1.0, 7), settings, detection, 48)
        centre = (size + 1) / 2.0 - 6.0  # 1-based x of the fainter galaxy
        rows = np.flatnonzero(np.hypot(out["x"] - centre, out["y"] - (size + 1) / 2.0) < 2.0)
        assert sorted(out["mdet_step"][rows]) == sorted(TYPES), (mask, out["mdet_step"][rows])
        near[mask] = out["adamom_g1"][rows], out["flags"][rows]
    g_alone, _ = near[None]
    g_masked, flags_masked = near[True]
    g_left, flags_left = near[False]
    assert np.all(flags_masked == 0) and np.all(np.abs(g_masked - g_alone) < 0.02), g_masked
    assert np.all((flags_left != 0) | (np.abs(g_left - g_alone) > 0.2)), g_left
    cells, _ = scenes(runner, cli, tmp_path, sigma=1.0)
    out = tmp_path / "masked.fits"
    args = ["measure", str(cells), "--metadetect", "--mask-neighbours", "-j", "1", "-o", str(out)]
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert fitsio.read_header(str(out), 1)["MASKNBR"] is True


def test_a_galaxy_split_by_the_deblending_is_kept_once():
    """A disk with a bright knot 7 px from its centre: sep deblends it into two detections
    whose adaptive moments converge on the same centroid (the same light, twice). With
    ``duplicate_radius`` 0 both rows stay; by default, in every version, the detection
    nearer the centroid keeps it and the other is flagged DUPLICATE with NaN features."""
    from megalut_cli import flags as fl

    psf = galsim.Gaussian(fwhm=3.6)
    disk = galsim.Exponential(half_light_radius=4.0, flux=7000.0)
    knot = galsim.Gaussian(sigma=1.0, flux=3500.0).shift(7.0, 0.0)
    noise = np.random.default_rng(3).normal(0.0, 1.0, (96, 96))
    image = galsim.Convolve(disk + knot, psf).drawImage(nx=96, ny=96, scale=1.0).array + noise
    psf_image = psf.drawImage(nx=33, ny=33, scale=1.0).array
    settings = MeasureSettings(metacal=MetacalSettings(STEP, 4))
    kept_both = DetectSettings(5.0, 4, 32, 0.005, duplicate_radius=0.0)
    both = metadetect_cell(image, psf_image, CellNoise(1.0, 7), settings, kept_both, 48)
    default = DetectSettings(5.0, 4, 32, 0.005)
    once = metadetect_cell(image, psf_image, CellNoise(1.0, 7), settings, default, 48)
    for kind in TYPES:
        two = np.flatnonzero(both["mdet_step"] == kind)
        assert len(two) == 2 and np.all(both["flags"][two] == 0), kind
        cx, cy = both["adamom_x"][two], both["adamom_y"][two]
        assert np.hypot(cx[0] - cx[1], cy[0] - cy[1]) < 0.01  # one light
        rows = np.flatnonzero(once["mdet_step"] == kind)
        assert np.array_equal(once["x"][rows], both["x"][two])
        dup = (once["flags"][rows] & fl.DUPLICATE) != 0
        assert dup.sum() == 1 and np.all(once["flags"][rows][~dup] == 0), kind
        assert np.isnan(once["adamom_g1"][rows][dup]).all()
        kept = rows[~dup][0]
        assert once["adamom_g1"][kept] == both["adamom_g1"][two][~dup][0]
        offsets = np.hypot(both["x"][two] - cx, both["y"][two] - cy)  # unsheared: ~0.5 px off
        assert np.argmin(offsets) == np.flatnonzero(~dup)[0]  # the nearer detection kept


def test_duplicates_are_flagged_by_their_centroids():
    """``flag_duplicates``: of rows whose centroids lie within the radius, all but the one
    detected nearest the centroid (the first of a tie) are flagged DUPLICATE with NaN
    features; a distinct centroid and a row without one take no part; radius 0: none."""
    from megalut_cli import flags as fl
    from megalut_cli.measure.cell_detect import flag_duplicates

    def feats() -> dict[str, np.ndarray]:
        return {
            "adamom_x": np.array([10.0, 10.125, 30.0, np.nan, 10.05]),
            "adamom_y": np.array([20.0, 20.0, 20.0, 20.0, 20.0]),
            "adamom_g1": np.array([0.1, 0.1, 0.2, np.nan, 0.1]),
            "flags": np.array([0, 0, 0, fl.HSM_FAILED, 0], dtype=np.int32),
        }

    x = np.array([14.0, 11.0, 30.0, 10.0, 12.0])  # row 1 detected nearest the shared light
    y = np.full(5, 20.0)
    out = feats()
    flag_duplicates(out, x, y, 0.25, MeasureSettings())
    assert list((out["flags"] & fl.DUPLICATE) != 0) == [True, False, False, False, True]
    assert np.isnan(out["adamom_g1"][[0, 4]]).all() and out["adamom_g1"][1] == 0.1
    assert out["flags"][3] == fl.HSM_FAILED
    untouched = feats()
    flag_duplicates(untouched, x, y, 0.0, MeasureSettings())
    assert np.all((untouched["flags"] & fl.DUPLICATE) == 0)
    tie = feats()
    flag_duplicates(tie, np.array([9.0, 11.125, 30.0, 10.0, 40.0]), y, 0.25, MeasureSettings())
    assert list((tie["flags"] & fl.DUPLICATE) != 0) == [False, True, False, False, True]


def test_the_galsim_engine_is_the_reference_route(measured, runner, cli, tmp_path):
    """``--engine galsim`` runs GalSim's operation on the cells (header MCALENG): the same
    detections as the cell engine on the nearly noiseless scenes, with shapes within 1e-3."""
    cells, _, fast, header = measured
    assert header["MCALENG"] == "fast"
    out = tmp_path / "galsim.fits"
    args = ["measure", str(cells), "--metadetect", "--engine", "galsim", "-j", "1", "-o", str(out)]
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert fitsio.read_header(str(out), 1)["MCALENG"] == "galsim"
    ref = read_catalog(out)
    assert len(ref) == len(fast)
    for kind in TYPES:
        a, b = fast[fast["mdet_step"] == kind], ref[ref["mdet_step"] == kind]
        np.testing.assert_allclose(a["x"], b["x"], atol=0.01)
        np.testing.assert_allclose(a["adamom_g1"], b["adamom_g1"], atol=1e-3)
        np.testing.assert_allclose(a["adamom_g2"], b["adamom_g2"], atol=1e-3)


def test_masked_pixels_are_interpolated_and_near_detections_flagged():
    """Masked pixels (a saturated star's core, a bad column of NaN): filled by the harmonic
    interpolation of their neighbours before the metacal operation; a detection whose
    unsheared position lies within ``mask_margin`` of a masked pixel is flagged NEAR_MASK
    with NaN features, ``mask_dist`` its distance; a galaxy beyond the margin is measured
    as without the masks, in every version."""
    from megalut_cli import flags as fl

    size = 128
    psf = galsim.Gaussian(fwhm=3.6)
    gal = galsim.Convolve(galsim.Exponential(half_light_radius=2.0, flux=3000.0), psf)
    clean = galsim.ImageD(size, size, scale=1.0)
    gal.drawImage(image=clean, offset=(-30.0, 10.0))
    noise = np.random.default_rng(5).normal(0.0, 1.0, (size, size))
    plain = clean.array + noise
    starry = galsim.ImageD(size, size, scale=1.0)
    psf.withFlux(2e5).drawImage(image=starry, offset=(25.0, -20.0))
    image = plain + starry.array
    bad = image > 2000.0  # the star's saturated core
    bad[:, 100] = True  # a bad column
    image = np.where(bad, np.nan, image)
    psf_image = psf.drawImage(nx=33, ny=33, scale=1.0).array
    settings = MeasureSettings(metacal=MetacalSettings(STEP, 4))
    detection = DetectSettings(5.0, 4, 32, 0.005)
    with pytest.raises(Exception, match="not masked"):
        metadetect_cell(image, psf_image, CellNoise(1.0, 7), settings, detection, 48)
    out = metadetect_cell(image, psf_image, CellNoise(1.0, 7), settings, detection, 48, bad)
    ref = metadetect_cell(plain, psf_image, CellNoise(1.0, 7), settings, detection, 48)
    yy, xx = np.nonzero(bad)
    brute = np.min(np.hypot(out["x"][:, None] - 1 - xx, out["y"][:, None] - 1 - yy), axis=1)
    near = out["mask_dist"] <= detection.mask_margin
    assert near.any() and np.all((out["flags"][near] & fl.NEAR_MASK) != 0)
    assert np.isnan(out["adamom_g1"][near]).all()
    np.testing.assert_allclose(out["mask_dist"], brute, atol=0.75)  # the pixel holding it
    assert np.isinf(ref["mask_dist"]).all() and np.all((ref["flags"] & fl.NEAR_MASK) == 0)
    centre = ((size + 1) / 2.0 - 30.0, (size + 1) / 2.0 + 10.0)
    for kind in TYPES:
        ours = (out["mdet_step"] == kind) & (
            np.hypot(out["x"] - centre[0], out["y"] - centre[1]) < 2
        )
        theirs = (ref["mdet_step"] == kind) & (
            np.hypot(ref["x"] - centre[0], ref["y"] - centre[1]) < 2
        )
        assert ours.sum() == theirs.sum() == 1, kind
        assert out["flags"][ours][0] == 0 and out["mask_dist"][ours][0] > 30
        for c in ("adamom_g1", "adamom_g2", "adamom_sigma"):
            assert abs(out[c][ours][0] - ref[c][theirs][0]) < 1e-5, (kind, c)


def test_the_versions_share_the_known_noise_in_their_snr(runner, cli, tmp_path):
    """Each version's ``snr`` is on the cell's known noise through the operation (the
    detection's noise, the same in the five versions), not on its stamp's edge MAD, which the
    operation resamples differently in each version: an S/N cut would otherwise select on
    noise the shear does not make (docs/metadetect.md)."""
    cells, _ = scenes(runner, cli, tmp_path, sigma=0.5)
    out = tmp_path / "det.fits"
    result = runner.invoke(cli, ["measure", str(cells), "--metadetect", "-o", str(out), "-j", "1"])
    assert result.exit_code == 0, result.output
    det = read_catalog(out)
    p, m = det[det["mdet_step"] == "1p"], det[det["mdet_step"] == "1m"]
    pairs = []
    for image in np.unique(p["image"]):
        a, b = p[p["image"] == image], m[m["image"] == image]
        if len(a) and len(b):
            d = np.hypot(
                np.asarray(a["x"])[:, None] - np.asarray(b["x"])[None, :],
                np.asarray(a["y"])[:, None] - np.asarray(b["y"])[None, :],
            )
            j = d.argmin(axis=1)
            good = (d[np.arange(len(a)), j] < 0.5) & (a["flags"] == 0) & (b["flags"][j] == 0)
            pairs += [(a[i], b[j[i]]) for i in np.flatnonzero(good)]
    assert len(pairs) >= 20
    snr = np.array([(x["snr"], y["snr"]) for x, y in pairs])
    sky = np.array([(x["skymad"], y["skymad"]) for x, y in pairs])
    flux = np.array([(x["adamom_flux"], y["adamom_flux"]) for x, y in pairs])
    moved = np.median(np.abs(np.log(snr[:, 0] / snr[:, 1])))
    # the edge MADs differ by a few per cent between versions, the fluxes by far less
    assert np.median(np.abs(np.log(sky[:, 0] / sky[:, 1]))) > 0.02
    assert moved < 2 * np.median(np.abs(np.log(flux[:, 0] / flux[:, 1]))) + 2e-3
    # the known noise is the level of the edge MADs (Eq. 10: snr = flux / (sqrt(area) noise));
    # neighbours' light raises a MAD (on pure noise the two agree within 2.5 %)
    size = np.array([(x["adamom_sigma"], y["adamom_sigma"]) for x, y in pairs])
    noise = flux / (snr * np.sqrt(effective_area(size)))
    assert 0.97 < np.median(sky) / np.median(noise) < 1.12
    assert np.ptp(noise) < 1e-6 * np.median(noise)  # one cell noise: the scenes share it
