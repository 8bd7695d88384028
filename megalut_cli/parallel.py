"""Mapping independent work units over a local process pool or a Dask cluster.

The library never manages workers itself: it maps a top-level function over a list of
work units through a :class:`concurrent.futures.Executor` — a process pool for ``-j N``,
or the executor of a Dask ``distributed.Client`` for ``--scheduler``. Work units carry
their own seeds, so results are identical whatever the engine and the number of workers.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import signal
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Executor, Future, ProcessPoolExecutor, as_completed
from multiprocessing import get_all_start_methods, get_context
from pathlib import Path
from typing import Any, TypeVar

from megalut_cli.errors import ArgumentError, ArgumentValueError, MegalutError
from megalut_cli.schema import Option

log = logging.getLogger(__name__)
T = TypeVar("T")

#: Local worker processes (``-j``), the same for every command.
NPROC_OPTION = Option(
    "nproc",
    "int",
    0,
    "Local worker processes (0 or less: all cores; env MEGALUT_NPROC). "
    "Results are identical for any value.",
    short="-j",
    envvar="MEGALUT_NPROC",
)
#: A Dask cluster instead of local processes (``--scheduler``).
SCHEDULER_OPTION = Option(
    "scheduler",
    "str",
    None,
    "Run on an existing Dask cluster: a scheduler address "
    "(tcp://host:8786) or a scheduler file. Needs the 'dask' extra.",
    metavar="ADDR",
)

_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")

#: How local workers start: forked from one server process per command that has imported
#: their modules once (``forkserver``), else (platforms without it) ``spawn``.
START_METHOD = "forkserver" if "forkserver" in get_all_start_methods() else "spawn"
#: Imported first by the worker server: Ctrl-C and start-up failures after the command left.
_SERVER_MODULE = "megalut_cli.worker_server"


def resolve_nproc(nproc: int) -> int:
    """``nproc <= 0`` means all cores."""
    return os.cpu_count() or 1 if nproc <= 0 else nproc


@contextlib.contextmanager
def _single_threaded_children() -> Iterator[None]:
    old = {k: os.environ.get(k) for k in _THREAD_VARS}
    os.environ.update({k: "1" for k in _THREAD_VARS})
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def ignore_interrupt() -> None:
    """Worker initializer: Ctrl-C is the parent's to handle (one line, exit 130), so local
    workers ignore SIGINT instead of each printing a traceback."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def stop_workers(pool: ProcessPoolExecutor) -> None:
    """Terminate the workers of ``pool`` now (after Ctrl-C) instead of letting them finish their
    units."""
    if hasattr(pool, "terminate_workers"):  # Python >= 3.14
        pool.terminate_workers()
        return
    # Older Pythons have no public way: the pool's own process table.
    for process in list((getattr(pool, "_processes", None) or {}).values()):
        process.terminate()


def start_worker_server(modules: Sequence[str]) -> None:
    """Start, in the background, the process that local workers are forked from, importing
    ``modules`` (those defining the functions the workers run).

    Called as a command starts, before its own imports, so that the server imports in
    parallel with the command; every pool of the command then forks its workers from it,
    warm. Its environment (one BLAS thread) is fixed when it starts. Nothing is done where
    the platform cannot fork from a server, or when the server already runs.
    """
    if START_METHOD != "forkserver":
        return
    from multiprocessing import forkserver  # its sockets and selectors: only with workers

    with _single_threaded_children(), _interrupt_ignored_by_children():
        get_context(START_METHOD).set_forkserver_preload([_SERVER_MODULE, *modules])
        forkserver.ensure_running()


@contextlib.contextmanager
def _interrupt_ignored_by_children() -> Iterator[None]:
    """Processes started inside ignore Ctrl-C from birth (an ignored signal stays ignored
    across exec, and Python keeps it so), not only once their imports are done; a Ctrl-C
    to this process in those milliseconds is lost."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


class LocalPool(ProcessPoolExecutor):
    """The local workers of ``-j N``: N - 1 processes, since this process runs units too
    (:func:`map_units` and :func:`map_ordered` hand each unit to whichever is free first)."""

    def __init__(self, workers: int, **options: Any) -> None:
        super().__init__(max_workers=workers, **options)
        self.workers = workers


class _SharedUnits:
    """Units handed out in order to a :class:`LocalPool`'s workers and to this process.

    Only this process's main thread advances ``items``, into ``buffer``. A worker that
    finishes takes the next buffered unit at once (its future's callback, in the pool's
    thread); this process runs one itself whenever no worker is free. The workers' first
    units are handed out by a short-lived thread, since starting a worker waits for the
    server it is forked from, and this process starts on its own units meanwhile. At most
    ``window`` units (None: any number) are taken ahead of the first not yet delivered in
    order.
    """

    def __init__(
        self,
        func: Callable[[Any], Any],
        items: Iterable[Any],
        pool: LocalPool,
        window: int | None,
    ) -> None:
        self.func = func
        self.items = iter(items)
        self.pool = pool
        self.workers = pool.workers
        self.window = None if window is None else max(window, 2 * self.workers + 1)
        self.lock = threading.RLock()  # a callback may run at once, in the thread adding it
        self.buffer: deque[tuple[int, Any]] = deque()
        self.finished: queue.SimpleQueue[tuple[int, Future | None]] = queue.SimpleQueue()
        self.running = 0  # units given to workers whose futures are not in ``finished`` yet
        self.futures: set[Future] = set()
        self.taken = 0  # units taken from ``items``
        self.delivered = 0  # units delivered in order (the window's start)
        self.exhausted = False
        self.closed = False

    def _fill(self) -> None:
        """Take units from ``items`` into ``buffer``, as the window allows (main thread)."""
        while not self.exhausted and (
            self.window is None or self.taken < self.delivered + self.window
        ):
            with self.lock:  # enough for this process and, while it runs one, the workers
                if len(self.buffer) > 2 * self.workers:
                    return
            try:
                unit = next(self.items)
            except StopIteration:
                self.exhausted = True
                return
            with self.lock:
                self.buffer.append((self.taken, unit))
            self.taken += 1

    def _dispatch(self) -> None:
        """Give buffered units to the free workers (any thread)."""
        while True:
            with self.lock:
                if self.closed or self.running >= self.workers or not self.buffer:
                    return
                index, unit = self.buffer.popleft()
                self.running += 1
            if not self._submit(index, unit):
                return

    def _submit(self, index: int, unit: Any) -> bool:
        """Run unit ``index`` on a worker (counted in ``running``); False if the pool is
        shutting down or broken, the unit then buffered again for this process."""
        try:
            future = self.pool.submit(self.func, unit)
        except RuntimeError:
            with self.lock:
                self.buffer.appendleft((index, unit))
                self.running -= 1
                self.closed = True
            self.finished.put((-1, None))  # wakes this process up, should it wait for a worker
            return False
        with self.lock:
            self.futures.add(future)
        future.add_done_callback(lambda f: self._worker_done(index, f))
        return True

    def _start(self, first: list[tuple[int, Any]]) -> None:
        """The workers' first units (thread ``megalut-start``)."""
        for k, (index, unit) in enumerate(first):
            if not self._submit(index, unit):  # the others back to the buffer too
                with self.lock:
                    self.buffer.extendleft(reversed(first[k + 1 :]))
                    self.running -= len(first) - k - 1
                return
        self._dispatch()

    def _worker_done(self, index: int, future: Future) -> None:
        with self.lock:
            self.finished.put((index, future))
            self.futures.discard(future)
            self.running -= 1
        self._dispatch()

    @staticmethod
    def _from_workers(item: tuple[int, Future | None]) -> Iterator[tuple[int, Any]]:
        """The result of a finished worker unit (none for a wake-up after a failed submit)."""
        index, future = item
        if future is not None:
            yield index, future.result()

    def results(self) -> Iterator[tuple[int, Any]]:
        """``(index, result)`` of every unit, as units finish."""
        self._fill()
        with self.lock:  # the first units go to the workers, the next to this process
            first = [self.buffer.popleft() for _ in range(min(self.workers, len(self.buffer)))]
            self.running += len(first)
        starter = threading.Thread(
            target=self._start, args=(first,), name="megalut-start", daemon=True
        )
        starter.start()
        try:
            while True:
                self._fill()
                if not starter.is_alive():  # the workers have started: handing out is quick
                    self._dispatch()
                with self.lock:
                    mine = self.buffer.popleft() if self.buffer else None
                    waiting = self.running > 0 or not self.finished.empty()
                if mine is not None:
                    yield mine[0], self.func(mine[1])
                elif waiting:
                    yield from self._from_workers(self.finished.get())
                elif self.exhausted:
                    return
                else:  # the first unit not delivered is always buffered, running or finished
                    raise MegalutError("internal error: no unit to run")
                while not self.finished.empty():
                    yield from self._from_workers(self.finished.get())
        finally:
            with self.lock:
                self.closed = True
                for future in self.futures:
                    future.cancel()

    def ordered(self) -> Iterator[tuple[int, Any]]:
        """:meth:`results` in unit order (a unit finished early waits for those before it)."""
        early: dict[int, Any] = {}
        for index, result in self.results():
            early[index] = result
            while self.delivered in early:
                yield self.delivered, early.pop(self.delivered)
                self.delivered += 1


def _dask_client(scheduler: str) -> Any:
    try:
        from distributed import Client
    except ImportError:
        raise ArgumentError("scheduler", " needs Dask: pip install 'megalut-cli[dask]'") from None
    try:
        if "://" in scheduler:
            return Client(scheduler, timeout="30s")
        if Path(scheduler).is_file():
            return Client(scheduler_file=scheduler, timeout="30s")
    except (OSError, TimeoutError) as err:
        raise MegalutError(f"cannot reach the Dask scheduler at {scheduler}: {err}") from None
    raise ArgumentValueError(
        "scheduler", f" {scheduler!r} is neither an address (tcp://host:port) nor a scheduler file"
    )


@contextlib.contextmanager
def executor(
    nproc: int = 1, scheduler: str | None = None, n_units: int | None = None
) -> Iterator[Executor | None]:
    """An executor for ``-j nproc`` or ``--scheduler``; ``None`` means run in this process.

    Local workers are forked from a warm server (:func:`start_worker_server`; ``spawn``
    where the platform has no fork server), with one BLAS thread each; ``-j N`` is this
    process and N - 1 workers (a :class:`LocalPool`), never more than ``n_units`` processes
    (when given), so that a small job does not pay for idle workers.
    """
    if scheduler:
        client = _dask_client(scheduler)
        try:
            log.info("running on Dask cluster %s", scheduler)
            yield client.get_executor(pure=False)
        finally:
            client.close()
        return
    n = resolve_nproc(nproc) if n_units is None else min(resolve_nproc(nproc), max(n_units, 1))
    if n == 1:
        yield None
        return
    # The pool starts its workers when work is first submitted, not here: the variables stay
    # set while it lives, so that every worker starts with one BLAS thread.
    start_worker_server(())  # where the command did not start it already
    with _single_threaded_children():
        pool = LocalPool(n - 1, mp_context=get_context(START_METHOD), initializer=ignore_interrupt)
        try:
            log.info("running on %d local worker processes (this one and %d more)", n, n - 1)
            yield pool
        except KeyboardInterrupt:
            stop_workers(pool)
            raise
        finally:
            pool.shutdown(wait=True, cancel_futures=True)


def _as_finished(
    func: Callable[..., T], units: Sequence[Any], pool: Executor | None
) -> Iterator[tuple[int, T]]:
    """``(i, func(units[i]))`` for every unit, as units finish: in this process, on a
    :class:`LocalPool` with this process, or on any other executor."""
    if pool is None:
        for i, unit in enumerate(units):
            yield i, func(unit)
    elif isinstance(pool, LocalPool):
        yield from _SharedUnits(func, units, pool, None).results()
    else:
        futures = {pool.submit(func, unit): i for i, unit in enumerate(units)}
        try:
            for fut in as_completed(futures):
                yield futures[fut], fut.result()
        finally:
            for fut in futures:
                fut.cancel()


def map_units(
    func: Callable[..., T],
    units: Sequence[Any],
    pool: Executor | None = None,
    progress: Callable[[int], None] | None = None,
    finished: Callable[[int, T], None] | None = None,
) -> list[T]:
    """Apply ``func`` to every unit, in this process or on ``pool``; results in unit order.

    ``progress(n)`` is called with the number of units just finished; ``finished(i, result)``
    with each result as it arrives (in the order of completion).
    """
    results: list[Any] = [None] * len(units)
    for i, result in _as_finished(func, units, pool):
        results[i] = result
        if finished:
            finished(i, result)
        if progress:
            progress(1)
    return results


def map_ordered(
    func: Callable[[Any], T], items: Iterable[tuple[Any, Any]], pool: Executor | None, window: int
) -> Iterator[tuple[Any, T]]:
    """``(key, func(unit))`` for the ``(key, unit)`` pairs of ``items``, in their order, with at
    most ``window`` units in flight: a stream whose memory does not grow with the number of
    units."""
    if pool is None:
        for key, unit in items:
            yield key, func(unit)
        return
    if isinstance(pool, LocalPool):
        keys: dict[int, Any] = {}

        def units() -> Iterator[Any]:
            for index, (key, unit) in enumerate(items):
                keys[index] = key
                yield unit

        for index, result in _SharedUnits(func, units(), pool, window).ordered():
            yield keys.pop(index), result
        return
    pending: deque[tuple[Any, Future]] = deque()
    try:
        for key, unit in items:
            pending.append((key, pool.submit(func, unit)))
            if len(pending) >= window:
                k, fut = pending.popleft()
                yield k, fut.result()
        while pending:
            k, fut = pending.popleft()
            yield k, fut.result()
    finally:
        for _, fut in pending:
            fut.cancel()


def chunk_ranges(n: int, n_chunks: int) -> list[tuple[int, int]]:
    """Split ``range(n)`` into ``n_chunks`` contiguous (start, stop) ranges of near-equal size."""
    n_chunks = max(1, min(n_chunks, n)) if n else 1
    bounds = [round(i * n / n_chunks) for i in range(n_chunks + 1)]
    return [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a] or [(0, 0)]
