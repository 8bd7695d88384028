"""Options shared by several subcommands, defined once."""

from __future__ import annotations

import functools
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from megalut_cli.atomic import OVERWRITE_OPTION
from megalut_cli.cli.commands import WORKER_MODULES
from megalut_cli.cli.console import progress as progress
from megalut_cli.engine import (
    DEVICE_OPTION,
    DEVICES,
    ENGINE_OPTION,
    ENGINES,
    described,
    resolve_device,
)
from megalut_cli.errors import InputError
from megalut_cli.measure.feature_sets import set_options
from megalut_cli.nn.options import (
    COMMITTEE_OPTIONS,
    OPTIMIZER_OPTIONS,
    VALIDATION_OPTIONS,
    TrainSpec,
    train_options,
)
from megalut_cli.nn.shipped import SHIPPED_MODELS, shipped_model
from megalut_cli.parallel import NPROC_OPTION, SCHEDULER_OPTION, resolve_nproc, start_worker_server
from megalut_cli.schema import Option
from megalut_cli.seeding import SEED_OPTION

log = logging.getLogger(__name__)

F = Callable[..., Any]


def overwrite_option(f: F) -> F:
    """``--overwrite`` (:data:`megalut_cli.atomic.OVERWRITE_OPTION`)."""
    return schema_option(OVERWRITE_OPTION)(f)


def engine_option(what: str) -> Callable[[F], F]:
    """``--engine`` (:data:`megalut_cli.engine.ENGINE_OPTION`), saying what the engine does here."""
    return schema_option(
        ENGINE_OPTION, help=f"How {what} ({described(ENGINES)}).", show_default=True
    )


def device_option(what: str) -> Callable[[F], F]:
    """``--device`` (:data:`megalut_cli.engine.DEVICE_OPTION`), saying what runs there."""
    return schema_option(
        DEVICE_OPTION,
        help=f"Where {what} ({described(DEVICES)}; env MEGALUT_DEVICE; docs/gpu.md).",
        show_default=True,
    )


def seed_option(default: int = 1, help: str | None = None) -> Callable[[F], F]:
    """``--seed`` (:data:`megalut_cli.seeding.SEED_OPTION`) with this command's default and help."""
    return schema_option(SEED_OPTION.with_default(default), help=help, show_default=True)


def _no_dash(ctx: click.Context, param: click.Parameter, value: str | None) -> str | None:
    if value == "-":
        raise click.BadParameter("this output cannot go to stdout ('-'); name a file")
    return value


def output_option(help: str = "Output file.", dash: bool = False) -> Callable[[F], F]:
    """``-o/--output``; with ``dash``, ``-o -`` writes the file to stdout, else ``-`` is refused
    (never a file named ``-``)."""
    return click.option(
        "-o",
        "--output",
        "output",
        required=True,
        type=click.Path(dir_okay=False, allow_dash=dash),
        callback=None if dash else _no_dash,
        help=help + (" '-': stdout." if dash else ""),
    )


def _plot_suffix(ctx: click.Context, param: click.Parameter, value: str | None) -> str | None:
    """``--plot``'s file type, checked while the options are read (a usage error, before any
    work)."""
    if value is not None:
        from megalut_cli.errors import ArgumentValueError
        from megalut_cli.shear.plots import check_plot_suffix  # SciPy, fitsio: not for --help

        try:
            check_plot_suffix(value)
        except ArgumentValueError as err:
            raise click.BadParameter(err.rest.lstrip(": "), ctx, param) from None
    return value


def plot_option(what: str) -> Callable[[F], F]:
    """``--plot PATH``: draw ``what`` into a .png/.pdf/.svg (its type checked up front)."""
    return click.option(
        "--plot",
        "plot_path",
        type=click.Path(dir_okay=False),
        default=None,
        callback=_plot_suffix,
        help=f"Draw {what} into this .png/.pdf/.svg (needs matplotlib: pip install matplotlib).",
    )


def given_on_command_line(name: str) -> bool:
    """Whether the current command's option ``name`` was typed, not left to its default."""
    source = click.get_current_context().get_parameter_source(name)
    return source == click.core.ParameterSource.COMMANDLINE


def execution_options(f: F) -> F:
    """``-j/--nproc`` and ``--scheduler`` (mutually exclusive; :mod:`megalut_cli.parallel`)."""
    f = schema_option(SCHEDULER_OPTION)(f)
    f = schema_option(NPROC_OPTION, show_default=True)(f)

    @functools.wraps(f)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        ctx = click.get_current_context()
        if kwargs.get("scheduler") and given_on_command_line("nproc"):
            raise click.UsageError("-j/--nproc and --scheduler are mutually exclusive")
        if (
            not kwargs.get("scheduler")
            and not kwargs.get("dry_run")
            and resolve_nproc(kwargs["nproc"]) > 1
        ):
            start_worker_server(WORKER_MODULES.get(ctx.command.name, ()))
        return f(*args, **kwargs)

    return wrapper


def feature_set_options(declared: dict[str, Option]) -> Callable[[F], F]:
    """The click options of the optional feature sets (``--morphology``, ...;
    :mod:`megalut_cli.measure.feature_sets`) as a command ``declared`` them, in registration
    order; the command takes them as ``**feature_flags``."""

    def decorate(f: F) -> F:
        for option in reversed(set_options()):
            f = schema_option(declared[option.name])(f)
        return f

    return decorate


def schema_option(
    option: Option, help: str | None = None, show_default: bool | None = None
) -> Callable[[F], F]:
    """The click option of a declared :class:`~megalut_cli.schema.Option`: its flags, type
    (``IntRange``/``FloatRange`` from its range, ``Choice`` from its choices), default,
    environment variable and help (``help`` replaces the declared one)."""
    kwargs: dict[str, Any] = {"default": option.default, "show_default": show_default}
    if option.kind in ("int", "float"):
        bounded = option.minimum is not None or option.maximum is not None
        if option.kind == "int":
            kwargs["type"] = click.IntRange(option.minimum, option.maximum) if bounded else int
        else:
            kwargs["type"] = (
                click.FloatRange(
                    option.minimum,
                    option.maximum,
                    min_open=option.min_open,
                    max_open=option.max_open,
                )
                if bounded
                else float
            )
    elif option.kind == "choice":
        kwargs["type"] = click.Choice(list(option.choices))
    elif option.kind == "bool":
        kwargs["is_flag"] = True
    elif option.kind == "path":
        kwargs["type"] = click.Path(dir_okay=False)
    elif option.kind in ("str_list", "int_list"):
        kwargs["default"] = (
            None if option.default is None else ",".join(str(v) for v in option.default)
        )
    if option.envvar is not None:
        kwargs["envvar"] = option.envvar
    flags = ([option.short] if option.short else []) + [option.cli_flag]
    return click.option(
        *flags, metavar=option.metavar, help=option.cli_help() if help is None else help, **kwargs
    )


def _stack(*decorators: Callable[[F], F]) -> Callable[[F], F]:
    """Apply option decorators so that they appear in ``--help`` in the order given."""

    def decorate(f: F) -> F:
        for d in reversed(decorators):
            f = d(f)
        return f

    return decorate


# Options of train-point and train-weight (megalut_cli.nn.options): the training options in
# their three declared groups, which each command places to keep its own order of options in
# --help; ``pass_spec`` gathers the values of a command's options into its training spec.


def validation_options(valid_help: str) -> Callable[[F], F]:
    """``--valid FILE`` and the validation options (``--valid-fraction``) of the training
    commands."""
    return _stack(
        click.option(
            "--valid", type=click.Path(exists=True, dir_okay=False), default=None, help=valid_help
        ),
        *(schema_option(o) for o in VALIDATION_OPTIONS),
    )


def committee_options(kind: str) -> Callable[[F], F]:
    """The committee options (``--members``, ``--keep``, ``--iterations``...) of a ``"point"``
    or ``"weight"`` training (its iteration default)."""
    options = {o.name: o for o in train_options(kind)}
    return _stack(*(schema_option(options[o.name]) for o in COMMITTEE_OPTIONS))


def optimizer_options(f: F) -> F:
    """The optimisation options (``--normalization``, ``--optimizer``, ``--precision``,
    ``--seed``) and ``--device`` of the training commands."""
    device = device_option("the costs and gradients are computed")
    # --seed shows its default even where the command's defaults are not shown (man pages), as
    # every --seed does
    options = (schema_option(o, show_default=o.name == "seed" or None) for o in OPTIMIZER_OPTIONS)
    return _stack(*options, device)(f)


def pass_spec(spec_class: type[TrainSpec]) -> Callable[[F], F]:
    """Pass the values of the options of a training command's spec to ``f`` as one
    ``spec`` (comma-separated lists split, ``--keep`` <= ``--members``), and ``device``
    resolved (:func:`megalut_cli.engine.resolve_device`)."""

    def decorate(f: F) -> F:
        @functools.wraps(f)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            values = {o.name: kwargs.pop(o.name) for o in spec_class.OPTIONS}
            if values["keep"] is not None and values["keep"] > values["members"]:
                raise click.UsageError(
                    f"--keep: must be <= --members ({values['members']}), got {values['keep']}"
                )
            device = resolve_device(kwargs.pop("device"))
            for o in spec_class.OPTIONS:
                if o.kind == "str_list":
                    values[o.name] = parse_list(values[o.name], o.cli_flag)
                elif o.kind == "int_list":
                    values[o.name] = parse_int_list(values[o.name], o.cli_flag)
            return f(*args, spec=spec_class.from_values(values), device=device, **kwargs)

        return wrapper

    return decorate


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
        raise click.BadParameter(
            f"{what} must be comma-separated integers, got {value!r}"
        ) from None
    if any(v <= 0 for v in out):
        raise click.BadParameter(f"{what} must be positive integers, got {value!r}")
    return out


class ModelFile(click.ParamType):
    """An existing file, or the name of a model shipped with megalut
    (:data:`megalut_cli.nn.shipped.SHIPPED_MODELS`), converted to its file; anything else is a
    usage error listing the shipped names. Used wherever a command takes a model."""

    name = "model"

    def __init__(self, allow_dash: bool = False) -> None:
        self.allow_dash = allow_dash

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> str:
        text = os.fspath(value)
        if Path(text).is_file() or (self.allow_dash and text == "-"):
            return text
        if text in SHIPPED_MODELS:
            try:
                return str(shipped_model(text))
            except InputError as err:
                self.fail(str(err), param, ctx)
        what = "a folder, not a file" if Path(text).is_dir() else "no such file"
        self.fail(
            f"{text!r}: {what}, nor a shipped model (shipped: {', '.join(SHIPPED_MODELS)})",
            param,
            ctx,
        )


#: The click type of a model argument: a file or a shipped model's name.
MODEL_FILE = ModelFile()
#: The same, or ``-`` for stdin (``megalut info``).
MODEL_FILE_OR_STDIN = ModelFile(allow_dash=True)


def model_help(help: str) -> str:
    """``help`` of a model option or argument, followed by the shipped models' names."""
    return (
        f"{help} Or a shipped model by name: {', '.join(SHIPPED_MODELS)} (megalut info --models)."
    )
