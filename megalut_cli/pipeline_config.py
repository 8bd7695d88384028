"""Pipeline-file validation shared by the standard and GREAT3 pipelines of ``megalut run``.

:class:`ConfigTable` (typed, key-checked access to a table; errors name the key),
:func:`merge_tables` (``extends`` and ``[sets.X.simulation]`` overrides), and the
specifications of the training and evaluation steps with their readers.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from megalut_cli.errors import ConfigError, MegalutError
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


class ConfigTable:
    """Typed, key-checked access to one table of the pipeline file (errors name the key)."""

    def __init__(self, data: Any, where: str, allowed: set[str] | None = None) -> None:
        if data is None:
            data = {}
        if not isinstance(data, Mapping):
            raise ConfigError(f"{where}: expected a table, got {data!r}")
        self.data, self.where = dict(data), where
        if allowed is not None:
            unknown = sorted(set(self.data) - allowed)
            if unknown:
                raise ConfigError(f"{self.key(unknown[0])}: unknown key (allowed: {', '.join(sorted(allowed))})")

    def key(self, name: str) -> str:
        return f"{self.where}.{name}" if self.where else name

    def get_int(self, name: str, default: int | None, minimum: int) -> int | None:
        v = self.data.get(name, default)
        if v is None:
            return None
        if isinstance(v, bool) or not isinstance(v, int):
            raise ConfigError(f"{self.key(name)}: expected an integer, got {v!r}")
        if v < minimum:
            raise ConfigError(f"{self.key(name)}: must be >= {minimum}, got {v}")
        return int(v)

    def get_float(self, name: str, default: float, lo: float, hi: float, lo_open: bool = False,
              hi_open: bool = False) -> float:
        v = self.data.get(name, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ConfigError(f"{self.key(name)}: expected a finite number, got {v!r}")
        if v < lo or v > hi or (lo_open and v == lo) or (hi_open and v == hi):
            interval = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
            raise ConfigError(f"{self.key(name)}: must be in {interval}, got {v!r}")
        return float(v)

    def get_str(self, name: str, default: str | None, choices: Sequence[str] | None = None) -> str | None:
        v = self.data.get(name, default)
        if v is None:
            return None
        if not isinstance(v, str) or not v.strip():
            raise ConfigError(f"{self.key(name)}: expected a non-empty string, got {v!r}")
        if choices is not None and v not in choices:
            raise ConfigError(f"{self.key(name)}: unknown value {v!r} (expected one of {', '.join(choices)})")
        return v

    def get_bool(self, name: str, default: bool) -> bool:
        v = self.data.get(name, default)
        if not isinstance(v, bool):
            raise ConfigError(f"{self.key(name)}: expected true or false, got {v!r}")
        return v

    def get_str_list(self, name: str, default: Sequence[str] | None, allow_empty: bool = False) -> list[str] | None:
        v = self.data.get(name, default)
        if v is None:
            return None
        if isinstance(v, str):
            v = [s.strip() for s in v.split(",") if s.strip()]
        if not isinstance(v, (list, tuple)) or not all(isinstance(s, str) and s for s in v):
            raise ConfigError(f"{self.key(name)}: expected a list of names, got {v!r}")
        if not v and not allow_empty:
            raise ConfigError(f"{self.key(name)}: the list is empty")
        dup = sorted({s for s in v if list(v).count(s) > 1})
        if dup:
            raise ConfigError(f"{self.key(name)}: {dup[0]!r} given twice")
        return list(v)

    def get_int_list(self, name: str, default: Sequence[int]) -> list[int]:
        v = self.data.get(name, default)
        if isinstance(v, int) and not isinstance(v, bool):
            v = [v]
        if (not isinstance(v, (list, tuple)) or not v
                or not all(isinstance(i, int) and not isinstance(i, bool) and i > 0 for i in v)):
            raise ConfigError(f"{self.key(name)}: expected a list of positive integers, got {v!r}")
        return list(v)


def merge_tables(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """Deep-merge ``over`` into a copy of ``base``; a table with a ``type`` key replaces, not merges."""
    out = copy.deepcopy(dict(base))
    for k, v in over.items():
        if isinstance(v, Mapping) and "type" not in v and isinstance(out.get(k), Mapping):
            out[k] = merge_tables(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def train_options_from(t: ConfigTable, iterations: int, seed: int) -> TrainOptions:
    opts = TrainOptions(
        members=t.get_int("members", 8, 1),
        iterations=t.get_int("iterations", iterations, 1),
        batch_fraction=t.get_float("batch_fraction", 0.25, 0.0, 1.0, lo_open=True),
        batch_iterations=t.get_int("batch_iterations", 30, 1),
        optimizer=t.get_str("optimizer", "bfgs", ("bfgs", "lbfgs")),
        normalization=t.get_str("normalization", "minmax", ("minmax", "robust")),
        valid_fraction=t.get_float("valid_fraction", 0.2, 0.0, 1.0, hi_open=True),
        seed=t.get_int("seed", seed, 0),
        dtype=t.get_str("precision", "float64", ("float64", "float32")),
        keep=t.get_int("keep", None, 1),
    )
    if opts.keep is not None and opts.keep > opts.members:
        raise ConfigError(f"{t.key('keep')}: must be <= {t.key('members')} ({opts.members}), got {opts.keep}")
    return opts


def key_names(table: str) -> dict[str, str]:
    """How library messages name their arguments: keys of the table ``table`` of the pipeline file."""
    return {arg: f"{table}.{arg}" for arg in ("select_cases", "select", "hidden", "valid_fraction", "by")}


def selection_expression(t: ConfigTable, name: str, case_mode: bool, default: str | None = None) -> str | None:
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


