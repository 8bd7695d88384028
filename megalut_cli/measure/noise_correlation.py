"""The correlation of a cell's noise, from a noise image, and its power spectrum: what the
moving fixnoise of correlated noise is coloured by (docs/metadetect.md, "A noise image").
"""

from __future__ import annotations

import math

import numpy as np
import scipy.fft

#: Lags (pixels, each axis) of the estimated correlation: kept whole up to
#: :data:`FLAT_LAG`, tapered by a half cosine to zero at :data:`MAX_LAG`.
FLAT_LAG = 8
MAX_LAG = 16


def lag_window(flat: int = FLAT_LAG, largest: int = MAX_LAG) -> np.ndarray:
    """The window of the lags ``-largest..largest`` (each axis; the product of the two):
    1 up to ``flat``, a half cosine down to 0 at ``largest``."""
    lag = np.abs(np.arange(-largest, largest + 1), dtype=np.float64)
    taper = np.clip((lag - flat) / (largest - flat), 0.0, 1.0)
    w = 0.5 * (1.0 + np.cos(math.pi * taper))
    return np.multiply.outer(w, w)


def noise_correlation(
    field: np.ndarray, bad: np.ndarray | None = None, largest: int = MAX_LAG
) -> np.ndarray:
    """The correlation function of the noise ``field`` (2-D, its good pixels, mean not
    removed: noise is zero-mean) at the lags ``-largest..largest`` in ``(y, x)``, lag 0 at
    the centre: each lag's mean product over the pairs of good pixels, times
    :func:`lag_window`."""
    field = np.asarray(field, dtype=np.float64)
    good = np.ones(field.shape) if bad is None else (~np.asarray(bad, bool)).astype(np.float64)
    ny, nx = field.shape
    shape = (scipy.fft.next_fast_len(ny + largest), scipy.fft.next_fast_len(nx + largest))

    def auto(values: np.ndarray) -> np.ndarray:
        spec = scipy.fft.rfft2(values, s=shape)
        full = scipy.fft.irfft2(spec * spec.conj(), s=shape)
        return np.roll(full, (largest, largest), axis=(0, 1))[: 2 * largest + 1, : 2 * largest + 1]

    pairs = auto(good)
    if pairs[largest, largest] < 1.0:
        raise ValueError("the noise image has no good pixel")
    products = auto(field * good)
    return np.where(pairs > 0.5, products / np.maximum(pairs, 1.0), 0.0) * lag_window(
        FLAT_LAG * largest // MAX_LAG, largest
    )


def spectrum_on_grid(correlation: np.ndarray, grid: int) -> np.ndarray:
    """The power spectrum of ``correlation`` (odd square, lag 0 at its centre) on the
    ``fft2`` frequencies of a ``grid`` x ``grid`` plane (real, the whole plane)."""
    n = correlation.shape[0]
    if n > grid:
        raise ValueError(f"a correlation of {n} lags does not fit a grid of {grid}")
    half = n // 2
    plane = np.zeros((grid, grid))
    plane[:n, :n] = correlation
    plane = np.roll(plane, (-half, -half), axis=(0, 1))
    return scipy.fft.fft2(plane).real


def spectrum_at(correlation: np.ndarray, kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
    """The power spectrum of ``correlation`` at the frequencies ``(kx, ky)`` (radians per
    pixel, any shape): the cosine sum over its lags."""
    n = correlation.shape[0]
    lags = np.arange(n) - n // 2
    kx, ky = np.asarray(kx, np.float64), np.asarray(ky, np.float64)
    phase_x = np.exp(1j * np.multiply.outer(kx, lags))  # (..., lx)
    phase_y = np.exp(1j * np.multiply.outer(ky, lags))  # (..., ly)
    rows = phase_y @ correlation  # sum over ly: (..., lx)
    return np.einsum("...j,...j->...", rows, phase_x).real
