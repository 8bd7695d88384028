"""Per-stamp Gaussian noise for the fast engine, compiled: one generator per seed, no objects.

Each stamp's standard normals come from its own integer seed only: xoshiro256** (Blackman
and Vigna 2018) with its state seeded by SplitMix64 from the seed, as its authors
recommend, and the ziggurat method with 256 layers (Marsaglia and Tsang 2000, in Doornik's
2005 ZIGNOR form: one 64-bit draw gives the layer and a 53-bit uniform). Hand-written
because numpy's generators cost ~30 us to construct per seed, more than the 4096 normals
of a 64 x 64 stamp take to draw here; the statistics are tested in ``tests/test_sim_normals.py``.

This module is the Python API; the compiled generator and draws are in :mod:`.normals_nb`.
"""

from __future__ import annotations

import math

import numpy as np

from megalut_cli.errors import MegalutError
from megalut_cli.sim.normals_nb import fill_normals

#: Ziggurat layers and the base strip's right edge r and area v (Marsaglia and Tsang 2000).
ZIGGURAT_LAYERS = 256
_R = 3.6541528853610088
_V = 0.00492867323399


def ziggurat_table() -> np.ndarray:
    """Layer edges x[0..256]: x[0] = v / f(r) (the base strip), x[1] = r, ..., x[256] = 0."""
    x = np.empty(ZIGGURAT_LAYERS + 1)
    x[0] = _V / math.exp(-0.5 * _R * _R)
    x[1] = _R
    for i in range(1, ZIGGURAT_LAYERS - 1):
        x[i + 1] = math.sqrt(-2.0 * math.log(_V / x[i] + math.exp(-0.5 * x[i] * x[i])))
    x[ZIGGURAT_LAYERS] = 0.0
    return x


_X = ziggurat_table()
_RATIO = _X[1:] / _X[:-1]  # accept u * x[i] at once where |u| < x[i+1] / x[i]

_CHUNK = 64  # stamps of normals drawn at once by add_gaussian_noise


def standard_normals(seeds: np.ndarray, size: int) -> np.ndarray:
    """``(len(seeds), size)`` standard normals (float64); row ``k`` depends on ``seeds[k]`` only."""
    seeds = np.atleast_1d(np.asarray(seeds)).astype(np.uint64)
    out = np.empty((len(seeds), int(size)))
    fill_normals(out, seeds, _X, _RATIO)
    return out


def add_gaussian_noise(
    stamps: np.ndarray, seeds: np.ndarray, sigma: float, signs: np.ndarray | None = None
) -> None:
    """Add ``sigma`` times :func:`standard_normals` (in float32) to the float32 ``stamps``
    ``(n, ...)`` in place, stamp ``k``'s from ``seeds[k]`` (times ``signs[k]``, +1 or -1:
    antithetic twins)."""
    seeds = np.atleast_1d(np.asarray(seeds)).astype(np.uint64)
    if len(seeds) != len(stamps):
        raise MegalutError(f"add_gaussian_noise: {len(seeds)} seeds for {len(stamps)} stamps")
    size = int(np.prod(stamps.shape[1:], dtype=np.int64))
    for a in range(0, len(stamps), _CHUNK):
        block = stamps[a : a + _CHUNK]
        scale: np.ndarray | np.float32 = np.float32(sigma)
        if signs is not None:
            scale = (np.float32(sigma) * np.asarray(signs[a : a + _CHUNK], np.float32))[:, None]
        block += (scale * standard_normals(seeds[a : a + _CHUNK], size).astype(np.float32)).reshape(
            block.shape
        )
