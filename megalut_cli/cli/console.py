"""What a person sees on the terminal: log setup, progress bars, ``-`` for stdin/stdout.

Logs and progress go to stderr only. ``-v`` shows megalut's debug lines, ``-vv`` also
those of third-party libraries (h5py, numba, distributed...), which otherwise stay at
WARNING. A progress bar is drawn only on an interactive terminal (never in CI, where
``CI`` is set, nor in a pipe); a log line printed while a bar is shown clears the bar's
line first, so the bar is redrawn on a line of its own.

``-`` as an input catalog reads all of stdin into a temporary file (FITS readers need to
seek); ``-`` as an output writes a temporary file, then copies it to stdout. Both
temporary files live in the system's temporary folder (``TMPDIR``) and are removed when
the command ends, interrupted or not: streaming costs disk space equal to the catalog's
size, not memory.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import click

from megalut_cli.progress import format_duration

#: The package's logger, parent of every module's ``logging.getLogger(__name__)``.
PACKAGE_LOGGER = "megalut_cli"
#: The name that stands for stdin (inputs) or stdout (outputs).
STDIO = "-"

#: Off a terminal, an info line estimates the time left once a tenth of the work is done
#: (and every unit running at once has reported), if that took at least this long (the bar
#: shows its own estimate on a terminal); it is redone from the pace since the last line once
#: each further quarter is done and at least this long has passed.
ESTIMATE_AFTER_SECONDS = 20.0

log = logging.getLogger(__name__)
_bar_shown = False
#: Temporary files standing for stdin/stdout -> the name a person should read instead.
_STREAM_NAMES: dict[str, str] = {}


def user_facing(text: str) -> str:
    """``text`` with the temporary files of ``-`` named ``stdin``/``stdout`` as the user knows
    them."""
    for path, name in _STREAM_NAMES.items():
        text = text.replace(path, name)
    return text


class BarAwareHandler(logging.StreamHandler):
    """Log to the current ``sys.stderr``, clearing a progress bar's line first."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)
        self.setFormatter(logging.Formatter("megalut: %(message)s"))

    def format(self, record: logging.LogRecord) -> str:
        return user_facing(super().format(record))

    def emit(self, record: logging.LogRecord) -> None:
        self.stream = sys.stderr  # follows redirections (CliRunner, contextlib.redirect_stderr)
        if _bar_shown:
            self.stream.write("\r\x1b[K")
        super().emit(record)


def setup_logging(verbosity: int) -> None:
    """Log level from ``-v`` count minus ``-q`` count: 0 info, 1 debug, -1 warning, ...

    Third-party loggers stay at WARNING unless ``verbosity >= 2``.
    """
    level = max(logging.DEBUG, min(logging.INFO - 10 * verbosity, logging.CRITICAL))
    root = logging.getLogger()
    for handler in list(root.handlers):
        if isinstance(handler, BarAwareHandler):
            root.removeHandler(handler)
    root.addHandler(BarAwareHandler())
    root.setLevel(level if verbosity >= 2 else max(level, logging.WARNING))
    logging.getLogger(PACKAGE_LOGGER).setLevel(level)
    logging.captureWarnings(True)


def interactive() -> bool:
    """Whether progress bars are drawn: stderr is a terminal and this is not CI."""
    return (
        sys.stderr.isatty() and not os.environ.get("CI") and log.getEffectiveLevel() <= logging.INFO
    )


@contextlib.contextmanager
def progress(label: str, length: int, parallel: int = 1) -> Iterator[Callable[[int], None]]:
    """A progress callback: a bar on an interactive terminal; elsewhere debug lines and a few
    estimates of the time left. The first waits for ``parallel`` updates (units that ran at
    once finish together: the first alone would give a pace ``parallel`` times too slow) and
    takes the pace since the start; each later one, a quarter of the work further on, takes
    the pace since the line before, so that a slow first round (twice as long as the next
    on 10^6-stamp CRN sets, measured) does not carry over."""
    global _bar_shown
    if interactive() and length > 0:
        with click.progressbar(
            length=length, label=label, file=sys.stderr, show_pos=True, show_eta=True
        ) as bar:
            _bar_shown = True
            try:
                yield bar.update
            finally:
                _bar_shown = False
        return
    done = 0
    step = max(1, length // 10)
    start = time.perf_counter()
    updates = 0
    last: tuple[int, float] | None = None  # (done, elapsed) at the last estimate

    def update(n: int) -> None:
        nonlocal done, updates, last
        before = done
        done += n
        updates += 1
        if done // step != before // step or done == length:
            log.debug("%s: %d/%d", label, done, length)
        elapsed = time.perf_counter() - start
        if done >= length or updates < parallel:
            return
        since_done, since = last or (0, 0.0)  # the pace since the start, then the last line
        gap = step if last is None else max(parallel, length // 4)
        if done - since_done >= gap and elapsed - since >= ESTIMATE_AFTER_SECONDS:
            last = (done, elapsed)  # for long jobs off a terminal
            pace = (elapsed - since) / (done - since_done)
            log.info(
                "%s: %d/%d in %s, about %s left",
                label,
                done,
                length,
                format_duration(elapsed),
                format_duration(pace * (length - done)),
            )

    yield update


def is_stdio(path: str | os.PathLike | None) -> bool:
    """Whether ``path`` is ``-`` (stdin or stdout)."""
    return path is not None and str(path) == STDIO


@contextlib.contextmanager
def stdin_path(path: str | None, what: str = "catalog") -> Iterator[str | None]:
    """``path`` as it is, or for ``-`` a temporary copy of all of stdin (removed at the end)."""
    if not is_stdio(path):
        yield path
        return
    stream = sys.stdin.buffer
    if stream.isatty():
        raise click.UsageError(
            f"'-' reads the {what} from stdin, but stdin is a terminal; pipe a file in"
        )
    with tempfile.TemporaryDirectory(prefix="megalut-stdin-") as tmp:
        target = Path(tmp) / "stdin.fits"
        _STREAM_NAMES[str(target)] = "stdin"
        with open(target, "wb") as f:
            shutil.copyfileobj(stream, f, 1 << 20)
        if target.stat().st_size == 0:
            raise click.ClickException(f"stdin: no {what} was piped in (empty input)")
        yield str(target)


@contextlib.contextmanager
def stdout_path(path: str | None, name: str = "stdout.fits") -> Iterator[str | None]:
    """``path`` as it is, or for ``-`` a temporary file whose content goes to stdout at the end."""
    if not is_stdio(path):
        yield path
        return
    if sys.stdout.isatty():
        raise click.UsageError(
            "'-o -' writes a FITS file to stdout, but stdout is a terminal; "
            "redirect it (> file.fits) or pipe it into another command"
        )
    with tempfile.TemporaryDirectory(prefix="megalut-stdout-") as tmp:
        target = Path(tmp) / name
        _STREAM_NAMES[str(target)] = "stdout"
        yield str(target)
        if target.exists():
            out = sys.stdout.buffer
            with open(target, "rb") as f:
                shutil.copyfileobj(f, out, 1 << 20)
            out.flush()


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
    """``-v/--verbose`` and ``-q/--quiet``, accepted before and after the subcommand (they add
    up)."""
    return [
        click.Option(
            ["-v", "--verbose"],
            count=True,
            expose_value=False,
            callback=_count_verbosity,
            help="More log output: -v megalut's debug lines, -vv also third-party libraries'.",
        ),
        click.Option(
            ["-q", "--quiet"],
            count=True,
            expose_value=False,
            callback=_count_verbosity,
            help="Less log output: -q warnings and errors only, -qq errors only.",
        ),
    ]


def flag_names(command: click.Command | None = None, **renamed: str) -> dict[str, str]:
    """How the library's messages name its arguments on this command line.

    Every parameter of ``command`` (default: the running one) by its first flag
    (``stamp_size`` -> ``--stamp-size``, ``output`` -> ``-o``), an argument by its metavar
    (``CONFIG``); ``renamed`` gives the library arguments whose name is not the
    parameter's (``psf_path="--psf"``). Passed as ``names=`` to library calls.
    """
    command = command or click.get_current_context().command
    out: dict[str, str] = {}
    for param in command.params:
        if param.name is None:
            continue
        if isinstance(param, click.Option):
            out[param.name] = param.opts[0]
        else:
            out[param.name] = param.human_readable_name
    return {**out, **renamed}
