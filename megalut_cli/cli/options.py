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
