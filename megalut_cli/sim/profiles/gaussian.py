"""``profile = "gaussian"``: a Gaussian galaxy (GalSim ``Gaussian``) of half-light radius
``rad`` and ellipticity ``ellipticity``; the fast engine renders it (without knots)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from megalut_cli.sim.profiles.base import GalaxyProfile, GalaxySpec, ProfileTruth
from megalut_cli.sim.profiles.common import (
    ONE_FLUX,
    PARAMETRIC_OPTIONS,
    RAD_REQUIRED,
    SERSICN_STEP,
    knot_dists,
    parametric_params,
    position_angle,
)


def parse(
    given: Mapping[str, Any],
    values: Mapping[str, Any],
    instrument: Mapping[str, float],
    config_path: str,
) -> GalaxySpec:
    mode, step, params = parametric_params(given, values, instrument)
    params.update(knot_dists(given))
    return GalaxySpec("gaussian", params, position_angle(values), mode, step)


def truth(spec: GalaxySpec, drawn: dict[str, np.ndarray], sequence: np.ndarray) -> ProfileTruth:
    rad = drawn["rad"]
    return ProfileTruth({"tru_rad": rad}, drawn["ellipticity"], rad)


def build(
    spec: GalaxySpec, truth: Mapping[str, np.ndarray], k: int, gsparams: Any, pad_pixels: float
) -> Any:
    from megalut_cli.sim import galaxies  # GalSim: not needed to read a config

    return galaxies.galaxy_profile(truth, k, gsparams, galaxies.round_gaussian)


PROFILE = GalaxyProfile(
    "gaussian",
    "a Gaussian galaxy (GalSim `Gaussian`), sheared by its ellipticity",
    (SERSICN_STEP, *PARAMETRIC_OPTIONS),
    (RAD_REQUIRED, ONE_FLUX),
    parse,
    truth,
    build,
    fast="gaussian",
)
