"""``megalut measure``: the features of every stamp of an input file.

:func:`measure_file_columns` finds the file's stamp source (:mod:`.sources`: a grid image
with an optional catalog of centres, :mod:`.grid`; a MEDS file, :mod:`.meds`), checks the
arguments, has the source measure its stamps (:mod:`.measurer`) and writes the catalog.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from megalut_cli.atomic import check_output
from megalut_cli.catalog import write_catalog
from megalut_cli.engine import DEFAULT_DEVICE, DEFAULT_ENGINE, resolve_device
from megalut_cli.errors import ConfigError, Names, namer
from megalut_cli.measure.defaults import FORMAT_VERSION
from megalut_cli.measure.grid import measure_grid
from megalut_cli.measure.measurer import MeasureSettings, MetacalSettings
from megalut_cli.measure.metacal_defaults import DEFAULT_TARGET
from megalut_cli.measure.options import MEASURE
from megalut_cli.measure.sources import (
    CellSettings,
    DetectSettings,
    MeasureRequest,
    stamp_source_for,
)
from megalut_cli.measure.stamps import grid_origins
from megalut_cli.progress import Progress

if TYPE_CHECKING:  # astropy.table costs ~0.4 s to import: only measure_file's Table needs it
    from astropy.table import Table

log = logging.getLogger(__name__)

#: Catalog columns in their order (name -> array), as :func:`measure_file_columns` handles them.
Columns = dict[str, np.ndarray]


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
    feature_sets: Sequence[str] = (),
) -> dict[str, np.ndarray]:
    """In memory: the features of the stamps of ``image`` (2-d array, axis 0 is y), the
    base set's columns and those of the optional ``feature_sets`` (``morphology`` is one) as
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
    sets = tuple(feature_sets) + (("morphology",) if morphology else ())
    settings = MeasureSettings(gain, engine, resolve_device(device), sets)
    return measure_grid(
        image, origins, stamp_size, settings, nproc=nproc, scheduler=scheduler, progress=progress
    )


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
    epochs: bool = MEASURE["epochs"].default,
    psf_model_path: str | os.PathLike | None = None,
    feature_sets: Sequence[str] = (),
    metacal_target: str = DEFAULT_TARGET,
    moments_retry: float = MEASURE["moments_retry"].default,
    metadetect: bool = MEASURE["metadetect"].default,
    detect: bool = MEASURE["detect"].default,
    detect_thresh: float = MEASURE["detect_thresh"].default,
    detect_minarea: int = MEASURE["detect_minarea"].default,
    deblend_nthresh: int = MEASURE["deblend_nthresh"].default,
    deblend_cont: float = MEASURE["deblend_cont"].default,
    no_clean: bool = MEASURE["no_clean"].default,
    mask_neighbours: bool = MEASURE["mask_neighbours"].default,
    mask_margin: float = MEASURE["mask_margin"].default,
    mask_fill: str = MEASURE["mask_fill"].default,
    duplicate_radius: float = MEASURE["duplicate_radius"].default,
    weight_path: str | os.PathLike | None = None,
    mask_path: str | os.PathLike | None = None,
    noise_path: str | os.PathLike | None = None,
    cell_size: int = MEASURE["cell_size"].default,
    cell_border: int = MEASURE["cell_border"].default,
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
        morphology: also measure the morphology set (``measure/morphology.py``), the same as
            ``feature_sets=("morphology",)``.
        device: ``cpu`` or ``gpu`` (resolved, :func:`megalut_cli.engine.resolve_device`): where
            the fast engine measures the moments.
        names: how messages name the arguments (e.g. ``{"stamp_size": "--stamp-size"}``).
        metacal: also the features of the five metacal versions of each stamp, ``X_<type>``
            (:mod:`.metacal`; needs ``psf_path``), and ``psf_adamom_*_<type>`` of the target
            PSF; header cards ``MCALSTEP``, ``MCALSEED``.
        metacal_step: the shear step of ``metacal``.
        seed: seed of the fixnoise fields of ``metacal``.
        cutout: MEDS input: the cutout index measured.
        epochs: MEDS input: every single-epoch cutout instead, one row per object and epoch
            (column ``cutout``).
        psf_model_path: a PSF model of the exposure the stamps are cut from (a PSFEx ``.psf``
            file or a Piff model, :mod:`.psf_model`; not with ``psf_path``): each row's PSF is
            the model's at its position (the catalog's ``x, y``, else the stamp centre), drawn
            in the exposure's pixels on a stamp like the galaxy's, for ``psf_adamom_*`` and
            ``metacal``; header cards ``PSFMODEL``, ``PSFMSHA``, ``PSFMTYPE``.
        feature_sets: the optional feature sets to measure too, by name
            (:mod:`megalut_cli.measure.feature_sets`).
        metacal_target: the target PSF of ``metacal`` by name
            (:mod:`megalut_cli.measure.metacal_targets`; header card ``MCALTARG`` when not
            the default round Gaussian).
        moments_retry: 0, or the step factor of the adaptive moments' damped retry on the
            stamps whose iteration fails (every stamp and metacal version; header card
            ``HSMRETRY``; :func:`megalut_cli.measure.adamom.adaptive_moments`).
        metadetect: ``stamps_path`` is a cells file (:mod:`.cells`, docs/metadetect.md):
            metacal on each whole cell, detection on each version, features of a stamp
            around each detection (``stamp_size``, default 48); format
            ``megalut.metadetect``, one row per detection per version.
        detect: like ``metadetect``, but detection on each cell itself, one row per
            detection (format ``megalut.features``); with ``metacal``, the metacal versions
            of each detection's stamp.
        detect_thresh, detect_minarea, deblend_nthresh, deblend_cont, no_clean: the
            detection of ``metadetect`` and ``detect`` (sep): threshold in noise sigmas, the
            fewest pixels, the deblending sub-thresholds and minimum contrast, sep's cleaning
            switched off.
        mask_neighbours: ``metadetect`` and ``detect``: the other detections' segments
            masked in each detection's stamp; ``mask_margin``: detections whose unsheared
            position lies that close to a masked pixel of the cell are flagged NEAR_MASK;
            ``mask_fill``: what the masked pixels hold ("interpolate" or "zero");
            ``duplicate_radius``: detections whose adaptive-moment centroids lie that close
            to another's of the same version are flagged DUPLICATE (one kept).
        weight_path, mask_path, noise_path, cell_size, cell_border: ``metadetect`` on one
            coadd image (:mod:`.coadd`): its inverse-variance map (required), mask bits and
            a noise realization (optional, for correlated noise), and the cells it is cut
            into: their side and the border outside each cell's inner region.

    Returns:
        The columns written (name -> array, in order) and the input catalog's header (empty
        in grid order); no astropy Table is made (see :func:`measure_file`).
    """
    name = namer(names)
    if psf_path is not None and psf_model_path is not None:
        raise ConfigError(
            f"{name('psf_path')} and {name('psf_model_path')} exclude each other: give one PSF"
        )
    if metacal and metadetect:
        raise ConfigError(
            f"{name('metacal')} (stamps) and {name('metadetect')} (cells) exclude each other"
        )
    if detect and metadetect:
        raise ConfigError(f"{name('detect')} and {name('metadetect')} exclude each other")
    sets = tuple(feature_sets) + (("morphology",) if morphology else ())
    settings = MeasureSettings(
        gain,
        engine,
        device,
        sets,
        MetacalSettings(float(metacal_step), int(seed), metacal_target)
        if metacal or metadetect
        else None,
        float(moments_retry),
        float(mask_margin),
    )
    detection = (
        DetectSettings(
            float(detect_thresh),
            int(detect_minarea),
            int(deblend_nthresh),
            float(deblend_cont),
            not no_clean,
            bool(mask_neighbours),
            float(mask_margin),
            str(mask_fill),
            float(duplicate_radius),
        )
        if metadetect or detect
        else None
    )
    cell_settings = CellSettings(
        *(None if p is None else str(p) for p in (weight_path, mask_path, noise_path)),
        int(cell_size),
        int(cell_border),
    )
    if not (metadetect or detect):
        given = [name(k) for k in cell_settings.given()]
        if given:
            raise ConfigError(f"{', '.join(given)}: for {name('metadetect')} on a coadd image only")
    request = MeasureRequest(
        str(stamps_path),
        None if catalog_path is None else str(catalog_path),
        str(output),
        settings,
        stamp_size,
        origin,
        None if psf_path is None else str(psf_path),
        None if psf_model_path is None else str(psf_model_path),
        stars,
        cutout,
        nproc,
        scheduler,
        progress,
        names,
        epochs,
        metadetect,
        detection,
        cell_settings,
        detect,
    )
    source = stamp_source_for(request.stamps_path, request)
    source.check(request)
    check_output(output, overwrite)
    if gain is not None and not (np.isfinite(gain) and gain > 0):
        raise ConfigError(f"{name('gain')} must be a positive number, got {gain}")
    if (metacal or metadetect) and not 0 < metacal_step <= MEASURE["metacal_step"].maximum:
        raise ConfigError(
            f"{name('metacal_step')} must be in (0, {MEASURE['metacal_step'].maximum}], got "
            f"{metacal_step}"
        )
    MEASURE["moments_retry"].check(moments_retry, name("moments_retry"))
    measured = source.measure(request)
    n_rows = len(measured.columns["flags"]) if "flags" in measured.columns else 0
    write_catalog(
        output,
        measured.columns,
        fmt=measured.fmt,
        fmt_version=FORMAT_VERSION,
        overwrite=overwrite,
        cards=measured.cards,
        history=measured.history,
        extra_hdus=measured.extra_hdus,
    )
    log.info("wrote %s (%d rows)", output, n_rows)
    return measured.columns, measured.meta


def measure_file(*args: Any, **kwargs: Any) -> Table:
    """:func:`measure_file_columns` (the same arguments), returning the table written as an
    astropy Table whose ``meta`` is the input catalog's header."""
    from astropy.table import Table

    columns, meta = measure_file_columns(*args, **kwargs)
    table = Table(columns, copy=False)
    table.meta.update(meta)
    return table
