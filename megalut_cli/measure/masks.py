"""Masked pixels of stamps (a bad-pixel mask, a weight map): what the moments leave out,
the sky MAD of the unmasked edge, the noise from the weights, and when a stamp is too
masked to be measured."""

from __future__ import annotations

import warnings

import numpy as np

from megalut_cli.measure.defaults import MAD_TO_SIGMA
from megalut_cli.measure.features import edge_pixels, sky_mad

#: A stamp with more than this fraction of its pixels masked is flagged MASKED_PIXELS.
MAX_MASKED_FRACTION = 0.25
#: A masked pixel closer than this (pixels) to the object's position in its stamp flags the
#: stamp MASKED_PIXELS: it takes a large share of the light that the moments weigh most.
CENTRAL_MASK_RADIUS = 2.0
#: Column of the number of masked pixels of each stamp.
MASKED_COLUMN = "n_masked"
#: Column of the noise from the weight map.
NOISE_COLUMN = "noise_weight"


def masked_pixels(
    weights: np.ndarray | None, bmasks: np.ndarray | None, shape: tuple[int, ...]
) -> np.ndarray:
    """Bad pixels: ``bmask != 0``, or a weight that is not positive (or not finite)."""
    masked = np.zeros(shape, dtype=bool)
    if bmasks is not None:
        masked |= np.asarray(bmasks) != 0
    if weights is not None:
        w = np.asarray(weights)
        masked |= ~(w > 0)  # NaN weights too
    return masked


def masked_sky_mad(stamps: np.ndarray, masked: np.ndarray) -> np.ndarray:
    """:func:`~megalut_cli.measure.features.sky_mad` of the edge pixels that are not masked
    (NaN where all are)."""
    if not edge_pixels(masked).any():
        return sky_mad(stamps)
    edges = edge_pixels(np.where(masked, np.nan, np.asarray(stamps, dtype=np.float64)))
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: NaN
        med = np.nanmedian(edges, axis=1, keepdims=True)
        return MAD_TO_SIGMA * np.nanmedian(np.abs(edges - med), axis=1)


def weight_noise(weights: np.ndarray, masked: np.ndarray) -> np.ndarray:
    """Per-stamp noise from a weight (inverse-variance) map: ``1 / sqrt(median w)`` over
    the pixels not masked with ``w > 0`` (NaN where none)."""
    w = np.where(masked | ~(weights > 0), np.nan, np.asarray(weights, dtype=np.float64))
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: NaN
        return 1.0 / np.sqrt(np.nanmedian(w.reshape(len(w), -1), axis=1))


def too_masked(masked: np.ndarray, centres: np.ndarray | None = None) -> np.ndarray:
    """Stamps whose measurement the mask makes unusable: more than
    :data:`MAX_MASKED_FRACTION` of the pixels masked, or a masked pixel within
    :data:`CENTRAL_MASK_RADIUS` of ``centres`` (``(n, 2)`` 0-based ``(col, row)`` of the object
    in its stamp; default the stamp centre)."""
    n, ny, nx = masked.shape
    if centres is None:
        centres = np.tile([(nx - 1) / 2.0, (ny - 1) / 2.0], (n, 1))
    centres = np.asarray(centres, dtype=np.float64).reshape(n, 2)
    frac = masked.reshape(n, -1).mean(axis=1) if n else np.zeros(0)
    yy, xx = np.mgrid[0:ny, 0:nx]
    near = (xx[None] - centres[:, 0, None, None]) ** 2 + (yy[None] - centres[:, 1, None, None]) ** 2
    central = (masked & (near <= CENTRAL_MASK_RADIUS**2)).any(axis=(1, 2))
    return (frac > MAX_MASKED_FRACTION) | central


def nan_flagged(columns: dict[str, np.ndarray], flags: np.ndarray, names: tuple[str, ...]) -> None:
    """Set ``names`` to NaN on the rows with ``flags != 0`` (in place)."""
    bad = flags != 0
    for c in names:
        if c in columns:
            columns[c][bad] = np.nan
