"""MEDS input of ``megalut measure``: one output row per object of a MEDS cutout file.

A MEDS file (Multi Epoch Data Structure, esheldon/meds; the layout of DES and of the
LSST DESC simulations) is a FITS file with a binary table ``object_data`` (one row per
object) and flat image extensions holding every cutout of every object, one after the
other: ``image_cutouts`` (required), ``weight_cutouts``, ``seg_cutouts``,
``bmask_cutouts`` (optional), and the PSF images ``psf`` (the name the ``meds`` package
writes and reads; ``psf_cutouts`` is accepted too). Cutout ``k`` of object ``i`` is the
``box_size[i]**2`` pixels starting at ``start_row[i, k]`` of each extension, reshaped to
``(box_size, box_size)`` (rows are y, as in FITS); its PSF the ``psf_row_size x
psf_col_size`` (else ``psf_box_size**2``) pixels from ``psf_start_row[i, k]``.

``object_data`` columns read (:data:`OBJECT_COLUMNS`): ``id``, ``number``, ``ncutout``,
``box_size``, ``start_row``, ``orig_row``, ``orig_col``, ``cutout_row``, ``cutout_col``,
``ra``, ``dec`` and, with PSF cutouts, ``psf_start_row`` and ``psf_row_size``,
``psf_col_size`` or ``psf_box_size``; the ``metadata`` table's ``first_image_is_coadd``
and ``image_info``'s ``image_path`` tell whether cutout 0 is a coadd.

:func:`is_meds` recognises a file (its ``object_data`` and ``image_cutouts``
extensions); :func:`read_meds` reads its layout into a :class:`MedsFile`, whose
:meth:`MedsFile.cutout` and :meth:`MedsFile.stamps` read cutouts with one fitsio row-range
read per run of nearby cutouts; :func:`measure_cutouts` is the in-memory core (a stack of
equal-size cutouts with their weight and bad-mask maps); :func:`measure_meds` measures a
file's objects over work units (``nproc``, ``scheduler``) and :func:`measure_meds_file`
writes the features catalog. :func:`write_meds` writes the subset of MEDS megalut reads,
for tests and examples.

Masked pixels (``bmask != 0``, or ``weight <= 0`` where there is a weight map) are left
out of the adaptive moments the way GalSim's ``FindAdaptiveMom(badpix=...)`` leaves them
out: HSM multiplies the image by its mask, so they are set to 0 before either engine
measures the stamp (the same numbers as GalSim's ``badpix``, to the bit), and out of the
sky MAD of the edge pixels.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import fitsio
import numpy as np

from megalut_cli import flags as fl
from megalut_cli.atomic import atomic_output, check_output
from megalut_cli.catalog import is_fits_file, write_catalog
from megalut_cli.engine import DEFAULT_DEVICE, DEFAULT_ENGINE
from megalut_cli.errors import ConfigError, InputError, Names, namer
from megalut_cli.measure.defaults import FORMAT, FORMAT_VERSION, MAD_TO_SIGMA, PSF_COLUMNS
from megalut_cli.measure.features import (
    FEATURE_COLUMNS,
    SOURCE_COLUMNS,
    default_max_shift,
    edge_pixels,
    measure_stamps,
    signal_to_noise,
    sky_mad,
    warn_if_mostly_flagged,
)
from megalut_cli.measure.metacal_defaults import (
    INTERPOLANT,
    TYPES,
    metacal_cards,
    metacal_columns,
)
from megalut_cli.measure.morphology import MORPHOLOGY_COLUMNS, morphology_of_measured
from megalut_cli.measure.options import MEASURE
from megalut_cli.measure.psf_model import cached_psf_model
from megalut_cli.measure.single_psf import single_psf_features, single_psf_stamp
from megalut_cli.parallel import executor, map_units, resolve_nproc
from megalut_cli.progress import Progress, no_progress
from megalut_cli.provenance import CREATOR

log = logging.getLogger(__name__)

#: The extensions that make a FITS file a MEDS file.
MEDS_EXTENSIONS: tuple[str, ...] = ("object_data", "image_cutouts")
#: The cutout extensions megalut reads, by cutout type.
CUTOUT_EXTENSIONS: dict[str, str] = {
    "image": "image_cutouts",
    "weight": "weight_cutouts",
    "seg": "seg_cutouts",
    "bmask": "bmask_cutouts",
}
#: Names of the PSF extension: ``psf`` (the meds package's), then ``psf_cutouts``.
PSF_EXTENSIONS: tuple[str, ...] = ("psf", "psf_cutouts")
#: ``object_data`` columns a MEDS file must have.
REQUIRED_COLUMNS: tuple[str, ...] = ("id", "ncutout", "box_size", "start_row")
#: ``object_data`` columns read when present (per-cutout ones are ``(n, NMAX)``).
OBJECT_COLUMNS: tuple[str, ...] = (
    *REQUIRED_COLUMNS,
    "number",
    "ra",
    "dec",
    "orig_row",
    "orig_col",
    "cutout_row",
    "cutout_col",
    "file_id",
    "psf_start_row",
    "psf_box_size",
    "psf_row_size",
    "psf_col_size",
)
#: Per-object columns copied to the output when the file has them.
PASSED_COLUMNS: tuple[str, ...] = ("id", "number", "box_size", "ncutout", "ra", "dec")
#: Per-cutout columns copied to the output (the measured cutout's value; NaN without one).
PASSED_CUTOUT_COLUMNS: tuple[str, ...] = ("orig_row", "orig_col")
#: The ``object_data`` columns of the MEDS layout (esheldon/meds README); any other scalar
#: column (a survey's own ids, a simulation's truth) is passed through to the output.
LAYOUT_COLUMNS: frozenset[str] = frozenset(
    (
        *OBJECT_COLUMNS,
        "orig_start_row",
        "orig_start_col",
        "dudrow",
        "dudcol",
        "dvdrow",
        "dvdcol",
        "psf_cutout_row",
        "psf_cutout_col",
    )
)

#: A stamp with more than this fraction of its pixels masked is flagged MASKED_PIXELS.
MAX_MASKED_FRACTION = 0.25
#: A masked pixel closer than this (pixels) to the object's position in its cutout
#: (``cutout_row, cutout_col``) flags the stamp MASKED_PIXELS: it takes a large share of the
#: light that the moments weigh most.
CENTRAL_MASK_RADIUS = 2.0
#: Objects per work unit.
CHUNK_OBJECTS = 1000
#: Value of ``n_masked`` for an object without the measured cutout.
NO_CUTOUT_MASKED = -1
#: Columns added to the features by MEDS input.
NOISE_COLUMN = "noise_weight"
MASKED_COLUMN = "n_masked"

#: Header cards of a catalog measured from a MEDS file.
CUTOUT_CARD = "MEDSCUT"
COADD_CARD = "MEDSCOAD"
FILE_CARD = "MEDSFILE"


class PsfDrawer(Protocol):
    """What measure needs of a PSF model: :meth:`megalut_cli.measure.psf_model.PsfModel.draw`."""

    def draw(
        self, x: np.ndarray, y: np.ndarray, size: int, pixel_scale: float | None = None
    ) -> np.ndarray:
        """``(n, size, size)`` unit-sum PSF images at 1-based image positions ``x, y``."""
        ...


@dataclasses.dataclass(frozen=True)
class Layout:
    """Where the cutouts of a stack of objects (one box size) lie in a MEDS file: what a
    work unit reads. ``psf_starts`` and ``psf_shape`` where the file has PSF cutouts."""

    path: str
    starts: np.ndarray
    box_size: int
    extensions: tuple[str, ...]
    psf_extension: str | None = None
    psf_starts: np.ndarray | None = None
    psf_shape: tuple[int, int] | None = None


@dataclasses.dataclass(frozen=True)
class Stamps:
    """Cutouts of a stack of objects, ``(n, S, S)`` each (None where the file has no such
    map); ``psfs`` ``(n, P, Q)``."""

    images: np.ndarray
    weights: np.ndarray | None = None
    bmasks: np.ndarray | None = None
    segs: np.ndarray | None = None
    psfs: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class Cutout:
    """One cutout of one object as 2-D arrays (None where the file has no such map)."""

    image: np.ndarray
    weight: np.ndarray | None
    bmask: np.ndarray | None
    seg: np.ndarray | None
    psf: np.ndarray | None


@dataclasses.dataclass
class MedsFile:
    """The layout of a MEDS file: its ``object_data`` columns (:data:`OBJECT_COLUMNS` it
    has; per-cutout ones ``(n, NMAX)``), ``image_info`` and ``metadata`` tables (None when
    absent), and the length in pixels of each cutout extension it holds."""

    path: str
    objects: dict[str, np.ndarray]
    image_info: np.ndarray | None
    metadata: np.ndarray | None
    extensions: dict[str, int]
    psf_extension: str | None = None

    def __len__(self) -> int:
        return len(self.objects["id"])

    @property
    def n_max(self) -> int:
        """The number of cutout slots per object (NMAX)."""
        return int(self.objects["start_row"].shape[1])

    def has(self, kind: str) -> bool:
        """Whether the file holds cutouts of ``kind`` (``image``, ``weight``, ``seg``,
        ``bmask``, ``psf``)."""
        return (
            self.psf_extension is not None
            if kind == "psf"
            else CUTOUT_EXTENSIONS[kind] in self.extensions
        )

    def first_is_coadd(self) -> bool:
        """Whether cutout 0 is a coadd, as the file says: a true ``first_image_is_coadd``
        in ``metadata``, else an ``image_info`` path of file 0 naming a coadd."""
        meta = self.metadata
        if (
            meta is not None
            and meta.dtype.names
            and "first_image_is_coadd" in meta.dtype.names
            and len(meta)
        ):
            return bool(meta["first_image_is_coadd"][0])
        info = self.image_info
        if info is not None and info.dtype.names and "image_path" in info.dtype.names and len(info):
            path = info["image_path"][0]
            text = path.decode(errors="replace") if isinstance(path, bytes) else str(path)
            return "coadd" in text.lower()
        return False

    def psf_shapes(self, cutout: int) -> np.ndarray:
        """``(n, 2)`` rows and columns of each object's PSF cutout ``cutout``."""
        obj = self.objects
        if "psf_row_size" in obj and "psf_col_size" in obj:
            rows, cols = obj["psf_row_size"], obj["psf_col_size"]
        elif "psf_box_size" in obj:
            rows = cols = obj["psf_box_size"]
        else:
            raise InputError(
                f"{self.path}: PSF cutouts without psf_box_size or psf_row_size, "
                "psf_col_size columns"
            )
        pick = lambda a: a[:, cutout] if a.ndim == 2 else a  # noqa: E731
        return np.stack([pick(rows), pick(cols)], axis=1).astype(np.int64)

    def layout(self, rows: np.ndarray, cutout: int = 0, psf: bool = True) -> Layout:
        """The :class:`Layout` of cutout ``cutout`` of the objects ``rows`` (one box size;
        with ``psf`` and PSF cutouts in the file, one PSF size)."""
        rows = np.asarray(rows, dtype=np.int64)
        boxes = np.unique(self.objects["box_size"][rows])
        if len(boxes) != 1:
            raise ValueError(f"objects of one box size expected, got {boxes.tolist()}")
        if np.any(self.objects["ncutout"][rows] <= cutout):
            raise ValueError(f"an object among rows has no cutout {cutout}")
        kinds = tuple(k for k in CUTOUT_EXTENSIONS if self.has(k))
        psf_starts = psf_shape = None
        if psf and self.psf_extension is not None:
            shapes = np.unique(self.psf_shapes(cutout)[rows], axis=0)
            if len(shapes) != 1:
                raise ValueError("objects of one PSF size expected")
            psf_shape = (int(shapes[0][0]), int(shapes[0][1]))
            psf_starts = self.objects["psf_start_row"][rows, cutout].astype(np.int64)
        return Layout(
            self.path,
            self.objects["start_row"][rows, cutout].astype(np.int64),
            int(boxes[0]),
            kinds,
            self.psf_extension if psf else None,
            psf_starts,
            psf_shape,
        )

    def stamps(self, rows: Sequence[int] | np.ndarray, cutout: int = 0) -> Stamps:
        """Cutout ``cutout`` of the objects ``rows`` (one box size) as stacks."""
        return read_stamps(self.layout(np.asarray(rows), cutout))

    def cutout(self, index: int, cutout: int = 0) -> Cutout:
        """Cutout ``cutout`` of object ``index`` as 2-D arrays."""
        if not 0 <= cutout < int(self.objects["ncutout"][index]):
            raise IndexError(
                f"object {index} has {int(self.objects['ncutout'][index])} cutout(s), "
                f"not {cutout + 1}"
            )
        s = self.stamps([index], cutout)
        first = lambda a: None if a is None else a[0]  # noqa: E731
        return Cutout(s.images[0], first(s.weights), first(s.bmasks), first(s.segs), first(s.psfs))


def is_meds(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a MEDS file: a FITS file with ``object_data`` and ``image_cutouts``
    extensions."""
    try:
        if not is_fits_file(path):
            return False
        with fitsio.FITS(str(path)) as f:
            return all(ext in f for ext in MEDS_EXTENSIONS)
    except (InputError, OSError, ValueError):  # missing or unreadable: the image reader says why
        return False


def _native(arr: np.ndarray) -> np.ndarray:
    return arr.astype(arr.dtype.newbyteorder("="), copy=False)


def _column(table: np.ndarray, name: str) -> np.ndarray:
    values = _native(np.asarray(table[name]))
    if values.dtype.kind == "S":
        values = np.char.strip(values.astype("U"))
    return values


def read_meds(path: str | os.PathLike) -> MedsFile:
    """Read the layout of a MEDS file (not its pixels), checked: the required columns, and
    every cutout lying inside its extensions (a truncated file is an InputError)."""
    path = str(path)
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{path}: no such file")
    if p.stat().st_size % 2880:
        raise InputError(f"{path}: not a readable FITS file (truncated or not FITS)")
    try:
        with fitsio.FITS(path) as f:
            missing = [e for e in MEDS_EXTENSIONS if e not in f]
            if missing:
                raise InputError(f"{path}: not a MEDS file (no {', '.join(missing)} extension)")
            hdu = f["object_data"]
            names = hdu.get_colnames()
            absent = [c for c in REQUIRED_COLUMNS if c not in names]
            if absent:
                raise InputError(
                    f"{path}: MEDS object_data lacks the column(s) {', '.join(absent)}"
                )
            table = hdu.read(
                columns=[c for c in names if c in OBJECT_COLUMNS or c not in LAYOUT_COLUMNS]
            )
            extensions = {
                e: int(np.prod(f[e].get_dims())) for e in CUTOUT_EXTENSIONS.values() if e in f
            }
            psf_ext = next((e for e in PSF_EXTENSIONS if e in f), None)
            if psf_ext is not None:
                extensions[psf_ext] = int(np.prod(f[psf_ext].get_dims()))
            image_info = _native_table(f["image_info"].read()) if "image_info" in f else None
            metadata = _native_table(f["metadata"].read()) if "metadata" in f else None
    except InputError:
        raise
    except (OSError, ValueError) as err:
        raise InputError(
            f"{path}: not a readable MEDS file ({str(err).splitlines()[0][:80]})"
        ) from None
    objects = {c: _column(table, c) for c in table.dtype.names}
    n = len(objects["id"])
    for c in (
        "start_row",
        "orig_row",
        "orig_col",
        "cutout_row",
        "cutout_col",
        "file_id",
        "psf_start_row",
    ):
        if c in objects and objects[c].ndim == 1:
            objects[c] = objects[c].reshape(n, 1)
    if psf_ext is not None and "psf_start_row" not in objects:
        log.warning(
            "%s: a %s extension but no psf_start_row column: PSF cutouts ignored", path, psf_ext
        )
        psf_ext = None
    meds = MedsFile(path, objects, image_info, metadata, extensions, psf_ext)
    _check_layout(meds)
    return meds


def _native_table(arr: np.ndarray) -> np.ndarray:
    dt = np.dtype([(n, arr.dtype[n].newbyteorder("=")) for n in arr.dtype.names])
    return arr.astype(dt, copy=False)


def _check_layout(meds: MedsFile) -> None:
    """Every used cutout inside its extensions; sane counts and sizes."""
    obj, path = meds.objects, meds.path
    ncut, box = obj["ncutout"].astype(np.int64), obj["box_size"].astype(np.int64)
    if np.any(ncut < 0) or np.any(ncut > meds.n_max):
        raise InputError(f"{path}: MEDS ncutout outside 0..{meds.n_max} (the start_row slots)")
    used = np.arange(meds.n_max)[None, :] < ncut[:, None]
    if np.any(box[ncut > 0] < 3):
        raise InputError(f"{path}: MEDS box_size below 3 pixels")
    starts = obj["start_row"].astype(np.int64)
    ends = starts + (box * box)[:, None]
    for ext in CUTOUT_EXTENSIONS.values():
        if ext not in meds.extensions:
            continue
        _check_inside(path, ext, starts[used], ends[used], meds.extensions[ext])
    if meds.psf_extension is not None:
        ext = meds.psf_extension
        pstarts = obj["psf_start_row"].astype(np.int64)
        sizes = np.stack([np.prod(meds.psf_shapes(k), axis=1) for k in range(meds.n_max)], axis=1)
        _check_inside(path, ext, pstarts[used], pstarts[used] + sizes[used], meds.extensions[ext])


def _check_inside(path: str, ext: str, starts: np.ndarray, ends: np.ndarray, length: int) -> None:
    if not len(starts):
        return
    if starts.min() < 0:
        raise InputError(f"{path}: MEDS object_data has negative start rows into {ext}")
    if ends.max() > length:
        raise InputError(
            f"{path}: truncated MEDS file: object_data puts cutouts up to pixel "
            f"{int(ends.max())} of {ext}, which holds {length}"
        )


def _read_flat(hdu: Any, starts: np.ndarray, npix: int) -> np.ndarray:
    """``(n, npix)`` pixels of the flat image ``hdu`` from each of ``starts``: one fitsio
    read per run of cutouts less than a cutout apart."""
    n = len(starts)
    out: np.ndarray | None = None
    order = np.argsort(starts, kind="stable")
    s = starts[order]
    i = 0
    while i < n:
        j, end = i + 1, s[i] + npix
        while j < n and s[j] - end <= npix:
            end, j = max(end, s[j] + npix), j + 1
        block = _native(np.asarray(hdu[int(s[i]) : int(end)]))
        if out is None:
            out = np.empty((n, npix), dtype=block.dtype)
        out[order[i:j]] = block[(s[i:j] - s[i])[:, None] + np.arange(npix)[None, :]]
        i = j
    return out if out is not None else np.empty((0, npix))


def read_stamps(layout: Layout) -> Stamps:
    """The cutouts a :class:`Layout` describes, one fitsio read per run of nearby cutouts
    and extension (images and weights as float64)."""
    size, n = layout.box_size, len(layout.starts)
    maps: dict[str, np.ndarray | None] = {k: None for k in CUTOUT_EXTENSIONS}
    psfs = None
    try:
        with fitsio.FITS(layout.path) as f:
            for kind, ext in CUTOUT_EXTENSIONS.items():
                if ext in layout.extensions or kind in layout.extensions:
                    flat = _read_flat(f[ext], layout.starts, size * size).reshape(n, size, size)
                    maps[kind] = flat.astype(np.float64) if kind in ("image", "weight") else flat
            if (
                layout.psf_extension is not None
                and layout.psf_starts is not None
                and layout.psf_shape is not None
            ):
                rows, cols = layout.psf_shape
                flat = _read_flat(f[layout.psf_extension], layout.psf_starts, rows * cols)
                psfs = flat.reshape(n, rows, cols).astype(np.float64)
    except (OSError, ValueError) as err:
        raise InputError(
            f"{layout.path}: cannot read MEDS cutouts ({str(err).splitlines()[0][:80]})"
        ) from None
    assert maps["image"] is not None
    return Stamps(maps["image"], maps["weight"], maps["bmask"], maps["seg"], psfs)


def masked_pixels(
    weights: np.ndarray | None, bmasks: np.ndarray | None, shape: tuple[int, ...]
) -> np.ndarray:
    """Bad pixels: ``bmask != 0``, or a weight that is not positive (or not finite)."""
    masked = np.zeros(shape, dtype=bool)
    if bmasks is not None:
        masked |= np.asarray(bmasks) != 0
    if weights is not None:
        w = np.asarray(weights)
        masked |= ~(w > 0)  # NaN weights too
    return masked


def masked_sky_mad(stamps: np.ndarray, masked: np.ndarray) -> np.ndarray:
    """:func:`~megalut_cli.measure.features.sky_mad` of the edge pixels that are not masked
    (NaN where all are)."""
    if not edge_pixels(masked).any():
        return sky_mad(stamps)
    edges = edge_pixels(np.where(masked, np.nan, np.asarray(stamps, dtype=np.float64)))
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: NaN
        med = np.nanmedian(edges, axis=1, keepdims=True)
        return MAD_TO_SIGMA * np.nanmedian(np.abs(edges - med), axis=1)


def weight_noise(weights: np.ndarray, masked: np.ndarray) -> np.ndarray:
    """Per-stamp noise from a weight (inverse-variance) map: ``1 / sqrt(median w)`` over
    the pixels not masked with ``w > 0`` (NaN where none)."""
    w = np.where(masked | ~(weights > 0), np.nan, np.asarray(weights, dtype=np.float64))
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: NaN
        return 1.0 / np.sqrt(np.nanmedian(w.reshape(len(w), -1), axis=1))


def clean_stamps(
    images: np.ndarray, weights: np.ndarray | None = None, bmasks: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``(stamps with masked pixels set to 0, mask)``: what GalSim's ``FindAdaptiveMom``
    measures of an image with a ``badpix`` map (:func:`masked_pixels`)."""
    images = np.asarray(images, dtype=np.float64)
    masked = masked_pixels(weights, bmasks, images.shape)
    return (np.where(masked, 0.0, images) if masked.any() else images), masked


def too_masked(masked: np.ndarray, centres: np.ndarray | None = None) -> np.ndarray:
    """Stamps whose measurement the mask makes unusable: more than
    :data:`MAX_MASKED_FRACTION` of the pixels masked, or a masked pixel within
    :data:`CENTRAL_MASK_RADIUS` of ``centres`` (``(n, 2)`` 0-based ``(col, row)`` of the object
    in its stamp; default the stamp centre)."""
    n, ny, nx = masked.shape
    if centres is None:
        centres = np.tile([(nx - 1) / 2.0, (ny - 1) / 2.0], (n, 1))
    centres = np.asarray(centres, dtype=np.float64).reshape(n, 2)
    frac = masked.reshape(n, -1).mean(axis=1) if n else np.zeros(0)
    yy, xx = np.mgrid[0:ny, 0:nx]
    near = (xx[None] - centres[:, 0, None, None]) ** 2 + (yy[None] - centres[:, 1, None, None]) ** 2
    central = (masked & (near <= CENTRAL_MASK_RADIUS**2)).any(axis=(1, 2))
    return (frac > MAX_MASKED_FRACTION) | central


def nan_flagged(columns: dict[str, np.ndarray], flags: np.ndarray, names: Sequence[str]) -> None:
    """Set ``names`` to NaN on the rows with ``flags != 0`` (in place)."""
    bad = flags != 0
    for c in names:
        if c in columns:
            columns[c][bad] = np.nan


def measure_cutouts(
    images: np.ndarray,
    weights: np.ndarray | None = None,
    bmasks: np.ndarray | None = None,
    *,
    origins: np.ndarray | None = None,
    centres: np.ndarray | None = None,
    gain: float | None = None,
    engine: str = DEFAULT_ENGINE,
    morphology: bool = False,
) -> dict[str, np.ndarray]:
    """The features of a stack of cutouts ``(n, S, S)`` with their optional weight and
    bad-mask maps: the :data:`FEATURE_COLUMNS` of
    :func:`~megalut_cli.measure.features.measure_stamps` on the stamps with masked pixels
    set to 0 (GalSim's badpix), ``skymad`` from the unmasked edge pixels, ``n_masked``,
    and with weights ``noise_weight`` (:func:`weight_noise`), which then gives ``snr``.
    Stamps :func:`too_masked` get MASKED_PIXELS. ``origins``: ``(n, 2)`` FITS 1-based
    ``(x, y)`` of each stamp's lower-left pixel in its image; ``centres``: the objects'
    0-based ``(col, row)`` in their stamps.
    """
    images = np.asarray(images, dtype=np.float64)
    n = len(images)
    clean, masked = clean_stamps(images, weights, bmasks)
    finite = np.isfinite(clean).all(axis=(1, 2)) if n else np.zeros(0, bool)
    skymad = masked_sky_mad(images, masked) if n else np.zeros(0)
    size = images.shape[1]
    feats = measure_stamps(
        clean,
        origins,
        gain,
        max_shift=default_max_shift(size),
        engine=engine,
        finite=finite,
        skymad=skymad,
    )
    feats[MASKED_COLUMN] = masked.reshape(n, -1).sum(axis=1).astype(np.int32)
    bad = too_masked(masked, centres)
    feats["flags"][bad] |= fl.MASKED_PIXELS
    nan_flagged(feats, feats["flags"], SOURCE_COLUMNS)
    if weights is not None:
        noise = weight_noise(np.asarray(weights), masked)
        feats[NOISE_COLUMN] = noise
        use = (feats["flags"] == 0) & np.isfinite(noise)
        feats["snr"][use] = signal_to_noise(
            feats["adamom_flux"][use], feats["adamom_sigma"][use], noise[use], gain
        )
    if morphology:
        feats.update(morphology_of_measured(clean, origins, feats))
    return feats


def psf_features(psfs: np.ndarray, engine: str = DEFAULT_ENGINE) -> dict[str, np.ndarray]:
    """``psf_adamom_g1, psf_adamom_g2, psf_adamom_sigma, psf_adamom_rho4`` of each PSF image
    ``(n, P, P)`` and ``flags`` (PSF_FAILED where it cannot be measured)."""
    psfs = np.asarray(psfs, dtype=np.float64)
    n = len(psfs)
    if psfs.ndim != 3 or psfs.shape[1] != psfs.shape[2]:
        raise InputError(f"PSF cutouts must be square, got {psfs.shape[1]}x{psfs.shape[2]}")
    res = measure_stamps(psfs, engine=engine) if n else {c: np.zeros(0) for c in FEATURE_COLUMNS}
    out = {p: np.asarray(res[p[len("psf_") :]], dtype=np.float64) for p in PSF_COLUMNS}
    out["flags"] = np.where(np.asarray(res["flags"]) != 0, fl.PSF_FAILED, 0).astype(np.int32)
    return out


def _measure_unit(unit: dict[str, Any]) -> dict[str, np.ndarray]:
    """Worker: read a unit's cutouts and measure them (features, PSF, metacal)."""
    layout: Layout = unit["layout"]
    stamps = read_stamps(layout)
    feats = measure_cutouts(
        stamps.images,
        stamps.weights,
        stamps.bmasks,
        origins=unit["origins"],
        centres=unit["centres"],
        gain=unit["gain"],
        engine=unit["engine"],
        morphology=unit["morphology"],
    )
    psfs = None
    if stamps.psfs is not None and unit.get("psf_source") == "file":
        psfs = stamps.psfs
    elif unit.get("psf_model_path") is not None or unit.get("psf_model") is not None:
        model = unit.get("psf_model") or cached_psf_model(unit["psf_model_path"])
        xy = unit["model_xy"]
        psfs = np.asarray(model.draw(xy[:, 0], xy[:, 1], layout.box_size), dtype=np.float64)
    if psfs is not None:
        psf = psf_features(psfs, unit["engine"])
        feats["flags"] |= psf.pop("flags")
        nan_flagged(feats, feats["flags"], SOURCE_COLUMNS + MORPHOLOGY_COLUMNS)
        feats.update(psf)
    mc = unit.get("metacal")
    if mc is not None:
        clean, _ = clean_stamps(stamps.images, stamps.weights, stamps.bmasks)
        feats.update(_metacal(unit, mc, clean, feats, psfs))
    return feats


def _metacal(
    unit: dict[str, Any],
    mc: dict[str, Any],
    clean: np.ndarray,
    feats: dict[str, np.ndarray],
    psfs: np.ndarray | None,
) -> dict[str, np.ndarray]:
    """The metacal columns ``X_<type>`` of a unit's cleaned stamps, with the unit's PSFs."""
    from megalut_cli.measure.metacal import (  # GalSim: metacal only
        dilated_sigma,
        fixnoise_seeds,
        metacal_features,
        target_psf_columns,
    )

    n, size = len(clean), unit["layout"].box_size
    names = list(FEATURE_COLUMNS) + (list(MORPHOLOGY_COLUMNS) if unit["morphology"] else [])
    out = {c: np.full(n, np.nan) for c in metacal_columns(names) if not c.startswith("flags_")}
    for kind in TYPES:
        out[f"flags_{kind}"] = np.zeros(n, dtype=np.int32)
    base = feats["flags"] & (fl.MASKED_PIXELS | fl.PSF_FAILED | fl.BAD_PIXELS)
    ok = base == 0
    noise = feats.get(NOISE_COLUMN, np.full(n, np.nan))
    noise = np.where(np.isfinite(noise), noise, feats["skymad"])
    if ok.any():
        if psfs is None:
            psf_images, index, sigma_t = mc["psf"], None, np.full(n, mc["target_sigma"])
        else:
            psf_images, index = distinct_psfs(same_parity_psfs(psfs[ok], size))
            sigma_t = dilated_sigma(feats["psf_adamom_sigma"], mc["step"])
        res = metacal_features(
            clean[ok],
            psf_images,
            mc["step"],
            noise_sigma=noise[ok],
            seeds=fixnoise_seeds(mc["seed"], unit["keys"][ok]),
            metacal_engine=unit["engine"],
            psf_index=index,
            morphology=unit["morphology"],
            origins=unit["origins"][ok],
            gain=unit["gain"],
            max_shift=default_max_shift(size),
            engine=unit["engine"],
        )
        for c, v in res.items():
            out[c][ok] = v
    else:
        sigma_t = np.full(n, np.nan)
    for kind in TYPES:
        out[f"flags_{kind}"] |= base
        nan_flagged(
            out, out[f"flags_{kind}"], [f"{c}_{kind}" for c in SOURCE_COLUMNS + MORPHOLOGY_COLUMNS]
        )
    if psfs is not None:  # per-object PSFs (one PSF for all: the caller adds its columns)
        out.update(target_psf_columns(np.where(ok, sigma_t, np.nan), size))
    return out


def extra_columns(meds: MedsFile) -> list[str]:
    """The scalar ``object_data`` columns outside the MEDS layout, passed through to the output
    (those named like a feature column are left out)."""
    own = (
        set(FEATURE_COLUMNS)
        | set(PSF_COLUMNS)
        | set(MORPHOLOGY_COLUMNS)
        | {MASKED_COLUMN, NOISE_COLUMN}
    )
    return [
        c
        for c, v in meds.objects.items()
        if c not in LAYOUT_COLUMNS and c not in own and v.ndim == 1
    ]


def distinct_psfs(psfs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct images of a PSF stack ``(n, P, P)`` and each stamp's index into them: objects
    sharing a PSF (a constant PSF, or one cutout per CCD) go through metacal's operation
    together."""
    flat = np.ascontiguousarray(psfs).reshape(len(psfs), -1)
    _, first, index = np.unique(
        flat.view(np.dtype((np.void, flat.shape[1] * flat.itemsize))).ravel(),
        return_index=True,
        return_inverse=True,
    )
    return psfs[first], index.ravel()


def same_parity_psfs(psfs: np.ndarray, size: int) -> np.ndarray:
    """PSF images ``(n, P, P)`` for stamps of ``size`` pixels: as they are when ``P`` has the
    parity of ``size``, else each redrawn (``lanczos15`` interpolation, no further pixel) on
    ``P + 1`` pixels with its profile's centre kept at the image's true centre, where metacal
    expects it (MEDS PSF cutouts are often odd-sized, boxes even)."""
    psfs = np.asarray(psfs, dtype=np.float64)
    if psfs.shape[1] % 2 == size % 2:
        return psfs
    import galsim

    p = psfs.shape[1] + 1
    out = np.empty((len(psfs), p, p))
    for i, img in enumerate(psfs):
        prof = galsim.InterpolatedImage(galsim.ImageD(img, scale=1.0), x_interpolant=INTERPOLANT)
        out[i] = prof.drawImage(nx=p, ny=p, scale=1.0, method="no_pixel").array
    return out


def _parity_check(psf_size: int, boxes: np.ndarray, what: str, names: Names | None) -> None:
    name = namer(names)
    odd = boxes % 2 != psf_size % 2
    if odd.any():
        raise InputError(
            f"{what}: a {psf_size}-pixel PSF for {int(boxes[odd][0])}-pixel MEDS cutouts: "
            "an even and an odd size put their centres half a pixel apart, which "
            f"{name('metacal')} cannot use; cut the PSF to a size of the same parity"
        )


@dataclasses.dataclass(frozen=True)
class MedsOptions:
    """What :func:`measure_meds` (and :func:`measure_meds_file`) measures of a MEDS file's
    objects: the ``measure`` options that apply to MEDS input."""

    cutout: int = MEASURE["cutout"].default
    gain: float | None = MEASURE["gain"].default
    psf_path: str | os.PathLike | None = None
    psf_model_path: str | os.PathLike | None = None
    engine: str = DEFAULT_ENGINE
    morphology: bool = MEASURE["morphology"].default
    metacal: bool = MEASURE["metacal"].default
    metacal_step: float = MEASURE["metacal_step"].default
    seed: int = MEASURE["seed"].default


def measure_meds(
    meds: MedsFile,
    options: MedsOptions | None = None,
    *,
    psf_model: PsfDrawer | None = None,
    nproc: int = 1,
    scheduler: str | None = None,
    progress: Progress | None = None,
    names: Names | None = None,
) -> dict[str, np.ndarray]:
    """The output columns of a MEDS file's objects, one row per object in file order: the
    :data:`PASSED_COLUMNS` and :data:`PASSED_CUTOUT_COLUMNS` it has, the features of its
    cutout ``options.cutout`` (:func:`measure_cutouts`), ``psf_adamom_*`` from its PSF
    cutouts, else ``psf_model`` (an object with :meth:`PsfDrawer.draw`, in this process) or
    the model file ``options.psf_model_path`` (loaded in each worker), else the single PSF
    image ``options.psf_path``; with ``options.metacal``, the metacal columns (per-object PSF,
    fixnoise at ``noise_weight`` where there are weights, else ``skymad``). Objects without
    the cutout get NO_CUTOUT and NaN features. ``options``: default :class:`MedsOptions`.
    """
    options = options or MedsOptions()
    name = namer(names)
    obj, n = meds.objects, len(meds)
    if options.cutout < 0:
        raise ConfigError(f"{name('cutout')} must be 0 or more, got {options.cutout}")
    has = np.asarray(obj["ncutout"]) > options.cutout
    if options.cutout >= meds.n_max or not has.any():
        raise InputError(
            f"{meds.path}: no object has a cutout {options.cutout} ({name('cutout')}; "
            f"at most {meds.n_max} per object)"
        )
    model_given = psf_model is not None or options.psf_model_path is not None
    if options.psf_path is not None and model_given:
        raise ConfigError(f"give {name('psf_path')} or {name('psf_model_path')}, not both")
    if model_given:
        source: str | None = "model"
    elif options.psf_path is not None:
        source = "single"
    else:
        source = "file" if meds.has("psf") else None
    if meds.has("psf") and source != "file":
        log.info(
            "%s: the PSF cutouts of the file are not used: the PSF comes from %s",
            meds.path,
            name("psf_model_path") if source == "model" else name("psf_path"),
        )
    if options.metacal and source is None:
        raise ConfigError(
            f"{name('metacal')} needs a PSF: PSF cutouts in the MEDS file, {name('psf_path')} "
            f"or {name('psf_model_path')}"
        )
    what = (
        "the coadd"
        if options.cutout == 0 and meds.first_is_coadd()
        else (
            "the first cutout; the file does not mark it as a coadd"
            if options.cutout == 0
            else "a single-epoch cutout"
        )
    )
    log.info(
        "%s: measuring cutout %d (%s) of each of %d objects",
        meds.path,
        options.cutout,
        what,
        int(has.sum()),
    )
    if (~has).any():
        log.warning(
            "%s: %d object(s) without cutout %d: flagged NO_CUTOUT",
            meds.path,
            int((~has).sum()),
            options.cutout,
        )

    rows_all = np.arange(n)
    box = obj["box_size"].astype(np.int64)
    k = options.cutout

    def per_cutout(c: str, default: np.ndarray) -> np.ndarray:
        return obj[c][:, k].astype(np.float64) if c in obj else default

    centre = (box - 1) / 2.0
    crow, ccol = per_cutout("cutout_row", centre), per_cutout("cutout_col", centre)
    orow, ocol = per_cutout("orig_row", crow), per_cutout("orig_col", ccol)
    origins = np.stack([ocol - ccol + 1.0, orow - crow + 1.0], axis=1)
    centres = np.stack([ccol, crow], axis=1)
    model_xy = np.stack([ocol + 1.0, orow + 1.0], axis=1)

    if options.psf_model_path is not None:  # load (and check) it here, before the long work
        model = cached_psf_model(str(options.psf_model_path))
        far = model.outside(model_xy[has, 0], model_xy[has, 1])
        if far.any():
            log.warning(
                "%s: %d of %d object(s) lie outside the area of the stars the model was fit to: "
                "its PSF there is an extrapolation",
                options.psf_model_path,
                int(far.sum()),
                int(has.sum()),
            )

    single = None
    mc: dict[str, Any] | None = None
    if source == "single":  # checked and measured before the long work
        single = single_psf_stamp(str(options.psf_path), int(box[has][0]))
        single_values = single_psf_features(str(options.psf_path), int(box[has][0]), options.engine)
    if options.metacal:
        top = MEASURE["metacal_step"].maximum
        if not 0 < options.metacal_step <= top:
            raise ConfigError(
                f"{name('metacal_step')} must be in (0, {top}], got {options.metacal_step}"
            )
        mc = {"step": float(options.metacal_step), "seed": int(options.seed)}
        if single is not None:
            from megalut_cli.measure.metacal import target_psf_sigma  # GalSim: metacal only

            _parity_check(single.shape[0], np.unique(box[has]), str(options.psf_path), names)
            mc["psf"] = single
            mc["target_sigma"] = target_psf_sigma(single, options.metacal_step)
        elif source == "file":
            shapes = meds.psf_shapes(k)[has]
            if np.any(shapes[:, 0] != shapes[:, 1]):
                raise InputError(f"{meds.path}: PSF cutouts must be square for {name('metacal')}")

    # work units: objects with the cutout, grouped by box size (and PSF cutout size)
    psf_shape = meds.psf_shapes(k) if source == "file" else np.zeros((n, 2), np.int64)
    keys = np.stack([box, psf_shape[:, 0], psf_shape[:, 1]], axis=1)
    groups: list[np.ndarray] = []
    for key in np.unique(keys[has], axis=0):
        groups.append(rows_all[has & np.all(keys == key, axis=1)])
    workers = 2 if scheduler else resolve_nproc(nproc)
    n_units = max(
        -(-int(has.sum()) // CHUNK_OBJECTS), min(4 * workers, int(has.sum())) if workers > 1 else 1
    )
    pieces: list[np.ndarray] = []
    for g in groups:
        share = max(1, round(n_units * len(g) / max(int(has.sum()), 1)))
        pieces += [p for p in np.array_split(g, min(share, len(g))) if len(p)]
    file_meds = dataclasses.replace(meds, path=os.path.abspath(meds.path))
    units = []
    for p in pieces:
        unit: dict[str, Any] = {
            "layout": file_meds.layout(p, options.cutout, psf=source == "file"),
            "origins": origins[p],
            "centres": centres[p],
            "gain": options.gain,
            "engine": options.engine,
            "morphology": options.morphology,
            "keys": p.astype(np.int64),
            "psf_source": source,
        }
        if source == "model":
            if psf_model is not None:
                unit["psf_model"] = psf_model
            else:
                unit["psf_model_path"] = os.path.abspath(str(options.psf_model_path))
            unit["model_xy"] = model_xy[p]
        if mc is not None:
            unit["metacal"] = mc
        units.append(unit)
    if source == "model" and psf_model is not None and (nproc != 1 or scheduler):
        nproc, scheduler = 1, None  # an object in memory: measured in this process

    names_out = (
        list(FEATURE_COLUMNS) + [MASKED_COLUMN] + ([NOISE_COLUMN] if meds.has("weight") else [])
    )
    names_out += list(MORPHOLOGY_COLUMNS) if options.morphology else []
    psf_cols = list(PSF_COLUMNS) if source is not None else []
    out: dict[str, np.ndarray] = {}
    for c in PASSED_COLUMNS:
        if c in obj:
            out[c] = obj[c]
    for c in PASSED_CUTOUT_COLUMNS:
        if c in obj:
            out[c] = np.where(has, obj[c][:, k].astype(np.float64), np.nan)
    for c in extra_columns(meds):
        out[c] = obj[c]
    cols: dict[str, np.ndarray] = {}
    for c in names_out + psf_cols:
        if c == "flags":
            cols[c] = np.where(has, 0, fl.NO_CUTOUT).astype(np.int32)
        elif c == MASKED_COLUMN:
            cols[c] = np.full(n, NO_CUTOUT_MASKED, dtype=np.int32)
        else:
            cols[c] = np.full(n, np.nan)
    if mc is not None:
        morph = list(MORPHOLOGY_COLUMNS) if options.morphology else []
        for c in metacal_columns(names_out[: len(FEATURE_COLUMNS)] + morph):
            cols[c] = (
                np.where(has, 0, fl.NO_CUTOUT).astype(np.int32)
                if c.startswith("flags_")
                else np.full(n, np.nan)
            )
        for c in metacal_columns(psf_cols):
            cols[c] = np.full(n, np.nan)

    t0 = time.perf_counter()
    with (
        executor(nproc, scheduler, len(units)) as pool,
        (progress or no_progress)("measuring MEDS objects", int(has.sum())) as update,
    ):
        sizes = iter([len(p) for p in pieces])
        results = map_units(_measure_unit, units, pool, lambda _n: update(next(sizes)))
    dt = time.perf_counter() - t0
    if has.any():
        log.info(
            "measured %d objects in %.1f s (%.2f ms/object)",
            int(has.sum()),
            dt,
            1e3 * dt / int(has.sum()),
        )
    for piece, res in zip(pieces, results):
        for c, v in res.items():
            if c in cols:
                cols[c][piece] = v
    if single is not None:
        for c in PSF_COLUMNS:
            cols[c][:] = single_values[c]
        if mc is not None:
            from megalut_cli.measure.metacal import target_psf_columns  # GalSim: metacal only

            for b in np.unique(box[has]):
                rows = has & (box == b)
                for c, v in target_psf_columns(
                    np.full(int(rows.sum()), mc["target_sigma"]), int(b)
                ).items():
                    cols[c][rows] = v
    out.update(cols)
    return out


def measure_meds_file(
    meds_path: str | os.PathLike,
    output: str | os.PathLike,
    options: MedsOptions | None = None,
    *,
    nproc: int = 1,
    scheduler: str | None = None,
    overwrite: bool = False,
    progress: Progress | None = None,
    device: str = DEFAULT_DEVICE,
    names: Names | None = None,
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Measure the objects of the MEDS file ``meds_path`` (:func:`measure_meds`) and write
    the features catalog ``output`` (format ``megalut.features``, one row per object).
    Returns the columns written and the header cards added."""
    options = options or MedsOptions()
    name = namer(names)
    check_output(output, overwrite)
    if options.gain is not None and not (math.isfinite(options.gain) and options.gain > 0):
        raise ConfigError(f"{name('gain')} must be a positive number, got {options.gain}")
    if device == "gpu":
        log.info(
            "MEDS input is measured on the CPU (masked stamps); %s gpu is not used here",
            name("device"),
        )
    meds = read_meds(meds_path)
    columns = measure_meds(
        meds, options, nproc=nproc, scheduler=scheduler, progress=progress, names=names
    )
    flags = columns["flags"]
    log.info("%d of %d objects flagged (features NaN)", int((flags != 0).sum()), len(flags))
    warn_if_mostly_flagged(flags, str(meds_path), names)
    boxes = np.unique(meds.objects["box_size"])
    cards: dict[str, Any] = {
        FILE_CARD: (os.path.basename(str(meds_path)), "MEDS file measured"),
        CUTOUT_CARD: (int(options.cutout), "MEDS cutout index measured (0: coadd or first)"),
        COADD_CARD: (
            bool(options.cutout == 0 and meds.first_is_coadd()),
            "the measured cutouts are coadds",
        ),
        "STAMPSZ": (int(boxes[0]), "stamp size [pixels]") if len(boxes) == 1 else None,
        "GAIN": (options.gain, "gain [e-/ADU] of the S/N (Eq. 8)")
        if options.gain is not None
        else None,
        "MAXSHIFT": (default_max_shift(int(boxes[0])), "centroid shift limit [pixels]")
        if len(boxes) == 1
        else None,
        "MENGINE": (options.engine, "engine of the adaptive moments (megalut --engine)"),
        "NOISEWT": (meds.has("weight"), "snr from the weight-map noise (noise_weight)"),
        "MASKFRAC": (MAX_MASKED_FRACTION, "masked fraction above which MASKED_PIXELS"),
        "MASKRAD": (CENTRAL_MASK_RADIUS, "masked pixel this close to centre: MASKED_PIXELS"),
    }
    if options.psf_model_path is not None:
        cards.update(cached_psf_model(str(options.psf_model_path)).header_cards())
    if options.metacal:
        cards.update(metacal_cards(options.metacal_step, options.seed, "measure"))
    write_catalog(
        output, columns, fmt=FORMAT, fmt_version=FORMAT_VERSION, overwrite=overwrite, cards=cards
    )
    log.info("wrote %s (%d rows)", output, len(flags))
    return columns, cards


def _as_cutout_lists(stamps: Any, n: int | None, what: str) -> list[list[np.ndarray]] | None:
    """``stamps`` as one list of 2-D arrays per object: an ``(n, S, S)`` array is one cutout
    per object; a sequence holds each object's cutouts (a 2-D array or a list of them)."""
    if stamps is None:
        return None
    if isinstance(stamps, np.ndarray) and stamps.ndim == 3:
        out = [[s] for s in stamps]
    else:
        out = [[np.asarray(c)] if np.ndim(c) == 2 else [np.asarray(s) for s in c] for c in stamps]
    if n is not None and len(out) != n:
        raise ValueError(f"{what}: {len(out)} objects, expected {n}")
    return out


def write_meds(
    path: str | os.PathLike,
    images: Any,
    weights: Any = None,
    bmasks: Any = None,
    psfs: Any = None,
    ids: Sequence[int] | np.ndarray | None = None,
    *,
    segs: Any = None,
    numbers: Sequence[int] | np.ndarray | None = None,
    orig_rows: Any = None,
    orig_cols: Any = None,
    ra: Sequence[float] | np.ndarray | None = None,
    dec: Sequence[float] | np.ndarray | None = None,
    first_is_coadd: bool = True,
    pixel_scale: float = 1.0,
    extra: Mapping[str, Any] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write the subset of MEDS megalut reads, for tests and examples.

    ``images``: an ``(n, S, S)`` array (one cutout per object) or, per object, a list of its
    cutouts (2-D arrays of one box size; an empty list: no cutout). ``weights``, ``bmasks``,
    ``segs`` and ``psfs`` (PSF images, any size) follow the same structure. ``ids`` default
    to ``1..n``, ``numbers`` (segmentation numbers) too. ``orig_rows``, ``orig_cols``: the
    0-based position of each object in the image of each cutout, ``(n,)`` or ``(n, NMAX)``
    (default: the cutout centre, i.e. the cutout is the image); ``ra``, ``dec`` (degrees)
    are written when given, and ``extra`` scalar columns (name -> ``(n,)`` values, e.g. a
    simulation's truth) after the layout's. The jacobian is
    ``pixel_scale`` on the diagonal (``dudcol = dvdrow``); ``metadata`` records
    ``first_is_coadd`` and ``image_info`` one image per cutout slot (0: ``coadd``).
    Written atomically; an existing ``path`` is refused without ``overwrite``.
    """
    imgs = _as_cutout_lists(images, None, "images")
    assert imgs is not None
    n = len(imgs)
    maps = {
        "weight": _as_cutout_lists(weights, n, "weights"),
        "bmask": _as_cutout_lists(bmasks, n, "bmasks"),
        "seg": _as_cutout_lists(segs, n, "segs"),
    }
    psf_lists = _as_cutout_lists(psfs, n, "psfs")
    ncut = np.array([len(c) for c in imgs], dtype=np.int64)
    nmax = max(int(ncut.max()) if n else 1, 1)
    if not ncut.sum():
        raise ValueError("write_meds needs at least one cutout")
    boxes = np.zeros(n, dtype=np.int64)
    for i, cuts in enumerate(imgs):
        shapes = {c.shape for c in cuts}
        if len(shapes) > 1 or any(s[0] != s[1] for s in shapes):
            raise ValueError(
                f"object {i}: cutouts must be square and of one size, got {sorted(shapes)}"
            )
        boxes[i] = next(iter(shapes))[0] if shapes else (boxes[i - 1] if i else 32)
        for kind, lists in maps.items():
            if lists is not None and [c.shape for c in lists[i]] != [c.shape for c in cuts]:
                raise ValueError(f"object {i}: {kind} cutouts do not match the image cutouts")
        if psf_lists is not None and len(psf_lists[i]) != len(cuts):
            raise ValueError(f"object {i}: {len(psf_lists[i])} PSF images for {len(cuts)} cutouts")

    def slots(values: Any, default: np.ndarray) -> np.ndarray:
        if values is None:
            return default
        arr = np.asarray(values, dtype=np.float64)
        return np.repeat(arr[:, None], nmax, axis=1) if arr.ndim == 1 else arr[:, :nmax]

    dtype: list[Any] = [
        ("id", "i8"),
        ("number", "i4"),
        ("box_size", "i8"),
        *([("ra", "f8"), ("dec", "f8")] if ra is not None and dec is not None else []),
        ("ncutout", "i8"),
        ("file_id", "i8", (nmax,)),
        ("start_row", "i8", (nmax,)),
        ("orig_row", "f8", (nmax,)),
        ("orig_col", "f8", (nmax,)),
        ("orig_start_row", "i8", (nmax,)),
        ("orig_start_col", "i8", (nmax,)),
        ("cutout_row", "f8", (nmax,)),
        ("cutout_col", "f8", (nmax,)),
        ("dudrow", "f8", (nmax,)),
        ("dudcol", "f8", (nmax,)),
        ("dvdrow", "f8", (nmax,)),
        ("dvdcol", "f8", (nmax,)),
    ]
    if psf_lists is not None:
        dtype += [
            ("psf_box_size", "i8"),
            ("psf_row_size", "i8", (nmax,)),
            ("psf_col_size", "i8", (nmax,)),
            ("psf_start_row", "i8", (nmax,)),
            ("psf_cutout_row", "f8", (nmax,)),
            ("psf_cutout_col", "f8", (nmax,)),
        ]
    extra = {c: np.asarray(v) for c, v in (extra or {}).items()}
    clash = sorted(set(extra) & LAYOUT_COLUMNS)
    if clash or any(v.shape != (n,) for v in extra.values()):
        raise ValueError(
            "extra columns must be (n,) arrays outside the MEDS layout "
            f"(got {clash or list(extra)})"
        )
    dtype += [(c, v.dtype.str) for c, v in extra.items()]
    od = np.zeros(n, dtype=dtype)
    for c in od.dtype.names:
        if c not in ("ncutout",):
            od[c] = -9999  # the meds package's default value
    od["id"] = np.arange(1, n + 1) if ids is None else np.asarray(ids)
    od["number"] = np.arange(1, n + 1) if numbers is None else np.asarray(numbers)
    od["box_size"], od["ncutout"] = boxes, ncut
    for c, v in extra.items():
        od[c] = v
    if ra is not None and dec is not None:
        od["ra"], od["dec"] = np.asarray(ra), np.asarray(dec)
    centre = np.repeat(((boxes - 1) / 2.0)[:, None], nmax, axis=1)
    orow, ocol = slots(orig_rows, centre), slots(orig_cols, centre)
    start, pstart = 0, 0
    for i, cuts in enumerate(imgs):
        b = int(boxes[i])
        for k in range(len(cuts)):
            od["file_id"][i, k] = k
            od["start_row"][i, k] = start
            start += b * b
            od["cutout_row"][i, k] = od["cutout_col"][i, k] = (b - 1) / 2.0
            od["orig_row"][i, k], od["orig_col"][i, k] = orow[i, k], ocol[i, k]
            od["orig_start_row"][i, k] = int(round(orow[i, k] - (b - 1) / 2.0))
            od["orig_start_col"][i, k] = int(round(ocol[i, k] - (b - 1) / 2.0))
            od["dudrow"][i, k] = od["dvdcol"][i, k] = 0.0
            od["dudcol"][i, k] = od["dvdrow"][i, k] = pixel_scale
            if psf_lists is not None:
                p = psf_lists[i][k]
                od["psf_row_size"][i, k], od["psf_col_size"][i, k] = p.shape
                od["psf_start_row"][i, k] = pstart
                od["psf_cutout_row"][i, k] = (p.shape[0] - 1) / 2.0
                od["psf_cutout_col"][i, k] = (p.shape[1] - 1) / 2.0
                pstart += p.size
        if psf_lists is not None and psf_lists[i]:
            od["psf_box_size"][i] = psf_lists[i][0].shape[0]

    info = np.zeros(
        nmax,
        dtype=[
            ("image_path", "S16"),
            ("image_ext", "i2"),
            ("image_id", "i8"),
            ("image_flags", "i8"),
            ("magzp", "f4"),
            ("scale", "f4"),
            ("position_offset", "f8"),
        ],
    )
    info["image_path"] = [
        ("coadd" if k == 0 and first_is_coadd else f"epoch_{k}").encode() for k in range(nmax)
    ]
    info["image_id"] = np.arange(nmax)
    info["magzp"], info["scale"], info["position_offset"] = 30.0, 1.0, 1.0
    meta = np.zeros(
        1,
        dtype=[
            ("medsconf", "S16"),
            ("first_image_is_coadd", "i2"),
            ("creator", f"S{len(CREATOR)}"),
        ],
    )
    meta["medsconf"], meta["first_image_is_coadd"], meta["creator"] = (
        b"megalut",
        int(first_is_coadd),
        CREATOR.encode(),
    )

    def flat(lists: list[list[np.ndarray]], dtype: str) -> np.ndarray:
        parts = [np.asarray(c, dtype=dtype).ravel() for cuts in lists for c in cuts]
        return np.concatenate(parts) if parts else np.zeros(0, dtype=dtype)

    with atomic_output(path, overwrite) as tmp, fitsio.FITS(str(tmp), "rw", clobber=True) as f:
        f.write(od, extname="object_data")
        f.write(info, extname="image_info")
        f.write(meta, extname="metadata")
        f.write(flat(imgs, "f4"), extname="image_cutouts")
        for kind, dt in (("weight", "f4"), ("seg", "i4"), ("bmask", "i4")):
            lists = maps[kind]
            if lists is not None:
                f.write(flat(lists, dt), extname=CUTOUT_EXTENSIONS[kind])
        if psf_lists is not None:
            f.write(flat(psf_lists, "f4"), extname="psf")
    return Path(path)
