"""Imported first by the server that local workers are forked from (``-j N``).

:func:`megalut_cli.parallel.start_worker_server` starts that server as a command starts;
Ctrl-C is the command's to handle (one line, exit 130), so the server and its workers ignore
it. A worker that cannot start because the command has already gone (interrupted while its
workers started: the pool's pipes and semaphores are gone) exits without a traceback.
When the command has gone, the server leaves at once, without Python's teardown of the
modules it preloaded (0.15-0.25 s, during which it kept the command's stdout and stderr open:
a reader of the command's output waited for it).
"""

import atexit
import signal
import sys
from types import TracebackType

from megalut_cli.leave import leave_now

signal.signal(signal.SIGINT, signal.SIG_IGN)


def _quiet_when_orphaned(
    kind: type[BaseException], value: BaseException, tb: TracebackType | None
) -> None:
    """The server calls the hook only when a worker fails to start; an OS or end-of-file
    error there means that the command left."""
    if issubclass(kind, (OSError, EOFError)):
        return
    sys.__excepthook__(kind, value, tb)


sys.excepthook = _quiet_when_orphaned


atexit.register(leave_now, 0)  # the last handler, so it runs first; workers use os._exit
