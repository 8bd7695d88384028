"""``profile = "sersic"``: a Sérsic galaxy (GalSim ``Sersic``) of half-light radius ``rad``,
index ``sersicn`` and ellipticity ``ellipticity``, the paper's galaxies; the fast engine
renders it (without knots)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from megalut_cli.schema import Required
from megalut_cli.sim.distributions import short_text
from megalut_cli.sim.profiles.base import GalaxyProfile, GalaxySpec, ProfileTruth
from megalut_cli.sim.profiles.common import (
    ONE_FLUX,
    PARAMETRIC_OPTIONS,
    RAD_REQUIRED,
    SERSICN,
    SERSICN_STEP,
    check_sersic_index,
    knot_dists,
    parametric_params,
    position_angle,
    round_sersicn,
)


def parse(
    given: Mapping[str, Any],
    values: Mapping[str, Any],
    instrument: Mapping[str, float],
    config_path: str,
) -> GalaxySpec:
    mode, step, params = parametric_params(given, values, instrument)
    params.update(knot_dists(given))
    return GalaxySpec("sersic", params, position_angle(values), mode, step)


def truth(spec: GalaxySpec, drawn: dict[str, np.ndarray], sequence: np.ndarray) -> ProfileTruth:
    rad = drawn["rad"]
    columns = {"tru_rad": rad, "tru_sersicn": round_sersicn(drawn["sersicn"], spec.sersicn_step)}
    return ProfileTruth(columns, drawn["ellipticity"], rad)


def build(
    spec: GalaxySpec, truth: Mapping[str, np.ndarray], k: int, gsparams: Any, pad_pixels: float
) -> Any:
    from megalut_cli.sim import galaxies  # GalSim: not needed to read a config

    return galaxies.galaxy_profile(truth, k, gsparams, galaxies.round_sersic)


def check(spec: GalaxySpec, stamp_size: int) -> None:
    check_sersic_index(spec.params, "sersicn", spec.sersicn_step)


def summary(table: Mapping[str, Any]) -> str:
    n, rad = (short_text(table.get(k, "?")) for k in ("sersicn", "rad"))
    return f"Sersic galaxies (n {n}, rad {rad} px)"


PROFILE = GalaxyProfile(
    "sersic",
    "a Sérsic galaxy (GalSim `Sersic`), sheared by its ellipticity; the paper's galaxies",
    (SERSICN, SERSICN_STEP, *PARAMETRIC_OPTIONS),
    (RAD_REQUIRED, ONE_FLUX, Required("sersicn", "Sersic index")),
    parse,
    truth,
    build,
    truth_columns=("tru_sersicn",),
    fast="sersic",
    check=check,
    summary=summary,
)
