"""The metadetect catalog of the cell sources (:mod:`.cells`, :mod:`.coadd`): the inner
region, the columns' order of the contract (docs/metadetect.md), the header cards and the
log of the detections.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import numpy as np

from megalut_cli.measure.defaults import FORMAT as FEATURES_FORMAT
from megalut_cli.measure.defaults import MDET_FORMAT, PSF_COLUMNS
from megalut_cli.measure.features import warn_if_mostly_flagged
from megalut_cli.measure.measurer import measure_cards
from megalut_cli.measure.metacal_defaults import (
    MDET_COLUMN,
    MDET_STEP_CARD,
    SEED_CARD,
    TARGET_CARD,
    TYPES,
)
from megalut_cli.measure.source_registry import MeasureRequest

log = logging.getLogger(__name__)


#: Header card: the fixnoise of a metadetect catalog, coloured by a noise image's
#: correlation (``NOISE``) or white noise of the weight map (``white``).
FIXNOISE_CARD = "MDETFIX"


FIXNOISE_TEXT = "fixnoise colour: the NOISE image's, or white from WGT"


def inner_region(x: np.ndarray, y: np.ndarray, size: int, border: int) -> np.ndarray:
    """Whether the 1-based cell positions ``x, y`` lie in the inner region of a cell of
    ``size`` pixels: ``border < x - 0.5 <= size - border``, likewise ``y`` (half-open, so
    that the inner regions of cells ``size - 2 border`` apart tile a plane)."""
    lo, hi = border + 0.5, size - border + 0.5
    return (x > lo) & (x <= hi) & (y > lo) & (y <= hi)


def ordered_features(merged: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The measured columns in the contract's order: the features, the PSF's, ``flags``, then
    the metacal versions' of ``--detect --metacal``."""
    versioned = tuple(f"_{kind}" for kind in TYPES)
    own = [c for c in merged if not c.endswith(versioned)]
    first = [c for c in own if c not in PSF_COLUMNS and c != "flags"]
    order = [*first, *(c for c in PSF_COLUMNS if c in merged), "flags"]
    return {c: merged[c] for c in (*order, *(c for c in merged if c not in order))}


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
        "MASKMRGN": (float(detection.mask_margin), "NEAR_MASK within this of a masked pixel [px]"),
        "MASKFILL": (detection.mask_fill, "what the masked pixels hold (measure --mask-fill)"),
        "DUPRAD": (float(detection.duplicate_radius), "DUPLICATE within this of a centroid [px]"),
        "DETECTOR": ("sep", "detection code (Source Extractor as a library)"),
    }
