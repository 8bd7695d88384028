"""Cells files as ``measure`` input (``--metadetect``, ``--detect``): a stamp source.

A cells file (docs/metadetect.md; what ``megalut simulate --scene`` writes, format
``megalut.scenes``) holds square cells of one size: the cubes ``SCI`` (the images), ``WGT``
(inverse variance, 0 where a pixel is bad), optionally ``MSK`` (mask bits, non-zero bad),
``NOISE`` (a noise realization with the data's correlations) and ``PSF`` (the PSF image at
each cell's centre, unit sum, pixel included), and optionally an ``IMAGES`` table
(``image``, ``field``, ``pair_sign``, ...). Each cell is read in a worker and measured by
:func:`.cell_detect.metadetect_cell` (or :func:`.cell_detect.detect_cell`); its rows make
the catalog of :mod:`.cell_catalog`.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Any

import fitsio
import numpy as np

from megalut_cli.catalog import is_fits_file
from megalut_cli.errors import ConfigError, InputError, namer
from megalut_cli.fits_header import header_dict
from megalut_cli.measure.cell_catalog import (
    FIXNOISE_CARD,
    FIXNOISE_TEXT,
    inner_region,
    log_detections,
    metadetect_cards,
    ordered_features,
    output_format,
)
from megalut_cli.measure.cell_detect import (
    CellNoise,
    cell_noise,
    check_psf,
    detect_cell,
    metadetect_cell,
)
from megalut_cli.measure.defaults import CELLS_FORMAT, INNER_CARD, MDET_STAMP_SIZE
from megalut_cli.measure.grid import pixel_scale
from megalut_cli.measure.measurer import MeasureSettings
from megalut_cli.measure.metacal_defaults import MDET_COLUMN
from megalut_cli.measure.options import MEASURE
from megalut_cli.measure.source_registry import (
    DetectSettings,
    Measured,
    MeasureRequest,
    StampSourceType,
    register_stamp_source,
)
from megalut_cli.parallel import executor, map_units
from megalut_cli.progress import no_progress
from megalut_cli.provenance import sha256_file

log = logging.getLogger(__name__)

#: Columns of the ``IMAGES`` table copied to every row of their cell.
IMAGE_COLUMNS: tuple[str, ...] = ("image", "field", "pair_sign", "tru_g1", "tru_g2")
#: Relative difference of the cells' and the PSF's pixel scales beyond which they disagree.
SCALE_TOLERANCE = 1e-3


@dataclass(frozen=True)
class CellsLayout:
    """What a cells file holds: ``n`` cells of ``size`` pixels, the PSF size, which optional
    cubes it has, its ``IMAGES`` columns (or None) and its primary header cards."""

    path: str
    n: int
    size: int
    psf_size: int
    has_weight: bool
    has_mask: bool
    has_noise: bool
    images: dict[str, np.ndarray] | None
    cards: dict[str, Any]

    @property
    def inner_border(self) -> int:
        """The border outside the inner region (card :data:`INNER_CARD`, default 0)."""
        return int(self.cards.get(INNER_CARD, 0) or 0)

    def keys(self) -> np.ndarray:
        """The fixnoise key of each cell: its field (the +g and -g images of a pair share
        their fixnoise field, as they share their noise), else its index."""
        if self.images is not None and "field" in self.images:
            return np.asarray(self.images["field"], dtype=np.int64)
        return np.arange(self.n, dtype=np.int64)


def _extnames(path: str) -> list[str]:
    """The upper-case extension names of a FITS file (the primary's EXTNAME too)."""
    with fitsio.FITS(path) as f:
        return [str(h.get_extname()).upper() for h in f]


def recognises(path: str) -> bool:
    """Whether ``path`` is a cells file: its MLFORMAT is :data:`CELLS_FORMAT`, or it has a
    ``SCI`` extension and a ``PSF`` or ``WGT`` one (one without a PSF is then refused as an
    incomplete cells file, not read as an image of stamps)."""
    if not os.path.isfile(path) or not is_fits_file(path):
        return False
    try:
        names = _extnames(path)
        fmt = str(fitsio.read_header(path, 0).get("MLFORMAT", "")).strip()
    except OSError:
        return False
    return fmt == CELLS_FORMAT or ("SCI" in names and ("PSF" in names or "WGT" in names))


def read_layout(path: str) -> CellsLayout:
    """The layout of a cells file, checked (one line per problem: a missing PSF, cubes of
    different shapes, non-square cells)."""
    names = _extnames(path)
    if "SCI" not in names and names and names[0] in ("", "PRIMARY"):
        names[0] = "SCI"  # the primary holds the images when unnamed
    if "PSF" not in names:
        raise InputError(
            f"{path}: a cells file needs a PSF cube (the PSF image at each cell's centre); it has "
            f"{', '.join(n for n in names if n) or 'no named extension'}"
        )
    with fitsio.FITS(path) as f:
        sci = f[names.index("SCI")]
        dims = tuple(int(d) for d in sci.get_dims())
        cards = header_dict(sci.read_header())
        if len(dims) == 2:
            dims = (1, *dims)
        if len(dims) != 3 or dims[1] != dims[2]:
            raise InputError(f"{path}: SCI must hold square cells (n, S, S), got shape {dims}")
        for ext in ("WGT", "MSK", "NOISE"):
            if ext in names:
                d = tuple(int(x) for x in f[names.index(ext)].get_dims())
                if (d if len(d) == 3 else (1, *d)) != dims:
                    raise InputError(f"{path}: {ext} has shape {d}, SCI {dims}: they must agree")
        pd = tuple(int(x) for x in f[names.index("PSF")].get_dims())
        pd = pd if len(pd) == 3 else (1, *pd)
        if pd[0] != dims[0] or pd[1] != pd[2]:
            raise InputError(
                f"{path}: PSF must hold one square image per cell ({dims[0]}), got shape {pd}"
            )
        scales = [pixel_scale(c) for c in (cards, header_dict(f[names.index("PSF")].read_header()))]
        if None not in scales and abs(scales[1] / scales[0] - 1.0) > SCALE_TOLERANCE:
            raise InputError(
                f"{path}: the PSF cube's pixels are {scales[1]:.4g} arcsec, the cells' "
                f"{scales[0]:.4g}: give the PSF in the cells' pixels"
            )
        images = None
        if "IMAGES" in names:
            table = f[names.index("IMAGES")].read()
            images = {c: np.asarray(table[c]) for c in IMAGE_COLUMNS if c in table.dtype.names}
            if len(table) != dims[0]:
                raise InputError(f"{path}: IMAGES has {len(table)} rows for {dims[0]} cells")
    layout = CellsLayout(
        path,
        dims[0],
        dims[1],
        pd[1],
        "WGT" in names,
        "MSK" in names,
        "NOISE" in names,
        images,
        cards,
    )
    if not 0 <= layout.inner_border < layout.size / 2:
        raise InputError(
            f"{path}: {INNER_CARD} must be in [0, {layout.size / 2}), got {layout.inner_border}"
        )
    return layout


def read_cell(path: str, index: int) -> dict[str, np.ndarray | None]:
    """Cell ``index`` of a cells file: ``image``, ``bad`` (WGT <= 0, MSK != 0), ``weight``
    (ones without WGT), ``psf`` and ``noise`` (the NOISE cube's realization, else None),
    float64."""
    names = _extnames(path)
    if "SCI" not in names:
        names[0] = "SCI"

    def cube(f: Any, ext: str) -> np.ndarray:
        hdu = f[names.index(ext)]
        arr = hdu.read() if len(hdu.get_dims()) == 2 else hdu[index : index + 1, :, :][0]
        return np.asarray(arr, dtype=np.float64)

    with fitsio.FITS(path) as f:
        image = cube(f, "SCI")
        psf = cube(f, "PSF")
        weight = cube(f, "WGT") if "WGT" in names else np.ones_like(image)
        bad = ~(weight > 0)
        if "MSK" in names:
            bad |= cube(f, "MSK") != 0
        noise = cube(f, "NOISE") if "NOISE" in names else None
    return {"image": image, "weight": weight, "bad": bad, "psf": psf, "noise": noise}


@dataclass(frozen=True)
class CellJob:
    """One cell of a file to measure (picklable: read in the worker): metadetection, or
    with ``detect_only`` plain detection (``key``: the cell's fixnoise key)."""

    path: str
    index: int
    seed: int
    settings: MeasureSettings
    detection: DetectSettings
    stamp_size: int
    detect_only: bool = False
    key: int = 0


def measure_cell(job: CellJob) -> dict[str, np.ndarray]:
    """Worker: read one cell and run :func:`metadetect_cell` (or :func:`detect_cell`) on it."""
    cell = read_cell(job.path, job.index)
    try:
        if cell["bad"].all():
            raise InputError("every pixel is masked (WGT 0 or MSK bits)")
        check_psf(cell["psf"], "its PSF")
        noise = cell_noise(cell["weight"], cell["bad"])
        if job.detect_only:
            return detect_cell(
                cell["image"],
                cell["psf"],
                noise,
                job.key,
                job.settings,
                job.detection,
                job.stamp_size,
                cell["bad"],
                cell["weight"],
            )
        return metadetect_cell(
            cell["image"],
            cell["psf"],
            CellNoise(noise, job.seed, cell["noise"], correlated=True),
            job.settings,
            job.detection,
            job.stamp_size,
            cell["bad"],
        )
    except InputError as err:
        raise InputError(f"{job.path}: cell {job.index}: {err}") from None


def check_request(request: MeasureRequest) -> None:
    """The arguments that apply to a cells file: ``--metadetect`` and its options."""
    name = namer(request.names)
    if not request.detects:
        raise ConfigError(
            f"{request.stamps_path} is a cells file (SCI, PSF cubes): measure it with "
            f"{name('metadetect')} (or {name('detect')})"
        )
    if request.catalog_path is not None:
        raise ConfigError(f"{request.stamps_path} is a cells file: give it no catalog")
    wrong = [
        name(k)
        for k, given in (
            ("psf_path", request.psf_path is not None),
            ("psf_model_path", request.psf_model_path is not None),
            ("origin", request.origin != 1),
            ("stars", bool(request.stars)),
            ("epochs", request.epochs),
            ("cutout", request.cutout != MEASURE["cutout"].default),
        )
        if given
    ]
    wrong += [name(k) for k in (request.cells.given() if request.cells is not None else [])]
    if wrong:
        raise ConfigError(
            f"{request.stamps_path} is a cells file (each cell has its PSF, weight, mask and "
            f"size): leave out "
            f"{', '.join(wrong)}"
        )
    read_layout(request.stamps_path)


def metadetect_columns(
    layout: CellsLayout, results: list[dict[str, np.ndarray]]
) -> dict[str, np.ndarray]:
    """The catalog's columns from each cell's :func:`metadetect_cell` result, in the order of
    the contract (docs/metadetect.md): ``mdet_step``, ``image``, ``field``, ``pair_sign``
    (with an IMAGES table), ``x``, ``y``, ``inner``, then the features."""
    counts = np.array([len(r["x"]) for r in results], dtype=np.int64)
    cell = np.repeat(np.arange(layout.n), counts)
    merged = {c: np.concatenate([r[c] for r in results]) for c in results[0]}
    out: dict[str, np.ndarray] = {}
    if MDET_COLUMN in merged:
        out[MDET_COLUMN] = merged.pop(MDET_COLUMN).astype("U7")
    images = layout.images or {}
    out["image"] = np.asarray(images.get("image", np.arange(layout.n)))[cell].astype(np.int64)
    out["field"] = np.asarray(images.get("field", np.arange(layout.n)))[cell].astype(np.int64)
    if "pair_sign" in images:
        out["pair_sign"] = np.asarray(images["pair_sign"])[cell].astype(np.int16)
    for c in ("tru_g1", "tru_g2"):  # a simulated file's shears: for evaluate, not the estimate
        if c in images:
            out[c] = np.asarray(images[c], dtype=np.float64)[cell]
    out["x"], out["y"] = merged.pop("x"), merged.pop("y")
    out["inner"] = inner_region(out["x"], out["y"], layout.size, layout.inner_border)
    out.update(ordered_features(merged))
    return out


def measure_request(request: MeasureRequest) -> Measured:
    """Metadetection on every cell of a cells file (module docstring) into a catalog of
    format ``megalut.metadetect`` (``--detect``: plain detection, ``megalut.features``)."""
    settings, detection = request.settings, request.detect
    assert detection is not None
    layout = read_layout(request.stamps_path)
    size = request.stamp_size or MDET_STAMP_SIZE
    if size > layout.size:
        raise ConfigError(
            f"{namer(request.names)('stamp_size')} {size} is larger than the cells "
            f"({layout.size} pixels)"
        )
    keys = layout.keys()
    seeds = np.zeros(layout.n, np.int64)
    if request.metadetect:
        from megalut_cli.measure.metacal import fixnoise_seeds  # GalSim: metadetect only

        assert settings.metacal is not None
        seeds = fixnoise_seeds(settings.metacal.seed, keys)
    jobs = [
        CellJob(
            request.stamps_path,
            i,
            int(seeds[i]),
            settings,
            detection,
            size,
            request.detect_only,
            int(keys[i]),
        )
        for i in range(layout.n)
    ]
    with (
        executor(request.nproc, request.scheduler, len(jobs)) as pool,
        (request.progress or no_progress)("metadetection on cells", len(jobs)) as update,
    ):
        results = map_units(measure_cell, jobs, pool, update)
    columns = metadetect_columns(layout, results)
    empty = [i for i, r in enumerate(results) if not len(r["x"])]
    if empty:
        log.info("%d of %d cells have no detection", len(empty), layout.n)
    log_detections(request, columns, f"{layout.n} cells")
    return Measured(columns, cells_file_cards(request, layout, size), output_format(request))


def cells_file_cards(request: MeasureRequest, layout: CellsLayout, size: int) -> dict[str, Any]:
    """Header cards of a cells file's metadetect catalog: the file, its cells, the cards of
    every metadetect catalog (:func:`metadetect_cards`) and the simulation's."""
    cards: dict[str, Any] = {
        "CELLFILE": (os.path.basename(request.stamps_path), "cells file measured"),
        "CELLSHA": (sha256_file(request.stamps_path), "sha256 of the cells file"),
        "NCELLS": (layout.n, "number of cells"),
        "CELLSZ": (layout.size, "side of a cell [pixels]"),
        INNER_CARD: (layout.inner_border, "border outside the inner region [pixels]"),
        **metadetect_cards(request, size),
    }
    if request.metadetect:
        cards[FIXNOISE_CARD] = ("NOISE" if layout.has_noise else "white", FIXNOISE_TEXT)
    for key, card in (("PIXSCALE", "PIXSCALE"), ("SEED", "CELLSEED"), ("PAIRS", "PAIRS")):
        if key in layout.cards:
            cards[card] = (layout.cards[key], f"the cells file's {key}")
    return cards


CELLS_SOURCE = register_stamp_source(
    StampSourceType("cells", recognises, check_request, measure_request)
)
