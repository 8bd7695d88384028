"""``megalut measure``: features of every stamp of a FITS image of stamps.

The stamps are located by a catalog's centres ``x, y`` or, without a catalog, in grid
order (see :mod:`.stamps`). All catalog columns are passed through, and the features of
:mod:`.features` are added; with a PSF image, the PSF features ``psf_adamom_g1,
psf_adamom_g2, psf_adamom_sigma, psf_adamom_rho4`` too.

Work units are chunks of stamps sorted by their position in the image; each worker reads
only the band of image rows its stamps cover, so memory stays bounded for big images
(with ``--scheduler``, the workers must see the input files under the same paths).

PSF images (``--psf``):

* an image of the same shape as the galaxy image is a grid of PSF stamps with the same
  layout: each row gets the PSF stamp at its own galaxy stamp's position;
* otherwise, an image that is a grid of several stamps (stamp size from its ``STAMPSZ``
  card, else the galaxies') is a star field, e.g. GREAT3's 3x3 ``starfield_image``: its
  first (lower-left) stamp is measured;
* otherwise the whole (square) image is one PSF stamp.

In the last two cases every row gets the same PSF features. A per-row PSF stamp that
cannot be measured sets the ``PSF_FAILED`` flag; a single PSF that cannot be measured is
an error.

A PSF model (``--psf-model``, :mod:`.psf_model`: PSFEx or Piff) gives each row the model's
PSF at its position (the catalog's ``x, y``; in grid order the stamp centre, meaningful only
when the stamps image is the exposure the model was fit on), drawn by the work unit on a
stamp like the galaxy's and measured as a per-row PSF stamp of a grid would be.

Catalogs may be FITS tables or text files with ``# name`` header lines (GREAT3's
``galaxy_catalog-SSS.txt``; :func:`megalut_cli.catalog.read_text_catalog`). A
catalog whose centres form a regular grid with a spacing that is not a multiple of the
stamp size, or whose centres all fall off the image, is an error naming the file.

Star fields (``stars``, automatic for images named ``starfield_image-*``, e.g. GREAT3's
3x3 grids of PSF stamps) are measured star by star into ``psf_adamom_*`` columns (see
:data:`STAR_COLUMNS`); a star field without any measurable star is an error.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from megalut_cli import flags as fl
from megalut_cli.atomic import check_output
from megalut_cli.catalog import (
    catalog_info,
    is_fits_file,
    read_cards,
    read_carried_hdus,
    read_catalog_columns,
    read_text_catalog,
    require_columns,
    write_catalog,
)
from megalut_cli.engine import DEFAULT_DEVICE, DEFAULT_ENGINE, resolve_device
from megalut_cli.errors import ConfigError, InputError, Names, namer
from megalut_cli.measure.defaults import FORMAT, FORMAT_VERSION, PSF_COLUMNS
from megalut_cli.measure.features import (
    FEATURE_COLUMNS,
    default_guess_sigma,
    default_max_shift,
    features_from_moments,
    measure_stamps,
    warn_if_mostly_flagged,
)
from megalut_cli.measure.meds import MedsOptions, is_meds, measure_meds_file
from megalut_cli.measure.metacal_defaults import TYPES, metacal_cards, metacal_columns
from megalut_cli.measure.morphology import MORPHOLOGY_COLUMNS, morphology_of_measured
from megalut_cli.measure.options import MEASURE
from megalut_cli.measure.psf_model import cached_psf_model
from megalut_cli.measure.single_psf import single_psf_features, single_psf_stamp
from megalut_cli.measure.stamps import (
    ImageInfo,
    catalog_origins,
    check_grid,
    cut_and_measure,
    cut_stamps,
    cut_stamps_checked,
    grid_origins,
    image_info,
    inside,
    pixel_rows,
    read_band,
    stamp_centres,
    stamp_size_of,
)
from megalut_cli.parallel import executor, map_units, resolve_nproc
from megalut_cli.progress import Progress, no_progress

if TYPE_CHECKING:  # astropy.table costs ~0.4 s to import: only measure_file's Table needs it
    from astropy.table import Table

log = logging.getLogger(__name__)

#: Catalog columns in their order (name -> array), as :func:`measure_file_columns` handles them.
Columns = dict[str, np.ndarray]

#: Output format name of star-field measurements.
STARS_FORMAT = "megalut.stars"

#: Columns of a star-field measurement (``stars``): the features of each star.
STAR_COLUMNS: tuple[str, ...] = (
    "psf_adamom_flux",
    "psf_adamom_g1",
    "psf_adamom_g2",
    "psf_adamom_sigma",
    "psf_adamom_rho4",
    "psf_adamom_x",
    "psf_adamom_y",
)
#: File-name prefixes of star fields measured star by star without ``stars=True``.
STARFIELD_PREFIXES = ("starfield_image", "deep_starfield_image")

#: Stamps per work unit (about 0.3 s of HSM each at 64x64 pixels).
CHUNK_STAMPS = 1000


def _row_band(origins: np.ndarray, size: int) -> tuple[int, int]:
    """The image rows ``y0 .. y1 - 1`` (0-based) that stamps at ``origins`` cover."""
    return int(origins[:, 1].min()) - 1, int(origins[:, 1].max()) - 1 + size


def _measure_unit(unit: dict[str, Any]) -> dict[str, np.ndarray]:
    """Worker: read the band of rows covering ``unit['origins']`` (or take it from
    ``unit['rows']``, for an image in memory) and measure its stamps."""
    size: int = unit["stamp_size"]
    origins: np.ndarray = unit["origins"]
    device = unit.get("device", DEFAULT_DEVICE)
    if unit.get("psf_model") is not None:  # PSF stamps drawn by a model at the rows' positions
        stamps = _model_psfs(unit["psf_model"], size)
        return measure_stamps(
            stamps,
            origins,
            unit["gain"],
            max_shift=unit["max_shift"],
            engine=unit["engine"],
            device=device,
        )
    y0, y1 = _row_band(origins, size)
    rows = unit["rows"] if "rows" in unit else read_band(unit["info"], y0, y1, mapped=True)
    if unit["engine"] == "fast" and device == "gpu":  # the device measures the pixel checks itself
        stamps = cut_stamps(rows, y0, origins, size)
        feats = measure_stamps(
            stamps, origins, unit["gain"], max_shift=unit["max_shift"], engine="fast", device=device
        )
    elif (
        unit["engine"] == "fast" and not unit.get("morphology") and unit.get("metacal") is None
    ):  # the features alone: each stamp cut, checked and measured in one compiled pass
        found = cut_and_measure(rows, y0, origins, size, default_guess_sigma(size))
        return features_from_moments(
            found.moments,
            found.skymad,
            found.finite,
            np.asarray(origins, dtype=np.float64),
            size,
            unit["gain"],
            unit["max_shift"],
        )
    else:  # one pass over the pixels: float64 stamps, whether they are finite, skymad
        cut = cut_stamps_checked(rows, y0, origins, size)
        stamps = cut.stamps
        feats = measure_stamps(
            stamps,
            origins,
            unit["gain"],
            max_shift=unit["max_shift"],
            engine=unit["engine"],
            device=device,
            finite=cut.finite,
            skymad=cut.skymad,
        )
    if unit.get("morphology"):
        feats.update(morphology_of_measured(stamps, origins, feats))
    mc = unit.get("metacal")
    if mc is not None:
        feats.update(_metacal_unit(unit, mc, stamps, feats))
    return feats


def _unit_psf_model(spec: dict[str, Any], rows: np.ndarray) -> dict[str, Any]:
    """A PSF model's spec (``path``, ``xy`` of every stamp) for the stamps ``rows`` of a unit."""
    return {**spec, "xy": np.ascontiguousarray(spec["xy"][rows])}


def _model_psfs(spec: dict[str, Any], size: int) -> np.ndarray:
    """The PSF stamps ``(n, size, size)`` of a unit's PSF model spec, loaded once per process."""
    xy = spec["xy"]
    return cached_psf_model(spec["path"]).draw(xy[:, 0], xy[:, 1], size)


def _metacal_unit(
    unit: dict[str, Any], mc: dict[str, Any], stamps: np.ndarray, feats: dict[str, np.ndarray]
) -> dict[str, np.ndarray]:
    """The metacal features of a unit's stamps (:func:`.metacal.metacal_features`)."""
    from megalut_cli.measure.metacal import fixnoise_seeds, metacal_features  # GalSim: metacal only

    size, origins = unit["stamp_size"], unit["origins"]
    bad = ~np.isfinite(stamps).all(axis=(1, 2))
    if bad.any():
        x, y = stamp_centres(origins[bad][:1], size)[0]
        raise InputError(
            f"{int(bad.sum())} stamp(s) hold NaN or infinite pixels (the first centred at x={x:g}, "
            f"y={y:g}); metacalibration needs whole stamps: cut those rows from the catalog"
        )
    if mc.get("psf") is not None:
        psfs = mc["psf"]
    elif mc.get("psf_model") is not None:
        psfs = _model_psfs(mc["psf_model"], size)
        bad = ~np.isfinite(psfs).all(axis=(1, 2))
        if bad.any():
            x, y = mc["psf_model"]["xy"][bad][0]
            raise InputError(
                f"{mc['psf_model']['path']}: the PSF model has no positive flux at x={x:g}, y={y:g}"
            )
    else:
        y0, y1 = _row_band(origins, size)
        psfs = cut_stamps(read_band(mc["psf_info"], y0, y1), y0, origins, size)
    return metacal_features(
        stamps,
        psfs,
        mc["step"],
        noise_sigma=feats["skymad"],
        seeds=fixnoise_seeds(mc["seed"], mc["keys"]),
        metacal_engine=unit["engine"],
        morphology=bool(unit.get("morphology")),
        origins=origins,
        gain=unit["gain"],
        max_shift=unit["max_shift"],
        engine=unit["engine"],
        device=unit.get("device", DEFAULT_DEVICE),
    )


def _units(
    image: ImageInfo | np.ndarray,
    origins: np.ndarray,
    size: int,
    gain: float | None,
    n_workers: int,
    engine: str,
) -> tuple[list[dict[str, Any]], list[np.ndarray]]:
    """Split the stamps (all inside the image) into chunks sorted by position; a unit of an
    image in memory carries its band of rows."""
    if isinstance(image, ImageInfo):
        image = dataclasses.replace(image, path=os.path.abspath(image.path))  # for remote workers
    order = np.lexsort((origins[:, 0], origins[:, 1]))
    n_units = max(
        -(-len(order) // CHUNK_STAMPS), min(4 * n_workers, len(order)) if n_workers > 1 else 1
    )
    pieces = [p for p in np.array_split(order, max(n_units, 1)) if len(p)]
    units = []
    for p in pieces:
        unit = {
            "stamp_size": size,
            "origins": np.ascontiguousarray(origins[p]),
            "gain": gain,
            "max_shift": default_max_shift(size),
            "engine": engine,
        }
        if isinstance(image, ImageInfo):
            unit["info"] = image
        else:
            y0, y1 = _row_band(unit["origins"], size)
            unit["rows"] = pixel_rows(image[y0:y1])
        units.append(unit)
    return units, pieces


def _run_units(
    image: ImageInfo | np.ndarray,
    origins: np.ndarray,
    size: int,
    gain: float | None,
    nproc: int,
    scheduler: str | None,
    progress: Progress | None,
    label: str,
    engine: str = DEFAULT_ENGINE,
    morphology: bool = False,
    device: str = DEFAULT_DEVICE,
    metacal: dict[str, Any] | None = None,
    psf_model: dict[str, Any] | None = None,
) -> dict[str, np.ndarray]:
    """Measure stamps at ``origins``; stamps off the image get STAMP_OFF_IMAGE and NaN.
    With ``morphology``, the :data:`MORPHOLOGY_COLUMNS` too. On the (resolved) ``device``
    "gpu", the units run in this process. ``metacal``: ``{"step", "seed", "keys" (one per stamp:
    its fixnoise field's, seeded in the worker), "psf" (one PSF image), "psf_info" (a grid of
    PSF stamps like the image) or "psf_model" (below)}`` adds the metacal columns ``X_<type>``.
    ``psf_model``: ``{"path": a PSF model file, "xy": (n, 2) 1-based positions in its
    exposure}``: the stamps measured are the model's PSFs at those positions (drawn in the
    worker, :func:`.psf_model.cached_psf_model`), not the image's."""
    if device == "gpu" and not scheduler:
        nproc = 1
    n = len(origins)
    names = FEATURE_COLUMNS + (MORPHOLOGY_COLUMNS if morphology else ())
    flag_cols = ["flags"] + ([f"flags_{kind}" for kind in TYPES] if metacal is not None else [])
    if metacal is not None:
        names = names + tuple(metacal_columns(names))
    out = {c: np.full(n, np.nan) for c in names if c not in flag_cols}
    ok = inside(origins, size, image.shape)
    for c in flag_cols:
        out[c] = np.zeros(n, dtype=np.int32)
        out[c][~ok] |= fl.STAMP_OFF_IMAGE
    if (~ok).any():
        where = image.path if isinstance(image, ImageInfo) else "image"
        log.warning(
            "%s: %d stamp(s) not entirely inside the image: flagged", where, int((~ok).sum())
        )
    idx = np.flatnonzero(ok)
    if not len(idx):
        return out
    workers = 2 if scheduler else resolve_nproc(nproc)
    units, pieces = _units(image, origins[idx], size, gain, workers, engine)
    for unit, piece in zip(units, pieces):
        unit["morphology"] = morphology
        unit["device"] = device
        if metacal is not None:
            unit["metacal"] = {**metacal, "keys": metacal["keys"][idx[piece]]}
            if metacal.get("psf_model") is not None:
                unit["metacal"]["psf_model"] = _unit_psf_model(metacal["psf_model"], idx[piece])
        if psf_model is not None:
            unit["psf_model"] = _unit_psf_model(psf_model, idx[piece])
    sizes = [len(p) for p in pieces]
    t0 = time.perf_counter()
    with (
        executor(nproc, scheduler, len(units)) as pool,
        (progress or no_progress)(label, len(idx)) as update,
    ):
        done = iter(sizes)

        def tick(_n: int) -> None:
            update(next(done))

        # map_units reports finished units in completion order; stamp counts are close
        # enough for a progress display.
        results = map_units(_measure_unit, units, pool, tick)
    dt = time.perf_counter() - t0
    log.info(
        "%s: measured %d stamps in %.1f s (%.2f ms/stamp)", label, len(idx), dt, 1e3 * dt / len(idx)
    )
    for piece, res in zip(pieces, results):
        rows = idx[piece]
        for c, v in res.items():
            if c in flag_cols:
                out[c][rows] |= v
            else:
                out[c][rows] = v
    return out


def measure_image(
    image: np.ndarray,
    stamp_size: int,
    origins: np.ndarray | None = None,
    gain: float | None = MEASURE["gain"].default,
    *,
    nproc: int = 1,
    scheduler: str | None = None,
    progress: Progress | None = None,
    engine: str = DEFAULT_ENGINE,
    morphology: bool = MEASURE["morphology"].default,
    device: str = DEFAULT_DEVICE,
) -> dict[str, np.ndarray]:
    """In memory: the features of the stamps of ``image`` (2-d array, axis 0 is y), the
    :data:`FEATURE_COLUMNS` (and with ``morphology`` the :data:`MORPHOLOGY_COLUMNS`) as
    arrays. ``origins`` are the stamps' FITS 1-based lower-left pixels ``(x, y)``
    (:func:`megalut_cli.measure.stamps.catalog_origins` from centres); by default the whole
    grid of ``stamp_size`` stamps in grid order. Stamps not inside the image are flagged
    ``STAMP_OFF_IMAGE``. Work is split as :func:`measure_file`'s (``nproc``, ``scheduler``).
    """
    image = np.asarray(image)
    if image.ndim != 2:
        raise ValueError(f"image must be 2-d, got shape {image.shape}")
    if origins is None:
        n_y, n_x = image.shape[0] // stamp_size, image.shape[1] // stamp_size
        origins = grid_origins(n_y, n_x, stamp_size)
    origins = np.asarray(origins, dtype=np.int64).reshape(-1, 2)
    return _run_units(
        image,
        origins,
        stamp_size,
        gain,
        nproc,
        scheduler,
        progress,
        "measuring stamps",
        engine,
        morphology,
        resolve_device(device),
    )


#: Header cards that may give an image's pixel scale (arcsec per pixel), in this order.
PIXEL_SCALE_CARDS = ("PIXSCALE", "PIXSCAL", "SECPIX")


def pixel_scale(header: dict[str, Any]) -> float | None:
    """An image's pixel scale in arcsec from its header (a pixel-scale card, else its WCS),
    or None when it does not say."""
    for key in PIXEL_SCALE_CARDS:
        value = header.get(key)
        if isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0:
            return float(value)
    if "CD1_1" in header or "CDELT1" in header:
        cd11 = float(header.get("CD1_1", header.get("CDELT1", 0.0)))
        cd21 = float(header.get("CD2_1", 0.0))
        scale = 3600.0 * float(np.hypot(cd11, cd21))
        return scale if scale > 0 else None
    return None


def _metacal_psf(
    psf_path: str, gal_info: ImageInfo, size: int, names: Names | None
) -> dict[str, Any]:
    """The PSF of ``--metacal``: one PSF stamp, or a grid like the galaxy image; checked for
    its pixel scale and its size's parity against the galaxy stamps'."""
    name = namer(names)
    psf_info = image_info(psf_path)
    gal_scale, psf_scale = pixel_scale(gal_info.header), pixel_scale(psf_info.header)
    if gal_scale is not None and psf_scale is not None and abs(psf_scale / gal_scale - 1) > 1e-3:
        raise InputError(
            f"{psf_path}: PSF pixels of {psf_scale:g} arcsec for galaxy pixels of {gal_scale:g} "
            f"arcsec ({gal_info.path}); {name('metacal')} needs the PSF at the galaxy image's "
            "pixel scale"
        )
    if psf_info.shape == gal_info.shape:
        return {"psf_info": dataclasses.replace(psf_info, path=os.path.abspath(psf_path))}
    stamp = single_psf_stamp(psf_path, size)
    if stamp.shape[0] % 2 != size % 2:
        raise InputError(
            f"{psf_path}: a {stamp.shape[0]}-pixel PSF stamp for {size}-pixel galaxy stamps: an "
            "even and an odd size put their centres half a pixel apart; cut the PSF to a size of "
            "the same parity"
        )
    return {"psf": stamp}


def _target_psf_columns(
    psf: dict[str, Any], feats: dict[str, np.ndarray], size: int
) -> dict[str, np.ndarray]:
    """``psf_adamom_*_<type>``: the features of each row's target PSF (round, the sigma the
    operation chose for its PSF; the same for the five types)."""
    from megalut_cli.measure.metacal import (  # GalSim: metacal only
        dilated_sigma,
        target_psf_columns,
        target_psf_sigma,
    )

    n = len(feats["psf_adamom_sigma"])
    if "psf" in psf:
        sigma = np.full(n, target_psf_sigma(psf["psf"], psf["step"]))
    else:
        sigma = dilated_sigma(feats["psf_adamom_sigma"], psf["step"])  # the PSF stamps' HSM sigma
    return target_psf_columns(sigma, size)


def _psf_model_spec(
    path: str, positions: np.ndarray, origins: np.ndarray, size: int, gal_info: ImageInfo
) -> dict[str, Any]:
    """Load (and check) the PSF model ``path`` in this process and say what it will give; its
    spec for the work units: ``{"path": absolute, "xy": positions}`` (1-based, one per row)."""
    model = cached_psf_model(path)
    ok = inside(origins, size, gal_info.shape)
    log.info(
        "%s: a %s PSF model (sha256 %s...), drawn at each row's position in the exposure's pixels",
        path,
        model.kind,
        model.sha256[:12],
    )
    out = model.outside(positions[ok, 0], positions[ok, 1]) if ok.any() else np.zeros(0, bool)
    if out.any():
        log.warning(
            "%s: %d of %d position(s) lie outside the area of the stars the model was fit to: "
            "its PSF there is an extrapolation",
            path,
            int(out.sum()),
            int(ok.sum()),
        )
    gal_scale = pixel_scale(gal_info.header)
    if gal_scale is not None and ok.any():
        model_scale = model.native_scale(*np.median(positions[ok], axis=0))
        if model_scale is not None and abs(model_scale / gal_scale - 1) > PIXEL_SCALE_TOLERANCE:
            log.warning(
                "%s: the model's pixels are %.4g arcsec, %s's %.4g arcsec: the stamps should be "
                "cut from the exposure the model was fit on",
                path,
                model_scale,
                gal_info.path,
                gal_scale,
            )
    return {"path": os.path.abspath(path), "xy": np.ascontiguousarray(positions, dtype=np.float64)}


#: Relative difference of pixel scales above which a PSF model's exposure and the stamps'
#: image are said to differ.
PIXEL_SCALE_TOLERANCE = 0.02


def _psf_features(
    psf_path: str,
    gal_info: ImageInfo,
    origins: np.ndarray,
    size: int,
    nproc: int,
    scheduler: str | None,
    progress: Progress | None,
    engine: str = DEFAULT_ENGINE,
    psf_model: dict[str, Any] | None = None,
) -> dict[str, np.ndarray]:
    """``psf_adamom_*`` and ``flags`` (PSF_FAILED) of each row: from a PSF image ``psf_path``, or
    with ``psf_model`` (:func:`_run_units`'s) from the PSF model ``psf_path`` at each row's
    position."""
    n = len(origins)
    res = None
    if psf_model is not None:
        log.info("%s: the PSF model's PSF at each row's position", psf_path)
        res = _run_units(
            gal_info,
            origins,
            size,
            None,
            nproc,
            scheduler,
            progress,
            "drawing and measuring PSFs",
            engine,
            psf_model=psf_model,
        )
    elif image_info(psf_path).shape == gal_info.shape:
        log.info("%s: a PSF stamp per galaxy stamp", psf_path)
        res = _run_units(
            image_info(psf_path),
            origins,
            size,
            None,
            nproc,
            scheduler,
            progress,
            "measuring PSF stamps",
            engine,
        )
    if res is not None:
        out = {p: res[p[len("psf_") :]] for p in PSF_COLUMNS}
        failed = (res["flags"] & ~fl.STAMP_OFF_IMAGE) != 0
        out["flags"] = np.where(failed, fl.PSF_FAILED, 0).astype(np.int32)
        if failed.any():
            log.warning(
                "%s: %d PSF stamp(s) could not be measured: flagged", psf_path, int(failed.sum())
            )
        return out
    values = single_psf_features(psf_path, size, engine)
    log.info(
        "%s: one PSF for all rows (g1=%.4f, g2=%.4f, sigma=%.4f)",
        psf_path,
        values["psf_adamom_g1"],
        values["psf_adamom_g2"],
        values["psf_adamom_sigma"],
    )
    out = {p: np.full(n, values[p]) for p in PSF_COLUMNS}
    out["flags"] = np.zeros(n, dtype=np.int32)
    return out


#: Provenance cards that a stamp image and its catalog, simulated together, share.
SHARED_CARDS = {
    "SEED": "seed",
    "CFGSHA": "config hash",
    "NCASES": "cases",
    "NREA": "realizations",
    "NSTAMPX": "grid stamps per row",
    "STAMPSZ": "stamp size",
}


def check_belongs_together(
    stamps_path: str,
    image_header: dict[str, Any],
    catalog_path: str,
    catalog_header: dict[str, Any],
) -> None:
    """Refuse a catalog whose provenance cards disagree with the stamp image's (another
    simulation)."""

    def short(value: Any) -> str:
        return (
            repr(value[:12] + "...") if isinstance(value, str) and len(value) > 16 else repr(value)
        )

    diffs = [
        f"{what} {key} = {short(catalog_header[key])} vs {short(image_header[key])}"
        for key, what in SHARED_CARDS.items()
        if key in image_header
        and key in catalog_header
        and catalog_header[key] != image_header[key]
    ]
    if diffs:
        raise InputError(
            f"{catalog_path} does not belong to {stamps_path} (catalog vs image: "
            f"{'; '.join(diffs)}); pass the catalog written with these stamps"
        )


def _n_grid_stamps(info: ImageInfo, n_grid: int) -> int:
    """Stamps of a grid: the ``NSTAMPS`` header card (a last row may be partly filled), else all."""
    card = info.header.get("NSTAMPS")
    if card is None:
        return n_grid
    if isinstance(card, bool) or not isinstance(card, int) or not 0 < card <= n_grid:
        raise InputError(
            f"{info.path}: bad NSTAMPS header card {card!r} for a grid of {n_grid} stamps"
        )
    return card


def _read_positions_catalog(path: str | os.PathLike) -> tuple[Columns, dict[str, Any]]:
    """A FITS catalog, or a text catalog with ``# name`` header lines, holding ``x, y``: its
    columns and its header (a Table's ``meta``)."""
    if is_fits_file(path):
        n_rows, names, _ = catalog_info(path)
        require_columns(names, ["x", "y"], path)
        if n_rows == 0:
            raise InputError(f"{path}: the catalog has no rows")
        return read_catalog_columns(path)
    table = read_text_catalog(path)
    require_columns(table.colnames, ["x", "y"], path)
    if len(table) == 0:
        raise InputError(f"{path}: the catalog has no rows")
    return {name: np.asarray(table[name]) for name in table.colnames}, dict(table.meta)


def _card_value(card: Any) -> Any:
    """The value of a header card given as a value or a ``(value, comment)`` pair."""
    return card[0] if isinstance(card, tuple) else card


def _grid_step(v: np.ndarray) -> tuple[float | None, int, bool]:
    """``(step, n_unique, regular)`` of the distinct values of ``v`` (step None if < 3:
    two values always look like a regular grid)."""
    u = np.unique(np.round(v[np.isfinite(v)], 6))
    if u.size < 3:
        return None, int(u.size), True
    d = np.diff(u)
    step = float(d.min())
    return step, int(u.size), bool(np.allclose(d / step, np.round(d / step), rtol=0, atol=1e-6))


def _check_spacing(x: np.ndarray, y: np.ndarray, size: int, path: str, size_key: str) -> None:
    """Error if the centres form a full regular grid whose spacing is not a multiple of ``size``."""
    sx, nx, rx = _grid_step(x)
    sy, ny, ry = _grid_step(y)
    if not (rx and ry) or nx * ny != len(x):
        return  # not a full regular grid: nothing to compare
    for name, step in (("x", sx), ("y", sy)):
        if step is not None and abs(step / size - round(step / size)) > 1e-6:
            raise InputError(
                f"{path}: the catalog centres form a grid {step:g} pixels apart in {name}, which "
                f"does not match the stamp size {size} (wrong {size_key}?)"
            )


def _catalog_positions(table: Columns, path: str) -> tuple[np.ndarray, np.ndarray]:
    require_columns(list(table), ["x", "y"], path)
    bad = [
        c
        for c in ("x", "y")
        if np.asarray(table[c]).dtype.kind not in "iuf" or np.ndim(table[c]) != 1
    ]
    if bad:
        raise InputError(f"{path}: column(s) {', '.join(bad)} must be numeric scalars")
    return np.asarray(table["x"], np.float64), np.asarray(table["y"], np.float64)


def measure_file_columns(
    stamps_path: str | os.PathLike,
    catalog_path: str | os.PathLike | None,
    output: str | os.PathLike,
    stamp_size: int | None = MEASURE["stamp_size"].default,
    origin: int = int(MEASURE["origin"].default),
    gain: float | None = MEASURE["gain"].default,
    psf_path: str | os.PathLike | None = None,
    nproc: int = 1,
    scheduler: str | None = None,
    overwrite: bool = False,
    progress: Progress | None = None,
    stars: bool | None = MEASURE["stars"].default,
    engine: str = DEFAULT_ENGINE,
    morphology: bool = MEASURE["morphology"].default,
    device: str = DEFAULT_DEVICE,
    names: Names | None = None,
    metacal: bool = MEASURE["metacal"].default,
    metacal_step: float = MEASURE["metacal_step"].default,
    seed: int = MEASURE["seed"].default,
    cutout: int = MEASURE["cutout"].default,
    psf_model_path: str | os.PathLike | None = None,
) -> tuple[Columns, dict[str, Any]]:
    """Measure every stamp of ``stamps_path`` and write the features catalog ``output``.

    A MEDS file as ``stamps_path`` (:func:`megalut_cli.measure.meds.is_meds`) is measured
    object by object instead (:func:`megalut_cli.measure.meds.measure_meds_file`: its
    ``cutout``, one row per object); it takes no catalog, ``stamp_size``, ``origin`` or ``stars``.

    Args:
        stamps_path: FITS image of stamps.
        catalog_path: FITS or text (``# name`` header lines) catalog with stamp centres
            ``x, y`` (all its columns are passed through), or None for grid order (then
            ``x, y`` centres are added; the image's ``NSTAMPS`` card, if any, gives the
            number of stamps).
        output: features catalog to write (format ``megalut.features``).
        stamp_size: stamp size in pixels; None reads the image's ``STAMPSZ`` card.
        origin: 1 if catalog centres are FITS 1-based, 0 if 0-based (GREAT3).
        gain: electrons/ADU for the S/N (Eq. 8); None: Eq. 10.
        psf_path: optional FITS image of PSF stamps (see the module docstring).
        nproc, scheduler: local worker processes, or a Dask scheduler address/file.
        overwrite: replace ``output`` if it exists.
        progress: a :data:`megalut_cli.progress.Progress` (stamps measured).
        stars: measure a star field star by star into :data:`STAR_COLUMNS` (format
            ``megalut.stars``); None: when the file name starts with ``starfield_image``.
            Without ``stamp_size`` or a ``STAMPSZ`` card, a square star field is taken
            as GREAT3's 3x3 grid.
        engine: ``fast`` (compiled adaptive moments) or ``galsim`` (``FindAdaptiveMom``),
            see :mod:`megalut_cli.engine`.
        morphology: also measure :data:`MORPHOLOGY_COLUMNS` (``measure/morphology.py``).
        device: ``cpu`` or ``gpu`` (resolved, :func:`megalut_cli.engine.resolve_device`): where
            the fast engine measures the moments.
        names: how messages name the arguments (e.g. ``{"stamp_size": "--stamp-size"}``).
        metacal: also the features of the five metacal versions of each stamp, ``X_<type>``
            (:mod:`.metacal`; needs ``psf_path``), and ``psf_adamom_*_<type>`` of the target
            PSF; header cards ``MCALSTEP``, ``MCALSEED``.
        metacal_step: the shear step of ``metacal``.
        seed: seed of the fixnoise fields of ``metacal``.
        cutout: MEDS input: the cutout index measured.
        psf_model_path: a PSF model of the exposure the stamps are cut from (a PSFEx ``.psf``
            file or a Piff model, :mod:`.psf_model`; not with ``psf_path``): each row's PSF is
            the model's at its position (the catalog's ``x, y``, else the stamp centre), drawn
            in the exposure's pixels on a stamp like the galaxy's, for ``psf_adamom_*`` and
            ``metacal``; header cards ``PSFMODEL``, ``PSFMSHA``, ``PSFMTYPE``.

    Returns:
        The columns written (name -> array, in order) and the input catalog's header (empty
        in grid order); no astropy Table is made (see :func:`measure_file`).
    """
    name = namer(names)
    if psf_path is not None and psf_model_path is not None:
        raise ConfigError(
            f"{name('psf_path')} and {name('psf_model_path')} exclude each other: give one PSF"
        )
    if is_meds(stamps_path):  # a MEDS cutout file: one row per object (measure/meds.py)
        if catalog_path is not None:
            raise ConfigError(
                f"{stamps_path} is a MEDS file, which carries its own objects: give it no catalog"
            )
        wrong = [
            name(k)
            for k, given in (
                ("stamp_size", stamp_size is not None),
                ("origin", origin != 1),
                ("stars", bool(stars)),
            )
            if given
        ]
        if wrong:
            raise ConfigError(
                f"{stamps_path} is a MEDS file (each object has its box_size): leave out "
                f"{', '.join(wrong)}"
            )
        options = MedsOptions(
            cutout=cutout,
            gain=gain,
            psf_path=psf_path,
            psf_model_path=psf_model_path,
            engine=engine,
            morphology=morphology,
            metacal=metacal,
            metacal_step=metacal_step,
            seed=seed,
        )
        columns, _ = measure_meds_file(
            stamps_path,
            output,
            options,
            nproc=nproc,
            scheduler=scheduler,
            overwrite=overwrite,
            progress=progress,
            device=device,
            names=names,
        )
        return columns, {}
    if cutout != MEASURE["cutout"].default:
        raise ConfigError(
            f"{name('cutout')} applies to MEDS files only; {stamps_path} is an image of stamps"
        )
    check_output(output, overwrite)
    if gain is not None and not (np.isfinite(gain) and gain > 0):
        raise ConfigError(f"{name('gain')} must be a positive number, got {gain}")
    if origin not in (0, 1):
        raise ConfigError(f"{name('origin')} must be 0 or 1, got {origin}")
    if metacal and psf_path is None and psf_model_path is None:
        raise ConfigError(
            f"{name('metacal')} needs {name('psf_path')} or {name('psf_model_path')}: the PSF to "
            "deconvolve each stamp by"
        )
    if metacal and not 0 < metacal_step <= MEASURE["metacal_step"].maximum:
        raise ConfigError(
            f"{name('metacal_step')} must be in (0, {MEASURE['metacal_step'].maximum}], got "
            f"{metacal_step}"
        )
    stamps_path = str(stamps_path)
    info = image_info(stamps_path)
    if stars is None:
        stars = os.path.basename(stamps_path).startswith(STARFIELD_PREFIXES)
        if stars:
            log.info("%s: a star field: measuring its stars into psf_adamom_* columns", stamps_path)
    if stars and metacal:
        raise ConfigError(f"{name('metacal')} does not apply to a star field")
    for key, given in (("psf_path", psf_path), ("psf_model_path", psf_model_path)):
        if stars and given is not None:
            raise ConfigError(f"{name(key)} does not apply to a star field (its stars are the PSF)")
    if psf_model_path is not None:
        cached_psf_model(str(psf_model_path))  # fail early on a file that is no PSF model
    if (
        stars
        and stamp_size is None
        and info.header.get("STAMPSZ") is None
        and info.shape[0] == info.shape[1]
    ):
        stamp_size = info.shape[0] // 3  # GREAT3: a 3x3 grid of stars
        log.info("%s: no stamp size given: a 3x3 grid of %d-pixel stars", stamps_path, stamp_size)
    if stamp_size is not None and info.header.get("STAMPSZ") not in (None, stamp_size):
        raise InputError(
            f"{stamps_path}: stamp size {stamp_size} ({name('stamp_size')}) contradicts the "
            f"image's STAMPSZ = {info.header.get('STAMPSZ')} card; leave {name('stamp_size')} out "
            "to use the card"
        )
    size = stamp_size_of(info, stamp_size, name("stamp_size"))
    n_y, n_x = check_grid(info, size)

    extra_hdus: dict[str, np.ndarray] = {}
    if catalog_path is not None:
        table, meta = _read_positions_catalog(catalog_path)
        check_belongs_together(stamps_path, info.header, str(catalog_path), meta)
        x, y = _catalog_positions(table, str(catalog_path))
        _check_spacing(x, y, size, str(catalog_path), name("stamp_size"))
        origins = catalog_origins(x, y, size, origin, name("origin"))
        if not inside(origins, size, info.shape).any():
            raise InputError(
                f"{catalog_path}: no stamp centre falls on {stamps_path} ({n_x}x{n_y} stamps of "
                f"{size} pixels; wrong {name('origin')} or {name('stamp_size')}?)"
            )
        history = meta.get("HISTORY")
        if is_fits_file(catalog_path):  # carried with their comments, and the CONFIG HDU
            cards = read_cards(catalog_path)
            extra_hdus = read_carried_hdus(catalog_path)
        else:
            cards = {k: v for k, v in meta.items() if k not in ("HISTORY", "COMMENT")}
    else:
        origins = grid_origins(n_y, n_x, size)[: _n_grid_stamps(info, n_y * n_x)]
        centres = stamp_centres(origins, size)
        table, meta = {"x": centres[:, 0].copy(), "y": centres[:, 1].copy()}, {}
        history = info.header.get("HISTORY")
        cards = read_cards(stamps_path, ext=info.ext)  # the image's provenance (seed, config)
    log.info("%s: %d stamps of %dx%d pixels", stamps_path, len(origins), size, size)
    header_gain = _card_value(cards.get("GAIN", info.header.get("GAIN")))
    if gain is None and header_gain is not None:
        log.warning(
            "the input header has GAIN=%s but no %s was given: snr uses Eq. 10 "
            "(sky-limited); pass %s %s for Eq. 8",
            header_gain,
            name("gain"),
            name("gain"),
            header_gain,
        )

    mc = None
    model_spec = None
    if psf_model_path is not None:  # each row's position in the exposure, 1-based
        positions = (
            (np.column_stack([x, y]) + (1 - origin)) if catalog_path is not None else centres
        )
        model_spec = _psf_model_spec(str(psf_model_path), positions, origins, size, info)
        psf_path = model_spec["path"]
        cards.update(cached_psf_model(psf_path).header_cards())
    if psf_path is not None:
        psf_path = str(psf_path)
        if model_spec is None:
            image_info(psf_path)  # fail early on a bad PSF file, before the long measurement
        if metacal:
            if model_spec is not None:
                mc = {"psf_model": model_spec, "step": float(metacal_step)}
            else:
                mc = {**_metacal_psf(psf_path, info, size, names), "step": float(metacal_step)}
            common = bool(_card_value(cards.get("CRN", False))) and "rea" in table
            # the fields' keys: the realization in a common-random-number set, else the row
            mc["keys"] = (
                np.asarray(table["rea"], dtype=np.int64) if common else np.arange(len(origins))
            )
            mc["seed"] = int(seed)

    if stars and morphology:
        raise ConfigError(f"{name('morphology')} does not apply to a star field")
    feats = _run_units(
        info,
        origins,
        size,
        gain,
        nproc,
        scheduler,
        progress,
        "measuring stamps",
        engine,
        morphology,
        device,
        mc,
    )
    psf = None
    if psf_path is not None:
        psf = _psf_features(
            psf_path, info, origins, size, nproc, scheduler, progress, engine, model_spec
        )
        psf_flags = psf.pop("flags")
        feats["flags"] |= psf_flags
        if mc is not None:
            for kind in TYPES:
                feats[f"flags_{kind}"] |= psf_flags
            psf.update(_target_psf_columns(mc, psf, size))

    if stars:
        return _write_stars(
            stamps_path,
            table,
            feats,
            output,
            overwrite,
            size,
            origin if catalog_path else 1,
            cards,
            history,
            extra_hdus,
        ), meta

    feature_cols = list(FEATURE_COLUMNS) + (list(MORPHOLOGY_COLUMNS) if morphology else [])
    psf_cols = list(PSF_COLUMNS) if psf is not None else []
    if mc is not None:
        feature_cols += metacal_columns(feature_cols)
        psf_cols += metacal_columns(psf_cols)
    new_cols = feature_cols + psf_cols
    replaced = [c for c in new_cols if c in table]
    if replaced:
        log.warning("replacing existing column(s) %s", ", ".join(replaced))
        for c in replaced:
            del table[c]
    for c in feature_cols:
        table[c] = feats[c]
    if psf is not None:
        for c in psf_cols:
            table[c] = psf[c]

    nflag = int((feats["flags"] != 0).sum())
    log.info("%d of %d stamps flagged (features NaN)", nflag, len(origins))
    warn_if_mostly_flagged(feats["flags"], stamps_path, names)
    cards.update(
        {
            "STAMPSZ": (size, "stamp size [pixels]"),
            "XYORIGIN": (
                origin if catalog_path is not None else 1,
                "coordinate of the first pixel in x, y",
            ),
            "GAIN": (gain, "gain [e-/ADU] of the S/N (Eq. 8)") if gain is not None else None,
            "MAXSHIFT": (default_max_shift(size), "centroid shift limit [pixels]"),
            "MENGINE": (engine, "engine of the adaptive moments (megalut --engine)"),
        }
    )
    if mc is not None:
        cards.update(metacal_cards(metacal_step, seed, "measure"))
    if "MEASURED" in cards:  # a simulation's card: the features are now measured
        cards["MEASURED"] = (True, "the catalog holds measured features")
    write_catalog(
        output,
        table,
        fmt=FORMAT,
        fmt_version=FORMAT_VERSION,
        overwrite=overwrite,
        cards=cards,
        history=history,
        extra_hdus=extra_hdus,
    )
    log.info("wrote %s (%d rows)", output, len(origins))
    return table, meta


def measure_file(*args: Any, **kwargs: Any) -> Table:
    """:func:`measure_file_columns` (the same arguments), returning the table written as an
    astropy Table whose ``meta`` is the input catalog's header."""
    from astropy.table import Table

    columns, meta = measure_file_columns(*args, **kwargs)
    table = Table(columns, copy=False)
    table.meta.update(meta)
    return table


def _write_stars(
    path: str,
    table: Columns,
    feats: dict[str, np.ndarray],
    output: str | os.PathLike,
    overwrite: bool,
    size: int,
    origin: int,
    cards: dict[str, Any],
    history: list[str] | None,
    extra_hdus: dict[str, np.ndarray],
) -> Columns:
    """Write the star-by-star PSF features of a star field (format ``megalut.stars``)."""
    good = feats["flags"] == 0
    if not good.any():
        raise InputError(f"{path}: no star could be measured (a star field without stars?)")
    if "star" not in table:
        table["star"] = np.arange(len(good), dtype=np.int64)
    replaced = [c for c in (*STAR_COLUMNS, "flags") if c in table]
    if replaced:
        log.warning("replacing existing column(s) %s", ", ".join(replaced))
        for c in replaced:
            del table[c]
    for c in STAR_COLUMNS:
        table[c] = feats[c[len("psf_") :]]
    table["flags"] = feats["flags"]
    if not good.all():
        log.warning(
            "%s: %d of %d star stamp(s) could not be measured: flagged",
            path,
            int((~good).sum()),
            len(good),
        )
    cards.update(
        {
            "STAMPSZ": (size, "stamp size [pixels]"),
            "XYORIGIN": (origin, "coordinate of the first pixel in x, y"),
            "NSTARS": (int(good.sum()), "stars measured"),
        }
    )
    cards.pop("MEASURED", None)
    write_catalog(
        output,
        table,
        fmt=STARS_FORMAT,
        fmt_version=FORMAT_VERSION,
        overwrite=overwrite,
        cards=cards,
        history=history,
        extra_hdus=extra_hdus,
    )
    log.info("wrote %s (%d stars)", output, len(good))
    return table
