"""The batched stamp cut (one compiled call per band of rows) against the per-stamp slicing
it replaces, its pixel checks against ``np.isfinite`` and ``sky_mad``, and the Table-free
catalog path of ``measure``."""

from __future__ import annotations

import fitsio
import numpy as np
import pytest

from megalut_cli.catalog import read_catalog, read_catalog_columns, write_catalog
from megalut_cli.measure.features import (
    default_guess_sigma,
    default_max_shift,
    features_from_moments,
    measure_stamps,
    sky_mad,
)
from megalut_cli.measure.measure import measure_file, measure_file_columns
from megalut_cli.measure.stamps import (
    cut_and_measure,
    cut_stamps,
    cut_stamps_checked,
    grid_origins,
    image_info,
    pixel_rows,
    read_band,
    read_rows,
)


def _per_stamp_cut(rows: np.ndarray, row0: int, origins: np.ndarray, size: int) -> np.ndarray:
    """The cut as it was: one numpy slice per stamp, into float64."""
    out = np.empty((len(origins), size, size), dtype=np.float64)
    for i, (ox, oy) in enumerate(origins):
        y, x = int(oy) - 1 - row0, int(ox) - 1
        out[i] = rows[y : y + size, x : x + size]
    return out


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Same dtype, shape and bytes (NaN payloads and the sign of zero included)."""
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def _same_values(a: np.ndarray, b: np.ndarray) -> bool:
    """:func:`_same`, except that NaNs match whatever their payload (cfitsio's reads give
    NaN pixels its own)."""
    a, b = np.asarray(a), np.asarray(b)
    nan_a, nan_b = np.isnan(a), np.isnan(b)
    return (
        a.dtype == b.dtype
        and (nan_a == nan_b).all()
        and _same(np.where(nan_a, 0, a).astype(a.dtype), np.where(nan_b, 0, b).astype(b.dtype))
    )


def _random_origins(
    rng: np.random.Generator, n: int, size: int, shape: tuple[int, int], row0: int
) -> np.ndarray:
    x = rng.integers(1, shape[1] - size + 2, n)
    y = rng.integers(1, shape[0] - size + 2, n) + row0
    return np.column_stack([x, y]).astype(np.int64)


@pytest.mark.parametrize("dtype", [np.float32, np.float64, ">f4", ">f8", np.int16, np.int32])
@pytest.mark.parametrize("size", [3, 8, 13])
def test_batched_cut_equals_the_per_stamp_cut(dtype, size):
    rng = np.random.default_rng(size)
    rows = (rng.normal(0, 50, (40, 57))).astype(dtype)
    origins = _random_origins(rng, 60, size, rows.shape, row0=17)
    expected = _per_stamp_cut(rows, 17, origins, size)
    assert _same(cut_stamps(rows, 17, origins, size), expected)
    assert _same(cut_stamps_checked(rows, 17, origins, size).stamps, expected)


def test_grid_cut_equals_the_per_stamp_cut():
    rng = np.random.default_rng(1)
    size = 16
    image = rng.normal(size=(5 * size, 7 * size)).astype(np.float32)
    origins = grid_origins(5, 7, size)
    assert _same(cut_stamps(image, 0, origins, size), _per_stamp_cut(image, 0, origins, size))


def _awkward_stamps(size: int) -> np.ndarray:
    """Noise, integer ties, zeros of both signs, NaN and infinities at edges and inside."""
    rng = np.random.default_rng(size)
    stamps = [rng.normal(3.0, 2.0, (size, size)) for _ in range(6)]
    stamps.append(np.round(rng.normal(0, 2.0, (size, size))))  # many ties
    stamps.append(np.zeros((size, size)))
    stamps.append(-np.zeros((size, size)))
    signed = np.zeros((size, size))
    signed[::2] = -0.0
    signed[1, 1] = 1.0
    stamps.append(signed)
    for where in [
        (0, 0),
        (size - 1, size // 2),
        (size // 2, 0),
        (size // 2, size - 1),
        (size // 2, size // 2),
    ]:
        for value in (np.nan, np.inf, -np.inf):
            s = rng.normal(size=(size, size))
            s[where] = value
            stamps.append(s)
    half = rng.normal(size=(size, size))
    half[0, :] = np.inf  # more than half the edges infinite: NaN deviations
    half[:, 0] = np.inf
    half[-1, :] = np.inf
    stamps.append(half)
    few = rng.normal(size=(size, size))
    few[0, :2] = [np.inf, -np.inf]
    stamps.append(few)
    stamps.append(np.full((size, size), 7.0))
    return np.array(stamps)


@pytest.mark.parametrize("size", [3, 4, 5, 8, 33, 64])
def test_checks_equal_isfinite_and_sky_mad_exactly(size):
    stamps = _awkward_stamps(size)
    n = len(stamps)
    rows = stamps.reshape(n * size, size)  # a column of stamps
    origins = np.column_stack([np.ones(n), 1 + size * np.arange(n)]).astype(np.int64)
    cut = cut_stamps_checked(rows, 0, origins, size)
    assert _same(cut.stamps, stamps)
    assert _same(cut.finite, np.isfinite(stamps).all(axis=(1, 2)))
    with np.errstate(invalid="ignore"):
        expected = sky_mad(stamps)
    assert _same(cut.skymad, expected)


def test_edge_mad_equals_numpy_median_with_ties_and_sorted_edges():
    """The compiled selection gives numpy's order statistics on edges with many ties (counts
    quantized to a few values), already sorted or reversed, and plain noise."""
    rng = np.random.default_rng(11)
    size = 64
    stamps = [np.round(rng.normal(0, s, (size, size))) for s in (0.3, 1.0, 3.0) for _ in range(40)]
    stamps += [rng.normal(0, 1, (size, size)) for _ in range(200)]
    ramp = np.add.outer(np.arange(size), np.arange(size)).astype(float)
    stamps += [ramp, -ramp, ramp.T, np.abs(ramp - size)]
    stamps = np.array(stamps)
    n = len(stamps)
    origins = np.column_stack([np.ones(n), 1 + size * np.arange(n)]).astype(np.int64)
    cut = cut_stamps_checked(stamps.reshape(n * size, size), 0, origins, size)
    assert _same(cut.skymad, sky_mad(stamps))


def test_checks_on_float32_rows_equal_those_of_float64_stamps():
    rng = np.random.default_rng(3)
    rows = rng.normal(0, 1, (48, 96)).astype(np.float32)
    rows[5, 7] = np.nan
    origins = grid_origins(3, 6, 16)
    cut = cut_stamps_checked(rows, 0, origins, 16)
    stamps = _per_stamp_cut(rows, 0, origins, 16)
    assert _same(cut.finite, np.isfinite(stamps).all(axis=(1, 2)))
    assert _same(cut.skymad, sky_mad(stamps))


def test_cut_refuses_stamps_outside_the_rows():
    rows = np.zeros((10, 10))
    for bad in ([[0, 1]], [[1, 0]], [[5, 1]], [[1, 5]]):
        with pytest.raises(ValueError, match="inside"):
            cut_stamps(rows, 0, np.array(bad), 7)
    with pytest.raises(ValueError, match="inside"):
        cut_stamps(rows, 3, np.array([[1, 1]]), 3)  # above row0
    assert cut_stamps(rows, 0, np.zeros((0, 2), np.int64), 7).shape == (0, 7, 7)
    with pytest.raises(ValueError, match="at least"):
        cut_stamps_checked(rows, 0, np.array([[1, 1]]), 2)


def test_pixel_rows_keeps_float32_and_converts_the_rest():
    assert pixel_rows(np.zeros((2, 2), np.float32)).dtype == np.float32
    swapped = pixel_rows(np.arange(4, dtype=">f8").reshape(2, 2))
    assert swapped.dtype == np.float64 and swapped.dtype.isnative
    assert pixel_rows(np.ones((2, 2), np.int16)).dtype == np.float64
    assert pixel_rows(np.ones((4, 4))[:, ::2]).flags.c_contiguous


@pytest.mark.parametrize("dtype", ["f4", "f8", "i2"])
def test_read_band_reads_the_rows_of_read_rows(tmp_path, dtype):
    data = (np.arange(12 * 10).reshape(12, 10) - 30).astype(dtype)
    path = tmp_path / "img.fits"
    fitsio.write(str(path), data, clobber=True)
    info = image_info(path)
    band = read_band(info, 3, 9)
    assert band.dtype == (np.float32 if dtype == "f4" else np.float64) and band.dtype.isnative
    assert _same(np.asarray(band, np.float64), read_rows(info, 3, 9))
    assert _same(read_rows(info, 3, 9), data[3:9].astype(np.float64))


@pytest.mark.parametrize("dtype", ["f4", "f8"])
@pytest.mark.parametrize("ext", [0, 1])
def test_read_band_maps_a_float_image_as_stored(tmp_path, dtype, ext):
    """An uncompressed float image's rows, mapped from the file, are its bytes as stored
    (big-endian, no copy), with the values that reading them gives, in any HDU."""
    data = np.random.default_rng(1).normal(0, 10, (12, 10)).astype(dtype)
    data[4, 2] = np.nan
    path = tmp_path / "img.fits"
    with fitsio.FITS(str(path), "rw", clobber=True) as f:
        if ext:
            f.write(np.zeros((3, 5), np.int16))
        f.write(data)
    info = image_info(path, ext)
    assert info.stored_offset is not None and np.dtype(info.stored_dtype).byteorder == ">"
    mapped = read_band(info, 3, 9, mapped=True)
    assert not mapped.dtype.isnative and not mapped.flags.writeable
    assert _same_values(mapped.astype(data.dtype), data[3:9])
    assert _same_values(read_band(info, 3, 9), data[3:9])
    origins = np.array([[1, 4], [4, 5], [2, 4]], np.int64)
    for mapped_cut, read_cut in zip(
        cut_stamps_checked(mapped, 3, origins, 5).__dict__.values(),
        cut_stamps_checked(read_band(info, 3, 9), 3, origins, 5).__dict__.values(),
        strict=True,
    ):
        assert _same_values(mapped_cut, read_cut)


def test_read_band_reads_what_cannot_be_used_as_stored(tmp_path):
    """Integer, scaled and compressed images are read (and converted) as before."""
    data = np.arange(12 * 10, dtype=np.float32).reshape(12, 10)
    cases = {
        "int.fits": (data.astype(np.int16), {}),
        "scaled.fits": (data, {"header": {"BSCALE": 2.0, "BZERO": 1.0}}),
        "compressed.fits": (data, {"compress": "gzip"}),
    }
    for name, (pixels, options) in cases.items():
        path = tmp_path / name
        fitsio.write(str(path), pixels, clobber=True, **options)
        info = image_info(path)
        assert info.stored_offset is None, name
        band = read_band(info, 3, 9, mapped=True)
        assert band.dtype.isnative, name
        assert _same(band, read_band(info, 3, 9)), name


def test_measure_stamps_with_the_checks_given_equals_without():
    stamps = _awkward_stamps(16)
    cut = cut_stamps_checked(
        stamps.reshape(-1, 16),
        0,
        np.column_stack([np.ones(len(stamps)), 1 + 16 * np.arange(len(stamps))]).astype(np.int64),
        16,
    )
    with np.errstate(invalid="ignore"):
        plain = measure_stamps(stamps)
    given = measure_stamps(stamps, finite=cut.finite, skymad=cut.skymad)
    assert plain.keys() == given.keys()
    for c in plain:
        assert _same(plain[c], given[c]), c
    with pytest.raises(ValueError, match="both"):
        measure_stamps(stamps, finite=cut.finite)
    with pytest.raises(ValueError, match="one value per stamp"):
        measure_stamps(stamps, finite=cut.finite[:2], skymad=cut.skymad[:2])


def _galaxy_stamps(size: int, n: int, seed: int) -> np.ndarray:
    """Noisy elliptical Gaussians of random size, shape, offset and flux (some too faint to
    measure), with the awkward stamps of :func:`_awkward_stamps` among them."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[:size, :size] + 1.0
    stamps = []
    for _ in range(n):
        s = rng.uniform(1.0, size / 6)
        e1, e2 = rng.uniform(-0.5, 0.5, 2)
        cx, cy = (size + 1) / 2 + rng.uniform(-3, 3, 2)
        dx, dy = x - cx, y - cy
        q = ((1 - e1) * dx * dx + (1 + e1) * dy * dy - 2 * e2 * dx * dy) / (s * s)
        flux = 10 ** rng.uniform(0, 3)
        stamps.append(flux * np.exp(-0.5 * q) + rng.normal(0, 1.0, (size, size)))
    stamps = np.concatenate([np.array(stamps), _awkward_stamps(size)])
    return stamps[rng.permutation(len(stamps))]


@pytest.mark.parametrize("size, dtype", [(16, np.float64), (48, np.float32), (64, np.float32)])
def test_cut_and_measure_equals_the_cut_then_the_moments(size, dtype):
    """The one-pass kernel gives, bit for bit, what cutting the stack and measuring it gives:
    finite, skymad, moments (NaN where HSM fails or a pixel is not finite), features, flags."""
    stamps = _galaxy_stamps(size, 300, seed=size).astype(dtype)
    n = len(stamps)
    per_row = 7  # stamps on a grid of 7 columns, in rows from row0 = 5 of a taller image
    rows = np.zeros(((n + per_row - 1) // per_row * size + 5 + 3, per_row * size + 2), dtype)
    origins = np.zeros((n, 2), dtype=np.int64)
    for k, stamp in enumerate(stamps):
        oy, ox = 5 + 1 + (k // per_row) * size, 2 + (k % per_row) * size
        rows[oy - 1 : oy - 1 + size, ox - 1 : ox - 1 + size] = stamp
        origins[k] = ox, oy
    band = rows[5:]
    guess = default_guess_sigma(size)
    found = cut_and_measure(band, 5, origins, size, guess)
    stored = cut_and_measure(band.astype(band.dtype.newbyteorder(">")), 5, origins, size, guess)
    for a, b in zip(found.__dict__.values(), stored.__dict__.values(), strict=True):
        assert _same(a, b)  # FITS's big-endian rows, as mapped from a file: the same bits
    cut = cut_stamps_checked(band, 5, origins, size)
    assert _same(found.finite, cut.finite) and _same(found.skymad, cut.skymad)
    with np.errstate(invalid="ignore"):
        expected = measure_stamps(
            cut.stamps,
            origins,
            2.5,
            max_shift=default_max_shift(size),
            finite=cut.finite,
            skymad=cut.skymad,
        )
    got = features_from_moments(
        found.moments,
        found.skymad,
        found.finite,
        origins.astype(float),
        size,
        2.5,
        default_max_shift(size),
    )
    assert got.keys() == expected.keys()
    for column in got:
        assert _same(got[column], expected[column]), column
    measured = np.isfinite(found.moments).all(axis=1)
    assert 0.5 * n < measured.sum() < n  # most measured, some failed or not finite
    assert not measured[~found.finite].any()
    with pytest.raises(ValueError, match="inside"):
        cut_and_measure(band, 5, origins + [0, 10_000], size, guess)
    empty = cut_and_measure(band, 5, np.zeros((0, 2), np.int64), size, guess)
    assert empty.moments.shape == (0, 7) and empty.finite.shape == (0,)


def test_read_catalog_columns_reads_what_read_catalog_reads(tmp_path):
    path = tmp_path / "cat.fits"
    cols = {
        "x": np.array([1.5, 2.5]),
        "n": np.array([3, 4], np.int32),
        "v": np.arange(6.0).reshape(2, 3),
        "s": np.array(["ab", "c"]),
        "b": np.array([True, False]),
    }
    write_catalog(path, cols, fmt="test", cards={"SEED": (4, "seed")}, history=["made by test"])
    table = read_catalog(path)
    columns, header = read_catalog_columns(path)
    assert list(columns) == table.colnames
    for c in columns:
        assert _same(columns[c], np.asarray(table[c])), c
    assert header == dict(table.meta)


def test_measure_file_columns_writes_what_measure_file_writes(tmp_path):
    rng = np.random.default_rng(2)
    size = 24
    image = rng.normal(0, 1, (2 * size, 3 * size)).astype(np.float32)
    yy, xx = np.mgrid[: 2 * size, : 3 * size]
    for cy in (size / 2, 1.5 * size):
        for cx in (size / 2, 1.5 * size, 2.5 * size):
            image += (40 * np.exp(-((xx - cx + 0.5) ** 2 + (yy - cy + 0.5) ** 2) / 8.0)).astype(
                np.float32
            )
    fitsio.write(str(tmp_path / "st.fits"), image, header={"STAMPSZ": size}, clobber=True)
    columns, meta = measure_file_columns(tmp_path / "st.fits", None, tmp_path / "a.fits")
    table = measure_file(tmp_path / "st.fits", None, tmp_path / "b.fits")
    assert meta == {} and list(columns) == table.colnames
    a, b = fitsio.read(str(tmp_path / "a.fits")), fitsio.read(str(tmp_path / "b.fits"))
    assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
    for c in columns:
        assert _same(np.asarray(table[c]), np.asarray(columns[c])), c
    assert (table["flags"] == 0).all()
