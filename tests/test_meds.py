"""MEDS input of ``megalut measure`` (megalut_cli/measure/meds.py): MEDS files made here from
GalSim stamps with known shapes, noise and PSFs (the layout of esheldon/meds, without it)."""

from __future__ import annotations

from dataclasses import replace

import fitsio
import galsim
import numpy as np
import pytest
from helpers import invoke_fails
from numpy.lib import recfunctions

from megalut_cli import flags as fl
from megalut_cli.catalog import read_catalog_columns
from megalut_cli.measure.features import FEATURE_COLUMNS, measure_stamps, signal_to_noise
from megalut_cli.measure.measure import measure_image
from megalut_cli.measure.meds import (
    MAX_MASKED_FRACTION,
    MedsOptions,
    extra_columns,
    is_meds,
    measure_cutouts,
    measure_epochs,
    measure_meds,
    read_meds,
    write_meds,
)

S = 32  # box size
PSF_SIGMA = 1.5
NOISE = 2.0


def galaxy_stamps(
    n: int, seed: int = 5, size: int = S, noise: float | np.ndarray = NOISE, flux: float = 1500.0
):
    """``n`` sheared Gaussian galaxies convolved with a Gaussian PSF (float32, like stamps
    files), with Gaussian noise of ``noise`` (one value, or one per stamp); and their shears."""
    rng = np.random.default_rng(seed)
    g = rng.uniform(-0.25, 0.25, (n, 2))
    noise = np.broadcast_to(np.asarray(noise, dtype=np.float64), (n,))
    out = np.empty((n, size, size), np.float32)
    psf = galsim.Gaussian(sigma=PSF_SIGMA)
    for i in range(n):
        gal = galsim.Gaussian(sigma=2.0 + 0.5 * rng.uniform(), flux=flux).shear(
            g1=g[i, 0], g2=g[i, 1]
        )
        img = galsim.Convolve(gal, psf).drawImage(nx=size, ny=size, scale=1.0).array
        out[i] = img + rng.normal(0.0, noise[i], img.shape)
    return out, g


def psf_image(sigma: float = PSF_SIGMA, size: int = S) -> np.ndarray:
    return galsim.Gaussian(sigma=sigma).drawImage(nx=size, ny=size, scale=1.0).array


def rewrite(src, dst, *, object_data=None, rename=None, truncate=None, drop=()):
    """Copy a MEDS file with its object_data replaced, extensions renamed, cut or dropped."""
    rename, truncate = rename or {}, truncate or {}
    with fitsio.FITS(str(src)) as f, fitsio.FITS(str(dst), "rw", clobber=True) as out:
        for hdu in f[1:]:
            name = hdu.get_extname()
            if name in drop:
                continue
            data = object_data if name == "object_data" and object_data is not None else hdu.read()
            if name in truncate:
                data = data[: truncate[name]]
            out.write(data, extname=rename.get(name, name))


@pytest.fixture(scope="module")
def grid():
    """Six galaxy stamps, as a 3x2 grid image and as a MEDS file placing each cutout where
    its stamp lies in the grid (orig_row, orig_col)."""
    stamps, _ = galaxy_stamps(6)
    stamps[5] = np.float32(0.0)  # an empty stamp: HSM fails, flagged alike
    nx = 3
    image = np.zeros((2 * S, nx * S), np.float32)
    rows, cols = [], []
    for k, s in enumerate(stamps):
        r, c = divmod(k, nx)
        image[r * S : (r + 1) * S, c * S : (c + 1) * S] = s
        rows.append(r * S + (S - 1) / 2.0)
        cols.append(c * S + (S - 1) / 2.0)
    return stamps, image, np.array(rows), np.array(cols)


def test_write_read_round_trip(tmp_path):
    """Every cutout, weight, mask and PSF comes back where write_meds put it; objects keep
    their ids; a FITS image or catalog is not a MEDS file."""
    rng = np.random.default_rng(1)
    imgs = [[rng.normal(size=(S, S)) for _ in range(k)] for k in (1, 3, 0, 2)]
    imgs[3] = [rng.normal(size=(24, 24)) for _ in range(2)]  # another box size
    wts = [[np.full(c.shape, 0.25) for c in cuts] for cuts in imgs]
    bms = [[(rng.uniform(size=c.shape) < 0.1).astype(np.int32) for c in cuts] for cuts in imgs]
    psfs = [[psf_image(1.0 + 0.1 * j, 17) for j, _ in enumerate(cuts)] for cuts in imgs]
    path = tmp_path / "o.meds.fits"
    write_meds(
        path,
        imgs,
        wts,
        bms,
        psfs,
        ids=[11, 12, 13, 14],
        ra=[1.0, 2.0, 3.0, 4.0],
        dec=[-1.0, -2.0, -3.0, -4.0],
    )
    assert is_meds(path)
    meds = read_meds(path)
    assert len(meds) == 4 and meds.n_max == 3 and meds.first_is_coadd()
    assert list(meds.objects["id"]) == [11, 12, 13, 14] and list(meds.objects["ncutout"]) == [
        1,
        3,
        0,
        2,
    ]
    for i, cuts in enumerate(imgs):
        for k, img in enumerate(cuts):
            c = meds.cutout(i, k)
            np.testing.assert_array_equal(c.image, img.astype(np.float32))
            np.testing.assert_array_equal(c.weight, wts[i][k])
            np.testing.assert_array_equal(c.bmask, bms[i][k])
            np.testing.assert_array_equal(c.psf, psfs[i][k].astype(np.float32))
    with pytest.raises(IndexError):
        meds.cutout(2, 0)
    stack = meds.stamps([0, 1], 0)  # one read per run of nearby cutouts, in the order asked
    np.testing.assert_array_equal(stack.images[1], imgs[1][0].astype(np.float32))
    image, catalog = tmp_path / "i.fits", tmp_path / "c.fits"
    fitsio.write(str(image), np.zeros((8, 8)))
    fitsio.write(str(catalog), np.zeros(3, dtype=[("x", "f8")]))
    assert not is_meds(image) and not is_meds(catalog) and not is_meds(tmp_path / "missing.fits")


def test_features_equal_the_grid_path(grid, tmp_path):
    """Without weights or masks, a MEDS file measures exactly as the same stamps in a grid
    image (every feature, morphology and flag, centroids in the image's pixels); with weight
    maps only snr changes, to Eq. 10 with the weight-map noise."""
    stamps, image, rows, cols = grid
    ref = measure_image(image, S)
    path = tmp_path / "g.meds.fits"
    write_meds(path, stamps, orig_rows=rows, orig_cols=cols, ids=np.arange(100, 106))
    out = measure_meds(read_meds(path), MedsOptions(morphology=True))
    ref_morph = measure_image(image, S, morphology=True)
    for c in FEATURE_COLUMNS + ("morph_conc", "morph_conc_inner", "morph_size_ratio"):
        np.testing.assert_array_equal(out[c], ref_morph[c], err_msg=c)
    assert list(out["flags"]) == [0] * 5 + [fl.HSM_FAILED]
    assert list(out["id"]) == list(range(100, 106)) and list(out["number"]) == list(range(1, 7))
    np.testing.assert_array_equal(out["n_masked"], 0)
    assert "noise_weight" not in out

    path_w = tmp_path / "w.meds.fits"
    write_meds(
        path_w, stamps, weights=np.full(stamps.shape, 1 / 3.0**2), orig_rows=rows, orig_cols=cols
    )
    out_w = measure_meds(read_meds(path_w))
    for c in FEATURE_COLUMNS:
        if c != "snr":
            np.testing.assert_array_equal(out_w[c], ref[c], err_msg=c)
    np.testing.assert_allclose(out_w["noise_weight"], 3.0, rtol=1e-6)
    good = out_w["flags"] == 0
    expected = signal_to_noise(ref["adamom_flux"], ref["adamom_sigma"], np.full(6, 3.0))
    np.testing.assert_allclose(out_w["snr"][good], expected[good], rtol=1e-6)
    assert not np.allclose(out_w["snr"][good], ref["snr"][good], rtol=1e-3)


def test_weight_noise_recovers_the_simulated_sigma(tmp_path):
    """Noise varying from object to object (sigma 1 to 4) and within each stamp (weights with
    a 20 % scatter, pixel noise drawn from them): noise_weight recovers each object's sigma
    within 3 %, better than the edge-pixel skymad beside it."""
    rng = np.random.default_rng(7)
    n = 12
    sigma = np.linspace(1.0, 4.0, n)
    clean, _ = galaxy_stamps(n, noise=0.0)
    weights = (1.0 / sigma[:, None, None] ** 2) * rng.uniform(0.8, 1.2, (n, S, S))
    images = clean + rng.normal(size=(n, S, S)) / np.sqrt(weights)
    path = tmp_path / "n.meds.fits"
    write_meds(path, images, weights=weights)
    out = measure_meds(read_meds(path))
    # the median weight of a uniform 0.8..1.2 scatter is the mean: 1/sqrt recovers sigma
    np.testing.assert_allclose(out["noise_weight"], sigma, rtol=0.03)
    err_w = np.abs(out["noise_weight"] / sigma - 1)
    err_mad = np.abs(out["skymad"] / sigma - 1)
    assert err_w.mean() < err_mad.mean()
    assert np.all(out["flags"] == 0)


def test_masked_cosmic_ray_is_left_out_of_the_moments(tmp_path):
    """A bright cosmic-ray pixel 5 pixels from the centre biases the moments; flagged in the
    bad mask, the stamp gives the clean stamp's moments within a small tolerance (GalSim's
    badpix: the fast engine, the GalSim engine and FindAdaptiveMom(badpix=...) agree)."""
    clean, _ = galaxy_stamps(3, seed=11)
    hit = clean.copy()
    hit[:, 16 + 5, 16] += 200.0  # 100 sigma; brighter ones make HSM fail outright
    bmask = np.zeros(clean.shape, np.int32)
    bmask[:, 16 + 5, 16] = 1
    ref = measure_cutouts(clean)
    raw = measure_cutouts(hit)
    fast = measure_cutouts(hit, bmasks=bmask)
    gs = measure_cutouts(hit, bmasks=bmask, engine="galsim")
    assert np.all(fast["flags"] == 0) and np.all(fast["n_masked"] == 1)
    for c in ("adamom_g1", "adamom_g2", "adamom_sigma"):
        np.testing.assert_allclose(fast[c], gs[c], rtol=0, atol=1e-12)
    assert np.all(raw["flags"] == 0)  # measured, but biased
    d_masked = np.hypot(fast["adamom_g1"] - ref["adamom_g1"], fast["adamom_g2"] - ref["adamom_g2"])
    d_raw = np.hypot(raw["adamom_g1"] - ref["adamom_g1"], raw["adamom_g2"] - ref["adamom_g2"])
    # masked: the pixel's galaxy light is lost too (0.006 here); unmasked: 0.18 to 0.19
    assert np.all(d_masked < 0.01) and np.all(d_raw > 0.1), (d_masked, d_raw)
    assert np.all(np.abs(fast["adamom_sigma"] / ref["adamom_sigma"] - 1) < 0.01)
    assert np.all(np.abs(raw["adamom_sigma"] / ref["adamom_sigma"] - 1) > 0.02)
    res = galsim.hsm.FindAdaptiveMom(
        galsim.ImageD(hit[0].astype(np.float64)), badpix=galsim.ImageI(bmask[0]), guess_sig=4.0
    )
    assert fast["adamom_sigma"][0] == pytest.approx(res.moments_sigma, abs=1e-9)
    assert fast["adamom_g1"][0] == pytest.approx(res.observed_shape.g1, abs=1e-9)


def test_too_many_or_central_masked_pixels_are_flagged():
    """A stamp masked over more than MAX_MASKED_FRACTION, or next to its centre, gets
    MASKED_PIXELS and NaN features; a masked strip along one edge does not, and its skymad
    comes from the other edge pixels."""
    stamps, _ = galaxy_stamps(4, seed=3)
    bm = np.zeros(stamps.shape, np.int32)
    bm[0, : int(S * (MAX_MASKED_FRACTION + 0.05)) + 1, :] = 4  # > 25 % of the rows
    bm[1, 16, 17] = 1  # 1.6 pixels from the centre (15.5, 15.5)
    bm[2, :, :3] = 2  # a strip along the left edge: about 9 %
    weights = np.full(stamps.shape, 0.25)
    weights[3, 16, 15] = 0.0  # zero weight next to the centre masks too
    out = measure_cutouts(stamps, weights=weights, bmasks=bm)
    assert [bool(f & fl.MASKED_PIXELS) for f in out["flags"]] == [True, True, False, True]
    assert np.isnan(out["adamom_g1"][[0, 1, 3]]).all() and np.isfinite(out["adamom_g1"][2])
    assert np.isfinite(out["skymad"]).all()  # kept on flagged stamps (the sky, not the source)
    assert list(out["n_masked"]) == [int((bm[0] != 0).sum()), 1, 3 * S, 1]
    edges = stamps[2].astype(np.float64).copy()
    edges[:, :3] = np.nan
    kept = np.concatenate([edges[0, 3:], edges[-1, 3:], edges[1:-1, -1]])
    assert out["skymad"][2] == pytest.approx(
        1.4826 * np.median(np.abs(kept - np.median(kept))), rel=1e-12
    )
    assert fl.explain(fl.MASKED_PIXELS | fl.NO_CUTOUT) == ["NO_CUTOUT", "MASKED_PIXELS"]


def test_objects_without_the_cutout_are_flagged(tmp_path):
    """One row per object in file order, ids passed through; an object without the cutout
    measured gets NO_CUTOUT, NaN features and n_masked -1; --cutout 1 measures the second
    cutout of each object (its own pixels, not the coadd's)."""
    stamps, _ = galaxy_stamps(4, seed=2)
    epoch, _ = galaxy_stamps(4, seed=9)
    cuts = [[stamps[0], epoch[0]], [stamps[1]], [], [stamps[3], epoch[3]]]
    path = tmp_path / "e.meds.fits"
    write_meds(path, cuts, ids=[7, 8, 9, 10])
    meds = read_meds(path)
    out = measure_meds(meds)
    assert list(out["id"]) == [7, 8, 9, 10] and list(out["ncutout"]) == [2, 1, 0, 2]
    assert list(out["flags"]) == [0, 0, fl.NO_CUTOUT, 0] and list(out["n_masked"]) == [0, 0, -1, 0]
    assert np.isnan(out["adamom_sigma"][2]) and np.isnan(out["orig_row"][2])
    one = measure_meds(meds, MedsOptions(cutout=1))
    assert list(one["flags"]) == [0, fl.NO_CUTOUT, fl.NO_CUTOUT, 0]
    direct = measure_stamps(epoch[[0, 3]].astype(np.float64))
    np.testing.assert_array_equal(one["adamom_g1"][[0, 3]], direct["adamom_g1"])


def test_psf_cutouts_give_psf_features(tmp_path):
    """Per-object PSF cutouts (here of different sizes) give each object its own
    psf_adamom_sigma: the HSM size of a pixelated Gaussian, sqrt(sigma^2 + 1/12) to 1 %;
    the meds package's psf extension name and psf_box_size column work alike."""
    stamps, _ = galaxy_stamps(4, seed=4)
    sig = np.array([1.2, 1.6, 2.0, 2.4])
    psfs = [[psf_image(s, 25 if i % 2 else 33)] for i, s in enumerate(sig)]
    path = tmp_path / "p.meds.fits"
    write_meds(path, stamps, psfs=psfs)
    out = measure_meds(read_meds(path))
    np.testing.assert_allclose(out["psf_adamom_sigma"], np.sqrt(sig**2 + 1 / 12), rtol=0.01)
    np.testing.assert_allclose(out["psf_adamom_g1"], 0.0, atol=1e-6)
    assert np.all(out["flags"] == 0)
    # another writer's layout: a 'psf_cutouts' extension and only psf_box_size
    with fitsio.FITS(str(path)) as f:
        od = f["object_data"].read()
    od = recfunctions.drop_fields(od, ["psf_row_size", "psf_col_size"], usemask=False)
    other = tmp_path / "q.meds.fits"
    rewrite(path, other, object_data=od, rename={"psf": "psf_cutouts"})
    out2 = measure_meds(read_meds(other))
    np.testing.assert_array_equal(out2["psf_adamom_sigma"], out["psf_adamom_sigma"])


class FakePsfModel:
    """A PSF model whose Gaussian size grows with x (the API of measure/psf_model.py)."""

    def __init__(self) -> None:
        self.calls: list[tuple[np.ndarray, np.ndarray, int]] = []

    @staticmethod
    def sigma(x: np.ndarray) -> np.ndarray:
        return 1.2 + 0.01 * np.asarray(x)

    def draw(self, x, y, size, pixel_scale=None):
        self.calls.append((np.asarray(x), np.asarray(y), size))
        return np.stack([psf_image(s, size) for s in self.sigma(x)])


def test_psf_model_at_each_objects_position(grid, tmp_path):
    """A PSF model is drawn at each object's (orig_col + 1, orig_row + 1) and gives its
    psf_adamom_sigma; the file's PSF cutouts are then not used."""
    stamps, _, rows, cols = grid
    path = tmp_path / "m.meds.fits"
    write_meds(path, stamps, psfs=[[psf_image(3.0)]] * 6, orig_rows=rows, orig_cols=cols)
    model = FakePsfModel()
    out = measure_meds(read_meds(path), psf_model=model)
    x = np.concatenate([c[0] for c in model.calls])
    y = np.concatenate([c[1] for c in model.calls])
    np.testing.assert_array_equal(np.sort(x), np.sort(cols + 1))
    np.testing.assert_array_equal(np.sort(y), np.sort(rows + 1))
    np.testing.assert_allclose(
        out["psf_adamom_sigma"], np.sqrt(model.sigma(cols + 1) ** 2 + 1 / 12), rtol=0.01
    )


def test_epochs_are_each_cutout_measured_with_one_setup(tmp_path, monkeypatch):
    """measure_epochs gives, row for row, what measure_meds gives for each single-epoch cutout
    (the same features and metacal versions, with the fixnoise of each object and cutout), in
    object then cutout order; the single PSF is read and measured once per box size and the
    work units of every epoch run together (one executor)."""
    from megalut_cli.measure import meds as meds_module

    stamps, _ = galaxy_stamps(5, seed=3)
    epoch, _ = galaxy_stamps(5, seed=4)
    later, _ = galaxy_stamps(5, seed=5)
    cuts = [[stamps[0], epoch[0], later[0]], [stamps[1], epoch[1]], [stamps[2]]]
    cuts += [[stamps[3], epoch[3], later[3]], [stamps[4], epoch[4]]]
    path = tmp_path / "ep.meds.fits"
    write_meds(path, cuts, weights=[[np.full((S, S), 1 / NOISE**2)] * len(c) for c in cuts])
    psf_file = tmp_path / "psf.fits"
    fitsio.write(str(psf_file), psf_image(PSF_SIGMA, S))
    meds = read_meds(path)
    options = MedsOptions(metacal=True, seed=3, psf_path=psf_file)
    calls = {"single_psf_features": 0, "measure_units": 0}

    def counted(name):
        function = getattr(meds_module, name)

        def call(*args, **kwargs):
            calls[name] += 1
            return function(*args, **kwargs)

        return call

    for name in calls:
        monkeypatch.setattr(meds_module, name, counted(name))
    out = measure_epochs(meds, options, nproc=2)
    assert calls == {"single_psf_features": 1, "measure_units": 1}
    assert list(out["id"]) == [1, 1, 2, 4, 4, 5] and list(out["cutout"]) == [1, 2, 1, 1, 2, 1]
    # the same work units (-j 2): metacal's FFTs of one batch are not bit for bit another's
    each = {k: measure_meds(meds, replace(options, cutout=k), nproc=2) for k in (1, 2)}
    for i, (row, k) in enumerate(zip(out["id"] - 1, out["cutout"])):
        for c in ("adamom_g1", "adamom_sigma_1p", "adamom_g2_2m", "flags_noshear", "n_masked"):
            assert each[k][c][row] == out[c][i], (c, row, k)
    assert out["adamom_g1_1p"][0] != out["adamom_g1_1p"][1]  # each cutout its own pixels


def test_metacal_on_meds(tmp_path):
    """--metacal on MEDS adds the X_noshear ... X_2m columns with the per-object PSF cutouts;
    they respond to the applied shear (g1_1p > g1_1m); the same PSF given once (--psf)
    gives the same columns; PSF cutouts of the other parity are redrawn to the stamps'
    parity, a single --psf of the other parity is refused."""
    stamps, _ = galaxy_stamps(3, seed=6)
    psf = psf_image(PSF_SIGMA, 32)
    path = tmp_path / "mc.meds.fits"
    write_meds(path, stamps, weights=np.full(stamps.shape, 1 / NOISE**2), psfs=[[psf]] * 3)
    psf_file = tmp_path / "psf.fits"
    fitsio.write(str(psf_file), psf)
    meds = read_meds(path)
    out = measure_meds(meds, MedsOptions(metacal=True, seed=3))
    for kind in ("noshear", "1p", "1m", "2p", "2m"):
        assert np.isfinite(out[f"adamom_g1_{kind}"]).all() and np.all(out[f"flags_{kind}"] == 0)
        assert np.isfinite(out[f"psf_adamom_sigma_{kind}"]).all()
    assert np.all(out["adamom_g1_1p"] > out["adamom_g1_1m"]) and np.all(
        out["adamom_g2_2p"] > out["adamom_g2_2m"]
    )
    single = measure_meds(meds, MedsOptions(metacal=True, seed=3, psf_path=psf_file))
    for c in ("adamom_g1_1p", "adamom_sigma_noshear", "psf_adamom_sigma_2m", "psf_adamom_sigma"):
        np.testing.assert_allclose(single[c], out[c], rtol=1e-6, err_msg=c)
    path_odd = tmp_path / "mc33.meds.fits"  # odd PSF cutouts for even boxes (as DES's)
    write_meds(
        path_odd,
        stamps,
        weights=np.full(stamps.shape, 1 / NOISE**2),
        psfs=[[psf_image(PSF_SIGMA, 33)]] * 3,
    )
    odd = measure_meds(read_meds(path_odd), MedsOptions(metacal=True, seed=3))
    for c in (
        "adamom_g1_1p",
        "adamom_g2_2m",
        "adamom_g1_noshear",
    ):  # 7e-6 here; the response is 0.013
        np.testing.assert_allclose(odd[c], out[c], rtol=0, atol=2e-5, err_msg=c)
    np.testing.assert_allclose(odd["adamom_sigma_noshear"], out["adamom_sigma_noshear"], rtol=5e-5)
    odd_file = tmp_path / "odd.fits"
    fitsio.write(str(odd_file), psf_image(PSF_SIGMA, 33))
    from megalut_cli.errors import InputError

    with pytest.raises(InputError, match="parity"):
        measure_meds(meds, MedsOptions(metacal=True, psf_path=odd_file))


def test_cli_contract(runner, cli, grid, tmp_path):
    """`megalut measure X.meds.fits -o F.fits` writes one row per object with its cards; a
    catalog or --stamp-size with a MEDS file is a usage error (2), a truncated file or an
    even PSF for odd cutouts with --metacal a runtime error (1): one line, nothing written;
    --cutout on an image of stamps is a usage error; no overwrite without --overwrite."""
    stamps, image, rows, cols = grid
    meds, out = tmp_path / "o.meds.fits", tmp_path / "f.fits"
    write_meds(meds, stamps, weights=np.full(stamps.shape, 0.25), orig_rows=rows, orig_cols=cols)
    result = runner.invoke(cli, ["measure", str(meds), "-o", str(out)])
    assert result.exit_code == 0, result.output
    table, header = read_catalog_columns(out)
    assert len(table["id"]) == 6 and header["MEDSCUT"] == 0 and header["MEDSCOAD"] is True
    assert header["MLFORMAT"] == "megalut.features" and header["STAMPSZ"] == S
    assert "cutout 0 (the coadd) of each of 6 objects" in (
        result.stderr if hasattr(result, "stderr") else result.output
    )
    invoke_fails(runner, cli, ["measure", str(meds), "-o", str(out)], 1, "--overwrite")
    retried = tmp_path / "r.fits"  # the moments' retry reaches the MEDS route: same rows here
    result = runner.invoke(
        cli, ["measure", str(meds), "-o", str(retried), "--moments-retry", "0.5"]
    )
    assert result.exit_code == 0, result.output
    again, cards = read_catalog_columns(retried)
    assert cards["HSMRETRY"] == 0.5 and "HSMRETRY" not in header
    np.testing.assert_array_equal(again["adamom_g1"], table["adamom_g1"])

    bad = tmp_path / "bad.fits"
    cat = tmp_path / "cat.fits"
    fitsio.write(str(cat), np.zeros(2, dtype=[("x", "f8"), ("y", "f8")]))
    invoke_fails(
        runner, cli, ["measure", str(meds), str(cat), "-o", str(bad)], 2, "MEDS", "no catalog"
    )
    invoke_fails(
        runner, cli, ["measure", str(meds), "-o", str(bad), "--stamp-size", "32"], 2, "--stamp-size"
    )
    trunc = tmp_path / "t.meds.fits"
    rewrite(meds, trunc, truncate={"image_cutouts": 5 * S * S + 10})
    invoke_fails(runner, cli, ["measure", str(trunc), "-o", str(bad)], 1, "truncated MEDS")
    even = tmp_path / "even.fits"
    fitsio.write(str(even), psf_image(PSF_SIGMA, 32) + 0 * np.zeros(1))
    odd_meds = tmp_path / "odd.meds.fits"
    write_meds(odd_meds, [s[:31, :31] for s in stamps])
    invoke_fails(
        runner,
        cli,
        ["measure", str(odd_meds), "-o", str(bad), "--psf", str(even), "--metacal"],
        1,
        "parity",
    )
    grid_image = tmp_path / "stamps.fits"
    fitsio.write(str(grid_image), image, header={"STAMPSZ": S})
    invoke_fails(
        runner,
        cli,
        ["measure", str(grid_image), "-o", str(bad), "--cutout", "1"],
        2,
        "--cutout",
        "MEDS",
    )
    assert not bad.exists() and not list(tmp_path.glob(".bad.fits*"))


def test_a_masked_pixel_near_the_object_flags_near_mask(runner, cli, tmp_path):
    """``--mask-margin`` (default 10) on MEDS input: an object with a masked pixel of its
    cutout within 10 px is flagged NEAR_MASK with NaN features (every metacal version too),
    ``mask_dist`` holds the distance (inf without masked pixels); ``--mask-margin 0`` flags
    nothing and writes no ``mask_dist``."""
    stamps, _ = galaxy_stamps(3, seed=7)
    bmask = np.zeros(stamps.shape, np.int32)
    bmask[0, :, 16 + 6] = 1  # a bad column 6 px from the centre (16, 16): flagged
    bmask[1, :, 16 + 13] = 1  # 13 px: measured
    meds = tmp_path / "m.meds.fits"
    write_meds(meds, stamps, bmasks=bmask, psfs=np.stack([psf_image()] * 3))
    out, off = tmp_path / "f.fits", tmp_path / "off.fits"
    result = runner.invoke(cli, ["measure", str(meds), "-o", str(out), "--metacal"])
    assert result.exit_code == 0, result.output
    table, header = read_catalog_columns(out)
    assert header["MASKMRGN"] == 10.0
    np.testing.assert_allclose(table["mask_dist"][:2], [6.0, 13.0], atol=0.75)
    assert np.isinf(table["mask_dist"][2])
    assert table["flags"][0] & fl.NEAR_MASK and table["flags"][1] == 0 == table["flags"][2]
    assert table["flags_1p"][0] & fl.NEAR_MASK and np.isnan(table["adamom_g1_1p"][0])
    assert np.isfinite(table["adamom_g1_1p"][1:]).all()
    args = ["measure", str(meds), "-o", str(off), "--metacal", "--mask-margin", "0"]
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    again, header = read_catalog_columns(off)
    assert "mask_dist" not in again and header["MASKMRGN"] == 0.0
    assert (again["flags"] == 0).all()
    # the other objects as before (to the float32 sums of a metacal block of other size)
    np.testing.assert_allclose(again["adamom_g1_1p"][1:], table["adamom_g1_1p"][1:], atol=1e-6)


def test_meds_with_a_psfex_model_end_to_end(runner, cli, grid, tmp_path):
    """`megalut measure X.meds.fits --psf-model DECam.psf [--metacal]`: each object's
    psf_adamom_* are those of the real DECam PSFEx model drawn at (orig_col + 1,
    orig_row + 1) (tests/data, from GalSim's repository), and the header records the model."""
    from pathlib import Path

    from megalut_cli.measure.psf_model import load_psf_model

    decam = Path(__file__).with_name("data") / "DECam_00154912_12_psfcat.psf"
    stamps, _, _, _ = grid
    model = load_psf_model(decam)
    x0, x1, y0, y1 = model.bounds
    rows = np.linspace(y0 + 50, y1 - 50, 6) - 1  # spread over the chip, 0-based
    cols = np.linspace(x0 + 50, x1 - 50, 6)[::-1] - 1
    meds, out = tmp_path / "d.meds.fits", tmp_path / "f.fits"
    write_meds(meds, stamps[:5], orig_rows=rows[:5], orig_cols=cols[:5])
    result = runner.invoke(
        cli, ["measure", str(meds), "-o", str(out), "--psf-model", str(decam), "--metacal"]
    )
    assert result.exit_code == 0, result.output
    table, header = read_catalog_columns(out)
    ref = measure_stamps(model.draw(cols[:5] + 1, rows[:5] + 1, S))
    for c in ("adamom_g1", "adamom_g2", "adamom_sigma"):
        np.testing.assert_array_equal(table[f"psf_{c}"], ref[c])
    assert np.ptp(table["psf_adamom_sigma"]) > 0.01  # the PSF varies over the chip
    assert header["PSFMODEL"] == decam.name and header["PSFMTYPE"] == "psfex"
    assert np.isfinite(table["adamom_g1_noshear"]).all() and np.all(table["flags_noshear"] == 0)


def test_extra_object_columns_are_passed_through(tmp_path):
    """Scalar object_data columns outside the MEDS layout (a simulation's truth) reach the
    output."""
    rng = np.random.default_rng(5)
    images = rng.normal(0.0, 1.0, (6, 24, 24))
    truth = {"tru_g1": np.linspace(-0.05, 0.05, 6), "case": np.arange(6, dtype=np.int32)}
    path = write_meds(tmp_path / "x.meds.fits", images, extra=truth)
    assert extra_columns(read_meds(path)) == ["tru_g1", "case"]
    out = measure_meds(read_meds(path))
    np.testing.assert_array_equal(out["tru_g1"], truth["tru_g1"])
    np.testing.assert_array_equal(out["case"], truth["case"])
    with pytest.raises(ValueError, match="outside the MEDS layout"):
        write_meds(tmp_path / "y.meds.fits", images, extra={"box_size": np.ones(6)})


def test_your_data_example_makes_a_meds_file_measure_reads(runner, cli, tmp_path):
    """examples/your-data: make_meds.py turns a simulated grid into a MEDS file whose PSF
    cutouts measure as the config's Moffat, whose weight maps give its noise, and whose truth
    reaches the features catalog (what `evaluate` needs)."""
    import subprocess
    import sys
    from pathlib import Path

    example = Path(__file__).resolve().parents[1] / "examples" / "your-data"
    truth, stamps, meds, out = (tmp_path / n for n in ("t.fits", "s.fits", "m.fits", "f.fits"))
    r = runner.invoke(
        cli,
        [
            "simulate",
            str(example / "survey.toml"),
            "-o",
            str(truth),
            "--stamps",
            str(stamps),
            "--n-cases",
            "2",
            "--n-realizations",
            "50",
            "--seed",
            "15",
        ],
    )
    assert r.exit_code == 0, r.output
    subprocess.run(
        [
            sys.executable,
            str(example / "make_meds.py"),
            str(stamps),
            str(truth),
            str(example / "survey.toml"),
            "-o",
            str(meds),
        ],
        check=True,
        capture_output=True,
    )
    r = runner.invoke(cli, ["measure", str(meds), "-o", str(out)])
    assert r.exit_code == 0, r.output
    table, _ = read_catalog_columns(out)
    sim, _ = read_catalog_columns(truth)
    np.testing.assert_array_equal(table["tru_g1"], sim["tru_g1"])
    np.testing.assert_array_equal(table["case"], sim["case"])
    moffat = (
        galsim.Moffat(beta=3.0, fwhm=5.0)
        .shear(g1=0.01, g2=-0.02)
        .drawImage(nx=48, ny=48, scale=1.0)
    )
    expected = galsim.hsm.FindAdaptiveMom(moffat).moments_sigma
    np.testing.assert_allclose(table["psf_adamom_sigma"], expected, rtol=1e-5)
    np.testing.assert_allclose(table["noise_weight"], 2.0, rtol=1e-6)
    assert np.all(table["n_masked"] >= 0) and table["n_masked"].sum() == 2  # 2 % of 100 objects


def test_incomplete_files_a_wrong_box_size_and_an_all_flagged_file(
    runner, cli, grid, tmp_path, caplog
):
    """A MEDS file missing either extension is named an incomplete MEDS file (not an image); a
    box_size that runs into the next cutout is refused; an all-flagged MEDS file's warning
    names what may be wrong with a MEDS file, not --stamp-size or --origin."""
    stamps = grid[0]
    meds, bad = tmp_path / "o.meds.fits", tmp_path / "bad.fits"
    write_meds(meds, stamps)
    for ext in ("image_cutouts", "object_data"):
        partial = tmp_path / f"no-{ext}.meds.fits"
        rewrite(meds, partial, drop=(ext,))
        invoke_fails(
            runner, cli, ["measure", str(partial), "-o", str(bad)], 1, "incomplete MEDS", ext
        )
    with fitsio.FITS(str(meds)) as f:
        od = f["object_data"].read()
    od["box_size"][2] = S + 2
    wrong = tmp_path / "box.meds.fits"
    rewrite(meds, wrong, object_data=od)
    invoke_fails(runner, cli, ["measure", str(wrong), "-o", str(bad)], 1, "box_size disagrees")
    assert not bad.exists()

    empty = tmp_path / "empty.meds.fits"
    write_meds(empty, np.zeros_like(stamps))
    with caplog.at_level("WARNING"):
        result = runner.invoke(cli, ["measure", str(empty), "-o", str(tmp_path / "e.fits")])
    assert result.exit_code == 0, result.output
    text = result.output + caplog.text
    assert "6 of 6 stamps flagged" in text and "--cutout" in text
    assert "--stamp-size" not in text and "--origin" not in text


def test_info_validates_a_meds_file(runner, cli, tmp_path):
    """``megalut info`` on a MEDS file: objects, cutouts, maps, PSF sizes and what the
    Jacobians say (turned, flipped); an incomplete one is refused with one line (exit 1)."""
    stamps, _ = galaxy_stamps(4)
    turn = 0.2 * np.array([[0.0, -1.0], [1.0, 0.0]])
    flip = 0.2 * np.diag([1.0, -1.0])
    path = tmp_path / "j.meds.fits"
    write_meds(
        path,
        [[s, s] for s in stamps],
        weights=[[np.ones_like(s)] * 2 for s in stamps],
        psfs=[[psf_image(), psf_image()]] * 4,
        jacobians=[[0.2 * np.eye(2), turn], [0.2 * np.eye(2), flip]] * 2,
        extra={"tru_g1": np.zeros(4)},
    )
    result = runner.invoke(cli, ["info", str(path)])
    assert result.exit_code == 0, result.output
    out = result.output
    assert "4 objects, 8 cutouts" in out and "cutout 0: the coadd" in out
    assert "maps: weight, psf; PSF cutouts 32x32" in out
    assert "8 of 8 cutouts with a usable Jacobian" in out and "2 turned, 2 flipped" in out
    assert "passed through by measure: tru_g1" in out
    bad = tmp_path / "half.fits"
    fitsio.write(str(bad), np.zeros(3, dtype=[("id", "i8")]), extname="object_data")
    invoke_fails(runner, cli, ["info", str(bad)], 1, "incomplete MEDS file")


def test_meds_and_info_read_stdin(runner, cli, tmp_path):
    """A MEDS file piped into ``measure -`` and ``info -`` is read as from a file; STAMPS and
    CATALOG cannot both be stdin."""
    stamps, _ = galaxy_stamps(3)
    path = tmp_path / "s.meds.fits"
    write_meds(path, stamps, weights=np.ones_like(stamps))
    data = path.read_bytes()
    info = runner.invoke(cli, ["info", "-"], input=data)
    assert info.exit_code == 0, info.output
    assert info.output.startswith("stdin: MEDS cutout file, 3 objects")
    measured = runner.invoke(cli, ["measure", "-", "-o", "-"], input=data)
    assert measured.exit_code == 0, measured.output
    direct = tmp_path / "f.fits"
    assert runner.invoke(cli, ["measure", str(path), "-o", str(direct)]).exit_code == 0
    piped = tmp_path / "p.fits"
    piped.write_bytes(measured.stdout_bytes)
    a, _ = read_catalog_columns(piped)
    b, _ = read_catalog_columns(direct)
    np.testing.assert_array_equal(a["adamom_g1"], b["adamom_g1"])
    invoke_fails(runner, cli, ["measure", "-", "-", "-o", str(tmp_path / "x.fits")], 2, "stdin")
