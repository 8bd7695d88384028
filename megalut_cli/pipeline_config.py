"""Pipeline-file validation shared by the standard and GREAT3 pipelines of ``megalut run``.

:class:`~megalut_cli.schema.Table` (typed, key-checked access to a table; errors name the key),
:func:`merge_tables` (``extends`` and ``[sets.X.simulation]`` overrides), and the
specifications of the training and evaluation steps with their readers.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from megalut_cli.errors import ConfigError, MegalutError
from megalut_cli.nn.options import OPTION as TRAIN_OPTION
from megalut_cli.schema import Table
from megalut_cli.training import TrainOptions


@dataclass(frozen=True)
class TrainPointSpec:
    features: list[str]
    targets: list[str]
    hidden: list[int]
    cost: str
    select_cases: str | None
    init: str
    options: TrainOptions


@dataclass(frozen=True)
class TrainWeightSpec:
    features: list[str] | None  # None: those of the point model
    hidden: list[int]
    select: str | None
    options: TrainOptions


@dataclass(frozen=True)
class EvaluateSpec:
    by: list[str]
    bins: int
    select: str | None
    select_cases: str | None
    plot: bool


def merge_tables(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """Deep-merge ``over`` into a copy of ``base``; a table with a ``type`` key replaces, not merges."""
    out = copy.deepcopy(dict(base))
    for k, v in over.items():
        if isinstance(v, Mapping) and "type" not in v and isinstance(out.get(k), Mapping):
            out[k] = merge_tables(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def train_options_from(t: Table, iterations: int, seed: int) -> TrainOptions:
    """The training options of a table (``iterations`` and ``seed``: its defaults), checked by
    their declarations (:mod:`megalut_cli.nn.options`)."""
    values = {k: v for k, v in t.data.items() if k in TRAIN_OPTION}
    return TrainOptions.from_values(values, t.where, {"iterations": iterations, "seed": seed})


def key_names(table: str) -> dict[str, str]:
    """How library messages name their arguments: keys of the table ``table`` of the pipeline file."""
    return {arg: f"{table}.{arg}" for arg in ("select_cases", "select", "hidden", "valid_fraction", "by")}


def selection_expression(t: Table, name: str, case_mode: bool, default: str | None = None) -> str | None:
    """A selection expression, syntax-checked (columns are checked later); ``""`` means none."""
    from megalut_cli.expr import check_expression

    if t.data.get(name) == "":
        return None
    expr = t.get_str(name, default)
    if expr is not None:
        try:
            check_expression(expr, None, case_mode=case_mode)
        except MegalutError as err:
            raise ConfigError(f"{t.key(name)}: {err}") from None
    return expr


