"""PSF models (``megalut_cli/measure/psf_model.py``) and ``measure --psf-model``.

A real DECam PSFEx model (tests/data, from GalSim's repository), synthetic PSFEx files with
a known PSF, and a small Piff model fit here to stars drawn with GalSim.
"""

from __future__ import annotations

import sys
from pathlib import Path

import fitsio
import galsim
import galsim.des
import numpy as np
import pytest
from helpers import FLOAT32_SUMS, assert_same_column

from megalut_cli.catalog import read_catalog, write_catalog, write_image
from megalut_cli.measure.defaults import PSF_COLUMNS
from megalut_cli.measure.features import measure_stamps
from megalut_cli.measure.measurer import same_parity_psfs
from megalut_cli.measure.metacal import metacal_features
from megalut_cli.measure.psf_model import PIFF, PSFEX, file_kind, load_psf_model
from megalut_cli.provenance import sha256_file

DECAM = Path(__file__).with_name("data") / "DECam_00154912_12_psfcat.psf"
S = 48
NX, NY = 4, 3


def _hsm(stamp: np.ndarray) -> galsim.hsm.ShapeData:
    return galsim.hsm.FindAdaptiveMom(galsim.ImageD(stamp, scale=1.0))


def _galsim_psfex(x: float, y: float, size: int) -> np.ndarray:
    """GalSim's own drawing of the DECam model (DES_PSFEx.getPSF, no pixel), unit sum."""
    image = (
        galsim.des.DES_PSFEx(str(DECAM))
        .getPSF(galsim.PositionD(x, y))
        .drawImage(nx=size, ny=size, scale=1.0, method="no_pixel")
        .array
    )
    return image / image.sum()


def _galsim_reference(x: float, y: float, size: int) -> np.ndarray:
    """GalSim's drawing of the DECam model as megalut draws it: on an odd stamp as GalSim
    draws it, on an even one on a pixel fewer and moved half a pixel (``same_parity_psfs``,
    lanczos15), unit sum."""
    if size % 2:
        return _galsim_psfex(x, y, size)
    image = same_parity_psfs(_galsim_psfex(x, y, size - 1)[None], size)[0]
    return image / image.sum()


def _gaussian_basis(sigma: float, n: int = 25) -> np.ndarray:
    r2 = (np.arange(n) - (n - 1) / 2.0) ** 2
    g = np.exp(-(r2[:, None] + r2[None, :]) / (2 * sigma**2))
    return g / g.sum()


def _write_psfex(
    path: Path,
    basis: np.ndarray,
    zero=(0.0, 0.0),
    scale=(1.0, 1.0),
    order: int = 1,
    samp: float = 1.0,
) -> Path:
    """A PSFEx file as PSFEx writes it (PSF_DATA table, POL* and PSF* cards)."""
    k, ny, nx = basis.shape
    data = np.zeros(1, dtype=[("PSF_MASK", "f4", (k, ny, nx))])
    data["PSF_MASK"][0] = basis
    header = {
        "POLNAXIS": 2,
        "POLGRP1": 1,
        "POLNAME1": "X_IMAGE",
        "POLZERO1": zero[0],
        "POLSCAL1": scale[0],
        "POLGRP2": 1,
        "POLNAME2": "Y_IMAGE",
        "POLZERO2": zero[1],
        "POLSCAL2": scale[1],
        "POLNGRP": 1,
        "POLDEG1": order,
        "PSF_SAMP": samp,
        "PSFNAXIS": 3,
        "PSFAXIS1": nx,
        "PSFAXIS2": ny,
        "PSFAXIS3": k,
    }
    with fitsio.FITS(str(path), "rw", clobber=True) as f:
        f.write(None)
        f.write_table(data, extname="PSF_DATA", header=header)
    return path


#: The synthetic PSFEx model: Gaussian of SIGMA0 at u = 0 and SIGMA1 at u = 1,
#: u = (x - X0) / XSCALE.
SIGMA0, SIGMA1 = 1.8, 2.6
X0, XSCALE = 24.5, 3 * S


@pytest.fixture
def synthetic(tmp_path) -> Path:
    g0, g1 = _gaussian_basis(SIGMA0), _gaussian_basis(SIGMA1)
    return _write_psfex(
        tmp_path / "synthetic.psf",
        np.stack([g0, g1 - g0, np.zeros_like(g0)]),
        zero=(X0, 100.0),
        scale=(XSCALE, 100.0),
    )


# ------------------------------------------------------------------------------- library


def test_psfex_draw_agrees_with_galsim_getpsf():
    """The vectorised drawing equals DES_PSFEx.getPSF(pos).drawImage(method='no_pixel') to
    1e-6 of the peak (achieved ~2e-7: GalSim sums the basis in float32) on odd stamps, and
    on even ones that drawing on a pixel fewer moved half a pixel by lanczos15, anywhere on
    the chip (corners included)."""
    model = load_psf_model(DECAM)
    assert model.kind == PSFEX and model.sha256 == sha256_file(DECAM)
    x = np.array([1.0, 2048.0, 1024.3, 77.7, 1900.2])
    y = np.array([1.0, 4096.0, 2048.9, 3999.1, 123.4])
    for size in (47, 48):
        drawn = model.draw(x, y, size)
        assert drawn.shape == (len(x), size, size) and drawn.dtype == np.float64
        for i in range(len(x)):
            ref = _galsim_reference(x[i], y[i], size)
            assert np.abs(drawn[i] - ref).max() < 1e-6 * ref.max()
    single = model.draw(77.7, 3999.1, 48)  # scalars: a stack of one, the same bits as in a batch
    np.testing.assert_array_equal(single[0], model.draw(x, y, 48)[3])


def test_unit_sum_and_centring(synthetic):
    """Every stamp sums to 1; a symmetric model's HSM centroid is the stamp's true centre
    (GalSim's convention: between pixels for an even size) to < 0.01 px (achieved ~1e-6); the
    real model's centroid is GalSim's own drawing's."""
    model = load_psf_model(synthetic)
    for size in (47, 48, 33):
        drawn = model.draw([X0, X0 + XSCALE / 2, X0 + XSCALE], [100.0, 80.0, 130.0], size)
        np.testing.assert_allclose(drawn.sum(axis=(1, 2)), 1.0, rtol=0, atol=1e-12)
        for stamp in drawn:
            c = _hsm(stamp).moments_centroid  # 1-based, as the stamp's true centre (size + 1) / 2
            assert abs(c.x - (size + 1) / 2) < 0.01 and abs(c.y - (size + 1) / 2) < 0.01
    real = load_psf_model(DECAM)
    for x, y in ((300.0, 500.0), (1800.0, 3500.0)):
        stamp = real.draw(x, y, 48)[0]
        assert abs(stamp.sum() - 1) < 1e-12
        ours, ref = _hsm(stamp).moments_centroid, _hsm(_galsim_reference(x, y, 48)).moments_centroid
        assert abs(ours.x - ref.x) < 1e-4 and abs(ours.y - ref.y) < 1e-4
        assert abs(ours.x - 24.5) < 0.05 and abs(ours.y - 24.5) < 0.05  # the model's own asymmetry


def test_psf_size_varies_across_the_field_as_the_model_says(synthetic):
    """The synthetic model is a Gaussian of sigma 1.8 px at u = 0 and 2.6 px at u = 1: the
    measured sigma is that to 1e-5 on an odd stamp (its pixels are the basis's) and on an even
    one (drawn on a pixel fewer, moved by lanczos15: 1.3e-6; GalSim's Lanczos(3) half a pixel
    off the basis samples narrows it by 0.4 %); the real model's sigma over the chip is that
    of GalSim's drawing (to 1e-5 px) and varies by far more than that."""
    model = load_psf_model(synthetic)
    for size, rel in ((47, 1e-5), (48, 1e-5)):
        feats = measure_stamps(model.draw([X0, X0 + XSCALE / 2, X0 + XSCALE], [100.0] * 3, size))
        assert feats["adamom_sigma"][0] == pytest.approx(SIGMA0, rel=rel)
        assert feats["adamom_sigma"][2] == pytest.approx(SIGMA1, rel=rel)
        assert SIGMA0 < feats["adamom_sigma"][1] < SIGMA1
    real = load_psf_model(DECAM)
    gx, gy = np.meshgrid(np.linspace(30, 2020, 4), np.linspace(30, 4070, 4))
    sigma = measure_stamps(real.draw(gx.ravel(), gy.ravel(), S))["adamom_sigma"]
    ref = np.array(
        [_hsm(_galsim_reference(x, y, S)).moments_sigma for x, y in zip(gx.ravel(), gy.ravel())]
    )
    np.testing.assert_allclose(sigma, ref, rtol=0, atol=1e-5)
    assert np.ptp(sigma) > 0.02  # 1.79 .. 1.83 px over the chip


#: A PSFEx model fit by PSFEx to 1 500 stars of a known PSF (tests/data/make_psfex_moffat.py):
#: that PSF, pixel included.
PSFEX_FIT = Path(__file__).with_name("data") / "psfex_moffat.psf"
FIT_PROFILE = galsim.Convolve(
    galsim.Moffat(beta=3.5, fwhm=3.8).shear(g1=0.02, g2=-0.05), galsim.Pixel(1.0)
)


def _true_psf(size: int) -> np.ndarray:
    image = FIT_PROFILE.drawImage(nx=size, ny=size, scale=1.0, method="no_pixel").array
    return np.asarray(image / image.sum(), dtype=np.float64)


def test_a_psfex_fit_is_drawn_at_its_true_size_on_odd_and_even_stamps():
    """The model PSFEx fit to stars of a known PSF (sampled every 0.979 px), drawn on 47 and
    48 px at the field's centre: its adaptive-moment sigma is the true PSF's within 0.1 % and
    its g within 3e-4 (measured: 1e-5 and 1.1e-4 on both; GalSim's drawing on the even
    stamp is 1.0 % narrower)."""
    model = load_psf_model(PSFEX_FIT)
    for size in (47, 48):
        truth = measure_stamps(_true_psf(size)[None])
        drawn = measure_stamps(model.draw(1000.0, 1000.0, size))
        assert drawn["adamom_sigma"][0] == pytest.approx(truth["adamom_sigma"][0], rel=1e-3)
        for g in ("adamom_g1", "adamom_g2"):
            assert abs(drawn[g][0] - truth[g][0]) < 3e-4


def _metacal_m(stamps: dict[int, np.ndarray], psf: np.ndarray, shear: float) -> float:
    """m of stamp metacal (adaptive moments, noiseless) from the stamps at +shear and -shear."""
    e1 = {}
    for sign, stack in stamps.items():
        f = metacal_features(
            stack, psf[None], 0.01, metacal_engine="fast", psf_index=np.zeros(len(stack), int)
        )
        assert not f["flags_noshear"].any()
        r11 = (f["adamom_g1_1p"] - f["adamom_g1_1m"]) / 0.02
        e1[sign] = f["adamom_g1_noshear"].mean() / r11.mean()
    return (e1[1] - e1[-1]) / (2 * shear) - 1


def test_metacal_through_a_psfex_fit_on_even_stamps_recovers_the_shear():
    """Noiseless exponential galaxies (half-light radius 1 to 3 px, ellipticity to 0.4, four
    orientations) sheared by g1 = +-0.02 and seen through the known PSF on 48-px stamps, stamp
    metacal deconvolving the PSFEx fit drawn on the stamps: m within 4e-3 of metacal's with
    the true PSF (measured: -2.1e-3 against +1.4e-4, the fit's own error; -2.1e-2 with the
    model drawn on the even stamp as GalSim draws it)."""
    rng = np.random.default_rng(1)
    size, shear = 48, 0.02
    galaxies = [(rng.uniform(1.0, 3.0), rng.uniform(0.05, 0.4)) for _ in range(20)]
    stamps = {}
    for sign in (1, -1):
        stamps[sign] = np.array(
            [
                galsim.Convolve(
                    galsim.Exponential(half_light_radius=r)
                    .shear(e=e, beta=angle * galsim.degrees)
                    .shear(g1=sign * shear, g2=0.0),
                    FIT_PROFILE,
                )
                .drawImage(nx=size, ny=size, scale=1.0, method="no_pixel")
                .array
                for r, e in galaxies
                for angle in (0, 45, 90, 135)
            ],
            dtype=np.float64,
        )
    m_true = _metacal_m(stamps, _true_psf(size), shear)
    m_model = _metacal_m(stamps, load_psf_model(PSFEX_FIT).draw(1000.0, 1000.0, size)[0], shear)
    assert abs(m_true) < 1e-3
    assert abs(m_model - m_true) < 4e-3


def test_outside_the_fitted_area(tmp_path):
    """Positions off the stars' area are told apart; where the polynomial leaves no positive
    flux (an extrapolation), the PSF is NaN, so that its row is flagged PSF_FAILED."""
    model = load_psf_model(DECAM)
    np.testing.assert_array_equal(
        model.outside([1024.0, 5.0, 1024.0], [2048.0, 2048.0, 4090.0]), [False, True, True]
    )
    g = _gaussian_basis(2.0)
    fading = load_psf_model(
        _write_psfex(tmp_path / "fading.psf", np.stack([g, -g, 0 * g]))
    )  # flux 1 - x
    drawn = fading.draw([0.5, 2.0], [0.0, 0.0], 21)
    assert abs(drawn[0].sum() - 1) < 1e-12 and np.isnan(drawn[1]).all()
    assert measure_stamps(drawn)["flags"][1] != 0


# ------------------------------------------------------------------------------- CLI


def _exposure(tmp_path: Path, offsets: bool = True):
    """A 4x3 grid of 48-px galaxy stamps (an 'exposure' in the model's pixel frame), with a
    catalog of centres a little off the stamps' true centres."""
    rng = np.random.default_rng(3)
    big = galsim.ImageD(NX * S, NY * S, scale=1.0)
    xs, ys = [], []
    psf = galsim.Gaussian(sigma=1.8)
    for k in range(NX * NY):
        i, j = k % NX, k // NX
        b = galsim.BoundsI(i * S + 1, (i + 1) * S, j * S + 1, (j + 1) * S)
        dx, dy = rng.uniform(0.0, 0.45, 2) if offsets else (0.0, 0.0)  # the same stamp (stamps.py)
        gal = galsim.Exponential(half_light_radius=2.0 + 0.1 * k, flux=3000.0).shear(
            g1=0.1, g2=-0.05
        )
        galsim.Convolve(gal, psf).drawImage(big[b], offset=(dx, dy))
        xs.append(b.true_center.x + dx)
        ys.append(b.true_center.y + dy)
    arr = big.array + rng.normal(0.0, 1.0, big.array.shape)
    write_image(tmp_path / "exposure.fits", arr, fmt="megalut.stamps", cards={"STAMPSZ": S})
    write_catalog(
        tmp_path / "cat.fits", {"x": np.array(xs), "y": np.array(ys)}, fmt="megalut.catalog"
    )
    write_catalog(
        tmp_path / "cat0.fits",
        {"x": np.array(xs) - 1, "y": np.array(ys) - 1},
        fmt="megalut.catalog",
    )
    return np.array(xs), np.array(ys)


def _psf_grid(
    tmp_path: Path, model_path: Path, xs: np.ndarray, ys: np.ndarray, name: str = "psfgrid.fits"
) -> Path:
    """The PSF of the model at each catalog position, as a grid image like the exposure
    (float64)."""
    drawn = load_psf_model(model_path).draw(xs, ys, S)
    grid = np.zeros((NY * S, NX * S))
    for k, stamp in enumerate(drawn):
        i, j = k % NX, k // NX
        grid[j * S : (j + 1) * S, i * S : (i + 1) * S] = stamp
    write_image(tmp_path / name, grid, fmt="test")
    return tmp_path / name


def _run(runner, cli, args):
    result = runner.invoke(cli, ["measure", *map(str, args)])
    assert result.exit_code == 0, result.output + getattr(result, "stderr", "")
    return result


def test_measure_psf_model_equals_the_same_psfs_as_a_grid(runner, cli, tmp_path):
    """measure --psf-model gives bit for bit the psf_adamom_* and flags of measure --psf with a
    grid of the same PSFs (drawn by the model at the catalog's positions), from 1-based and
    0-based (--origin 0) catalogs alike, with -j 2 too; the header records the model."""
    xs, ys = _exposure(tmp_path)
    grid = _psf_grid(tmp_path, DECAM, xs, ys)
    exposure = tmp_path / "exposure.fits"
    _run(
        runner, cli, [exposure, tmp_path / "cat.fits", "-o", tmp_path / "grid.fits", "--psf", grid]
    )
    _run(
        runner,
        cli,
        [exposure, tmp_path / "cat.fits", "-o", tmp_path / "model.fits", "--psf-model", DECAM],
    )
    _run(
        runner,
        cli,
        [
            exposure,
            tmp_path / "cat0.fits",
            "-o",
            tmp_path / "model0.fits",
            "--psf-model",
            DECAM,
            "--origin",
            "0",
            "-j",
            "2",
        ],
    )
    a, b, c = (read_catalog(tmp_path / n) for n in ("grid.fits", "model.fits", "model0.fits"))
    assert (b["flags"] == 0).all()
    for col in (*PSF_COLUMNS, "flags", "adamom_g1", "adamom_sigma"):
        np.testing.assert_array_equal(np.asarray(a[col]), np.asarray(b[col]))
        np.testing.assert_array_equal(np.asarray(b[col]), np.asarray(c[col]))
    assert np.all(np.isfinite(b["psf_adamom_sigma"])) and np.ptp(b["psf_adamom_sigma"]) > 0
    assert b.meta["PSFMTYPE"] == "psfex" and b.meta["PSFMSHA"] == sha256_file(DECAM)
    assert b.meta["PSFMODEL"] == DECAM.name


def test_grid_order_uses_the_stamp_centres(runner, cli, tmp_path, synthetic):
    """Without a catalog the positions are the stamps' centres in the image: the synthetic
    model's sigma runs from 1.8 px (first column, u = 0) to 2.6 px (fourth, u = 1), to 0.5 %
    (48-px stamps: see the test above)."""
    _exposure(tmp_path, offsets=False)
    _run(
        runner,
        cli,
        [tmp_path / "exposure.fits", "-o", tmp_path / "f.fits", "--psf-model", synthetic],
    )
    t = read_catalog(tmp_path / "f.fits")
    sigma = np.asarray(t["psf_adamom_sigma"]).reshape(NY, NX)
    np.testing.assert_allclose(sigma[:, 0], SIGMA0, rtol=5e-3)
    np.testing.assert_allclose(sigma[:, -1], SIGMA1, rtol=5e-3)
    assert np.all(np.diff(sigma, axis=1) > 0)


def test_metacal_with_psf_model_equals_metacal_with_the_grid(runner, cli, tmp_path):
    """--metacal --psf-model deconvolves each stamp by the model's PSF at its position: every
    column equals --metacal --psf with the grid of those PSFs, bit for bit on an AVX-512 Xeon,
    to float32 rounding elsewhere (the operation's sums take other shapes); flags equal."""
    xs, ys = _exposure(tmp_path)
    grid = _psf_grid(tmp_path, DECAM, xs, ys)
    common = [tmp_path / "exposure.fits", tmp_path / "cat.fits", "--metacal", "--seed", "7"]
    _run(runner, cli, [*common, "-o", tmp_path / "grid.fits", "--psf", grid])
    _run(runner, cli, [*common, "-o", tmp_path / "model.fits", "--psf-model", DECAM])
    a, b = read_catalog(tmp_path / "grid.fits"), read_catalog(tmp_path / "model.fits")
    assert (
        a.colnames == b.colnames
        and "adamom_g1_1p" in b.colnames
        and "psf_adamom_sigma_noshear" in b.colnames
    )
    for col in a.colnames:
        assert_same_column(b[col], a[col], col, FLOAT32_SUMS)
    assert (b["flags_1p"] == 0).all()


def _fails(runner, cli, args, code, *words):
    result = runner.invoke(cli, ["measure", *map(str, args)])
    text = result.output + getattr(result, "stderr", "")
    assert result.exit_code == code, text
    assert "Traceback" not in text
    lines = [
        ln for ln in (getattr(result, "stderr", "") or result.output).splitlines() if ln.strip()
    ]
    assert len(lines) == 1, text
    for w in words:
        assert w in text, text
    return text


def test_errors_are_one_line_and_write_nothing(runner, cli, tmp_path, monkeypatch):
    _exposure(tmp_path)
    exposure, cat, out = tmp_path / "exposure.fits", tmp_path / "cat.fits", tmp_path / "out.fits"
    # not a PSF model: a FITS image, a text file
    _fails(
        runner,
        cli,
        [exposure, cat, "-o", out, "--psf-model", exposure],
        1,
        "exposure.fits",
        "not a PSF model",
    )
    (tmp_path / "notes.psf").write_text("not FITS\n" * 400)
    _fails(
        runner,
        cli,
        [exposure, cat, "-o", out, "--psf-model", tmp_path / "notes.psf"],
        1,
        "notes.psf",
        "not a PSF model",
    )
    # a PSFEx file GalSim refuses (PSFAXIS3 does not match the polynomial degree)
    bad = _write_psfex(tmp_path / "bad.psf", np.stack([_gaussian_basis(2.0)] * 3), order=2)
    _fails(runner, cli, [exposure, cat, "-o", out, "--psf-model", bad], 1, "bad.psf", "PSFEx")
    # --psf with --psf-model; --metacal without either; --psf-model on a star field
    _fails(
        runner,
        cli,
        [exposure, cat, "-o", out, "--psf-model", DECAM, "--psf", exposure],
        2,
        "--psf",
        "--psf-model",
    )
    _fails(runner, cli, [exposure, cat, "-o", out, "--metacal"], 2, "--psf-model")
    _fails(
        runner,
        cli,
        [exposure, "-o", out, "--psf-model", DECAM, "--stars"],
        2,
        "--psf-model",
        "star field",
    )
    # a Piff model without piff installed
    fake = tmp_path / "model.piff"
    with fitsio.FITS(str(fake), "rw", clobber=True) as f:
        f.write(None, header={"PIFF_VERSION": "1.7.0"})
        f.write_table(np.zeros(1, dtype=[("type", "S10")]), extname="psf")
    assert file_kind(fake) == PIFF
    monkeypatch.setitem(sys.modules, "piff", None)  # import piff raises ImportError
    _fails(
        runner,
        cli,
        [exposure, cat, "-o", out, "--psf-model", fake],
        1,
        "model.piff is a Piff model",
        "pip install 'megalut-cli[piff]'",
    )
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


# ------------------------------------------------------------------------------- Piff

#: The Piff model's truth: a sheared Gaussian whose sigma (arcsec) grows linearly in x, on an
#: exposure with a rotated and sheared WCS.
PIFF_WCS = galsim.JacobianWCS(0.0, 0.26, -0.25, 0.01)  # rotated by ~90 degrees, like DECam's


def _piff_truth(x: float, y: float) -> galsim.GSObject:
    return galsim.Gaussian(sigma=0.45 + 0.25 * x / 1024).shear(g1=0.06, g2=-0.03)


@pytest.fixture(scope="module")
def piff_model(tmp_path_factory) -> Path:
    """A Piff model (Gaussian, linear interpolation) fit to 30 stars drawn with GalSim (~1.5 s)."""
    import piff  # the test extra has it: a missing piff fails, not skips (docs/testing.md)

    full = galsim.ImageD(1024, 1024, wcs=PIFF_WCS)
    rng = np.random.default_rng(11)
    stars = []
    for x, y in rng.uniform(30, 994, (30, 2)):
        b = galsim.BoundsI(int(x) - 12, int(x) + 12, int(y) - 12, int(y) + 12)
        _piff_truth(x, y).withFlux(1e4).drawImage(full[b], center=(x, y))
        weight = galsim.ImageD(b, init_value=1.0, wcs=full.wcs)
        data = piff.StarData(
            full[b].copy(), galsim.PositionD(x, y), weight=weight, properties={"chipnum": 0}
        )
        stars.append(piff.Star(data, None))
    psf = piff.SimplePSF(piff.Gaussian(), piff.Polynomial(order=1), max_iter=3)
    psf.fit(stars, {0: full.wcs}, None)
    path = tmp_path_factory.mktemp("piff") / "exposure.piff"
    psf.write(str(path))
    return path


def test_piff_draw_is_the_fitted_psf(piff_model):
    """In the exposure's pixels (its rotated WCS) and at a pixel scale in sky coordinates, the
    drawn Piff PSF has the truth's moments (sigma to 0.5 %, shape to 0.005), is centred on the
    stamp's true centre and sums to 1."""
    model = load_psf_model(piff_model)
    assert model.kind == PIFF and model.native_scale(500.0, 500.0) == pytest.approx(0.26, rel=0.05)
    xs, ys = np.array([100.0, 512.0, 900.0]), np.array([800.0, 512.0, 200.0])
    for scale in (None, 0.26):
        drawn = model.draw(xs, ys, 32, pixel_scale=scale)
        np.testing.assert_allclose(drawn.sum(axis=(1, 2)), 1.0, rtol=0, atol=1e-12)
        for stamp, x, y in zip(drawn, xs, ys):
            wcs = PIFF_WCS if scale is None else galsim.PixelScale(scale)
            truth = _piff_truth(x, y).drawImage(nx=32, ny=32, wcs=wcs).array
            ours, ref = _hsm(stamp), _hsm(truth)
            assert ours.moments_sigma == pytest.approx(ref.moments_sigma, rel=5e-3)
            assert abs(ours.observed_shape.g1 - ref.observed_shape.g1) < 5e-3
            assert abs(ours.observed_shape.g2 - ref.observed_shape.g2) < 5e-3
            assert (
                abs(ours.moments_centroid.x - 16.5) < 0.01
                and abs(ours.moments_centroid.y - 16.5) < 0.01
            )
    native, sky = model.draw(512.0, 512.0, 32), model.draw(512.0, 512.0, 32, pixel_scale=0.26)
    assert (
        _hsm(native[0]).observed_shape.g1 * _hsm(sky[0]).observed_shape.g1 < 0
    )  # the WCS rotates g1's sign


def test_measure_piff_model_equals_the_same_psfs_as_a_grid(runner, cli, tmp_path, piff_model):
    xs, ys = _exposure(tmp_path)
    grid = _psf_grid(tmp_path, piff_model, xs, ys)
    common = [tmp_path / "exposure.fits", tmp_path / "cat.fits"]
    _run(runner, cli, [*common, "-o", tmp_path / "grid.fits", "--psf", grid])
    _run(runner, cli, [*common, "-o", tmp_path / "model.fits", "--psf-model", piff_model])
    a, b = read_catalog(tmp_path / "grid.fits"), read_catalog(tmp_path / "model.fits")
    for col in (*PSF_COLUMNS, "flags"):
        np.testing.assert_array_equal(np.asarray(a[col]), np.asarray(b[col]))
    assert (b["flags"] == 0).all() and b.meta["PSFMTYPE"] == "piff"
