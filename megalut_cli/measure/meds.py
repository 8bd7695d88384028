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
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import fitsio
import numpy as np

from megalut_cli import flags as fl
from megalut_cli.atomic import atomic_output
from megalut_cli.catalog import is_fits_file
from megalut_cli.engine import DEFAULT_ENGINE
from megalut_cli.errors import ConfigError, InputError, Names, namer
from megalut_cli.measure.defaults import FORMAT, PSF_COLUMNS
from megalut_cli.measure.feature_sets import column_descriptions, optional_columns
from megalut_cli.measure.features import FEATURE_COLUMNS, warn_if_mostly_flagged
from megalut_cli.measure.masks import (
    CENTRAL_MASK_RADIUS,
    MASK_DISTANCE_COLUMN,
    MASKED_COLUMN,
    MAX_MASKED_FRACTION,
    NOISE_COLUMN,
    masked_pixels,
)
from megalut_cli.measure.measurer import (
    Measurer,
    MeasureSettings,
    MetacalSettings,
    PsfImages,
    StampBatch,
    distinct_psfs,
    measure_cards,
    metacal_cards,
    metacal_columns,
)
from megalut_cli.measure.options import MEASURE
from megalut_cli.measure.psf_model import cached_psf_model
from megalut_cli.measure.single_psf import single_psf_features, single_psf_stamp
from megalut_cli.measure.source_registry import (
    Measured,
    MeasureRequest,
    StampSourceType,
    register_stamp_source,
)
from megalut_cli.measure.units import empty_columns, measure_units, n_units, workers
from megalut_cli.progress import Progress
from megalut_cli.provenance import CREATOR, sha256_file
from megalut_cli.shear.frame import JACOBIAN_COLUMNS, usable_jacobians

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
    *JACOBIAN_COLUMNS,
)
#: Per-object columns copied to the output when the file has them.
PASSED_COLUMNS: tuple[str, ...] = ("id", "number", "box_size", "ncutout", "ra", "dec")
#: Per-cutout columns copied to the output (the measured cutout's value; NaN without one):
#: its position and the Jacobian that turns its shears to the world frame.
PASSED_CUTOUT_COLUMNS: tuple[str, ...] = ("orig_row", "orig_col", *JACOBIAN_COLUMNS)
#: The ``object_data`` columns of the MEDS layout (esheldon/meds README); any other scalar
#: column (a survey's own ids, a simulation's truth) is passed through to the output.
LAYOUT_COLUMNS: frozenset[str] = frozenset(
    (
        *OBJECT_COLUMNS,
        "orig_start_row",
        "orig_start_col",
        "psf_cutout_row",
        "psf_cutout_col",
    )
)

#: Value of ``n_masked`` for an object without the measured cutout.
NO_CUTOUT_MASKED = -1

#: Header cards of a catalog measured from a MEDS file.
CUTOUT_CARD = "MEDSCUT"
COADD_CARD = "MEDSCOAD"
FILE_CARD = "MEDSFILE"
FILE_SHA_CARD = "MEDSSHA"


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


def meds_extensions(path: str | os.PathLike) -> int:
    """How many of the :data:`MEDS_EXTENSIONS` the FITS file ``path`` has (0 for a file that
    is missing, unreadable or not FITS: the image reader then says why)."""
    try:
        if not is_fits_file(path):
            return 0
        with fitsio.FITS(str(path)) as f:
            return sum(ext in f for ext in MEDS_EXTENSIONS)
    except (InputError, OSError, ValueError):
        return 0


def is_meds(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a MEDS file: a FITS file with ``object_data`` and ``image_cutouts``
    extensions."""
    return meds_extensions(path) == len(MEDS_EXTENSIONS)


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
                raise InputError(
                    f"{path}: an incomplete MEDS file (no {', '.join(missing)} extension)"
                )
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
        *JACOBIAN_COLUMNS,
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
    order = np.argsort(starts[used], kind="stable")
    overlap = np.flatnonzero(starts[used][order][1:] < ends[used][order][:-1])
    if len(overlap):
        row = int(np.nonzero(used)[0][order][overlap[0]])
        raise InputError(
            f"{path}: MEDS box_size disagrees with the cutout layout: object {row}'s "
            f"{int(box[row])}x{int(box[row])} cutout runs into the next cutout's start_row"
        )
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


@dataclasses.dataclass(frozen=True)
class MedsUnit:
    """Cutout ``layout`` of some objects (one box size and PSF size) measured into the output
    ``rows``: their ``origins`` in their images, ``centres`` in their cutouts, their PSF:
    ``psf_source`` ``file`` (the file's PSF cutouts), ``model`` (``psf_model`` in this
    process, else the file ``psf_model_path``, drawn at ``model_xy``) or ``single`` (one
    image), and the keys of their fixnoise fields (one per object and cutout)."""

    rows: np.ndarray
    layout: Layout
    origins: np.ndarray
    centres: np.ndarray
    psf_source: str | None = None
    single: np.ndarray | None = None
    psf_model_path: str | None = None
    psf_model: PsfDrawer | None = None
    model_xy: np.ndarray | None = None
    fixnoise_keys: np.ndarray | None = None

    def batch(self, settings: MeasureSettings) -> StampBatch:
        """The unit's cutouts with their masks, weights and PSFs."""
        stamps = read_stamps(self.layout)
        masked = masked_pixels(stamps.weights, stamps.bmasks, stamps.images.shape)
        psfs = None
        if self.psf_source == "file" and stamps.psfs is not None:
            psfs = PsfImages(*distinct_psfs(stamps.psfs))
        elif self.psf_source == "model" and self.model_xy is not None:
            model = self.psf_model or cached_psf_model(str(self.psf_model_path))
            xy, size = self.model_xy, self.layout.box_size
            drawn = np.asarray(model.draw(xy[:, 0], xy[:, 1], size), dtype=np.float64)
            psfs = PsfImages(drawn, np.arange(len(drawn)))
        elif self.psf_source == "single" and self.single is not None:
            psfs = PsfImages(self.single[None], np.zeros(len(self.rows), dtype=np.int64))
        keys = self.rows if self.fixnoise_keys is None else self.fixnoise_keys
        return StampBatch(
            stamps.images,
            self.origins,
            masked=masked,
            centres=self.centres,
            weights=stamps.weights,
            psfs=psfs,
            fixnoise_keys=keys.astype(np.int64),
        )


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
    feature_sets: Sequence[str] = (),
) -> dict[str, np.ndarray]:
    """The features of a stack of cutouts ``(n, S, S)`` with their optional weight and
    bad-mask maps (:class:`~.measurer.Measurer` with a mask): the :data:`FEATURE_COLUMNS`
    with masked pixels set to 0 (GalSim's badpix), ``skymad`` from the unmasked edge pixels,
    ``n_masked``, and with weights ``noise_weight``, which then gives ``snr``; stamps too
    masked get MASKED_PIXELS. ``origins``: ``(n, 2)`` FITS 1-based ``(x, y)`` of each stamp's
    lower-left pixel in its image; ``centres``: the objects' 0-based ``(col, row)`` in their
    stamps."""
    images = np.asarray(images, dtype=np.float64)
    n = len(images)
    sets = tuple(feature_sets) + (("morphology",) if morphology else ())
    settings = MeasureSettings(gain, engine, feature_sets=sets)
    batch = StampBatch(
        images,
        np.ones((n, 2)) if origins is None else np.asarray(origins, dtype=np.float64),
        masked=masked_pixels(weights, bmasks, images.shape),
        centres=centres,
        weights=weights,
    )
    return Measurer(settings).measure(batch)


def extra_columns(meds: MedsFile) -> list[str]:
    """The scalar ``object_data`` columns outside the MEDS layout, passed through to the output
    (those named like a feature column are left out)."""
    own = set(column_descriptions()) | set(PSF_COLUMNS)
    own |= {MASKED_COLUMN, NOISE_COLUMN, MASK_DISTANCE_COLUMN}
    return [
        c
        for c, v in meds.objects.items()
        if c not in LAYOUT_COLUMNS and c not in own and v.ndim == 1
    ]


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
    feature_sets: tuple[str, ...] = ()
    epochs: bool = MEASURE["epochs"].default
    moments_retry: float = MEASURE["moments_retry"].default
    #: a masked pixel of the stamp this close to the object flags NEAR_MASK (0: never)
    mask_margin: float = 0.0


def epoch_cutouts(meds: MedsFile) -> list[int]:
    """The single-epoch cutout indices some object has: all but cutout 0 when the file marks
    it as a coadd."""
    first = 1 if meds.first_is_coadd() else 0
    ncut = np.asarray(meds.objects["ncutout"])
    return [k for k in range(first, meds.n_max) if np.any(ncut > k)]


def measure_epochs(
    meds: MedsFile,
    options: MedsOptions | None = None,
    *,
    psf_model: PsfDrawer | None = None,
    nproc: int = 1,
    scheduler: str | None = None,
    progress: Progress | None = None,
    names: Names | None = None,
) -> dict[str, np.ndarray]:
    """Every single-epoch cutout of every object (:func:`epoch_cutouts`), each measured as
    :func:`measure_meds` measures one cutout, with its own PSF, weight map and Jacobian: one
    row per object and epoch, in object order then cutout order, with the cutout index in
    ``cutout``; objects without any epoch have no row. The setup that does not depend on the
    cutout is done once (:func:`meds_plan`), and the epochs' work units run together."""
    options = options or MedsOptions()
    ks = epoch_cutouts(meds)
    if not ks:
        raise InputError(
            f"{meds.path}: no single-epoch cutout to measure (each object has only "
            f"{'the coadd' if meds.first_is_coadd() else 'no cutout'})"
        )
    ncut = np.asarray(meds.objects["ncutout"])
    log.info("%s: measuring %d single-epoch cutout slot(s): %s", meds.path, len(ks), ks)
    plan = meds_plan(meds, options, ks, psf_model=psf_model, names=names)
    n_workers = workers(nproc, scheduler)
    units: list[MedsUnit] = []
    epochs: list[tuple[int, np.ndarray, slice]] = []  # cutout, who has it, its output rows
    start = 0
    for k in ks:
        has = ncut > k
        rows = np.full(len(meds), -1, dtype=np.int64)  # each object's output row
        rows[has] = start + np.arange(int(has.sum()))
        units += cutout_units(plan, k, has, rows, n_workers, names)
        epochs.append((k, has, slice(start, start + int(has.sum()))))
        start = epochs[-1][2].stop
    measured = _measured_columns(plan, units, start, None, nproc, scheduler, progress)
    parts: list[dict[str, np.ndarray]] = []
    objects: list[np.ndarray] = []
    for k, has, block in epochs:
        part = {c: v[has] for c, v in passed_columns(meds, has, k).items()}
        part.update({c: v[block] for c, v in measured.items()})
        part["cutout"] = np.full(int(has.sum()), k, dtype=np.int32)
        parts.append(part)
        objects.append(np.flatnonzero(has))
    order = np.argsort(np.concatenate(objects), kind="stable")  # object order, then cutout order
    names_out = list(parts[0])
    return {c: np.concatenate([p[c] for p in parts])[order] for c in names_out}


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
    n, k = len(meds), options.cutout
    if k < 0:
        raise ConfigError(f"{name('cutout')} must be 0 or more, got {k}")
    has = np.asarray(meds.objects["ncutout"]) > k
    if k >= meds.n_max or not has.any():
        raise InputError(
            f"{meds.path}: no object has a cutout {k} ({name('cutout')}; "
            f"at most {meds.n_max} per object)"
        )
    plan = meds_plan(meds, options, [k], psf_model=psf_model, names=names)
    units = cutout_units(plan, k, has, np.arange(n), workers(nproc, scheduler), names)
    if (~has).any():
        log.warning(
            "%s: %d object(s) without cutout %d: flagged NO_CUTOUT",
            meds.path,
            int((~has).sum()),
            k,
        )
    out = passed_columns(meds, has, k)
    out.update(_measured_columns(plan, units, n, has, nproc, scheduler, progress))
    return out


@dataclasses.dataclass(frozen=True)
class MedsPlan:
    """What measuring cutouts of a MEDS file sets up once, whichever the cutout
    (:func:`meds_plan`): the file as given and with its path absolute (as the workers open
    it), the options, where the PSFs come from (``source``: the file's PSF cutouts ``file``,
    a ``model``, one ``single`` image, or None), the model in this process (``psf_model``) or
    its file for the workers (``model_path``), the single PSF image by the box size it was
    cut for, what is measured and the columns measured."""

    meds: MedsFile
    worker_meds: MedsFile
    options: MedsOptions
    source: str | None
    psf_model: PsfDrawer | None
    model_path: str | None
    singles: dict[int, np.ndarray]
    settings: MeasureSettings
    columns: list[str]


def meds_plan(
    meds: MedsFile,
    options: MedsOptions,
    cutouts: Sequence[int],
    *,
    psf_model: PsfDrawer | None = None,
    names: Names | None = None,
) -> MedsPlan:
    """The :class:`MedsPlan` of measuring the ``cutouts`` (indices) of ``meds``, checked: one
    PSF source, a PSF for ``metacal`` and its step, the single PSF image read and measured
    (for the box size of the first object with each cutout) before the long work."""
    name = namer(names)
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
    singles: dict[int, np.ndarray] = {}
    if source == "single":  # checked and measured before the long work
        box = meds.objects["box_size"].astype(np.int64)
        ncut = np.asarray(meds.objects["ncutout"])
        for k in cutouts:
            size = int(box[ncut > k][0])
            if size not in singles:
                singles[size] = single_psf_stamp(str(options.psf_path), size)
                single_psf_features(str(options.psf_path), size, options.engine)
    if options.metacal:
        top = MEASURE["metacal_step"].maximum
        if not 0 < options.metacal_step <= top:
            raise ConfigError(
                f"{name('metacal_step')} must be in (0, {top}], got {options.metacal_step}"
            )
    settings = meds_settings(options)
    columns = list(FEATURE_COLUMNS) + [MASKED_COLUMN]
    columns += [MASK_DISTANCE_COLUMN] if settings.mask_margin > 0 else []
    columns += [NOISE_COLUMN] if meds.has("weight") else []
    columns += list(optional_columns(settings.feature_sets))
    psf_cols = list(PSF_COLUMNS) if source is not None else []
    columns += psf_cols
    if settings.metacal is not None:
        columns += metacal_columns(settings.feature_columns) + metacal_columns(psf_cols)
    model_path = (
        os.path.abspath(str(options.psf_model_path))
        if source == "model" and psf_model is None
        else None
    )
    return MedsPlan(
        meds,
        dataclasses.replace(meds, path=os.path.abspath(meds.path)),
        options,
        source,
        psf_model,
        model_path,
        singles,
        settings,
        columns,
    )


def cutout_units(
    plan: MedsPlan,
    k: int,
    has: np.ndarray,
    rows: np.ndarray,
    n_workers: int,
    names: Names | None = None,
) -> list[MedsUnit]:
    """The work units of cutout ``k`` of the objects that have it (``has``), measured into
    the output ``rows`` (one per object), for ``n_workers``: objects grouped by box size (and
    PSF cutout size), each group cut into its share of the units. Checks what depends on the
    cutout: the PSF model's area, the parity of a single PSF and the squareness of the
    file's PSF cutouts for ``metacal``."""
    name = namer(names)
    meds, options, source = plan.meds, plan.options, plan.source
    obj, n = meds.objects, len(meds)
    what = (
        "the coadd"
        if k == 0 and meds.first_is_coadd()
        else (
            "the first cutout; the file does not mark it as a coadd"
            if k == 0
            else "a single-epoch cutout"
        )
    )
    log.info(
        "%s: measuring cutout %d (%s) of each of %d objects",
        meds.path,
        k,
        what,
        int(has.sum()),
    )
    box = obj["box_size"].astype(np.int64)

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
    single = plan.singles[int(box[has][0])] if source == "single" else None
    if options.metacal:
        if single is not None:
            _parity_check(single.shape[0], np.unique(box[has]), str(options.psf_path), names)
        elif source == "file":
            shapes = meds.psf_shapes(k)[has]
            if np.any(shapes[:, 0] != shapes[:, 1]):
                raise InputError(f"{meds.path}: PSF cutouts must be square for {name('metacal')}")

    # work units: objects with the cutout, grouped by box size (and PSF cutout size)
    psf_shape = meds.psf_shapes(k) if source == "file" else np.zeros((n, 2), np.int64)
    keys = np.stack([box, psf_shape[:, 0], psf_shape[:, 1]], axis=1)
    rows_all = np.arange(n)
    groups = [rows_all[has & np.all(keys == key, axis=1)] for key in np.unique(keys[has], axis=0)]
    n_has = int(has.sum())
    total_units = n_units(n_has, n_workers)
    pieces: list[np.ndarray] = []
    for g in groups:
        share = max(1, round(total_units * len(g) / max(n_has, 1)))
        pieces += [p for p in np.array_split(g, min(share, len(g))) if len(p)]
    return [
        MedsUnit(
            rows[p],
            plan.worker_meds.layout(p, k, psf=source == "file"),
            origins[p],
            centres[p],
            source,
            single,
            plan.model_path,
            plan.psf_model,
            model_xy[p] if source == "model" else None,
            p + k * n,  # one fixnoise field per object and cutout
        )
        for p in pieces
    ]


def _measured_columns(
    plan: MedsPlan,
    units: Sequence[MedsUnit],
    n_rows: int,
    has: np.ndarray | None,
    nproc: int,
    scheduler: str | None,
    progress: Progress | None,
) -> dict[str, np.ndarray]:
    """The measured columns of ``n_rows`` output rows (NO_CUTOUT where not ``has``): the
    ``units`` run on the workers, or in this process for a PSF model object in memory."""
    flags = None if has is None else np.where(has, 0, fl.NO_CUTOUT)
    cols = empty_columns(n_rows, plan.columns, flags)
    cols[MASKED_COLUMN] = np.full(n_rows, NO_CUTOUT_MASKED, dtype=np.int32)
    if plan.source == "model" and plan.psf_model is not None and (nproc != 1 or scheduler):
        nproc, scheduler = 1, None  # an object in memory: measured in this process
    return measure_units(
        units,
        plan.settings,
        cols,
        nproc=nproc,
        scheduler=scheduler,
        progress=progress,
        label="measuring MEDS objects",
    )


def passed_columns(meds: MedsFile, has: np.ndarray, k: int) -> dict[str, np.ndarray]:
    """The columns of the file carried into the output, one row per object: the
    :data:`PASSED_COLUMNS`, the :data:`PASSED_CUTOUT_COLUMNS` of cutout ``k`` (NaN where not
    ``has``; unusable Jacobians checked, :func:`_check_jacobians`) and :func:`extra_columns`."""
    obj = meds.objects
    out: dict[str, np.ndarray] = {}
    for c in PASSED_COLUMNS:
        if c in obj:
            out[c] = obj[c]
    for c in PASSED_CUTOUT_COLUMNS:
        if c in obj:
            out[c] = np.where(has, obj[c][:, k].astype(np.float64), np.nan)
    _check_jacobians(out, has, meds.path)
    for c in extra_columns(meds):
        out[c] = obj[c]
    return out


def _check_jacobians(out: dict[str, np.ndarray], has: np.ndarray, path: str) -> None:
    """Keep the measured cutouts' Jacobians where they are usable: a degenerate one
    (determinant near 0, non-finite, or the meds package's -9999 fill) becomes NaN, and
    without any usable one the columns are dropped (shears stay in the pixel frame)."""
    if not all(c in out for c in JACOBIAN_COLUMNS):
        for c in JACOBIAN_COLUMNS:
            out.pop(c, None)
        return
    ok = usable_jacobians(*(out[c] for c in JACOBIAN_COLUMNS))
    bad = has & ~ok
    if not (has & ok).any():
        log.warning(
            "%s: no measured cutout has a usable Jacobian (dudrow .. dvdcol): the columns are "
            "left out and shears stay in the cutouts' pixel frame",
            path,
        )
        for c in JACOBIAN_COLUMNS:
            out.pop(c)
        return
    if bad.any():
        log.warning(
            "%s: %d object(s) with a degenerate Jacobian: NaN (their world-frame shears "
            "cannot be computed)",
            path,
            int(bad.sum()),
        )
        for c in JACOBIAN_COLUMNS:
            out[c] = np.where(ok, out[c], np.nan)


def meds_settings(options: MedsOptions) -> MeasureSettings:
    """What is measured of a MEDS file's objects, on the CPU (masked stamps)."""
    return MeasureSettings(
        options.gain,
        options.engine,
        "cpu",
        tuple(options.feature_sets) + (("morphology",) if options.morphology else ()),
        MetacalSettings(float(options.metacal_step), int(options.seed))
        if options.metacal
        else None,
        float(options.moments_retry),
        float(options.mask_margin),
    )


def check_request(request: MeasureRequest) -> None:
    """The arguments that apply to a MEDS file (it carries its own objects and box sizes)."""
    name = namer(request.names)
    if request.metadetect:
        raise ConfigError(
            f"{name('metadetect')} measures a cells file (SCI, WGT, PSF cubes, "
            f"docs/metadetect.md); {request.stamps_path} is a MEDS file"
        )
    if request.catalog_path is not None:
        raise ConfigError(
            f"{request.stamps_path} is a MEDS file, which carries its own objects: give it no "
            "catalog"
        )
    wrong = [
        name(k)
        for k, given in (
            ("stamp_size", request.stamp_size is not None),
            ("origin", request.origin != 1),
            ("stars", bool(request.stars)),
        )
        if given
    ]
    if wrong:
        raise ConfigError(
            f"{request.stamps_path} is a MEDS file (each object has its box_size): leave out "
            f"{', '.join(wrong)}"
        )
    if request.epochs and request.cutout != MEASURE["cutout"].default:
        raise ConfigError(
            f"give {name('cutout')} (one cutout) or {name('epochs')} (every single-epoch "
            "cutout), not both"
        )


def measure_request(request: MeasureRequest) -> Measured:
    """Measure the objects of a MEDS file (:func:`measure_meds`) into a features catalog
    (format ``megalut.features``, one row per object)."""
    settings = request.settings
    options = MedsOptions(
        cutout=request.cutout,
        gain=settings.gain,
        psf_path=request.psf_path,
        psf_model_path=request.psf_model_path,
        engine=settings.engine,
        metacal=settings.metacal is not None,
        metacal_step=settings.metacal.step if settings.metacal else MEASURE["metacal_step"].default,
        seed=settings.metacal.seed if settings.metacal else MEASURE["seed"].default,
        feature_sets=settings.feature_sets,
        epochs=request.epochs,
        moments_retry=settings.moments_retry,
        mask_margin=settings.mask_margin,
    )
    if settings.device == "gpu":
        log.info(
            "MEDS input is measured on the CPU (masked stamps); %s gpu is not used here",
            namer(request.names)("device"),
        )
    meds = read_meds(request.stamps_path)
    columns = (measure_epochs if options.epochs else measure_meds)(
        meds,
        options,
        nproc=request.nproc,
        scheduler=request.scheduler,
        progress=request.progress,
        names=request.names,
    )
    flags = columns["flags"]
    what = "object cutouts" if options.epochs else "objects"
    log.info("%d of %d %s flagged (features NaN)", int((flags != 0).sum()), len(flags), what)
    warn_if_mostly_flagged(
        flags,
        request.stamps_path,
        request.names,
        f"masks, weights or PSFs of the file, or {namer(request.names)('cutout')}",
    )
    boxes = np.unique(meds.objects["box_size"])
    cards: dict[str, Any] = {
        FILE_CARD: (os.path.basename(request.stamps_path), "MEDS file measured"),
        FILE_SHA_CARD: (sha256_file(request.stamps_path), "sha256 of the MEDS file"),
        CUTOUT_CARD: (
            (-1, "every single-epoch cutout (--epochs): column cutout")
            if options.epochs
            else (int(options.cutout), "MEDS cutout index measured (0: coadd or first)")
        ),
        COADD_CARD: (
            bool(not options.epochs and options.cutout == 0 and meds.first_is_coadd()),
            "the measured cutouts are coadds",
        ),
        "STAMPSZ": (int(boxes[0]), "stamp size [pixels]") if len(boxes) == 1 else None,
        **measure_cards(
            dataclasses.replace(settings, metacal=None), int(boxes[0]) if len(boxes) == 1 else None
        ),
        "NOISEWT": (meds.has("weight"), "snr from the weight-map noise (noise_weight)"),
        "MASKFRAC": (MAX_MASKED_FRACTION, "masked fraction above which MASKED_PIXELS"),
        "MASKRAD": (CENTRAL_MASK_RADIUS, "masked pixel this close to centre: MASKED_PIXELS"),
        "MASKMRGN": (float(options.mask_margin), "masked pixel this close: NEAR_MASK [px]"),
    }
    if options.psf_model_path is not None:
        cards.update(cached_psf_model(str(options.psf_model_path)).header_cards())
    if options.metacal:
        cards.update(metacal_cards(options.metacal_step, options.seed, "measure"))
    return Measured(columns, cards, FORMAT)


def recognises(path: str) -> bool:
    """Whether ``path`` is meant as a MEDS file: a FITS file with either extension of
    :data:`MEDS_EXTENSIONS` (one without the other is then said to be an incomplete MEDS
    file, not an image)."""
    return meds_extensions(path) > 0


MEDS_SOURCE = register_stamp_source(
    StampSourceType("meds", recognises, check_request, measure_request)
)


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
    jacobians: Any = None,
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
    simulation's truth) after the layout's. ``jacobians``: each cutout's Jacobian
    ``[[dudcol, dudrow], [dvdcol, dvdrow]]``, ``(n, 2, 2)`` or ``(n, NMAX, 2, 2)``; by
    default ``pixel_scale`` on the diagonal (``dudcol = dvdrow``); ``metadata`` records
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
    jac = np.broadcast_to(pixel_scale * np.eye(2), (n, nmax, 2, 2))
    if jacobians is not None:
        given = np.asarray(jacobians, dtype=np.float64)
        if given.ndim == 3:
            given = given[:, None]
        if given.shape[0] != n or given.shape[-2:] != (2, 2):
            raise ValueError(f"jacobians must be (n, 2, 2) or (n, NMAX, 2, 2), got {given.shape}")
        jac = np.broadcast_to(given, (n, nmax, 2, 2)) if given.shape[1] == 1 else given
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
            od["dudcol"][i, k], od["dudrow"][i, k] = jac[i, k, 0]
            od["dvdcol"][i, k], od["dvdrow"][i, k] = jac[i, k, 1]
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
