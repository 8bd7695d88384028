"""A work unit of the fast engine on the device: render, noise, measure; features back.

:func:`draw_unit_device` is :func:`megalut_cli.sim.draw.draw_unit_fast` with the pixels on the
device. The host draws the cases (truth, offsets, seeds:
:func:`megalut_cli.sim.structure.draw_case`) and plans the stamps
(:meth:`megalut_cli.sim.render.StampRenderer.plan`); the stamps of the
unit are grouped by PSF and FFT grid into fixed-shape batches, rendered, given their noise
(Gaussian noise on the device, from the CPU engine's per-stamp stream; CCD and correlated
noise on the host) and measured there; only the features (and the stamps when they are kept)
come back.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from megalut_cli.errors import MegalutError
from megalut_cli.gpu import jax_device
from megalut_cli.gpu import measure as gmeasure
from megalut_cli.gpu import render as grender
from megalut_cli.gpu.measure import measure_on_device, padded_size, split_measurements
from megalut_cli.gpu.noise import add_gaussian_noise
from megalut_cli.measure.features import (
    default_guess_sigma,
    default_max_shift,
    features_from_moments,
)
from megalut_cli.measure.measurer import Measurer, MeasureSettings, StampBatch
from megalut_cli.sim.draw import (
    WorkUnit,
    case_columns,
    case_psfs,
    stamp_origins,
    stamp_parameters,
    stamp_renderer,
)
from megalut_cli.sim.noise import StampNoise
from megalut_cli.sim.render import RadialProfile, RenderPlan
from megalut_cli.sim.structure import draw_case

#: Most stamps given their noise at once (the generator's state and normals: ~33 KB per
#: 64 x 64 stamp).
NOISE_STAMPS = 32768


def _padded(a: np.ndarray, size: int, fill: float = 0.0) -> np.ndarray:
    out = np.full((size, *a.shape[1:]), fill, dtype=a.dtype)
    out[: len(a)] = a
    return out


@jax.jit
def place_rows(stamps: jnp.ndarray, block: jnp.ndarray, rows: jnp.ndarray) -> jnp.ndarray:
    """``stamps`` with ``block`` written at ``rows`` (rows past the end dropped): fixed shapes,
    so one compiled kernel per batch size rather than one per group's remainder."""
    return stamps.at[rows].set(block, mode="drop")


def draw_unit_device(unit: WorkUnit) -> dict[str, Any]:
    """:func:`megalut_cli.sim.draw.draw_unit` of a fast-engine unit on the device."""
    dev = jax_device()
    cfg = unit.config
    s = cfg.structure
    S, n_rea = s.stamp_size, s.n_realizations
    gal = cfg.galaxy
    renderer = stamp_renderer(S, dict(cfg.gsparams))
    n_total = (unit.case_stop - unit.case_start) * n_rea
    first = unit.case_start * n_rea
    truth_parts: list[dict[str, np.ndarray]] = []
    groups: dict[tuple[str, int, int], list[np.ndarray]] = {}  # (psf key, N, Nk) -> stamp rows
    psfs: dict[str, tuple[Any, str]] = {}
    plans: list[RenderPlan] = []
    rows_of_plan: list[np.ndarray] = []
    seeds = np.empty(n_total, dtype=np.int64)
    noises: list[StampNoise] = []
    noise_of = np.empty(n_total, dtype=np.int64)
    for case in range(unit.case_start, unit.case_stop):
        d = draw_case(cfg, unit.seed, case)
        base = (case - unit.case_start) * n_rea
        seeds[base : base + n_rea] = d.noise_seeds
        noise_of[base : base + n_rea] = len(noises)
        noises.append(d.noise)
        case_psf_list = case_psfs(cfg, d)
        for p in case_psf_list:
            psfs[p.key] = (p.psf, p.method)
            try:
                plan = renderer.plan(
                    p.psf, p.key, p.method, gal.profile, *stamp_parameters(d, p.rows)
                )
            except MegalutError as err:
                raise MegalutError(f"case {case}: {err}") from None
            plans.append(plan)
            rows_of_plan.append(base + p.rows)
            for nf, nk in set(zip(plan.n_fft.tolist(), plan.n_k.tolist())):
                pick = (plan.n_fft == nf) & (plan.n_k == nk)
                groups.setdefault((p.key, nf, nk), []).append(
                    np.stack(
                        [
                            np.full(pick.sum(), len(plans) - 1),
                            np.flatnonzero(pick),
                            base + p.rows[pick],
                        ],
                        axis=1,
                    )
                )
        truth_parts.append(case_columns(d, [p.truth for p in case_psf_list]))

    # Per-stamp inputs, gathered from the plans; one table of radial profiles for the unit.
    profiles: list[RadialProfile] = []
    index_of: dict[int, int] = {}  # id of a (cached) radial profile -> its row in the unit's table
    amat = np.zeros((n_total, 4))
    flux, shx, shy = np.zeros(n_total), np.zeros(n_total), np.zeros(n_total)
    table = np.zeros(n_total, dtype=np.int64)
    for plan, rows in zip(plans, rows_of_plan):
        amat[rows], flux[rows], shx[rows], shy[rows] = (
            plan.amat,
            plan.flux,
            plan.shift_x,
            plan.shift_y,
        )
        for prof in plan.profiles:
            if id(prof) not in index_of:
                index_of[id(prof)] = len(profiles)
                profiles.append(prof)
        table[rows] = np.array([index_of[id(prof)] for prof in plan.profiles], dtype=np.int64)[
            plan.table
        ]
    eparams, eint, coef = (
        (jax.device_put(a, dev) for a in grender.profile_arrays(profiles))
        if profiles
        else (None,) * 3
    )
    gaussian = np.array([nz.kind == "gaussian" and nz.sigma > 0 for nz in noises])[noise_of]
    sigma = np.array([nz.sigma for nz in noises])[noise_of]
    host_noise = np.array([nz.kind not in ("gaussian", "none") for nz in noises])[noise_of]
    guess = default_guess_sigma(S)

    stamps = jnp.zeros((n_total, S, S), jnp.float32, device=dev)
    for (key, nf, nk), parts in groups.items():
        rows = np.concatenate(parts)[:, 2]
        psf, method = psfs[key]
        kpsf = jax.device_put(renderer.psf_kimage(psf, key, method, nf, nk), dev)
        dest, weight, conj = (jax.device_put(a, dev) for a in grender.fold_indices(nf, nk))
        for a in range(0, len(rows), gmeasure.BATCH_STAMPS):
            sel = rows[a : a + gmeasure.BATCH_STAMPS]
            size = padded_size(len(sel))
            pad_amat = _padded(amat[sel], size)
            pad_amat[len(sel) :, 0] = pad_amat[len(sel) :, 3] = (
                1.0  # padding: zero flux, identity transform
            )
            rendered = grender.render_batch(
                kpsf,
                pad_amat,
                _padded(flux[sel], size),
                _padded(shx[sel], size),
                _padded(shy[sel], size),
                _padded(table[sel], size),
                eparams,
                eint,
                coef,
                dest,
                weight,
                conj,
                n_fft=nf,
                n_k=nk,
                size=S,
            )
            put = _padded(sel, size, fill=n_total)  # the padding goes nowhere
            stamps = place_rows(stamps, rendered, jnp.asarray(put))
    # The noise over large batches (its generator loops over the pixels: the loop's cost per
    # step hardly depends on the batch size).
    if gaussian.any():
        noisy = []
        for a in range(0, n_total, NOISE_STAMPS):
            b = min(a + NOISE_STAMPS, n_total)
            size = padded_size(b - a, NOISE_STAMPS)
            block = jnp.concatenate([stamps[a:b], jnp.zeros((size - (b - a), S, S), jnp.float32)])
            noisy.append(
                add_gaussian_noise(
                    block,
                    _padded(seeds[a:b], size),
                    _padded(np.where(gaussian[a:b], sigma[a:b], 0.0), size),
                )[: b - a]
            )
        stamps = jnp.concatenate(noisy)
    if host_noise.any():
        host = np.array(stamps)
        for k in np.flatnonzero(host_noise):
            noises[noise_of[k]].add_batch(host[k : k + 1], seeds[k : k + 1])
        stamps = jax.device_put(host, dev)
    keep = unit.keep_stamps or (
        unit.measure and bool(unit.feature_sets)
    )  # the optional feature sets are measured on the host
    kept = np.asarray(stamps) if keep else None
    results = measure_on_device(stamps, guess) if unit.measure else None

    columns = (
        {k: np.concatenate([p[k] for p in truth_parts]) for k in truth_parts[0]}
        if truth_parts
        else {}
    )
    if unit.measure:
        origins = stamp_origins(np.arange(first, first + n_total), unit.n_x, S)
        moments, skymad, finite = split_measurements(results)
        base = features_from_moments(
            moments, skymad, finite, origins, S, cfg.gain, default_max_shift(S)
        )
        settings = MeasureSettings(cfg.gain, unit.engine, unit.device, unit.feature_sets)
        columns.update(Measurer(settings).measure(StampBatch(kept, origins, base=base)))
    return {"columns": columns, "stamps": kept if unit.keep_stamps else None}
