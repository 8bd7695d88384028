"""The fast engine's k-space renderer on the device: k-image fill, fold, batched inverse FFT.

The host plans the stamps with :meth:`megalut_cli.sim.render.StampRenderer.plan` (GalSim's FFT
grid rule, transforms, radial k-profiles from GalSim's Sérsic tables) and gives the PSF x
pixel k-image once per PSF and grid (GalSim ``drawKImage``). On the device every k-value of
GalSim's (Nk+1) x (Nk/2+1) grid is computed at once for a batch of stamps sharing a grid:
galaxy F(q) (the renderer's exact radial form: a cubic per interval of GalSim's table in
``log q``), times the PSF, the flux and the offset's phase, in float64; the values are folded
onto the N x (N/2+1) grid as GalSim wraps them (a scatter-add with indices fixed per grid),
rounded to complex64 and inverse-transformed; only the first S x S pixels are kept.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from megalut_cli.sim.render import RadialProfile, stack_profiles

jax.config.update("jax_enable_x64", True)


@functools.lru_cache(maxsize=64)
def fold_indices(n_fft: int, n_k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each k-value (j, i) of GalSim's grid lands on the N x (N/2+1) grid (flat
    index), its weight and whether it is conjugated, as the CPU fill folds it: columns
    beyond N/2 by conjugation, a stored column kx > 0 counting twice, numpy's columns 0 and
    N/2 once, its others twice."""
    half, n_half = n_k // 2, n_fft // 2
    j, i = np.meshgrid(np.arange(n_k + 1), np.arange(half + 1), indexing="ij")
    row = (j - half) % n_fft
    cx = i % n_fft
    conj = cx > n_half
    dest_row = np.where(conj, (n_fft - row) % n_fft, row)
    cx = np.where(conj, n_fft - cx, cx)
    w = np.where(i == 0, 1.0, 2.0) * np.where((cx != 0) & (cx != n_half), 0.5, 1.0)
    return (dest_row * (n_half + 1) + cx).ravel(), w.ravel(), conj.ravel()


def _pad_rows(a: np.ndarray, rows: int) -> np.ndarray:
    out = np.zeros((rows, *a.shape[1:]), dtype=a.dtype)
    out[: len(a)] = a
    return out


def profile_arrays(profiles: list[RadialProfile]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact radial forms as arrays (params, integers, cubics), padded to power-of-two row
    counts so that batches with different profile sets share compiled kernels."""
    eparams, eint, coef, _ = stack_profiles(profiles)
    t = max(8, 1 << math.ceil(math.log2(len(eparams))))
    c = max(1024, 1 << math.ceil(math.log2(len(coef))))
    return _pad_rows(eparams, t), _pad_rows(eint, t), _pad_rows(coef, c)


def radial(q2: jnp.ndarray, p: jnp.ndarray, ei: jnp.ndarray, coef: jnp.ndarray) -> jnp.ndarray:
    """The exact form of F(q) at ``q2`` (any shape), ``p``/``ei`` broadcast against it (the
    last axis holding the 8 params and 6 integers): ``megalut_cli.sim.render._radial``."""
    kind = ei[..., 0]
    # Sersic: quartic, cubic in log q, asymptote
    safe = jnp.where(q2 > 0, q2, 1.0)
    x = (0.5 * jnp.log(safe) - p[..., 0]) / p[..., 1]
    k = jnp.floor(jnp.maximum(x, 0.0))
    t = x - k
    idx = jnp.minimum(k.astype(jnp.int64) + ei[..., 1], ei[..., 2])
    idx = jnp.clip(idx, 0, coef.shape[0] - 1)
    c = coef[idx]
    cubic = (c[..., 0] + t * (c[..., 1] + t * (c[..., 2] + t * c[..., 3]))) / safe
    q = jnp.sqrt(safe)
    sersic = jnp.where(
        q2 < p[..., 2],
        1.0 + q2 * (p[..., 3] + q2 * p[..., 4]),
        jnp.where(q2 >= p[..., 5], (p[..., 6] + p[..., 7] / q) / safe, cubic),
    )
    gauss = jnp.exp(-0.5 * q2)
    sheared = jnp.where(
        q2 > p[..., 1], 0.0, jnp.where(q2 < p[..., 0], 1.0 - 0.5 * q2 * (1.0 - 0.25 * q2), gauss)
    )
    return jnp.where(kind == 0, sersic, jnp.where(kind == -2, gauss, sheared))


@functools.partial(jax.jit, static_argnames=("n_fft", "n_k", "size"))
def render_batch(
    kpsf: jnp.ndarray,
    amat: jnp.ndarray,
    flux: jnp.ndarray,
    shift_x: jnp.ndarray,
    shift_y: jnp.ndarray,
    table: jnp.ndarray,
    eparams: jnp.ndarray,
    eint: jnp.ndarray,
    coef: jnp.ndarray,
    dest: jnp.ndarray,
    weight: jnp.ndarray,
    conj: jnp.ndarray,
    n_fft: int,
    n_k: int,
    size: int,
) -> jnp.ndarray:
    """Noiseless float32 stamps (m, size, size) of one batch on one grid (N, Nk)."""
    half = n_k // 2
    dk = 2.0 * math.pi / n_fft
    m = amat.shape[0]
    i = jnp.arange(half + 1, dtype=jnp.float64)
    jj = jnp.arange(n_k + 1, dtype=jnp.float64) - half
    a00, a01, a10, a11 = (amat[:, c] for c in range(4))
    cxx = ((a00 * a00 + a10 * a10) * dk * dk)[:, None, None]
    cxy = ((a00 * a01 + a10 * a11) * dk * dk)[:, None, None]
    cyy = ((a01 * a01 + a11 * a11) * dk * dk)[:, None, None]
    ii, jy = i[None, None, :], jj[None, :, None]
    q2 = (cxx * ii + 2.0 * cxy * jy) * ii + cyy * jy * jy
    fq = radial(q2, eparams[table][:, None, None, :], eint[table][:, None, None, :], coef)
    phx = jnp.exp(-1j * dk * i[None, :] * shift_x[:, None])  # (m, half+1)
    rowf = flux[:, None] * jnp.exp(-1j * dk * jj[None, :] * shift_y[:, None])  # (m, Nk+1)
    val = fq * kpsf.astype(jnp.complex128)[None] * phx[:, None, :] * rowf[:, :, None]
    val = val.reshape(m, -1)
    val = jnp.where(conj[None], jnp.conj(val), val) * weight[None]
    grid = jnp.zeros((m, n_fft * (n_fft // 2 + 1)), jnp.complex128).at[:, dest].add(val)
    kimages = grid.astype(jnp.complex64).reshape(m, n_fft, n_fft // 2 + 1)
    rows = jnp.fft.ifft(kimages, axis=1)[:, :size, :]
    return jnp.fft.irfft(rows, n=n_fft, axis=2)[:, :, :size]
