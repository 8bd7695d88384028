"""Batched k-space rendering of parametric galaxies, pixel for pixel as GalSim's drawImage.

:class:`StampRenderer` draws many Sersic or Gaussian galaxies (sheared by their intrinsic
ellipticity, then by the lensing shear, convolved with one PSF and the pixel, at sub-pixel
offsets) the way ``galsim.Convolve(gal, psf).drawImage(image, offset=..., method=...)``
does: same FFT grid (N, Nk) per stamp, same k-values, same wrapping, same centring. It
only skips GalSim's per-stamp Python objects and per-stamp FFTs: the galaxy k-values come
from a table of GalSim's own radial k-profile, the PSF x pixel k-image is cached per grid,
and one inverse FFT runs per batch of stamps sharing a grid. See ``docs/render.md``.

GalSim is imported only where it builds what the disk cache (:mod:`megalut_cli.cache`) does
not hold: a Sersic table, a PSF's summary or k-image (fixed PSFs:
:mod:`megalut_cli.sim.psf_store`); GSParams are plain numbers
(:mod:`megalut_cli.sim.gsparams`). A warm fast-engine run with a fixed PSF does not load it.
"""

from __future__ import annotations

import functools
import math
from collections import OrderedDict
from collections.abc import Hashable, Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from megalut_cli.cache import load_arrays, source_digest, store_arrays
from megalut_cli.errors import MegalutError
from megalut_cli.sim import render_nb
from megalut_cli.sim.gsparams import GsParams, galsim_version, good_fft_size
from megalut_cli.sim.profiles import GALAXY_PROFILES
from megalut_cli.sim.psf_store import StoredPsf
from megalut_cli.sim.render_nb import FAST_BITS, fill_kimages, radial_values

#: Most bytes of complex k-images per FFT batch: small enough that a batch filled stays in
#: the core's cache for its inverse FFT (1 MB: 0.26 ms/stamp against 0.31-0.36 with 64 MB).
BATCH_BYTES = 2**20
#: Most stamps per FFT batch.
MAX_BATCH = 256

_GAUSSIAN_HLR_FACTOR = 1.1774100225154747  # galsim.Gaussian._hlr_factor: hlr / sigma
_SERSIC_CACHE_MAX = 64  # distinct (n, GSParams) radial tables kept per process
_KIMAGE_CACHE_BYTES = 256 * 2**20  # PSF x pixel k-images kept per renderer (LRU, the newest always)
_PSF_CACHE_MAX = 512  # PSF summaries (stepk, maxk, GSParams) kept per renderer
# Sersic k-profiles: GalSim tabulates them up to k r0 = 500, then uses a k^-2, k^-3 asymptote.
_SERSIC_TABLE_END = 500.0


def can_render(profile: str) -> bool:
    """Whether :class:`StampRenderer` draws galaxies of this profile (else use GalSim): its
    registration names a radial family of :data:`RADIAL_FAMILIES` (``GalaxyProfile.fast``)."""
    kind = GALAXY_PROFILES.get(profile)
    return kind is not None and kind.fast is not None


def fast_profiles() -> tuple[str, ...]:
    """The galaxy profiles :class:`StampRenderer` draws."""
    return tuple(name for name in GALAXY_PROFILES if can_render(name))


@dataclass(frozen=True)
class RadialProfile:
    """The radial k-profile F(q) (flux 1, unit radius) of a round galaxy as GalSim evaluates
    it, in an exact form and a fast one.

    Exact: ``kind`` 0 is a Sersic of scale radius 1 (quartic below ``params[2]`` = q^2_min,
    piecewise cubic in ``u = log q`` of ``F q^2``, one cubic per interval of GalSim's own
    table, reconstructed exactly, and ``(a + b / q) / q^2`` from ``params[5]`` on); ``kind``
    -1 and -2 are Gaussians of sigma 1, transformed (SBGaussian's fill with a Jacobian:
    quadratic below ``params[0]``, zero beyond ``params[1]``) and round (exact exp).
    Fast: over ``q^2`` in [2^lo, 2^hi), ``2^FAST_BITS`` cubics per octave in the mantissa
    of ``q^2`` (no logarithm per pixel); intervals holding a break of the exact form are NaN
    and fall back to it. Sersic ``stepk``, ``maxk`` are for scale radius 1, ``hlr_factor``
    is hlr / r0; Gaussians leave them 0.
    """

    kind: int
    params: np.ndarray
    coef: np.ndarray
    octaves: tuple[int, int]
    fast: np.ndarray
    stepk: float = 0.0
    maxk: float = 0.0
    hlr_factor: float = 0.0

    def arrays(self) -> dict[str, np.ndarray]:
        """The profile as named arrays (for the disk cache); inverse of :meth:`from_arrays`."""
        scalars = np.array([self.stepk, self.maxk, self.hlr_factor])
        ints = np.array([self.kind, *self.octaves], dtype=np.int64)
        return {
            "params": self.params,
            "coef": self.coef,
            "fast": self.fast,
            "scalars": scalars,
            "ints": ints,
        }

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray]) -> RadialProfile:
        """The profile stored by :meth:`arrays`."""
        kind, lo, hi = (int(v) for v in arrays["ints"])
        stepk, maxk, hlr_factor = (float(v) for v in arrays["scalars"])
        return cls(
            kind,
            arrays["params"],
            arrays["coef"],
            (lo, hi),
            arrays["fast"],
            stepk,
            maxk,
            hlr_factor,
        )

    def kvalue(self, q: np.ndarray, fast: bool = False) -> np.ndarray:
        """F(q) as the renderer evaluates it (the fast form with ``fast``)."""
        eparams, eint, coef, fcoef = _stack([self])
        q = np.asarray(q, dtype=float)
        values = radial_values(q.ravel() ** 2, eparams[0], eint[0], coef, fcoef, fast)
        return values.reshape(q.shape)


#: The fast form of Sersic profiles covers q^2 < 2^30 (q r0 < 32768); the exact one beyond.
_FAST_MAX_OCTAVE = 30


_SERSIC_TABLES: OrderedDict[tuple[float, GsParams], RadialProfile] = OrderedDict()


def sersic_table(n: float, gsparams: GsParams | Any) -> RadialProfile:
    """The :class:`RadialProfile` of Sersic index ``n`` (cached per process, LRU, and on disk).

    A new ``n`` costs what it costs GalSim (0.03-0.3 s, growing with n: its SersicInfo
    Hankel transforms) plus ~10-20 ms of samples and fits. Indices with at most four
    decimals (grids) are kept in the disk cache (:mod:`megalut_cli.cache`), so processes
    and later runs load them in about a millisecond; others (continuous draws, fits) once
    per process, as in GalSim. ``gsparams``: a :class:`GsParams` or a ``galsim.GSParams``.
    """
    gsparams = GsParams.of(gsparams)
    key = (float(n), gsparams)
    hit = _SERSIC_TABLES.get(key)
    if hit is not None:
        _SERSIC_TABLES.move_to_end(key)
        return hit
    n = float(n)
    disk_key = sersic_table_key(n, gsparams) if round(n, 4) == n else None
    stored = load_arrays("sersic", disk_key) if disk_key else None
    if stored is not None:
        table = RadialProfile.from_arrays(stored)
    else:
        table = _build_sersic_table(n, gsparams)
        if disk_key:
            store_arrays("sersic", disk_key, table.arrays())
    _SERSIC_TABLES[key] = table
    while len(_SERSIC_TABLES) > _SERSIC_CACHE_MAX:
        _SERSIC_TABLES.popitem(last=False)
    return table


def sersic_table_key(n: float, gsparams: GsParams | Any) -> str:
    """Everything a Sersic table depends on: ``n``, the GSParams, GalSim's and numpy's
    versions and the source of this module and its kernels (any change of the code that
    builds it)."""
    return (
        f"sersic n={n!r} {GsParams.of(gsparams)!r} galsim={galsim_version()} "
        f"numpy={np.__version__} "
        f"render={source_digest(__file__, render_nb.__file__)}"
    )


def _build_sersic_table(n: float, gsp: GsParams) -> RadialProfile:
    import galsim

    gsp_g = gsp.galsim()
    try:
        unit = galsim.Sersic(n, scale_radius=1.0, gsparams=gsp_g)
        stepk, maxk = float(unit.stepk), float(unit.maxk)
    except (galsim.GalSimError, RuntimeError) as err:
        raise MegalutError(f"Sersic n={n}: GalSim cannot build the profile ({err})") from None
    hlr_factor = float(galsim.Sersic(n, half_light_radius=1.0, gsparams=gsp_g).calculateHLRFactor())

    def f_q2(q: np.ndarray) -> np.ndarray:  # F(q) q^2, as GalSim evaluates it
        return np.array([unit.kValue(float(x), 0.0).real for x in q]) * q * q

    # GalSim's table (SBSersic.cpp, SersicInfo::buildFT): knots at log(kmin) - 0.001 + i dlogk.
    g2n = math.gamma(2.0 * n)
    kd2 = -math.gamma(4.0 * n) / (4.0 * g2n)
    kd4 = math.gamma(6.0 * n) / (64.0 * g2n)
    kd6 = math.gamma(8.0 * n) / (2304.0 * g2n)
    kmin = (gsp.kvalue_accuracy / kd6) ** (1.0 / 6.0)
    h = gsp.table_spacing * math.sqrt(math.sqrt(gsp.kvalue_accuracy / 10.0))
    u0 = math.log(kmin) - 0.001
    knots = [u0]  # accumulated as GalSim does (logk += dlogk)
    while knots[-1] < math.log(_SERSIC_TABLE_END) + h:
        knots.append(knots[-1] + h)
    knots = np.array(knots)
    n_int = len(knots) - 1
    # Four interior samples per interval fix its cubic (interval 0 starts at kmin: below it,
    # the quartic; the last knot of GalSim's table already belongs to the asymptote).
    ts = np.array([0.05, 0.35, 0.65, 0.95])
    lo = np.maximum(knots[:-1], math.log(kmin))
    us = lo[:, None] + ts[None, :] * (knots[1:] - lo)[:, None]
    vals = f_q2(np.exp(us.ravel())).reshape(us.shape)
    t_samples = (us - knots[:-1, None]) / h
    vander = t_samples[:, :, None] ** np.arange(4)
    coef = np.linalg.solve(vander, vals[:, :, None])[:, :, 0]
    # GalSim's table ends at a knot (ksq_max) from which on F q^2 = a + b / q: the first
    # interval from which on every interval's samples are linear in 1/q.
    inv_q = np.exp(-us)
    slope = (vals[:, 3] - vals[:, 0]) / (inv_q[:, 3] - inv_q[:, 0])
    linear = vals[:, 0, None] + slope[:, None] * (inv_q - inv_q[:, 0, None])
    asym = (np.abs(vals - linear) <= 1e-11 * np.abs(vals)).all(axis=1)
    tail = np.logical_and.accumulate(asym[::-1])[::-1]
    first = int(np.argmax(tail)) if tail.any() else n_int
    q_fit = np.array(
        [
            math.exp(knots[first] + 0.5 * h) if first < n_int else _SERSIC_TABLE_END,
            1.5 * _SERSIC_TABLE_END,
        ]
    )
    fa = f_q2(q_fit)
    b = (fa[0] - fa[1]) / (1.0 / q_fit[0] - 1.0 / q_fit[1])
    a = fa[1] - b / q_fit[1]
    q2_asym = math.exp(2.0 * knots[first]) if first < n_int else math.inf
    params = np.array([u0, h, kmin * kmin, kd2, kd4, q2_asym, a, b])
    coef = np.ascontiguousarray(coef[: max(first, 1)])
    lo = math.floor(math.log2(kmin * kmin))
    hi = _FAST_MAX_OCTAVE  # the asymptote too: it costs a square root and two divisions
    fast = _fast_cubics(0, params, coef, lo, hi, [kmin * kmin, q2_asym])
    return RadialProfile(0, params, coef, (lo, hi), fast, stepk, maxk, hlr_factor)


@functools.lru_cache(maxsize=8)
def gaussian_profile(gsparams: GsParams, transformed: bool) -> RadialProfile:
    """The :class:`RadialProfile` of a Gaussian of sigma 1 (``transformed``: sheared)."""
    params = np.zeros(8)
    params[0] = (gsparams.kvalue_accuracy * 48.0) ** (1.0 / 3.0)  # SBGaussian.cpp
    params[1] = -2.0 * math.log(gsparams.kvalue_accuracy)
    kind = -1 if transformed else -2
    lo, hi = -40, _FAST_MAX_OCTAVE
    coef = np.zeros((1, 4))
    fast = _fast_cubics(kind, params, coef, lo, hi, list(params[:2]) if transformed else [])
    return RadialProfile(kind, params, coef, (lo, hi), fast)


def _fast_cubics(
    kind: int, params: np.ndarray, coef: np.ndarray, lo: int, hi: int, breaks: list[float]
) -> np.ndarray:
    """The fast form's cubics (see :class:`RadialProfile`), fitted to the exact form at four
    points of each interval; NaN on the intervals holding a break."""
    per = 1 << FAST_BITS
    idx = np.arange((hi - lo) * per)
    scale = np.ldexp(1.0, lo + idx // per)  # 2^octave
    start = scale * (1.0 + (idx % per) / per)
    width = scale / per
    ts = np.array([0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0])
    q2 = (start[:, None] + ts[None, :] * width[:, None]).ravel()
    eint = np.array([kind, 0, len(coef) - 1, lo, hi, 0], dtype=np.int64)
    vals = radial_values(q2, params, eint, coef, np.zeros((1, 4)), False).reshape(-1, 4)
    fast = vals @ np.linalg.inv(np.vander(ts, 4, increasing=True)).T
    for b in breaks:
        if math.isfinite(b) and b > 0:
            fast[(start <= b) & (b <= start + width)] = np.nan
    return np.ascontiguousarray(fast)


@dataclass
class _PsfInfo:
    psf: Any  # the GalSim profile, or a StoredPsf (built only for a k-image not on disk)
    gsparams: GsParams  # those of the drawing
    stepk: float  # of the PSF alone
    maxk: float
    pixel_stepk: float  # 0 for "no_pixel"
    pixel_maxk: float
    drawn: Any = None  # the PSF (x pixel unless "no_pixel") with the drawing GSParams, or None

    def arrays(self) -> dict[str, np.ndarray]:
        """The summary as named arrays (for the disk cache); see :meth:`from_arrays`."""
        scalars = [self.stepk, self.maxk, self.pixel_stepk, self.pixel_maxk]
        return {
            "gsparams": np.array(self.gsparams.values(), dtype=np.float64),
            "scalars": np.array(scalars, dtype=np.float64),
        }

    @classmethod
    def from_arrays(cls, psf: Any, arrays: Mapping[str, np.ndarray]) -> _PsfInfo:
        """The summary of ``psf`` stored by :meth:`arrays` (its drawn profile not built)."""
        stepk, maxk, pixel_stepk, pixel_maxk = (float(v) for v in arrays["scalars"])
        gsp = GsParams.from_values(arrays["gsparams"])
        return cls(psf, gsp, stepk, maxk, pixel_stepk, pixel_maxk)


class StampRenderer:
    """Draws batches of parametric galaxies convolved with one PSF, as GalSim's drawImage would.

    ``gsparams`` is the config's ``[gsparams]`` table (GSParams keyword arguments); empty
    or None: GalSim's defaults combined with the PSF's own, as ``galsim.Convolve`` does.
    A PSF is a GalSim profile, or a :class:`~megalut_cli.sim.psf_store.StoredPsf` whose
    summary and k-images come from the disk cache (GalSim builds it on a miss).
    """

    def __init__(self, stamp_size: int, gsparams: dict[str, float] | None = None):
        if int(stamp_size) < 1:
            raise MegalutError(f"stamp size must be >= 1, got {stamp_size}")
        self.stamp_size = int(stamp_size)
        self.gsparams = dict(gsparams or {})
        self._gsp = GsParams(**self.gsparams) if self.gsparams else None
        self._psfs: OrderedDict[tuple[Hashable, str], _PsfInfo] = OrderedDict()
        self._kimages: OrderedDict[tuple[Hashable, str, int, int], np.ndarray] = OrderedDict()

    # -- PSF --------------------------------------------------------------------------------
    def _psf_info(self, psf: Any, psf_key: Hashable, method: str) -> _PsfInfo:
        key = (psf_key, method)
        hit = self._psfs.get(key)
        if hit is not None:
            self._psfs.move_to_end(key)
            return hit
        if method not in ("auto", "no_pixel"):
            raise MegalutError(f"renderer: unknown drawing method {method!r} (auto or no_pixel)")
        if isinstance(psf, StoredPsf):
            stored = psf.load(self._stored_name(method))
            if stored is not None:
                info = _PsfInfo.from_arrays(psf, stored)
            else:
                info = self._build_psf_info(psf, method)
                psf.store(self._stored_name(method), info.arrays())
        else:
            info = self._build_psf_info(psf, method)
        self._psfs[key] = info
        while len(self._psfs) > _PSF_CACHE_MAX:
            self._psfs.popitem(last=False)
        return info

    def _stored_name(self, method: str, n_fft: int | None = None, n_k: int | None = None) -> str:
        """What a stored PSF's entry holds: its summary, or its k-image on grid (N, Nk), for
        ``method`` and this renderer's GSParams."""
        what = f"renderer {self._gsp!r} {method}"
        return what if n_fft is None else f"{what} kimage {n_fft} {n_k}"

    def _build_psf_info(self, psf: Any, method: str) -> _PsfInfo:
        """The summary of ``psf`` (a GalSim profile or a StoredPsf, then built), with GalSim."""
        import galsim

        profile = psf.profile() if isinstance(psf, StoredPsf) else psf
        gsp = (
            self._gsp.galsim()
            if self._gsp is not None
            else galsim.GSParams.combine([galsim.GSParams(), profile.gsparams])
        )
        psf_g = profile.withGSParams(gsp)
        if method == "auto":
            pixel = galsim.Pixel(1.0, gsparams=gsp)
            drawn = galsim.Convolve(psf_g, pixel, gsparams=gsp)
            pix_stepk, pix_maxk = float(pixel.stepk), float(pixel.maxk)
        else:
            drawn, pix_stepk, pix_maxk = psf_g, 0.0, math.inf
        return _PsfInfo(
            psf,
            GsParams.of(gsp),
            float(psf_g.stepk),
            float(psf_g.maxk),
            pix_stepk,
            pix_maxk,
            drawn,
        )

    def _psf_kimage(
        self, info: _PsfInfo, psf_key: Hashable, method: str, n_fft: int, n_k: int
    ) -> np.ndarray:
        key = (psf_key, method, n_fft, n_k)
        hit = self._kimages.get(key)
        if hit is not None:
            self._kimages.move_to_end(key)
            return hit
        stored = info.psf if isinstance(info.psf, StoredPsf) else None
        name = self._stored_name(method, n_fft, n_k)
        arrays = stored.load(name) if stored is not None else None
        if arrays is not None:
            kimage = arrays["kimage"]
        else:
            kimage = self._draw_psf_kimage(info, method, n_fft, n_k)
            if stored is not None:
                stored.store(name, {"kimage": kimage})
        self._kimages[key] = kimage
        while (
            len(self._kimages) > 1
            and sum(k.nbytes for k in self._kimages.values()) > _KIMAGE_CACHE_BYTES
        ):
            self._kimages.popitem(last=False)
        return kimage

    def _draw_psf_kimage(self, info: _PsfInfo, method: str, n_fft: int, n_k: int) -> np.ndarray:
        """The PSF (x pixel) k-image on grid (N, Nk), drawn by GalSim."""
        import galsim

        if info.drawn is None:  # a summary from the disk cache
            info.drawn = self._build_psf_info(info.psf, method).drawn
        half = n_k // 2
        image = galsim.ImageCD(galsim.BoundsI(0, half, -half, half), scale=2.0 * np.pi / n_fft)
        info.drawn.drawKImage(image=image, recenter=False)
        kimage = np.ascontiguousarray(image.array, dtype=np.complex64)  # GalSim's own precision
        if not kimage.imag.any():  # centrosymmetric PSF: a real k-image (the fill specialises)
            kimage = np.ascontiguousarray(kimage.real)
        return kimage

    # -- geometry ---------------------------------------------------------------------------
    def _convolved(
        self,
        info: _PsfInfo,
        profile: str,
        rad: np.ndarray,
        sersicn: np.ndarray | None,
        e1: np.ndarray,
        e2: np.ndarray,
        g1: np.ndarray,
        g2: np.ndarray,
    ) -> tuple[Any, ...]:
        """Per-galaxy stepk and maxk of the sheared galaxy convolved with the PSF (no offset,
        no pixel), its Jacobian, and the radial profiles (table, profiles, size)."""
        if not can_render(profile):
            only = ", ".join(fast_profiles())
            raise MegalutError(f"renderer: cannot draw galaxy profile {profile!r} (only {only})")
        rad = np.atleast_1d(np.asarray(rad, dtype=float))
        m = len(rad)
        e1, e2, g1, g2 = (
            np.broadcast_to(np.asarray(v, dtype=float), (m,)) for v in (e1, e2, g1, g2)
        )
        if not (
            np.all(np.isfinite(rad) & (rad > 0))
            and all(np.isfinite(v).all() for v in (e1, e2, g1, g2))
        ):
            raise MegalutError(
                "renderer: half-light radii must be finite and > 0, shapes and offsets finite"
            )
        family = RADIAL_FAMILIES[GALAXY_PROFILES[profile].fast]
        table, profiles, stepk, maxk, size = family(info.gsparams, rad, sersicn, e1, e2, g1, g2)
        jac = _shear_jacobian(e1, e2, g1, g2)
        # Transformation: maxk / minor, stepk / major (galsim/transform.py).
        h1 = np.hypot(jac[:, 0, 0] + jac[:, 1, 1], jac[:, 0, 1] - jac[:, 1, 0])
        h2 = np.hypot(jac[:, 0, 0] - jac[:, 1, 1], jac[:, 0, 1] + jac[:, 1, 0])
        major, minor = 0.5 * np.abs(h1 + h2), 0.5 * np.abs(h1 - h2)
        gal_stepk, gal_maxk = stepk / major, maxk / minor
        # Convolution with the PSF.
        stepk_c = (gal_stepk**-2 + info.stepk**-2) ** -0.5
        maxk_c = np.minimum(gal_maxk, info.maxk)
        return stepk_c, maxk_c, jac, table, profiles, size

    def _geometry(
        self,
        info: _PsfInfo,
        profile: str,
        rad: np.ndarray,
        sersicn: np.ndarray | None,
        e1: np.ndarray,
        e2: np.ndarray,
        g1: np.ndarray,
        g2: np.ndarray,
        dx: np.ndarray,
        dy: np.ndarray,
    ) -> tuple[np.ndarray, ...]:
        """Per-stamp arrays: N, Nk, k-transform matrix, radial-profile index, shifts (the
        offset, centring and S // 2, so that the stamp is the FFT's first S x S pixels);
        and the radial profiles."""
        S = self.stamp_size
        m = len(np.atleast_1d(rad))
        stepk_c, maxk_c, jac, table, profiles, size = self._convolved(
            info, profile, rad, sersicn, e1, e2, g1, g2
        )
        dx, dy = (np.broadcast_to(np.asarray(v, dtype=float), (m,)) for v in (dx, dy))
        if not (np.isfinite(dx).all() and np.isfinite(dy).all()):
            raise MegalutError(
                "renderer: half-light radii must be finite and > 0, shapes and offsets finite"
            )
        # Shift by the offset (+ centring), convolution with the pixel.
        sx = dx - 0.5 if S % 2 == 0 else dx.copy()
        sy = dy - 0.5 if S % 2 == 0 else dy.copy()
        dr = np.hypot(sx, sy)
        shifted = (sx != 0.0) | (sy != 0.0)
        stepk_c = np.where(shifted, math.pi / (math.pi / stepk_c + dr), stepk_c)
        if info.pixel_stepk > 0:
            stepk_c = (stepk_c**-2 + info.pixel_stepk**-2) ** -0.5
            maxk_c = np.minimum(maxk_c, info.pixel_maxk)
        n_fft, n_k = fft_grid(stepk_c, maxk_c, S, info.gsparams)
        # q = |A k| in units of the profile's radius: A = size J^T.
        amat = np.empty((m, 4))
        amat[:, 0], amat[:, 1] = jac[:, 0, 0] * size, jac[:, 1, 0] * size
        amat[:, 2], amat[:, 3] = jac[:, 0, 1] * size, jac[:, 1, 1] * size
        return n_fft, n_k, amat, table.astype(np.int64), sx + S // 2, sy + S // 2, profiles

    def good_image_sizes(
        self, psf: Any, psf_key: Hashable, method: str, profile: str, rad, sersicn, e1, e2, g1, g2
    ) -> np.ndarray:
        """GalSim's ``getGoodImageSize(1)`` of each sheared galaxy convolved with ``psf``
        (no pixel, no offset): the side of the stamp a scene draws it on."""
        info = self._psf_info(psf, psf_key, method)
        stepk_c = self._convolved(info, profile, rad, sersicn, e1, e2, g1, g2)[0]
        n_good = np.ceil(2.0 * np.pi / stepk_c * (1.0 - 1.0e-12)).astype(np.int64)
        return n_good + n_good % 2

    def grid_sizes(
        self,
        psf: Any,
        psf_key: Hashable,
        method: str,
        profile: str,
        rad,
        sersicn,
        e1,
        e2,
        g1,
        g2,
        dx,
        dy,
    ) -> tuple[np.ndarray, np.ndarray]:
        """GalSim's FFT sizes (N, Nk) for these stamps (``drawFFT_makeKImage``)."""
        info = self._psf_info(psf, psf_key, method)
        n_fft, n_k, *_ = self._geometry(info, profile, rad, sersicn, e1, e2, g1, g2, dx, dy)
        return n_fft, n_k

    # -- drawing ----------------------------------------------------------------------------
    def plan(
        self,
        psf: Any,
        psf_key: Hashable,
        method: str,
        profile: str,
        rad,
        flux,
        sersicn,
        e1,
        e2,
        g1,
        g2,
        dx,
        dy,
    ) -> RenderPlan:
        """What :meth:`draw` computes on the host before filling k-images (arguments as there):
        per-stamp grids, transforms, fluxes, shifts and the radial profiles; checked."""
        info = self._psf_info(psf, psf_key, method)
        n_fft, n_k, amat, table, shx, shy, profiles = self._geometry(
            info, profile, rad, sersicn, e1, e2, g1, g2, dx, dy
        )
        m = len(n_fft)
        flux = np.broadcast_to(np.asarray(flux, dtype=float), (m,))
        if not np.isfinite(flux).all():
            raise MegalutError("renderer: fluxes must be finite")
        too_big = n_k > info.gsparams.maximum_fft_size
        if too_big.any():
            size = int(n_k[too_big].max())
            raise MegalutError(
                f"drawFFT requires a very large FFT: the required FFT size would be {size} x "
                f"{size}, which requires {size * size * 24 / 1024**3:.2f} GB of memory; if you can "
                "handle the large FFT, you may update gsparams.maximum_fft_size "
                f"(now {info.gsparams.maximum_fft_size}), or raise gsparams.folding_threshold"
            )
        return RenderPlan(n_fft, n_k, amat, table, shx, shy, np.array(flux), profiles)

    def psf_kimage(
        self, psf: Any, psf_key: Hashable, method: str, n_fft: int, n_k: int
    ) -> np.ndarray:
        """The PSF (x pixel) k-image on GalSim's (Nk+1) x (Nk/2+1) grid for FFT size N
        (complex64, or float32 when real), cached per renderer."""
        return self._psf_kimage(
            self._psf_info(psf, psf_key, method), psf_key, method, int(n_fft), int(n_k)
        )

    def draw(
        self,
        psf: Any,
        psf_key: Hashable,
        method: str,
        profile: str,
        rad,
        flux,
        sersicn,
        e1,
        e2,
        g1,
        g2,
        dx,
        dy,
    ) -> np.ndarray:
        """Noiseless stamps (m, S, S) float32 of ``profile`` galaxies of half-light radius
        ``rad`` (pixels), ``flux``, index ``sersicn`` (None for Gaussians), intrinsic shape
        (e1, e2) then shear (g1, g2), offset (dx, dy) pixels from the stamp centre, convolved
        with ``psf`` (and the pixel unless ``method`` is "no_pixel").

        ``psf_key`` names the PSF for the caches: pass the same key only for the same PSF.
        """
        p = self.plan(psf, psf_key, method, profile, rad, flux, sersicn, e1, e2, g1, g2, dx, dy)
        n_fft, n_k, amat, table, shx, shy, flux = (
            p.n_fft,
            p.n_k,
            p.amat,
            p.table,
            p.shift_x,
            p.shift_y,
            p.flux,
        )
        m = len(n_fft)
        S = self.stamp_size
        if m == 0:
            return np.empty((0, S, S), dtype=np.float32)
        eparams, eint, coef, fcoef = _stack(p.profiles)
        stamps = np.empty((m, S, S), dtype=np.float32)
        grids = np.stack([n_fft, n_k], axis=1)
        for n_f, n_kk in np.unique(grids, axis=0):
            idx = np.flatnonzero((n_fft == n_f) & (n_k == n_kk))
            kpsf = self.psf_kimage(psf, psf_key, method, int(n_f), int(n_kk))
            per = int(n_f) * (int(n_f) // 2 + 1) * 8
            batch = max(1, min(MAX_BATCH, BATCH_BYTES // per))
            buf = np.empty((min(batch, len(idx)), int(n_f), int(n_f) // 2 + 1), dtype=np.complex64)
            for a in range(0, len(idx), batch):
                sel = idx[a : a + batch]
                kbuf = buf[: len(sel)]
                fill_kimages(
                    kbuf,
                    kpsf,
                    kpsf.dtype == np.float32,
                    int(n_f),
                    int(n_kk),
                    2.0 * np.pi / int(n_f),
                    amat[sel],
                    flux[sel],
                    shx[sel],
                    shy[sel],
                    table[sel],
                    eparams,
                    eint,
                    coef,
                    fcoef,
                )
                stamps[sel] = inverse_fft_window(kbuf, int(n_f), S)
        return stamps


class RadialSet(NamedTuple):
    """The radial k-profiles of a batch of galaxies (:class:`RadialProfile`): each stamp's
    index in ``profiles``, their stepk and maxk (pixels^-1, per stamp or one for all) and the
    radius (pixels) that q is measured in."""

    table: np.ndarray
    profiles: list[RadialProfile]
    stepk: np.ndarray | float
    maxk: np.ndarray | float
    size: np.ndarray


def sersic_radials(
    gsp: GsParams,
    rad: np.ndarray,
    sersicn: np.ndarray | None,
    e1: np.ndarray,
    e2: np.ndarray,
    g1: np.ndarray,
    g2: np.ndarray,
) -> RadialSet:
    """Sersic galaxies of half-light radii ``rad``, indices ``sersicn`` (a table per index)."""
    if sersicn is None:
        raise MegalutError("renderer: Sersic galaxies need sersicn")
    ns = np.broadcast_to(np.asarray(sersicn, dtype=float), rad.shape)
    uniq, table = np.unique(ns, return_inverse=True)
    profiles = [sersic_table(float(n), gsp) for n in uniq]
    hlr_factor = np.array([t.hlr_factor for t in profiles])[table]
    r0 = rad / hlr_factor  # Sersic scale radius, as galsim.Sersic computes it
    inv_r0 = 1.0 / r0
    stepk = np.array([t.stepk for t in profiles])[table] * inv_r0
    maxk = np.array([t.maxk for t in profiles])[table] * inv_r0
    return RadialSet(table, profiles, stepk, maxk, r0)


def gaussian_radials(
    gsp: GsParams,
    rad: np.ndarray,
    sersicn: np.ndarray | None,
    e1: np.ndarray,
    e2: np.ndarray,
    g1: np.ndarray,
    g2: np.ndarray,
) -> RadialSet:
    """Gaussian galaxies of half-light radii ``rad``: round ones are filled separably (exact
    exp), transformed ones with GalSim's cutoffs."""
    table = np.where((e1 == 0) & (e2 == 0) & (g1 == 0) & (g2 == 0), 1, 0)
    profiles = [gaussian_profile(gsp, True), gaussian_profile(gsp, False)]
    sigma = rad / _GAUSSIAN_HLR_FACTOR
    r_fold = max(
        math.sqrt(-2.0 * math.log(gsp.folding_threshold)),
        gsp.stepk_minimum_hlr * _GAUSSIAN_HLR_FACTOR,
    )
    maxk = math.sqrt(-2.0 * math.log(gsp.maxk_threshold)) / sigma
    stepk = math.pi / (r_fold * sigma)
    return RadialSet(table, profiles, stepk, maxk, sigma)


#: The radial families of the renderer, by the name a galaxy profile's ``fast`` gives.
RADIAL_FAMILIES = {"sersic": sersic_radials, "gaussian": gaussian_radials}


@dataclass(frozen=True)
class RenderPlan:
    """Per-stamp inputs of the k-image fill (:meth:`StampRenderer.plan`): FFT size N and
    k-grid size Nk, the k-transform ``amat`` (m, 4: q = A k in units of the profile's
    radius), the index of each stamp's radial profile in ``profiles``, the shifts (offset,
    centring and S // 2, in pixels) and the fluxes."""

    n_fft: np.ndarray
    n_k: np.ndarray
    amat: np.ndarray
    table: np.ndarray
    shift_x: np.ndarray
    shift_y: np.ndarray
    flux: np.ndarray
    profiles: list[RadialProfile]


def stack_profiles(
    profiles: list[RadialProfile],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Radial profiles as flat arrays: exact params (T, 8), integers (T, 6: kind, first and
    last exact cubic, fast octaves lo and hi, first fast cubic), exact cubics, fast cubics."""
    return _stack(profiles)


def inverse_fft_window(kimages: np.ndarray, n_fft: int, size: int) -> np.ndarray:
    """The first ``size`` x ``size`` pixels of the inverse real FFTs of ``kimages`` (m, N,
    N/2+1, complex64; overwritten): the y transform, in place, keeps only ``size`` rows
    before the x transform. numpy's pocketfft, in single precision: the bits of SciPy's
    (``scipy.fft``, which the renderer used before; a test checks it) without its 0.1 s
    import."""
    np.fft.ifft(kimages, axis=1, out=kimages)
    return np.fft.irfft(kimages[:, :size, :], n=n_fft, axis=2)[:, :, :size]


def fft_grid(
    stepk: np.ndarray, maxk: np.ndarray, stamp_size: int, gsparams: GsParams | Any
) -> tuple[np.ndarray, np.ndarray]:
    """GalSim's FFT sizes (N, Nk) for profiles of ``stepk``, ``maxk`` (pixel scale 1) drawn
    on a ``stamp_size`` image (``GSObject.getGoodImageSize``, ``drawFFT_makeKImage``)."""
    stepk = np.asarray(stepk, dtype=float)
    n_good = np.ceil(2.0 * np.pi / stepk * (1.0 - 1.0e-12)).astype(np.int64)
    n_good = 2 * ((n_good + 1) // 2)
    n_good = np.maximum(n_good, stamp_size)  # the image itself: 2 max|bounds| or its size
    uniq, inv = np.unique(n_good, return_inverse=True)
    good = np.array([good_fft_size(int(v)) for v in uniq], dtype=np.int64)
    n_fft = np.maximum(good[inv], int(gsparams.minimum_fft_size))
    dk = 2.0 * np.pi / n_fft
    maxk = np.broadcast_to(np.asarray(maxk, dtype=float), n_fft.shape)
    with np.errstate(over="ignore", invalid="ignore"):
        n_k = np.where(n_fft * dk / 2 > maxk, n_fft, np.ceil(maxk / dk).astype(np.int64) * 2)
    return n_fft.reshape(stepk.shape), n_k.reshape(stepk.shape)


def _shear_jacobian(e1: np.ndarray, e2: np.ndarray, g1: np.ndarray, g2: np.ndarray) -> np.ndarray:
    """(m, 2, 2) Jacobians of shear (e1, e2) then shear (g1, g2), as GalSim composes them."""
    je, jg = _shear_matrix(e1, e2), _shear_matrix(g1, g2)
    jac = np.einsum("mij,mjk->mik", jg, je)
    only_e = (g1 == 0) & (g2 == 0)
    jac[only_e] = je[only_e]
    only_g = (e1 == 0) & (e2 == 0)
    jac[only_g] = jg[only_g]
    return jac


def _shear_matrix(g1: np.ndarray, g2: np.ndarray) -> np.ndarray:
    """``galsim.Shear(g1=g1, g2=g2).getMatrix()`` for arrays (identity where g = 0)."""
    g = np.abs(g1 + 1j * g2)
    if np.any(g >= 1.0):
        raise MegalutError(
            f"renderer: shear or ellipticity modulus must be < 1, got {float(g.max())}"
        )
    norm = np.sqrt(1.0 - g**2)
    mat = np.empty((len(g1), 2, 2))
    mat[:, 0, 0] = (1.0 + g1) / norm
    mat[:, 0, 1] = g2 / norm
    mat[:, 1, 0] = g2 / norm
    mat[:, 1, 1] = (1.0 - g1) / norm
    return mat


def _stack(profiles: list[RadialProfile]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Radial profiles as flat arrays for the numba kernels: exact params (T, 8), integers
    (T, 6: kind, first and last exact cubic, fast octaves lo and hi, first fast cubic),
    exact cubics, fast cubics."""
    eparams = np.stack([p.params for p in profiles])
    sizes = np.array([len(p.coef) for p in profiles])
    fsizes = np.array([len(p.fast) for p in profiles])
    first = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    ffirst = np.concatenate([[0], np.cumsum(fsizes)[:-1]])
    eint = np.array(
        [
            [p.kind, first[k], first[k] + sizes[k] - 1, p.octaves[0], p.octaves[1], ffirst[k]]
            for k, p in enumerate(profiles)
        ],
        dtype=np.int64,
    )
    return (
        eparams,
        eint,
        np.concatenate([p.coef for p in profiles]),
        np.concatenate([p.fast for p in profiles]),
    )
