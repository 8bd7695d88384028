"""The compiled kernels of :mod:`.render` (numba): the radial k-profile F(q) of a
:class:`megalut_cli.sim.render.RadialProfile` in its exact and fast forms
(:func:`radial_values`), and the fill of the galaxy x PSF x pixel x phase k-values of a batch
of stamps onto their FFT grids (:func:`fill_kimages`).
"""

from __future__ import annotations

import math

import numpy as np

from megalut_cli.jit import njit

#: Cubics per octave of q^2 in the fast form (relative width 2^-8 of q^2).
FAST_BITS = 8


@njit(cache=True)
def _radial(q2: float, p: np.ndarray, ei: np.ndarray, coef: np.ndarray) -> float:
    """Exact form of F(q) at ``q2 = q^2`` (see :class:`RadialProfile`); ``p`` its params,
    ``ei`` = (kind, first and last of its cubics in ``coef``, ...)."""
    kind = ei[0]
    if kind == 0:
        if q2 < p[2]:
            return 1.0 + q2 * (p[3] + q2 * p[4])
        if q2 >= p[5]:
            q = math.sqrt(q2)
            return (p[6] + p[7] / q) / q2
        x = (0.5 * math.log(q2) - p[0]) / p[1]
        i = int(x)
        t = x - i
        i += ei[1]
        if i > ei[2]:
            i = ei[2]
        return (coef[i, 0] + t * (coef[i, 1] + t * (coef[i, 2] + t * coef[i, 3]))) / q2
    if kind == -2:
        return math.exp(-0.5 * q2)
    if q2 > p[1]:
        return 0.0
    if q2 < p[0]:
        return 1.0 - 0.5 * q2 * (1.0 - 0.25 * q2)
    return math.exp(-0.5 * q2)


_MANTISSA_SHIFT = 52 - FAST_BITS
_FRACTION_MASK = (1 << _MANTISSA_SHIFT) - 1
_FRACTION_SCALE = 1.0 / (1 << _MANTISSA_SHIFT)


@njit(cache=True)
def _fast_index(bits: int, lo: int, hi: int, first: int) -> int:
    """Row of the fast cubic for ``q^2`` of IEEE-754 bit pattern ``bits`` (-1: none): the
    octave ``e - lo`` (``e`` the unbiased exponent, ``lo <= e < hi``) times 2^FAST_BITS plus
    the first FAST_BITS bits of the mantissa, which for a positive ``q^2`` are one shift of
    ``bits`` minus a constant (a negative ``q^2`` or a NaN falls outside)."""
    u = (bits >> _MANTISSA_SHIFT) - ((1023 + lo) << FAST_BITS)
    if u < 0 or u >= (hi - lo) << FAST_BITS:
        return -1
    return first + u


@njit(cache=True)
def _fraction(bits: int) -> float:
    """Position of ``q^2`` (bit pattern ``bits``) in its fast interval, in [0, 1)."""
    return (bits & _FRACTION_MASK) * _FRACTION_SCALE


@njit(cache=True)
def radial_values(
    q2: np.ndarray, p: np.ndarray, ei: np.ndarray, coef: np.ndarray, fcoef: np.ndarray, fast: bool
) -> np.ndarray:
    """F at each ``q2`` (exact or fast form)."""
    out = np.empty(q2.shape[0])
    q2c = np.ascontiguousarray(q2)
    bits = q2c.view(np.int64)
    for k in range(q2.shape[0]):
        c = _fast_index(bits[k], ei[3], ei[4], ei[5]) if fast else -1
        if c >= 0 and fcoef[c, 0] == fcoef[c, 0]:  # not NaN
            t = _fraction(bits[k])
            out[k] = fcoef[c, 0] + t * (fcoef[c, 1] + t * (fcoef[c, 2] + t * fcoef[c, 3]))
        else:
            out[k] = _radial(q2c[k], p, ei, coef)
    return out


@njit(cache=True)
def fill_kimages(
    out,
    kpsf,
    real_psf,
    n_fft,
    n_k,
    dk,
    amat,
    flux,
    shift_x,
    shift_y,
    table,
    eparams,
    eint,
    coef,
    fcoef,
):
    """Galaxy x PSF x pixel x phase k-values of each stamp, wrapped onto its FFT grid.

    ``out[s]`` (N, N/2+1) receives the sum over GalSim's (Nk+1) x (Nk/2+1) k-image (rows
    ky = -Nk/2..Nk/2, columns kx = 0..Nk/2), folded as GalSim's Hermitian wrap does and
    weighted so that numpy's inverse real FFT of ``out[s]`` equals GalSim's real image:
    a stored column kx > 0 counts twice (it stands for -kx too), numpy's columns 0 and N/2
    once, its others twice.
    """
    half = n_k // 2
    n_half = n_fft // 2
    m = out.shape[0]
    phx = np.empty(half + 1, dtype=np.complex128)
    phx_re = np.empty(half + 1)
    phx_im = np.empty(half + 1)
    q2 = np.empty(half + 1)
    fq = np.empty(half + 1)
    bits = q2.view(np.int64)
    out_f = out.view(np.float32)  # (m, N, 2 (N/2+1)): real and imaginary parts
    for s in range(m):
        if n_k != n_fft:
            out[s, :, :] = 0
        for i in range(half + 1):
            a = -i * dk * shift_x[s]
            phx[i] = complex(math.cos(a), math.sin(a))
            phx_re[i] = phx[i].real
            phx_im[i] = phx[i].imag
        p = eparams[table[s]]
        ei = eint[table[s]]
        lo, hi, ffirst = ei[3], ei[4], ei[5]
        # q^2 = (c_xx i^2 + 2 c_xy i jj + c_yy jj^2) dk^2, q = A k
        a00, a01, a10, a11 = amat[s, 0], amat[s, 1], amat[s, 2], amat[s, 3]
        cxx = (a00 * a00 + a10 * a10) * dk * dk
        cxy = (a00 * a01 + a10 * a11) * dk * dk
        cyy = (a01 * a01 + a11 * a11) * dk * dk
        f = flux[s]
        for j in range(n_k + 1):
            jj = j - half
            a = -jj * dk * shift_y[s]
            rowf = f * complex(math.cos(a), math.sin(a))
            qy2 = cyy * jj * jj
            qxy = 2.0 * cxy * jj
            for i in range(half + 1):
                q2[i] = (cxx * i + qxy) * i + qy2
            # F(q) for the row (the table lookup), then the products in branch-free loops.
            for i in range(half + 1):
                c = _fast_index(bits[i], lo, hi, ffirst)
                if c >= 0 and fcoef[c, 0] == fcoef[c, 0]:  # not NaN
                    t = _fraction(bits[i])
                    fq[i] = fcoef[c, 0] + t * (fcoef[c, 1] + t * (fcoef[c, 2] + t * fcoef[c, 3]))
                else:
                    fq[i] = _radial(q2[i], p, ei, coef)
            kp = kpsf[j]
            row = jj % n_fft
            if n_k == n_fft:  # no aliasing: column i stays i; rows -N/2 and N/2 share row N/2
                dest = out[s, row]
                if j == n_k:
                    for i in range(half):
                        dest[i] += fq[i] * kp[i] * phx[i] * rowf
                elif real_psf:  # real PSF k-image: the complex products in real arithmetic
                    # (the same operations as the complex ones, in the same order: same bits)
                    dest_f = out_f[s, row]
                    fr, fi = rowf.real, rowf.imag
                    for i in range(half):
                        r = fq[i] * kp[i].real
                        pr = r * phx_re[i]
                        pi = r * phx_im[i]
                        dest_f[2 * i] = pr * fr - pi * fi
                        dest_f[2 * i + 1] = pr * fi + pi * fr
                else:
                    for i in range(half):
                        dest[i] = fq[i] * kp[i] * phx[i] * rowf
                val = 2.0 * (fq[half] * kp[half] * phx[half] * rowf)  # column N/2 counts twice
                if j == n_k:
                    dest[half] += val
                else:
                    dest[half] = val
            else:
                for i in range(half + 1):
                    val = fq[i] * kp[i] * phx[i] * rowf
                    # Fold (i, jj) onto the N grid; columns beyond N/2 by conjugation.
                    cx = i % n_fft
                    dest_row = row
                    if cx > n_half:
                        cx = n_fft - cx
                        dest_row = (n_fft - row) % n_fft
                        val = val.conjugate()
                    w = 1.0 if i == 0 else 2.0
                    if cx != 0 and cx != n_half:
                        w *= 0.5
                    out[s, dest_row, cx] += w * val
