"""The ``[galaxy]`` table of a simulation config: its ``profile`` picks a registered galaxy
profile (:mod:`megalut_cli.sim.profiles`), whose declared keys are checked here
(:func:`~megalut_cli.schema.check_params`) before the profile parses them; and the ranges
of the parameters, once the ``[catalog]`` is read."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from megalut_cli.schema import Option, check_choice, check_params, check_table
from megalut_cli.sim.distributions import check_bounds
from megalut_cli.sim.profiles import GALAXY_PROFILES, GalaxyProfile
from megalut_cli.sim.profiles.base import GalaxySpec
from megalut_cli.sim.profiles.common import check_modulus

__all__ = [
    "GALAXY_OPTION",
    "GalaxySpec",
    "check_galaxy_ranges",
    "galaxy_keys",
    "parse_galaxy",
    "refusal",
]

#: ``galaxy.profile``, declared once (its choices: the registered profiles).
GALAXY_OPTION = Option(
    "profile", "choice", "sersic", "the galaxy profile (below)", choices=tuple(GALAXY_PROFILES)
)


def galaxy_keys() -> set[str]:
    """Every key of ``[galaxy]``: ``profile`` and the keys of every registered profile."""
    return {"profile"}.union(*(p.keys for p in GALAXY_PROFILES.values()))


def refusal(profile: GalaxyProfile, key: str) -> str:
    """Why ``profile`` does not take ``key``, a key of other profiles: its own reason, or the
    profiles that take it (named latest registered first, as messages always have)."""
    if key in profile.refuses or profile.only_own_keys:
        reason = profile.refuses.get(key, "")
        return f"not a key of profile {profile.name!r}" + (f" ({reason})" if reason else "")
    owners = [p.name for p in reversed(GALAXY_PROFILES.values()) if key in p.keys]
    return "only for profile = " + " or ".join(repr(name) for name in owners)


def parse_galaxy(
    raw: Mapping[str, Any], instrument: Mapping[str, float], config_path: str = "<config>"
) -> GalaxySpec:
    """The ``[galaxy]`` table of the config ``raw``, parsed by its profile."""
    t = check_table(raw.get("galaxy"), "galaxy", galaxy_keys(), required=True)
    name = check_choice(
        t.get("profile", GALAXY_OPTION.default), "galaxy.profile", tuple(GALAXY_PROFILES)
    )
    profile = GALAXY_PROFILES[name]
    given = {k: v for k, v in t.items() if k != "profile"}
    values = check_params(
        given, "galaxy", profile.options, profile.rules, lambda key: refusal(profile, key)
    )
    return profile.parse(given, values, instrument, config_path)


def check_galaxy_ranges(galaxy: GalaxySpec, stamp_size: int) -> None:
    """The drawn parameters stay within their ranges (checked on the bounds of their
    distributions, once the ``[catalog]`` columns are read): the shared ones, then the
    profile's own (its ``check``), then the knots'."""
    g = galaxy.params
    if "rad" in g:
        check_bounds(g["rad"], 0.0, None, "the half-light radius", strict_lo=True)
    if galaxy.flux_mode in ("flux", "sb"):
        what = "the flux" if galaxy.flux_mode == "flux" else "the surface brightness"
        check_bounds(g[galaxy.flux_mode], 0.0, None, what)
    if "ellipticity" in g:
        check_modulus(g["ellipticity"], "the ellipticity modulus")
    check = GALAXY_PROFILES[galaxy.profile].check
    if check is not None:
        check(galaxy, stamp_size)
    for name, lo, hi, what in (
        ("knots_fraction", 0.0, 1.0, "the knots' fraction of the disk's flux"),
        ("knots", 0.0, 10000.0, "the number of knots"),
    ):
        if name in g:
            check_bounds(g[name], lo, hi, what)
