"""Per-stamp Gaussian noise for the fast engine, compiled: one generator per seed, no objects.

Each stamp's standard normals come from its own integer seed only: xoshiro256** (Blackman
and Vigna 2018) with its state seeded by SplitMix64 from the seed, as its authors
recommend, and the ziggurat method with 256 layers (Marsaglia and Tsang 2000, in Doornik's
2005 ZIGNOR form: one 64-bit draw gives the layer and a 53-bit uniform). Hand-written
because numpy's generators cost ~30 us to construct per seed, more than the 4096 normals
of a 64 x 64 stamp take to draw here; the statistics are tested in ``tests/test_sim_normals.py``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from megalut_cli.errors import MegalutError

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

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_U53 = 1.0 / 9007199254740992.0  # 2^-53
_CHUNK = 64  # stamps of normals drawn at once by add_gaussian_noise


@njit(cache=True)
def _splitmix(state: np.uint64) -> tuple[np.uint64, np.uint64]:
    """SplitMix64: (next state, output)."""
    state = state + _GOLDEN
    z = state
    z = (z ^ (z >> np.uint64(30))) * _M1
    z = (z ^ (z >> np.uint64(27))) * _M2
    return state, z ^ (z >> np.uint64(31))


@njit(cache=True)
def _rotl(x: np.uint64, k: int) -> np.uint64:
    return (x << np.uint64(k)) | (x >> np.uint64(64 - k))


@njit(cache=True)
def _seed_state(seed: np.uint64) -> tuple[np.uint64, np.uint64, np.uint64, np.uint64]:
    """xoshiro256** state from ``seed`` by SplitMix64."""
    st, s0 = _splitmix(seed)
    st, s1 = _splitmix(st)
    st, s2 = _splitmix(st)
    st, s3 = _splitmix(st)
    return s0, s1, s2, s3


@njit(cache=True)
def _next(
    s0: np.uint64, s1: np.uint64, s2: np.uint64, s3: np.uint64
) -> tuple[np.uint64, np.uint64, np.uint64, np.uint64, np.uint64]:
    """xoshiro256**: (output, next state)."""
    result = _rotl(s1 * np.uint64(5), 7) * np.uint64(9)
    t = s1 << np.uint64(17)
    s2 ^= s0
    s3 ^= s1
    s1 ^= s2
    s0 ^= s3
    s2 ^= t
    s3 = _rotl(s3, 45)
    return result, s0, s1, s2, s3


@njit(cache=True)
def _uniform(
    s0: np.uint64, s1: np.uint64, s2: np.uint64, s3: np.uint64
) -> tuple[float, np.uint64, np.uint64, np.uint64, np.uint64]:
    """Uniform in (0, 1], and the next state."""
    r, s0, s1, s2, s3 = _next(s0, s1, s2, s3)
    return (np.int64(r >> np.uint64(11)) + 1) * _U53, s0, s1, s2, s3


@njit(cache=True)
def _wedge_or_tail(
    s0: np.uint64, s1: np.uint64, s2: np.uint64, s3: np.uint64, x: np.ndarray, layer: int, u: float
) -> tuple[float, np.uint64, np.uint64, np.uint64, np.uint64]:
    """ZIGNOR's rare branches: the tail beyond r (layer 0, Marsaglia 1964) or the wedge of
    ``layer`` at ``u``; NaN when rejected (draw again). Returns the next state too."""
    if layer == 0:
        while True:
            u1, s0, s1, s2, s3 = _uniform(s0, s1, s2, s3)
            u2, s0, s1, s2, s3 = _uniform(s0, s1, s2, s3)
            xt = -math.log(u1) / x[1]
            yt = -math.log(u2)
            if yt + yt > xt * xt:
                return (x[1] + xt if u > 0 else -x[1] - xt), s0, s1, s2, s3
    xu = u * x[layer]
    f0 = math.exp(-0.5 * (x[layer] * x[layer] - xu * xu))
    f1 = math.exp(-0.5 * (x[layer + 1] * x[layer + 1] - xu * xu))
    u1, s0, s1, s2, s3 = _uniform(s0, s1, s2, s3)
    return (xu if f1 + u1 * (f0 - f1) < 1.0 else math.nan), s0, s1, s2, s3


@njit(cache=True)
def _fill_normals(out: np.ndarray, seeds: np.ndarray, x: np.ndarray, ratio: np.ndarray) -> None:
    """``out[k, :]`` = standard normals from ``seeds[k]`` (ZIGNOR: one 64-bit draw gives the
    layer, low 8 bits, and a uniform in [-1, 1), high 53 bits)."""
    for k in range(out.shape[0]):
        s0, s1, s2, s3 = _seed_state(np.uint64(seeds[k]))
        for p in range(out.shape[1]):
            while True:
                bits, s0, s1, s2, s3 = _next(s0, s1, s2, s3)
                layer = np.int64(bits & np.uint64(0xFF))
                u = 2.0 * (np.int64(bits >> np.uint64(11)) * _U53) - 1.0
                if abs(u) < ratio[layer]:
                    z = u * x[layer]
                    break
                z, s0, s1, s2, s3 = _wedge_or_tail(s0, s1, s2, s3, x, layer, u)
                if z == z:
                    break
            out[k, p] = z


def standard_normals(seeds: np.ndarray, size: int) -> np.ndarray:
    """``(len(seeds), size)`` standard normals (float64); row ``k`` depends on ``seeds[k]`` only."""
    seeds = np.atleast_1d(np.asarray(seeds)).astype(np.uint64)
    out = np.empty((len(seeds), int(size)))
    _fill_normals(out, seeds, _X, _RATIO)
    return out


def add_gaussian_noise(stamps: np.ndarray, seeds: np.ndarray, sigma: float) -> None:
    """Add ``sigma`` times :func:`standard_normals` (in float32) to the float32 ``stamps``
    ``(n, ...)`` in place, stamp ``k``'s from ``seeds[k]``."""
    seeds = np.atleast_1d(np.asarray(seeds)).astype(np.uint64)
    if len(seeds) != len(stamps):
        raise MegalutError(f"add_gaussian_noise: {len(seeds)} seeds for {len(stamps)} stamps")
    size = int(np.prod(stamps.shape[1:], dtype=np.int64))
    for a in range(0, len(stamps), _CHUNK):
        block = stamps[a : a + _CHUNK]
        block += (
            np.float32(sigma) * standard_normals(seeds[a : a + _CHUNK], size).astype(np.float32)
        ).reshape(block.shape)
