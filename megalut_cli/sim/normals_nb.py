"""The compiled kernels of :mod:`.normals` (numba): xoshiro256** seeded by SplitMix64 and the
ziggurat draws of standard normals (:func:`fill_normals`), with the constants they read.
"""

from __future__ import annotations

import math

import numpy as np

from megalut_cli.jit import njit

#: SplitMix64's multipliers and increment (the golden ratio), and 2^-53: the generator's
#: constants, read by these kernels and by the device port (``megalut_cli.gpu.noise``).
SPLITMIX_M1 = np.uint64(0xBF58476D1CE4E5B9)
SPLITMIX_M2 = np.uint64(0x94D049BB133111EB)
SPLITMIX_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
U53 = 1.0 / 9007199254740992.0  # 2^-53


@njit(cache=True)
def _splitmix(state: np.uint64) -> tuple[np.uint64, np.uint64]:
    """SplitMix64: (next state, output)."""
    state = state + SPLITMIX_GOLDEN
    z = state
    z = (z ^ (z >> np.uint64(30))) * SPLITMIX_M1
    z = (z ^ (z >> np.uint64(27))) * SPLITMIX_M2
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
    return (np.int64(r >> np.uint64(11)) + 1) * U53, s0, s1, s2, s3


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
def fill_normals(out: np.ndarray, seeds: np.ndarray, x: np.ndarray, ratio: np.ndarray) -> None:
    """``out[k, :]`` = standard normals from ``seeds[k]`` (ZIGNOR: one 64-bit draw gives the
    layer, low 8 bits, and a uniform in [-1, 1), high 53 bits)."""
    for k in range(out.shape[0]):
        s0, s1, s2, s3 = _seed_state(np.uint64(seeds[k]))
        for p in range(out.shape[1]):
            while True:
                bits, s0, s1, s2, s3 = _next(s0, s1, s2, s3)
                layer = np.int64(bits & np.uint64(0xFF))
                u = 2.0 * (np.int64(bits >> np.uint64(11)) * U53) - 1.0
                if abs(u) < ratio[layer]:
                    z = u * x[layer]
                    break
                z, s0, s1, s2, s3 = _wedge_or_tail(s0, s1, s2, s3, x, layer, u)
                if z == z:
                    break
            out[k, p] = z
