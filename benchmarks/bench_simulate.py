"""Throughput of ``megalut simulate --measure`` against a plain GalSim loop, and its -j scaling.

On a scaled-down fiducial TP config (``examples/fiducial/tp.toml``: 64x64 stamps, Sersic
galaxies with gridded index convolved with a circular Gaussian PSF of sigma 2 px, Gaussian
noise of sigma 1, Table 1 of the paper), measured in ONE run, interleaved and repeated
because the machine is shared:

* ``megalut -j 1`` / ``megalut -j 2``: the library call
  ``megalut_cli.sim.simulate.simulate(config, out, measure=True, nproc=N)`` (what
  ``megalut simulate CONFIG -o OUT --measure -j N`` runs after parsing its options), timed
  from the call to its return, so it includes the worker start-up for ``-j 2`` and writing
  the FITS catalog;
* ``plain loop``: the same kind of galaxies (same parameter distributions, drawn here with
  numpy per stamp), one stamp at a time in this process: ``galsim.Sersic`` sheared by the
  intrinsic ellipticity then the shear, ``Convolve`` with the PSF, ``drawImage`` (64x64,
  sub-pixel offset), ``addNoise`` (Gaussian, sigma 1), ``galsim.hsm.FindAdaptiveMom``;
* ``-j 2 start-up``: ``simulate`` on 2 cases x 1 realization at ``-j 2``, i.e. the fixed
  cost of spawning the workers and importing GalSim, SciPy, megalut in them.

A warm-up (megalut -j 1 and the plain loop on a few stamps) runs first, so that the
in-process runs see warm imports and GalSim's Sersic cache, as in a long run; the
``-j 2`` workers are new processes for every call, as with the CLI. BLAS/OpenMP are
limited to one thread per process (``galsim.set_omp_threads(1)``, as megalut's workers do).

CPU time (this process for ``-j 1`` and the plain loop, this process plus the reaped
workers for ``-j 2``) is reported next to the wall clock: on a loaded machine
``cpu share`` = CPU seconds / (wall seconds x workers) shows how much of the cores the
benchmark actually got, and ``other jobs`` = the machine's busy CPU seconds (``/proc/stat``)
minus the benchmark's own, per wall second, how many cores the other users took meanwhile.
Run::

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

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "examples" / "fiducial" / "tp.toml"

#: The plain loop's parameter distributions: those of examples/fiducial/tp.toml (Table 1).
STAMP_SIZE = 64
PSF_SIGMA = 2.0
NOISE_SIGMA = 1.0
SERSIC_N = np.round(np.arange(1.0, 4.0 + 1e-9, 0.1), 1)  # grid, step 0.1 (GalSim's cache)
RAD = (2.0, 8.0)  # half-light radius, pixels, uniform
SB = (1.0, 15.0)  # surface brightness, flux = sb * pi * rad^2, uniform
ELL_MODE, ELL_MAX = 0.2, 0.6  # Rayleigh of mode 0.2 truncated to [0, 0.6]
SHEAR_MAX = 0.1  # g1, g2 uniform in [-0.1, 0.1]
OFFSET = 0.5  # sub-pixel offset uniform in [-0.5, 0.5] px

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
    """CPU seconds all cores of the machine spent busy since boot (``/proc/stat``); NaN if unknown."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
    except OSError:
        return math.nan
    # cpu user nice system idle iowait irq softirq steal ...
    busy = sum(int(fields[i]) for i in (1, 2, 3, 6, 7, 8) if i < len(fields))
    return busy / os.sysconf("SC_CLK_TCK")


def truncated_rayleigh(rng: np.random.Generator, n: int, mode: float, hi: float) -> np.ndarray:
    """Rayleigh of ``mode`` truncated to [0, hi] (inverse CDF)."""
    q_hi = math.exp(-(hi**2) / (2 * mode**2))
    q = 1.0 - rng.random(n) * (1.0 - q_hi)
    return np.sqrt(-2 * mode**2 * np.log(q))


def plain_loop(n: int, seed: int) -> np.ndarray:
    """Draw, noise and measure ``n`` fiducial stamps with plain GalSim calls; adamom sigmas."""
    rng = np.random.default_rng(seed)
    sersicn = rng.choice(SERSIC_N, n)
    rad = rng.uniform(*RAD, n)
    flux = rng.uniform(*SB, n) * np.pi * rad**2
    ell = truncated_rayleigh(rng, n, ELL_MODE, ELL_MAX)
    theta = rng.uniform(0.0, np.pi, n)
    e1, e2 = ell * np.cos(2 * theta), ell * np.sin(2 * theta)
    g1, g2 = rng.uniform(-SHEAR_MAX, SHEAR_MAX, (2, n))
    dx, dy = rng.uniform(-OFFSET, OFFSET, (2, n))
    noise_seeds = rng.integers(1, 2**31 - 1, n)
    psf = galsim.Gaussian(sigma=PSF_SIGMA)
    sigma = np.full(n, np.nan)
    for i in range(n):
        gal = galsim.Sersic(n=sersicn[i], half_light_radius=rad[i], flux=flux[i])
        gal = gal.shear(g1=e1[i], g2=e2[i]).shear(g1=g1[i], g2=g2[i])
        image = galsim.Convolve(gal, psf).drawImage(
            nx=STAMP_SIZE, ny=STAMP_SIZE, scale=1.0, offset=(dx[i], dy[i])
        )
        noise = galsim.GaussianNoise(galsim.BaseDeviate(int(noise_seeds[i])), sigma=NOISE_SIGMA)
        image.addNoise(noise)
        res = galsim.hsm.FindAdaptiveMom(image, strict=False)
        if res.moments_status == 0:
            sigma[i] = res.moments_sigma
    return sigma


def timed(func: Job) -> Sample:
    """Run ``func`` (returning n_stamps, phase seconds, sigmas) under wall and CPU clocks."""
    load1 = os.getloadavg()[0]
    b0, c0, t0 = machine_busy(), cpu_seconds(), time.perf_counter()
    n, phase, sigma = func()
    wall, cpu, busy = time.perf_counter() - t0, cpu_seconds() - c0, machine_busy() - b0
    return Sample(wall, cpu, load1, n, max(busy - cpu, 0.0) / wall, phase, sigma)


def run_megalut(config: SimConfig, out: Path, nproc: int, seed: int) -> Job:
    """``simulate(config, out, measure=True, nproc=nproc)`` as a job for :func:`timed`."""

    def func() -> tuple[int, float, np.ndarray]:
        res = simulate(config, out, measure=True, seed=seed, nproc=nproc, overwrite=True)
        return res.n_stamps, res.seconds, np.zeros(0)

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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-cases", type=int, default=100, help="cases of the scaled-down TP config")
    ap.add_argument("--n-realizations", type=int, default=40, help="realizations per case")
    ap.add_argument("--repeats", type=int, default=3, help="interleaved repeats of every measurement")
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
        log("warm-up (imports, GalSim Sersic cache) ...")
        simulate(warm_cfg, out, measure=True, seed=args.seed, nproc=1, overwrite=True)
        plain_loop(len(SERSIC_N) * 2, args.seed + 1000)
        for index in SERSIC_N:  # every gridded index in GalSim's Sersic cache
            galsim.Sersic(n=index, half_light_radius=4.0).drawImage(nx=STAMP_SIZE, ny=STAMP_SIZE, scale=1.0)

        modes: dict[str, Job] = {
            "megalut -j 1": run_megalut(config, out, 1, args.seed),
            "megalut -j 2": run_megalut(config, out, 2, args.seed),
            "plain loop": lambda: (n, math.nan, plain_loop(n, args.seed)),
            "-j 2 start-up": run_megalut(startup_cfg, Path(tmp) / "startup.fits", 2, args.seed),
        }
        names = list(modes)
        samples: dict[str, list[Sample]] = {k: [] for k in names}
        megalut_sigma = np.zeros(0)
        for r in range(args.repeats):
            order = names[r % len(names):] + names[: r % len(names)]  # rotate the order
            for name in order:
                s = timed(modes[name])
                samples[name].append(s)
                if name == "megalut -j 1" and not len(megalut_sigma):
                    megalut_sigma = features(out)
                log(f"repeat {r + 1}/{args.repeats} {name:14s} {s.n_stamps / s.wall:8.1f} stamps/s "
                    f"({s.wall:.2f} s wall, {s.cpu:.2f} s cpu, load {s.load1:.2f}, "
                    f"other jobs {s.others:.2f} cores)")
    load_end = os.getloadavg()
    elapsed = time.perf_counter() - t_start
    others_all = max(machine_busy() - busy_start - (cpu_seconds() - cpu_start), 0.0) / elapsed

    workers = {"megalut -j 1": 1, "megalut -j 2": 2, "plain loop": 1, "-j 2 start-up": 2}

    def rates(name: str) -> list[float]:
        return [s.n_stamps / s.wall for s in samples[name]]

    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    print(f"# bench_simulate: {now}")
    print()
    print(f"- machine: {os.cpu_count()} cores ({cpu_model()}), Python {platform.python_version()}, "
          f"GalSim {galsim.__version__}, numpy {np.__version__}")
    print(f"- config: {CONFIG.relative_to(ROOT)} scaled to {args.n_cases} cases x "
          f"{args.n_realizations} realizations = {n} stamps of {config.structure.stamp_size}x"
          f"{config.structure.stamp_size} px; {args.repeats} interleaved repeats; megalut through "
          "the library call simulate(..., measure=True, nproc=N)")
    print(f"- load average (1, 5, 15 min): {load_start[0]:.2f} {load_start[1]:.2f} {load_start[2]:.2f} "
          f"at start, {load_end[0]:.2f} {load_end[1]:.2f} {load_end[2]:.2f} at end; "
          f"whole benchmark {elapsed:.0f} s, during which other jobs kept {others_all:.2f} of the "
          f"{os.cpu_count()} cores busy on average")
    print()
    print("Median over repeats (min–max in brackets).")
    print()
    print("| run | workers | wall s | stamps/s | stamps/s per core | draw+measure phase stamps/s "
          "| CPU ms per stamp | cpu share | load (1 min) | other jobs (cores) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in names[:3]:
        ss, w = samples[name], workers[name]
        rr = rates(name)
        phase = [s.n_stamps / s.phase for s in ss if math.isfinite(s.phase) and s.phase > 0]
        print(f"| {name} | {w} | {med_range([s.wall for s in ss], '.2f')} | {med_range(rr, '.0f')} | {med_range([x / w for x in rr], '.0f')} "
              f"| {med_range(phase, '.0f')} | {med_range([1e3 * s.cpu / s.n_stamps for s in ss], '.2f')} "
              f"| {med_range([s.cpu / (s.wall * w) for s in ss], '.0%')} "
              f"| {med_range([s.load1 for s in ss], '.2f')} | {med_range([s.others for s in ss], '.2f')} |")
    st = samples["-j 2 start-up"]
    print(f"| -j 2 start-up (2 stamps) | 2 | {med_range([s.wall for s in st], '.2f')} | — | — | — | — "
          f"| {med_range([s.cpu / (s.wall * 2) for s in st], '.0%')} "
          f"| {med_range([s.load1 for s in st], '.2f')} | {med_range([s.others for s in st], '.2f')} |")
    print()

    j1 = [s.wall for s in samples["megalut -j 1"]]
    j2 = [s.wall for s in samples["megalut -j 2"]]
    pl = [s.wall for s in samples["plain loop"]]
    su = [s.wall for s in st]
    # Per-repeat ratios (the runs of one repeat are adjacent in time, so they saw similar load).
    ratio = [p / a for a, p in zip(j1, pl)]
    speedup = [a / b for a, b in zip(j1, j2)]
    net = [a / (b - c) for a, b, c in zip(j1, j2, su) if b > c]
    cpu_ratio = [p.cpu / a.cpu for a, p in zip(samples["megalut -j 1"], samples["plain loop"])]
    print("| quantity | median (min–max) over repeats |")
    print("|---|---|")
    print(f"| megalut -j 1 / plain loop, stamps/s per core (wall) | {med_range(ratio, '.2f')} |")
    print(f"| megalut -j 1 / plain loop, stamps per CPU second | {med_range(cpu_ratio, '.2f')} |")
    print(f"| speed-up -j 1 -> -j 2 (wall, as measured) | {med_range(speedup, '.2f')} |")
    print(f"| -j 2 fixed start-up (spawn 2 workers, imports), s | {med_range(su, '.2f')} |")
    print(f"| speed-up -j 1 -> -j 2 net of that start-up (derived) | {med_range(net, '.2f')} |")
    print()

    print("Per repeat (stamps/s, and in brackets the cores other jobs kept busy meanwhile):")
    print()
    print("| repeat | megalut -j 1 | megalut -j 2 | plain loop | -j 2 start-up s "
          "| -j1/plain | speed-up 1->2 | net of start-up |")
    print("|---|---|---|---|---|---|---|---|")
    for r in range(args.repeats):
        a, b, p, c = (samples[k][r] for k in names)
        cells = [f"{x.n_stamps / x.wall:.0f} ({x.others:.2f})" for x in (a, b, p)]
        net_r = f"{a.wall / (b.wall - c.wall):.2f}" if b.wall > c.wall else "—"
        print(f"| {r + 1} | {' | '.join(cells)} | {c.wall:.2f} ({c.others:.2f}) "
              f"| {p.wall / a.wall:.2f} | {a.wall / b.wall:.2f} | {net_r} |")
    print()

    s_m = megalut_sigma[np.isfinite(megalut_sigma)]
    s_p = samples["plain loop"][0].sigma
    fp = float(np.mean(~np.isfinite(s_p))) if len(s_p) else math.nan
    s_p = s_p[np.isfinite(s_p)]
    print("Same kind of galaxies? adamom_sigma (px) of the measured stamps:")
    print()
    print("| run | failed/flagged | median | 10%–90% |")
    print("|---|---|---|---|")
    if len(megalut_sigma):
        print(f"| megalut | {1 - len(s_m) / len(megalut_sigma):.1%} | {np.median(s_m):.2f} "
              f"| {np.percentile(s_m, 10):.2f}–{np.percentile(s_m, 90):.2f} |")
    if len(s_p):
        print(f"| plain loop | {fp:.1%} | {np.median(s_p):.2f} "
              f"| {np.percentile(s_p, 10):.2f}–{np.percentile(s_p, 90):.2f} |")


if __name__ == "__main__":
    main()
