"""The metacal image operation on a whole stack at once (``engine="fast"`` of :mod:`.metacal`).

GalSim's reference, numerics included (they matter at the 1e-3 level on noise), with
matrix products over the stack instead of an FFT per stamp and version:

* the ``InterpolatedImage`` k-values are a Quintic interpolation of the DFT of the stamp
  zero-padded to ``good_fft_size(4 S)`` (times the Lanczos transform, which cancels against
  the PSF's): that padded DFT is computed where the 6x6 Quintic taps reach, then
  interpolated at the sheared k points ``S k`` (``S`` the symmetric shear matrix);
* ``Deconvolve`` is ``1 / P`` inside the PSF image's ``maxk``, 0 outside;
* ``drawImage`` samples ``T(k) I(S k) / P(S k)`` (``T`` the target's Fourier kernel,
  :meth:`~.metacal_targets.MetacalTarget.kvalue_shifted`) on GalSim's k grid of spacing
  ``2 pi / N`` (``N`` from the profile's ``stepk``, at least 128, so per stamp: from its
  flux radius) and transforms back with wrap-around at period ``N`` (on noise, ``N``
  changes the result by up to ~10 % of the rms): the same grid, only the stamp's pixels.

The transforms are split into even and odd parts (half the work). What depends on the PSF,
the step and the sizes is built once and cached. The arithmetic is float32 by default.

This module is the Python API; its compiled kernels (shared with :mod:`.metacal_fft_multi`)
are in :mod:`.metacal_fft_nb`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator
from dataclasses import dataclass

import galsim
import numpy as np

from megalut_cli.measure.metacal_defaults import INTERPOLANT, SHEARS, TYPES
from megalut_cli.measure.metacal_fft_nb import (
    add_versions,
    fold_x,
    fold_y,
    padded_dft,
    slots_full,
    slots_sep,
    unfold,
)
from megalut_cli.measure.metacal_targets import MetacalTarget
from megalut_cli.measure.metacal_targets.gauss import GaussTarget

_SHEARS = tuple(SHEARS[kind] for kind in TYPES)
_QUINTIC = galsim.Quintic()
_LANCZOS = galsim.Lanczos(15)
_GSPARAMS = galsim.GSParams()
#: Stamps per block: the block's work arrays stay in the core's cache.
BLOCK = 16


def shear_matrix(g1: float, g2: float) -> np.ndarray:
    """GalSim's shear as a 2x2 matrix (symmetric, determinant 1); k-values of a sheared
    profile are the original's at ``matrix @ k``."""
    return np.array([[1.0 + g1, g2], [g2, 1.0 - g1]]) / math.sqrt(1.0 - g1 * g1 - g2 * g2)


def pad_size(size: int) -> int:
    """Side of GalSim's zero-padded ``InterpolatedImage`` (pad_factor 4)."""
    return int(galsim.Image.good_fft_size(int(math.ceil(4.0 * size))))


def quintic_taps(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First node and the six Quintic weights of each interpolation point ``u`` (in nodes)."""
    first = np.floor(u).astype(np.int64) - 2
    x = (first[:, None] + np.arange(6)[None, :]) - u[:, None]
    return first, _QUINTIC.xval(x.ravel()).reshape(x.shape)


def axis_taps(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`quintic_taps`, or a single tap of weight 1 where every ``u`` is a node."""
    if np.all(np.abs(u - np.round(u)) < 1e-9):
        return np.round(u).astype(np.int64), np.ones((len(u), 1))
    return quintic_taps(u)


def _interpolated_dft(image: np.ndarray, qx: np.ndarray, qy: np.ndarray) -> np.ndarray:
    """GalSim's ``InterpolatedImage(image).kValue`` at ``(qx, qy)`` but for the x
    interpolant's transform: the Quintic interpolation of the padded DFT, times the
    half-pixel phase of even sizes (for the PSF)."""
    size = image.shape[0]
    x = np.arange(size) - size // 2
    dkp = 2.0 * math.pi / pad_size(size)
    px, wx = quintic_taps(qx / dkp)
    py, wy = quintic_taps(qy / dkp)
    p = np.arange(px.min(), px.max() + 6)
    r = np.arange(py.min(), py.max() + 6)
    nodes = (
        np.exp(-1j * dkp * np.outer(r, x))
        @ image.astype(complex)
        @ np.exp(-1j * dkp * np.outer(x, p))
    )
    six = np.arange(6)
    flat = ((py - r[0])[:, None, None] + six[:, None]) * len(p) + (px - p[0])[:, None, None] + six
    taps = nodes.ravel()[flat.reshape(len(qx), 36)].view(np.float64).reshape(len(qx), 36, 2)
    val = np.einsum("nkc,nk->nc", taps, (wy[:, :, None] * wx[:, None, :]).reshape(-1, 36))
    shift = 0.5 if size % 2 == 0 else 0.0  # the true centre of an even-sized image
    return (val[:, 0] + 1j * val[:, 1]) * np.exp(-1j * shift * (qx + qy))


def lanczos_kvalue(q: np.ndarray) -> np.ndarray:
    """The Lanczos-15 kernel's transform at ``q`` (evaluated once per distinct value)."""
    vals, inv = np.unique(q, return_inverse=True)
    return _LANCZOS.kval(vals)[inv.ravel()]


def sheared_k2(ii: np.ndarray, jj: np.ndarray, dk: float, g1: float, g2: float) -> np.ndarray:
    """``|S k|^2`` of the grid points ``(ii, jj) dk`` in GalSim's ``Deconvolution``
    floating-point arithmetic (grid points can lie exactly on the maxk circle)."""
    kx, ky = ii.astype(np.float64), jj.astype(np.float64)
    if g1 or g2:
        jac = galsim.Shear(g1=g1, g2=g2).getMatrix()
        kx, ky = (jac[0, 0] * kx + jac[1, 0] * ky), (jac[0, 1] * kx + jac[1, 1] * ky)
    return (kx**2 + ky**2) * dk**2


def _beyond(
    ii: np.ndarray, jj: np.ndarray, dk: float, g1: float, g2: float, maxk: float
) -> np.ndarray:
    """Where GalSim's ``Deconvolution`` sets the k image to 0: ``|S k|^2 > maxk^2``."""
    return sheared_k2(ii, jj, dk, g1, g2) > maxk**2


@dataclass(frozen=True)
class Version:
    """How to get one version's k image from the padded DFT ``F``.

    Slots ``(j, i)``, ``0 <= j <= ky``, ``0 <= i <= kx``, each with the two k points
    ``(+-j dk, i dk)`` (index 0 and 1 of the first axis of ``wr``, ``wi``: the complex
    weights ``T / P`` times phases, 0 where the point is outside ``maxk``).
    ``sep`` (a diagonal shear): Quintic taps per kx column (``p0`` first node, ``wx``
    weights) and per ky row ``-ky..ky`` (``r0``, ``wy``); else six by six taps per point,
    ``p0, r0`` of shape ``(2, ky + 1, kx + 1)`` and ``wx, wy`` with a last axis of 6.
    """

    sep: bool
    p0: np.ndarray
    wx: np.ndarray
    r0: np.ndarray
    wy: np.ndarray
    wr: np.ndarray
    wi: np.ndarray


@dataclass(frozen=True)
class Plan:
    """One PSF image, step, target, stamp size and k grid ``N``: the version tables and
    the folded transform matrices (positions ``t = 0..c``, ``c = S // 2``)."""

    size: int
    ry: int  # F rows r = -ry..ry (times the padded grid's dk)
    np_: int  # F columns p = p_lo..p_lo + np_ - 1
    ky: int
    kx: int
    in_xc: np.ndarray  # (c + 1, np_): cos(p dkp t)
    in_xs: np.ndarray  # sin
    in_yc: np.ndarray  # (ry + 1, c + 1): cos(r dkp t)
    in_ys: np.ndarray
    out_yc: np.ndarray  # (c + 1, ky + 1): cos(j dk t)
    out_ys: np.ndarray
    out_xc: np.ndarray  # (kx + 1, c + 1): cos(i dk t)
    out_xs: np.ndarray
    versions: tuple[Version, ...]


@functools.lru_cache(maxsize=16)
def _plan(
    psf_bytes: bytes,
    psf_size: int,
    size: int,
    n_grid: int,
    step: float,
    target: MetacalTarget,
    dtype: str,
) -> Plan:
    """The plan (cached on the PSF's bytes and the parameters), in ``dtype``."""
    psf, maxk, _ = psf_params(psf_bytes, psf_size)
    min_acc = _GSPARAMS.kvalue_accuracy  # Deconvolve: 1 / max(|P|, flux * kvalue_accuracy)
    dk = 2.0 * math.pi / n_grid
    dkp = 2.0 * math.pi / pad_size(size)
    # candidate grid points: |k| <= maxk / (smallest singular value of the shear) + margin
    reach = min(int(math.ceil(maxk * (1.0 + 2.0 * step) / dk)) + 1, n_grid // 2)
    ii, jj = np.meshgrid(np.arange(reach + 1), np.arange(-reach, reach + 1))
    ii, jj = ii.ravel(), jj.ravel()
    kx, ky = ii * dk, jj * dk
    shift = 0.5 if size % 2 == 0 else 0.0
    # the target, the half-pixel recentring of drawImage for even sizes, the irfft's 1 / N^2
    # and the doubling of kx > 0 (GalSim's Hermitian wrap doubles the kx = N/2 column too)
    base = target.kvalue_shifted(kx, ky, shift) / n_grid**2
    base = base * np.where(ii == 0, 1.0, 2.0)
    points = []
    for s1, s2 in _SHEARS:
        m = shear_matrix(s1 * step, s2 * step)
        inside = ~_beyond(ii, jj, dk, s1 * step, s2 * step, maxk)
        qx = m[0, 0] * kx[inside] + m[0, 1] * ky[inside]
        qy = m[1, 0] * kx[inside] + m[1, 1] * ky[inside]
        points.append((m[0, 1] == 0.0, inside, qx, qy))
    qx_all = np.concatenate([p[2] for p in points])
    qy_all = np.concatenate([p[3] for p in points])
    lanczos = lanczos_kvalue(qx_all) * lanczos_kvalue(
        qy_all
    )  # the x interpolant, the stamp's and the PSF's
    pk_all = _interpolated_dft(psf, qx_all, qy_all) * lanczos
    raw = []
    first = 0
    for sep, inside, qx, qy in points:
        sl = slice(first, first + len(qx))
        first += len(qx)
        pk = pk_all[sl]
        deconv = np.where(np.abs(pk) < min_acc, 1.0 / min_acc, 1.0 / np.where(pk == 0, 1.0, pk))
        w = base[inside] * deconv * lanczos[sl] * np.exp(-1j * shift * (qx + qy))
        raw.append((sep, qx / dkp, qy / dkp, w, jj[inside], ii[inside]))
    ky_n = int(max(np.abs(r[4]).max() for r in raw))
    kx_n = int(max(r[5].max() for r in raw))
    tables = []
    for sep, u, v, w, j, i in raw:
        sign = (j < 0).astype(np.int64)
        slot = (sign, np.abs(j), i)
        wc = np.zeros((2, ky_n + 1, kx_n + 1), dtype=complex)
        wc[slot] = w
        if sep:  # u depends on kx only, v on ky only
            ux = np.zeros(kx_n + 1)
            ux[i] = u
            vy = np.zeros(2 * ky_n + 1)
            vy[j + ky_n] = v
            p0, wx = axis_taps(ux)
            r0, wy = axis_taps(vy)
        else:
            pf, wxf = quintic_taps(u)
            rf, wyf = quintic_taps(v)
            p0 = np.zeros((2, ky_n + 1, kx_n + 1), dtype=np.int64)
            r0 = np.zeros_like(p0)
            wx = np.zeros((2, ky_n + 1, kx_n + 1, 6))
            wy = np.zeros_like(wx)
            p0[slot], r0[slot], wx[slot], wy[slot] = pf, rf, wxf, wyf
            # absent points: taps inside F (their weight is 0)
            p0[wc == 0] = int(np.median(pf))
            r0[wc == 0] = 0
        tables.append([sep, p0, wx, r0, wy, wc.real, wc.imag])
    ry = int(max(max(np.abs(t[3]).max(), np.abs(t[3] + t[4].shape[-1] - 1).max()) for t in tables))
    p_lo = int(min(t[1].min() for t in tables))
    np_ = int(max((t[1] + t[2].shape[-1] - 1).max() for t in tables)) + 1 - p_lo
    dt = np.dtype(dtype)
    versions = []
    for sep, p0, wx, r0, wy, wr, wi in tables:
        p0 = p0 - p_lo
        r0 = r0 + ry
        versions.append(
            Version(sep, p0, wx.astype(dt), r0, wy.astype(dt), wr.astype(dt), wi.astype(dt))
        )
    t = np.arange(size // 2 + 1)
    r, p = np.arange(ry + 1), np.arange(p_lo, p_lo + np_)
    j, i = np.arange(ky_n + 1), np.arange(kx_n + 1)

    def mat(a: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(a, dtype=dt)

    return Plan(
        size=size, ry=ry, np_=np_, ky=ky_n, kx=kx_n,
        in_xc=mat(np.cos(dkp * np.outer(t, p))), in_xs=mat(np.sin(dkp * np.outer(t, p))),
        in_yc=mat(np.cos(dkp * np.outer(r, t))), in_ys=mat(np.sin(dkp * np.outer(r, t))),
        out_yc=mat(np.cos(dk * np.outer(t, j))), out_ys=mat(np.sin(dk * np.outer(t, j))),
        out_xc=mat(np.cos(dk * np.outer(i, t))), out_xs=mat(np.sin(dk * np.outer(i, t))),
        versions=tuple(versions),
    )  # fmt: skip


class Workspace:
    """Work arrays for blocks of up to ``m`` stamps (allocated once per call)."""

    def __init__(self, plan: Plan, m: int):
        dt = plan.in_xc.dtype
        size, h, n = plan.size, plan.size // 2 + 1, plan.np_
        kq = 2 * (plan.kx + 1)
        self.ex = np.empty((m, size, h), dt)
        self.dx = np.empty((m, size, h), dt)
        self.gc = np.empty((m * size, n), dt)
        self.gs = np.empty((m * size, n), dt)
        self.m = m
        self.ey = np.empty((h, m, 2 * n), dt)
        self.dy = np.empty((h, m, 2 * n), dt)
        self.top = np.empty((plan.ry + 1, m, 2 * n), dt)
        self.bottom = np.empty((plan.ry + 1, m, 2 * n), dt)
        self.f = np.empty((2 * plan.ry + 1, n, 2 * m), dt)
        self.q = np.empty((2 * (plan.ky + 1), m, kq), dt)
        self.a = np.empty((h, m, kq), dt)
        self.b = np.empty((h, m, kq), dt)
        self.u = np.empty((4, h, m, h), dt)
        self.work = np.empty((2 * plan.ry + 1, plan.kx + 1, 2 * m), dt)


def stack_dft(plan: Plan, images: np.ndarray, ws: Workspace) -> None:
    """The padded DFTs of the stamps ``images`` (m, S, S) into ``ws.f`` (``ws.m == m``)."""
    m, size = images.shape[0], plan.size
    h = size // 2 + 1
    fold_x(images, ws.ex, ws.dx)
    np.matmul(ws.ex.reshape(m * size, h), plan.in_xc, out=ws.gc)
    np.matmul(ws.dx.reshape(m * size, h), plan.in_xs, out=ws.gs)
    fold_y(ws.gc, ws.gs, size, ws.ey, ws.dy)
    np.matmul(plan.in_yc, ws.ey.reshape(h, -1), out=ws.top.reshape(plan.ry + 1, -1))
    np.matmul(plan.in_ys, ws.dy.reshape(h, -1), out=ws.bottom.reshape(plan.ry + 1, -1))
    padded_dft(ws.top, ws.bottom, ws.f)


def draw_slots(plan: Plan, ws: Workspace, out: np.ndarray) -> None:
    """The stamps ``out`` (m, S, S) of the slots' k values in ``ws.q`` (``ws.m == m``)."""
    m, h = ws.m, plan.size // 2 + 1
    ky1, kx1 = plan.ky + 1, plan.kx + 1
    q, u = ws.q, ws.u
    a2, b2 = ws.a.reshape(h * m, -1), ws.b.reshape(h * m, -1)
    np.matmul(plan.out_yc, q[:ky1].reshape(ky1, -1), out=ws.a.reshape(h, -1))
    np.matmul(plan.out_ys, q[ky1:].reshape(ky1, -1), out=ws.b.reshape(h, -1))
    np.matmul(a2[:, :kx1], plan.out_xc, out=u[0].reshape(h * m, h))
    np.matmul(b2[:, :kx1], plan.out_xc, out=u[1].reshape(h * m, h))
    np.matmul(a2[:, kx1:], plan.out_xs, out=u[2].reshape(h * m, h))
    np.matmul(b2[:, kx1:], plan.out_xs, out=u[3].reshape(h * m, h))
    unfold(u[0], u[1], u[2], u[3], out)


def _run(
    plan: Plan, images: np.ndarray, out: np.ndarray, which: tuple[int, ...], ws: Workspace
) -> None:
    """Versions ``which`` of the stamps ``images`` (m, S, S) into ``out`` (V, m, S, S)."""
    if images.shape[0] != ws.m:
        ws = Workspace(plan, images.shape[0])
    stack_dft(plan, images, ws)
    for v in which:
        ver = plan.versions[v]
        if ver.sep:
            slots_sep(ws.f, ver.p0, ver.wx, ver.r0, ver.wy, ver.wr, ver.wi, ws.q, ws.work)
        else:
            slots_full(ws.f, ver.p0, ver.wx, ver.r0, ver.wy, None, ver.wr, ver.wi, ws.q)
        draw_slots(plan, ws, out[v])


@functools.lru_cache(maxsize=8)
def _rings(size: int) -> np.ndarray:
    """One-hot ``(S * S, dmax + 1)``: the square ring (Chebyshev distance ``d`` from the
    centre pixel) of each pixel, for ``d <= dmax = (S - 1) // 2``."""
    idx = np.arange(size) - size // 2
    d = np.maximum(np.abs(idx)[:, None], np.abs(idx)[None, :]).ravel()
    return (d[:, None] == np.arange((size - 1) // 2 + 1)[None, :]).astype(np.float64)


def _flux_radius(images: np.ndarray) -> np.ndarray:
    """GalSim's ``CalculateSizeContainingFlux`` of each stamp: ``d + 0.5``, ``d`` the
    half-side of the first square about the centre pixel holding 99.5 % of the flux."""
    n, size = images.shape[:2]
    dmax = (size - 1) // 2
    flat = images.reshape(n, size * size)
    box = np.cumsum(flat @ _rings(size), axis=1)[:, 1:]
    target = (1.0 - _GSPARAMS.folding_threshold) * flat.sum(axis=1)
    sign = np.where(target > 0, 1.0, -1.0)
    ok = sign[:, None] * box >= (sign * target)[:, None]
    return np.where(ok.any(axis=1), np.argmax(ok, axis=1) + 1, dmax + 1) + 0.5


@functools.lru_cache(maxsize=16)
def psf_params(psf_bytes: bytes, psf_size: int) -> tuple[np.ndarray, float, float]:
    """The PSF image normalised to a unit sum, and GalSim's ``maxk`` and ``stepk`` of its
    ``InterpolatedImage``."""
    psf = np.frombuffer(psf_bytes, dtype=np.float64).reshape(psf_size, psf_size)
    psf = psf / psf.sum()
    psf_ii = galsim.InterpolatedImage(galsim.ImageD(psf, scale=1.0), x_interpolant=INTERPOLANT)
    return psf, psf_ii.maxk, psf_ii.stepk


def grid_sizes(
    images: np.ndarray, psf_stepk: float | np.ndarray, target_stepk: float | np.ndarray, step: float
) -> np.ndarray:
    """GalSim's FFT size ``N`` for each stamp (n, 2): of the noshear and of the sheared
    versions (``drawFFT_makeKImage``: from the ``stepk`` of the drawn profile). The PSF's and
    the target's ``stepk``: one for all stamps, or one per stamp (n,)."""
    size = images.shape[1]
    stepk = math.pi / np.hypot(_flux_radius(images), _LANCZOS.xrange)
    deconvolved = (stepk**-2 + psf_stepk**-2) ** -0.5
    out = np.empty((len(images), 2), dtype=np.int64)
    major = math.sqrt((1.0 + step) / (1.0 - step))  # the shear's larger singular value
    for col, scale in enumerate((1.0, major)):
        sk = ((deconvolved / scale) ** -2 + target_stepk**-2) ** -0.5
        if size % 2 == 0:  # drawImage's half-pixel shift
            sk = math.pi / (math.pi / sk + math.hypot(0.5, 0.5))
        nd = np.ceil(2.0 * math.pi / sk * (1.0 - 1e-12)).astype(np.int64)
        nd = np.maximum(2 * ((nd + 1) // 2), size)
        vals, inv = np.unique(nd, return_inverse=True)
        good = np.array([galsim.Image.good_fft_size(int(x)) for x in vals])
        out[:, col] = np.maximum(good[inv.ravel()], _GSPARAMS.minimum_fft_size)
    return out


def grid_jobs(grids: np.ndarray) -> dict[int, list[tuple[np.ndarray, tuple[int, ...]]]]:
    """The work per k grid ``N``: ``{N: [(stamps, versions), ...]}`` from the stamps' grid
    sizes (n, 2) (noshear uses ``grids[:, 0]``, the sheared versions ``grids[:, 1]``)."""
    jobs: dict[int, list[tuple[np.ndarray, tuple[int, ...]]]] = {}
    for pair in np.unique(grids, axis=0):
        sel = np.flatnonzero((grids == pair).all(axis=1))
        if pair[0] == pair[1]:
            jobs.setdefault(int(pair[0]), []).append((sel, (0, 1, 2, 3, 4)))
        else:
            jobs.setdefault(int(pair[0]), []).append((sel, (0,)))
            jobs.setdefault(int(pair[1]), []).append((sel, (1, 2, 3, 4)))
    return jobs


def versions_out(out: np.ndarray | None, n: int, size: int) -> np.ndarray:
    """The array ``(5, n, S, S)`` the versions of ``n`` stamps of side ``size`` go into: a new
    one, or ``out`` (checked: C-contiguous float64 of that shape)."""
    if out is None:
        return np.empty((len(TYPES), n, size, size))
    if (
        out.shape != (len(TYPES), n, size, size)
        or out.dtype != np.float64
        or not out.flags.c_contiguous
    ):
        raise ValueError(f"out must be a C-contiguous float64 array {(len(TYPES), n, size, size)}")
    return out


def as_target(target: float | MetacalTarget) -> MetacalTarget:
    """``target``, or the round Gaussian of sigma ``target`` (pixels)."""
    return target if isinstance(target, MetacalTarget) else GaussTarget(float(target))


def fft_versions(
    images: np.ndarray,
    psf_image: np.ndarray,
    step: float,
    target: float | MetacalTarget,
    dtype: str = "float32",
    out: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """The five metacal versions ``{type: (n, S, S) float64}`` of a stack ``(n, S, S)`` of
    stamps sharing ``psf_image`` ``(P, P)``: deconvolved by it, sheared by ``step``,
    reconvolved with ``target`` (a :class:`~.metacal_targets.MetacalTarget`, or the sigma in
    pixels of a round Gaussian), as GalSim draws them. ``dtype``: the arithmetic,
    ``"float32"`` or ``"float64"``. ``out``: a C-contiguous float64 array ``(5, n, S, S)``
    to write the versions into (in :data:`TYPES` order; the result's arrays are its views),
    e.g. reused from call to call: fresh output pages cost about as much as the operation."""
    images, psf = _checked(images, psf_image)
    n, size = images.shape[:2]
    out = versions_out(out, n, size)
    for plan, ws, idx, which in _blocks(images, psf, step, target, dtype):
        i0, i1 = int(idx[0]), int(idx[-1]) + 1
        if i1 - i0 == len(idx):  # a contiguous run: in place
            _run(plan, images[i0:i1], out[:, i0:i1], which, ws)
        else:
            tmp = np.empty((len(TYPES), len(idx), size, size))
            _run(plan, images[idx], tmp, which, ws)
            for v in which:
                out[v, idx] = tmp[v]
    return {kind: out[v] for v, kind in enumerate(TYPES)}


def _checked(images: np.ndarray, psf_image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The stack (float32 or float64, C-contiguous) and the PSF image (float64), checked."""
    images = np.asarray(images)
    psf = np.ascontiguousarray(psf_image, dtype=np.float64)
    if images.ndim != 3 or images.shape[1] != images.shape[2]:
        raise ValueError(f"expected a stack of square stamps (n, S, S), got shape {images.shape}")
    if psf.ndim != 2 or psf.shape[0] != psf.shape[1]:
        raise ValueError(f"expected a square PSF image (P, P), got shape {psf.shape}")
    if images.dtype not in (np.float32, np.float64):
        images = images.astype(np.float64)
    return np.ascontiguousarray(images), psf


def _blocks(
    images: np.ndarray,
    psf: np.ndarray,
    step: float,
    target: float | MetacalTarget,
    dtype: str,
) -> Iterator[tuple[Plan, Workspace, np.ndarray, tuple[int, ...]]]:
    """The work of :func:`fft_versions`: ``(plan, workspace, rows, versions)`` per block of up
    to :data:`BLOCK` rows of ``images`` sharing a k grid. The blocks (which rows, in which
    order) fix the float32 sums' order: the versions of an image are bit for bit the same
    only within the same block."""
    n, size = images.shape[:2]
    if not n:
        return
    key = (psf.tobytes(), psf.shape[0])
    psf_stepk = psf_params(*key)[2]
    target = as_target(target)
    jobs = grid_jobs(grid_sizes(images, psf_stepk, target.stepk, step))
    for n_grid, todo in jobs.items():
        plan = _plan(*key, size, n_grid, float(step), target, np.dtype(dtype).name)
        ws = Workspace(plan, min(BLOCK, n))
        for sel, which in todo:
            for b in range(0, len(sel), BLOCK):
                yield plan, ws, sel[b : b + BLOCK], which


def fft_versions_fixnoise(
    stack: np.ndarray,
    n: int,
    field_rows: np.ndarray,
    psf_image: np.ndarray,
    step: float,
    target: float | MetacalTarget,
    dtype: str = "float32",
    out: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Metacal's fixnoise on a stack ``(n + f, S, S)``: ``n`` stamps, then ``f`` noise fields
    rotated by 90 degrees, field ``k`` that of stamp ``field_rows[k]`` (distinct rows). The
    versions of each stamp (``{type: (n, S, S)}``, views of ``out`` as in
    :func:`fft_versions`) plus the versions of its field rotated back: bit for bit
    ``fft_versions(stack)``'s first ``n`` rows with ``np.rot90(v[n + k], -1)`` added to row
    ``field_rows[k]``, the fields' versions added block by block instead of held."""
    stack, psf = _checked(stack, psf_image)
    size = stack.shape[1]
    field_rows = np.asarray(field_rows, dtype=np.int64)
    if len(field_rows) != len(stack) - n or (
        len(field_rows) and (field_rows.min() < 0 or field_rows.max() >= n)
    ):
        raise ValueError("field_rows must give each noise field one of the n stamps")
    out = versions_out(out, n, size)
    dest = np.concatenate([np.arange(n, dtype=np.int64), field_rows])  # each row's stamp
    done = np.zeros((len(TYPES), n), dtype=np.bool_)  # version v of stamp i holds a part
    tmp = np.empty((len(TYPES), min(BLOCK, len(stack)), size, size))
    for plan, ws, idx, which in _blocks(stack, psf, step, target, dtype):
        i0, i1 = int(idx[0]), int(idx[-1]) + 1
        rows = stack[i0:i1] if i1 - i0 == len(idx) else stack[idx]
        if i1 <= n and i1 - i0 == len(idx) and not done[list(which), i0:i1].any():
            _run(plan, rows, out[:, i0:i1], which, ws)  # stamps alone: in place
            done[list(which), i0:i1] = True
            continue
        block = tmp[:, : len(idx)]
        _run(plan, rows, block, which, ws)
        add_versions(block, np.array(which, dtype=np.int64), idx, n, dest, out, done)
    return {kind: out[v] for v, kind in enumerate(TYPES)}
