"""The ``megalut`` command-line interface: a thin click layer over the library.

One module per subcommand; options shared between them live in :mod:`.options`.
Library errors (:class:`megalut_cli.errors.MegalutError`) become one-line messages with
exit code 1 (runtime) or 2 (usage/configuration); click's own usage errors exit with 2;
Ctrl-C prints one line and exits with 130 (while click and megalut are imported, before the
group exists: :mod:`megalut_cli.__main__`, the console script's entry point).
"""

from __future__ import annotations

import atexit
import importlib
import logging
import os
import sys
from typing import Any

import click

from megalut_cli import __version__
from megalut_cli.cli.commands import COMMANDS
from megalut_cli.cli.console import (
    flag_names,
    setup_logging,
    user_facing,
    verbosity,
    verbosity_options,
)
from megalut_cli.errors import ArgumentError, HintError, MegalutError, OutputExistsError
from megalut_cli.leave import leave_now
from megalut_cli.provenance import set_command_line

log = logging.getLogger(__name__)

#: Exit status after Ctrl-C (128 + SIGINT, as shells report it).
EXIT_INTERRUPTED = 130


#: The exit status of the ``megalut`` process, once its command has finished.
_exit_status: list[int] = []


def _exit_now() -> None:
    """Leave the process with its exit status once the other exit handlers have run, without
    Python's teardown of every module and object: 0.3–0.8 s after a command that imported
    GalSim and numba (benchmarks/startup.md). Outputs are closed and renamed by then."""
    logging.shutdown()
    leave_now(_exit_status[0] if _exit_status else 1)


class MegalutGroup(click.Group):
    """A group that reports library errors as one clear line instead of a traceback."""

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        """``megalut`` as the shell runs it (``click.testing`` calls :meth:`main` instead):
        exits through :func:`_exit_now`, registered first so that it runs last."""
        atexit.register(_exit_now)
        try:
            return super().__call__(*args, **kwargs)
        except SystemExit as done:  # click's standalone mode always ends here
            code = done.code
            _exit_status.append(code if isinstance(code, int) else (0 if code is None else 1))
            raise
        except KeyboardInterrupt:  # before click could handle it (e.g. while importing)
            _exit_status.append(EXIT_INTERRUPTED)
            raise

    def main(self, args: Any = None, prog_name: str | None = None, **kwargs: Any) -> Any:
        argv = list(args) if args is not None else sys.argv[1:]
        set_command_line(["megalut", *argv])  # recorded in every output's HISTORY
        return super().main(args=args, prog_name=prog_name, **kwargs)

    def make_context(
        self,
        info_name: str | None,
        args: list[str],
        parent: click.Context | None = None,
        **extra: Any,
    ) -> click.Context:
        """The group's context; Ctrl-C while its options are read (``--help``, ``--version``) is
        one line and 130, not click's "Aborted!" and 1."""
        try:
            return super().make_context(info_name, args, parent=parent, **extra)
        except KeyboardInterrupt:
            click.echo("megalut: interrupted", err=True)
            raise click.exceptions.Exit(EXIT_INTERRUPTED) from None

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)  # the order of the data flow, not alphabetical

    def get_command(self, ctx: click.Context | None, cmd_name: str) -> click.Command | None:
        """The subcommand ``cmd_name``, its module imported on first use (fast start-up)."""
        if cmd_name not in self.commands and cmd_name in COMMANDS:
            command = importlib.import_module(COMMANDS[cmd_name][0]).command
            command.params.extend(verbosity_options())
            self.add_command(command, cmd_name)
        return self.commands.get(cmd_name)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """The subcommands and their one-line help, without importing them."""
        with formatter.section("Commands"):
            formatter.write_dl([(name, text) for name, (_, text) in COMMANDS.items()])

    def message(self, ctx: click.Context, err: MegalutError) -> str:
        """A library error in the words of the command line: an argument it names becomes
        the running subcommand's flag (``workdir`` -> ``--workdir``)."""
        if isinstance(err, OutputExistsError):
            return err.named("--overwrite")
        if not isinstance(err, (ArgumentError, HintError)):
            return str(err)
        command = self.get_command(ctx, ctx.invoked_subcommand or "")
        flags = flag_names(command) if command is not None else {}

        def flag(argument: str) -> str:
            return flags.get(argument, "--" + argument.replace("_", "-"))

        if isinstance(err, ArgumentError):
            return err.named(flag(err.argument))
        return err.named({a: flag(a) for a in err.arguments})

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except MegalutError as err:
            exc = click.ClickException(user_facing(self.message(ctx, err)))
            exc.exit_code = err.exit_code
            raise exc from None
        except KeyboardInterrupt:
            # Temporary outputs are removed on the way up (atomic_output, console).
            click.echo("megalut: interrupted", err=True)
            ctx.exit(EXIT_INTERRUPTED)
        except BrokenPipeError:
            # Output piped into a command that stopped reading (e.g. `| head`): exit quietly.
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            ctx.exit(0)
        except (click.exceptions.Exit, click.ClickException, click.Abort):
            raise
        except MemoryError:
            raise click.ClickException(
                "out of memory; use smaller chunks or more workers"
            ) from None
        except OSError as err:
            where = f"{err.filename}: " if getattr(err, "filename", None) else ""
            raise click.ClickException(user_facing(f"{where}{err.strerror or err}")) from None
        except Exception as err:  # a bug: say so plainly, traceback with -v
            log.debug("internal error", exc_info=True)
            raise click.ClickException(
                f"internal error ({type(err).__name__}: {err}); run with -v for the traceback"
            ) from None


@click.group(
    cls=MegalutGroup,
    context_settings={"help_option_names": ["-h", "--help"]},
    short_help="Weak-lensing shear measurement with machine learning.",
)
@click.version_option(__version__, "--version", prog_name="megalut")
def main() -> None:
    """Weak-lensing shear measurement with machine learning (Tewes et al. 2019).

    Simulate galaxies with known shear, measure adaptive-moment features, train neural
    network committees with the mean-square-bias cost, predict shear estimates and
    weights for any stamp catalog, and evaluate multiplicative and additive biases.

    A small end-to-end run: 3000 training and 4000 validation stamps, 60 training
    iterations; 1.5 min measured on a busy 2-core machine.

    \b
    Example:
      megalut simulate examples/fiducial/tp.toml -o tp.fits --measure \\
          --n-cases 60 --n-realizations 50
      megalut train-point tp.fits -o model.h5 \\
          --select-cases "mean(snr) > 10" --iterations 60
      megalut simulate examples/fiducial/vo.toml -o vo.fits --measure \\
          --n-cases 20 --n-realizations 200
      megalut predict vo.fits --model model.h5 -o shears.fits
      megalut evaluate shears.fits

    Stamps to biases in one shell pipeline ('-' is stdin or stdout; logs go to stderr):

    \b
    Example:
      megalut measure stamps.fits cat.fits -o - \\
          | megalut predict - --model model.h5 -o - | megalut evaluate -

    -j/--nproc defaults to all cores (env MEGALUT_NPROC); -v/-q work before or after the
    subcommand. Exit status: 0 success, 1 runtime error, 2 usage error, 130 interrupted.
    """
    setup_logging(verbosity(click.get_current_context()))


main.params.extend(verbosity_options())
