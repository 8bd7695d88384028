"""Grid images as a stamp source: stamps located by a catalog's centres ``x, y`` (FITS, or
text with ``# name`` lines such as GREAT3's; every column passed through) or in grid order,
star fields measured star by star, and the PSF of each stamp:

* ``--psf`` an image of the galaxy image's shape: a grid of PSF stamps, one per stamp;
* ``--psf`` another image: one PSF for every row (the whole square image, or the first
  stamp of a grid of ``STAMPSZ`` stamps such as GREAT3's star field); one that cannot be
  measured is an error;
* ``--psf-model`` (:mod:`.psf_model`): the model's PSF at each row's position (the
  catalog's ``x, y``, else the stamp centre), drawn in the work unit.

Work units are chunks of stamps sorted by their position in the image; each worker reads
only the band of image rows its stamps cover, so memory stays bounded for big images.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from megalut_cli import flags as fl
from megalut_cli.catalog import (
    catalog_info,
    is_fits_file,
    read_cards,
    read_carried_hdus,
    read_catalog_columns,
    read_text_catalog,
    require_columns,
)
from megalut_cli.errors import ConfigError, InputError, Names, namer
from megalut_cli.measure.defaults import FORMAT, PSF_COLUMNS
from megalut_cli.measure.features import (
    default_guess_sigma,
    default_max_shift,
    features_from_moments,
    warn_if_mostly_flagged,
)
from megalut_cli.measure.measurer import (
    MeasureSettings,
    PsfImages,
    StampBatch,
    distinct_psfs,
    measure_cards,
    metacal_columns,
    retry_cards,
    twin_fixnoise,
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
from megalut_cli.measure.units import (
    empty_columns,
    measure_units,
    n_units,
    workers,
)
from megalut_cli.progress import Progress
from megalut_cli.shear.frame import JACOBIAN_COLUMNS, celestial_jacobians, is_celestial

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GridPsf:
    """The PSF of grid stamps: ``single`` (one image for every stamp), ``grid`` (an image of
    PSF stamps laid out like the galaxy image) or ``model_path`` (a PSF model drawn at
    ``model_xy``, each stamp's 1-based position in the model's exposure)."""

    single: np.ndarray | None = None
    grid: ImageInfo | None = None
    model_path: str | None = None
    model_xy: np.ndarray | None = None


def row_band(origins: np.ndarray, size: int) -> tuple[int, int]:
    """The image rows ``y0 .. y1 - 1`` (0-based) that stamps at ``origins`` cover."""
    return int(origins[:, 1].min()) - 1, int(origins[:, 1].max()) - 1 + size


@dataclass(frozen=True)
class GridUnit:
    """Stamps of a grid image at ``origins`` (all inside it), filling output ``rows``: read
    from ``image``, or from ``band`` (its rows, for an image in memory)."""

    rows: np.ndarray
    origins: np.ndarray
    stamp_size: int
    image: ImageInfo | None = None
    band: np.ndarray | None = None
    psf: GridPsf | None = None
    fixnoise_keys: np.ndarray | None = None
    fixnoise_signs: np.ndarray | None = None

    def batch(self, settings: MeasureSettings) -> StampBatch:
        """The unit's stamps; with the fast engine on the CPU and nothing asked beyond the base
        features, each stamp is cut, checked and measured in one compiled pass."""
        size, origins = self.stamp_size, self.origins
        y0, y1 = row_band(origins, size)
        rows = self.band if self.band is not None else read_band(self.image, y0, y1, mapped=True)  # type: ignore[arg-type]
        psfs = self.psf_images(y0, y1, settings)
        keys, signs = self.fixnoise_keys, self.fixnoise_signs
        if settings.engine == "fast" and settings.device == "gpu":  # the device checks the pixels
            stamps = cut_stamps(rows, y0, origins, size)
            if settings.metacal is not None:
                self.check_whole(np.isfinite(stamps).all(axis=(1, 2)))
            return StampBatch(stamps, origins, psfs=psfs, fixnoise_keys=keys, fixnoise_signs=signs)
        if settings.engine == "fast" and not settings.needs_pixels:
            found = cut_and_measure(
                rows, y0, origins, size, default_guess_sigma(size), settings.moments_retry
            )
            base = features_from_moments(
                found.moments,
                found.skymad,
                found.finite,
                np.asarray(origins, dtype=np.float64),
                size,
                settings.gain,
                default_max_shift(size),
            )
            return StampBatch(None, origins, psfs=psfs, base=base)
        cut = cut_stamps_checked(rows, y0, origins, size)
        if settings.metacal is not None:
            self.check_whole(cut.finite)
        return StampBatch(
            cut.stamps,
            origins,
            cut.finite,
            cut.skymad,
            psfs=psfs,
            fixnoise_keys=keys,
            fixnoise_signs=signs,
        )

    def check_whole(self, finite: np.ndarray) -> None:
        """Metacal needs whole stamps: NaN or infinite pixels are an error."""
        if not finite.all():
            x, y = stamp_centres(self.origins[~finite][:1], self.stamp_size)[0]
            raise InputError(
                f"{int((~finite).sum())} stamp(s) hold NaN or infinite pixels (the first centred "
                f"at x={x:g}, y={y:g}); metacalibration needs whole stamps: cut those rows from "
                "the catalog"
            )

    def psf_images(self, y0: int, y1: int, settings: MeasureSettings) -> PsfImages | None:
        """The PSF of each stamp of the unit."""
        psf, n, size = self.psf, len(self.origins), self.stamp_size
        if psf is None:
            return None
        if psf.single is not None:
            return PsfImages(psf.single[None], np.zeros(n, dtype=np.int64))
        if psf.grid is not None:
            images, index = distinct_psfs(
                cut_stamps(read_band(psf.grid, y0, y1), y0, self.origins, size)
            )
            return PsfImages(images, index)
        assert psf.model_path is not None and psf.model_xy is not None
        xy = psf.model_xy
        images = np.asarray(cached_psf_model(psf.model_path).draw(xy[:, 0], xy[:, 1], size))
        bad = ~np.isfinite(images).all(axis=(1, 2))
        if bad.any() and settings.metacal is not None:
            x, y = xy[bad][0]
            raise InputError(
                f"{psf.model_path}: the PSF model has no positive flux at x={x:g}, y={y:g}"
            )
        return PsfImages(images, np.arange(n))


def grid_columns(settings: MeasureSettings, psf: bool) -> list[str]:
    """The columns a grid measurement writes: features, ``psf_adamom_*`` with a PSF, and with
    metacal both again per version (the PSF's of the target PSF)."""
    features = list(settings.feature_columns)
    psf_cols = list(PSF_COLUMNS) if psf else []
    if settings.metacal is not None:
        features += metacal_columns(features)
        psf_cols += metacal_columns(psf_cols)
    return features + psf_cols


def measure_grid(
    image: ImageInfo | np.ndarray,
    origins: np.ndarray,
    size: int,
    settings: MeasureSettings,
    *,
    psf: GridPsf | None = None,
    fixnoise_keys: np.ndarray | None = None,
    fixnoise_signs: np.ndarray | None = None,
    nproc: int = 1,
    scheduler: str | None = None,
    progress: Progress | None = None,
) -> dict[str, np.ndarray]:
    """The columns (:func:`grid_columns`) of stamps at ``origins`` of an image (a file or an
    array); stamps not entirely inside it get STAMP_OFF_IMAGE and NaN."""
    n = len(origins)
    ok = inside(origins, size, image.shape)
    initial = np.where(ok, 0, fl.STAMP_OFF_IMAGE).astype(np.int32)
    columns = empty_columns(n, grid_columns(settings, psf is not None), initial)
    if (~ok).any():
        where = image.path if isinstance(image, ImageInfo) else "image"
        log.warning(
            "%s: %d stamp(s) not entirely inside the image: flagged", where, int((~ok).sum())
        )
    idx = np.flatnonzero(ok)
    if not len(idx):
        return columns
    if isinstance(image, ImageInfo):
        image = dataclasses.replace(image, path=os.path.abspath(image.path))  # remote workers
    if psf is not None and psf.grid is not None:
        psf = dataclasses.replace(
            psf, grid=dataclasses.replace(psf.grid, path=os.path.abspath(psf.grid.path))
        )
    order = idx[np.lexsort((origins[idx, 0], origins[idx, 1]))]
    units = []
    for rows in np.array_split(order, n_units(len(order), workers(nproc, scheduler))):
        if not len(rows):
            continue
        unit_origins = np.ascontiguousarray(origins[rows])
        band = None
        if not isinstance(image, ImageInfo):
            y0, y1 = row_band(unit_origins, size)
            band = pixel_rows(image[y0:y1])
        unit_psf = psf
        if psf is not None and psf.model_xy is not None:
            unit_psf = dataclasses.replace(psf, model_xy=np.ascontiguousarray(psf.model_xy[rows]))
        units.append(
            GridUnit(
                rows,
                unit_origins,
                size,
                image if isinstance(image, ImageInfo) else None,
                band,
                unit_psf,
                None if fixnoise_keys is None else fixnoise_keys[rows],
                None if fixnoise_signs is None else fixnoise_signs[rows],
            )
        )
    measure_units(units, settings, columns, nproc=nproc, scheduler=scheduler, progress=progress)
    if psf is not None:
        failed = (columns["flags"] & fl.PSF_FAILED) != 0
        if failed.any():
            log.warning("%d PSF stamp(s) could not be measured: flagged", int(failed.sum()))
    return columns


# --------------------------------------------------------------------------- the file source

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

#: Header cards that may give an image's pixel scale (arcsec per pixel), in this order.
PIXEL_SCALE_CARDS = ("PIXSCALE", "PIXSCAL", "SECPIX")
#: Relative difference of pixel scales above which a PSF model's exposure and the stamps'
#: image are said to differ.
PIXEL_SCALE_TOLERANCE = 0.02

#: Provenance cards that a stamp image and its catalog, simulated together, share.
SHARED_CARDS = {
    "SEED": "seed",
    "CFGSHA": "config hash",
    "NCASES": "cases",
    "NREA": "realizations",
    "NSTAMPX": "grid stamps per row",
    "STAMPSZ": "stamp size",
}

#: Catalog columns in their order (name -> array).
Columns = dict[str, np.ndarray]


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


def n_grid_stamps(info: ImageInfo, n_grid: int) -> int:
    """Stamps of a grid: the ``NSTAMPS`` header card (a last row may be partly filled), else all."""
    card = info.header.get("NSTAMPS")
    if card is None:
        return n_grid
    if isinstance(card, bool) or not isinstance(card, int) or not 0 < card <= n_grid:
        raise InputError(
            f"{info.path}: bad NSTAMPS header card {card!r} for a grid of {n_grid} stamps"
        )
    return card


def read_positions_catalog(path: str | os.PathLike) -> tuple[Columns, dict[str, Any]]:
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


def card_value(card: Any) -> Any:
    """The value of a header card given as a value or a ``(value, comment)`` pair."""
    return card[0] if isinstance(card, tuple) else card


def grid_step(v: np.ndarray) -> tuple[float | None, int, bool]:
    """``(step, n_unique, regular)`` of the distinct values of ``v`` (step None if < 3:
    two values always look like a regular grid)."""
    u = np.unique(np.round(v[np.isfinite(v)], 6))
    if u.size < 3:
        return None, int(u.size), True
    d = np.diff(u)
    step = float(d.min())
    return step, int(u.size), bool(np.allclose(d / step, np.round(d / step), rtol=0, atol=1e-6))


def check_spacing(x: np.ndarray, y: np.ndarray, size: int, path: str, size_key: str) -> None:
    """Error if the centres form a full regular grid whose spacing is not a multiple of ``size``."""
    sx, nx, rx = grid_step(x)
    sy, ny, ry = grid_step(y)
    if not (rx and ry) or nx * ny != len(x):
        return  # not a full regular grid: nothing to compare
    for name, step in (("x", sx), ("y", sy)):
        if step is not None and abs(step / size - round(step / size)) > 1e-6:
            raise InputError(
                f"{path}: the catalog centres form a grid {step:g} pixels apart in {name}, which "
                f"does not match the stamp size {size} (wrong {size_key}?)"
            )


def catalog_positions(table: Columns, path: str) -> tuple[np.ndarray, np.ndarray]:
    """The numeric centres ``x, y`` of a positions catalog."""
    require_columns(list(table), ["x", "y"], path)
    bad = [
        c
        for c in ("x", "y")
        if np.asarray(table[c]).dtype.kind not in "iuf" or np.ndim(table[c]) != 1
    ]
    if bad:
        raise InputError(f"{path}: column(s) {', '.join(bad)} must be numeric scalars")
    return np.asarray(table["x"], np.float64), np.asarray(table["y"], np.float64)


def check_metacal_psf(
    psf_path: str, gal_info: ImageInfo, psf: GridPsf, size: int, names: Names | None
) -> None:
    """The PSF of ``--metacal`` checked for its pixel scale and its size's parity against the
    galaxy stamps'."""
    name = namer(names)
    psf_info = image_info(psf_path)
    gal_scale, psf_scale = pixel_scale(gal_info.header), pixel_scale(psf_info.header)
    if gal_scale is not None and psf_scale is not None and abs(psf_scale / gal_scale - 1) > 1e-3:
        raise InputError(
            f"{psf_path}: PSF pixels of {psf_scale:g} arcsec for galaxy pixels of {gal_scale:g} "
            f"arcsec ({gal_info.path}); {name('metacal')} needs the PSF at the galaxy image's "
            "pixel scale"
        )
    if psf.single is not None and psf.single.shape[0] % 2 != size % 2:
        raise InputError(
            f"{psf_path}: a {psf.single.shape[0]}-pixel PSF stamp for {size}-pixel galaxy "
            "stamps: an even and an odd size put their centres half a pixel apart; cut the PSF "
            "to a size of the same parity"
        )


def model_psf(
    path: str, positions: np.ndarray, origins: np.ndarray, size: int, gal_info: ImageInfo
) -> GridPsf:
    """Load (and check) the PSF model ``path`` in this process and say what it will give;
    the :class:`GridPsf` of the work units (absolute path, 1-based positions of every row)."""
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
    return GridPsf(
        model_path=os.path.abspath(path),
        model_xy=np.ascontiguousarray(positions, dtype=np.float64),
    )


def image_psf(psf_path: str, gal_info: ImageInfo, size: int, engine: str) -> GridPsf:
    """The PSF of ``--psf`` without metacal: a grid like the galaxy image (a PSF stamp per
    stamp), else one PSF for every row (checked and measured here, before the long work)."""
    psf_info = image_info(psf_path)
    if psf_info.shape == gal_info.shape:
        log.info("%s: a PSF stamp per galaxy stamp", psf_path)
        return GridPsf(grid=psf_info)
    values = single_psf_features(psf_path, size, engine)
    log.info(
        "%s: one PSF for all rows (g1=%.4f, g2=%.4f, sigma=%.4f)",
        psf_path,
        values["psf_adamom_g1"],
        values["psf_adamom_g2"],
        values["psf_adamom_sigma"],
    )
    return GridPsf(single=single_psf_stamp(psf_path, size))


def check_request(request: MeasureRequest) -> None:
    """The arguments that apply to a grid image."""
    name = namer(request.names)
    for key, given in (
        ("cutout", request.cutout != MEASURE["cutout"].default),
        ("epochs", request.epochs),
    ):
        if given:
            raise ConfigError(
                f"{name(key)} applies to MEDS files only; {request.stamps_path} is an image of "
                "stamps"
            )


@dataclass
class GridInput:
    """The stamps of a grid image as its catalog (or the grid) gives them: the image, the stamp
    size, whether it is a star field, each row's stamp ``origins`` and 1-based ``positions``
    in the exposure, the catalog's columns, header, cards, HISTORY and carried HDUs, and the
    coordinate of the first pixel its ``x, y`` use."""

    info: ImageInfo
    size: int
    stars: bool
    origins: np.ndarray
    positions: np.ndarray
    table: Columns
    meta: dict[str, Any]
    cards: dict[str, Any]
    history: list[str] | None
    extra_hdus: dict[str, np.ndarray]
    xy_origin: int


def read_grid_input(request: MeasureRequest) -> GridInput:
    """The image, its stamp size and the rows to measure (a catalog's centres, else the grid),
    with every argument checked against them."""
    name = namer(request.names)
    stamps_path, catalog_path = request.stamps_path, request.catalog_path
    stamp_size, origin, stars = request.stamp_size, request.origin, request.stars
    psf_path, psf_model_path = request.psf_path, request.psf_model_path
    metacal = request.settings.metacal is not None
    if origin not in (0, 1):
        raise ConfigError(f"{name('origin')} must be 0 or 1, got {origin}")
    if metacal and psf_path is None and psf_model_path is None:
        raise ConfigError(
            f"{name('metacal')} needs {name('psf_path')} or {name('psf_model_path')}: the PSF to "
            "deconvolve each stamp by"
        )
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
    if stars and request.settings.feature_sets:
        raise ConfigError(
            f"{name(request.settings.feature_sets[0])} does not apply to a star field"
        )
    if psf_model_path is not None:
        cached_psf_model(psf_model_path)  # fail early on a file that is no PSF model
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
        table, meta = read_positions_catalog(catalog_path)
        check_belongs_together(stamps_path, info.header, catalog_path, meta)
        x, y = catalog_positions(table, catalog_path)
        check_spacing(x, y, size, catalog_path, name("stamp_size"))
        origins = catalog_origins(x, y, size, origin, name("origin"))
        if not inside(origins, size, info.shape).any():
            raise InputError(
                f"{catalog_path}: no stamp centre falls on {stamps_path} ({n_x}x{n_y} stamps of "
                f"{size} pixels; wrong {name('origin')} or {name('stamp_size')}?)"
            )
        positions = np.column_stack([x, y]) + (1 - origin)
        history = meta.get("HISTORY")
        if is_fits_file(catalog_path):  # carried with their comments, and the CONFIG HDU
            cards = read_cards(catalog_path)
            extra_hdus = read_carried_hdus(catalog_path)
        else:
            cards = {k: v for k, v in meta.items() if k not in ("HISTORY", "COMMENT")}
    else:
        origins = grid_origins(n_y, n_x, size)[: n_grid_stamps(info, n_y * n_x)]
        positions = stamp_centres(origins, size)
        table, meta = {"x": positions[:, 0].copy(), "y": positions[:, 1].copy()}, {}
        history = info.header.get("HISTORY")
        cards = read_cards(stamps_path, ext=info.ext)  # the image's provenance (seed, config)
    log.info("%s: %d stamps of %dx%d pixels", stamps_path, len(origins), size, size)
    header_gain = card_value(cards.get("GAIN", info.header.get("GAIN")))
    if request.settings.gain is None and header_gain is not None:
        log.warning(
            "the input header has GAIN=%s but no %s was given: snr uses Eq. 10 "
            "(sky-limited); pass %s %s for Eq. 8",
            header_gain,
            name("gain"),
            name("gain"),
            header_gain,
        )
    xy_origin = origin if catalog_path is not None else 1
    return GridInput(
        info, size, stars, origins, positions, table, meta, cards, history, extra_hdus, xy_origin
    )


def grid_psf(request: MeasureRequest, grid: GridInput) -> GridPsf | None:
    """The PSF of each row: a model at its position, a PSF image or grid, or none."""
    if request.psf_model_path is not None:  # each row's position in the exposure, 1-based
        path = request.psf_model_path
        psf = model_psf(path, grid.positions, grid.origins, grid.size, grid.info)
        grid.cards.update(cached_psf_model(path).header_cards())
        log.info("%s: the PSF model's PSF at each row's position", path)
        return psf
    if request.psf_path is None:
        return None
    psf = image_psf(request.psf_path, grid.info, grid.size, request.settings.engine)
    if request.settings.metacal is not None:
        check_metacal_psf(request.psf_path, grid.info, psf, grid.size, request.names)
    return psf


def fixnoise_keys(grid: GridInput) -> tuple[np.ndarray, np.ndarray | None]:
    """The key of each row's metacal fixnoise field: its realization in a common-random-number
    set (so that its cases share their fields), else the row; and its sign in a set of
    antithetic twins (``ANTITHET = T``: realizations ``2k, 2k+1`` share key ``k``, the second
    with the opposite field, as ``simulate --metacal`` makes them), else None."""
    crn = bool(card_value(grid.cards.get("CRN", False))) and "rea" in grid.table
    keys = np.asarray(grid.table["rea"], dtype=np.int64) if crn else np.arange(len(grid.origins))
    if not (bool(card_value(grid.cards.get("ANTITHET", False))) and "rea" in grid.table):
        return keys, None
    return twin_fixnoise(keys, np.asarray(grid.table["rea"]))


def measure_request(request: MeasureRequest) -> Measured:
    """Measure the stamps of a grid image (module docstring)."""
    grid = read_grid_input(request)
    psf = grid_psf(request, grid)
    keys, signs = fixnoise_keys(grid) if request.settings.metacal is not None else (None, None)
    feats = measure_grid(
        grid.info,
        grid.origins,
        grid.size,
        request.settings,
        psf=psf,
        fixnoise_keys=keys,
        fixnoise_signs=signs,
        nproc=request.nproc,
        scheduler=request.scheduler,
        progress=request.progress,
    )
    if grid.stars:
        return stars_catalog(request.stamps_path, grid, feats, request.settings.moments_retry)
    return features_catalog(request, grid, feats, psf is not None)


def features_catalog(
    request: MeasureRequest, grid: GridInput, feats: dict[str, np.ndarray], psf: bool
) -> Measured:
    """The catalog's columns with the features added (replacing any of the same name), and the
    cards of the measurement."""
    table, cards = grid.table, grid.cards
    new_cols = grid_columns(request.settings, psf)
    replaced = [c for c in new_cols if c in table]
    if replaced:
        log.warning("replacing existing column(s) %s", ", ".join(replaced))
        for c in replaced:
            del table[c]
    for c in new_cols:
        table[c] = feats[c]
    if is_celestial(grid.info.header):  # the world frame of each stamp, and its sky position
        sky = celestial_jacobians(grid.info.header, grid.positions[:, 0], grid.positions[:, 1])
        for c, values in sky.items():
            if c in JACOBIAN_COLUMNS or c not in table:
                table[c] = values
        log.info("%s: a celestial WCS: each stamp's Jacobian (world frame) added", grid.info.path)
    nflag = int((feats["flags"] != 0).sum())
    log.info("%d of %d stamps flagged (features NaN)", nflag, len(grid.origins))
    warn_if_mostly_flagged(feats["flags"], request.stamps_path, request.names)
    cards.update(
        {
            "STAMPSZ": (grid.size, "stamp size [pixels]"),
            "XYORIGIN": (grid.xy_origin, "coordinate of the first pixel in x, y"),
            **measure_cards(request.settings, grid.size),
        }
    )
    if "MEASURED" in cards:  # a simulation's card: the features are now measured
        cards["MEASURED"] = (True, "the catalog holds measured features")
    return Measured(table, cards, FORMAT, grid.history, grid.extra_hdus, grid.meta)


def stars_catalog(
    path: str, grid: GridInput, feats: dict[str, np.ndarray], moments_retry: float = 0.0
) -> Measured:
    """The star-by-star PSF features of a star field (format ``megalut.stars``), measured with
    the moments' damped retry ``moments_retry`` (0: none; its card when set)."""
    table, cards = grid.table, grid.cards
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
            "STAMPSZ": (grid.size, "stamp size [pixels]"),
            "XYORIGIN": (grid.xy_origin, "coordinate of the first pixel in x, y"),
            "NSTARS": (int(good.sum()), "stars measured"),
            **retry_cards(moments_retry),
        }
    )
    cards.pop("MEASURED", None)
    return Measured(table, cards, STARS_FORMAT, grid.history, grid.extra_hdus, grid.meta)


def any_file(path: str) -> bool:
    """The grid source takes any file no other source recognises."""
    return True


GRID_SOURCE = register_stamp_source(
    StampSourceType("grid", any_file, check_request, measure_request, fallback=True)
)
