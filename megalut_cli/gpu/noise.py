"""Per-stamp Gaussian noise on the device: the CPU fast engine's generator, ported.

The same stream as :mod:`megalut_cli.sim.normals`: xoshiro256** seeded by SplitMix64 from
each stamp's seed, ZIGNOR with 256 layers, in uint64 arithmetic. The CPU kernel draws one
stamp's normals in a loop with nested rejection loops; here every stamp of a batch advances
one 64-bit draw per step of a state machine (main draw, wedge test, tail's two uniforms), so
that each stamp consumes exactly the CPU's sequence of draws. The values are the CPU's to the
last bit on the main branch (>98 % of draws); the wedge and tail use XLA's ``exp``/``log``,
which may differ from libm by an ulp (rarely an acceptance decision, never seen in tests).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from megalut_cli.sim.normals import ziggurat_table
from megalut_cli.sim.normals_nb import SPLITMIX_GOLDEN, SPLITMIX_M1, SPLITMIX_M2, U53

jax.config.update("jax_enable_x64", True)


def _u(v: int) -> jnp.ndarray:
    return jnp.uint64(v)


def _splitmix(state: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    state = state + SPLITMIX_GOLDEN
    z = state
    z = (z ^ (z >> _u(30))) * SPLITMIX_M1
    z = (z ^ (z >> _u(27))) * SPLITMIX_M2
    return state, z ^ (z >> _u(31))


def _rotl(x: jnp.ndarray, k: int) -> jnp.ndarray:
    return (x << _u(k)) | (x >> _u(64 - k))


def _next(s: tuple[jnp.ndarray, ...]) -> tuple[jnp.ndarray, tuple[jnp.ndarray, ...]]:
    s0, s1, s2, s3 = s
    result = _rotl(s1 * _u(5), 7) * _u(9)
    t = s1 << _u(17)
    s2 = s2 ^ s0
    s3 = s3 ^ s1
    s1 = s1 ^ s2
    s0 = s0 ^ s3
    s2 = s2 ^ t
    s3 = _rotl(s3, 45)
    return result, (s0, s1, s2, s3)


def _uniform(r: jnp.ndarray) -> jnp.ndarray:
    """Uniform in (0, 1] from one 64-bit draw (as ``normals_nb._uniform``)."""
    return ((r >> _u(11)).astype(jnp.int64) + 1).astype(jnp.float64) * U53


@functools.partial(jax.jit, static_argnums=(1,))
def standard_normals(seeds: jnp.ndarray, size: int) -> jnp.ndarray:
    """``(len(seeds), size)`` standard normals (float64), row ``k`` from ``seeds[k]`` only:
    the values of :func:`megalut_cli.sim.normals.standard_normals`."""
    x = jnp.asarray(ziggurat_table())
    ratio = x[1:] / x[:-1]
    m = seeds.shape[0]
    st = seeds.astype(jnp.uint64)
    st, a = _splitmix(st)
    st, b = _splitmix(st)
    st, c = _splitmix(st)
    st, d = _splitmix(st)
    rows = jnp.arange(m)
    zero = jnp.zeros(m)
    # mode 0: main draw; 1: wedge test pending; 2: tail's first uniform; 3: its second
    init = (
        (a, b, c, d),
        jnp.zeros(m, jnp.int32),
        jnp.zeros(m, jnp.int32),
        jnp.zeros(m, jnp.int32),
        zero,
        zero,
        jnp.zeros((m, size)),
    )

    def cond(carry):
        return jnp.any(carry[1] < size)

    def body(carry):
        state, pos, mode, layer, u, xt, out = carry
        active = pos < size
        r, new_state = _next(state)
        state = tuple(jnp.where(active, n, o) for n, o in zip(new_state, state))
        # mode 0
        lay0 = (r & _u(0xFF)).astype(jnp.int32)
        u0 = 2.0 * ((r >> _u(11)).astype(jnp.int64).astype(jnp.float64) * U53) - 1.0
        quick = jnp.abs(u0) < ratio[lay0]
        z0 = u0 * x[lay0]
        # mode 1: the wedge of ``layer`` at ``u``
        uni = _uniform(r)
        xu = u * x[layer]
        f0 = jnp.exp(-0.5 * (x[layer] * x[layer] - xu * xu))
        f1 = jnp.exp(-0.5 * (x[layer + 1] * x[layer + 1] - xu * xu))
        wedge_ok = f1 + uni * (f0 - f1) < 1.0
        # modes 2 and 3: the tail beyond r (Marsaglia 1964)
        xt_new = -jnp.log(uni) / x[1]
        yt = -jnp.log(uni)
        tail_ok = yt + yt > xt * xt
        z_tail = jnp.where(u > 0, x[1] + xt, -x[1] - xt)
        accept = (
            jnp.select([mode == 0, mode == 1, mode == 2], [quick, wedge_ok, False], tail_ok)
            & active
        )
        z = jnp.select([mode == 0, mode == 1], [z0, xu], z_tail)
        next_mode = jnp.select(
            [mode == 0, mode == 1, mode == 2],
            [jnp.where(quick, 0, jnp.where(lay0 == 0, 2, 1)), 0, 3],
            jnp.where(tail_ok, 0, 2),
        )
        starts = (mode == 0) & active
        layer = jnp.where(starts, lay0, layer)
        u = jnp.where(starts, u0, u)
        xt = jnp.where((mode == 2) & active, xt_new, xt)
        mode = jnp.where(active, jnp.where(accept, 0, next_mode), mode)
        out = out.at[rows, jnp.where(accept, pos, size)].set(z, mode="drop")
        pos = pos + accept.astype(jnp.int32)
        return state, pos, mode, layer, u, xt, out

    return jax.lax.while_loop(cond, body, init)[-1]


@functools.partial(jax.jit, static_argnums=(2,))
def _noise(seeds: jnp.ndarray, sigma: jnp.ndarray, shape: tuple[int, ...]) -> jnp.ndarray:
    size = int(np.prod(shape[1:]))
    normals = standard_normals(seeds, size).astype(jnp.float32).reshape(shape)
    return sigma.astype(jnp.float32).reshape(shape[0], *([1] * (len(shape) - 1))) * normals


@jax.jit
def _add(stamps: jnp.ndarray, noise: jnp.ndarray) -> jnp.ndarray:
    return stamps + noise


def add_gaussian_noise(stamps: jnp.ndarray, seeds: jnp.ndarray, sigma: jnp.ndarray) -> jnp.ndarray:
    """``stamps`` (float32, (m, S, S)) plus ``sigma`` (one per stamp) times the normals of
    their seeds, in float32 as :func:`megalut_cli.sim.normals.add_gaussian_noise` adds them:
    the product is rounded before the sum (a separate kernel: XLA would fuse a
    multiply-add and round once)."""
    return _add(stamps, _noise(jnp.asarray(seeds), jnp.asarray(sigma), tuple(stamps.shape)))
