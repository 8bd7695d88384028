"""The registry of feature sets: what a measurement adds to a catalog, declared once.

A :class:`FeatureSet` names its columns with their units and descriptions, how they are
computed from a stack of stamps and the base features, which columns a flagged row has
NaN, and the option of ``measure`` and ``simulate`` that asks for it. Modules that define a
set call :func:`register_feature_set`; :mod:`.feature_sets` imports them all.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from megalut_cli.schema import Option

#: ``compute(stamps, origins, base_features) -> columns`` of a set derived from the base one.
Compute = Callable[[np.ndarray, "np.ndarray | None", dict[str, np.ndarray]], dict[str, np.ndarray]]


@dataclass(frozen=True)
class Column:
    """One catalog column: its name, FITS unit (empty: dimensionless) and description."""

    name: str
    unit: str
    description: str


@dataclass(frozen=True)
class FeatureSet:
    """A set of feature columns. ``compute`` is None for the base set (measured by
    :func:`megalut_cli.measure.features.measure_stamps`); ``option``, a bool option of
    ``measure`` and ``simulate --measure`` that adds the set (None: always measured);
    ``nan_when_flagged``, the columns set to NaN on a row with non-zero flags."""

    name: str
    columns: tuple[Column, ...]
    compute: Compute | None = None
    option: Option | None = None
    nan_when_flagged: tuple[str, ...] = ()

    @property
    def names(self) -> tuple[str, ...]:
        """The column names, in order."""
        return tuple(c.name for c in self.columns)


_REGISTRY: dict[str, FeatureSet] = {}


def register_feature_set(feature_set: FeatureSet) -> FeatureSet:
    """Register ``feature_set`` under its name (once) and return it."""
    if feature_set.name in _REGISTRY:
        raise ValueError(f"feature set {feature_set.name!r} is registered already")
    clash = {c for s in _REGISTRY.values() for c in s.names} & set(feature_set.names)
    if clash:
        raise ValueError(f"feature set {feature_set.name!r}: columns {sorted(clash)} taken")
    _REGISTRY[feature_set.name] = feature_set
    return feature_set


def registered_feature_sets() -> tuple[FeatureSet, ...]:
    """Every registered set, in registration order."""
    return tuple(_REGISTRY.values())


def get_feature_set(name: str) -> FeatureSet:
    """The set registered as ``name``."""
    try:
        return _REGISTRY[name]
    except KeyError:
        known = ", ".join(_REGISTRY)
        raise ValueError(f"unknown feature set {name!r} (known: {known})") from None


def check_feature_set_names(names: Sequence[str]) -> tuple[str, ...]:
    """``names`` as a tuple of registered set names, each once, in registration order."""
    wanted = set(names)
    for n in wanted:
        if get_feature_set(n).compute is None:
            raise ValueError(f"feature set {n!r} is always measured: it is not an optional set")
    return tuple(n for n in _REGISTRY if n in wanted)


def unregister_feature_set(name: str) -> None:
    """Remove the set registered as ``name`` (a plug-in's or a test's)."""
    get_feature_set(name)
    del _REGISTRY[name]
