"""Options shared by several subcommands, defined once."""

from __future__ import annotations

import contextlib
import functools
import logging
import sys
from collections.abc import Callable, Iterator
from typing import Any

import click

log = logging.getLogger("megalut")

F = Callable[..., Any]


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


def seed_option(default: int = 1, help: str = "Seed of every random draw of this step.") -> Callable[[F], F]:
    return click.option("--seed", type=int, default=default, show_default=True, help=help)


def output_option(help: str = "Output file.") -> Callable[[F], F]:
    return click.option(
        "-o", "--output", "output", required=True, type=click.Path(dir_okay=False), help=help
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
        default=1,
        show_default=True,
        help="Local worker processes (0 or less: all cores).",
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
        from megalut_cli.training import TrainOptions

        options = TrainOptions(dtype=kwargs.pop("precision"), **{k: kwargs.pop(k) for k in _TRAIN_OPTION_FIELDS})
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


@contextlib.contextmanager
def progress(label: str, length: int) -> Iterator[Callable[[int], None]]:
    """A progress callback: a bar on an interactive terminal, log lines otherwise."""
    interactive = sys.stderr.isatty() and log.getEffectiveLevel() <= logging.INFO
    if interactive and length > 0:
        with click.progressbar(length=length, label=label, file=sys.stderr, show_pos=True) as bar:
            yield bar.update
        return
    done = 0
    step = max(1, length // 10)

    def update(n: int) -> None:
        nonlocal done
        before = done
        done += n
        if done // step != before // step or done == length:
            log.info("%s: %d/%d", label, done, length)

    yield update
