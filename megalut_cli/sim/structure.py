"""The cases x realizations structure: which parameters are drawn once per case and which
per realization, shape-noise cancellation (SNC), sub-pixel offsets.

Per case ``c`` every draw comes from three generators seeded by ``(seed, c)`` (through
:func:`megalut_cli.seeding.rng_for`): one for the case-level parameters, one for the
per-realization parameters and one for offsets and noise seeds. The result therefore
never depends on how cases are split into work units, and lowering ``n_realizations``
keeps the galaxies of each case.

Antithetic noise (``structure.antithetic = true``): realizations ``2k, 2k+1`` are twins, drawn
as realization ``k`` of a set of half the size, the second with its noise and metacal fixnoise
negated.

Common random numbers (``structure.common = true``): the per-realization generator and the
offset/noise-seed generator are seeded by ``seed`` alone (stream ``STREAM_COMMON``), not by
the case, so realization ``k`` has the same galaxy, position angle, offset and noise seed in
every case (star-forming knots too); only the case-level draws (shear, and PSF and noise
level when per case) differ.

SNC groups: with ``snc = "ring"`` all realizations of a case form one group whose
position angles are ``theta_k = theta_0 + k * 180 deg / n`` (so the intrinsic ellipticities
sum exactly to zero); with ``"pairs"`` consecutive realizations ``2j, 2j+1`` form groups
rotated by 90 deg; with ``"none"`` every realization is its own group. Per-realization
parameters are drawn once per group.

The paper's structures (Figs. 4-6):

- shear training (Fig. 4): ``per_realization = ["angle"]``, ``snc = "ring"``;
- weight training (Fig. 5): ``per_realization = ["galaxy"]`` (one shear per case);
- ellipticity pretraining (Fig. 6): ``per_realization = []``, no ``[shear]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from megalut_cli.seeding import STREAM_COMMON, STREAM_SIMULATE, rng_for
from megalut_cli.sim.config import SimConfig
from megalut_cli.sim.distributions import Distribution, draw, sample_level
from megalut_cli.sim.intrinsic import ellipticity_components, galaxy_fluxes, mag_from_flux
from megalut_cli.sim.noise import StampNoise, make_noise
from megalut_cli.sim.profiles import GALAXY_PROFILES

#: Sub-keys of rng_for(seed, STREAM_SIMULATE, case, KEY).
_CASE_KEY, _REA_KEY, _NOISE_KEY, _KNOT_KEY = 0, 1, 2, 3


@dataclass
class CaseDraw:
    """Everything drawn for one case; per-realization arrays have length n_realizations."""

    case: int
    truth: dict[str, np.ndarray]
    galaxy_index: np.ndarray  # realization -> index of its galaxy (0..)
    psf_index: np.ndarray  # realization -> index into psf_specs
    psf_specs: list[tuple[dict[str, Any], float, float]]  # (scalar spec, field x, field y)
    noise: StampNoise
    noise_seeds: np.ndarray
    offsets: np.ndarray  # (n, 2) pixels
    extra: dict[str, Any] = field(
        default_factory=dict
    )  # "theta": position angles (deg, not reduced)
    #: The sign of each realization's noise (and fixnoise): -1 for the second of antithetic
    #: twins; None: all +1.
    noise_signs: np.ndarray | None = None


def antithetic_twins(d: CaseDraw) -> CaseDraw:
    """The draw of ``d``'s realizations each doubled into twins ``2k, 2k+1`` that share every
    parameter and noise seed, the second with its noise negated (``noise_signs``)."""

    def twice(a: np.ndarray) -> np.ndarray:
        return np.repeat(np.asarray(a), 2, axis=0)

    n = len(d.noise_seeds)
    return CaseDraw(
        d.case,
        {k: twice(v) for k, v in d.truth.items()},
        twice(d.galaxy_index),
        twice(d.psf_index),
        d.psf_specs,
        d.noise,
        twice(d.noise_seeds),
        twice(d.offsets),
        {k: twice(v) for k, v in d.extra.items()},
        np.tile(np.array([1.0, -1.0]), n),
    )


def ring_angles(theta0: np.ndarray, n_rea: int, group_size: int) -> np.ndarray:
    """Position angles (deg) of realizations ``k``: ``theta0[k // gs] + (k % gs) * 180 / gs``."""
    k = np.arange(n_rea)
    return np.asarray(theta0, dtype=float)[k // group_size] + (k % group_size) * (
        180.0 / group_size
    )


def draw_case(config: SimConfig, seed: int, case: int) -> CaseDraw:
    """Draw all parameters of case ``case`` (with antithetic noise: those of half as many
    realizations, each doubled into twins, :func:`antithetic_twins`)."""
    s = config.structure
    if s.antithetic:
        half = config.with_structure(n_realizations=s.n_realizations // 2, antithetic=False)
        return antithetic_twins(draw_case(half, seed, case))
    n, gs, ng = s.n_realizations, s.group_size, s.n_groups
    group_of = np.arange(n) // gs
    rng_case = rng_for(seed, STREAM_SIMULATE, case, _CASE_KEY)
    if s.common:  # the same realizations in every case
        rng_rea = rng_for(seed, STREAM_COMMON, _REA_KEY)
        rng_noise = rng_for(seed, STREAM_COMMON, _NOISE_KEY)
    else:
        rng_rea = rng_for(seed, STREAM_SIMULATE, case, _REA_KEY)
        rng_noise = rng_for(seed, STREAM_SIMULATE, case, _NOISE_KEY)
    nrows = config.catalog_rows

    def level(
        group: str, dists: dict[str, Distribution]
    ) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """Samples per realization and the realization -> draw index map."""
        if not dists:
            return {}, np.zeros(n, dtype=np.int64)
        if s.varies(group):
            vals = sample_level(dists, rng_rea, ng, nrows)
            return {k: v[group_of] for k, v in vals.items()}, group_of
        vals = sample_level(dists, rng_case, 1, nrows, positions=np.array([case]))
        return {k: np.repeat(v, n) for k, v in vals.items()}, np.zeros(n, dtype=np.int64)

    truth: dict[str, np.ndarray] = {}
    shear, _ = level("shear", config.shear)
    truth["tru_g1"] = shear.get("g1", np.zeros(n))
    truth["tru_g2"] = shear.get("g2", np.zeros(n))

    # Field position and PSF parameters: one level ("psf").
    psf_dists = {k: v for k, v in config.psf.items() if isinstance(v, Distribution)}
    field_vals, field_idx = level("psf", config.field or {})
    psf_vals, psf_idx = level("psf", psf_dists)
    psf_index = field_idx if config.field else psf_idx
    if config.field:
        truth["tru_field_x"] = field_vals["x"]
        truth["tru_field_y"] = field_vals["y"]
    specs: list[tuple[dict[str, Any], float, float]] = []
    # psf_index is non-decreasing: the first realization of each draw
    firsts = np.searchsorted(psf_index, np.arange(int(psf_index.max()) + 1))
    for k in firsts.tolist():
        spec = {
            key: (float(psf_vals[key][k]) if key in psf_vals else val)
            for key, val in config.psf.items()
        }
        fx = float(field_vals["x"][k]) if config.field else 0.0
        fy = float(field_vals["y"][k]) if config.field else 0.0
        specs.append((spec, fx, fy))

    # Galaxy: its profile makes its truth of the drawn parameters.
    gal = config.galaxy
    gvals, gal_index = level("galaxy", gal.params)
    sequence = group_of if s.varies("galaxy") else np.full(n, case)  # the galaxy's place in the run
    galaxy_truth = GALAXY_PROFILES[gal.profile].truth(gal, gvals, sequence)
    truth.update(galaxy_truth.columns)
    if gal.knots:  # one seed per galaxy draw, from its own stream (the other draws are unchanged)
        n_draws = int(gal_index.max()) + 1
        knot_rng = (
            rng_for(seed, STREAM_COMMON, _KNOT_KEY)
            if s.common
            else rng_for(seed, STREAM_SIMULATE, case, _KNOT_KEY)
        )
        knot_seeds = knot_rng.integers(1, 2**31 - 1, n_draws)
        truth["tru_knots"] = np.round(gvals["knots"]).astype(np.int64)
        truth["tru_knots_fraction"] = np.where(truth["tru_knots"] > 0, gvals["knots_fraction"], 0.0)
        truth["tru_knot_seed"] = knot_seeds[gal_index]
    flux_rad = galaxy_truth.flux_rad
    flux = galaxy_fluxes(gal.flux_mode, gvals[gal.flux_mode], flux_rad, config.instrument)
    truth["tru_flux"] = flux
    truth["tru_sb"] = flux / (np.pi * flux_rad**2)
    inst = config.instrument
    if gal.flux_mode == "mag":
        truth["tru_mag"] = gvals["mag"]
    elif all(k in inst for k in ("zeropoint", "exptime", "gain")):
        truth["tru_mag"] = mag_from_flux(flux, inst["zeropoint"], inst["exptime"], inst["gain"])

    # Position angle: per group (with SNC rotations within the group) or per case.
    if s.varies("angle"):
        theta0 = gal.angle.sample(rng_rea, ng)
    else:
        theta0 = np.repeat(draw(gal.angle, rng_case, 1, positions=np.array([case])), ng)
    theta = ring_angles(theta0, n, gs)
    ell = galaxy_truth.ellipticity
    e1, e2 = ellipticity_components(ell, theta)
    truth["tru_e1"], truth["tru_e2"] = e1, e2
    truth["tru_ell"], truth["tru_theta"] = ell, np.mod(theta, 180.0)

    # Noise (per case), offsets and noise seeds (per realization).
    drawn = sample_level(config.noise.params, rng_case, 1, nrows, positions=np.array([case]))
    nparams = {k: float(v[0]) for k, v in drawn.items()}
    noise = make_noise(
        config.noise.type,
        nparams,
        config.instrument,
        config.noise.override_sigma,
        config.noise.source,
    )
    truth["tru_sky_sigma"] = np.full(n, noise.sky_sigma)
    offsets = rng_noise.uniform(-s.offset, s.offset, (n, 2)) if s.offset > 0 else np.zeros((n, 2))
    truth["tru_dx"], truth["tru_dy"] = offsets[:, 0], offsets[:, 1]
    seeds = rng_noise.integers(1, 2**31 - 1, n)
    return CaseDraw(
        case, truth, gal_index, psf_index, specs, noise, seeds, offsets, {"theta": theta}
    )
