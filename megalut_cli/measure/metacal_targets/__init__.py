"""Metacal target PSFs (``metacal_target(name, psf_image, step)``), one module each,
registered here (:mod:`.base`): a new target is a module and a line below."""

from __future__ import annotations

from megalut_cli.measure.metacal_defaults import DEFAULT_TARGET, TARGET_CARD
from megalut_cli.measure.metacal_targets import gauss
from megalut_cli.measure.metacal_targets.base import (
    METACAL_TARGETS,
    MetacalTarget,
    TargetFactory,
    metacal_target,
    register_metacal_target,
)

__all__ = [
    "DEFAULT_TARGET",
    "METACAL_TARGETS",
    "TARGET_CARD",
    "MetacalTarget",
    "TargetFactory",
    "metacal_target",
    "register_metacal_target",
]

register_metacal_target(gauss.NAME, gauss.from_psf)
