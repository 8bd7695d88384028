"""The fast metacal operation (:mod:`.metacal_fft`) on a stack whose stamps have different
PSF images: one pass over many PSFs instead of one plan per PSF.

:func:`.metacal_fft.fft_versions` builds a plan per PSF (~30 ms: the PSF's padded DFT, its
Quintic interpolation at the sheared k points, the tap tables, the transform matrices).
Here the stamps of up to ``chunk`` PSFs (of one PSF size, on one k grid ``N``) share one
:class:`MultiPlan`:

* the tap tables and transform matrices cover the union of the PSFs' maxk discs, built from
  a PSF-independent :class:`Geometry` (cached on the stamp size, the PSF size, ``N`` and
  the step);
* the weights ``T / P`` (target over PSF, with GalSim's ``Deconvolve`` cut ``|P| <
  kvalue_accuracy`` and 0 outside each PSF's own maxk) are per PSF, and the slot kernels
  apply each stamp's own.

Same arithmetic as :mod:`.metacal_fft` but for the longer float32 sums of the union's
tables: the versions agree with the one-PSF path to ~1e-8 of the peak.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import galsim
import numpy as np
from numba import njit

from megalut_cli.measure.metacal_defaults import SHEARS, TYPES
from megalut_cli.measure.metacal_fft import (
    BLOCK,
    Plan,
    Version,
    Workspace,
    axis_taps,
    draw_slots,
    grid_jobs,
    grid_sizes,
    lanczos_kvalue,
    pad_size,
    psf_params,
    quintic_taps,
    shear_matrix,
    sheared_k2,
    stack_dft,
)

#: PSFs per :class:`MultiPlan`: bounds its memory (weights ~0.35 MB per PSF at N = 128,
#: float32; the PSFs' k values ~0.5 MB per PSF while it is built).
PSF_CHUNK = 64
_KVALUE_ACCURACY = galsim.GSParams().kvalue_accuracy

# --------------------------------------------------------------------------------------------
# numba kernels


@njit(cache=True, nogil=True)
def _gather36(
    nodes: np.ndarray,
    idx: np.ndarray,
    px: np.ndarray,
    wx: np.ndarray,
    py: np.ndarray,
    wy: np.ndarray,
    out: np.ndarray,
) -> None:
    """``out[n, k] = sum_ty sum_tx wy[i, ty] wx[i, tx] nodes[py[i] + ty, px[i] + tx, k]``
    (``i = idx[n]``): six by six Quintic taps of the PSFs' padded DFTs ``nodes`` (rows,
    columns, PSFs; complex values as float pairs) at the points ``idx``."""
    n_k = nodes.shape[2]
    for n in range(idx.shape[0]):
        i = idx[n]
        p, r = px[i], py[i]
        o = out[n]
        o[:] = 0.0
        for ty in range(6):
            row = nodes[r + ty]
            v = wy[i, ty]
            for tx in range(6):
                w = v * wx[i, tx]
                src = row[p + tx]
                for k in range(n_k):
                    o[k] += src[k] * w


@njit(cache=True, nogil=True)
def _fill_weights(
    g: np.ndarray, idx: np.ndarray, psf_factor: np.ndarray, shared: np.ndarray, r2: np.ndarray,
    gauss: np.ndarray, maxk2: np.ndarray, min_acc: float, jj: np.ndarray, ii: np.ndarray,
    wr: np.ndarray, wi: np.ndarray,
) -> None:  # fmt: skip
    """The weights of the points ``idx`` into their slots ``wr, wi (2, ky + 1, kx + 1, K)``:
    ``w = T * shared / P`` (GalSim's ``Deconvolve``: ``1 / min_acc`` where ``|P| < min_acc``),
    ``P = g[n, k] * psf_factor`` (PSF ``k``'s Quintic sum times its half-pixel phase and
    Lanczos factor), ``T = gauss[k, i] * gauss[k, |j|]`` (the target); 0 where
    ``r2 > maxk2[k]`` (outside PSF ``k``'s maxk)."""
    for n in range(idx.shape[0]):
        p = idx[n]
        jv, iv = jj[p], ii[p]
        h = 1 if jv < 0 else 0
        ja = -jv if jv < 0 else jv
        sr, si = shared[p].real, shared[p].imag
        f = psf_factor[p]
        for k in range(g.shape[1]):
            if r2[p] > maxk2[k]:
                continue
            a = g[n, k] * f
            if abs(a) < min_acc:
                dr, di = 1.0 / min_acc, 0.0
            else:
                d = 1.0 / a
                dr, di = d.real, d.imag
            e = gauss[k, iv] * gauss[k, ja]
            wr[h, ja, iv, k] = e * (sr * dr - si * di)
            wi[h, ja, iv, k] = e * (sr * di + si * dr)


@njit(cache=True, nogil=True, inline="always")
def _store_multi(
    ap: np.ndarray, am: np.ndarray, wr: np.ndarray, wi: np.ndarray, j: int, i: int, q: np.ndarray
) -> None:
    """:mod:`.metacal_fft`'s slot store with the weights of stamp ``s`` in ``wr[:, j, i, s]``."""
    m = q.shape[1]
    kyh = q.shape[0] // 2
    kxh = q.shape[2] // 2
    w0r, w0i, w1r, w1i = wr[0, j, i], wi[0, j, i], wr[1, j, i], wi[1, j, i]
    for s in range(m):
        c0, d0, c1, d1 = w0r[s], w0i[s], w1r[s], w1i[s]
        pr = ap[s] * c0 - ap[m + s] * d0
        pi = ap[s] * d0 + ap[m + s] * c0
        mr = am[s] * c1 - am[m + s] * d1
        mi = am[s] * d1 + am[m + s] * c1
        q[j, s, i] = pr + mr
        q[j, s, kxh + i] = pi + mi
        q[kyh + j, s, i] = pi - mi
        q[kyh + j, s, kxh + i] = mr - pr


@njit(cache=True, nogil=True, fastmath=True)
def _slots_full_multi(
    f: np.ndarray, p0: np.ndarray, wx: np.ndarray, r0: np.ndarray, wy: np.ndarray,
    live: np.ndarray, wr: np.ndarray, wi: np.ndarray, q: np.ndarray,
) -> None:  # fmt: skip
    """Each slot's two k values by six by six Quintic taps of ``f`` with per-stamp weights
    ``wr, wi (2, ky + 1, kx + 1, m)`` (``live``: the slots some PSF uses), into ``q``."""
    m2 = f.shape[2]
    acc = np.empty((2, m2), f.dtype)
    for j in range(live.shape[1]):
        for i in range(live.shape[2]):
            for h in range(2):
                a = acc[h]
                a[:] = 0.0
                if live[h, j, i] == 0:
                    continue
                p = p0[h, j, i]
                w0, w1, w2 = wx[h, j, i, 0], wx[h, j, i, 1], wx[h, j, i, 2]
                w3, w4, w5 = wx[h, j, i, 3], wx[h, j, i, 4], wx[h, j, i, 5]
                for t in range(6):
                    src = f[r0[h, j, i] + t]
                    wt = wy[h, j, i, t]
                    s0, s1, s2, s3, s4, s5 = (
                        src[p],
                        src[p + 1],
                        src[p + 2],
                        src[p + 3],
                        src[p + 4],
                        src[p + 5],
                    )
                    for s in range(m2):
                        a[s] += wt * (
                            w0 * s0[s]
                            + w1 * s1[s]
                            + w2 * s2[s]
                            + w3 * s3[s]
                            + w4 * s4[s]
                            + w5 * s5[s]
                        )
            _store_multi(acc[0], acc[1], wr, wi, j, i, q)


@njit(cache=True, nogil=True, fastmath=True)
def _slots_sep_multi(
    f: np.ndarray, p0: np.ndarray, wx: np.ndarray, r0: np.ndarray, wy: np.ndarray,
    wr: np.ndarray, wi: np.ndarray, q: np.ndarray, work: np.ndarray,
) -> None:  # fmt: skip
    """Each slot's two k values by separable Quintic taps (or a single tap of weight 1) with
    per-stamp weights ``wr, wi (2, ky + 1, kx + 1, m)``, into ``q``."""
    m2 = f.shape[2]
    ky = wr.shape[1] - 1
    n_col = p0.shape[0]
    acc = np.empty((2, m2), f.dtype)
    if wx.shape[1] == 1:  # the k points are nodes of the padded grid
        for j in range(ky + 1):
            fp, fm = f[r0[ky + j]], f[r0[ky - j]]
            for i in range(n_col):
                _store_multi(fp[p0[i]], fm[p0[i]], wr, wi, j, i, q)
        return
    r_lo = r0.min()
    for r in range(r_lo, r0.max() + 6):
        src = f[r]
        wk = work[r - r_lo]
        for i in range(n_col):
            p = p0[i]
            w0, w1, w2, w3, w4, w5 = wx[i, 0], wx[i, 1], wx[i, 2], wx[i, 3], wx[i, 4], wx[i, 5]
            s0, s1, s2, s3, s4, s5 = (
                src[p],
                src[p + 1],
                src[p + 2],
                src[p + 3],
                src[p + 4],
                src[p + 5],
            )
            d = wk[i]
            for s in range(m2):
                d[s] = w0 * s0[s] + w1 * s1[s] + w2 * s2[s] + w3 * s3[s] + w4 * s4[s] + w5 * s5[s]
    a0, a1 = acc[0], acc[1]
    for j in range(ky + 1):
        rp, rm = r0[ky + j] - r_lo, r0[ky - j] - r_lo
        v0, v1, v2, v3, v4, v5 = (
            wy[ky + j, 0],
            wy[ky + j, 1],
            wy[ky + j, 2],
            wy[ky + j, 3],
            wy[ky + j, 4],
            wy[ky + j, 5],
        )
        w0, w1, w2, w3, w4, w5 = (
            wy[ky - j, 0],
            wy[ky - j, 1],
            wy[ky - j, 2],
            wy[ky - j, 3],
            wy[ky - j, 4],
            wy[ky - j, 5],
        )
        t0, t1, t2, t3, t4, t5 = (
            work[rp],
            work[rp + 1],
            work[rp + 2],
            work[rp + 3],
            work[rp + 4],
            work[rp + 5],
        )
        u0, u1, u2, u3, u4, u5 = (
            work[rm],
            work[rm + 1],
            work[rm + 2],
            work[rm + 3],
            work[rm + 4],
            work[rm + 5],
        )
        for i in range(n_col):
            b0, b1, b2, b3, b4, b5 = t0[i], t1[i], t2[i], t3[i], t4[i], t5[i]
            for s in range(m2):
                a0[s] = v0 * b0[s] + v1 * b1[s] + v2 * b2[s] + v3 * b3[s] + v4 * b4[s] + v5 * b5[s]
            b0, b1, b2, b3, b4, b5 = u0[i], u1[i], u2[i], u3[i], u4[i], u5[i]
            for s in range(m2):
                a1[s] = w0 * b0[s] + w1 * b1[s] + w2 * b2[s] + w3 * b3[s] + w4 * b4[s] + w5 * b5[s]
            _store_multi(a0, a1, wr, wi, j, i, q)


# --------------------------------------------------------------------------------------------
# the PSF-independent geometry


@dataclass(frozen=True)
class VersionGeometry:
    """One version at every grid point within ``N // 2``: the sheared k ``qx, qy``,
    ``|S k|^2`` (GalSim's arithmetic, for the maxk cut), the stamp's Quintic taps (versions
    with an off-diagonal shear), the PSF's Quintic taps (on its own padded grid), the Lanczos
    factor, the PSF's and the stamp's half-pixel phases."""

    sep: bool
    qx: np.ndarray
    qy: np.ndarray
    r2: np.ndarray
    g_pf: np.ndarray | None
    g_wx: np.ndarray | None
    g_rf: np.ndarray | None
    g_wy: np.ndarray | None
    p_px: np.ndarray
    p_wx: np.ndarray
    p_py: np.ndarray
    p_wy: np.ndarray
    lanczos: np.ndarray
    psf_phase: np.ndarray
    gal_phase: np.ndarray


@dataclass(frozen=True)
class Geometry:
    """What a plan needs that does not depend on the PSF's pixels nor on the target: the grid
    points ``ii, jj``, ``base0`` (the stamp's half-pixel phase, the 1 / N^2 of the inverse
    transform, the doubling of kx > 0), the versions and the matrices of the PSF's padded
    DFT on the rows ``r_lo..`` and columns ``p_lo..`` the taps reach."""

    size: int
    psf_size: int
    n_grid: int
    ii: np.ndarray
    jj: np.ndarray
    base0: np.ndarray
    versions: tuple[VersionGeometry, ...]
    r_lo: int
    p_lo: int
    e_r: np.ndarray  # (n_r, P): exp(-i dkq r y)
    e_p: np.ndarray  # (P, n_p): exp(-i dkq x p)


@functools.lru_cache(maxsize=8)
def geometry(size: int, psf_size: int, n_grid: int, step: float) -> Geometry:
    """The geometry of stamp size ``size``, PSF size ``psf_size``, k grid ``n_grid`` and ``step``
    (as :mod:`.metacal_fft`'s plan computes it, for all candidate points)."""
    dk = 2.0 * math.pi / n_grid
    dkp = 2.0 * math.pi / pad_size(size)
    dkq = 2.0 * math.pi / pad_size(psf_size)
    reach = n_grid // 2
    ii, jj = np.meshgrid(np.arange(reach + 1), np.arange(-reach, reach + 1))
    ii, jj = ii.ravel(), jj.ravel()
    kx, ky = ii * dk, jj * dk
    shift = 0.5 if size % 2 == 0 else 0.0
    pshift = 0.5 if psf_size % 2 == 0 else 0.0
    base0 = np.exp(1j * shift * (kx + ky)) / n_grid**2 * np.where(ii == 0, 1.0, 2.0)
    out = []
    for kind in TYPES:
        g1, g2 = SHEARS[kind][0] * step, SHEARS[kind][1] * step
        m = shear_matrix(g1, g2)
        qx = m[0, 0] * kx + m[0, 1] * ky
        qy = m[1, 0] * kx + m[1, 1] * ky
        sep = bool(m[0, 1] == 0.0)
        g: tuple[np.ndarray | None, ...] = (None, None, None, None)
        if not sep:
            g = (*quintic_taps(qx / dkp), *quintic_taps(qy / dkp))
        px, pwx = quintic_taps(qx / dkq)
        py, pwy = quintic_taps(qy / dkq)
        lz = lanczos_kvalue(qx) * lanczos_kvalue(qy)
        out.append(
            VersionGeometry(
                sep, qx, qy, sheared_k2(ii, jj, dk, g1, g2), *g, px, pwx, py, pwy, lz,
                np.exp(-1j * pshift * (qx + qy)), np.exp(-1j * shift * (qx + qy)),
            )
        )  # fmt: skip
    r_lo = int(min(v.p_py.min() for v in out))
    r_hi = int(max(v.p_py.max() for v in out)) + 6
    p_lo = int(min(v.p_px.min() for v in out))
    p_hi = int(max(v.p_px.max() for v in out)) + 6
    x = np.arange(psf_size) - psf_size // 2
    e_r = np.exp(-1j * dkq * np.outer(np.arange(r_lo, r_hi), x))
    e_p = np.exp(-1j * dkq * np.outer(x, np.arange(p_lo, p_hi)))
    return Geometry(size, psf_size, n_grid, ii, jj, base0, tuple(out), r_lo, p_lo, e_r, e_p)


@functools.lru_cache(maxsize=32)
def _trig(
    size: int, n_grid: int, ry: int, p_lo: int, np_: int, ky: int, kx: int, dtype: str
) -> tuple[np.ndarray, ...]:
    """A plan's eight transform matrices ``in_xc, in_xs, in_yc, in_ys, out_yc, out_ys, out_xc,
    out_xs`` (as :mod:`.metacal_fft`'s plan builds them)."""
    dt = np.dtype(dtype)
    dk = 2.0 * math.pi / n_grid
    dkp = 2.0 * math.pi / pad_size(size)
    t = np.arange(size // 2 + 1)
    r, p = np.arange(ry + 1), np.arange(p_lo, p_lo + np_)
    j, i = np.arange(ky + 1), np.arange(kx + 1)

    def mat(a: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(a, dtype=dt)

    return (
        mat(np.cos(dkp * np.outer(t, p))), mat(np.sin(dkp * np.outer(t, p))),
        mat(np.cos(dkp * np.outer(r, t))), mat(np.sin(dkp * np.outer(r, t))),
        mat(np.cos(dk * np.outer(t, j))), mat(np.sin(dk * np.outer(t, j))),
        mat(np.cos(dk * np.outer(i, t))), mat(np.sin(dk * np.outer(i, t))),
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# the plan of a chunk of PSFs


@dataclass(frozen=True)
class MultiPlan:
    """A :class:`~.metacal_fft.Plan` whose tap tables serve PSFs ``0..K-1`` (the union of
    their maxk discs; its versions' own ``wr, wi`` are unused zeros) with per-PSF weights
    ``weights[v] = (wr, wi)`` ``(2, ky + 1, kx + 1, K)`` (0 outside a PSF's own maxk) and
    ``live[v]`` ``(2, ky + 1, kx + 1)`` uint8: the slots some PSF uses."""

    plan: Plan
    weights: tuple[tuple[np.ndarray, np.ndarray], ...]
    live: tuple[np.ndarray, ...]


def _version_table(
    vg: VersionGeometry, idx: np.ndarray, geo: Geometry, ky_n: int, kx_n: int, dkp: float
) -> tuple:
    """The tap table ``(sep, p0, wx, r0, wy, live)`` of a version at its points ``idx`` (as
    :mod:`.metacal_fft`'s plan builds it; positions before the final offsets)."""
    j, i = geo.jj[idx], geo.ii[idx]
    slot = ((j < 0).astype(np.int64), np.abs(j), i)
    live = np.zeros((2, ky_n + 1, kx_n + 1), dtype=bool)
    live[slot] = True
    if vg.sep:  # qx depends on kx only, qy on ky only
        ux = np.zeros(kx_n + 1)
        ux[i] = vg.qx[idx] / dkp
        vy = np.zeros(2 * ky_n + 1)
        vy[j + ky_n] = vg.qy[idx] / dkp
        p0, wx = axis_taps(ux)
        r0, wy = axis_taps(vy)
    else:
        p0 = np.zeros((2, ky_n + 1, kx_n + 1), dtype=np.int64)
        r0 = np.zeros_like(p0)
        wx = np.zeros((2, ky_n + 1, kx_n + 1, 6))
        wy = np.zeros_like(wx)
        p0[slot], r0[slot], wx[slot], wy[slot] = (
            vg.g_pf[idx],
            vg.g_rf[idx],
            vg.g_wx[idx],
            vg.g_wy[idx],
        )
        p0[~live] = int(np.median(vg.g_pf[idx]))  # absent points: taps inside F (weight 0)
        r0[~live] = 0
    return vg.sep, p0, wx, r0, wy, live


def multi_plan(
    psfs: np.ndarray,
    maxk: np.ndarray,
    target_sigma: np.ndarray,
    size: int,
    n_grid: int,
    step: float,
    dtype: str,
) -> MultiPlan:
    """The plan of the unit-sum PSF images ``psfs`` (K, P, P) with their GalSim ``maxk`` (K,)
    and targets ``target_sigma`` (K,), for stamps of side ``size`` on the k grid ``n_grid``."""
    geo = geometry(size, psfs.shape[1], n_grid, float(step))
    dkp = 2.0 * math.pi / pad_size(size)
    dt = np.dtype(dtype)
    nodes = np.ascontiguousarray(
        (geo.e_r[None] @ psfs.astype(complex) @ geo.e_p[None]).transpose(1, 2, 0)
    )
    maxk2 = np.asarray(maxk, dtype=np.float64) ** 2
    k1 = np.arange(n_grid // 2 + 1) * (2.0 * math.pi / n_grid)
    gauss = np.exp(
        -0.5 * np.asarray(target_sigma, dtype=np.float64)[:, None] ** 2 * (k1 * k1)[None, :]
    )
    points = [np.flatnonzero(~(vg.r2 > maxk2.max())) for vg in geo.versions]  # the union
    ky_n = int(max(np.abs(geo.jj[idx]).max() for idx in points))
    kx_n = int(max(geo.ii[idx].max() for idx in points))
    tables, weights, live = [], [], []
    for vg, idx in zip(geo.versions, points):
        g = np.empty((len(idx), len(psfs)), complex)  # the PSFs' Quintic sums (real weights)
        px, py = vg.p_px - geo.p_lo, vg.p_py - geo.r_lo
        _gather36(nodes.view(np.float64), idx, px, vg.p_wx, py, vg.p_wy, g.view(np.float64))
        wr = np.zeros((2, ky_n + 1, kx_n + 1, len(psfs)), dt)
        wi = np.zeros_like(wr)
        shared = geo.base0 * vg.lanczos * vg.gal_phase
        psf_factor = vg.psf_phase * vg.lanczos
        _fill_weights(
            g,
            idx,
            psf_factor,
            shared,
            vg.r2,
            gauss,
            maxk2,
            _KVALUE_ACCURACY,
            geo.jj,
            geo.ii,
            wr,
            wi,
        )
        weights.append((wr, wi))
        table = _version_table(vg, idx, geo, ky_n, kx_n, dkp)
        tables.append(table)
        live.append(table[5].astype(np.uint8))
    ry = int(max(max(np.abs(t[3]).max(), np.abs(t[3] + t[4].shape[-1] - 1).max()) for t in tables))
    p_lo = int(min(t[1].min() for t in tables))
    np_ = int(max((t[1] + t[2].shape[-1] - 1).max() for t in tables)) + 1 - p_lo
    zeros = np.zeros((2, ky_n + 1, kx_n + 1), dt)
    versions = tuple(
        Version(sep, p0 - p_lo, wx.astype(dt), r0 + ry, wy.astype(dt), zeros, zeros)
        for sep, p0, wx, r0, wy, _ in tables
    )
    trig = _trig(size, n_grid, ry, p_lo, np_, ky_n, kx_n, dt.name)
    return MultiPlan(Plan(size, ry, np_, ky_n, kx_n, *trig, versions), tuple(weights), tuple(live))


# --------------------------------------------------------------------------------------------
# the runs


def _run_multi(
    mp: MultiPlan,
    images: np.ndarray,
    col: np.ndarray,
    out: np.ndarray,
    which: tuple[int, ...],
    ws: Workspace,
) -> None:
    """Versions ``which`` of the stamps ``images`` (m, S, S), stamp ``s`` with PSF ``col[s]``
    of ``mp``, into ``out`` (V, m, S, S)."""
    plan = mp.plan
    if images.shape[0] != ws.m:
        ws = Workspace(plan, images.shape[0])
    stack_dft(plan, images, ws)
    for v in which:
        ver = plan.versions[v]
        wr, wi = (np.ascontiguousarray(w[..., col]) for w in mp.weights[v])  # the block's
        if ver.sep:
            _slots_sep_multi(ws.f, ver.p0, ver.wx, ver.r0, ver.wy, wr, wi, ws.q, ws.work)
        else:
            _slots_full_multi(ws.f, ver.p0, ver.wx, ver.r0, ver.wy, mp.live[v], wr, wi, ws.q)
        draw_slots(plan, ws, out[v])


def _chunks(used: np.ndarray, psf_sizes: np.ndarray, chunk: int) -> Iterator[np.ndarray]:
    """The PSF indices ``used`` in chunks of up to ``chunk`` PSFs of one size."""
    for p in np.unique(psf_sizes[used]):
        same = used[psf_sizes[used] == p]
        for c in range(0, len(same), chunk):
            yield same[c : c + chunk]


def fft_versions_multi(
    images: np.ndarray,
    psf_images: Sequence[np.ndarray] | np.ndarray,
    psf_index: Sequence[int] | np.ndarray,
    step: float,
    target_sigma: Sequence[float] | np.ndarray,
    dtype: str = "float32",
    out: np.ndarray | None = None,
    chunk: int = PSF_CHUNK,
) -> dict[str, np.ndarray]:
    """:func:`.metacal_fft.fft_versions` of a stack ``(n, S, S)`` whose stamp ``i`` has the PSF
    image ``psf_images[psf_index[i]]`` (square, of any sizes) and the target sigma
    ``target_sigma[psf_index[i]]``. The stamps of up to ``chunk`` PSFs of one size on one k
    grid go through one pass together; a PSF's stamps in a contiguous run are computed in
    place (so order the stack by PSF)."""
    images = np.asarray(images)
    if images.ndim != 3 or images.shape[1] != images.shape[2]:
        raise ValueError(f"expected a stack of square stamps (n, S, S), got shape {images.shape}")
    psfs = [np.ascontiguousarray(p, dtype=np.float64) for p in psf_images]
    if any(p.ndim != 2 or p.shape[0] != p.shape[1] for p in psfs):
        raise ValueError("expected square PSF images (P, P)")
    psf_index = np.asarray(psf_index, dtype=np.int64)
    target_sigma = np.asarray(target_sigma, dtype=np.float64)
    n, size = images.shape[:2]
    if psf_index.shape != (n,) or (n and (psf_index.min() < 0 or psf_index.max() >= len(psfs))):
        raise ValueError("psf_index must give each stamp one of the PSF images")
    if target_sigma.shape != (len(psfs),):
        raise ValueError(f"expected one target sigma per PSF image ({len(psfs)})")
    if chunk < 1:
        raise ValueError("chunk must be at least 1")
    if images.dtype not in (np.float32, np.float64):
        images = images.astype(np.float64)
    images = np.ascontiguousarray(images)
    if out is None:
        out = np.empty((len(TYPES), n, size, size))
    elif (
        out.shape != (len(TYPES), n, size, size)
        or out.dtype != np.float64
        or not out.flags.c_contiguous
    ):
        raise ValueError(f"out must be a C-contiguous float64 array {(len(TYPES), n, size, size)}")
    if not n:
        return {kind: out[v] for v, kind in enumerate(TYPES)}
    used = np.unique(psf_index)
    psf_sizes = np.array([p.shape[0] for p in psfs])
    unit = [np.empty((0, 0))] * len(psfs)
    maxk, psf_stepk, target_stepk = (np.full(len(psfs), np.nan) for _ in range(3))
    for j in used:
        unit[j], maxk[j], psf_stepk[j] = psf_params(psfs[j].tobytes(), psfs[j].shape[0])
        target_stepk[j] = galsim.Gaussian(sigma=float(target_sigma[j])).stepk
    grids = grid_sizes(images, psf_stepk[psf_index], target_stepk[psf_index], step)
    col_of = np.full(len(psfs), -1, np.int64)
    for n_grid, todo in grid_jobs(grids).items():
        for sel, which in todo:
            for psf_chunk in _chunks(np.unique(psf_index[sel]), psf_sizes, chunk):
                rows = sel[np.isin(psf_index[sel], psf_chunk)]
                stack = np.array([unit[j] for j in psf_chunk])
                mp = multi_plan(
                    stack,
                    maxk[psf_chunk],
                    target_sigma[psf_chunk],
                    size,
                    n_grid,
                    step,
                    np.dtype(dtype).name,
                )
                col_of[psf_chunk] = np.arange(len(psf_chunk))
                ws = Workspace(mp.plan, min(BLOCK, len(rows)))
                for b in range(0, len(rows), BLOCK):
                    idx = rows[b : b + BLOCK]
                    i0, i1 = int(idx[0]), int(idx[-1]) + 1
                    if i1 - i0 == len(idx):  # a contiguous run: in place
                        _run_multi(
                            mp, images[i0:i1], col_of[psf_index[i0:i1]], out[:, i0:i1], which, ws
                        )
                        continue
                    tmp = np.empty((len(TYPES), len(idx), size, size))
                    _run_multi(mp, images[idx], col_of[psf_index[idx]], tmp, which, ws)
                    for v in which:
                        out[v, idx] = tmp[v]
    return {kind: out[v] for v, kind in enumerate(TYPES)}
