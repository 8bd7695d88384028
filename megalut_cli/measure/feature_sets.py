"""The feature sets megalut measures (:mod:`.feature_registry`): importing this module
registers them all. A new set is a module that calls ``register_feature_set`` and one
import line here."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from megalut_cli.measure import features, morphology
from megalut_cli.measure.feature_registry import (
    FeatureSet,
    check_feature_set_names,
    get_feature_set,
    registered_feature_sets,
)
from megalut_cli.schema import Option

#: The set every measurement holds.
BASE_SET: FeatureSet = features.ADAMOM_SET
#: Sets registered by the modules imported above (kept so that the imports are used).
BUILTIN_SETS: tuple[FeatureSet, ...] = (features.ADAMOM_SET, morphology.MORPHOLOGY_SET)


def optional_sets() -> tuple[FeatureSet, ...]:
    """The sets a command asks for with an option, in registration order."""
    return tuple(s for s in registered_feature_sets() if s.option is not None)


def set_options() -> tuple[Option, ...]:
    """The bool options of :func:`optional_sets` (``--morphology``, ...)."""
    return tuple(s.option for s in optional_sets() if s.option is not None)


def requested_sets(values: Mapping[str, object]) -> tuple[str, ...]:
    """The names of the optional sets whose option is true in ``values`` (option name ->
    value, e.g. a command's keyword arguments)."""
    return tuple(
        s.name for s in optional_sets() if s.option is not None and values.get(s.option.name)
    )


def optional_columns(set_names: Sequence[str]) -> tuple[str, ...]:
    """The columns of the optional sets ``set_names``, in registration order."""
    return tuple(c for n in check_feature_set_names(set_names) for c in get_feature_set(n).names)


def nan_when_flagged(set_names: Sequence[str]) -> tuple[str, ...]:
    """The columns of the base set and of ``set_names`` that a flagged row has NaN."""
    names = check_feature_set_names(set_names)
    return BASE_SET.nan_when_flagged + tuple(
        c for n in names for c in get_feature_set(n).nan_when_flagged
    )


def compute_extra(
    set_names: Sequence[str],
    stamps: np.ndarray,
    origins: np.ndarray | None,
    base: dict[str, np.ndarray],
) -> dict[str, np.ndarray]:
    """The columns of the optional sets ``set_names`` from the stamps and their base features."""
    out: dict[str, np.ndarray] = {}
    for name in check_feature_set_names(set_names):
        compute = get_feature_set(name).compute
        if compute is not None:
            out.update(compute(stamps, origins, base))
    return out


def column_descriptions() -> dict[str, tuple[str, str]]:
    """``(unit, description)`` of every column of every registered set."""
    return {c.name: (c.unit, c.description) for s in registered_feature_sets() for c in s.columns}
