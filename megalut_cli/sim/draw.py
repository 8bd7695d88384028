"""Drawing a work unit: a contiguous chunk of cases, in any process.

:func:`draw_unit` is the top-level function mapped over workers. It draws every stamp of
its cases (galaxy convolved with the PSF, pixel response included, centred on the stamp
centre plus the sub-pixel offset), adds the noise seeded per (case, realization), and
returns the truth columns, plus the measured features (``measure``) and/or the stamps
(``keep_stamps``). With the ``fast`` engine the stamps of a case are rendered in batches
(:mod:`megalut_cli.sim.render`) and the noise is added with numpy; with ``galsim`` (and for
galaxies the fast renderer does not cover) GalSim draws them one by one, reusing profiles
within a case and image buffers between stamps.

GalSim, and the modules that load it (galaxies, twins, metacal), are imported by the
functions of the GalSim engine and of metacal, not with this module: a fast-engine run with
a PSF kept in the disk cache (:mod:`megalut_cli.sim.psf_store`) does not load them.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from megalut_cli.engine import DEFAULT_DEVICE, DEFAULT_ENGINE, device_backend
from megalut_cli.errors import MegalutError
from megalut_cli.measure.measurer import (
    Measurer,
    MeasureSettings,
    MetacalSettings,
    PsfImages,
    StampBatch,
    twin_fixnoise,
)
from megalut_cli.sim import psf as psf_mod
from megalut_cli.sim import render
from megalut_cli.sim.config import SimConfig
from megalut_cli.sim.gsparams import GsParams
from megalut_cli.sim.profiles import GALAXY_PROFILES
from megalut_cli.sim.psf import make_psf
from megalut_cli.sim.psf_store import StoredPsf, stored_psf, stores_psf
from megalut_cli.sim.structure import draw_case

if TYPE_CHECKING:
    import galsim

#: Stamps measured at once when the images are not kept (bounds the memory of a unit).
MEASURE_BATCH = 1024
#: The fast engine renders a case in blocks of at most this many realizations, so that a
#: worker's memory does not grow with ``n_realizations`` (16 KB per 64-px stamp).
CASE_BLOCK = 8 * MEASURE_BATCH

_PSF_CACHE: dict[str, tuple[galsim.GSObject, dict[str, float]]] = {}
_PSF_CACHE_MAX = 512


@dataclass(frozen=True)
class WorkUnit:
    """Plain, picklable description of a chunk of cases to draw."""

    config: SimConfig
    seed: int
    case_start: int
    case_stop: int
    n_x: int
    keep_stamps: bool = False
    measure: bool = False
    engine: str = DEFAULT_ENGINE
    feature_sets: tuple[str, ...] = ()  # with measure: the optional feature sets measured too
    device: str = DEFAULT_DEVICE  # "cpu" or "gpu" (resolved): where the fast engine runs
    metacal_step: float | None = (
        None  # with measure: also the metacal features (measure/metacal.py)
    )
    moments_retry: float = 0.0  # with measure: the moments' damped retry (0: none)

    @property
    def renders_fast(self) -> bool:
        """Whether this unit's stamps go through the batched renderer."""
        return self.engine == "fast" and renders_galaxies(self.config)


def renders_galaxies(config: SimConfig) -> bool:
    """Whether the fast renderer draws this config's galaxies: a single Sersic or Gaussian
    (knots or any other model go through GalSim)."""
    return render.can_render(config.galaxy.profile) and not config.galaxy.knots


def psf_includes_pixel(spec: dict[str, Any]) -> bool:
    """Whether the PSF profile already holds the pixel response (then draw with no_pixel)."""
    return bool(psf_mod.psf_includes_pixel(spec))


def get_psf(
    spec: dict[str, Any],
    field_x: float,
    field_y: float,
    varies: bool,
    gsparams: dict[str, float] | None = None,
) -> tuple[galsim.GSObject, dict[str, float]]:
    """The PSF (pixel units) and its truth, cached per process (PSFs can be costly)."""
    key = psf_cache_key(spec, field_x, field_y, varies, gsparams)
    hit = _PSF_CACHE.get(key)
    if hit is None:
        if len(_PSF_CACHE) >= _PSF_CACHE_MAX:
            _PSF_CACHE.clear()
        set_up_galsim()
        psf, truth = make_psf(spec, field_x, field_y)
        if gsparams:
            psf = psf.withGSParams(GsParams(**gsparams).galsim())
        hit = _PSF_CACHE[key] = (psf, dict(truth))
    return hit


def psf_cache_key(
    spec: dict[str, Any],
    field_x: float,
    field_y: float,
    varies: bool,
    gsparams: dict[str, float] | None = None,
) -> str:
    """A string that names one PSF: its spec, GSParams and (for a variable PSF) field position."""
    key = json.dumps([spec, gsparams or {}], sort_keys=True, default=str)
    if varies:
        key += f"|{field_x!r}|{field_y!r}"
    return key


def stamp_origins(index: np.ndarray, n_x: int, stamp_size: int) -> np.ndarray:
    """FITS 1-based (x, y) of the lower-left pixel of grid stamps ``index``."""
    index = np.asarray(index, dtype=np.int64)
    return np.stack(
        [(index % n_x) * stamp_size + 1, (index // n_x) * stamp_size + 1], axis=1
    ).astype(float)


def grid_stamp_centres(
    index: np.ndarray, n_x: int, stamp_size: int
) -> tuple[np.ndarray, np.ndarray]:
    """FITS 1-based (x, y) centres of grid stamps ``index``."""
    o = stamp_origins(index, n_x, stamp_size)
    half = (stamp_size - 1) / 2.0
    return o[:, 0] + half, o[:, 1] + half


class _Measurer:
    """Accumulates stamps and measures them in batches (:class:`~megalut_cli.measure.measurer.
    Measurer`; with ``unit.metacal_step``, also their metacal versions, deconvolved by the PSF
    image each stamp was drawn with)."""

    def __init__(self, unit: WorkUnit):
        metacal = (
            None if unit.metacal_step is None else MetacalSettings(unit.metacal_step, unit.seed)
        )
        self.measurer = Measurer(
            MeasureSettings(
                unit.config.gain,
                unit.engine,
                unit.device,
                unit.feature_sets,
                metacal,
                unit.moments_retry,
            )
        )
        s = unit.config.structure
        self.common, self.n_rea = bool(s.common), s.n_realizations
        self.antithetic = bool(s.antithetic)
        self.size = s.stamp_size
        self.parts: list[dict[str, np.ndarray]] = []
        self.psf_images: dict[int, np.ndarray] = {}  # id -> PSF image (with the pixel, as drawn)

    def psf_id(self, psf: Any, method: str, key: Any) -> int:
        """An id of the PSF ``psf`` (drawn with ``method``; a GalSim profile or a
        :class:`StoredPsf`), its image stored for metacal."""
        pid = hash((key, method)) & 0x7FFFFFFF
        if self.measurer.settings.metacal is not None and pid not in self.psf_images:
            size = self.size
            if isinstance(psf, StoredPsf):
                psf = psf.profile()
            self.psf_images[pid] = psf.drawImage(
                nx=size, ny=size, scale=1.0, method=method
            ).array.astype(np.float64)
        return pid

    def __call__(
        self,
        stamps: np.ndarray,
        origins: np.ndarray,
        index: np.ndarray | None = None,
        psf_ids: np.ndarray | None = None,
    ) -> None:
        if not len(stamps):
            return
        psfs = keys = signs = None
        if self.measurer.settings.metacal is not None and index is not None and psf_ids is not None:
            ids = np.unique(psf_ids)
            images = np.stack([self.psf_images[int(i)] for i in ids])
            psfs = PsfImages(images, np.searchsorted(ids, psf_ids), columns=False)
            keys = index % self.n_rea if self.common else index
            if self.antithetic:  # twins 2k, 2k+1: the field of the half-size set's k, signed
                keys, signs = twin_fixnoise(keys, index % self.n_rea)
        self.parts.append(
            self.measurer.measure(
                StampBatch(stamps, origins, psfs=psfs, fixnoise_keys=keys, fixnoise_signs=signs)
            )
        )

    def columns(self) -> dict[str, np.ndarray]:
        if not self.parts:
            return {}
        names = list(self.parts[0])
        return {k: np.concatenate([p[k] for p in self.parts]) for k in names}


def set_up_galsim() -> None:
    """Import GalSim with one OpenMP thread (its threads only slow small stamps down: busy
    waiting on shared cores, noise generation measured 10-50x slower; parallelism is across
    work units), and with FFTs beyond ``gsparams.maximum_fft_size`` an error, as they were
    before GalSim 2.7 and are in the fast engine (GalSim 2.7+ only warns, and draws)."""
    global _THREADS_SET
    if not _THREADS_SET:
        import galsim

        galsim.set_omp_threads(1)
        galsim.errors.raise_fft_size_error = True
        _THREADS_SET = True


def fft_too_large(err: Any) -> str:
    """One line for GalSim's ``GalSimFFTSizeError`` ``err``, with the fix."""
    return (
        f"FFT too large for GalSim ({err.size}^2 pixels); raise gsparams.maximum_fft_size "
        "or gsparams.folding_threshold"
    )


_THREADS_SET = False


def real_pad_pixels(stamp_size: int) -> float:
    """Side (pixels) over which a real galaxy's HST noise is padded in a stamp of
    ``stamp_size``: the stamp's diagonal, whatever the galaxy's rotation, plus a margin."""
    return 1.5 * stamp_size + 4.0


def wide_draw_size(stamp_size: int, padded_side: float, shear: float, psf: galsim.GSObject) -> int:
    """Side of the image a real galaxy padded over a square of ``padded_side`` pixels is drawn
    into, so that the FFT's period keeps the padding's periodic copies out of the stamp: the
    padding rotated (at most its half-diagonal), sheared by ``shear`` and blurred by the PSF
    (the radius GalSim folds it at) reaches ``reach``; its copy one period away must stay
    beyond the stamp's half side (and the sub-pixel offset)."""
    import galsim

    reach = padded_side / np.sqrt(2.0) / (1.0 - abs(shear)) + np.pi / psf.stepk
    return galsim.Image.good_fft_size(int(np.ceil(reach + 0.5 * stamp_size + 1.0)))


def draw_wide(
    obj: galsim.GSObject,
    image: galsim.Image,
    offset: tuple[float, float],
    method: str,
    size: int,
) -> galsim.Image:
    """``obj.drawImage(image=image, offset=offset, method=method)``, but with an FFT period of
    at least ``size`` pixels: drawn into a ``size``-wide image around the same centre, whose
    middle is copied into ``image``. GalSim chooses the period from the profile's ``stepk``,
    which for a noise-padded real galaxy is that of the unpadded cutout (issue 39)."""
    import galsim

    b = image.bounds
    grow = max(0, (size - min(b.xmax - b.xmin + 1, b.ymax - b.ymin + 1) + 1) // 2)
    if not grow:
        return obj.drawImage(image=image, offset=offset, method=method)
    wide = galsim.ImageF(b.withBorder(grow), scale=image.scale)
    obj.drawImage(image=wide, offset=offset, method=method, center=image.true_center)
    image.copyFrom(wide[b])
    return image


#: Fewest padding-only pixels of a stamp to measure the variance of its HST noise on.
_MIN_PAD_PIXELS = 200


def _process_hst_noise(
    image: galsim.Image,
    clean: np.ndarray,
    d: Any,
    k: int,
    t: dict[str, np.ndarray],
    real: dict[str, Any],
    psf: galsim.GSObject,
    psf_sigma: float,
    method: str,
    gsp: galsim.GSParams,
    mode: str,
    twin: galsim.GSObject | None = None,
) -> float:
    """Symmetrize (order 4) or whiten the HST noise of a drawn real galaxy, then add Gaussian
    noise up to the case's sigma; returns the variance of the processed HST noise
    (``tru_hst_noise_var``; above sigma^2 no Gaussian noise is added).

    ``clean`` is the same galaxy drawn without noise padding: outside its HST footprint
    (plus 3 PSF sigmas), ``image - clean`` is pure padding noise, whose variance calibrates
    the noise model (its shape comes from :func:`megalut_cli.sim.galaxies.real_noise`).
    With ``twin`` (its Sérsic twin, PSF-convolved), the twin replaces the galaxy and gets a
    fresh realization of that noise model before the same symmetrization and Gaussian noise.
    """
    import galsim

    from megalut_cli.sim.galaxies import real_footprint, real_noise

    seed = int(d.noise_seeds[k])
    index = int(t["tru_real_index"][k])
    kernel = psf if method == "no_pixel" else galsim.Convolve(psf, galsim.Pixel(1.0))
    cn = real_noise(
        real,
        index,
        t["tru_flux"][k],
        d.extra["theta"][k],
        t["tru_g1"][k],
        t["tru_g2"][k],
        kernel,
        (seed * 69069 + 1) % 2147483647 + 1,
        gsp,
    )
    n = image.array.shape[0]
    yy, xx = np.mgrid[:n, :n] - (n - 1) / 2.0
    r_fp = real_footprint(real, index) + 3.0 * psf_sigma + 2.0
    outside = np.hypot(xx - d.offsets[k, 0], yy - d.offsets[k, 1]) > r_fp
    if outside.sum() >= _MIN_PAD_PIXELS:
        v = float(np.var((image.array - clean)[outside].astype(np.float64)))
        if v > 0:
            cn = cn.withVariance(v)
    if twin is not None:
        twin.drawImage(image=image, offset=(d.offsets[k, 0], d.offsets[k, 1]), method=method)
        image.addNoise(cn.copy(rng=galsim.BaseDeviate((seed * 48271 + 7) % 2147483647 + 1)))
    var = float(cn.whitenImage(image) if mode == "whiten" else cn.symmetrizeImage(image, order=4))
    rest = d.noise.sky_sigma**2 - var
    if rest > 0:
        image.addNoise(galsim.GaussianNoise(galsim.BaseDeviate(seed), sigma=float(np.sqrt(rest))))
    return var


def draw_unit(unit: WorkUnit) -> dict[str, Any]:
    """Draw (and measure) the cases ``[case_start, case_stop)`` of ``unit``.

    Returns ``{"columns": {name: array}, "stamps": array (n, S, S) or None}`` with one
    row per stamp, ordered by case then realization.
    """
    if unit.renders_fast and (unit.keep_stamps or unit.measure):
        return draw_unit_fast(unit)
    set_up_galsim()
    import galsim

    from megalut_cli.sim.galaxies import make_gsparams, oriented, real_padded_side, rotated
    from megalut_cli.sim.twins import real_twin, twin_truth

    cfg = unit.config
    s = cfg.structure
    S, n_rea = s.stamp_size, s.n_realizations
    n_cases = unit.case_stop - unit.case_start
    n_total = n_cases * n_rea
    first = unit.case_start * n_rea
    gal = cfg.galaxy
    profile = GALAXY_PROFILES[gal.profile]

    keep = unit.keep_stamps
    render = keep or unit.measure  # else: truth only, nothing to draw
    nbuf = n_total if keep else (min(MEASURE_BATCH, n_total) if unit.measure else 0)
    stamps = np.empty((max(nbuf, 1), S, S), dtype=np.float32)
    psf_ids = np.zeros(max(nbuf, 1), dtype=np.int64)  # the PSF of each buffered stamp (metacal)
    measurer = _Measurer(unit) if unit.measure else None
    image = galsim.ImageF(S, S, scale=1.0)
    gsp = make_gsparams(cfg.gsparams)
    conv_gsp = gsp if cfg.gsparams else None  # else GalSim combines the components' own

    truth_parts: list[dict[str, np.ndarray]] = []
    # Real galaxies: pad with HST noise over the stamp, symmetrize (or whiten) it, add the
    # rest of the noise.
    hst_mode = gal.real.get("hst_noise", "keep") if gal.real is not None and render else "keep"
    if cfg.noise.type == "none" and cfg.noise.override_sigma is None:
        hst_mode = "keep"  # noiseless stamps: the HST noise stays in the galaxy's own footprint
    pad = real_pad_pixels(S) if hst_mode != "keep" else 0.0
    scratch = galsim.ImageF(S, S, scale=1.0)
    base0 = twin_base = None
    padded = 0.0  # side of the current real galaxy's noise padding (pixels)
    twin_mode = gal.real is not None and render and gal.real.get("twin", "none") != "none"
    fill = 0  # stamps in the buffer
    buf_first = first  # global index of stamps[0]
    for case in range(unit.case_start, unit.case_stop):
        d = draw_case(cfg, unit.seed, case)
        t = d.truth
        hst_var = np.zeros(n_rea) if hst_mode != "keep" else None
        psf_truths: list[dict[str, float]] = []  # one per PSF draw (psf_index order)
        last_gal, last_psf = -1, -1
        base = psf = None
        for k in range(n_rea):
            gi = int(d.galaxy_index[k])
            if gi != last_gal and render:
                base = profile.build(gal, t, k, gsp, pad)
                if pad:  # the same galaxy without its noise padding
                    base0 = profile.build(gal, t, k, gsp, 0.0)
                    padded = real_padded_side(gal.real, int(t["tru_real_index"][k]), pad)
                if twin_mode:  # its Sersic twin, drawn in its place (docs/realgal.md)
                    index = int(t["tru_real_index"][k])
                    twin_base = real_twin(gal.real, index, t["tru_flux"][k], gsp)
                last_gal = gi
            pi = int(d.psf_index[k])
            if pi != last_psf:
                spec, fx, fy = d.psf_specs[pi]
                psf, ptruth = get_psf(spec, fx, fy, cfg.psf_varies, cfg.gsparams)
                # A star-image PSF already holds the pixel response.
                method = "no_pixel" if psf_includes_pixel(spec) else "auto"
                psf_truths.append(ptruth)
                last_psf = pi
                pid = (
                    measurer.psf_id(
                        psf, method, psf_cache_key(spec, fx, fy, cfg.psf_varies, cfg.gsparams)
                    )
                    if measurer is not None and render
                    else 0
                )
            if not render:
                continue
            hst_k = hst_var is not None and d.noise.kind != "none"
            # (a real galaxy's twin replaces it here, or after the HST-noise measurement)
            shown = twin_base if twin_mode and not hst_k else base
            gal_k = oriented(shown, t, k, d.extra["theta"][k])
            obj = galsim.Convolve(gal_k, psf, gsparams=conv_gsp)
            offset = (d.offsets[k, 0], d.offsets[k, 1])
            # a noise-padded galaxy: an FFT period wide enough for its padding
            wide = (
                wide_draw_size(S, padded, np.hypot(t["tru_g1"][k], t["tru_g2"][k]), psf)
                if pad and shown is base
                else S
            )
            try:
                draw_wide(obj, image, offset, method, wide)
            except galsim.GalSimFFTSizeError as err:
                raise MegalutError(f"case {case}, realization {k}: {fft_too_large(err)}") from None
            except (galsim.GalSimError, MemoryError) as err:
                raise MegalutError(
                    f"case {case}, realization {k}: GalSim could not draw the stamp ({err})"
                ) from None
            if hst_k:
                clean = draw_wide(  # drawn like the padded galaxy
                    galsim.Convolve(
                        rotated(base0, d.extra["theta"][k], t["tru_g1"][k], t["tru_g2"][k]),
                        psf,
                        gsparams=conv_gsp,
                    ),
                    scratch,
                    offset,
                    method,
                    wide,
                ).array
                twin_k = (
                    None
                    if twin_base is None
                    else galsim.Convolve(
                        rotated(twin_base, d.extra["theta"][k], t["tru_g1"][k], t["tru_g2"][k]),
                        psf,
                        gsparams=conv_gsp,
                    )
                )
                hst_var[k] = _process_hst_noise(
                    image,
                    clean,
                    d,
                    k,
                    t,
                    gal.real,
                    psf,
                    psf_truths[-1]["tru_psf_sigma"],
                    method,
                    gsp,
                    hst_mode,
                    twin_k,
                )
            else:
                d.noise.add(
                    image, int(d.noise_seeds[k]), 1.0 if d.noise_signs is None else d.noise_signs[k]
                )
            stamps[fill] = image.array
            psf_ids[fill] = pid
            fill += 1
            if not keep and measurer is not None and fill == nbuf:
                idx = np.arange(buf_first, buf_first + fill)
                measurer(stamps[:fill], stamp_origins(idx, unit.n_x, S), idx, psf_ids[:fill])
                buf_first += fill
                fill = 0
        cols = case_columns(d, psf_truths)
        if hst_var is not None:
            cols["tru_hst_noise_var"] = hst_var
        if gal.real is not None and "twin_catalog" in gal.real:
            cols.update(twin_truth(gal.real, t["tru_real_index"]))
        truth_parts.append(cols)

    if measurer is not None and fill:
        idx = np.arange(buf_first, buf_first + fill)
        if keep:
            for a in range(0, fill, MEASURE_BATCH):
                b = min(a + MEASURE_BATCH, fill)
                measurer(stamps[a:b], stamp_origins(idx[a:b], unit.n_x, S), idx[a:b], psf_ids[a:b])
        else:
            measurer(stamps[:fill], stamp_origins(idx, unit.n_x, S), idx, psf_ids[:fill])
    columns = (
        {k: np.concatenate([p[k] for p in truth_parts]) for k in truth_parts[0]}
        if truth_parts
        else {}
    )
    if measurer is not None:
        columns.update(measurer.columns())
    return {"columns": columns, "stamps": stamps[:n_total] if keep else None}


@dataclass(frozen=True)
class CasePsf:
    """One PSF of a drawn case, as the batched renderers take it."""

    psf: Any  # the GalSim object, or a StoredPsf
    key: str  # psf_cache_key: the renderer's cache of PSF k-images
    method: str  # GalSim drawing method ("no_pixel" when the PSF includes the pixel)
    rows: np.ndarray  # the realizations of the case drawn with it
    truth: dict[str, float]  # its truth columns


def case_psfs(cfg: Any, d: Any) -> list[CasePsf]:
    """The PSFs of the drawn case ``d``, in ``d.psf_index`` order: :class:`StoredPsf` where
    the run's PSF is kept in the disk cache (:func:`stores_psf`), else GalSim profiles."""
    out = []
    stored = stores_psf(cfg.psf, cfg.psf_varies)
    for pi, (spec, fx, fy) in enumerate(d.psf_specs):
        key = psf_cache_key(spec, fx, fy, cfg.psf_varies, cfg.gsparams)
        if stored:
            build = functools.partial(get_psf, spec, fx, fy, cfg.psf_varies, cfg.gsparams)
            psf = stored_psf(key, build)
            ptruth = psf.truth()
        else:
            psf, ptruth = get_psf(spec, fx, fy, cfg.psf_varies, cfg.gsparams)
        method = "no_pixel" if psf_includes_pixel(spec) else "auto"
        out.append(CasePsf(psf, key, method, np.flatnonzero(d.psf_index == pi), ptruth))
    return out


def stamp_parameters(d: Any, rows: np.ndarray) -> tuple[Any, ...]:
    """The per-stamp arguments of the batched renderers for the realizations ``rows`` of the
    drawn case ``d``: rad, flux, sersicn (or None), e1, e2, g1, g2, dx, dy."""
    t = d.truth
    return (
        t["tru_rad"][rows],
        t["tru_flux"][rows],
        t["tru_sersicn"][rows] if "tru_sersicn" in t else None,
        t["tru_e1"][rows],
        t["tru_e2"][rows],
        t["tru_g1"][rows],
        t["tru_g2"][rows],
        d.offsets[rows, 0],
        d.offsets[rows, 1],
    )


def case_columns(d: Any, psf_truths: list[dict[str, float]]) -> dict[str, np.ndarray]:
    """The catalog columns of one drawn case: ``case, rea``, its truth and its PSF truth."""
    n_rea = len(d.noise_seeds)
    cols: dict[str, np.ndarray] = {
        "case": np.full(n_rea, d.case, dtype=np.int64),
        "rea": np.arange(n_rea, dtype=np.int64),
    }
    cols.update(d.truth)
    for name in psf_truths[0]:
        cols[name] = np.array([p[name] for p in psf_truths], dtype=float)[d.psf_index]
    return cols


_RENDERERS: dict[str, render.StampRenderer] = {}


def stamp_renderer(stamp_size: int, gsparams: dict[str, float]) -> render.StampRenderer:
    """The batched renderer of this process for a stamp size and GSParams (its caches are kept)."""
    key = json.dumps([stamp_size, gsparams], sort_keys=True)
    if key not in _RENDERERS:
        _RENDERERS[key] = render.StampRenderer(stamp_size, gsparams)
    return _RENDERERS[key]


def draw_unit_fast(unit: WorkUnit) -> dict[str, Any]:
    """:func:`draw_unit` with the fast engine: each case's stamps of one PSF rendered in one
    batch, noise added in bulk, features measured :data:`MEASURE_BATCH` stamps at a time
    (on the device with ``unit.device == "gpu"``: :func:`megalut_cli.engine.device_backend`)."""
    if unit.device == "gpu":
        return device_backend().draw_unit(unit)
    cfg = unit.config
    s = cfg.structure
    S, n_rea = s.stamp_size, s.n_realizations
    gal = cfg.galaxy
    if cfg.noise.type == "correlated":  # GalSim draws it (StampNoise.add_batch)
        set_up_galsim()
    renderer = stamp_renderer(S, dict(cfg.gsparams))
    measurer = _Measurer(unit) if unit.measure else None
    kept: list[np.ndarray] = []
    pending: list[np.ndarray] = []  # rendered stamps not yet measured
    pending_psf: list[np.ndarray] = []  # their PSF ids (metacal)
    n_pending = 0
    measured_to = unit.case_start * n_rea  # global index of the first pending stamp
    truth_parts: list[dict[str, np.ndarray]] = []

    def measure_pending(final: bool) -> None:
        nonlocal pending, pending_psf, n_pending, measured_to
        if measurer is None or not pending:
            return
        block = np.concatenate(pending)
        block_psf = np.concatenate(pending_psf)
        stop = len(block) if final else len(block) - len(block) % MEASURE_BATCH
        for a in range(0, stop, MEASURE_BATCH):
            b = min(a + MEASURE_BATCH, stop)
            idx = np.arange(measured_to + a, measured_to + b)
            measurer(block[a:b], stamp_origins(idx, unit.n_x, S), idx, block_psf[a:b])
        measured_to += stop
        pending = [block[stop:]] if stop < len(block) else []
        pending_psf = [block_psf[stop:]] if stop < len(block) else []
        n_pending = len(block) - stop

    for case in range(unit.case_start, unit.case_stop):
        d = draw_case(cfg, unit.seed, case)
        psfs = case_psfs(cfg, d)
        truth_parts.append(case_columns(d, [p.truth for p in psfs]))
        # each stamp is rendered, and gets its noise, on its own: blocks change nothing
        for lo in range(0, n_rea, CASE_BLOCK):
            hi = min(lo + CASE_BLOCK, n_rea)
            stamps = np.empty((hi - lo, S, S), dtype=np.float32)
            block_psf = np.zeros(hi - lo, dtype=np.int64)
            for p in psfs:
                rows = p.rows[np.searchsorted(p.rows, lo) : np.searchsorted(p.rows, hi)]
                if not len(rows):
                    continue
                try:
                    stamps[rows - lo] = renderer.draw(
                        p.psf, p.key, p.method, gal.profile, *stamp_parameters(d, rows)
                    )
                except MegalutError as err:
                    raise MegalutError(f"case {case}: {err}") from None
                if measurer is not None:
                    block_psf[rows - lo] = measurer.psf_id(p.psf, p.method, p.key)
            d.noise.add_batch(
                stamps,
                d.noise_seeds[lo:hi],
                None if d.noise_signs is None else d.noise_signs[lo:hi],
            )
            if unit.keep_stamps:
                kept.append(stamps)
            if measurer is not None:
                pending.append(stamps)
                pending_psf.append(block_psf)
                n_pending += hi - lo
                if n_pending >= MEASURE_BATCH:
                    measure_pending(final=False)
    measure_pending(final=True)
    columns = (
        {k: np.concatenate([p[k] for p in truth_parts]) for k in truth_parts[0]}
        if truth_parts
        else {}
    )
    if measurer is not None:
        columns.update(measurer.columns())
    stamps_out = np.concatenate(kept) if unit.keep_stamps and kept else None
    return {"columns": columns, "stamps": stamps_out}
