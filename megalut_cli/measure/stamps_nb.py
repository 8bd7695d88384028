"""Compiled kernels of :mod:`.stamps`: cutting a stack of stamps out of a band of image rows
in one call, with each stamp's pixel checks, and (:func:`cut_measure_stack`) measuring each
stamp's adaptive moments as it is cut (the Python API is
:func:`megalut_cli.measure.stamps.cut_stamps_checked` and
:func:`megalut_cli.measure.stamps.cut_and_measure`).

The edge statistic is ``numpy.median``'s arithmetic exactly: the mean ``(a + b) / 2`` of the
two middle order statistics of the ``4 S - 4`` edge pixels (an even count), then the same of
the absolute deviations from it; a NaN among the edges or among the deviations gives NaN.
"""

from __future__ import annotations

import math

import numpy as np
from numba import types
from numba.extending import overload

from megalut_cli.jit import njit, prefetch
from megalut_cli.measure.adamom_nb import measure_into, moments_workspace

#: Bytes of a cache line, for :func:`_prefetch_stamp`.
LINE_BYTES = 64


def pixel_value(row: np.ndarray, x: int) -> float:
    """Pixel ``x`` of an image row as float64: a float row's value, or the float32 (uint32
    row) or float64 (uint64 row) whose big-endian bytes (FITS's) the row holds."""
    value = row[x]
    if row.dtype == np.uint32:
        return float(value.byteswap().view(np.float32))
    if row.dtype == np.uint64:
        return float(value.byteswap().view(np.float64))
    return float(value)


@njit(cache=True, inline="always")
def _byteswap32(u: np.uint64) -> np.uint32:
    """The 4 low bytes of ``u`` in reverse order."""
    return np.uint32(
        ((u & 0xFF) << 24) | ((u & 0xFF00) << 8) | ((u >> 8) & 0xFF00) | ((u >> 24) & 0xFF)
    )


@overload(pixel_value)
def _pixel_value_compiled(row, x):  # type: ignore[no-untyped-def]  # noqa: ANN001, ANN202
    """The compiled :func:`pixel_value`, chosen by the row's type."""
    if row.dtype == types.uint32:

        def big_endian_float32(row, x):  # type: ignore[no-untyped-def]
            return np.float64(_byteswap32(np.uint64(row[x])).view(np.float32))

        return big_endian_float32
    if row.dtype == types.uint64:

        def big_endian_float64(row, x):  # type: ignore[no-untyped-def]
            u = np.uint64(row[x])
            low = np.uint64(_byteswap32(u & np.uint64(0xFFFFFFFF)))
            high = np.uint64(_byteswap32(u >> np.uint64(32)))
            return np.float64(np.uint64((low << np.uint64(32)) | high).view(np.float64))

        return big_endian_float64
    if isinstance(row.dtype, types.Float):
        return lambda row, x: np.float64(row[x])
    return None


@njit(cache=True, error_model="numpy")
def _select(a: np.ndarray, k: int) -> None:
    """Rearrange ``a`` (no NaN) so that ``a[k]`` is its ``k``-th smallest value and the values
    before it are the ``k`` smallest (quickselect).

    Each round splits ``a[lo..hi]`` around a median-of-three pivot ``p`` into the values
    below ``p``, those equal to it and those above, with branch-free Lomuto passes (a swap
    per value and a counter moved by the comparison): on the 252 edge values of a 64-pixel
    stamp, a third of the time of Hoare's passes, whose branches the noise makes
    unpredictable. Only the order of the values differs; the order statistics are the same.
    """
    lo = 0
    hi = a.shape[0] - 1
    while hi > lo:
        x, y, z = a[lo], a[(lo + hi) >> 1], a[hi]
        if x < y:
            p = y if y < z else (z if x < z else x)
        else:
            p = x if x < z else (z if y < z else y)
        below = lo  # a[lo:below] < p
        for i in range(lo, hi + 1):
            v = a[i]
            a[i] = a[below]
            a[below] = v
            below += v < p
        if k < below:
            hi = below - 1
            continue
        equal = below  # a[below:equal] == p (p is one of the values: equal > below)
        for i in range(below, hi + 1):
            v = a[i]
            a[i] = a[equal]
            a[equal] = v
            equal += v <= p
        if k < equal:
            return
        lo = equal


@njit(cache=True, error_model="numpy")
def _median_even(a: np.ndarray) -> float:
    """``numpy.median`` of ``a`` (an even count, no NaN; ``a`` is reordered)."""
    h = a.shape[0] // 2
    _select(a, h)
    low = a[0]
    for i in range(1, h):
        if a[i] > low:
            low = a[i]
    return (low + a[h]) / 2.0


@njit(cache=True, error_model="numpy")
def _edge_mad(stamp: np.ndarray, edges: np.ndarray, work: np.ndarray) -> float:
    """``median(|e - median(e)|)`` of the edge pixels ``e`` of ``stamp`` (NaN if a NaN enters)."""
    s = stamp.shape[0]
    j = 0
    for x in range(s):
        edges[j] = stamp[0, x]
        edges[j + s] = stamp[s - 1, x]
        j += 1
    j = 2 * s
    for y in range(1, s - 1):
        edges[j] = stamp[y, 0]
        edges[j + s - 2] = stamp[y, s - 1]
        j += 1
    for i in range(edges.shape[0]):
        if math.isnan(edges[i]):
            return np.nan
        work[i] = edges[i]
    centre = _median_even(work)
    for i in range(edges.shape[0]):
        d = abs(edges[i] - centre)
        if math.isnan(d):
            return np.nan
        work[i] = d
    return _median_even(work)


@njit(cache=True, error_model="numpy", fastmath={"reassoc"})
def _cut_one(rows: np.ndarray, y0: int, x0: int, stamp: np.ndarray) -> bool:
    """Copy the stamp at 0-based ``(x0, y0)`` of ``rows`` into ``stamp`` (float64); whether
    all its pixels are finite (``v * 0`` is 0 for a finite ``v``, NaN otherwise: no branch,
    so the copy vectorises)."""
    s = stamp.shape[0]
    bad = 0.0
    for y in range(s):
        src = rows[y0 + y]
        dst = stamp[y]
        for x in range(s):
            v = pixel_value(src, x0 + x)
            dst[x] = v
            bad += v * 0.0
    return bad == 0.0


@njit(cache=True, error_model="numpy")
def _prefetch_stamp(rows: np.ndarray, row0: int, origins: np.ndarray, k: int, s: int) -> None:
    """Prefetch the cache lines of stamp ``k`` (if any) of ``origins`` (as in :func:`cut_stack`)
    in ``rows``: a stamp's rows are far apart in the image, too far for the CPU's own
    prefetching to follow."""
    if k >= origins.shape[0]:
        return
    y0 = origins[k, 1] - 1 - row0
    x0 = origins[k, 0] - 1
    step = max(1, LINE_BYTES // rows.itemsize)
    for y in range(y0, y0 + s):
        for x in range(x0, x0 + s, step):
            prefetch(rows, y, x)
        prefetch(rows, y, x0 + s - 1)


@njit(cache=True, error_model="numpy", nogil=True)
def cut_stack(
    rows: np.ndarray,
    row0: int,
    origins: np.ndarray,
    out: np.ndarray,
    finite: np.ndarray,
    mad: np.ndarray,
    checks: bool,
) -> None:
    """Copy the stamps whose 1-based lower-left pixels are ``origins`` (``(n, 2)``, ``x, y``) out
    of ``rows`` (image rows from the 0-based ``row0``) into ``out`` (``(n, S, S)`` float64).
    With ``checks``, ``finite[k]`` says whether every pixel of stamp ``k`` is finite and
    ``mad[k]`` is the median absolute deviation of its edge pixels (not rescaled)."""
    s = out.shape[1]
    edges = np.empty(4 * s - 4)
    work = np.empty(4 * s - 4)
    for k in range(out.shape[0]):
        _prefetch_stamp(rows, row0, origins, k + 1, s)
        ok = _cut_one(rows, origins[k, 1] - 1 - row0, origins[k, 0] - 1, out[k])
        if checks:
            finite[k] = ok
            mad[k] = _edge_mad(out[k], edges, work)


@njit(cache=True, error_model="numpy", nogil=True)
def cut_measure_stack(
    rows: np.ndarray,
    row0: int,
    origins: np.ndarray,
    stamp_size: int,
    guess_sigma: np.ndarray,
    settings: tuple,
    finite: np.ndarray,
    mad: np.ndarray,
    status: np.ndarray,
    n_iter: np.ndarray,
    results: np.ndarray,
) -> None:
    """:func:`cut_stack` with checks, then :func:`adaptive_moments_stack`'s moments of each
    finite stamp, one stamp at a time: each stamp is cut into one float64 buffer that stays
    in the core's cache while it is measured, instead of a stack of them written to memory
    and read back. The same functions on the same float64 stamp: the same bits."""
    s = stamp_size
    stamp = np.empty((s, s))
    edges = np.empty(4 * s - 4)
    work = np.empty(4 * s - 4)
    moments_work = moments_workspace(s, s)
    for k in range(origins.shape[0]):
        _prefetch_stamp(rows, row0, origins, k + 1, s)  # brought in while stamp k is measured
        finite[k] = _cut_one(rows, origins[k, 1] - 1 - row0, origins[k, 0] - 1, stamp)
        mad[k] = _edge_mad(stamp, edges, work)
        if finite[k]:
            measure_into(stamp, k, guess_sigma, settings, moments_work, status, n_iter, results)
