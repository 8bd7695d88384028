"""Locating square stamps in a big FITS image, and reading them.

Coordinates are FITS-like: pixel ``(1, 1)`` is the centre of the image's first
(lower-left) pixel, ``x`` runs along the image's last numpy axis and ``y`` along the
first. A stamp is given by the 1-based ``(x, y)`` of its lower-left pixel (its *origin*).

* From a catalog of stamp centres ``x, y`` (1-based, or 0-based with ``origin=0`` as in
  GREAT3): the lower-left pixel is ``floor(x1 - S/2 + 0.5)`` where ``x1`` is the 1-based
  centre. This maps both the true centre of a stamp (``32.5`` for ``S = 64``) and GalSim's
  nominal centre (``33``) to the same stamp. A centre exactly half-way between two
  candidate stamps (an integer centre of an even stamp, half a pixel below the true
  centre: GREAT3's ``x = column S + (S - 1) // 2``, e.g. 23 for the first 48-pixel stamp)
  goes to the candidate that lies on the image's grid of stamps (lower-left pixel at
  ``1 + k S``); so GREAT3's integer centres, true centres and GalSim's nominal centres
  all find the same grid stamp.
* In grid order (no catalog): stamp ``k`` sits at grid column ``k mod n_x`` and grid row
  ``k div n_x``, counted from the image's first pixel, with ``n_x = width // S``; an
  ``NSTAMPS`` header card limits the number of stamps (a partly filled last row).

Stamps not entirely inside the image are reported (``inside`` mask) rather than read.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import fitsio
import numpy as np

from megalut_cli.errors import ConfigError, InputError
from megalut_cli.fits_header import header_dict, image_ext
from megalut_cli.measure.defaults import MAD_TO_SIGMA, MIN_STAMP_SIZE, ORIGINS

#: Header card holding the stamp size of an image of stamps.
STAMP_SIZE_CARD = "STAMPSZ"

#: Tolerance making ``floor`` robust to centres stored as e.g. 32.49999999.
_EPS = 1e-6


@dataclass(frozen=True)
class ImageInfo:
    """Where an image lives in a FITS file, its shape ``(ny, nx)`` and header; and, for an
    uncompressed and unscaled float image (BITPIX -32 or -64), the byte offset of its pixels
    in the file and their type as stored (big-endian), so that they can be mapped rather
    than read (None otherwise)."""

    path: str
    ext: int
    shape: tuple[int, int]
    header: dict[str, Any]
    stored_offset: int | None = None
    stored_dtype: str | None = None


#: The numpy types of the FITS float images that can be used as stored, by BITPIX.
STORED_FLOAT_TYPES = {-32: ">f4", -64: ">f8"}


def _unreadable(path: str | os.PathLike) -> InputError:
    return InputError(f"{path}: not a readable FITS file (truncated or not FITS)")


def image_info(path: str | os.PathLike, ext: int | None = None) -> ImageInfo:
    """Locate the image HDU of ``path`` (first with data unless ``ext``) and check it is whole.

    Raises :class:`InputError` for a missing, non-FITS or truncated file, or no 2-D image.
    """
    if not os.path.isfile(path):
        raise InputError(f"{path}: no such file")
    try:
        with fitsio.FITS(str(path)) as f:
            ext = image_ext(f, path, ext)
            hdu = f[ext]
            if hdu.get_exttype() != "IMAGE_HDU":
                raise InputError(f"{path}: HDU {ext} is not an image")
            dims = hdu.get_dims()
            if len(dims) != 2:
                raise InputError(f"{path}: expected a 2-D image, got {len(dims)} dimension(s)")
            cards = hdu.read_header()
            header = header_dict(cards)
            scaled = cards.get("BSCALE", 1) != 1 or cards.get("BZERO", 0) != 0
            hinfo = hdu.get_info()
            nbytes = abs(int(hinfo["img_type"])) // 8 * int(dims[0]) * int(dims[1])
            data_end = int(hinfo["data_start"]) + nbytes
            compressed = bool(hinfo["is_compressed_image"])
    except InputError:
        raise
    except (OSError, ValueError, IndexError):
        raise _unreadable(path) from None
    if not compressed and data_end > os.path.getsize(path):
        raise InputError(f"{path}: truncated FITS file (image data incomplete)")
    stored = STORED_FLOAT_TYPES.get(int(hinfo["img_type"]))
    if compressed or scaled:
        stored = None
    return ImageInfo(
        str(path),
        int(ext),
        (int(dims[0]), int(dims[1])),
        header,
        int(hinfo["data_start"]) if stored else None,
        stored,
    )


def pixel_rows(rows: np.ndarray) -> np.ndarray:
    """``rows`` as the cutting kernel takes them: float32 and float64 pixels as they are (in
    native byte order, C order), any other type as float64."""
    rows = np.asarray(rows)
    if rows.dtype.type in (np.float32, np.float64):
        return np.ascontiguousarray(rows, dtype=rows.dtype.newbyteorder("="))
    return np.ascontiguousarray(rows, dtype=np.float64)


def kernel_rows(rows: np.ndarray) -> np.ndarray:
    """``rows`` as the cutting kernels of :mod:`.stamps_nb` take them: :func:`pixel_rows`,
    except that C-ordered big-endian float32 or float64 rows (FITS's bytes, as
    :func:`read_band` maps them) are given as the uint32 or uint64 view of their bytes,
    which the kernels swap as they read each pixel (``stamps_nb.pixel_value``): no copy."""
    rows = np.asarray(rows)
    if (
        rows.dtype.type in (np.float32, np.float64)
        and not rows.dtype.isnative
        and rows.flags.c_contiguous
    ):
        return rows.view(np.uint32 if rows.dtype.itemsize == 4 else np.uint64)
    return pixel_rows(rows)


def _mapped_band(info: ImageInfo, y0: int, y1: int) -> np.ndarray:
    """Rows ``y0 .. y1 - 1`` of an image whose pixels can be used as stored, mapped from the
    file (big-endian, read-only)."""
    assert info.stored_offset is not None and info.stored_dtype is not None
    dtype = np.dtype(info.stored_dtype)
    nx = info.shape[1]
    offset = info.stored_offset + y0 * nx * dtype.itemsize
    return np.asarray(np.memmap(info.path, dtype, "r", offset, (y1 - y0, nx)))


def read_band(info: ImageInfo, y0: int, y1: int, mapped: bool = False) -> np.ndarray:
    """Read image rows ``y0 .. y1 - 1`` (0-based numpy indices) in one read, as
    :func:`pixel_rows` (float32 pixels are not converted). With ``mapped``, an uncompressed,
    unscaled float image's rows are mapped from the file instead, as stored (big-endian
    float: pass them to the cutting functions, which read them without a copy)."""
    if mapped and info.stored_offset is not None and y1 > y0:
        try:
            return _mapped_band(info, y0, y1)
        except (OSError, ValueError):
            raise _unreadable(info.path) from None
    try:
        with fitsio.FITS(info.path) as f:
            data = f[info.ext][y0:y1, :]
    except (OSError, ValueError):
        raise _unreadable(info.path) from None
    return pixel_rows(data)


def read_rows(info: ImageInfo, y0: int, y1: int) -> np.ndarray:
    """Read image rows ``y0 .. y1 - 1`` (0-based numpy indices) as float64."""
    return np.asarray(read_band(info, y0, y1), dtype=np.float64)


def stamp_size_of(info: ImageInfo, stamp_size: int | None, where: str = "stamp_size") -> int:
    """The stamp size: ``stamp_size`` if given, else the image's ``STAMPSZ`` header card
    (messages name the argument ``where``)."""
    if stamp_size is None:
        card = info.header.get(STAMP_SIZE_CARD)
        if card is None:
            raise ConfigError(
                f"{info.path}: stamp size unknown: give {where} or a {STAMP_SIZE_CARD} header card"
            )
        try:
            value = float(card)
        except (TypeError, ValueError):
            value = float("nan")
        if isinstance(card, bool) or not value.is_integer():
            raise InputError(f"{info.path}: bad {STAMP_SIZE_CARD} header card {card!r}")
        stamp_size = int(value)
    if stamp_size < MIN_STAMP_SIZE:
        raise ConfigError(f"stamp size must be at least {MIN_STAMP_SIZE} pixels, got {stamp_size}")
    return int(stamp_size)


def check_grid(info: ImageInfo, stamp_size: int) -> tuple[int, int]:
    """``(n_y, n_x)`` stamps of the grid; an error if ``stamp_size`` does not divide the image."""
    ny, nx = info.shape
    if ny % stamp_size or nx % stamp_size:
        raise InputError(
            f"{info.path}: stamp size {stamp_size} does not divide the {nx}x{ny} image"
        )
    return ny // stamp_size, nx // stamp_size


def grid_origins(n_y: int, n_x: int, stamp_size: int) -> np.ndarray:
    """1-based lower-left ``(x, y)`` of the ``n_y * n_x`` stamps of a grid, in grid order."""
    k = np.arange(n_y * n_x, dtype=np.int64)
    return np.column_stack([(k % n_x) * stamp_size + 1, (k // n_x) * stamp_size + 1])


def catalog_origins(
    x: np.ndarray, y: np.ndarray, stamp_size: int, origin: int = 1, where: str = "origin"
) -> np.ndarray:
    """1-based lower-left ``(x, y)`` of the stamps centred at catalog positions ``x, y``.

    ``origin`` is the coordinate of the first pixel's centre in the catalog (1: FITS,
    0: numpy/GREAT3). A centre half-way between two stamps goes to the one on the grid
    of ``stamp_size`` stamps from pixel 1 (see the module docstring). Non-finite centres
    give the origin ``INT64_MIN`` (never inside). Messages name ``origin`` ``where``.
    """
    if origin not in ORIGINS:
        raise ConfigError(f"{where} must be 0 or 1, got {origin}")
    xy = np.column_stack([np.asarray(x, np.float64), np.asarray(y, np.float64)]) + (1 - origin)
    t = xy - stamp_size / 2.0 + 0.5
    ll = np.floor(t + _EPS)
    with np.errstate(invalid="ignore"):
        # Exactly half-way between candidates ll and ll + 1: prefer the one on the grid.
        halfway = np.abs(t - ll - 0.5) < _EPS
        on_grid_up = np.mod(ll, stamp_size) == 0  # (ll + 1) - 1 is a multiple of S
        ll = np.where(halfway & on_grid_up, ll + 1, ll)
    bad = ~np.isfinite(ll).all(axis=1)
    out = np.empty(ll.shape, dtype=np.int64)
    out[~bad] = ll[~bad].astype(np.int64)
    out[bad] = np.iinfo(np.int64).min
    return out


def inside(origins: np.ndarray, stamp_size: int, shape: tuple[int, int]) -> np.ndarray:
    """Mask of stamps lying entirely inside an image of ``shape`` ``(ny, nx)``."""
    ny, nx = shape
    ox, oy = origins[:, 0], origins[:, 1]
    return (ox >= 1) & (oy >= 1) & (ox + stamp_size - 1 <= nx) & (oy + stamp_size - 1 <= ny)


@dataclass(frozen=True)
class CheckedStamps:
    """Stamps cut by :func:`cut_stamps_checked`: ``stamps`` ``(n, S, S)`` float64, whether all
    pixels of each are finite, and the sky MAD of its edge pixels (``features.sky_mad``)."""

    stamps: np.ndarray
    finite: np.ndarray
    skymad: np.ndarray


def _checked_cut_arguments(
    rows: np.ndarray, row0: int, origins: np.ndarray, stamp_size: int, checks: bool
) -> tuple[np.ndarray, np.ndarray]:
    """``rows`` as :func:`kernel_rows` and ``origins`` as ``(n, 2)`` int64, checked: every stamp
    inside the rows, and (``checks``) large enough for the edge statistic."""
    rows = kernel_rows(rows)
    if rows.ndim != 2:
        raise ValueError(f"rows must be 2-d, got shape {rows.shape}")
    origins = np.ascontiguousarray(np.asarray(origins).reshape(-1, 2), dtype=np.int64)
    if checks and stamp_size < MIN_STAMP_SIZE:  # the edge statistic needs an inside
        raise ValueError(f"stamps must be at least {MIN_STAMP_SIZE} pixels, got {stamp_size}")
    x0, y0 = origins[:, 0] - 1, origins[:, 1] - 1 - row0
    if (
        len(origins)
        and not (
            (x0 >= 0)
            & (y0 >= 0)
            & (x0 + stamp_size <= rows.shape[1])
            & (y0 + stamp_size <= rows.shape[0])
        ).all()
    ):
        raise ValueError("stamps must lie inside the rows they are cut from")
    return rows, origins


def _cut(
    rows: np.ndarray, row0: int, origins: np.ndarray, stamp_size: int, checks: bool
) -> CheckedStamps:
    from megalut_cli.measure.stamps_nb import cut_stack  # numba: loaded where stamps are cut

    rows, origins = _checked_cut_arguments(rows, row0, origins, stamp_size, checks)
    n = len(origins)
    out = np.empty((n, stamp_size, stamp_size), dtype=np.float64)
    finite = np.zeros(n if checks else 0, dtype=np.bool_)
    mad = np.zeros(n if checks else 0, dtype=np.float64)
    if n:
        cut_stack(rows, int(row0), origins, out, finite, mad, checks)
    return CheckedStamps(out, finite, MAD_TO_SIGMA * mad)


def cut_stamps(rows: np.ndarray, row0: int, origins: np.ndarray, stamp_size: int) -> np.ndarray:
    """Cut stamps ``(n, S, S)`` (float64) from a block of image ``rows`` whose first row is
    ``row0`` (0-based), in one compiled call."""
    return _cut(rows, row0, origins, stamp_size, False).stamps


def cut_stamps_checked(
    rows: np.ndarray, row0: int, origins: np.ndarray, stamp_size: int
) -> CheckedStamps:
    """:func:`cut_stamps`, and in the same pass over the pixels whether every pixel of each
    stamp is finite and its ``skymad`` (:func:`megalut_cli.measure.features.sky_mad`, exactly)."""
    return _cut(rows, row0, origins, stamp_size, True)


@dataclass(frozen=True)
class MeasuredStamps:
    """What :func:`cut_and_measure` finds on each stamp: whether all its pixels are finite,
    the sky MAD of its edge pixels and its adaptive ``moments`` ``(n, 7)``: ``amp, g1, g2,
    sigma, rho4, x, y``, NaN rows where a pixel is not finite or HSM failed (the input of
    :func:`megalut_cli.measure.features.features_from_moments`)."""

    finite: np.ndarray
    skymad: np.ndarray
    moments: np.ndarray


def cut_and_measure(
    rows: np.ndarray,
    row0: int,
    origins: np.ndarray,
    stamp_size: int,
    guess_sigma: float,
    retry_step: float = 0.0,
) -> MeasuredStamps:
    """:func:`cut_stamps_checked`, then the adaptive moments of each finite stamp
    (:func:`megalut_cli.measure.adamom.adaptive_moments` from ``guess_sigma``, with its
    ``retry_step``), in one
    compiled pass that keeps each stamp in the core's cache: the same values as the two
    calls, without the stack of float64 stamps."""
    from megalut_cli.measure.adamom import SUCCESS, guess_sigmas, kernel_settings
    from megalut_cli.measure.stamps_nb import cut_measure_stack  # numba

    rows, origins = _checked_cut_arguments(rows, row0, origins, stamp_size, True)
    n = len(origins)
    finite = np.zeros(n, dtype=np.bool_)
    mad = np.zeros(n, dtype=np.float64)
    status = np.full(n, -1, dtype=np.int32)  # -1: not measured (a pixel is not finite)
    n_iter = np.zeros(n, dtype=np.int32)
    moments = np.full((n, 7), np.nan)
    if n:
        settings = kernel_settings(stamp_size, stamp_size, retry_step=retry_step)
        guess = guess_sigmas(guess_sigma, n)
        cut_measure_stack(
            rows,
            int(row0),
            origins,
            stamp_size,
            guess,
            settings,
            finite,
            mad,
            status,
            n_iter,
            moments,
        )
    moments[status != SUCCESS] = np.nan
    return MeasuredStamps(finite, MAD_TO_SIGMA * mad, moments)


def stamp_centres(origins: np.ndarray, stamp_size: int) -> np.ndarray:
    """True centres (1-based ``x, y``) of stamps with the given lower-left pixels."""
    return origins.astype(np.float64) + (stamp_size - 1) / 2.0
