"""Locating stamps in FITS images (grid order, 0/1-based centres) and measure_file."""

from __future__ import annotations

import galsim
import numpy as np
import pytest

from megalut_cli import flags as fl
from megalut_cli.catalog import read_catalog, read_image, write_catalog, write_image
from megalut_cli.errors import ConfigError, InputError
from megalut_cli.measure.defaults import PSF_COLUMNS
from megalut_cli.measure.measure import measure_file
from megalut_cli.measure.stamps import (
    ImageInfo,
    catalog_origins,
    check_grid,
    grid_origins,
    image_info,
    inside,
    stamp_size_of,
)

S = 32
NX, NY = 4, 3
SPECIAL = 6  # grid column 2, grid row 1


def _info(shape, header=None):
    return ImageInfo("img.fits", 0, shape, header or {})


def test_catalog_origins_true_and_nominal_centres():
    # 1-based: true centre (S+1)/2 and GalSim's nominal centre S/2+1 give the same stamp.
    x = np.array([16.5, 17.0, 16.5 + 32, 17.0 + 64])
    y = np.array([16.5, 17.0, 16.5 + 32 * 2, 17.0])
    np.testing.assert_array_equal(catalog_origins(x, y, S, 1), [[1, 1], [1, 1], [33, 65], [65, 1]])
    # 0-based (GREAT3: 48-pixel stamps with centres at 24, 72, ...).
    np.testing.assert_array_equal(
        catalog_origins(np.array([24.0, 72.0, 23.5]), np.array([24.0, 24.0, 71.5]), 48, 0),
        [[1, 1], [49, 1], [1, 49]],
    )
    # odd stamps
    np.testing.assert_array_equal(catalog_origins(np.array([3.0]), np.array([8.0]), 5, 1), [[1, 6]])
    # NaN centres never fall inside
    o = catalog_origins(np.array([np.nan]), np.array([3.0]), 5, 1)
    assert not inside(o, 5, (100, 100))[0]
    with pytest.raises(ConfigError):
        catalog_origins(x, y, S, 2)


def test_grid_order_from_lower_left():
    o = grid_origins(NY, NX, S)
    assert len(o) == NX * NY
    np.testing.assert_array_equal(o[0], [1, 1])
    np.testing.assert_array_equal(o[1], [S + 1, 1])
    np.testing.assert_array_equal(o[NX], [1, S + 1])
    np.testing.assert_array_equal(o[SPECIAL], [2 * S + 1, S + 1])


def test_inside():
    o = np.array([[1, 1], [0, 1], [97, 1], [98, 1], [1, 69], [1, 70]])
    np.testing.assert_array_equal(inside(o, S, (100, 128)), [True, False, True, False, True, False])


def test_grid_and_stamp_size_checks():
    assert check_grid(_info((96, 128)), 32) == (3, 4)
    with pytest.raises(InputError, match="does not divide"):
        check_grid(_info((96, 100)), 32)
    assert stamp_size_of(_info((96, 128), {"STAMPSZ": 32}), None) == 32
    assert stamp_size_of(_info((96, 128), {"STAMPSZ": 32}), 16) == 16
    with pytest.raises(ConfigError, match="STAMPSZ"):
        stamp_size_of(_info((96, 128)), None)
    with pytest.raises(InputError, match="STAMPSZ"):
        stamp_size_of(_info((96, 128), {"STAMPSZ": 31.5}), None)


def _grid_image(tmp_path, stampsz_card=True, noise=0.5):
    """A 4x3 grid of small round galaxies, with one big elliptical galaxy at SPECIAL."""
    big = galsim.ImageF(NX * S, NY * S, scale=1.0)
    centres = []
    for k in range(NX * NY):
        i, j = k % NX, k // NX
        b = galsim.BoundsI(i * S + 1, (i + 1) * S, j * S + 1, (j + 1) * S)
        if k == SPECIAL:
            prof = galsim.Gaussian(sigma=4.0, flux=3000.0).shear(g1=0.3, g2=0.0)
        else:
            prof = galsim.Gaussian(sigma=1.5, flux=1000.0)
        prof.drawImage(big[b], add_to_image=True)
        centres.append((b.true_center.x, b.true_center.y))
    rng = np.random.default_rng(1)
    arr = big.array + rng.normal(0.0, noise, size=big.array.shape)
    path = tmp_path / "stamps.fits"
    write_image(
        path,
        arr,
        fmt="megalut.stamps",
        cards={"STAMPSZ": S} if stampsz_card else None,
        history=["megalut simulate x.toml"],
    )
    return path, np.array(centres)


def test_grid_order_finds_the_special_stamp(tmp_path):
    path, centres = _grid_image(tmp_path)
    out = measure_file(path, None, tmp_path / "f.fits")
    assert len(out) == NX * NY
    assert np.argmax(out["adamom_sigma"]) == SPECIAL
    assert out["adamom_g1"][SPECIAL] > 0.25
    np.testing.assert_allclose(out["x"], centres[:, 0])
    np.testing.assert_allclose(out["y"], centres[:, 1])
    # centroids lie in their own stamps, in big-image coordinates
    np.testing.assert_allclose(out["adamom_x"], centres[:, 0], atol=0.2)
    np.testing.assert_allclose(out["adamom_y"], centres[:, 1], atol=0.2)
    written = read_catalog(tmp_path / "f.fits")
    assert written.meta["MLFORMAT"] == "megalut.features"
    assert written.meta["STAMPSZ"] == S
    assert written.meta["HISTORY"][0] == "megalut simulate x.toml"


@pytest.mark.parametrize("origin", [0, 1])
def test_catalog_centres_find_the_special_stamp(tmp_path, origin):
    path, centres = _grid_image(tmp_path)
    order = np.random.default_rng(0).permutation(NX * NY)
    # nominal (GalSim) centres, shifted to the catalog's convention
    xy = np.floor(centres[order]) + 1 - (1 - origin)
    cat = {
        "x": xy[:, 0],
        "y": xy[:, 1],
        "ID": order.astype(np.int64),
        "name": np.array([f"g{k}" for k in order]),
    }
    write_catalog(tmp_path / "cat.fits", cat, fmt="test", history=["made by test"])
    out = measure_file(path, tmp_path / "cat.fits", tmp_path / "f.fits", origin=origin)
    assert list(out.colnames[:4]) == ["x", "y", "ID", "name"]
    np.testing.assert_array_equal(out["ID"], order)
    assert out["ID"][np.argmax(out["adamom_sigma"])] == SPECIAL
    assert (out["flags"] == 0).all()
    np.testing.assert_allclose(out["adamom_x"], centres[order, 0], atol=0.2)
    assert read_catalog(tmp_path / "f.fits").meta["HISTORY"][0] == "made by test"


def test_wrong_origin_shifts_stamps(tmp_path):
    """0-based centres read as 1-based cut stamps one pixel lower-left.

    (True centres: GalSim's nominal 0-based centres misread as 1-based sit half a pixel
    below the true centre, which is GREAT3's own integer-centre convention and finds the
    grid stamp, see test_great3_integer_centres_find_grid_stamps.)
    """
    path, centres = _grid_image(tmp_path)
    xy = centres - 1.0  # 0-based true centres
    write_catalog(tmp_path / "cat.fits", {"x": xy[:, 0], "y": xy[:, 1]}, fmt="test")
    right = measure_file(path, tmp_path / "cat.fits", tmp_path / "a.fits", origin=0)
    wrong = measure_file(path, tmp_path / "cat.fits", tmp_path / "b.fits", origin=1)
    assert (right["flags"] == 0).all()
    first_col_or_row = (xy[:, 0] < S) | (xy[:, 1] < S)
    assert (wrong["flags"][first_col_or_row] == fl.STAMP_OFF_IMAGE).all()
    assert (wrong["flags"][~first_col_or_row] == 0).all()
    # the same galaxies, measured in big-image coordinates, on shifted stamps
    np.testing.assert_allclose(
        right["adamom_x"][~first_col_or_row], wrong["adamom_x"][~first_col_or_row], atol=1e-3
    )


def test_great3_integer_centres_find_grid_stamps():
    """GREAT3 writes x = column S + (S - 1) // 2 (23, 71, ... for S = 48), half a pixel
    below the true centre; with true and GalSim nominal centres, all give the grid stamp."""
    col = np.arange(4)
    for centre in (col * 48 + 23.0, col * 48 + 23.5, col * 48 + 24.0):
        o = catalog_origins(centre, centre[::-1], 48, 0)
        np.testing.assert_array_equal(o[:, 0], col * 48 + 1)
        np.testing.assert_array_equal(o[:, 1], col[::-1] * 48 + 1)
    # 1-based, odd stamps: half a pixel either side of the true centre 3 (S = 5)
    np.testing.assert_array_equal(
        catalog_origins(np.array([2.5, 3.5]), np.array([3.0, 3.0]), 5, 1), [[1, 1], [1, 1]]
    )
    # off the grid, the half-way rule keeps the lower candidate
    np.testing.assert_array_equal(
        catalog_origins(np.array([30.0]), np.array([30.0]), 48, 0), [[7, 7]]
    )


def test_off_image_stamps_are_flagged_not_fatal(tmp_path):
    path, centres = _grid_image(tmp_path)
    x = np.append(centres[:, 0], [2.0, np.nan, 1e6])
    y = np.append(centres[:, 1], [50.0, 10.0, 10.0])
    write_catalog(tmp_path / "cat.fits", {"x": x, "y": y}, fmt="test")
    out = measure_file(path, tmp_path / "cat.fits", tmp_path / "f.fits")
    assert (out["flags"][: NX * NY] == 0).all()
    assert (out["flags"][NX * NY :] == fl.STAMP_OFF_IMAGE).all()
    assert np.isnan(out["adamom_sigma"][NX * NY :]).all()
    assert np.isnan(out["skymad"][NX * NY :]).all()


def test_single_psf_stamp_for_all_rows(tmp_path):
    path, _ = _grid_image(tmp_path)
    psf = (
        galsim.Gaussian(sigma=2.0)
        .shear(g1=0.1, g2=-0.05)
        .drawImage(nx=25, ny=25, scale=1.0, method="no_pixel")
    )
    write_image(tmp_path / "psf.fits", psf.array, fmt="test")
    out = measure_file(path, None, tmp_path / "f.fits", psf_path=tmp_path / "psf.fits")
    for c in PSF_COLUMNS:
        assert np.all(out[c] == out[c][0])
    assert out["psf_adamom_g1"][0] == pytest.approx(0.1, abs=1e-4)
    assert out["psf_adamom_g2"][0] == pytest.approx(-0.05, abs=1e-4)
    assert out["psf_adamom_sigma"][0] == pytest.approx(2.0, rel=1e-4)


def test_star_grid_uses_the_lower_left_star(tmp_path):
    path, _ = _grid_image(tmp_path)
    field = galsim.ImageF(3 * S, 3 * S, scale=1.0)
    for k in range(9):
        i, j = k % 3, k // 3
        b = galsim.BoundsI(i * S + 1, (i + 1) * S, j * S + 1, (j + 1) * S)
        galsim.Gaussian(sigma=1.0 + 0.2 * k).drawImage(field[b], method="no_pixel")
    write_image(tmp_path / "stars.fits", field.array, fmt="test")
    out = measure_file(path, None, tmp_path / "f.fits", psf_path=tmp_path / "stars.fits")
    assert out["psf_adamom_sigma"][0] == pytest.approx(1.0, rel=1e-2)  # next star: 1.2


def test_psf_grid_per_row(tmp_path):
    path, _ = _grid_image(tmp_path)
    field = galsim.ImageF(NX * S, NY * S, scale=1.0)
    sig = 1.5 + 0.1 * np.arange(NX * NY)
    for k in range(NX * NY):
        i, j = k % NX, k // NX
        b = galsim.BoundsI(i * S + 1, (i + 1) * S, j * S + 1, (j + 1) * S)
        galsim.Gaussian(sigma=sig[k]).drawImage(field[b], method="no_pixel")
    field.array[S // 2, 3 * S + 2 :: 1] = np.nan  # breaks the PSF stamps of grid row 0, column 3
    write_image(tmp_path / "psfs.fits", field.array, fmt="test")
    out = measure_file(path, None, tmp_path / "f.fits", psf_path=tmp_path / "psfs.fits")
    good = np.arange(NX * NY) != 3
    np.testing.assert_allclose(out["psf_adamom_sigma"][good], sig[good], rtol=1e-3)
    assert out["flags"][3] == fl.PSF_FAILED
    assert np.isnan(out["psf_adamom_sigma"][3])
    assert (out["flags"][good] == 0).all()


def test_bad_psf_image_is_an_error(tmp_path):
    path, _ = _grid_image(tmp_path)
    write_image(tmp_path / "psf.fits", np.zeros((20, 20)), fmt="test")
    with pytest.raises(InputError, match="PSF"):
        measure_file(path, None, tmp_path / "f.fits", psf_path=tmp_path / "psf.fits")
    assert not (tmp_path / "f.fits").exists()


def test_catalog_errors(tmp_path):
    path, _ = _grid_image(tmp_path)
    write_catalog(tmp_path / "noxy.fits", {"ra": np.zeros(3)}, fmt="test")
    with pytest.raises(InputError, match="x, y"):
        measure_file(path, tmp_path / "noxy.fits", tmp_path / "f.fits")
    write_catalog(tmp_path / "empty.fits", {"x": np.zeros(0), "y": np.zeros(0)}, fmt="test")
    with pytest.raises(InputError, match="no rows"):
        measure_file(path, tmp_path / "empty.fits", tmp_path / "f.fits")
    assert not (tmp_path / "f.fits").exists()


def test_image_info_rejects_truncated_and_non_fits(tmp_path):
    path, _ = _grid_image(tmp_path)
    data = path.read_bytes()
    (tmp_path / "trunc.fits").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="truncated"):
        image_info(tmp_path / "trunc.fits")
    (tmp_path / "text.fits").write_text("not a FITS file\n" * 50)
    with pytest.raises(InputError, match="not a readable FITS"):
        image_info(tmp_path / "text.fits")
    write_catalog(tmp_path / "table.fits", {"x": np.zeros(2)}, fmt="test")
    with pytest.raises(InputError, match="no image"):
        image_info(tmp_path / "table.fits")


def test_nstamps_card_limits_grid_order(tmp_path):
    path, _ = _grid_image(tmp_path)
    arr = read_image(path)[0]
    write_image(
        tmp_path / "partial.fits", arr, fmt="megalut.stamps", cards={"STAMPSZ": S, "NSTAMPS": 7}
    )
    out = measure_file(tmp_path / "partial.fits", None, tmp_path / "f.fits")
    assert len(out) == 7 and np.argmax(out["adamom_sigma"]) == SPECIAL
    write_image(
        tmp_path / "bad.fits", arr, fmt="megalut.stamps", cards={"STAMPSZ": S, "NSTAMPS": 99}
    )
    with pytest.raises(InputError, match="NSTAMPS"):
        measure_file(tmp_path / "bad.fits", None, tmp_path / "g.fits")


def test_measure_image_in_memory_equals_measure_file(tmp_path):
    """The in-memory core gives the file command's features, for any number of workers."""
    import fitsio
    from sim_configs import write

    from megalut_cli.measure.features import FEATURE_COLUMNS
    from megalut_cli.measure.measure import measure_image
    from megalut_cli.sim.config import load_config
    from megalut_cli.sim.simulate import simulate

    cfg = load_config(write(tmp_path), n_cases=3, n_realizations=6)
    simulate(cfg, tmp_path / "truth.fits", stamps=tmp_path / "st.fits", seed=5)
    measure_file(tmp_path / "st.fits", None, tmp_path / "f.fits")
    on_file = read_catalog(tmp_path / "f.fits")
    image = fitsio.read(str(tmp_path / "st.fits"))
    size = cfg.structure.stamp_size
    for nproc in (1, 2):
        feats = measure_image(image, size, nproc=nproc)
        n = len(on_file)
        assert (feats["flags"][:n] == 0).sum() >= n - 2
        for col in FEATURE_COLUMNS:  # the grid has empty places after the last stamp
            assert np.array_equal(feats[col][:n], np.asarray(on_file[col]), equal_nan=True), col
    off = measure_image(image, size, origins=np.array([[1, 1], [image.shape[1], 1]]))
    assert off["flags"][1] & fl.STAMP_OFF_IMAGE and np.isnan(off["adamom_g1"][1])
    assert off["adamom_g1"][0] == on_file["adamom_g1"][0]
