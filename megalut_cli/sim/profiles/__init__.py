"""Galaxy profiles (``galaxy.profile``), one module each, registered here in the order that
messages and docs list them (:mod:`megalut_cli.sim.profiles.base`)."""

from __future__ import annotations

from megalut_cli.sim.profiles import bulgedisk, cosmos_fit, gaussian, real, sersic
from megalut_cli.sim.profiles.base import GALAXY_PROFILES, GalaxyProfile, register_galaxy_profile

__all__ = ["GALAXY_PROFILES", "GalaxyProfile", "register_galaxy_profile"]

for profile in (
    sersic.PROFILE,
    gaussian.PROFILE,
    bulgedisk.PROFILE,
    cosmos_fit.PROFILE,
    real.PROFILE,
):
    register_galaxy_profile(profile)
