"""The registry of galaxy profiles (``galaxy.profile``): what a profile is made of.

A profile is declared once, in its own module of :mod:`megalut_cli.sim.profiles`, as a
:class:`GalaxyProfile` (GalSim's ``RegisterObjectType`` is the model) and registered in
that package's ``__init__``: its keys of ``[galaxy]`` (schema declarations, checked by
:func:`~megalut_cli.schema.check_params`; the docs tables come from them), how its table
becomes a :class:`GalaxySpec`, its truth columns, how GalSim draws it and whether the fast
engine renders it.

Nothing here imports GalSim: the config is read (and ``--help`` shown) without it; a
profile's ``build`` imports it when it draws.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from megalut_cli.schema import OneOf, Option, Required
from megalut_cli.sim.distributions import Distribution


@dataclass(frozen=True)
class GalaxySpec:
    """The ``[galaxy]`` table of a config, parsed by its profile (plain, picklable)."""

    profile: str
    params: dict[str, Distribution]  # rad, sersicn, flux|sb|mag, ellipticity (draw order)
    angle: Distribution  # position angle, degrees
    flux_mode: str
    sersicn_step: float
    #: profile "real": {"catalog": file, "dir": image folder, "pixel_scale": arcsec/pixel}
    real: dict[str, Any] | None = None
    #: profile "cosmos_fit": {"fit": "sersic" | "bulgedisk" | "auto",
    #: "pixel_scale": arcsec/pixel or None}
    model: dict[str, Any] | None = None

    @property
    def knots(self) -> bool:
        """Whether galaxies may get star-forming knots."""
        return "knots" in self.params


class ProfileTruth(NamedTuple):
    """What a profile makes of the galaxy parameters drawn for a case: its truth columns
    (``tru_rad`` among them, in the catalog's order), the ellipticity modulus of each
    realization's galaxy, and the radius R of its ``F = S pi R^2`` (``sb``)."""

    columns: dict[str, np.ndarray]
    ellipticity: np.ndarray
    flux_rad: np.ndarray


#: ``parse(given, values, instrument, config_path)``: the table's keys as given, every key's
#: value (checked scalars, defaults where not given), ``[instrument]``, the config file.
ParseFunction = Callable[
    [Mapping[str, Any], Mapping[str, Any], Mapping[str, float], str], GalaxySpec
]
#: ``truth(spec, drawn, sequence)``: the drawn parameters of a case (per realization) and the
#: place of each realization's galaxy in the run (its SNC group, or its case).
TruthFunction = Callable[[GalaxySpec, dict[str, np.ndarray], np.ndarray], ProfileTruth]
#: ``build(spec, truth, k, gsparams, pad_pixels)``: the GalSim object of truth row ``k``
#: before its orientation and the lensing shear (``pad_pixels``: noise padding of real images).
BuildFunction = Callable[[GalaxySpec, Mapping[str, np.ndarray], int, Any, float], Any]


@dataclass(frozen=True)
class GalaxyProfile:
    """One galaxy profile: its keys, its checks, its truth and how it is drawn.

    ``options`` are the keys of ``[galaxy]`` it takes besides ``profile`` (its docs table),
    ``rules`` its required keys and exactly-one groups, in the order they are checked.
    ``refuses`` names keys of other profiles it does not take, with the reason (said as
    "not a key of profile P (reason)"); with ``only_own_keys`` every other key is refused
    that way, else as another profile's ("only for profile = ...").

    ``fast`` is the radial family of the fast renderer that draws it (``"sersic"``,
    ``"gaussian"``: :mod:`megalut_cli.sim.render`), None when GalSim alone draws it.
    ``truth_columns`` are the truth columns it adds (besides the shared ones).

    ``check(spec, stamp_size)`` checks the ranges of its own parameters once the
    ``[catalog]`` is read; ``catalog`` says why it needs a ``[catalog]`` table (empty: it
    does not) and ``select_rows(spec, parts, n_rows)`` keeps the rows it can draw;
    ``summary(table)`` is its one-line description in a model's provenance.
    """

    name: str
    help: str
    options: tuple[Option, ...]
    rules: tuple[Required | OneOf, ...]
    parse: ParseFunction
    truth: TruthFunction
    build: BuildFunction
    truth_columns: tuple[str, ...] = ()
    fast: str | None = None
    check: Callable[[GalaxySpec, int], None] | None = None
    refuses: Mapping[str, str] = field(default_factory=dict)
    only_own_keys: bool = False
    catalog: str = ""
    select_rows: Callable[[GalaxySpec, dict[str, dict[str, Any]], int], int] | None = None
    summary: Callable[[Mapping[str, Any]], str] | None = None

    @property
    def keys(self) -> tuple[str, ...]:
        """Its keys of ``[galaxy]`` (besides ``profile``)."""
        return tuple(o.name for o in self.options)

    def describe(self, table: Mapping[str, Any]) -> str:
        """Its galaxies of the ``[galaxy]`` table ``table``, in a few words."""
        return self.summary(table) if self.summary is not None else f"{self.name} galaxies"


#: Every galaxy profile by name, in the order of registration (``galaxy.profile`` values).
GALAXY_PROFILES: dict[str, GalaxyProfile] = {}


def register_galaxy_profile(profile: GalaxyProfile) -> None:
    """Make ``profile`` available as ``galaxy.profile = "<name>"``."""
    if profile.name in GALAXY_PROFILES:
        raise ValueError(f"galaxy profile {profile.name!r} is already registered")
    GALAXY_PROFILES[profile.name] = profile
