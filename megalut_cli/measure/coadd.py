"""Coadd input of ``megalut measure IMAGE --weight WEIGHT --metadetect``: one image in cells.

The image, its weight map (and optionally a mask and a noise image) are cut into square
cells that overlap by twice the border, so that their inner regions tile the image; each
cell is read in its worker and measured as a cell of a cells file
(:func:`.cell_detect.metadetect_cell`). Positions are the image's 1-based pixels, with ``ra, dec``
when it has a celestial WCS (docs/metadetect.md, "A coadd image").
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from typing import Any

import fitsio
import numpy as np

from megalut_cli.errors import ConfigError, InputError, namer
from megalut_cli.measure import cell_catalog, cell_detect, cells
from megalut_cli.measure.defaults import INNER_CARD, MDET_STAMP_SIZE
from megalut_cli.measure.grid import pixel_scale
from megalut_cli.measure.measurer import MeasureSettings
from megalut_cli.measure.metacal_defaults import MDET_COLUMN
from megalut_cli.measure.options import MEASURE
from megalut_cli.measure.psf_model import cached_psf_model
from megalut_cli.measure.single_psf import single_psf_stamp
from megalut_cli.measure.source_registry import (
    COADD_IMAGES,
    DetectSettings,
    Measured,
    MeasureRequest,
    StampSourceType,
    register_stamp_source,
)
from megalut_cli.measure.stamps import ImageInfo, image_info
from megalut_cli.parallel import executor, map_units
from megalut_cli.progress import no_progress
from megalut_cli.provenance import sha256_file
from megalut_cli.shear.frame import JACOBIAN_COLUMNS, celestial_jacobians, is_celestial

log = logging.getLogger(__name__)

#: Side of the square tiles of the fixnoise field: each tile's normals come from the seed and
#: the tile's place in the image, so that overlapping cells share their fixnoise pixels.
NOISE_TILE = 64
#: Side of the PSF image a PSF model is drawn on at each cell's centre (odd: centred on a pixel).
MODEL_PSF_SIZE = 63


@dataclass(frozen=True)
class CoaddInput:
    """A coadd image to measure in cells: the image, weight, mask and noise images (the last
    two optional), one PSF image or a PSF model file, and the cells' side and border."""

    image: ImageInfo
    weight: ImageInfo
    mask: ImageInfo | None
    noise: ImageInfo | None
    psf: np.ndarray | None
    psf_model_path: str | None
    size: int
    border: int

    @property
    def step(self) -> int:
        """The side of a cell's inner region: the distance between cells."""
        return self.size - 2 * self.border


def cell_origins(shape: tuple[int, int], size: int, border: int) -> np.ndarray:
    """The 0-based ``(x0, y0)`` of the lower-left pixel of each cell of an image of ``shape``
    ``(ny, nx)``, row by row: cells of ``size`` pixels ``size - 2 border`` apart, the first
    ``border`` pixels before the image, so that the inner regions tile it."""
    step = size - 2 * border
    ny, nx = shape
    xs = np.arange(math.ceil(nx / step)) * step - border
    ys = np.arange(math.ceil(ny / step)) * step - border
    return np.array([(x0, y0) for y0 in ys for x0 in xs], dtype=np.int64).reshape(-1, 2)


def read_region(info: ImageInfo, x0: int, y0: int, size: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``size`` x ``size`` region of an image whose lower-left pixel is the 0-based
    ``(x0, y0)``: its float64 pixels (0 outside the image) and where it lies outside."""
    ny, nx = info.shape
    out = np.zeros((size, size))
    outside = np.ones((size, size), dtype=bool)
    xa, xb = max(x0, 0), min(x0 + size, nx)
    ya, yb = max(y0, 0), min(y0 + size, ny)
    if xa < xb and ya < yb:
        with fitsio.FITS(info.path) as f:
            part = f[info.ext][ya:yb, xa:xb]
        out[ya - y0 : yb - y0, xa - x0 : xb - x0] = part
        outside[ya - y0 : yb - y0, xa - x0 : xb - x0] = False
    return out, outside


def tiled_normals(seed: int, x0: int, y0: int, size: int) -> np.ndarray:
    """Unit normals on the ``size`` x ``size`` region at the 0-based ``(x0, y0)`` of an image,
    the same at a pixel whatever the region: drawn tile by tile (:data:`NOISE_TILE`), each
    tile from ``seed`` and its indices."""
    out = np.empty((size, size))
    t = NOISE_TILE
    for ty in range(y0 // t, (y0 + size - 1) // t + 1):
        for tx in range(x0 // t, (x0 + size - 1) // t + 1):
            key = [int(seed), tx + (1 << 30), ty + (1 << 30)]  # non-negative entropy
            tile = np.random.default_rng(np.random.SeedSequence(key)).standard_normal((t, t))
            ya, yb = max(ty * t, y0), min((ty + 1) * t, y0 + size)
            xa, xb = max(tx * t, x0), min((tx + 1) * t, x0 + size)
            out[ya - y0 : yb - y0, xa - x0 : xb - x0] = tile[
                ya - ty * t : yb - ty * t, xa - tx * t : xb - tx * t
            ]
    return out


def check_scales(image: ImageInfo, psf_path: str) -> None:
    """Refuse a PSF image whose pixel scale (header card or WCS) differs from the image's."""
    psf_scale = pixel_scale(image_info(psf_path).header)
    scale = pixel_scale(image.header)
    if psf_scale is not None and scale is not None:
        if abs(psf_scale / scale - 1.0) > cells.SCALE_TOLERANCE:
            raise InputError(
                f"{psf_path}: the PSF's pixels are {psf_scale:.4g} arcsec, the image's "
                f"{scale:.4g}: give the PSF in the image's pixels"
            )


def read_coadd_input(request: MeasureRequest) -> CoaddInput:
    """The coadd image of ``request`` and its companions, checked: the same shape for every
    image, a PSF of the image's pixel scale, centred on its image."""
    c = request.cells
    assert c is not None and c.weight_path is not None
    image = image_info(request.stamps_path)
    parts: dict[str, ImageInfo | None] = {}
    for companion in COADD_IMAGES:
        path = getattr(c, companion.field)
        info = None if path is None else image_info(path)
        if info is not None and info.shape != image.shape:
            raise InputError(
                f"{path}: the {companion.label} image is {info.shape[1]}x{info.shape[0]} pixels, "
                f"{request.stamps_path} {image.shape[1]}x{image.shape[0]}: they must agree"
            )
        parts[companion.field] = info
    psf = None
    if request.psf_path is not None:
        check_scales(image, request.psf_path)
        psf = single_psf_stamp(request.psf_path, MODEL_PSF_SIZE)
        cell_detect.check_psf(psf, request.psf_path)
    weight = parts["weight_path"]
    assert weight is not None
    return CoaddInput(
        image,
        weight,
        parts["mask_path"],
        parts["noise_path"],
        psf,
        request.psf_model_path,
        c.size,
        c.border,
    )


@dataclass(frozen=True)
class CoaddCellJob:
    """One cell of a coadd image to measure (picklable: read in the worker)."""

    coadd: CoaddInput
    index: int
    x0: int
    y0: int
    seed: int
    settings: MeasureSettings
    detection: DetectSettings
    stamp_size: int
    detect_only: bool = False


def cell_psf(coadd: CoaddInput, x0: int, y0: int) -> np.ndarray:
    """The PSF of the cell at ``(x0, y0)``: the one PSF image, or the model's at the cell's
    centre (1-based image pixels)."""
    if coadd.psf is not None:
        return coadd.psf
    assert coadd.psf_model_path is not None
    centre = x0 + (coadd.size + 1) / 2.0, y0 + (coadd.size + 1) / 2.0
    psf = cached_psf_model(coadd.psf_model_path).draw(*centre, MODEL_PSF_SIZE)[0]
    if not np.isfinite(psf).all():
        raise InputError(
            f"{coadd.psf_model_path}: the PSF model has no flux at ({centre[0]:.1f}, "
            f"{centre[1]:.1f})"
        )
    return psf


def measure_coadd_cell(job: CoaddCellJob) -> dict[str, np.ndarray] | None:
    """Worker: read one cell of the coadd and run :func:`.cell_detect.metadetect_cell` on it; None
    when every pixel of the cell is bad or off the image. Positions in the image's pixels,
    ``inner`` from the cell's inner region."""
    co, size = job.coadd, job.coadd.size
    image, outside = read_region(co.image, job.x0, job.y0, size)
    weight, _ = read_region(co.weight, job.x0, job.y0, size)
    bad = outside | ~(weight > 0)
    if co.mask is not None:
        bad |= read_region(co.mask, job.x0, job.y0, size)[0] != 0
    if bad.all():
        return None
    psf = cell_psf(co, job.x0, job.y0)
    sigma = cell_detect.cell_noise(weight, bad)
    try:
        if job.detect_only:
            result = cell_detect.detect_cell(
                image,
                psf,
                sigma,
                job.index,
                job.settings,
                job.detection,
                job.stamp_size,
                bad,
                weight,
            )
        else:
            result = cell_detect.metadetect_cell(
                image,
                psf,
                coadd_cell_noise(co, job, sigma, weight, bad),
                job.settings,
                job.detection,
                job.stamp_size,
                bad,
            )
    except InputError as err:
        raise InputError(
            f"{co.image.path}: the cell at x {job.x0 + 1}, y {job.y0 + 1}: {err}"
        ) from None
    return located(result, job)


def coadd_cell_noise(
    co: CoaddInput, job: CoaddCellJob, sigma: float, weight: np.ndarray, bad: np.ndarray
) -> cell_detect.CellNoise:
    """The noise of a coadd's cell (``sigma`` from its weight map): the noise image's region,
    whose correlation colours the cell's unit white field (:func:`tiled_normals`), else
    white noise of each pixel's variance, the same pixels in every cell over them."""
    normals = tiled_normals(job.seed, job.x0, job.y0, co.size)
    if co.noise is not None:
        field = read_region(co.noise, job.x0, job.y0, co.size)[0]
        return cell_detect.CellNoise(sigma, job.seed, field, correlated=True, unit=normals)
    with np.errstate(divide="ignore"):
        scale = np.where(bad, 0.0, 1.0 / np.sqrt(np.where(bad, 1.0, weight)))
    return cell_detect.CellNoise(sigma, job.seed, normals * scale)


def located(result: dict[str, np.ndarray], job: CoaddCellJob) -> dict[str, np.ndarray]:
    """A cell's rows with ``inner`` (from the cell's inner region) and their positions in the
    image's pixels."""
    result["inner"] = cell_catalog.inner_region(
        result["x"], result["y"], job.coadd.size, job.coadd.border
    )
    result["x"] = result["x"] + job.x0
    result["y"] = result["y"] + job.y0
    return result


def coadd_columns(
    coadd: CoaddInput, jobs: list[CoaddCellJob], results: list[dict[str, np.ndarray] | None]
) -> dict[str, np.ndarray]:
    """The catalog's columns in the order of the contract: ``mdet_step``, ``cell``, ``x``,
    ``y`` (``ra``, ``dec``, ``dudcol``, ``dudrow``, ``dvdcol``, ``dvdrow``), ``inner``, then
    the features."""
    kept = [(job, r) for job, r in zip(jobs, results) if r is not None]
    if not kept:
        raise InputError(f"{coadd.image.path}: every pixel is bad (weight 0 or masked)")
    counts = np.array([len(r["x"]) for _, r in kept], dtype=np.int64)
    merged = {c: np.concatenate([r[c] for _, r in kept]) for c in kept[0][1]}
    out: dict[str, np.ndarray] = {}
    if MDET_COLUMN in merged:
        out[MDET_COLUMN] = merged.pop(MDET_COLUMN).astype("U7")
    out["cell"] = np.repeat([job.index for job, _ in kept], counts).astype(np.int64)
    out["x"], out["y"] = merged.pop("x"), merged.pop("y")
    if is_celestial(coadd.image.header) and len(out["x"]):
        sky = celestial_jacobians(coadd.image.header, out["x"], out["y"])
        # the sky position and the local Jacobian (calibrate's world frame)
        out.update({c: sky[c] for c in ("ra", "dec", *JACOBIAN_COLUMNS)})
    out["inner"] = merged.pop("inner")
    out.update(cell_catalog.ordered_features(merged))
    return out


def claims(request: MeasureRequest) -> bool:
    """``--metadetect`` (or ``--detect``) on a file no other source recognises: a coadd."""
    return request.detects


def check_request(request: MeasureRequest) -> None:
    """The arguments of a coadd image: ``--weight``, one PSF, no catalog nor stamp options."""
    name = namer(request.names)
    flag = name("metadetect" if request.metadetect else "detect")
    c = request.cells
    if c is None or c.weight_path is None:
        raise ConfigError(
            f"{flag} on an image ({request.stamps_path}) needs "
            f"{name('weight_path')}, its inverse-variance map (or give a cells file, "
            "docs/metadetect.md)"
        )
    if request.catalog_path is not None:
        raise ConfigError(f"{flag} finds the objects itself: give no catalog")
    if (request.psf_path is None) == (request.psf_model_path is None):
        raise ConfigError(
            f"{flag} on an image needs one PSF: {name('psf_path')} (one PSF "
            f"image) or {name('psf_model_path')}"
        )
    if request.detect_only and c.noise_path is not None:
        raise ConfigError(f"{name('noise_path')} is the fixnoise field of {name('metadetect')}")
    wrong = [
        name(k)
        for k, given in (
            ("origin", request.origin != 1),
            ("stars", bool(request.stars)),
            ("epochs", request.epochs),
            ("cutout", request.cutout != MEASURE["cutout"].default),
        )
        if given
    ]
    if wrong:
        raise ConfigError(f"{', '.join(wrong)}: not for {flag} on an image")
    if 2 * c.border >= c.size:
        raise ConfigError(
            f"{name('cell_border')} {c.border} leaves no inner region in cells of "
            f"{c.size} pixels: it must be below {name('cell_size')} / 2"
        )
    size = request.stamp_size or MDET_STAMP_SIZE
    if size > c.size:
        raise ConfigError(f"{name('stamp_size')} {size} is larger than the cells ({c.size} pixels)")


def measure_request(request: MeasureRequest) -> Measured:
    """Metadetection on every cell of a coadd image (module docstring) into a catalog of
    format ``megalut.metadetect``."""
    settings, detection = request.settings, request.detect
    assert detection is not None
    coadd = read_coadd_input(request)
    size = request.stamp_size or MDET_STAMP_SIZE
    from megalut_cli.measure.metacal import fixnoise_seeds  # GalSim: metadetect only

    origins = cell_origins(coadd.image.shape, coadd.size, coadd.border)
    seed = 0
    if settings.metacal is not None:  # one fixnoise field over the image
        seed = int(fixnoise_seeds(settings.metacal.seed, [0])[0])
    jobs = [
        CoaddCellJob(
            coadd, i, int(x0), int(y0), seed, settings, detection, size, request.detect_only
        )
        for i, (x0, y0) in enumerate(origins)
    ]
    with (
        executor(request.nproc, request.scheduler, len(jobs)) as pool,
        (request.progress or no_progress)("metadetection on cells", len(jobs)) as update,
    ):
        results = map_units(measure_coadd_cell, jobs, pool, update)
    columns = coadd_columns(coadd, jobs, results)
    skipped = sum(r is None for r in results)
    if skipped:
        log.info("%d of %d cells lie wholly on bad pixels: skipped", skipped, len(jobs))
    where = f"{len(jobs) - skipped} cells of {coadd.size} pixels"
    cell_catalog.log_detections(request, columns, where)
    cards = coadd_cards(request, coadd, len(jobs), size)
    return Measured(columns, cards, cell_catalog.output_format(request))


def coadd_cards(
    request: MeasureRequest, coadd: CoaddInput, n_cells: int, size: int
) -> dict[str, Any]:
    """Header cards: the input files and their sha256, the cells, then those of every
    metadetect catalog (:func:`.cell_catalog.metadetect_cards`)."""
    cards: dict[str, Any] = {}
    assert request.cells is not None
    for key, what, path in (
        ("IMG", "coadd image", request.stamps_path),
        *((i.card, i.what, getattr(request.cells, i.field)) for i in COADD_IMAGES),
        ("PSF", "PSF image", request.psf_path),
    ):
        if path is not None:
            cards[f"{key}FILE"] = (os.path.basename(path)[:68], f"{what} measured")
            cards[f"{key}SHA"] = (sha256_file(path), f"sha256 of the {what}")
    if coadd.psf_model_path is not None:
        cards.update(cached_psf_model(coadd.psf_model_path).header_cards())
    scale = pixel_scale(coadd.image.header)
    if scale is not None:
        cards["PIXSCALE"] = (scale, "pixel scale of the image [arcsec]")
    cards["NCELLS"] = (n_cells, "number of cells the image is cut into")
    cards["CELLSZ"] = (coadd.size, "side of a cell [pixels]")
    cards[INNER_CARD] = (coadd.border, "border outside the inner region [pixels]")
    if request.metadetect:
        fixnoise = "white" if coadd.noise is None else "NOISE"
        cards[cell_catalog.FIXNOISE_CARD] = (fixnoise, cell_catalog.FIXNOISE_TEXT)
    cards.update(cell_catalog.metadetect_cards(request, size))
    return cards


COADD_SOURCE = register_stamp_source(
    StampSourceType("coadd", lambda path: False, check_request, measure_request, claims=claims)
)
