"""``profile = "bulgedisk"``: an exponential disk plus a Sérsic bulge (de Vaucouleurs by
default), both GalSim profiles, built in the galaxy's own frame and rotated; ``rad`` is the
half-light radius of the round composite (``docs/config.md``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from megalut_cli.errors import ConfigError
from megalut_cli.schema import Option, Required
from megalut_cli.sim.distributions import check_bounds, parse_distribution
from megalut_cli.sim.profiles.base import GalaxyProfile, GalaxySpec, ProfileTruth
from megalut_cli.sim.profiles.common import (
    ANGLE,
    ELLIPTICITY,
    FLUX,
    KNOTS,
    KNOTS_FRACTION,
    MAG,
    ONE_FLUX,
    RAD,
    RAD_REQUIRED,
    SB,
    SERSICN_STEP,
    check_modulus,
    check_sersic_index,
    composite_hlr,
    knot_dists,
    parametric_params,
    position_angle,
    round_sersicn,
    with_help,
)

#: The bulge's keys, in their draw order (all but ``bulge_fraction`` have a default).
BULGE_OPTIONS = (
    Option(
        "bulge_fraction",
        "dist",
        None,
        "bulge flux / total flux B",
        default_text="required",
        allowed_text="*dist*, [0, 1]",
    ),
    Option(
        "bulge_rad_ratio",
        "dist",
        0.5,
        "bulge half-light radius / disk half-light radius",
        allowed_text="*dist*, > 0",
    ),
    Option(
        "bulge_sersicn",
        "dist",
        4.0,
        "the bulge's Sérsic index (rounded to `sersicn_step`)",
        allowed_text="*dist*, GalSim range 0.3–6.2",
    ),
    Option(
        "bulge_ellipticity",
        "dist",
        0.0,
        "the bulge's ellipticity modulus",
        allowed_text="*dist*, [0, 1)",
    ),
    Option(
        "bulge_angle",
        "dist",
        0.0,
        "the bulge's position angle **relative to the disk's**, degrees (e.g. "
        '`{type = "normal", mean = 0, sigma = 10}`: tied to the disk with a small scatter)',
    ),
    Option(
        "bulge_dx",
        "dist",
        0.0,
        "the bulge's centroid offset from the disk's along x, pixels, in the galaxy "
        "frame (x along the disk's major axis)",
        allowed_text="*dist*, \\|offset\\| ≤ stamp_size/4",
    ),
    Option(
        "bulge_dy",
        "dist",
        0.0,
        "the bulge's centroid offset from the disk's along y, pixels, in the galaxy frame",
        allowed_text="*dist*, \\|offset\\| ≤ stamp_size/4",
    ),
)
OPTIONS = (
    with_help(RAD, "half-light radius of the **composite** (round disk + round bulge), pixels"),
    with_help(ELLIPTICITY, "the **disk's** ellipticity modulus"),
    with_help(ANGLE, "the **disk's** position angle θ, degrees"),
    *BULGE_OPTIONS,
    FLUX,
    SB,
    MAG,
    SERSICN_STEP,
    KNOTS,
    KNOTS_FRACTION,
)


def parse(
    given: Mapping[str, Any],
    values: Mapping[str, Any],
    instrument: Mapping[str, float],
    config_path: str,
) -> GalaxySpec:
    mode, step, params = parametric_params(given, values, instrument)
    for o in BULGE_OPTIONS:
        params[o.name] = parse_distribution(values[o.name], f"galaxy.{o.name}")
    params.update(knot_dists(given))
    return GalaxySpec("bulgedisk", params, position_angle(values), mode, step)


def truth(spec: GalaxySpec, drawn: dict[str, np.ndarray], sequence: np.ndarray) -> ProfileTruth:
    """The composite half-light radius (``rad``) sets the disk's and the bulge's."""
    rad = np.asarray(drawn["rad"], dtype=float)
    frac = np.asarray(drawn["bulge_fraction"], dtype=float)
    ratio = np.asarray(drawn["bulge_rad_ratio"], dtype=float)
    nb = round_sersicn(drawn["bulge_sersicn"], spec.sersicn_step)
    disk_rad = rad / composite_hlr(frac, ratio, nb)
    columns = {
        "tru_rad": rad,
        "tru_disk_rad": disk_rad,
        "tru_disk_sersicn": np.ones_like(rad),
        "tru_bulge_fraction": frac,
        "tru_bulge_rad": ratio * disk_rad,
        "tru_bulge_sersicn": nb,
        "tru_bulge_ell": np.asarray(drawn["bulge_ellipticity"], dtype=float),
        "tru_bulge_dtheta": np.asarray(drawn["bulge_angle"], dtype=float),
        "tru_bulge_dx": np.asarray(drawn["bulge_dx"], dtype=float),
        "tru_bulge_dy": np.asarray(drawn["bulge_dy"], dtype=float),
    }
    return ProfileTruth(columns, drawn["ellipticity"], rad)


def build(
    spec: GalaxySpec, truth: Mapping[str, np.ndarray], k: int, gsparams: Any, pad_pixels: float
) -> Any:
    from megalut_cli.sim import galaxies  # GalSim: not needed to read a config

    return galaxies.galaxy_profile(truth, k, gsparams)


def check(spec: GalaxySpec, stamp_size: int) -> None:
    g = spec.params
    check_sersic_index(g, "bulge_sersicn", spec.sersicn_step)
    check_bounds(g["bulge_fraction"], 0.0, 1.0, "the bulge's flux fraction")
    check_bounds(
        g["bulge_rad_ratio"], 0.0, None, "the bulge-to-disk half-light radius ratio", strict_lo=True
    )
    check_modulus(g["bulge_ellipticity"], "the bulge's ellipticity modulus")
    for name in ("bulge_dx", "bulge_dy"):
        reach = max(abs(v) for v in g[name].bounds())
        if reach > stamp_size / 4:
            raise ConfigError(
                f"galaxy.{name}: the bulge offset must stay within stamp_size/4 pixels, "
                f"but values reach {reach:g}"
            )


TRUTH_COLUMNS = (
    "tru_disk_rad",
    "tru_disk_sersicn",
    "tru_bulge_fraction",
    "tru_bulge_rad",
    "tru_bulge_sersicn",
    "tru_bulge_ell",
    "tru_bulge_dtheta",
    "tru_bulge_dx",
    "tru_bulge_dy",
)

PROFILE = GalaxyProfile(
    "bulgedisk",
    "an exponential disk plus a Sérsic bulge (below)",
    OPTIONS,
    (RAD_REQUIRED, ONE_FLUX, Required("bulge_fraction", "fraction of the flux in the bulge, 0-1")),
    parse,
    truth,
    build,
    truth_columns=TRUTH_COLUMNS,
    check=check,
)
