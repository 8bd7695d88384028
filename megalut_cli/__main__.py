"""The ``megalut`` program: the console script (``megalut_cli.__main__:run``) and
``python -m megalut_cli``.

Ctrl-C prints one line and exits with 130 at any moment. The command group handles it while
a command runs (temporary outputs are removed on the way up); :func:`run` covers the
moments around that: while click and megalut are imported (about 0.1 s, before the group
exists), and while the process exits. Python's own handler would print a traceback there.
Nothing is imported before the handler is in place (``os``, ``sys``, ``types`` and ``_signal``
are loaded with the interpreter; ``signal`` would cost its enums first). Before this module
runs, while the interpreter itself starts (its ``site`` module), a Ctrl-C is Python's own
"Fatal Python error", which no program can handle.
"""

from __future__ import annotations

import os
import sys
from types import FrameType

try:  # the C module behind ``signal``, already loaded
    import _signal as signal
except ImportError:  # pragma: no cover - a Python without it
    import signal  # type: ignore[no-redef]

#: Exit status after Ctrl-C (128 + SIGINT, as shells report it); the group's ``EXIT_INTERRUPTED``.
EXIT_INTERRUPTED = 130


def interrupted(signum: int = signal.SIGINT, frame: FrameType | None = None) -> None:
    """Leave now, with one line and status 130 (a SIGINT handler, where nothing is half-written)."""
    try:
        sys.stderr.write("megalut: interrupted\n")
        sys.stderr.flush()
    except (OSError, ValueError):  # a closed stderr: the status says it
        pass
    os._exit(EXIT_INTERRUPTED)


def run() -> None:
    """Run ``megalut`` with the command line of the process."""
    signal.signal(signal.SIGINT, interrupted)  # until the group handles Ctrl-C itself
    from megalut_cli.cli import main  # click and megalut: the imports of every command

    signal.signal(
        signal.SIGINT, signal.default_int_handler
    )  # KeyboardInterrupt: outputs cleaned up
    try:
        main()
    except SystemExit:  # the command is over: a Ctrl-C while the process exits is one line too
        signal.signal(signal.SIGINT, interrupted)
        raise
    except KeyboardInterrupt:  # outside the group's handling (between its steps)
        interrupted()


if __name__ == "__main__":
    run()
