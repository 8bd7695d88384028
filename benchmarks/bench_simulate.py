"""Throughput of ``megalut simulate --measure``: fast and galsim engines against a plain
GalSim loop.

On a scaled-down fiducial TP config (``examples/fiducial/tp.toml``: 64x64 stamps, Sersic
galaxies with gridded index convolved with a circular Gaussian PSF of sigma 2 px, Gaussian
noise of sigma 1, Table 1 of the paper), measured in ONE run, interleaved and repeated
because the machine is shared:

* ``fast -j 1`` / ``fast -j 2`` / ``galsim -j 1``: the library call
  ``megalut_cli.sim.simulate.simulate(config, out, measure=True, nproc=N, engine=E)`` (what
  ``megalut simulate CONFIG -o OUT --measure -j N --engine E`` runs after parsing its
  options), timed from the call to its return, so it includes the worker start-up for
  ``-j 2`` and writing the FITS catalog;
* ``plain loop``: the same kind of galaxies (same parameter distributions, drawn here with
  numpy per stamp), one stamp at a time in this process: ``galsim.Sersic`` sheared by the
  intrinsic ellipticity then the shear, ``Convolve`` with the PSF, ``drawImage`` (64x64,
  sub-pixel offset), ``addNoise`` (Gaussian, sigma 1), ``galsim.hsm.FindAdaptiveMom``;
* ``fast -j 2 start-up``: ``simulate`` on 2 cases x 1 realization at ``-j 2``, i.e. the fixed
  cost of spawning the workers, importing GalSim, SciPy, numba and megalut in them and
  loading the compiled kernels; each new worker also builds the fast engine's Sersic tables
  of the indices it meets (GalSim's Sersic cache, which the plain loop also pays once).

A warm-up runs first, so that the in-process runs see warm imports, GalSim's Sersic cache
and the fast engine's tables, as in a long run; the ``-j 2`` workers are new processes for
every call, as with the CLI. BLAS/OpenMP are limited to one thread per process.

CPU time (this process, plus the reaped workers for ``-j 2``) is reported next to the wall
clock: on a loaded machine ``cpu share`` = CPU seconds / (wall seconds x workers) shows how
much of the cores the benchmark actually got, and ``other jobs`` = the machine's busy CPU
seconds (``/proc/stat``) minus the benchmark's own, per wall second, how many cores the
other users took meanwhile. The ratios per CPU second are the robust ones. Run::

    python benchmarks/bench_simulate.py [--n-cases 100 --n-realizations 40 --repeats 3]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import datetime  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402

import fitsio  # noqa: E402
import galsim  # noqa: E402
import numpy as np  # noqa: E402

from megalut_cli.sim.config import SimConfig, load_config  # noqa: E402
from megalut_cli.sim.simulate import simulate  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from galsim_loops import SERSIC_N, STAMP_SIZE, plain_loop  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "examples" / "fiducial" / "tp.toml"

#: A timed job: returns (n_stamps, seconds of the draw+measure phase or NaN, adamom sigmas).
Job = Callable[[], tuple[int, float, np.ndarray]]


@dataclass
class Sample:
    """One timed measurement."""

    wall: float
    cpu: float
    load1: float
    n_stamps: int
    others: float  # cores kept busy by other jobs meanwhile (machine-wide, from /proc/stat)
    phase: float = math.nan  # SimulationResult.seconds (drawing + measuring only)
    sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))  # adamom_sigma, NaN if failed


def cpu_seconds() -> float:
    """CPU seconds (user + system) of this process plus its reaped children."""
    me = resource.getrusage(resource.RUSAGE_SELF)
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + ch.ru_utime + ch.ru_stime


def machine_busy() -> float:
    """CPU seconds all cores of the machine spent busy since boot (``/proc/stat``); NaN if
    unknown."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
    except OSError:
        return math.nan
    # cpu user nice system idle iowait irq softirq steal ...
    busy = sum(int(fields[i]) for i in (1, 2, 3, 6, 7, 8) if i < len(fields))
    return busy / os.sysconf("SC_CLK_TCK")


def timed(func: Job) -> Sample:
    """Run ``func`` (returning n_stamps, phase seconds, sigmas) under wall and CPU clocks."""
    load1 = os.getloadavg()[0]
    b0, c0, t0 = machine_busy(), cpu_seconds(), time.perf_counter()
    n, phase, sigma = func()
    wall, cpu, busy = time.perf_counter() - t0, cpu_seconds() - c0, machine_busy() - b0
    return Sample(wall, cpu, load1, n, max(busy - cpu, 0.0) / wall, phase, sigma)


def run_megalut(config: SimConfig, out: Path, nproc: int, seed: int, engine: str) -> Job:
    """``simulate(config, out, measure=True, nproc=nproc, engine=engine)`` as a job for
    :func:`timed`."""

    def func() -> tuple[int, float, np.ndarray]:
        res = simulate(
            config, out, measure=True, seed=seed, nproc=nproc, overwrite=True, engine=engine
        )
        return res.n_stamps, res.seconds, features(out)

    return func


def features(out: Path) -> np.ndarray:
    """adamom_sigma of a megalut catalog, NaN where flagged."""
    cat = fitsio.read(str(out), columns=["adamom_sigma", "flags"])
    return np.where(cat["flags"] == 0, cat["adamom_sigma"], np.nan)


def med_range(values: list[float], fmt: str) -> str:
    """``median (min–max)`` of ``values``."""
    if not values:
        return "—"
    med = statistics.median(values)
    if len(values) == 1:
        return format(med, fmt)
    return f"{format(med, fmt)} ({format(min(values), fmt)}–{format(max(values), fmt)})"


def cpu_model() -> str:
    """The CPU model name from ``/proc/cpuinfo``."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


#: The timed runs: name -> (engine or None for the plain loop, workers).
MODES: dict[str, tuple[str | None, int]] = {
    "fast -j 1": ("fast", 1),
    "fast -j 2": ("fast", 2),
    "galsim -j 1": ("galsim", 1),
    "plain loop": (None, 1),
    "fast -j 2 start-up": ("fast", 2),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n-cases", type=int, default=100, help="cases of the scaled-down TP config")
    ap.add_argument("--n-realizations", type=int, default=40, help="realizations per case")
    ap.add_argument(
        "--repeats", type=int, default=3, help="interleaved repeats of every measurement"
    )
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    if min(args.n_cases, args.n_realizations, args.repeats) < 1:
        ap.error("--n-cases, --n-realizations and --repeats must be >= 1")

    galsim.set_omp_threads(1)
    config = load_config(CONFIG, n_cases=args.n_cases, n_realizations=args.n_realizations)
    startup_cfg = load_config(CONFIG, n_cases=2, n_realizations=1)
    warm_cfg = load_config(CONFIG, n_cases=8, n_realizations=4)
    n = config.structure.n_stamps
    load_start = os.getloadavg()
    busy_start, cpu_start, t_start = machine_busy(), cpu_seconds(), time.perf_counter()

    def log(msg: str) -> None:
        print(f"[{time.perf_counter() - t_start:6.1f} s] {msg}", file=sys.stderr, flush=True)

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "sim.fits"
        log("warm-up (imports, numba cache, GalSim Sersic cache, the fast engine's tables) ...")
        for engine in ("fast", "galsim"):
            simulate(
                warm_cfg, out, measure=True, seed=args.seed, nproc=1, overwrite=True, engine=engine
            )
        plain_loop(len(SERSIC_N) * 2, args.seed + 1000)
        for (
            index
        ) in SERSIC_N:  # every gridded index in GalSim's Sersic cache and the fast engine's tables
            galsim.Sersic(n=index, half_light_radius=4.0).drawImage(
                nx=STAMP_SIZE, ny=STAMP_SIZE, scale=1.0
            )
        simulate(
            load_config(CONFIG, n_cases=len(SERSIC_N) * 3, n_realizations=1),
            out,
            measure=True,
            seed=args.seed,
            nproc=1,
            overwrite=True,
            engine="fast",
        )

        jobs: dict[str, Job] = {}
        for name, (engine, workers) in MODES.items():
            if engine is None:
                jobs[name] = lambda: (n, math.nan, plain_loop(n, args.seed))
            elif name.endswith("start-up"):
                jobs[name] = run_megalut(
                    startup_cfg, Path(tmp) / "startup.fits", workers, args.seed, engine
                )
            else:
                jobs[name] = run_megalut(config, out, workers, args.seed, engine)
        names = list(MODES)
        samples: dict[str, list[Sample]] = {k: [] for k in names}
        for r in range(args.repeats):
            order = names[r % len(names) :] + names[: r % len(names)]  # rotate the order
            for name in order:
                s = timed(jobs[name])
                samples[name].append(s)
                log(
                    f"repeat {r + 1}/{args.repeats} {name:20s} {s.n_stamps / s.wall:8.1f} stamps/s "
                    f"({s.wall:.2f} s wall, {s.cpu:.2f} s cpu, load {s.load1:.2f}, "
                    f"other jobs {s.others:.2f} cores)"
                )
    load_end = os.getloadavg()
    elapsed = time.perf_counter() - t_start
    others_all = max(machine_busy() - busy_start - (cpu_seconds() - cpu_start), 0.0) / elapsed

    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    print(f"# bench_simulate: {now}")
    print()
    print(
        f"- machine: {os.cpu_count()} cores ({cpu_model()}), Python {platform.python_version()}, "
        f"GalSim {galsim.__version__}, numpy {np.__version__}"
    )
    print(
        f"- config: {CONFIG.relative_to(ROOT)} scaled to {args.n_cases} cases x "
        f"{args.n_realizations} realizations = {n} stamps of {config.structure.stamp_size}x"
        f"{config.structure.stamp_size} px; {args.repeats} interleaved repeats; megalut through "
        "the library call simulate(..., measure=True, nproc=N, engine=E)"
    )
    print(
        f"- load average (1, 5, 15 min): {load_start[0]:.2f} {load_start[1]:.2f} "
        f"{load_start[2]:.2f} at start, {load_end[0]:.2f} {load_end[1]:.2f} {load_end[2]:.2f} at "
        f"end; whole benchmark {elapsed:.0f} s, during which other jobs kept {others_all:.2f} of "
        f"the {os.cpu_count()} cores busy on average"
    )
    print()
    print("Median over repeats (min–max in brackets).")
    print()
    print(
        "| run | workers | wall s | stamps/s | stamps/s per core | draw+measure phase stamps/s "
        "| CPU ms per stamp | cpu share | load (1 min) | other jobs (cores) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in names:
        ss, w = samples[name], MODES[name][1]
        if name.endswith("start-up"):
            print(
                f"| {name} (2 stamps) | {w} | {med_range([s.wall for s in ss], '.2f')} | — | — | "
                f"— | — | {med_range([s.cpu / (s.wall * w) for s in ss], '.0%')} | "
                f"{med_range([s.load1 for s in ss], '.2f')} | "
                f"{med_range([s.others for s in ss], '.2f')} |"
            )
            continue
        rr = [s.n_stamps / s.wall for s in ss]
        phase = [s.n_stamps / s.phase for s in ss if math.isfinite(s.phase) and s.phase > 0]
        print(
            f"| {name} | {w} | {med_range([s.wall for s in ss], '.2f')} | {med_range(rr, '.0f')} | "
            f"{med_range([x / w for x in rr], '.0f')} | {med_range(phase, '.0f')} | "
            f"{med_range([1e3 * s.cpu / s.n_stamps for s in ss], '.3f')} | "
            f"{med_range([s.cpu / (s.wall * w) for s in ss], '.0%')} | "
            f"{med_range([s.load1 for s in ss], '.2f')} | "
            f"{med_range([s.others for s in ss], '.2f')} |"
        )
    print()

    def per_repeat(a: str, b: str, cpu: bool = False) -> list[float]:
        """``b``'s time over ``a``'s, repeat by repeat (adjacent runs saw similar load)."""
        if cpu:
            return [y.cpu / x.cpu for x, y in zip(samples[a], samples[b])]
        return [y.wall / x.wall for x, y in zip(samples[a], samples[b])]

    su = [s.wall for s in samples["fast -j 2 start-up"]]
    net = [
        b.wall / (a.wall - c)
        for a, b, c in zip(samples["fast -j 2"], samples["fast -j 1"], su)
        if a.wall > c
    ]
    print("| quantity | median (min–max) over repeats |")
    print("|---|---|")
    print(
        "| fast -j 1 / plain loop, stamps/s per core (wall) | "
        f"{med_range(per_repeat('fast -j 1', 'plain loop'), '.2f')} |"
    )
    print(
        "| fast -j 1 / plain loop, stamps per CPU second | "
        f"{med_range(per_repeat('fast -j 1', 'plain loop', True), '.2f')} |"
    )
    print(
        "| fast -j 1 / galsim -j 1, stamps per CPU second | "
        f"{med_range(per_repeat('fast -j 1', 'galsim -j 1', True), '.2f')} |"
    )
    print(
        "| galsim -j 1 / plain loop, stamps per CPU second | "
        f"{med_range(per_repeat('galsim -j 1', 'plain loop', True), '.2f')} |"
    )
    print(
        "| speed-up fast -j 1 -> -j 2 (wall, as measured) | "
        f"{med_range(per_repeat('fast -j 2', 'fast -j 1'), '.2f')} |"
    )
    print(
        "| -j 2 fixed start-up (spawn 2 workers, imports, numba cache), s | "
        f"{med_range(su, '.2f')} |"
    )
    print(
        f"| speed-up fast -j 1 -> -j 2 net of that start-up (derived) | {med_range(net, '.2f')} |"
    )
    print()

    print("Per repeat: stamps/s (cores other jobs kept busy meanwhile):")
    print()
    shown = [k for k in names if not k.endswith("start-up")]
    print("| repeat | " + " | ".join(shown) + " | fast/plain (CPU) |")
    print("|---" * (len(shown) + 2) + "|")
    for r in range(args.repeats):
        cells = [
            f"{samples[k][r].n_stamps / samples[k][r].wall:.0f} ({samples[k][r].others:.2f})"
            for k in shown
        ]
        ratio = samples["plain loop"][r].cpu / samples["fast -j 1"][r].cpu
        print(f"| {r + 1} | {' | '.join(cells)} | {ratio:.2f} |")
    print()

    print("Same galaxies? adamom_sigma (px) of the measured stamps (first repeat):")
    print()
    print("| run | failed/flagged | median | 10%–90% |")
    print("|---|---|---|---|")
    for name in shown:
        sig = samples[name][0].sigma
        ok = sig[np.isfinite(sig)]
        if len(sig) and len(ok):
            print(
                f"| {name} | {1 - len(ok) / len(sig):.1%} | {np.median(ok):.2f} "
                f"| {np.percentile(ok, 10):.2f}–{np.percentile(ok, 90):.2f} |"
            )


if __name__ == "__main__":
    main()
