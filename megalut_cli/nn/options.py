"""The training options, declared once: command-line options, pipeline keys, defaults.

``megalut train-point``/``train-weight`` build their click options from these
declarations, ``[train_point]``/``[train_weight]``/``[pretrain]`` tables of pipeline files
are checked with them, :class:`megalut_cli.training.TrainOptions` takes its defaults from
them and ``docs/pipeline.md`` shows them as a generated table. Choices come from the
modules that implement them; a new training option is one more :class:`Option` here and
one field of ``TrainOptions``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from typing import Any

from megalut_cli.errors import ConfigError
from megalut_cli.nn import normalization as norm
from megalut_cli.nn.train import (
    INIT_SCHEMES,
    OPTIMIZERS,
    POINT_ITERATIONS,
    PRECISIONS,
    WEIGHT_ITERATIONS,
    TrainSettings,
)
from megalut_cli.schema import Option, Table

#: Costs a point estimator can be trained with (MSE only for comparison).
POINT_COSTS = ("msb", "mse")
#: The paper's five input features (Sect. 5.3).
DEFAULT_FEATURES = ("adamom_g1", "adamom_g2", "adamom_sigma", "adamom_flux", "adamom_rho4")

#: Options of every committee training, in the order of ``--help``. ``precision`` is
#: ``TrainOptions.dtype``.
TRAIN_OPTIONS: tuple[Option, ...] = (
    Option("valid_fraction", "float", 0.2, "Fraction of the training cases held out for validation when no "
           "--valid is given (0: none).", minimum=0.0, maximum=1.0, max_open=True),
    Option("members", "int", 8, "Networks per committee.", minimum=1),
    Option("keep", "int", None, "Members kept (lowest validation cost).", minimum=1, default_text="half"),
    Option("iterations", "int", POINT_ITERATIONS, "Optimizer iterations per member.", minimum=1),
    Option("batch_fraction", "float", TrainSettings.batch_fraction,
           "Fraction of the training cases in each mini-batch (1: full batch).",
           minimum=0.0, maximum=1.0, min_open=True),
    Option("batch_iterations", "int", TrainSettings.batch_iterations, "Iterations on each mini-batch.", minimum=1),
    Option("normalization", "choice", norm.METHODS[0], "Input scaling: training range to [-1, 1] (paper), or "
           "1st-99th percentile to [-1, 1].", choices=norm.METHODS),
    Option("optimizer", "choice", TrainSettings.optimizer, "scipy optimizer.", choices=OPTIMIZERS),
    Option("precision", "choice", TrainSettings.dtype, "Arithmetic of the network passes during training "
           "(float32 is about twice as fast).", choices=PRECISIONS),
    Option("seed", "int", 1, "Seed of the random draws (initial parameters, mini-batches, validation split).",
           minimum=0),
)
OPTION = {o.name: o for o in TRAIN_OPTIONS}

#: The declarations :class:`megalut_cli.nn.train.TrainSettings` checks a member's settings
#: with; a member may run 0 iterations (its starting parameters), the options ask for >= 1.
MEMBER_CHECKS = {
    **{n: OPTION[n] for n in ("batch_fraction", "batch_iterations", "optimizer", "precision")},
    "iterations": replace(OPTION["iterations"], minimum=0),
}

#: Iterations per member by kind of committee.
ITERATIONS = {"point": POINT_ITERATIONS, "weight": WEIGHT_ITERATIONS}

#: Options of point training only (pipeline keys of ``[train_point]``, flags of train-point).
POINT_OPTIONS: tuple[Option, ...] = (
    Option("features", "str_list", list(DEFAULT_FEATURES), "Input feature columns.", metavar="A,B,..."),
    Option("targets", "str_list", ["tru_g1", "tru_g2"], "Target columns, one committee each.", metavar="A,B"),
    Option("hidden", "int_list", [5, 5], "Hidden layer sizes.", metavar="N,N"),
    Option("cost", "choice", POINT_COSTS[0], "Cost function (MSE only for comparison).", choices=POINT_COSTS),
    Option("init", "choice", INIT_SCHEMES[0], "Starting parameters: N(0, 0.1), or near-identity on the matching "
           "feature (adamom_g1 for tru_g1).", choices=INIT_SCHEMES),
)
#: Options of weight training only.
WEIGHT_OPTIONS: tuple[Option, ...] = (
    Option("features", "str_list", None, "Input feature columns of the weight networks.", metavar="A,B,...",
           default_text="all features of the point model"),
    Option("hidden", "int_list", [5], "Hidden layer sizes.", metavar="N,N"),
)
POINT_OPTION = {o.name: o for o in POINT_OPTIONS}
WEIGHT_OPTION = {o.name: o for o in WEIGHT_OPTIONS}


def train_options(kind: str) -> tuple[Option, ...]:
    """The training options of a ``"point"`` or ``"weight"`` committee (its iteration default)."""
    return tuple(o.with_default(ITERATIONS[kind]) if o.name == "iterations" else o for o in TRAIN_OPTIONS)


def check_train_values(values: Mapping[str, Any], where: str = "",
                       defaults: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The values of :data:`TRAIN_OPTIONS` (option name -> value; missing ones from
    ``defaults``, then the declared defaults), checked, with ``keep <= members``; errors name
    the config key ``where.name``."""
    table = Table(values, where, set(OPTION))
    defaults = defaults or {}
    out = {o.name: table.option(o, defaults.get(o.name)) for o in TRAIN_OPTIONS}
    if out["keep"] is not None and out["keep"] > out["members"]:
        raise ConfigError(
            f"{table.key('keep')}: must be <= {table.key('members')} ({out['members']}), got {out['keep']}"
        )
    return out
