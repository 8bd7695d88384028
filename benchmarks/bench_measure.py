"""Throughput of ``measure``: the compiled HSM port against GalSim's, side by side, per core.

On a grid of fiducial stamps simulated by ``megalut simulate`` (the paper's Sérsic
galaxies, S/N from faint to bright; ``--stamps`` reuses an existing grid), interleaved in
one run and repeated, timing CPU time of this process (one core; the machine may be busy):

* ``fast``: ``measure_stamps(engine="fast")`` (all features, flags);
* ``galsim``: ``measure_stamps(engine="galsim")``;
* ``loop``: a plain ``galsim.hsm.FindAdaptiveMom(galsim.ImageD(stamp), guess_sig=5,
  strict=False)`` loop, HSM only;
* ``measure_file``: the whole ``megalut measure`` on the FITS grid (fast engine, -j 1).

Then where the fast engine's time goes (HSM kernel, sky MAD, the rest), the floor
(pixel visits of the HSM window per iteration times iterations, GalSim's exp per visit
against the port's cost per visit), and numba's first-call cost in fresh processes with a
cold and a warm cache (``NUMBA_CACHE_DIR`` in a temporary folder). Run::

    PYTHONPATH=. python benchmarks/bench_measure.py [--n 4000] [--repeat 5] [--stamps GRID.fits]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import galsim  # noqa: E402
import numpy as np  # noqa: E402

from megalut_cli.measure.adamom import HSMParams, adaptive_moments  # noqa: E402
from megalut_cli.measure.features import measure_stamps, sky_mad  # noqa: E402
from megalut_cli.measure.measure import measure_file  # noqa: E402
from megalut_cli.measure.stamps import check_grid, cut_stamps, grid_origins, image_info, read_rows  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
from galsim_loops import measure_loop  # noqa: E402


def simulate_grid(path: Path, n: int, seed: int) -> None:
    """A grid of ``n`` fiducial VO stamps (64 px) by ``megalut simulate``."""
    n_cases = 4
    cmd = [
        sys.executable,
        "-m",
        "megalut_cli",
        "simulate",
        str(ROOT / "examples/fiducial/vo.toml"),
        "-o",
        str(path.with_suffix(".cat.fits")),
        "--stamps",
        str(path),
        "--n-cases",
        str(n_cases),
        "--n-realizations",
        str(math.ceil(n / n_cases)),
        "--seed",
        str(seed),
        "-j",
        "1",
        "--overwrite",
    ]
    subprocess.run(cmd, check=True, cwd=ROOT)


def read_grid(path: Path) -> np.ndarray:
    """Every stamp of a grid image, ``(n, S, S)``."""
    info = image_info(path)
    size = int(info.header["STAMPSZ"])
    n_y, n_x = check_grid(info, size)
    origins = grid_origins(n_y, n_x, size)[: int(info.header.get("NSTAMPS", n_y * n_x))]
    return cut_stamps(read_rows(info, 0, info.shape[0]), 0, origins, size)


def cpu_time(func) -> float:
    t0 = time.process_time()
    func()
    return time.process_time() - t0


def window_pixels(res, nsig2: float, shape: tuple[int, int]) -> np.ndarray:
    """Pixels of each stamp's final HSM window (``rho^2 < nsig2``), from its moments."""
    ny, nx = shape
    out = np.zeros(len(res.status))
    yy, xx = np.mgrid[1 : ny + 1, 1 : nx + 1]
    for i in np.flatnonzero(res.status == 0):
        g = complex(res.g1[i], res.g2[i])
        e = 2.0 * g / (1.0 + abs(g) ** 2)
        trace = 2.0 * res.sigma[i] ** 2 / math.sqrt(1.0 - abs(e) ** 2)
        mxx, myy, mxy = trace * (1 + e.real) / 2, trace * (1 - e.real) / 2, trace * e.imag / 2
        det = mxx * myy - mxy**2
        dx, dy = xx - res.x[i], yy - res.y[i]
        rho2 = (myy * dx**2 - 2 * mxy * dx * dy + mxx * dy**2) / det
        out[i] = (rho2 < nsig2).sum()
    return out


FIRST_CALL = """
import resource, time
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime
c0 = cpu()
import numpy as np
from megalut_cli.measure.adamom import adaptive_moments
c1 = cpu()
adaptive_moments(np.random.default_rng(0).normal(size=(2, 64, 64)))
print(c1 - c0, cpu() - c1)
"""


def first_call_costs(repeat: int) -> None:
    """CPU seconds to import, then to run the first call, in fresh processes."""
    print("\nfirst call in a fresh process, CPU seconds (import numpy+numba+adamom / first call):")
    for _ in range(repeat):
        with tempfile.TemporaryDirectory() as cache:
            env = dict(os.environ, NUMBA_CACHE_DIR=cache, PYTHONPATH=str(ROOT))
            for label in ("cold cache", "warm cache"):
                out = subprocess.run(
                    [sys.executable, "-c", FIRST_CALL],
                    env=env,
                    check=True,
                    capture_output=True,
                    text=True,
                ).stdout.split()
                print(f"  {label}: {float(out[0]):.2f} / {float(out[1]):.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=4000, help="stamps to simulate")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--stamps", type=Path, help="an existing grid (STAMPSZ card) instead")
    ap.add_argument("--first-call-only", action="store_true", help="only the compile/cache costs")
    args = ap.parse_args()
    if args.first_call_only:
        first_call_costs(args.repeat)
        return

    with tempfile.TemporaryDirectory() as tmp:
        grid = args.stamps
        if grid is None:
            grid = Path(tmp) / "stamps.fits"
            simulate_grid(grid, args.n, args.seed)
        stamps = read_grid(grid)
        n = len(stamps)
        print(
            f"{platform.machine()} {platform.python_version()}, numpy {np.__version__}, "
            f"galsim {galsim.__version__}; {n} stamps of {stamps.shape[1]} px from {grid.name}"
        )
        t0 = time.perf_counter()
        measure_stamps(stamps[:2], engine="fast")
        print(
            f"first call (import + numba cache load or compile): {time.perf_counter() - t0:.2f} s"
        )

        runs = {
            "fast": lambda: measure_stamps(stamps, engine="fast"),
            "galsim": lambda: measure_stamps(stamps, engine="galsim"),
            "loop": lambda: measure_loop(stamps),
            "measure_file": lambda: measure_file(grid, None, Path(tmp) / "f.fits", overwrite=True),
        }
        times: dict[str, list[float]] = {k: [] for k in runs}
        for _ in range(args.repeat):
            for name, func in runs.items():  # interleaved
                times[name].append(cpu_time(func))
        print(f"\nCPU seconds per stamp (best / median of {args.repeat}, interleaved):")
        for name, ts in times.items():
            print(f"  {name:13s} {min(ts) / n * 1e6:8.1f} us  {np.median(ts) / n * 1e6:8.1f} us")
        for ref in ("loop", "galsim"):
            ratios = np.array(times[ref]) / np.array(times["fast"])
            print(
                f"  speed-up fast vs {ref}: best-of {min(times[ref]) / min(times['fast']):.1f}x, "
                f"median of per-repeat ratios {np.median(ratios):.1f}x"
            )
        e2e = np.array(times["loop"]) / np.array(times["measure_file"])
        print(f"  speed-up measure_file vs loop: median {np.median(e2e):.1f}x")

        # Where the fast engine's time goes.
        kernel = min(cpu_time(lambda: adaptive_moments(stamps, 5.0)) for _ in range(args.repeat))
        exact = min(
            cpu_time(lambda: adaptive_moments(stamps, 5.0, exact_exp=True))
            for _ in range(args.repeat)
        )
        mad = min(cpu_time(lambda: sky_mad(stamps)) for _ in range(args.repeat))
        fast = min(times["fast"])
        print("\nfast engine, best CPU times:")
        print(f"  HSM kernel (adaptive_moments)  {kernel:7.3f} s  {kernel / fast:5.1%}")
        print(f"  sky MAD (np.median of edges)   {mad:7.3f} s  {mad / fast:5.1%}")
        print(f"  the rest (finite check, S/N, columns) {fast - kernel - mad:7.3f} s")
        print(f"  kernel with an exp per pixel (exact_exp=True): {exact:.3f} s")

        # The floor: pixel visits x iterations.
        res = adaptive_moments(stamps, 5.0)
        nsig2 = -2.0 * math.log(HSMParams().convergence_threshold / 10.0)
        pix = window_pixels(res, nsig2, stamps.shape[1:])
        ok = res.status == 0
        visits = (pix[ok] * res.n_iter[ok]).sum()
        loop_t = min(times["loop"])
        print(f"\nfloor ({ok.sum()} converged stamps, {(~ok).sum()} failed):")
        print(
            f"  iterations: mean {res.n_iter[ok].mean():.1f}, "
            f"median {np.median(res.n_iter[ok]):.0f}; failed stamps: "
            f"{res.n_iter[~ok].sum()} iterations in all"
        )
        print(f"  window: mean {pix[ok].mean():.0f} pixels per iteration")
        print(
            "  pixel visits (= GalSim's exp calls) on converged stamps: "
            f"{visits / ok.sum():.0f} per stamp"
        )
        print(
            f"  kernel: {kernel / res.n_iter.sum() * 1e6:.2f} us per iteration; "
            f"exact_exp: {exact / res.n_iter.sum() * 1e6:.2f} us; "
            f"plain loop: {loop_t / res.n_iter.sum() * 1e6:.2f} us (all stamps' iterations)"
        )
        all_visits = visits * res.n_iter.sum() / res.n_iter[ok].sum()
        print(
            f"  per pixel visit (approx.): kernel {kernel / all_visits * 1e9:.2f} ns, "
            f"exact_exp {exact / all_visits * 1e9:.2f} ns, "
            f"plain loop {loop_t / all_visits * 1e9:.2f} ns"
        )
    first_call_costs(2)


if __name__ == "__main__":
    main()
