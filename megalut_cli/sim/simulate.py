"""``megalut simulate``: draw a configured set of stamps in parallel, write the catalog.

The cases are split into work units (contiguous chunks of cases) mapped over the
executor of :mod:`megalut_cli.parallel`; every random draw is seeded per case, so the
catalog is identical for any ``-j`` or Dask cluster. :func:`simulate_chunks` yields the
catalog in order, unit by unit (:func:`simulate_table`: all of it in memory);
:func:`simulate` streams it to the files:

- the catalog (``megalut.simulation``): one row per stamp, ordered by case then
  realization, with ``case, rea, x, y``, all ``tru_*`` truth and, with ``measure``, the
  features of :mod:`megalut_cli.measure.features`; a second HDU ``CONFIG`` holds the
  effective configuration as JSON;
- optionally the stamps (``megalut.stamps``): a FITS image grid, stamp ``k`` at grid
  column ``k mod n_x`` and row ``k div n_x`` from the first (lower-left) pixel.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import statistics
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from megalut_cli.atomic import atomic_output, check_output
from megalut_cli.catalog import CatalogWriter, catalog_writer, write_image
from megalut_cli.engine import DEFAULT_DEVICE, DEFAULT_ENGINE, check_engine, resolve_device
from megalut_cli.errors import MegalutError, Names, namer
from megalut_cli.measure.measurer import metacal_cards, retry_cards
from megalut_cli.parallel import chunk_ranges, executor, map_ordered, resolve_nproc
from megalut_cli.progress import Progress, format_duration, no_progress
from megalut_cli.sim.config import SimConfig
from megalut_cli.sim.draw import WorkUnit, draw_unit, grid_stamp_centres, renders_galaxies
from megalut_cli.sim.options import SIMULATE

log = logging.getLogger(__name__)

CATALOG_FORMAT = "megalut.simulation"
STAMPS_FORMAT = "megalut.stamps"
#: Stamps per work unit aimed at (a unit holds whole cases): about 0.2 s of work, small
#: enough that -j N workers finish together (benchmarks/startup.md).
UNIT_STAMPS = 1024
#: Stamps per work unit on the device (one process feeds it; bigger batches fill it better).
DEVICE_UNIT_STAMPS = 32768
#: Largest image written with --stamps (pixels; 4 GiB in float32): fail early, not out of memory.
MAX_STAMP_PIXELS = 2**30


@dataclass
class SimulationResult:
    n_stamps: int
    n_cases: int
    n_realizations: int
    seconds: float
    catalog: Path
    stamps: Path | None

    @property
    def stamps_per_second(self) -> float:
        return self.n_stamps / self.seconds if self.seconds > 0 else math.inf


def expected_workers(nproc: int, scheduler: str | None) -> int:
    """Workers to plan work units for: -j, or 8 for a Dask scheduler (its size is not known
    here)."""
    return 8 if scheduler else resolve_nproc(nproc)


def n_work_units(config: SimConfig, nproc: int = 1, scheduler: str | None = None) -> int:
    """How many work units :func:`simulate` will map (e.g. to size a progress bar)."""
    s = config.structure
    n_units = max(math.ceil(s.n_stamps / UNIT_STAMPS), 4 * expected_workers(nproc, scheduler))
    return min(n_units, s.n_cases)


#: The calibration draw of :func:`stamps_per_second`: ``CALIBRATION_DRAWS`` timed draws of
#: ``CALIBRATION_DRAW_STAMPS`` stamps after a warm-up of four times that many.
CALIBRATION_DRAW_STAMPS = 32
CALIBRATION_DRAWS = 5
CALIBRATION_STAMPS = (4 + CALIBRATION_DRAWS) * CALIBRATION_DRAW_STAMPS


def stamps_per_second(
    config: SimConfig,
    seed: int,
    measure: bool,
    keep_stamps: bool,
    n_stamps: int = CALIBRATION_DRAW_STAMPS,
    engine: str = DEFAULT_ENGINE,
    device: str = DEFAULT_DEVICE,
    n_draws: int = CALIBRATION_DRAWS,
    metacal_step: float | None = None,
) -> float:
    """Drawing rate of one worker: the median of ``n_draws`` tiny timed draws of ``n_stamps``.

    Cheap (well under a second at the paper's stamp size); per-case setup costs and work
    spread over several workers make the real rate differ by tens of percent.
    """
    s = config.structure

    def first_case(n: int) -> SimConfig:
        n = min(s.n_realizations, n)
        if s.snc == "pairs":
            n = max(2, n - n % 2)
        return dataclasses.replace(
            config, structure=dataclasses.replace(s, n_cases=1, n_realizations=n)
        )

    def draw(case: SimConfig, draw_seed: int) -> None:
        draw_unit(
            WorkUnit(
                case,
                draw_seed,
                0,
                1,
                case.structure.grid_nx,
                keep_stamps,
                measure,
                engine,
                device=device,
                metacal_step=metacal_step if measure else None,
            )
        )

    small = first_case(n_stamps)
    n_rea = small.structure.n_realizations
    # Warm up (lazy imports, compilation) on four times as many other galaxies. GalSim builds
    # a table per Sersic index once per process, which a long run pays once: a timed draw of
    # a few galaxies that meets an index the warm-up missed runs several times slower. The
    # median over draws of different galaxies leaves such a draw out.
    device = resolve_device(device)
    draw(first_case(4 * n_stamps), seed + 1)
    seconds = []
    for k in range(n_draws):
        t0 = time.perf_counter()
        draw(small, seed + 1 + k if k else seed)
        seconds.append(time.perf_counter() - t0)
    return n_rea / max(statistics.median(seconds), 1e-6)


#: Below this many stamps a run's plan gives no time estimate unless asked (``--dry-run``):
#: the calibration draw would cost more than 1 % of the work it estimates.
ESTIMATE_MIN_STAMPS = 100 * CALIBRATION_STAMPS


def plan_message(
    config: SimConfig,
    seed: int,
    measure: bool,
    keep_stamps: bool,
    nproc: int,
    scheduler: str | None,
    engine: str = DEFAULT_ENGINE,
    device: str = DEFAULT_DEVICE,
    metacal_step: float | None = None,
    estimate: bool | None = None,
) -> str:
    """What simulating ``config`` will do, with a time estimated from a tiny calibration draw
    (with ``metacal_step``: measured in metacal mode too). ``estimate``: whether to make that
    draw; by default only for runs of ``ESTIMATE_MIN_STAMPS`` or more."""
    s = config.structure
    measured = "measured" + (" (and metacal)" if metacal_step is not None else "")
    what = " and ".join(
        w for w, on in (("drawn into an image", keep_stamps), (measured, measure)) if on
    )
    head = (
        f"{s.n_cases} cases x {s.n_realizations} realizations = {s.n_stamps} stamps of "
        f"{s.stamp_size}x{s.stamp_size} px"
    )
    if not what:
        return f"{head}: truth only, nothing drawn"
    if resolve_device(device) == "gpu" and not scheduler and metacal_step is None:
        # one process feeds the device; a tiny draw there would time its compilation
        return f"{head}, {what}, on the device (one process; no time estimate)"
    workers = 0 if scheduler else min(resolve_nproc(nproc), n_work_units(config, nproc, scheduler))
    if not (s.n_stamps >= ESTIMATE_MIN_STAMPS if estimate is None else estimate):
        return f"{head}, {what}, " + (
            "on the Dask cluster" if scheduler else f"on {workers} worker(s)"
        )
    rate = stamps_per_second(
        config, seed, measure, keep_stamps, engine=engine, device=device, metacal_step=metacal_step
    )
    if scheduler:
        return (
            f"{head}, {what}: about {format_duration(s.n_stamps / rate)} of worker time "
            f"on the Dask cluster ({rate:.0f} stamps/s per worker in a calibration draw)"
        )
    return (
        f"{head}, {what}, on {workers} worker(s): about "
        f"{format_duration(s.n_stamps / rate / workers)} "
        f"({rate:.0f} stamps/s per worker in a calibration draw)"
    )


def make_units(
    config: SimConfig,
    seed: int,
    nproc: int,
    scheduler: str | None,
    keep_stamps: bool,
    measure: bool,
    engine: str = DEFAULT_ENGINE,
    feature_sets: tuple[str, ...] = (),
    device: str = DEFAULT_DEVICE,
    metacal_step: float | None = None,
    moments_retry: float = 0.0,
) -> list[WorkUnit]:
    """Split the cases into work units of about ``UNIT_STAMPS`` stamps (whole cases;
    ``DEVICE_UNIT_STAMPS`` on the device, ``device`` being resolved)."""
    s = config.structure
    n_units = n_work_units(config, nproc, scheduler)
    if device == "gpu" and not scheduler:
        n_units = min(s.n_cases, max(1, math.ceil(s.n_stamps / DEVICE_UNIT_STAMPS)))
    return [
        WorkUnit(
            config,
            seed,
            a,
            b,
            s.grid_nx,
            keep_stamps,
            measure,
            engine,
            feature_sets if measure else (),
            device,
            metacal_step if measure else None,
            moments_retry if measure else 0.0,
        )
        for a, b in chunk_ranges(s.n_cases, n_units)
    ]


def simulation_cards(
    config: SimConfig, seed: int, measured: bool, engine: str = DEFAULT_ENGINE
) -> dict[str, Any]:
    """Header cards of a simulated catalog: seed, structure and config provenance."""
    s = config.structure
    cards: dict[str, Any] = {
        "SEED": (seed, "seed of every random draw (megalut simulate --seed)"),
        "NCASES": (s.n_cases, "number of cases"),
        "NREA": (s.n_realizations, "realizations per case"),
        "STAMPSZ": (s.stamp_size, "stamp size in pixels"),
        "NSTAMPX": (s.grid_nx, "stamps per row of the stamp grid"),
        "SNC": (s.snc, "shape-noise cancellation"),
        "CRN": (s.common, "common random numbers: the same galaxies in every case"),
        "ANTITHET": (s.antithetic, "antithetic noise: realizations 2k, 2k+1 are twins"),
        "NOISE": (
            config.noise.type if config.noise.override_sigma is None else "gaussian",
            "noise model",
        ),
        "GAIN": (config.gain, "gain e-/ADU (CCD noise)"),
        "MEASURED": (bool(measured), "the catalog holds measured features"),
        "ENGINE": (engine, "stamp engine (megalut simulate --engine)"),
        "CFGFILE": (Path(config.path).name, "simulation config file"),
        "CFGSHA": (config.sha256, "sha256 of the config file"),
    }
    if config.overrides:
        cards["CFGOVR"] = (" ".join(config.overrides), "config overrides (full set in CONFIG HDU)")
    return cards


def config_table(config: SimConfig) -> np.ndarray:
    """The ``CONFIG`` HDU of a catalog: the effective configuration as JSON, its sha256."""
    text = config.to_json()
    arr = np.zeros(1, dtype=[("config_json", f"S{max(len(text), 1)}"), ("config_sha256", "S64")])
    arr["config_json"] = text.encode("ascii", "backslashreplace")
    arr["config_sha256"] = config.sha256.encode("ascii")
    return arr


def simulation_catalog_writer(
    path: str | os.PathLike, config: SimConfig, cards: dict[str, Any], overwrite: bool = False
) -> contextlib.AbstractContextManager[CatalogWriter]:
    """A streaming writer (:func:`megalut_cli.catalog.catalog_writer`) of a
    ``megalut.simulation`` catalog, the effective configuration in its ``CONFIG`` HDU."""
    return catalog_writer(
        path,
        fmt=CATALOG_FORMAT,
        cards=cards,
        overwrite=overwrite,
        extra_hdus={"CONFIG": config_table(config)},
    )


def write_simulation_catalog(
    path: str | os.PathLike,
    columns: dict[str, np.ndarray],
    config: SimConfig,
    cards: dict[str, Any],
) -> None:
    """Write (replace) a whole ``megalut.simulation`` catalog at ``path``; meant for the
    temporary file of ``atomic_output``."""
    with simulation_catalog_writer(path, config, cards, overwrite=True) as writer:
        writer.append(columns)


def order_columns(columns: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """case, rea, x, y, truth (sorted), then features in their given order."""
    first = [c for c in ("case", "rea", "x", "y") if c in columns]
    truth = sorted(c for c in columns if c.startswith("tru_"))
    rest = [c for c in columns if c not in first and c not in truth]
    return {c: columns[c] for c in first + truth + rest}


def check_outputs(
    config: SimConfig,
    output: str | os.PathLike,
    stamps: str | os.PathLike | None,
    overwrite: bool,
    names: Names | None = None,
) -> tuple[Path, Path | None]:
    """Pre-flight of :func:`simulate`: both outputs can be written, and the image is not too big
    (messages name the arguments by ``names``)."""
    name = namer(names)
    out = check_output(output, overwrite)
    st = check_output(stamps, overwrite) if stamps is not None else None
    if st is not None and st.resolve() == out.resolve():
        raise MegalutError(f"{name('stamps')} and {name('output')} must be different files")
    s = config.structure
    if st is not None:
        n_y = math.ceil(s.n_stamps / s.grid_nx)
        pixels = n_y * s.grid_nx * s.stamp_size**2
        if pixels > MAX_STAMP_PIXELS:
            raise MegalutError(
                f"{name('stamps')}: the image would have {pixels:.3g} pixels; lower "
                f"{name('n_cases')}/{name('n_realizations')} or use {name('measure')} without "
                f"{name('stamps')}"
            )
    return out, st


@dataclass
class SimulatedChunk:
    """Consecutive rows of a simulated catalog: stamps ``first, first + 1, ...``."""

    first: int
    #: catalog columns, in catalog order (:func:`order_columns`), with the grid centres ``x, y``
    columns: dict[str, np.ndarray]
    #: the stamps, shape (n, S, S), when asked for
    stamps: np.ndarray | None


def simulate_chunks(
    config: SimConfig,
    seed: int = SIMULATE["seed"].default,
    *,
    measure: bool = SIMULATE["measure"].default,
    keep_stamps: bool = False,
    nproc: int = 1,
    scheduler: str | None = None,
    progress: Progress | None = None,
    engine: str = DEFAULT_ENGINE,
    morphology: bool = SIMULATE["morphology"].default,
    device: str = DEFAULT_DEVICE,
    metacal_step: float | None = None,
    feature_sets: Sequence[str] = (),
    moments_retry: float = 0.0,
) -> Iterator[SimulatedChunk]:
    """Draw the configured stamps (and measure them), yielding the catalog in order, one
    work unit at a time, with a bounded number of units in flight: the memory does not grow
    with the size of the set. ``progress`` counts the units (:func:`n_work_units` in all).

    ``engine`` is ``fast`` or ``galsim``, ``device`` ``cpu``, ``gpu`` or ``auto``
    (:mod:`megalut_cli.engine`); on the device the units run in this process.
    ``metacal_step`` (with ``measure``): also the metacal features (on the CPU).
    ``feature_sets`` (with ``measure``; ``morphology`` is one): the optional feature sets
    (:mod:`megalut_cli.measure.feature_sets`) measured too. ``moments_retry`` (with
    ``measure``): the step factor of the moments' damped retry (0: none; on the CPU).
    """
    check_engine(engine)
    device = resolve_device(device)
    if metacal_step is not None and measure and device == "gpu":
        log.info("metacal runs on the CPU: drawing and measuring there")
        device = "cpu"
    if moments_retry > 0 and measure and device == "gpu":
        log.info("the moments' retry runs on the CPU: drawing and measuring there")
        device = "cpu"
    if config.structure.antithetic and device == "gpu":
        log.info("antithetic noise is drawn on the CPU")
        device = "cpu"
    if device == "gpu" and not scheduler:
        nproc = 1
    s = config.structure
    units = make_units(
        config,
        seed,
        nproc,
        scheduler,
        keep_stamps,
        measure,
        engine,
        tuple(feature_sets) + (("morphology",) if morphology else ()),
        device,
        metacal_step,
        moments_retry,
    )
    log_engine_fallback(config, engine, keep_stamps or measure)
    log.info(
        "simulating %d cases x %d realizations = %d stamps of %d px in %d work units",
        s.n_cases,
        s.n_realizations,
        s.n_stamps,
        s.stamp_size,
        len(units),
    )
    window = max(8, 4 * expected_workers(nproc, scheduler))
    names: list[str] | None = None
    with (
        executor(nproc, scheduler, len(units)) as pool,
        (progress or no_progress)(
            "simulate", len(units), min(len(units), expected_workers(nproc, scheduler))
        ) as update,
    ):
        for unit, res in map_ordered(draw_unit, ((u, u) for u in units), pool, window):
            columns = res["columns"]
            if names is None:
                names = list(columns)
            elif list(columns) != names:
                raise MegalutError("internal error: work units returned different columns")
            first = unit.case_start * s.n_realizations
            n = len(columns["case"])
            columns["x"], columns["y"] = grid_stamp_centres(
                np.arange(first, first + n), s.grid_nx, s.stamp_size
            )
            update(1)
            yield SimulatedChunk(
                first, order_columns(columns), res.get("stamps") if keep_stamps else None
            )


def simulate_table(
    config: SimConfig,
    seed: int = SIMULATE["seed"].default,
    *,
    keep_stamps: bool = False,
    **kwargs: Any,
) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
    """In memory: the catalog columns of the configured set and, with ``keep_stamps``, the
    stamps (n, S, S); ``kwargs`` as :func:`simulate_chunks`."""
    chunks = list(simulate_chunks(config, seed, keep_stamps=keep_stamps, **kwargs))
    columns = {k: np.concatenate([c.columns[k] for c in chunks]) for k in chunks[0].columns}
    warn_hst_noise(columns)
    stamps = np.concatenate([c.stamps for c in chunks]) if keep_stamps else None
    return columns, stamps


def simulate(
    config: SimConfig,
    output: str | os.PathLike,
    stamps: str | os.PathLike | None = None,
    measure: bool = SIMULATE["measure"].default,
    seed: int = SIMULATE["seed"].default,
    nproc: int = 1,
    scheduler: str | None = None,
    overwrite: bool = False,
    progress: Progress | None = None,
    engine: str = DEFAULT_ENGINE,
    morphology: bool = SIMULATE["morphology"].default,
    device: str = DEFAULT_DEVICE,
    names: Names | None = None,
    metacal: bool = SIMULATE["metacal"].default,
    metacal_step: float = SIMULATE["metacal_step"].default,
    feature_sets: Sequence[str] = (),
    moments_retry: float = SIMULATE["moments_retry"].default,
) -> SimulationResult:
    """Simulate the configured stamps into files: the catalog, streamed as the work units
    finish (:func:`simulate_chunks`), and the stamp grid image ``stamps``. With ``measure``
    and ``morphology`` (or any set of ``feature_sets``), the ``morph_*`` features are
    measured too; with ``measure`` and
    ``metacal``, the metacal features of :func:`megalut_cli.measure.measure.measure_file`
    (each stamp deconvolved by the PSF image it was drawn with, fixnoise seeded by ``seed``).
    ``moments_retry`` (with ``measure``): the step factor of the adaptive moments' damped
    retry (:func:`megalut_cli.measure.adamom.adaptive_moments`; header card ``HSMRETRY``).
    Messages name the arguments by ``names``.
    """
    check_engine(engine)
    SIMULATE["moments_retry"].check(moments_retry, namer(names)("moments_retry"))
    out, st = check_outputs(config, output, stamps, overwrite, names)
    s = config.structure
    if st is None and not measure:
        name = namer(names)
        log.info(
            "neither %s nor %s: writing the truth catalog only (nothing drawn)",
            name("stamps"),
            name("measure"),
        )
    t0 = time.perf_counter()
    image = None
    if st is not None:
        n_y = math.ceil(s.n_stamps / s.grid_nx)
        image = np.zeros((n_y * s.stamp_size, s.grid_nx * s.stamp_size), dtype=np.float32)
    cards = simulation_cards(config, seed, measure, engine)
    if metacal and measure:
        cards.update(metacal_cards(metacal_step, seed, "simulate"))
    if measure:
        cards.update(retry_cards(moments_retry))
    excess = HstNoiseExcess()
    chunks = simulate_chunks(
        config,
        seed,
        measure=measure,
        keep_stamps=st is not None,
        nproc=nproc,
        scheduler=scheduler,
        progress=progress,
        engine=engine,
        morphology=morphology,
        device=device,
        metacal_step=float(metacal_step) if metacal and measure else None,
        feature_sets=feature_sets,
        moments_retry=float(moments_retry),
    )
    with contextlib.ExitStack() as stack:
        writer = stack.enter_context(simulation_catalog_writer(out, config, cards, overwrite))
        tmp_st = stack.enter_context(atomic_output(st, overwrite)) if st is not None else None
        stack.enter_context(contextlib.closing(chunks))  # on error, stop the workers first
        for chunk in chunks:
            if image is not None:  # with stamps: every chunk has them
                _paste(image, chunk.stamps, chunk.first, s.grid_nx, s.stamp_size)
            excess.add(chunk.columns)
            writer.append(chunk.columns)
        if image is not None:  # and so tmp_st
            st_cards = {k: v for k, v in cards.items() if k not in ("MEASURED",)}
            st_cards["NSTAMPS"] = (writer.n_rows, "number of stamps in the grid")
            write_image(tmp_st, image, fmt=STAMPS_FORMAT, cards=st_cards, overwrite=True)
        excess.warn()
    seconds = time.perf_counter() - t0
    n = writer.n_rows
    log.info(
        "%d stamps in %.1f s (%.1f stamps/s)", n, seconds, n / seconds if seconds else math.inf
    )
    return SimulationResult(n, s.n_cases, s.n_realizations, seconds, out, st)


def log_engine_fallback(config: SimConfig, engine: str, draws: bool) -> None:
    """Say once when the fast engine hands a galaxy profile to GalSim."""
    gal = config.galaxy
    if engine == "fast" and draws and not renders_galaxies(config):
        what = f"galaxy profile {gal.profile!r}" + (" with knots" if gal.knots else "")
        log.info(
            "the fast engine does not render %s: its stamps are drawn by GalSim "
            "(features still measured by the fast engine)",
            what,
        )


@dataclass
class HstNoiseExcess:
    """Counts real-galaxy stamps whose own (symmetrized) HST noise exceeds the requested
    noise, over the chunks of a catalog; :meth:`warn` logs them."""

    over: int = 0
    n: int = 0

    def add(self, columns: dict[str, np.ndarray]) -> None:
        if "tru_hst_noise_var" in columns:
            self.over += int(np.sum(columns["tru_hst_noise_var"] > columns["tru_sky_sigma"] ** 2))
            self.n += len(columns["tru_hst_noise_var"])

    def warn(self) -> None:
        if self.over:
            log.warning(
                "%d of %d real-galaxy stamps carry more (symmetrized) HST noise than "
                "noise.sigma^2: their noise is higher than asked (column tru_hst_noise_var); lower "
                "the fluxes, raise noise.sigma or select brighter galaxies (galaxy.real_select)",
                self.over,
                self.n,
            )


def warn_hst_noise(columns: dict[str, np.ndarray]) -> None:
    """Warn about real-galaxy stamps whose own HST noise exceeds the requested noise."""
    excess = HstNoiseExcess()
    excess.add(columns)
    excess.warn()


def _paste(image: np.ndarray, stamps: np.ndarray, first: int, n_x: int, size: int) -> None:
    """Copy stamps ``first, first+1, ...`` into their places in the grid image."""
    for i, stamp in enumerate(stamps):
        k = first + i
        r, c = divmod(k, n_x)
        image[r * size : (r + 1) * size, c * size : (c + 1) * size] = stamp
