"""One PSF image for every row (``measure --psf`` given a single PSF stamp or a star grid):
its stamp, checked, and its features; for images of stamps and MEDS files alike."""

from __future__ import annotations

import logging

import numpy as np

from megalut_cli import flags as fl
from megalut_cli.engine import DEFAULT_ENGINE
from megalut_cli.errors import InputError
from megalut_cli.measure.defaults import PSF_COLUMNS
from megalut_cli.measure.features import measure_stamps
from megalut_cli.measure.stamps import image_info, read_rows, stamp_size_of

log = logging.getLogger(__name__)


def single_psf_stamp(path: str, size_hint: int) -> np.ndarray:
    """The PSF stamp of a one-PSF image (the whole square image, or the first stamp of a
    grid of ``STAMPSZ`` (else ``size_hint``) pixel stamps), checked: finite, not empty."""
    info = image_info(path)
    ny, nx = info.shape
    card = info.header.get("STAMPSZ")
    size = stamp_size_of(info, None) if card is not None else size_hint
    if ny % size == 0 and nx % size == 0 and (ny, nx) != (size, size):
        log.info(
            "%s: a %dx%d grid of PSF stamps: using the first (lower-left) one",
            path,
            nx // size,
            ny // size,
        )
        stamp = read_rows(info, 0, size)[:, :size]
    elif ny == nx:
        stamp = read_rows(info, 0, ny)
    else:
        raise InputError(
            f"{path}: a {nx}x{ny} PSF image is neither square, a grid of {size}-pixel stamps, "
            "nor a grid like the galaxy image"
        )
    if not np.all(np.isfinite(stamp)):
        raise InputError(f"{path}: the PSF stamp has NaN or infinite pixels")
    if not stamp.sum() > 0:
        raise InputError(f"{path}: the PSF stamp is empty (no star)")
    return np.asarray(stamp, dtype=np.float64)


def single_psf_features(
    path: str, size_hint: int, engine: str = DEFAULT_ENGINE
) -> dict[str, float]:
    """``psf_adamom_g1, psf_adamom_g2, psf_adamom_sigma, psf_adamom_rho4`` of a one-PSF image
    (:func:`single_psf_stamp`); an unmeasurable PSF is an InputError."""
    res = measure_stamps(single_psf_stamp(path, size_hint)[None], engine=engine)
    if res["flags"][0]:
        why = ", ".join(fl.explain(res["flags"][0]))
        raise InputError(f"{path}: the PSF stamp could not be measured ({why})")
    return {p: float(res[p[len("psf_") :]][0]) for p in PSF_COLUMNS}
