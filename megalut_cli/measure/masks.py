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
#: Largest region of connected masked pixels :func:`inpainted` interpolates (larger: 0).
MAX_INTERPOLATED_REGION = 4096
#: Column of a detection's distance to the nearest masked pixel of its cell (metadetection).
MASK_DISTANCE_COLUMN = "mask_dist"
#: Stamps per pass of :func:`_nearest_masked_squared`.
_CHUNK = 256


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
    with np.errstate(all="ignore"):
        med = nanmedian_rows(edges)
        return MAD_TO_SIGMA * nanmedian_rows(np.abs(edges - med[:, None]))


def nanmedian_rows(values: np.ndarray) -> np.ndarray:
    """``np.nanmedian(values, axis=1)`` bit for bit (NaN for an all-NaN row, no warning),
    4x faster on rows of a stamp's edge: NumPy takes its masked-array path below 600."""
    ordered = np.sort(values, axis=1)  # NaN last
    n = np.count_nonzero(~np.isnan(values), axis=1)
    half = n // 2
    rows = np.arange(len(ordered))
    low = ordered[rows, np.maximum(half - 1 + n % 2, 0)]  # the middle one or two
    high = ordered[rows, np.minimum(half, ordered.shape[1] - 1)]
    with np.errstate(invalid="ignore"):  # inf - inf: NaN, as NumPy's
        median = (low + high) / 2.0
    median[n == 0] = np.nan
    return median


def weight_noise(weights: np.ndarray, masked: np.ndarray) -> np.ndarray:
    """Per-stamp noise from a weight (inverse-variance) map: ``1 / sqrt(median w)`` over
    the pixels not masked with ``w > 0`` (NaN where none)."""
    w = np.where(masked | ~(weights > 0), np.nan, np.asarray(weights, dtype=np.float64))
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: NaN
        return 1.0 / np.sqrt(np.nanmedian(w.reshape(len(w), -1), axis=1))


def too_masked(
    masked: np.ndarray, centres: np.ndarray | None = None, distance: np.ndarray | None = None
) -> np.ndarray:
    """Stamps whose measurement the mask makes unusable: more than
    :data:`MAX_MASKED_FRACTION` of the pixels masked, or a masked pixel within
    :data:`CENTRAL_MASK_RADIUS` of ``centres`` (``(n, 2)`` 0-based ``(col, row)`` of the object
    in its stamp; default the stamp centre); ``distance``: :func:`stamp_mask_distance`, when
    known."""
    n = len(masked)
    frac = masked.reshape(n, -1).mean(axis=1) if n else np.zeros(0)
    if distance is None:
        central = _nearest_masked_squared(masked, centres) <= CENTRAL_MASK_RADIUS**2
    else:
        central = distance <= CENTRAL_MASK_RADIUS
    return (frac > MAX_MASKED_FRACTION) | central


def stamp_mask_distance(masked: np.ndarray, centres: np.ndarray | None = None) -> np.ndarray:
    """The distance (pixels) from each object's position in its stamp (``centres``, ``(n,
    2)`` 0-based ``(col, row)``; default the stamp centre) to the stamp's nearest masked
    pixel (inf where none)."""
    return np.sqrt(_nearest_masked_squared(masked, centres))


def _nearest_masked_squared(masked: np.ndarray, centres: np.ndarray | None) -> np.ndarray:
    """The squared distance from each stamp's ``centres`` (default its centre) to its nearest
    masked pixel (inf where none)."""
    n, ny, nx = masked.shape
    if centres is None:
        centres = np.tile([(nx - 1) / 2.0, (ny - 1) / 2.0], (n, 1))
    centres = np.asarray(centres, dtype=np.float64).reshape(n, 2)
    out = np.full(n, np.inf)
    some = np.flatnonzero(masked.reshape(n, -1).any(axis=1))
    for start in range(0, len(some), _CHUNK):  # (chunk, ny, nx) float64 at a time
        idx = some[start : start + _CHUNK]
        dx2 = (np.arange(nx)[None, :] - centres[idx, :1]) ** 2
        dy2 = (np.arange(ny)[None, :] - centres[idx, 1:]) ** 2
        squared = dx2[:, None, :] + dy2[:, :, None]
        out[idx] = np.where(masked[idx], squared, np.inf).min(axis=(1, 2))
    return out


def nan_flagged(columns: dict[str, np.ndarray], flags: np.ndarray, names: tuple[str, ...]) -> None:
    """Set ``names`` to NaN on the rows with ``flags != 0`` (in place)."""
    bad = flags != 0
    for c in names:
        if c in columns:
            columns[c][bad] = np.nan


def filled_stamps(stamps: np.ndarray, masked: np.ndarray) -> np.ndarray:
    """``stamps`` (n, S, S) with their ``masked`` pixels filled by :func:`inpainted` (the
    stamps without masked pixels as they are)."""
    out = np.array(stamps, dtype=np.float64)
    for i in np.flatnonzero(masked.reshape(len(masked), -1).any(axis=1)):
        out[i] = inpainted(out[i], masked[i])
    return out


def mask_distance_map(bad: np.ndarray) -> np.ndarray | None:
    """Each pixel's distance (pixels, centre to centre) to the image's nearest ``bad``
    pixel; None when it has none."""
    if not bad.any():
        return None
    from scipy import ndimage  # SciPy: cells with masked pixels only

    return ndimage.distance_transform_edt(~bad)


def mask_distance(
    bad: np.ndarray, x: np.ndarray, y: np.ndarray, distance: np.ndarray | None = None
) -> np.ndarray:
    """The distance (pixels) from the 0-based positions ``x, y`` of an image to its nearest
    ``bad`` pixel (centre to centre, from the pixel holding the position; inf when the image
    has none); ``distance``: :func:`mask_distance_map` of ``bad``, when known."""
    if distance is None:
        distance = mask_distance_map(bad)
    if distance is None:
        return np.full(len(x), np.inf)
    ny, nx = bad.shape
    col = np.clip(np.floor(np.asarray(x) + 0.5).astype(np.int64), 0, nx - 1)
    row = np.clip(np.floor(np.asarray(y) + 0.5).astype(np.int64), 0, ny - 1)
    return distance[row, col]


def inpainted(image: np.ndarray, bad: np.ndarray) -> np.ndarray:
    """``image`` with its ``bad`` pixels replaced by the harmonic interpolation of the good
    ones: each bad pixel the mean of its neighbours in the image (Laplace's equation, the
    good pixels its boundary). A region of bad pixels larger than
    :data:`MAX_INTERPOLATED_REGION` pixels (the part of a coadd's edge cell off the image),
    or touching no good pixel, is 0."""
    out = np.where(bad, 0.0, np.asarray(image, dtype=np.float64))
    if not bad.any():
        return out
    from scipy import ndimage, sparse  # SciPy: cells with masked pixels only
    from scipy.sparse.linalg import spsolve

    labels, n_regions = ndimage.label(bad)  # 4-connected regions
    small = np.bincount(labels.ravel()) <= MAX_INTERPOLATED_REGION
    small[0] = False
    bad = small[labels]
    if not bad.any():
        return out
    ny, nx = bad.shape
    bordered = np.zeros(n_regions + 1, dtype=bool)
    rows, cols = np.nonzero(bad)
    n = len(rows)
    index = np.full(bad.shape, -1, dtype=np.int64)
    index[rows, cols] = np.arange(n)
    diagonal, rhs = np.zeros(n), np.zeros(n)
    at_row, at_col, values = [], [], []
    for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        r, c = rows + dr, cols + dc
        k = np.flatnonzero((r >= 0) & (r < ny) & (c >= 0) & (c < nx))
        diagonal[k] += 1.0
        neighbour = index[r[k], c[k]]
        unknown = neighbour >= 0
        at_row.append(k[unknown])
        at_col.append(neighbour[unknown])
        values.append(np.full(int(unknown.sum()), -1.0))
        good = k[~unknown]
        rhs[good] += out[r[good], c[good]]
        bordered[labels[rows[good], cols[good]]] = True
    alone = ~bordered[labels[rows, cols]]  # a region with no good neighbour: 0
    keep = [~alone[r_] for r_ in at_row]
    diagonal[alone] = 1.0
    matrix = sparse.csr_matrix(
        (
            np.concatenate([diagonal, *(v[m] for v, m in zip(values, keep))]),
            (
                np.concatenate([np.arange(n), *(a[m] for a, m in zip(at_row, keep))]),
                np.concatenate([np.arange(n), *(a[m] for a, m in zip(at_col, keep))]),
            ),
        ),
        shape=(n, n),
    )
    out[rows, cols] = spsolve(matrix, np.where(alone, 0.0, rhs))
    return out
