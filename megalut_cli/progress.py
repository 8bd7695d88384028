"""The one progress interface of long library operations.

A long operation takes ``progress: Progress | None`` and opens it itself, with a label,
the total it knows and how many units it runs at once: ``with (progress or
no_progress)(label, total, parallel) as update: update(n)``. The command layer passes a
terminal bar (``cli.console.progress``). :func:`format_duration` writes a time as log and
progress lines give it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from typing import Protocol

#: A callback ``update(n)``: ``n`` more units of work are done.
Update = Callable[[int], None]


class Progress(Protocol):
    """``progress(label, total, parallel=1)``: a context manager yielding the :data:`Update` of
    one operation; ``parallel``: how many updates may arrive together (work units running at
    once), so that a time estimate waits for the first of them all."""

    def __call__(
        self, label: str, total: int, parallel: int = 1
    ) -> AbstractContextManager[Update]: ...


@contextlib.contextmanager
def no_progress(label: str, total: int, parallel: int = 1) -> Iterator[Update]:
    """The silent :data:`Progress`."""
    del label, total, parallel
    yield lambda n: None


def relabelled(progress: Progress | None, label: str) -> Progress:
    """``progress`` (or :func:`no_progress`) under another label."""
    bar = progress or no_progress

    def opened(_label: str, total: int, parallel: int = 1) -> AbstractContextManager[Update]:
        return bar(label, total, parallel)

    return opened


def format_duration(seconds: float) -> str:
    """``42 s``, ``7.5 min`` or ``3.2 h`` (for time estimates in logs)."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"
