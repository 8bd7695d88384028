"""Detection inside the calibration on one cell: the metacal versions of the whole cell
(:mod:`.cell_metacal`, or GalSim's operation), sep's detections on each version, and the
stamps cut around them (neighbours left in) measured by the one
:class:`~.measurer.Measurer` (:func:`metadetect_cell`); plain detection on the cell itself
(:func:`detect_cell`, ``--detect``); the cell's noise and its detection threshold. Arrays
in, columns out: the sources (:mod:`.cells`, :mod:`.coadd`) read the files.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from megalut_cli import flags as fl
from megalut_cli.engine import DEFAULT_ENGINE
from megalut_cli.errors import InputError
from megalut_cli.measure.defaults import MASK_FILLS, MDET_STAMP_SIZE
from megalut_cli.measure.feature_sets import nan_when_flagged
from megalut_cli.measure.masks import (
    MASK_DISTANCE_COLUMN,
    inpainted,
    mask_distance,
    mask_distance_map,
    nan_flagged,
)
from megalut_cli.measure.measurer import (
    Measurer,
    MeasureSettings,
    PsfImages,
    StampBatch,
    same_parity_psfs,
)
from megalut_cli.measure.metacal_defaults import MDET_COLUMN, SHEARS, TARGET_PSF_COLUMNS, TYPES
from megalut_cli.measure.noise_correlation import noise_correlation
from megalut_cli.measure.source_registry import DetectSettings


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


def cleaned_cell(
    image: np.ndarray, bad: np.ndarray | None, fill: str = MASK_FILLS[0]
) -> tuple[np.ndarray, np.ndarray]:
    """A cell as float64 with its bad pixels (None: none) filled (``fill``: "interpolate",
    the harmonic interpolation of the good pixels, :func:`~.masks.inpainted`; "zero"), and
    its bad-pixel mask; unmasked NaN or infinite pixels are an InputError."""
    image = np.asarray(image, dtype=np.float64)
    bad = np.zeros(image.shape, bool) if bad is None else np.asarray(bad, dtype=bool)
    if not np.isfinite(image[~bad]).all():
        raise InputError("the cell holds NaN or infinite pixels that are not masked")
    return (inpainted(image, bad) if fill == "interpolate" else np.where(bad, 0.0, image)), bad


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

    def cut(values: np.ndarray, outside: Any) -> np.ndarray:
        padded = np.full((ny + 2 * size, nx + 2 * size), outside, dtype=values.dtype)
        padded[size:-size, size:-size] = values
        return sliding_window_view(padded, (size, size))[y0 + size, x0 + size]

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


def detected_stamps(
    image: np.ndarray,
    noise: float,
    detection: DetectSettings,
    bad: np.ndarray,
    stamp_size: int,
) -> tuple[Detections, tuple[np.ndarray, np.ndarray], tuple[np.ndarray, ...]]:
    """sep's detections on ``image`` at ``detection.thresh`` times ``noise`` (0: a noiseless
    image, the threshold in units of a thousandth of its peak), the positions cut around
    (one blank place when there is no detection: the stamps' columns, none of their rows)
    and :func:`cut_around`'s stamps, masks, origins and centres there."""
    floor = noise if noise > 0 else 1e-3 * float(np.abs(image).max() or 1.0)
    found = detect(image, floor, detection, bad)
    at = (found.x, found.y) if len(found.x) else (np.zeros(1), np.zeros(1))
    return found, at, cut_around(image, bad, *at, stamp_size, found.segments)


def flag_near_mask(
    feats: dict[str, np.ndarray],
    distance: np.ndarray,
    margin: float,
    settings: MeasureSettings,
) -> None:
    """Add ``mask_dist`` (``distance``: each row's to the nearest masked pixel of its cell)
    to the columns ``feats`` and flag NEAR_MASK, with NaN features, the rows within
    ``margin`` (in place)."""
    feats[MASK_DISTANCE_COLUMN] = distance.astype(np.float32)
    feats["flags"][distance <= margin] |= fl.NEAR_MASK
    nan_flagged(feats, feats["flags"], nan_when_flagged(settings.feature_sets))


def flag_duplicates(
    feats: dict[str, np.ndarray],
    x: np.ndarray,
    y: np.ndarray,
    radius: float,
    settings: MeasureSettings,
) -> None:
    """Flag DUPLICATE, with NaN features, the detections (1-based positions ``x, y``) whose
    adaptive-moment centroid (``adamom_x``, ``adamom_y``: the same frame) lies within
    ``radius`` pixels of another's: the same light measured twice, kept by the detection
    nearest that centroid (the first of a tie); rows without a centroid take no part (in
    place)."""
    cx, cy = feats["adamom_x"], feats["adamom_y"]  # one row per detection
    measured = np.flatnonzero(np.isfinite(cx) & np.isfinite(cy))
    if radius <= 0 or len(measured) < 2:
        return
    from scipy.spatial import cKDTree

    pairs = cKDTree(np.c_[cx[measured], cy[measured]]).query_pairs(radius, output_type="ndarray")
    if not len(pairs):
        return
    first, second = measured[pairs[:, 0]], measured[pairs[:, 1]]  # first < second
    offset = np.hypot(x - cx, y - cy)
    farther = np.where(offset[first] <= offset[second], second, first)
    feats["flags"][farther] |= fl.DUPLICATE
    nan_flagged(feats, feats["flags"], nan_when_flagged(settings.feature_sets))


@functools.lru_cache(maxsize=8)
def _cell_psfs(psf_bytes: bytes, psf_size: int, cell_size: int) -> np.ndarray:
    """The PSF image (its bytes and side) as :func:`~.measurer.same_parity_psfs` gives it for
    cells of ``cell_size`` pixels, ``(1, P, P)`` (cached, read-only: one PSF image for every
    cell is redrawn once)."""
    psf = np.frombuffer(psf_bytes).reshape(1, psf_size, psf_size)
    psfs = same_parity_psfs(psf, cell_size)
    psfs.flags.writeable = False
    return psfs


@functools.lru_cache(maxsize=8)
def _target_psf_values(
    target: str, psf_bytes: bytes, psf_size: int, target_sigma: float, step: float, size: int
) -> dict[str, float]:
    """``psf_<X>_<type>``: the metacal target's features on a ``size``-pixel stamp, from the
    PSF image (its bytes and side) and the target's sigma (cached)."""
    from megalut_cli.measure.metacal import stamp_target_columns

    psf = np.frombuffer(psf_bytes).reshape(1, psf_size, psf_size)
    columns = stamp_target_columns(
        target, psf, np.zeros(1, np.int64), np.array([target_sigma]), step, size
    )
    return {c: float(v[0]) for c, v in columns.items()}


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
    features, ``psf_adamom_*`` (the target PSF's), ``n_masked`` and ``mask_dist`` (NEAR_MASK
    within ``detection.mask_margin``), one row per detection per version, version by
    version."""
    # GalSim: metadetect only
    from megalut_cli.measure.metacal import noise_field as drawn_noise

    mc = settings.metacal
    if mc is None:
        raise ValueError("metadetect needs settings.metacal (the step, seed and target)")
    image, bad = cleaned_cell(image, bad, detection.mask_fill)
    size = image.shape[0]
    psf = np.ascontiguousarray(psf, dtype=np.float64)
    psfs = _cell_psfs(psf.tobytes(), psf.shape[0], size)
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
    target = _target_psf_values(
        mc.target, psfs[0].tobytes(), psfs.shape[1], target_sigma, mc.step, stamp_size
    )
    measurer = Measurer(dataclasses.replace(settings, metacal=None, mask_margin=0.0))
    distance = mask_distance_map(bad)  # the versions share the cell's mask
    parts: list[dict[str, np.ndarray]] = []
    for kind in TYPES:
        found, _, (stamps, masked, origins, centres) = detected_stamps(
            versions[kind], version_sigma, detection, bad, stamp_size
        )
        x, y, n = found.x, found.y, len(found.x)
        known = np.full(len(stamps), version_sigma) if version_sigma > 0 else None
        feats = measurer.measure(
            StampBatch(stamps, origins, masked=masked, centres=centres, noise=known)
        )
        feats = {c: v[:n] for c, v in feats.items()}
        flag_duplicates(feats, x + 1.0, y + 1.0, detection.duplicate_radius, settings)
        ux, uy = unsheared(x, y, size, SHEARS[kind], mc.step)
        flag_near_mask(feats, mask_distance(bad, ux, uy, distance), detection.mask_margin, settings)
        row = {MDET_COLUMN: np.full(n, kind), "x": ux + 1.0, "y": uy + 1.0, **feats}
        for c in TARGET_PSF_COLUMNS:
            row[f"psf_{c}"] = np.full(n, target[f"psf_{c}_{kind}"])
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
    image, bad = cleaned_cell(image, bad, detection.mask_fill)
    found, (at_x, at_y), (stamps, masked, origins, centres) = detected_stamps(
        image, noise_sigma, detection, bad, stamp_size
    )
    x, y, n = found.x, found.y, len(found.x)
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
    cell_measurer = Measurer(dataclasses.replace(settings, mask_margin=0.0))  # the cell's below
    feats = {c: v[:n] for c, v in cell_measurer.measure(batch).items()}
    flag_duplicates(feats, x + 1.0, y + 1.0, detection.duplicate_radius, settings)
    flag_near_mask(feats, mask_distance(bad, x, y), detection.mask_margin, settings)
    return {"x": x + 1.0, "y": y + 1.0, **feats}
