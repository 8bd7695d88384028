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

This module is the Python API; its compiled kernels (the slot kernels of :mod:`.metacal_fft`,
here with per-stamp weights; the PSFs' Quintic sums and weights) are in :mod:`.metacal_fft_nb`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import galsim
import numpy as np

from megalut_cli.measure.metacal_defaults import SHEARS, TYPES
from megalut_cli.measure.metacal_fft import (
    BLOCK,
    Plan,
    Version,
    Workspace,
    as_target,
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
    versions_out,
)
from megalut_cli.measure.metacal_fft_nb import (
    fill_weights,
    gather36,
    slots_full,
    slots_sep,
    take_columns,
)
from megalut_cli.measure.metacal_targets import MetacalTarget

#: PSFs per :class:`MultiPlan`: bounds its memory (weights ~0.35 MB per PSF at N = 128,
#: float32; the PSFs' k values ~0.5 MB per PSF while it is built).
PSF_CHUNK = 64
_KVALUE_ACCURACY = galsim.GSParams().kvalue_accuracy

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
    targets: Sequence[MetacalTarget],
    size: int,
    n_grid: int,
    step: float,
    dtype: str,
) -> MultiPlan:
    """The plan of the unit-sum PSF images ``psfs`` (K, P, P) with their GalSim ``maxk`` (K,)
    and ``targets`` (K), for stamps of side ``size`` on the k grid ``n_grid``."""
    geo = geometry(size, psfs.shape[1], n_grid, float(step))
    dkp = 2.0 * math.pi / pad_size(size)
    dt = np.dtype(dtype)
    nodes = np.ascontiguousarray(
        (geo.e_r[None] @ psfs.astype(complex) @ geo.e_p[None]).transpose(1, 2, 0)
    )
    maxk2 = np.asarray(maxk, dtype=np.float64) ** 2
    k1 = np.arange(n_grid // 2 + 1) * (2.0 * math.pi / n_grid)
    kernel = np.ascontiguousarray([t.grid_kvalue(k1) for t in targets], dtype=np.float64)
    points = [np.flatnonzero(~(vg.r2 > maxk2.max())) for vg in geo.versions]  # the union
    ky_n = int(max(np.abs(geo.jj[idx]).max() for idx in points))
    kx_n = int(max(geo.ii[idx].max() for idx in points))
    tables, weights, live = [], [], []
    for vg, idx in zip(geo.versions, points):
        g = np.empty((len(idx), len(psfs)), complex)  # the PSFs' Quintic sums (real weights)
        px, py = vg.p_px - geo.p_lo, vg.p_py - geo.r_lo
        gather36(nodes.view(np.float64), idx, px, vg.p_wx, py, vg.p_wy, g.view(np.float64))
        wr = np.zeros((2, ky_n + 1, kx_n + 1, len(psfs)), dt)
        wi = np.zeros_like(wr)
        shared = geo.base0 * vg.lanczos * vg.gal_phase
        psf_factor = vg.psf_phase * vg.lanczos
        fill_weights(
            g,
            idx,
            psf_factor,
            shared,
            vg.r2,
            kernel,
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
    shape = (*mp.weights[0][0].shape[:3], len(col))
    wr, wi = np.empty(shape, plan.in_xc.dtype), np.empty(shape, plan.in_xc.dtype)
    col = np.ascontiguousarray(col, dtype=np.int64)
    for v in which:
        ver = plan.versions[v]
        take_columns(mp.weights[v][0], col, wr)  # the block's weights
        take_columns(mp.weights[v][1], col, wi)
        if ver.sep:
            slots_sep(ws.f, ver.p0, ver.wx, ver.r0, ver.wy, wr, wi, ws.q, ws.work)
        else:
            slots_full(ws.f, ver.p0, ver.wx, ver.r0, ver.wy, mp.live[v], wr, wi, ws.q)
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
    targets: Sequence[float | MetacalTarget | None] | np.ndarray,
    dtype: str = "float32",
    out: np.ndarray | None = None,
    chunk: int = PSF_CHUNK,
) -> dict[str, np.ndarray]:
    """:func:`.metacal_fft.fft_versions` of a stack ``(n, S, S)`` whose stamp ``i`` has the PSF
    image ``psf_images[psf_index[i]]`` (square, of any sizes) and the target
    ``targets[psf_index[i]]`` (a :class:`~.metacal_targets.MetacalTarget`, or the sigma of a
    round Gaussian; unused PSFs' may be None or NaN). The stamps of up to ``chunk`` PSFs of
    one size on one k grid go through one pass together; a PSF's stamps in a contiguous run
    are computed in place (so order the stack by PSF)."""
    images = np.asarray(images)
    if images.ndim != 3 or images.shape[1] != images.shape[2]:
        raise ValueError(f"expected a stack of square stamps (n, S, S), got shape {images.shape}")
    psfs = [np.ascontiguousarray(p, dtype=np.float64) for p in psf_images]
    if any(p.ndim != 2 or p.shape[0] != p.shape[1] for p in psfs):
        raise ValueError("expected square PSF images (P, P)")
    psf_index = np.asarray(psf_index, dtype=np.int64)
    n, size = images.shape[:2]
    if psf_index.shape != (n,) or (n and (psf_index.min() < 0 or psf_index.max() >= len(psfs))):
        raise ValueError("psf_index must give each stamp one of the PSF images")
    if len(targets) != len(psfs):
        raise ValueError(f"expected one target per PSF image ({len(psfs)})")
    if chunk < 1:
        raise ValueError("chunk must be at least 1")
    if images.dtype not in (np.float32, np.float64):
        images = images.astype(np.float64)
    images = np.ascontiguousarray(images)
    out = versions_out(out, n, size)
    if not n:
        return {kind: out[v] for v, kind in enumerate(TYPES)}
    used = np.unique(psf_index)
    psf_sizes = np.array([p.shape[0] for p in psfs])
    unit = [np.empty((0, 0))] * len(psfs)
    maxk, psf_stepk, target_stepk = (np.full(len(psfs), np.nan) for _ in range(3))
    target: list[MetacalTarget | None] = [None] * len(psfs)
    for j in used:
        unit[j], maxk[j], psf_stepk[j] = psf_params(psfs[j].tobytes(), psfs[j].shape[0])
        target[j] = t = as_target(targets[j])
        target_stepk[j] = t.stepk
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
                    [target[j] for j in psf_chunk],
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
