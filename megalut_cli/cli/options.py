"""Options shared by several subcommands, defined once."""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
from typing import Any

import click

from megalut_cli.cli.console import progress as progress
from megalut_cli.cli.console import setup_logging

log = logging.getLogger("megalut")

F = Callable[..., Any]


#: Where the group and its subcommands add up their -v and -q counts.
_VERBOSITY_KEY = "megalut.verbosity"


def _count_verbosity(ctx: click.Context, param: click.Parameter, value: int) -> int:
    if value:
        root = ctx.find_root()
        sign = 1 if param.name == "verbose" else -1
        root.meta[_VERBOSITY_KEY] = root.meta.get(_VERBOSITY_KEY, 0) + sign * value
        setup_logging(root.meta[_VERBOSITY_KEY])
    return value


def verbosity(ctx: click.Context) -> int:
    """The -v count minus the -q count given so far, before and after the subcommand."""
    return int(ctx.find_root().meta.get(_VERBOSITY_KEY, 0))


def verbosity_options() -> list[click.Option]:
    """``-v/--verbose`` and ``-q/--quiet``, accepted before and after the subcommand (they add up)."""
    return [
        click.Option(
            ["-v", "--verbose"], count=True, expose_value=False, callback=_count_verbosity,
            help="More log output: -v megalut's debug lines, -vv also third-party libraries'.",
        ),
        click.Option(
            ["-q", "--quiet"], count=True, expose_value=False, callback=_count_verbosity,
            help="Less log output: -q warnings and errors only, -qq errors only.",
        ),
    ]


def overwrite_option(f: F) -> F:
    return click.option(
        "--overwrite", is_flag=True, help="Replace the output file if it exists."
    )(f)


def engine_option(what: str) -> Callable[[F], F]:
    """``--engine``: choices and descriptions from :data:`megalut_cli.engine.ENGINES`."""
    from megalut_cli.engine import DEFAULT_ENGINE, ENGINES

    described = "; ".join(f"{name}: {text}" for name, text in ENGINES.items())
    return click.option(
        "--engine",
        type=click.Choice(list(ENGINES)),
        default=DEFAULT_ENGINE,
        show_default=True,
        help=f"How {what} ({described}).",
    )


def device_option(what: str) -> Callable[[F], F]:
    """``--device``: choices and descriptions from :data:`megalut_cli.engine.DEVICES`."""
    from megalut_cli.engine import DEFAULT_DEVICE, DEVICES

    described = "; ".join(f"{name}: {text}" for name, text in DEVICES.items())
    return click.option(
        "--device",
        type=click.Choice(list(DEVICES)),
        default=DEFAULT_DEVICE,
        show_default=True,
        envvar="MEGALUT_DEVICE",
        help=f"Where {what} ({described}; env MEGALUT_DEVICE; docs/gpu.md).",
    )


def seed_option(default: int = 1, help: str = "Seed of every random draw of this step.") -> Callable[[F], F]:
    return click.option("--seed", type=int, default=default, show_default=True, help=help)


def _no_dash(ctx: click.Context, param: click.Parameter, value: str | None) -> str | None:
    if value == "-":
        raise click.BadParameter("this output cannot go to stdout ('-'); name a file")
    return value


def output_option(help: str = "Output file.", dash: bool = False) -> Callable[[F], F]:
    """``-o/--output``; with ``dash``, ``-o -`` writes the file to stdout, else ``-`` is refused
    (never a file named ``-``)."""
    return click.option(
        "-o", "--output", "output", required=True, type=click.Path(dir_okay=False, allow_dash=dash),
        callback=None if dash else _no_dash, help=help + (" '-': stdout." if dash else ""),
    )


def execution_options(f: F) -> F:
    """``-j/--nproc`` and ``--scheduler`` (mutually exclusive)."""
    f = click.option(
        "--scheduler",
        metavar="ADDR",
        default=None,
        help="Run on an existing Dask cluster: a scheduler address (tcp://host:8786) "
        "or a scheduler file. Needs the 'dask' extra.",
    )(f)
    f = click.option(
        "-j",
        "--nproc",
        type=int,
        default=0,
        show_default=True,
        envvar="MEGALUT_NPROC",
        help="Local worker processes (0 or less: all cores; env MEGALUT_NPROC). "
        "Results are identical for any value.",
    )(f)

    @functools.wraps(f)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        ctx = click.get_current_context()
        nproc_given = ctx.get_parameter_source("nproc") == click.core.ParameterSource.COMMANDLINE
        if kwargs.get("scheduler") and nproc_given:
            raise click.UsageError("-j/--nproc and --scheduler are mutually exclusive")
        return f(*args, **kwargs)

    return wrapper


def _stack(*decorators: Callable[[F], F]) -> Callable[[F], F]:
    """Apply option decorators so that they appear in ``--help`` in the order given."""

    def decorate(f: F) -> F:
        for d in reversed(decorators):
            f = d(f)
        return f

    return decorate


# Options of train-point and train-weight, in three groups so that each command keeps its
# own order of options in --help; ``pass_train_options`` gathers their values.


def validation_options(valid_help: str) -> Callable[[F], F]:
    """``--valid FILE`` and ``--valid-fraction`` of the training commands."""
    return _stack(
        click.option("--valid", type=click.Path(exists=True, dir_okay=False), default=None, help=valid_help),
        click.option(
            "--valid-fraction",
            type=click.FloatRange(0.0, 1.0, max_open=True),
            default=0.2,
            help="Fraction of the training cases held out for validation when no --valid is given (0: none).",
        ),
    )


def committee_options(iterations_default: int) -> Callable[[F], F]:
    """``--members``, ``--keep``, ``--iterations``, ``--batch-fraction``, ``--batch-iterations``."""
    return _stack(
        click.option("--members", type=click.IntRange(1), default=8, help="Networks per committee."),
        click.option(
            "--keep", type=click.IntRange(1), default=None, help="Members kept (lowest validation cost). [default: half]"
        ),
        click.option(
            "--iterations", type=click.IntRange(1), default=iterations_default, help="Optimizer iterations per member."
        ),
        click.option(
            "--batch-fraction",
            type=click.FloatRange(0.0, 1.0, min_open=True),
            default=0.25,
            help="Fraction of the training cases in each mini-batch (1: full batch).",
        ),
        click.option("--batch-iterations", type=click.IntRange(1), default=30, help="Iterations on each mini-batch."),
    )


def optimizer_options(f: F) -> F:
    """``--normalization``, ``--optimizer``, ``--precision`` and ``--seed`` of the training commands."""
    return _stack(
        click.option(
            "--normalization",
            type=click.Choice(["minmax", "robust"]),
            default="minmax",
            help="Input scaling: training range to [-1, 1] (paper), or 1st-99th percentile to [-1, 1].",
        ),
        click.option("--optimizer", type=click.Choice(["bfgs", "lbfgs"]), default="bfgs", help="scipy optimizer."),
        click.option(
            "--precision",
            type=click.Choice(["float64", "float32"]),
            default="float64",
            help="Arithmetic of the network passes during training (float32 is about twice as fast).",
        ),
        seed_option(1, "Seed of the random draws (initial parameters, mini-batches, validation split)."),
        device_option("the costs and gradients are computed"),
    )(f)


#: Parameters of the training option groups that are fields of ``TrainOptions`` as they are
#: (``--precision`` is its ``dtype``).
_TRAIN_OPTION_FIELDS = (
    "members", "keep", "iterations", "batch_fraction", "batch_iterations", "valid_fraction",
    "normalization", "optimizer", "seed",
)


def pass_train_options(f: Callable[..., Any]) -> F:
    """Pass the values of the training option groups to ``f`` as one ``options: TrainOptions``."""

    @functools.wraps(f)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        from megalut_cli.engine import resolve_device
        from megalut_cli.training import TrainOptions

        options = TrainOptions(dtype=kwargs.pop("precision"), device=resolve_device(kwargs.pop("device")),
                               **{k: kwargs.pop(k) for k in _TRAIN_OPTION_FIELDS})
        return f(*args, options=options, **kwargs)

    return wrapper


def parse_list(value: str | None, what: str = "list") -> list[str] | None:
    """Split a comma-separated option value (``a,b,c``)."""
    if value is None:
        return None
    items = [v.strip() for v in value.split(",") if v.strip()]
    if not items:
        raise click.BadParameter(f"empty {what}")
    return items


def parse_int_list(value: str | None, what: str = "list") -> list[int] | None:
    items = parse_list(value, what)
    if items is None:
        return None
    try:
        out = [int(v) for v in items]
    except ValueError:
        raise click.BadParameter(f"{what} must be comma-separated integers, got {value!r}") from None
    if any(v <= 0 for v in out):
        raise click.BadParameter(f"{what} must be positive integers, got {value!r}")
    return out



#: How the training library's messages name its arguments on the command line.
TRAINING_FLAGS = {
    "select_cases": "--select-cases", "select": "--select", "hidden": "--hidden", "valid": "--valid FILE",
    "valid_fraction": "--valid-fraction", "output": "-o",
}
