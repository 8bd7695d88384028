"""Work units of a stamp source and the one loop that measures them: each unit reads its
stamps (in a worker) as a :class:`~.measurer.StampBatch`, the :class:`~.measurer.Measurer`
measures it, and the columns land in the unit's output rows."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Protocol

import numpy as np

from megalut_cli.measure.measurer import Measurer, MeasureSettings, StampBatch
from megalut_cli.measure.metacal_defaults import TYPES
from megalut_cli.parallel import executor, map_units, resolve_nproc
from megalut_cli.progress import Progress, no_progress

log = logging.getLogger(__name__)

#: Stamps per work unit (about 0.3 s of HSM each at 64x64 pixels).
CHUNK_STAMPS = 1000


class SourceUnit(Protocol):
    """A piece of a stamp source, picklable: the output ``rows`` it fills and how to read
    its stamps."""

    @property
    def rows(self) -> np.ndarray:
        """The output rows of its stamps, in their order."""
        ...

    def batch(self, settings: MeasureSettings) -> StampBatch:
        """Its stamps, read (in the worker) for ``settings``."""
        ...


def n_units(n_stamps: int, n_workers: int) -> int:
    """How many units ``n_stamps`` are split into: chunks of at most :data:`CHUNK_STAMPS`,
    and with several workers at least 4 per worker."""
    return max(-(-n_stamps // CHUNK_STAMPS), min(4 * n_workers, n_stamps) if n_workers > 1 else 1)


def workers(nproc: int, scheduler: str | None) -> int:
    """The number of workers units are planned for."""
    return 2 if scheduler else resolve_nproc(nproc)


def empty_columns(
    n: int, names: Sequence[str], flags: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Output columns of ``n`` rows before measurement: NaN, and for the flag columns
    (``flags``, ``flags_<type>``) the given initial ``flags`` (e.g. STAMP_OFF_IMAGE) or 0."""
    out: dict[str, np.ndarray] = {}
    for c in names:
        if c == "flags" or (c.startswith("flags_") and c[len("flags_") :] in TYPES):
            out[c] = np.zeros(n, dtype=np.int32) if flags is None else flags.astype(np.int32)
        else:
            out[c] = np.full(n, np.nan)
    return out


def measure_unit(job: tuple[SourceUnit, MeasureSettings]) -> dict[str, np.ndarray]:
    """Worker: read a unit's stamps and measure them."""
    unit, settings = job
    return Measurer(settings).measure(unit.batch(settings))


def measure_units(
    units: Sequence[SourceUnit],
    settings: MeasureSettings,
    columns: dict[str, np.ndarray],
    *,
    nproc: int = 1,
    scheduler: str | None = None,
    progress: Progress | None = None,
    label: str = "measuring stamps",
) -> dict[str, np.ndarray]:
    """Measure ``units`` (on ``nproc`` local workers or a Dask ``scheduler``; in this process
    on the device ``gpu``) into ``columns`` (from :func:`empty_columns`): each result column
    ``columns`` has is written into the unit's rows (flags OR-ed). Returns ``columns``."""
    if settings.device == "gpu" and not scheduler:
        nproc = 1
    sizes = [len(u.rows) for u in units]
    total = sum(sizes)
    t0 = time.perf_counter()
    with (
        executor(nproc, scheduler, len(units)) as pool,
        (progress or no_progress)(
            label, total, min(len(units), workers(nproc, scheduler))
        ) as update,
    ):
        done = iter(sizes)
        # completion order: stamp counts are close enough for a progress display
        results = map_units(
            measure_unit, [(u, settings) for u in units], pool, lambda _n: update(next(done))
        )
    dt = time.perf_counter() - t0
    if total:
        log.info(
            "%s: measured %d stamps in %.1f s (%.2f ms/stamp)", label, total, dt, 1e3 * dt / total
        )
    for unit, res in zip(units, results):
        for c, v in res.items():
            if c not in columns:
                continue
            if c.startswith("flags"):
                columns[c][unit.rows] |= v
            else:
                columns[c][unit.rows] = v
    return columns
