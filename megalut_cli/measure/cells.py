"""Cells input of ``megalut measure --metadetect``: detection inside the calibration.

A cells file (docs/metadetect.md; what ``megalut simulate --scene`` writes, format
``megalut.scenes``) holds square cells of one size: the cubes ``SCI`` (the images), ``WGT``
(inverse variance, 0 where a pixel is bad), optionally ``MSK`` (mask bits, non-zero bad) and
``PSF`` (the PSF image at each cell's centre, unit sum, pixel included), and optionally an
``IMAGES`` table (``image``, ``field``, ``pair_sign``, ...).

Per cell (metadetection, Sheldon et al. 2020): the metacal operation of :mod:`.metacal` on the
whole cell (the five versions, the round target PSF, fixnoise at the noise of the weight
map), detection with ``sep`` on each version independently, and the features of a stamp cut
around each detection in that version, neighbours left in, measured by the one
:class:`~.measurer.Measurer`. One row per detection per version (:func:`metadetect_cell`).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
from dataclasses import dataclass
from typing import Any

import fitsio
import numpy as np

from megalut_cli.catalog import is_fits_file
from megalut_cli.engine import DEFAULT_ENGINE
from megalut_cli.errors import ConfigError, InputError, namer
from megalut_cli.fits_header import header_dict
from megalut_cli.measure.defaults import CELLS_FORMAT, MDET_FORMAT, MDET_STAMP_SIZE, PSF_COLUMNS
from megalut_cli.measure.defaults import FORMAT as FEATURES_FORMAT
from megalut_cli.measure.features import warn_if_mostly_flagged
from megalut_cli.measure.grid import pixel_scale
from megalut_cli.measure.measurer import (
    Measurer,
    MeasureSettings,
    PsfImages,
    StampBatch,
    measure_cards,
    same_parity_psfs,
)
from megalut_cli.measure.metacal_defaults import (
    MDET_COLUMN,
    MDET_STEP_CARD,
    SEED_CARD,
    SHEARS,
    TARGET_CARD,
    TARGET_PSF_COLUMNS,
    TYPES,
)
from megalut_cli.measure.noise_correlation import noise_correlation
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
#: Header card of a cells file (and of the catalog): the width of the border (pixels) outside
#: each cell's inner region (overlapping cells); 0 or absent: the whole cell is inner.
INNER_CARD = "INNERBRD"
#: Header card: the fixnoise of a metadetect catalog, coloured by a noise image's
#: correlation (``NOISE``) or white noise of the weight map (``white``).
FIXNOISE_CARD = "MDETFIX"
FIXNOISE_TEXT = "fixnoise colour: the NOISE image's, or white from WGT"
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


def cell_noise(weight: np.ndarray, bad: np.ndarray) -> float:
    """The noise sigma of a cell from its weight map: ``1 / sqrt(median w)`` over the good
    pixels (NaN when there are none)."""
    w = weight[~bad]
    return float(1.0 / np.sqrt(np.median(w))) if w.size else float("nan")


def cell_operation(
    image: np.ndarray,
    psf: np.ndarray,
    step: float,
    target: str,
    engine: str = DEFAULT_ENGINE,
    moving_field: np.ndarray | None = None,
    rotated_field: np.ndarray | None = None,
    kinds: tuple[str, ...] = TYPES,
    moving_correlation: np.ndarray | None = None,
) -> tuple[dict[str, np.ndarray], float]:
    """The metacal versions ``kinds`` (default all five) of a cell and the target's sigma,
    as :func:`~.cell_metacal.cell_versions` (the default engine), or with
    ``engine="galsim"`` by GalSim's reference operation (:mod:`.metacal`,
    :mod:`.cell_fixnoise`; all five made)."""
    # GalSim, FFTs: metadetect only
    from megalut_cli.measure.cell_fixnoise import moving_fixnoise
    from megalut_cli.measure.cell_metacal import cell_versions
    from megalut_cli.measure.metacal import metacal_versions

    if engine != "galsim":
        return cell_versions(
            image, psf, step, target, moving_field, rotated_field, kinds, moving_correlation
        )
    fields = None if rotated_field is None else np.asarray(rotated_field, np.float64)[None]
    versions, sigma = metacal_versions(
        np.asarray(image, np.float64)[None],
        psf,
        step,
        engine="galsim",
        target=target,
        noise_fields=fields,
    )
    out = {kind: v[0] for kind, v in versions.items() if kind in kinds}
    if moving_field is not None:
        for kind, fixnoise in moving_fixnoise(
            moving_field, psf, step, target, moving_correlation
        ).items():
            if kind in out:
                out[kind] += fixnoise
    return out, float(sigma[0])


@functools.lru_cache(maxsize=64)
def _noise_gain(psf_bytes: bytes, psf_size: int, step: float, target: str, engine: str) -> float:
    """The rms of the noshear version of unit white noise (no fixnoise) for this PSF."""
    psf = np.frombuffer(psf_bytes).reshape(psf_size, psf_size)
    size = 96
    noise = np.random.default_rng(0).normal(0.0, 1.0, (size, size))
    return noshear_centre_rms(noise, psf, step, target, engine)


def noshear_centre_rms(
    image: np.ndarray, psf: np.ndarray, step: float, target: str, engine: str
) -> float:
    """The rms of the central half (in each axis) of ``image``'s noshear version."""
    versions, _ = cell_operation(image, psf, step, target, engine, kinds=("noshear",))
    q = image.shape[0] // 4
    return float(versions["noshear"][q:-q, q:-q].std())


def version_noise(
    psf: np.ndarray, sigma: float, step: float, target: str, engine: str = DEFAULT_ENGINE
) -> float:
    """The noise sigma of a metacal version of a cell of noise ``sigma``: the operation's
    gain on white noise, times sqrt(2) for fixnoise."""
    psf = np.ascontiguousarray(psf, dtype=np.float64)
    gain = _noise_gain(psf.tobytes(), psf.shape[0], step, target, engine)
    return float(sigma * np.sqrt(2.0) * gain)


#: Side of the central cut of a noise image whose noshear version gives the detection noise.
NOISE_CUT = 96


def field_version_noise(
    psf: np.ndarray, field: np.ndarray, step: float, target: str, engine: str = DEFAULT_ENGINE
) -> float:
    """The noise sigma of a metacal version of a cell whose noise is like ``field`` (a noise
    image with the data's correlations): the rms of the centre of the noshear version of the
    field's central cut, times sqrt(2) for fixnoise (the field itself, rotated)."""
    ny, nx = field.shape
    size = min(ny, nx, NOISE_CUT)
    y0, x0 = (ny - size) // 2, (nx - size) // 2
    cut = np.asarray(field[y0 : y0 + size, x0 : x0 + size], dtype=np.float64)
    return float(np.sqrt(2.0) * noshear_centre_rms(cut, psf, step, target, engine))


#: The farthest a PSF image's centroid may lie from the image's true centre (pixels).
PSF_CENTRE_TOLERANCE = 0.25


def check_psf(psf: np.ndarray, where: str) -> None:
    """Refuse a cell's PSF image that is not finite, has no flux, or whose centroid lies more
    than :data:`PSF_CENTRE_TOLERANCE` pixels from the image's true centre (e.g. an even-sized
    image centred on a pixel: the operation would shift every object)."""
    from megalut_cli.measure.features import measure_stamps

    if not np.isfinite(psf).all() or not psf.sum() > 0:
        raise InputError(f"{where}: the PSF image has NaN pixels or no flux")
    res = measure_stamps(np.asarray(psf, dtype=np.float64)[None], engine="fast")
    if res["flags"][0]:
        raise InputError(f"{where}: the PSF image could not be measured (adaptive moments)")
    centre = (psf.shape[0] + 1) / 2.0
    dx, dy = float(res["adamom_x"][0]) - centre, float(res["adamom_y"][0]) - centre
    if max(abs(dx), abs(dy)) > PSF_CENTRE_TOLERANCE:
        raise InputError(
            f"{where}: the PSF's centroid lies ({dx:+.2f}, {dy:+.2f}) pixels from the centre of "
            f"its {psf.shape[0]}-pixel image; it must be centred on the image's true centre "
            "(odd size: the central pixel; even size: between the four central pixels)"
        )


@dataclass(frozen=True)
class Detections:
    """sep's detections on one image: 0-based ``x`` (column), ``y`` (row), its windowless
    barycentres, and with ``mask_neighbours`` its segmentation map (detection ``i`` owns the
    pixels holding ``i + 1``; 0: none)."""

    x: np.ndarray
    y: np.ndarray
    segments: np.ndarray | None = None


def detect(
    image: np.ndarray, noise: float, settings: DetectSettings, bad: np.ndarray | None = None
) -> Detections:
    """Detections of sep on ``image`` (background 0) at ``settings.thresh`` times ``noise``."""
    import sep

    data = np.ascontiguousarray(image, dtype=np.float64)
    mask = None if bad is None or not bad.any() else np.ascontiguousarray(bad, dtype=np.uint8)
    found = sep.extract(
        data,
        settings.thresh,
        err=noise,
        mask=mask,
        minarea=settings.minarea,
        deblend_nthresh=settings.nthresh,
        deblend_cont=settings.cont,
        clean=settings.clean,
        segmentation_map=settings.mask_neighbours,
    )
    objects, segments = found if settings.mask_neighbours else (found, None)
    x = np.asarray(objects["x"], dtype=np.float64)
    return Detections(x, np.asarray(objects["y"], dtype=np.float64), segments)


def cleaned_cell(image: np.ndarray, bad: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """A cell as float64 with its bad pixels (None: none) set to 0, and its bad-pixel mask;
    unmasked NaN or infinite pixels are an InputError."""
    image = np.asarray(image, dtype=np.float64)
    bad = np.zeros(image.shape, bool) if bad is None else np.asarray(bad, dtype=bool)
    if not np.isfinite(image[~bad]).all():
        raise InputError("the cell holds NaN or infinite pixels that are not masked")
    return np.where(bad, 0.0, image), bad


def unsheared(
    x: np.ndarray, y: np.ndarray, size: int, direction: tuple[float, float], step: float
) -> tuple[np.ndarray, np.ndarray]:
    """The 0-based positions ``x, y`` of a version of a ``size``-pixel cell sheared by
    ``step`` along ``direction`` about the cell's true centre, taken back to the unsheared
    cell: the same place in every version (and in every cell over it)."""
    g1, g2 = direction[0] * step, direction[1] * step
    c = (size - 1) / 2.0
    dx, dy = x - c, y - c
    k = 1.0 / np.sqrt(1.0 - g1 * g1 - g2 * g2)  # the inverse of GalSim's shear matrix
    return c + k * ((1.0 - g1) * dx - g2 * dy), c + k * (-g2 * dx + (1.0 + g1) * dy)


def cut_around(
    image: np.ndarray,
    bad: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    size: int,
    segments: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Stamps of ``size`` pixels around 0-based positions ``x, y`` of ``image``: the stamps
    (0 outside the image), their masked pixels (``bad`` or outside; with ``segments``, the
    detections' segmentation map, also the pixels of the other detections), their FITS
    1-based lower-left ``origins`` and the objects' 0-based ``(col, row)`` in them."""
    n, (ny, nx) = len(x), image.shape
    x0 = np.floor(x - (size - 1) / 2.0 + 0.5).astype(np.int64)  # the centre within 0.5 px
    y0 = np.floor(y - (size - 1) / 2.0 + 0.5).astype(np.int64)
    rows = (y0 + size)[:, None, None] + np.arange(size)[None, :, None]
    cols = (x0 + size)[:, None, None] + np.arange(size)[None, None, :]

    def cut(values: np.ndarray, outside: Any) -> np.ndarray:
        padded = np.full((ny + 2 * size, nx + 2 * size), outside, dtype=values.dtype)
        padded[size:-size, size:-size] = values
        return padded[rows, cols]

    stamps, masked = cut(np.asarray(image, dtype=np.float64), 0.0), cut(bad, True)
    if segments is not None:  # the other detections' pixels
        owner = cut(segments, 0)
        masked |= (owner != 0) & (owner != np.arange(1, n + 1)[:, None, None])
    origins = np.stack([x0 + 1, y0 + 1], axis=1)
    centres = np.stack([x - x0, y - y0], axis=1)
    return stamps, masked, origins, centres


@dataclass(frozen=True, eq=False)
class CellNoise:
    """A cell's noise, from which its fixnoise and detection threshold are made: white of
    ``sigma`` (the weight map's, :func:`cell_noise`), its fixnoise drawn from ``seed``
    unless ``field`` (white noise of each pixel's variance) is given; a ``correlated``
    ``field`` (a noise image with the data's correlations) gives its correlation
    (:mod:`.noise_correlation`), which colours unit white noise (``unit``, else drawn from
    ``seed``)."""

    sigma: float
    seed: int
    field: np.ndarray | None = None
    correlated: bool = False
    unit: np.ndarray | None = None


def metadetect_cell(
    image: np.ndarray,
    psf: np.ndarray,
    noise: CellNoise,
    settings: MeasureSettings,
    detection: DetectSettings,
    stamp_size: int = MDET_STAMP_SIZE,
    bad: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Metadetection on one cell ``image`` (S, S) with its ``psf`` (P, P) and ``noise``:
    the five versions (``settings.metacal``: step, target; ``bad`` pixels set to 0 first;
    fixnoise that moves with the image, :mod:`.cell_fixnoise`), sep's detections on each at
    ``detection.thresh`` times its noise, and the features of a ``stamp_size`` stamp around
    each detection. Returns the columns ``mdet_step``, ``x``, ``y`` (1-based), the
    features, ``psf_adamom_*`` (the target PSF's) and ``n_masked``, one row per detection
    per version, version by version."""
    # GalSim: metadetect only
    from megalut_cli.measure.metacal import noise_field as drawn_noise
    from megalut_cli.measure.metacal import stamp_target_columns

    mc = settings.metacal
    if mc is None:
        raise ValueError("metadetect needs settings.metacal (the step, seed and target)")
    image, bad = cleaned_cell(image, bad)
    size = image.shape[0]
    psfs = same_parity_psfs(np.asarray(psf, dtype=np.float64)[None], size)
    sigma = noise.sigma if np.isfinite(noise.sigma) and noise.sigma > 0 else 0.0
    field = None
    if noise.field is not None:
        field = np.where(bad, 0.0, np.asarray(noise.field, dtype=np.float64))
        if field.shape != image.shape or not np.isfinite(field).all():
            raise InputError("the noise image must be finite and of the cell's shape")
    engine = settings.engine
    moving = correlation = None
    if field is not None and noise.correlated:  # a noise image: its colour on white noise
        correlation = noise_correlation(field, bad)
        unit = drawn_noise(1.0, noise.seed, image.shape) if noise.unit is None else noise.unit
        moving = np.where(bad, 0.0, unit)  # as the noise image, none on bad pixels
        version_sigma = field_version_noise(psfs[0], field, mc.step, mc.target, engine)
    else:
        if sigma > 0 or field is not None:  # white: fixnoise that moves with the image
            moving = field if field is not None else drawn_noise(sigma, noise.seed, image.shape)
        version_sigma = (
            version_noise(psfs[0], sigma, mc.step, mc.target, engine) if sigma > 0 else 0.0
        )
    versions, target_sigma = cell_operation(
        image, psfs[0], mc.step, mc.target, engine, moving, moving_correlation=correlation
    )
    target = stamp_target_columns(
        mc.target, psfs, np.zeros(1, np.int64), np.array([target_sigma]), mc.step, stamp_size
    )
    measurer = Measurer(dataclasses.replace(settings, metacal=None))
    parts: list[dict[str, np.ndarray]] = []
    for kind in TYPES:
        version = versions[kind]
        # a noiseless cell: a threshold in units of the faintest pixels worth a detection
        floor = version_sigma if version_sigma > 0 else 1e-3 * float(np.abs(version).max() or 1.0)
        found = detect(version, floor, detection, bad)
        x, y, n = found.x, found.y, len(found.x)
        # no detection: the columns of one blank stamp, none of its rows
        at_x, at_y = (x, y) if n else (np.zeros(1), np.zeros(1))
        stamps, masked, origins, centres = cut_around(
            version, bad, at_x, at_y, stamp_size, found.segments
        )
        feats = measurer.measure(StampBatch(stamps, origins, masked=masked, centres=centres))
        feats = {c: v[:n] for c, v in feats.items()}
        ux, uy = unsheared(x, y, size, SHEARS[kind], mc.step)
        row = {MDET_COLUMN: np.full(n, kind), "x": ux + 1.0, "y": uy + 1.0, **feats}
        for c in TARGET_PSF_COLUMNS:
            row[f"psf_{c}"] = np.full(n, target[f"psf_{c}_{kind}"][0])
        parts.append(row)
    return {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}


#: The fixnoise keys of the stamps of ``--detect --metacal``: the cell's key times this plus
#: the detection's index.
KEY_STRIDE = 1 << 20


def detect_cell(
    image: np.ndarray,
    psf: np.ndarray,
    noise_sigma: float,
    key: int,
    settings: MeasureSettings,
    detection: DetectSettings,
    stamp_size: int = MDET_STAMP_SIZE,
    bad: np.ndarray | None = None,
    weight: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Plain detection on one cell ``image`` (``--detect``): sep's detections at
    ``detection.thresh`` times ``noise_sigma`` and the features of a ``stamp_size`` stamp
    around each (neighbours left in), the PSF's features, and with ``settings.metacal`` the
    stamps' metacal versions (fixnoise keys ``key * KEY_STRIDE + i``): the stamp route on the
    cell. Returns ``x``, ``y`` (1-based) and the Measurer's columns, one row per detection."""
    image, bad = cleaned_cell(image, bad)
    floor = noise_sigma if noise_sigma > 0 else 1e-3 * float(np.abs(image).max() or 1.0)
    found = detect(image, floor, detection, bad)
    x, y, n = found.x, found.y, len(found.x)
    at_x, at_y = (x, y) if n else (np.zeros(1), np.zeros(1))
    stamps, masked, origins, centres = cut_around(
        image, bad, at_x, at_y, stamp_size, found.segments
    )
    weights = None
    if weight is not None:
        weights = cut_around(np.where(bad, 0.0, weight), bad, at_x, at_y, stamp_size)[0]
    batch = StampBatch(
        stamps,
        origins,
        masked=masked,
        centres=centres,
        weights=weights,
        psfs=PsfImages(np.asarray(psf, dtype=np.float64)[None], np.zeros(len(stamps), np.int64)),
        fixnoise_keys=int(key) * KEY_STRIDE + np.arange(len(stamps)),
    )
    feats = Measurer(settings).measure(batch)
    return {"x": x + 1.0, "y": y + 1.0, **{c: v[:n] for c, v in feats.items()}}


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


def inner_region(x: np.ndarray, y: np.ndarray, size: int, border: int) -> np.ndarray:
    """Whether the 1-based cell positions ``x, y`` lie in the inner region of a cell of
    ``size`` pixels: ``border < x - 0.5 <= size - border``, likewise ``y`` (half-open, so
    that the inner regions of cells ``size - 2 border`` apart tile a plane)."""
    lo, hi = border + 0.5, size - border + 0.5
    return (x > lo) & (x <= hi) & (y > lo) & (y <= hi)


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


def ordered_features(merged: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The measured columns in the contract's order: the features, the PSF's, ``flags``, then
    the metacal versions' of ``--detect --metacal``."""
    versioned = tuple(f"_{kind}" for kind in TYPES)
    own = [c for c in merged if not c.endswith(versioned)]
    first = [c for c in own if c not in PSF_COLUMNS and c != "flags"]
    order = [*first, *(c for c in PSF_COLUMNS if c in merged), "flags"]
    return {c: merged[c] for c in (*order, *(c for c in merged if c not in order))}


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


def output_format(request: MeasureRequest) -> str:
    """The format of the catalog: ``megalut.metadetect``, or ``megalut.features`` for
    ``--detect`` (one row per detection, a stamp catalog)."""
    return FEATURES_FORMAT if request.detect_only else MDET_FORMAT


def log_detections(request: MeasureRequest, columns: dict[str, np.ndarray], where: str) -> None:
    """Log the detections (per version) and warn when most rows are flagged."""
    per = ""
    if MDET_COLUMN in columns:
        counts = (f"{k} {int((columns[MDET_COLUMN] == k).sum())}" for k in TYPES)
        per = f" ({', '.join(counts)})"
    log.info("%d detections in %s%s", len(columns["x"]), where, per)
    if len(columns["x"]):
        warn_if_mostly_flagged(
            columns["flags"], request.stamps_path, request.names, "the detection settings"
        )


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


def metadetect_cards(request: MeasureRequest, size: int) -> dict[str, Any]:
    """Header cards of every metadetect catalog: the step (``MDETSTEP``; no ``MCALSTEP``: its
    rows are not a metacal catalog's), the seed, the target, the detection settings and the
    stamp size; of a ``--detect`` catalog, what was measured and the detection settings."""
    settings, detection = request.settings, request.detect
    assert detection is not None
    if request.detect_only:  # a stamp catalog: its metacal cards (MCALSTEP...) with --metacal
        cards = {"DETMODE": ("detect", "detection on the cells themselves (--detect)")}
        cards.update(measure_cards(settings, size))
    else:
        assert settings.metacal is not None
        cards = {
            MDET_STEP_CARD: (float(settings.metacal.step), "metadetect shear step"),
            **measure_cards(dataclasses.replace(settings, metacal=None), size),
            SEED_CARD: (int(settings.metacal.seed), "seed of the fixnoise fields (measure --seed)"),
            TARGET_CARD: (settings.metacal.target, "metacal target PSF"),
            "MCALENG": (settings.engine, "engine of the metacal operation on the cells"),
        }
    return {
        **cards,
        "STAMPSZ": (size, "stamp cut around each detection [pixels]"),
        "DETTHRSH": (float(detection.thresh), "detection threshold [noise sigma]"),
        "DETMINAR": (int(detection.minarea), "detection minimum area [pixels]"),
        "DBNTHRSH": (int(detection.nthresh), "deblending sub-thresholds"),
        "DBCONT": (float(detection.cont), "deblending minimum contrast"),
        "DBCLEAN": (bool(detection.clean), "sep's cleaning of the detections"),
        "MASKNBR": (bool(detection.mask_neighbours), "other detections masked in the stamps"),
        "DETECTOR": ("sep", "detection code (Source Extractor as a library)"),
    }


CELLS_SOURCE = register_stamp_source(
    StampSourceType("cells", recognises, check_request, measure_request)
)
