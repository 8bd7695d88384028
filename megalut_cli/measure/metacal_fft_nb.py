"""The compiled kernels of :mod:`.metacal_fft` and :mod:`.metacal_fft_multi` (numba).

The stack's transforms: the even and odd folds of the stamps (:func:`fold_x`) and of their
products with the x matrices (:func:`fold_y`), the assembly of the padded DFTs
(:func:`padded_dft`) and the unfold of the drawn stamps (:func:`unfold`). The slots' k values
by Quintic taps of the padded DFTs times the weights ``T / P`` (:func:`slots_full`,
:func:`slots_sep`), one copy for both layouts of the weights: ``wr, wi`` of shape
``(2, ky + 1, kx + 1)``, shared by the block's stamps (one PSF), or ``(2, ky + 1, kx + 1, m)``,
per stamp (several PSFs, :mod:`.metacal_fft_multi`); numba compiles each kernel once per
layout, its branches on ``wr.ndim`` resolved at compile time. The multi-PSF plan's Quintic
sums of the PSFs' padded DFTs (:func:`gather36`) and its per-PSF weights
(:func:`fill_weights`).
"""

from __future__ import annotations

import numpy as np

from megalut_cli.jit import njit


@njit(cache=True, nogil=True)
def fold_x(images: np.ndarray, e: np.ndarray, d: np.ndarray) -> None:
    """Even and odd parts of each row about the centre pixel ``c``: ``e[..., t] = I(c + t) +
    I(c - t)``, ``d[..., t] = I(c + t) - I(c - t)`` (``e[..., 0] = I(c)``, ``d[..., 0] = 0``,
    pixels beyond the stamp are 0)."""
    m, size = images.shape[0], images.shape[2]
    c = size // 2
    for s in range(m):
        for y in range(size):
            row = images[s, y]
            e[s, y, 0] = row[c]
            d[s, y, 0] = 0.0
            for t in range(1, c + 1):
                a = row[c + t] if c + t < size else 0.0
                b = row[c - t]
                e[s, y, t] = a + b
                d[s, y, t] = a - b


@njit(cache=True, nogil=True)
def fold_y(gc: np.ndarray, gs: np.ndarray, size: int, e: np.ndarray, d: np.ndarray) -> None:
    """:func:`fold_x` along the rows of ``[gc | gs]`` (m * S, np) into ``e, d`` (c + 1, m,
    2 np)."""
    n = gc.shape[1]
    c = size // 2
    m = gc.shape[0] // size
    for s in range(m):
        o = s * size + c
        for k in range(n):
            e[0, s, k] = gc[o, k]
            e[0, s, n + k] = gs[o, k]
            d[0, s, k] = 0.0
            d[0, s, n + k] = 0.0
        for t in range(1, c + 1):
            lo = o - t
            if c + t < size:
                hi = o + t
                for k in range(n):
                    e[t, s, k] = gc[hi, k] + gc[lo, k]
                    d[t, s, k] = gc[hi, k] - gc[lo, k]
                    e[t, s, n + k] = gs[hi, k] + gs[lo, k]
                    d[t, s, n + k] = gs[hi, k] - gs[lo, k]
            else:
                for k in range(n):
                    e[t, s, k] = gc[lo, k]
                    d[t, s, k] = -gc[lo, k]
                    e[t, s, n + k] = gs[lo, k]
                    d[t, s, n + k] = -gs[lo, k]


@njit(cache=True, nogil=True)
def padded_dft(top: np.ndarray, bottom: np.ndarray, f: np.ndarray) -> None:
    """The padded DFT ``F[r, p]`` (r = -ry..ry) of each stamp ``s`` into ``f[:, :, s]`` (real
    part) and ``f[:, :, m + s]`` (imaginary part), from ``top = [CC | CS]`` and
    ``bottom = [SC | SS]`` (ry + 1, m, 2 np): products of the stamp with cos / sin (r y) on
    the left and cos / sin (p x) on the right, r >= 0."""
    r1, m, n2 = top.shape
    n = n2 // 2
    ry = r1 - 1
    for r in range(r1):
        for s in range(m):
            for p in range(n):
                cc = top[r, s, p]
                cs = top[r, s, n + p]
                sc = bottom[r, s, p]
                ss = bottom[r, s, n + p]
                f[ry + r, p, s] = cc - ss
                f[ry + r, p, m + s] = -(cs + sc)
                f[ry - r, p, s] = cc + ss
                f[ry - r, p, m + s] = sc - cs


@njit(cache=True, nogil=True)
def unfold(u1: np.ndarray, u2: np.ndarray, u3: np.ndarray, u4: np.ndarray, out: np.ndarray) -> None:
    """The stamps ``out`` (m, S, S) from the folded products ``(ty, m, tx)``: at
    ``(c +- ty, c +- tx)``, ``u1 -+ u2 -+ u3 +- u4`` with the signs of the y side on u2 and of
    the x side on u3 (``u1 = A_r Cx``, ``u2 = B_r Cx``, ``u3 = A_i Sx``, ``u4 = B_i Sx``)."""
    m, size = out.shape[0], out.shape[1]
    c = size // 2
    for s in range(m):
        for ty in range(c + 1):
            for tx in range(c + 1):
                a, b, e, g = u1[ty, s, tx], u2[ty, s, tx], u3[ty, s, tx], u4[ty, s, tx]
                lo_y, lo_x = c - ty, c - tx
                hi_y, hi_x = c + ty, c + tx
                out[s, lo_y, lo_x] = a + b + e + g
                if hi_x < size:
                    out[s, lo_y, hi_x] = a + b - e - g
                if hi_y < size:
                    out[s, hi_y, lo_x] = a - b + e - g
                    if hi_x < size:
                        out[s, hi_y, hi_x] = a - b - e + g


@njit(cache=True, nogil=True)
def add_versions(
    block: np.ndarray, which: np.ndarray, rows: np.ndarray, n: int, dest: np.ndarray,
    out: np.ndarray, done: np.ndarray,
) -> None:  # fmt: skip
    """The versions ``which`` of a block ``(V, m, S, S)`` of stack rows ``rows`` into their
    stamps' ``out`` ``(V, n, S, S)``: a stamp's (row ``< n``) as they are, a noise field's
    (rotated by 90 degrees) rotated back (``np.rot90(., -1)``: ``[y, x]`` from ``[S - 1 - x,
    y]``), stored where ``done[v, stamp]`` is False, else added (the sum of the two parts
    does not depend on their order)."""
    size = out.shape[2]
    for v in which:
        for s in range(rows.shape[0]):
            r = rows[s]
            i = dest[r]
            src = block[v, s]
            dst = out[v, i]
            if r < n:
                if done[v, i]:
                    for y in range(size):
                        for x in range(size):
                            dst[y, x] += src[y, x]
                else:
                    dst[:, :] = src
            elif done[v, i]:
                for y in range(size):
                    for x in range(size):
                        dst[y, x] += src[size - 1 - x, y]
            else:
                for y in range(size):
                    for x in range(size):
                        dst[y, x] = src[size - 1 - x, y]
            done[v, i] = True


@njit(cache=True, nogil=True)
def take_columns(w: np.ndarray, col: np.ndarray, out: np.ndarray) -> None:
    """``out[..., s] = w[..., col[s]]`` for ``(2, ky + 1, kx + 1, K)`` weights: a block's
    per-stamp weights from its PSFs'."""
    for h in range(w.shape[0]):
        for j in range(w.shape[1]):
            for i in range(w.shape[2]):
                row = w[h, j, i]
                o = out[h, j, i]
                for s in range(col.shape[0]):
                    o[s] = row[col[s]]


@njit(cache=True, nogil=True)
def gather_fixnoise(
    versions: np.ndarray, rows: np.ndarray, field: np.ndarray, order: np.ndarray, out: np.ndarray
) -> None:
    """``out[v, order[i]] = versions[v, rows[i]]``, plus ``np.rot90(versions[v, rows[i] + 1],
    -1)`` (a fixnoise field's versions rotated back: ``[y, x]`` from ``[S - 1 - x, y]``) where
    ``field[i]``."""
    size = out.shape[2]
    for v in range(versions.shape[0]):
        for i in range(rows.shape[0]):
            src = versions[v, rows[i]]
            dst = out[v, order[i]]
            if field[i]:
                f = versions[v, rows[i] + 1]
                for y in range(size):
                    for x in range(size):
                        dst[y, x] = src[y, x] + f[size - 1 - x, y]
            else:
                dst[:, :] = src


@njit(cache=True, nogil=True, inline="always")
def _store_stamp(
    ap: np.ndarray, am: np.ndarray, c0: float, d0: float, c1: float, d1: float, j: int, i: int,
    s: int, q: np.ndarray,
) -> None:  # fmt: skip
    """Slot ``(j, i)`` of stamp ``s``: the k values ``O+- = acc+- * w+-`` of the points
    ``(+-j, i)`` (``w+ = c0 + i d0``, ``w- = c1 + i d1``) into ``q[:, s] = [[Oe_r, Oe_i],
    [Oo_i, -Oo_r]]`` (``Oe = O+ + O-``, ``Oo = O+ - O-``)."""
    m = q.shape[1]
    kyh = q.shape[0] // 2
    kxh = q.shape[2] // 2
    pr = ap[s] * c0 - ap[m + s] * d0
    pi = ap[s] * d0 + ap[m + s] * c0
    mr = am[s] * c1 - am[m + s] * d1
    mi = am[s] * d1 + am[m + s] * c1
    q[j, s, i] = pr + mr
    q[j, s, kxh + i] = pi + mi
    q[kyh + j, s, i] = pi - mi
    q[kyh + j, s, kxh + i] = mr - pr


@njit(cache=True, nogil=True, inline="always")
def _store_shared_weights(
    ap: np.ndarray, am: np.ndarray, wr: np.ndarray, wi: np.ndarray, j: int, i: int, q: np.ndarray
) -> None:
    """Slot ``(j, i)`` of every stamp (:func:`_store_stamp`), the weights ``wr, wi`` shared
    by the stamps."""
    c0, d0, c1, d1 = wr[0, j, i], wi[0, j, i], wr[1, j, i], wi[1, j, i]
    for s in range(q.shape[1]):
        _store_stamp(ap, am, c0, d0, c1, d1, j, i, s, q)


@njit(cache=True, nogil=True, inline="always")
def _store_per_stamp_weights(
    ap: np.ndarray, am: np.ndarray, wr: np.ndarray, wi: np.ndarray, j: int, i: int, q: np.ndarray
) -> None:
    """Slot ``(j, i)`` of every stamp (:func:`_store_stamp`), the weights of stamp ``s`` in
    ``wr[:, j, i, s], wi[:, j, i, s]``."""
    w0r, w0i, w1r, w1i = wr[0, j, i], wi[0, j, i], wr[1, j, i], wi[1, j, i]
    for s in range(q.shape[1]):
        _store_stamp(ap, am, w0r[s], w0i[s], w1r[s], w1i[s], j, i, s, q)


@njit(cache=True, nogil=True, fastmath=True)
def slots_full(
    f: np.ndarray,
    p0: np.ndarray,
    wx: np.ndarray,
    r0: np.ndarray,
    wy: np.ndarray,
    live: np.ndarray | None,
    wr: np.ndarray,
    wi: np.ndarray,
    q: np.ndarray,
) -> None:
    """Each slot's two k values by six by six Quintic taps of ``f``, into ``q``. The weights
    ``wr, wi``: shared by the stamps, ``(2, ky + 1, kx + 1)`` (a slot is skipped where both
    are 0), or per stamp, ``(2, ky + 1, kx + 1, m)`` with ``live`` ``(2, ky + 1, kx + 1)``
    the slots some PSF uses (the others are skipped), else None."""
    m2 = f.shape[2]
    acc = np.empty((2, m2), f.dtype)
    # per-stamp weights: ``live`` before them and the loop bounds from it make code ~1.5 times
    # faster than from ``wr`` (numba 0.68, measured)
    if wr.ndim == 3:
        n_j, n_i = wr.shape[1], wr.shape[2]
    else:
        n_j, n_i = live.shape[1], live.shape[2]
    for j in range(n_j):
        for i in range(n_i):
            for h in range(2):
                a = acc[h]
                a[:] = 0.0
                if wr.ndim == 3:
                    if wr[h, j, i] == 0.0 and wi[h, j, i] == 0.0:
                        continue
                elif live[h, j, i] == 0:
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
            if wr.ndim == 3:
                _store_shared_weights(acc[0], acc[1], wr, wi, j, i, q)
            else:
                _store_per_stamp_weights(acc[0], acc[1], wr, wi, j, i, q)


@njit(cache=True, nogil=True, fastmath=True)
def slots_sep(
    f: np.ndarray,
    p0: np.ndarray,
    wx: np.ndarray,
    r0: np.ndarray,
    wy: np.ndarray,
    wr: np.ndarray,
    wi: np.ndarray,
    q: np.ndarray,
    work: np.ndarray,
) -> None:
    """Each slot's two k values by separable Quintic taps (six along kx into ``work``, then
    six along ky; or a single tap of weight 1 in both), into ``q``. The weights ``wr, wi``:
    shared by the stamps, ``(2, ky + 1, kx + 1)``, or per stamp, ``(2, ky + 1, kx + 1, m)``."""
    m2 = f.shape[2]
    ky = wr.shape[1] - 1
    n_col = p0.shape[0]
    acc = np.empty((2, m2), f.dtype)
    if wx.shape[1] == 1:  # the k points are nodes of the padded grid
        for j in range(ky + 1):
            fp, fm = f[r0[ky + j]], f[r0[ky - j]]
            for i in range(n_col):
                if wr.ndim == 3:
                    _store_shared_weights(fp[p0[i]], fm[p0[i]], wr, wi, j, i, q)
                else:
                    _store_per_stamp_weights(fp[p0[i]], fm[p0[i]], wr, wi, j, i, q)
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
            if wr.ndim == 3:
                _store_shared_weights(a0, a1, wr, wi, j, i, q)
            else:
                _store_per_stamp_weights(a0, a1, wr, wi, j, i, q)


@njit(cache=True, nogil=True)
def gather36(
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
def fill_weights(
    g: np.ndarray, idx: np.ndarray, psf_factor: np.ndarray, shared: np.ndarray, r2: np.ndarray,
    kernel: np.ndarray, maxk2: np.ndarray, min_acc: float, jj: np.ndarray, ii: np.ndarray,
    wr: np.ndarray, wi: np.ndarray,
) -> None:  # fmt: skip
    """The weights of the points ``idx`` into their slots ``wr, wi (2, ky + 1, kx + 1, K)``:
    ``w = T * shared / P`` (GalSim's ``Deconvolve``: ``1 / min_acc`` where ``|P| < min_acc``),
    ``P = g[n, k] * psf_factor`` (PSF ``k``'s Quintic sum times its half-pixel phase and
    Lanczos factor), ``T = kernel[k, |j|, i]`` (PSF ``k``'s target); 0 where
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
            e = kernel[k, ja, iv]
            wr[h, ja, iv, k] = e * (sr * dr - si * di)
            wi[h, ja, iv, k] = e * (sr * di + si * dr)
