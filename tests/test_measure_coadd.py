"""``megalut measure IMAGE --weight W --psf P --metadetect`` (``measure/coadd.py``): a coadd
image cut into overlapping cells whose inner regions tile it; each galaxy counted once in
every version, positions in the image's pixels and on the sky, the fixnoise field shared by
overlapping cells, a noise image, a PSF model, and bad input."""

from __future__ import annotations

import fitsio
import galsim
import numpy as np
import pytest
from helpers import invoke_fails

from megalut_cli.catalog import read_catalog
from megalut_cli.measure.cell_catalog import inner_region
from megalut_cli.measure.cell_detect import field_version_noise, version_noise
from megalut_cli.measure.coadd import cell_origins, tiled_normals
from megalut_cli.measure.metacal_defaults import TYPES

SIZE, BORDER = 96, 16  # cells 64 pixels apart
SCALE = 0.25
PSF = galsim.Gaussian(fwhm=3.6 * SCALE)


def wcs_header(ny: int, nx: int, scale: float = SCALE) -> dict:
    """A TAN WCS, north up and east left (RA decreasing with x)."""
    return {
        "CTYPE1": "RA---TAN",
        "CTYPE2": "DEC--TAN",
        "CRVAL1": 150.0,
        "CRVAL2": 2.0,
        "CRPIX1": nx / 2.0,
        "CRPIX2": ny / 2.0,
        "CD1_1": -scale / 3600.0,
        "CD1_2": 0.0,
        "CD2_1": 0.0,
        "CD2_2": scale / 3600.0,
    }


def write_coadd(tmp_path, sigma: float = 0.05, shape=(230, 250), seed: int = 2):
    """A coadd of isolated round exponential galaxies on a jittered grid (one at every 36
    pixels, some on the cells' inner boundaries), its weight map and PSF; their truth."""
    ny, nx = shape
    rng = np.random.default_rng(seed)
    image = galsim.ImageF(nx, ny, scale=SCALE)
    xs, ys = np.meshgrid(np.arange(20, nx - 19, 36.0), np.arange(20, ny - 19, 36.0))
    x = xs.ravel() + rng.uniform(-3, 3, xs.size)
    y = ys.ravel() + rng.uniform(-3, 3, ys.size)
    n_x = xs.shape[1]
    x[1], x[3], y[n_x + 2] = 64.55, 128.45, 64.45  # by the inner boundaries (64.5, 128.5)
    gal = galsim.Exponential(half_light_radius=2.0 * SCALE, flux=400.0)
    for xi, yi in zip(x, y):
        stamp = galsim.Convolve(gal, PSF).drawImage(
            nx=41, ny=41, scale=SCALE, center=galsim.PositionD(xi, yi)
        )
        overlap = stamp.bounds & image.bounds
        image[overlap] += stamp[overlap]
    pixels = image.array + rng.normal(0.0, sigma, (ny, nx))
    header = wcs_header(ny, nx)
    paths = {k: tmp_path / f"{k}.fits" for k in ("coadd", "weight", "psf")}
    fitsio.write(str(paths["coadd"]), pixels.astype(np.float32), header=header, clobber=True)
    weight = np.full((ny, nx), 1.0 / sigma**2, np.float32)
    fitsio.write(str(paths["weight"]), weight, header=header, clobber=True)
    psf = PSF.drawImage(nx=33, ny=33, scale=SCALE).array
    fitsio.write(str(paths["psf"]), psf, header={"PIXSCALE": SCALE}, clobber=True)
    return paths, x, y


def test_cells_inner_regions_tile_the_image():
    ny, nx = 230, 250
    origins = cell_origins((ny, nx), SIZE, BORDER)
    assert len(origins) == 4 * 4  # ceil(250 / 64) x ceil(230 / 64)
    assert origins.min() == -BORDER
    # every pixel centre (and points between) lies in exactly one cell's inner region
    px, py = np.meshgrid(np.arange(1, nx + 1, 0.5), np.arange(1, ny + 1, 0.5))
    counts = np.zeros(px.shape, int)
    for x0, y0 in origins:
        counts += inner_region(px - x0, py - y0, SIZE, BORDER)
    assert (counts == 1).all()


def test_the_fixnoise_field_is_the_same_pixels_in_every_cell():
    a = tiled_normals(5, -16, -16, 96)
    b = tiled_normals(5, 48, 32, 96)
    np.testing.assert_array_equal(a[48:, 64:], b[:48, :32])  # the pixels the cells share
    assert abs(a.std() - 1.0) < 0.05 and abs(a.mean()) < 0.05
    assert not np.array_equal(tiled_normals(6, -16, -16, 96), a)


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    from click.testing import CliRunner

    from megalut_cli.cli import main

    tmp_path = tmp_path_factory.mktemp("coadd")
    paths, x, y = write_coadd(tmp_path)
    out = tmp_path / "det.fits"
    args = ["measure", str(paths["coadd"]), "--weight", str(paths["weight"])]
    args += ["--psf", str(paths["psf"]), "--metadetect", "-o", str(out), "-j", "1"]
    args += ["--cell-size", str(SIZE), "--cell-border", str(BORDER)]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    return paths, x, y, read_catalog(out), fitsio.read_header(str(out), 1)


def test_each_galaxy_counts_once_in_every_version(measured):
    _, x, y, det, _ = measured
    for kind in TYPES:
        rows = det[(det["mdet_step"] == kind) & (det["inner"] == 1)]
        dist = np.hypot(
            np.asarray(rows["x"])[:, None] - x[None, :], np.asarray(rows["y"])[:, None] - y[None]
        )
        nearest = dist.argmin(axis=1)
        assert dist.min(axis=1).max() < 0.5, kind  # image pixels, each version
        assert len(rows) == len(x) and len(np.unique(nearest)) == len(x), kind
    every = det[det["mdet_step"] == "noshear"]
    assert len(every) > len(x)  # the overlaps: galaxies seen by several cells, inner in one
    assert len(np.unique(every["cell"])) == 16


def test_the_catalog_holds_sky_positions_and_its_cards(measured):
    paths, _, _, det, header = measured
    names = list(det.colnames)
    jacobian = ["dudcol", "dudrow", "dvdcol", "dvdrow"]
    assert names[:11] == ["mdet_step", "cell", "x", "y", "ra", "dec", *jacobian, "inner"]
    wcs = galsim.FitsWCS(str(paths["coadd"]))
    ra, dec = wcs.xyToradec(np.asarray(det["x"]), np.asarray(det["y"]), units="deg")
    np.testing.assert_allclose(det["ra"], ra, atol=1e-9)
    np.testing.assert_allclose(det["dec"], dec, atol=1e-9)
    for row in det[:5]:  # the WCS's local Jacobian (arcsec per pixel): calibrate's world frame
        local = wcs.jacobian(galsim.PositionD(float(row["x"]), float(row["y"])))
        expect = [local.dudx, local.dudy, local.dvdx, local.dvdy]
        np.testing.assert_allclose([row[c] for c in jacobian], expect, rtol=1e-6, atol=1e-9)
    assert header["MLFORMAT"] == "megalut.metadetect"
    assert (header["CELLSZ"], header["INNERBRD"], header["NCELLS"]) == (SIZE, BORDER, 16)
    assert header["IMGFILE"] == "coadd.fits" and header["WGTFILE"] == "weight.fits"
    assert header["PIXSCALE"] == pytest.approx(SCALE)


def test_a_noise_image_sets_the_fixnoise_field_and_the_threshold(runner, cli, tmp_path):
    psf = PSF.drawImage(nx=33, ny=33, scale=SCALE).array
    white = np.random.default_rng(3).normal(0.0, 2.0, (128, 128))
    # a white noise image gives the white-noise threshold (within the cut's noise)
    assert field_version_noise(psf, white, 0.01, "gauss") == pytest.approx(
        version_noise(psf, 2.0, 0.01, "gauss"), rel=0.05
    )
    # correlated noise: smoothed white noise of the same pixel rms has another version noise
    smooth = galsim.ImageD(white.copy(), scale=1.0)
    corr = galsim.Gaussian(sigma=1.5).drawImage(nx=15, ny=15, scale=1.0).array
    from scipy.signal import fftconvolve

    smooth = fftconvolve(white, corr, mode="same")
    smooth *= 2.0 / smooth.std()
    assert field_version_noise(psf, smooth, 0.01, "gauss") > 1.3 * version_noise(
        psf, 2.0, 0.01, "gauss"
    )
    paths, _, _ = write_coadd(tmp_path, shape=(150, 150))
    noise = tmp_path / "noise.fits"
    rng = np.random.default_rng(9)
    fitsio.write(str(noise), rng.normal(0.0, 0.05, (150, 150)).astype(np.float32), clobber=True)
    out = tmp_path / "det.fits"
    args = ["measure", str(paths["coadd"]), "--weight", str(paths["weight"])]
    args += ["--psf", str(paths["psf"]), "--metadetect", "-o", str(out)]
    args += ["--cell-size", str(SIZE), "--cell-border", str(BORDER)]
    result = runner.invoke(cli, [*args, "--noise-image", str(noise)])
    assert result.exit_code == 0, result.output
    header = fitsio.read_header(str(out), 1)
    assert header["NOIFILE"] == "noise.fits"
    det = read_catalog(out)
    assert (det["inner"] == 1).sum() > 0


def test_bad_input_is_one_line(runner, cli, tmp_path):
    paths, _, _ = write_coadd(tmp_path, shape=(120, 120))
    out = tmp_path / "out.fits"
    base = ["measure", str(paths["coadd"]), "--metadetect", "-o", str(out)]
    with_weight = [*base, "--weight", str(paths["weight"])]
    # no weight map; no PSF; --weight without --metadetect; a cell border too wide
    invoke_fails(runner, cli, [*base, "--psf", str(paths["psf"])], 2, "--weight")
    invoke_fails(runner, cli, with_weight, 2, "--psf")
    args = ["measure", str(paths["coadd"]), "--weight", str(paths["weight"]), "-o", str(out)]
    invoke_fails(runner, cli, args, 2, "--weight", "--metadetect")
    args = [*with_weight, "--psf", str(paths["psf"]), "--cell-border", "48", "--cell-size", "96"]
    invoke_fails(runner, cli, args, 2, "--cell-border")
    # a weight map of another shape
    small = tmp_path / "small.fits"
    fitsio.write(str(small), np.ones((60, 60), np.float32))
    args = [*base, "--weight", str(small), "--psf", str(paths["psf"])]
    invoke_fails(runner, cli, args, 1, "small.fits", "agree")
    # a PSF of another pixel scale
    psf = fitsio.read(str(paths["psf"]))
    wrong = tmp_path / "psf_scale.fits"
    fitsio.write(str(wrong), psf, header={"PIXSCALE": 0.2}, clobber=True)
    invoke_fails(runner, cli, [*with_weight, "--psf", str(wrong)], 1, "pixels are 0.2")
    # a PSF of the wrong parity: an even image with the PSF centred on a pixel
    even = tmp_path / "psf_even.fits"
    fitsio.write(str(even), np.ascontiguousarray(psf[:-1, :-1]), clobber=True)
    invoke_fails(runner, cli, [*with_weight, "--psf", str(even)], 1, "centre")
    # every pixel masked; NaN pixels not masked
    zero = tmp_path / "zero.fits"
    fitsio.write(str(zero), np.zeros((120, 120), np.float32))
    args = [*base, "--weight", str(zero), "--psf", str(paths["psf"])]
    invoke_fails(runner, cli, args, 1, "every pixel is bad")
    nan = tmp_path / "nan.fits"
    pixels = fitsio.read(str(paths["coadd"]))
    pixels[60, 60] = np.nan
    fitsio.write(str(nan), pixels, clobber=True)
    args = ["measure", str(nan), "--metadetect", "-o", str(out), "--weight", str(paths["weight"])]
    invoke_fails(runner, cli, [*args, "--psf", str(paths["psf"])], 1, "NaN")
    assert not out.exists()


def test_the_coadds_images_are_named_by_their_flags(runner, cli, tmp_path):
    """--weight, --mask and --noise-image: each refused by its flag where it does not apply,
    each checked against the image's shape; every option of the table reaches the library
    argument whose messages name it."""
    from megalut_cli.cli.measure import COADD_IMAGE_OPTIONS, command
    from megalut_cli.measure.source_registry import COADD_IMAGES

    assert [arg for _, arg, _ in COADD_IMAGE_OPTIONS] == [i.field for i in COADD_IMAGES]
    options = {p.name: p.opts for p in command.params}
    for flag, arg, _ in COADD_IMAGE_OPTIONS:
        assert options[arg] == [flag]
    paths, _, _ = write_coadd(tmp_path, shape=(120, 120))
    out = tmp_path / "out.fits"
    image = ["measure", str(paths["coadd"]), "-o", str(out)]
    given = [
        *(x for f in ("--weight", "--mask", "--noise-image") for x in (f, str(paths["weight"])))
    ]
    invoke_fails(
        runner, cli, [*image, *given], 2, "--weight, --mask, --noise-image: for --metadetect"
    )
    psf = ["--psf", str(paths["psf"])]
    args = [*image, "--detect", *psf, "--weight", str(paths["weight"])]
    invoke_fails(runner, cli, [*args, "--noise-image", str(paths["weight"])], 2, "--noise-image")
    small = tmp_path / "small.fits"
    fitsio.write(str(small), np.ones((60, 60), np.float32))
    args = [*image, "--metadetect", *psf, "--weight", str(paths["weight"])]
    for flag, what in (("--mask", "the mask image"), ("--noise-image", "the noise image")):
        invoke_fails(runner, cli, [*args, flag, str(small)], 1, "small.fits", what, "agree")
    assert not out.exists()


def test_a_psf_model_and_workers(runner, cli, tmp_path):
    """A PSFEx model drawn at each cell's centre; the same rows with one or two workers and
    a Dask cluster."""
    from pathlib import Path

    import distributed

    decam = Path(__file__).with_name("data") / "DECam_00154912_12_psfcat.psf"
    paths, _, _ = write_coadd(tmp_path, shape=(150, 150))
    outs = []
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        for j, run in (("1", ["-j", "1"]), ("2", ["-j", "2"]), ("d", ["--scheduler"])):
            out = tmp_path / f"det{j}.fits"
            args = ["measure", str(paths["coadd"]), "--weight", str(paths["weight"])]
            args += ["--psf-model", str(decam), "--metadetect", "-o", str(out), *run]
            if j == "d":
                args.append(cluster.scheduler_address)
            result = runner.invoke(cli, [*args, "--cell-size", str(SIZE), "--cell-border", "16"])
            assert result.exit_code == 0, result.output
            outs.append(fitsio.read(str(out)))
    for other in outs[2:]:
        assert other.dtype == outs[0].dtype
        for name in outs[0].dtype.names:
            kind = outs[0][name].dtype.kind == "f"
            assert np.array_equal(outs[0][name], other[name], equal_nan=kind), name
    assert outs[0].dtype == outs[1].dtype
    for name in outs[0].dtype.names:
        same = np.array_equal(
            outs[0][name], outs[1][name], equal_nan=outs[0][name].dtype.kind == "f"
        )
        assert same, name
    header = fitsio.read_header(str(tmp_path / "det1.fits"), 1)
    assert header["PSFMTYPE"] == "psfex" and "PSFFILE" not in header
    assert (outs[0]["inner"] == 1).sum() >= 5 * 9  # five versions of nine galaxies at least
