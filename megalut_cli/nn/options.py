"""The training options, declared once: command-line options, pipeline keys, defaults, specs.

``megalut train-point``/``train-weight`` build their click options from these
declarations, ``[train_point]``/``[train_weight]``/``[pretrain]`` tables of pipeline files
are read with them, ``docs/pipeline.md`` shows them as generated tables, and
:data:`PointSpec` and :data:`WeightSpec` (what a training is) are made from them: one field
per declaration, named as the option, with its declared default. A new training option is
one more :class:`Option` here (and the field of :class:`megalut_cli.nn.train.TrainSettings`
that the members train with, when they do).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import field, make_dataclass, replace
from functools import partial
from typing import Any, ClassVar

from megalut_cli.errors import ConfigError
from megalut_cli.nn import normalization as norm
from megalut_cli.nn.defaults import (
    DEFAULT_FEATURES,
    INIT_SCHEMES,
    OPTIMIZERS,
    POINT_COSTS,
    POINT_ITERATIONS,
    PRECISIONS,
    WEIGHT_ITERATIONS,
)
from megalut_cli.schema import Option, Table

# The options of every committee training, in three groups that each command places in its
# --help (megalut_cli.cli.options): beside --valid FILE, the committee, the optimisation.
VALIDATION_OPTIONS: tuple[Option, ...] = (
    Option(
        "valid_fraction",
        "float",
        0.2,
        "Fraction of the training cases held out for validation when no "
        "--valid is given (0: none).",
        minimum=0.0,
        maximum=1.0,
        max_open=True,
    ),
)
COMMITTEE_OPTIONS: tuple[Option, ...] = (
    Option("members", "int", 8, "Networks per committee.", minimum=1),
    Option(
        "keep",
        "int",
        None,
        "Members kept (lowest validation cost).",
        minimum=1,
        default_text="half",
    ),
    Option("iterations", "int", POINT_ITERATIONS, "Optimizer iterations per member.", minimum=1),
    Option(
        "batch_fraction",
        "float",
        0.25,
        "Fraction of the training cases in each mini-batch (1: full batch).",
        minimum=0.0,
        maximum=1.0,
        min_open=True,
    ),
    Option("batch_iterations", "int", 30, "Iterations on each mini-batch.", minimum=1),
)
OPTIMIZER_OPTIONS: tuple[Option, ...] = (
    Option(
        "normalization",
        "choice",
        norm.METHODS[0],
        "Input scaling: training range to [-1, 1] (paper), or 1st-99th percentile to [-1, 1].",
        choices=norm.METHODS,
    ),
    Option("optimizer", "choice", OPTIMIZERS[0], "scipy optimizer.", choices=OPTIMIZERS),
    Option(
        "precision",
        "choice",
        PRECISIONS[0],
        "Arithmetic of the network passes during training (float32 is about twice as fast).",
        choices=PRECISIONS,
    ),
    Option(
        "seed",
        "int",
        1,
        "Seed of the random draws (initial parameters, mini-batches, validation split).",
        minimum=0,
    ),
)
#: Options of every committee training, in the order of ``--help``.
TRAIN_OPTIONS: tuple[Option, ...] = VALIDATION_OPTIONS + COMMITTEE_OPTIONS + OPTIMIZER_OPTIONS
OPTION = {o.name: o for o in TRAIN_OPTIONS}

#: The declarations :class:`megalut_cli.nn.train.TrainSettings` checks a member's settings
#: with (by field name); a member may run 0 iterations (its starting parameters), the options
#: ask for >= 1.
MEMBER_CHECKS = {**OPTION, "iterations": replace(OPTION["iterations"], minimum=0)}

#: Iterations per member by kind of committee.
ITERATIONS = {"point": POINT_ITERATIONS, "weight": WEIGHT_ITERATIONS}

#: Options of point training only (pipeline keys of ``[train_point]``, flags of train-point).
POINT_OPTIONS: tuple[Option, ...] = (
    Option(
        "features", "str_list", list(DEFAULT_FEATURES), "Input feature columns.", metavar="A,B,..."
    ),
    Option(
        "targets",
        "str_list",
        ["tru_g1", "tru_g2"],
        "Target columns, one committee each.",
        metavar="A,B",
    ),
    Option("hidden", "int_list", [5, 5], "Hidden layer sizes.", metavar="N,N"),
    Option(
        "cost",
        "choice",
        POINT_COSTS[0],
        "Cost function (MSE only for comparison).",
        choices=POINT_COSTS,
    ),
    Option(
        "select_cases",
        "str",
        None,
        "Keep only the cases for which EXPR holds, on aggregates "
        'over their valid realizations, e.g. "mean(snr) > 10" (also applied to --valid).',
        metavar="EXPR",
    ),
    Option(
        "init",
        "choice",
        INIT_SCHEMES[0],
        "Starting parameters: N(0, 0.1), or near-identity on the matching "
        "feature (adamom_g1 for tru_g1).",
        choices=INIT_SCHEMES,
    ),
)
#: Options of weight training only.
WEIGHT_OPTIONS: tuple[Option, ...] = (
    Option(
        "features",
        "str_list",
        None,
        "Input feature columns of the weight networks.",
        metavar="A,B,...",
        default_text="all features of the point model",
    ),
    Option("hidden", "int_list", [5], "Hidden layer sizes.", metavar="N,N"),
    Option(
        "select",
        "str",
        None,
        "Selection function on realizations; rows outside get no weight, "
        'e.g. "snr > 10 & adamom_sigma > 1.5".',
        metavar="EXPR",
    ),
)
POINT_OPTION = {o.name: o for o in POINT_OPTIONS}
WEIGHT_OPTION = {o.name: o for o in WEIGHT_OPTIONS}

#: The options whose values are selection expressions, and whether on cases (aggregates of
#: their realizations) or on realizations.
SELECTIONS = {"select_cases": True, "select": False}


def train_options(kind: str) -> tuple[Option, ...]:
    """The training options of a ``"point"`` or ``"weight"`` committee (its iteration default)."""
    return tuple(
        o.with_default(ITERATIONS[kind]) if o.name == "iterations" else o for o in TRAIN_OPTIONS
    )


def check_train_values(
    values: Mapping[str, Any], where: str = "", defaults: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """The values of :data:`TRAIN_OPTIONS` (option name -> value; missing ones from
    ``defaults``, then the declared defaults), checked, with ``keep <= members``; errors name
    the config key ``where.name``."""
    table = Table(values, where, set(OPTION))
    defaults = defaults or {}
    out = {o.name: table.option(o, defaults.get(o.name)) for o in TRAIN_OPTIONS}
    if out["keep"] is not None and out["keep"] > out["members"]:
        raise ConfigError(
            f"{table.key('keep')}: must be <= {table.key('members')} ({out['members']}), "
            f"got {out['keep']}"
        )
    return out


class TrainSpec:
    """What a committee training is, the base of :data:`PointSpec` and :data:`WeightSpec`:
    frozen dataclasses with one field per declaration of :attr:`OPTIONS`, named as the
    option, with its declared default. A pipeline step's parameters are
    ``dataclasses.asdict(spec)``; the step trains with the spec rebuilt from them."""

    #: The declarations of the fields, in order.
    OPTIONS: ClassVar[tuple[Option, ...]] = ()
    #: ``"point"`` or ``"weight"``.
    KIND: ClassVar[str] = ""

    @classmethod
    def from_values(
        cls, values: Mapping[str, Any], where: str = "", defaults: Mapping[str, Any] | None = None
    ) -> Any:
        """The spec of option values by name: those of :data:`TRAIN_OPTIONS` checked and
        converted (missing ones from ``defaults``, then the declared defaults; errors name
        ``where.<name>``), the others as given (missing ones: their declared defaults)."""
        own = {o.name: o.default for o in cls.OPTIONS if o.name in OPTION}
        shared = {k: v for k, v in values.items() if k in OPTION}
        checked = check_train_values(shared, where, {**own, **(defaults or {})})
        return cls(**{k: v for k, v in values.items() if k not in OPTION}, **checked)

    def train_values(self) -> dict[str, Any]:
        """The values of :data:`TRAIN_OPTIONS` (shared by point and weight training), by name."""
        return {o.name: getattr(self, o.name) for o in TRAIN_OPTIONS}

    def check(self) -> None:
        """Check the values of :data:`TRAIN_OPTIONS` against their declarations (errors name
        the option), with ``keep <= members``."""
        check_train_values(self.train_values())


#: The Python type of a field, by kind of option.
_FIELD_TYPES: dict[str, Any] = {
    "int": int,
    "float": float,
    "str": str,
    "bool": bool,
    "choice": str,
    "str_list": list[str],
    "int_list": list[int],
}


def spec_class(name: str, kind: str, options: tuple[Option, ...], doc: str) -> type[TrainSpec]:
    """A frozen dataclass of ``options``: one field per declaration, its declared default (a
    fresh copy of a list), ``None`` allowed where the default is ``None``."""

    def spec_field(o: Option) -> tuple[str, Any, Any]:
        kind_type = _FIELD_TYPES[o.kind]
        if isinstance(o.default, list):
            return o.name, kind_type | None, field(default_factory=partial(list, o.default))
        field_type = kind_type | None if o.default is None else kind_type
        return o.name, field_type, field(default=o.default)

    namespace = {"__doc__": doc, "__module__": __name__, "OPTIONS": options, "KIND": kind}
    return make_dataclass(
        name, [spec_field(o) for o in options], bases=(TrainSpec,), frozen=True, namespace=namespace
    )


#: A point training: :data:`POINT_OPTIONS` then the training options. ``features`` and
#: ``hidden`` ``None``: those of the model it continues (else their defaults).
PointSpec = spec_class(
    "PointSpec",
    "point",
    POINT_OPTIONS + train_options("point"),
    "A point training (MSB or MSE): one field per declaration of POINT_OPTIONS and TRAIN_OPTIONS.",
)
#: A weight training: :data:`WEIGHT_OPTIONS` then the training options (300 iterations).
#: ``features`` ``None``: those of the point model.
WeightSpec = spec_class(
    "WeightSpec",
    "weight",
    WEIGHT_OPTIONS + train_options("weight"),
    "A weight training (MSWB): one field per declaration of WEIGHT_OPTIONS and TRAIN_OPTIONS.",
)
