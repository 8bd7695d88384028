"""Whole commands as a user runs them (issue 26): start-up, small runs, -j 2, measure.

Every figure is a whole process (``python -m megalut_cli ...``, start-up and writing
included), timed from outside: wall clock and CPU seconds (user + system of the process and
its workers). The commands of one comparison run in turn, A B C A B C ..., after one warm-up
each, and the ratios are taken run by run, so they hold when the shared machine's speed
drifts; medians are quoted. Compared:

* ``now``: this working tree (Sersic tables in the disk cache, warm as after a first run;
  ``MEGALUT_CACHE`` points at a folder of this benchmark);
* ``before`` (with ``--before COMMIT``): the same commands on a git worktree of COMMIT, run
  with ``PYTHONPATH`` pointing at it;
* ``galsim``: the plain GalSim loops of ``benchmarks/galsim_loops.py`` as a process
  (draw + noise + ``FindAdaptiveMom`` per stamp; ``FindAdaptiveMom`` on a stamp grid);
* the floors (``--floors``): processes that only start the libraries a command cannot do
  without (numpy, whose FFT the fast engine uses; numba with one cached kernel, loaded by
  numba itself and by ``megalut_cli.jit``; SciPy's BFGS and h5py for training), then what
  the issue's targets would need of a command's own fixed cost, from the times measured in
  the same run.

Run from the repository root (about 15 minutes with the defaults)::

    python benchmarks/bench_startup.py --before c20cfea [--repeats 3] [--skip-30k] [--floors]
        [--large-j]
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TP = str(ROOT / "examples" / "fiducial" / "tp.toml")

#: A module with one cached numba kernel: what any process running our compiled kernels
#: pays (numba's import, its CPU target's set-up at the first call, loading the cache); the
#: light floor's kernel comes from ``megalut_cli.jit.njit`` (a module that imports only numba),
#: whose cached kernels load with numba's runtime alone, without the target's set-up.
FLOOR_KERNEL = """
from {module} import njit


@njit(cache=True)
def total(a):
    s = 0.0
    for v in a:
        s += v
    return s
"""
#: The floor processes: the libraries a command cannot start without, nothing of megalut's;
#: each leaves without Python's teardown, as ``megalut`` does (``LEAVE``).
LEAVE = "; import os; os._exit(0)"
FLOORS = {
    name: code + LEAVE
    for name, code in {
        "python": "pass",
        "numpy": "import numpy",
        "numba": "import numpy, floor_kernel; floor_kernel.total(numpy.zeros(3))",
        "numba light": "import numpy, floor_light; floor_light.total(numpy.zeros(3))",
        "bfgs+h5py": "import numpy, scipy.optimize, h5py",
    }.items()
}
ONE_THREAD = {v: "1" for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}


def run(cmd: Sequence[str], env: dict[str, str]) -> tuple[float, float]:
    """Wall and CPU seconds (user + system, the process and its reaped children) of ``cmd``,
    run in the folder of the code it runs (``python -m`` puts it first on the path)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run(
        list(cmd),
        env=env,
        cwd=env.get("PYTHONPATH", ROOT),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        sys.exit(f"failed ({done.returncode}): {' '.join(cmd)}\n{done.stderr[-2000:]}")
    return wall, after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime


def compare(
    title: str, commands: dict[str, tuple[list[str], dict[str, str]]], repeats: int
) -> dict[str, float]:
    """Run ``commands`` in turn ``repeats`` times after a warm-up; print medians and ratios to
    the first; return the median wall seconds of each."""
    for cmd, env in commands.values():
        run(cmd, env)
    times: dict[str, list[tuple[float, float]]] = {name: [] for name in commands}
    for _ in range(repeats):
        for name, (cmd, env) in commands.items():
            times[name].append(run(cmd, env))
    first = next(iter(commands))
    print(f"\n{title}  (medians of {repeats}; ratio = other / {first}, run by run)")
    print(f"  {'':10s} {'wall s':>8s} {'cpu s':>8s} {'wall ratio':>11s} {'cpu ratio':>10s}")
    for name, samples in times.items():
        wall = statistics.median(w for w, _ in samples)
        cpu = statistics.median(c for _, c in samples)
        rw = statistics.median(s[0] / f[0] for s, f in zip(samples, times[first]))
        rc = statistics.median(s[1] / f[1] for s, f in zip(samples, times[first]))
        print(f"  {name:10s} {wall:8.2f} {cpu:8.2f} {rw:11.2f} {rc:10.2f}")
    return {name: statistics.median(w for w, _ in samples) for name, samples in times.items()}


def print_target_arithmetic(floors: dict[str, float], medians: dict[str, dict[str, float]]) -> None:
    """What each target of issue 26 needs, from this run's medians: the least a command could
    take is its floor process plus its work (its time beyond the one-stamp command)."""
    floor = kernel = floors["numba light"]  # numpy's FFT comes with numpy
    one = medians["1"]["now"]
    print("\nwhat the targets need (medians of this run, seconds)")
    print(f"  simulate's own fixed cost: 1-stamp command {one:.2f} - floor numba light {floor:.2f}")
    print(f"    = {one - floor:.2f}")
    for label, factor in (("3000", 5.0), ("30 000", 8.0)):
        if label not in medians:
            continue
        m = medians[label]
        work = m["now"] - one
        allowed = m["galsim"] / factor
        least = floor + work
        print(
            f"  {label} stamps >= {factor:g}x: allowed {allowed:.2f}; work {work:.2f} + floor "
            f"{floor:.2f} = {least:.2f} (best ratio {m['galsim'] / least:.2f}x at no fixed cost "
            f"of ours; the work alone {m['galsim'] / work:.2f}x)"
        )
    j = medians.get("-j now")
    if j:
        work = j["-j 1"] - one
        least = floor + work / 2
        print(
            f"  -j 2 >= 1.8x at 4000 stamps: -j 1 {j['-j 1']:.2f} needs -j 2 <= "
            f"{j['-j 1'] / 1.8:.2f}; floor {floor:.2f} + work {work:.2f} / 2 = {least:.2f} "
            f"(best ratio {j['-j 1'] / least:.2f}, perfectly split, no fixed cost of ours)"
        )
    m = medians["measure"]
    allowed = m["galsim"] / 5.0
    print(
        f"  measure >= 5x: allowed {allowed:.2f}; the command {m['now']:.2f} is the floor "
        f"numba light {kernel:.2f} + {m['now'] - kernel:.2f} (reading, cutting, kernel, "
        "writing, imports)"
    )
    print(f"  train-point (bench_training.py --cli): floor bfgs+h5py {floors['bfgs+h5py']:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--before", help="a commit to compare with (git worktree in a temporary folder)"
    )
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--skip-30k", action="store_true", help="leave out the 30 000-stamp comparison"
    )
    parser.add_argument(
        "--large-j", action="store_true", help="also compare -j 1 and -j 2 on 40 000 stamps"
    )
    parser.add_argument(
        "--floors",
        action="store_true",
        help="also time the floor processes and print what each target needs of a command",
    )
    args = parser.parse_args()

    work = Path(tempfile.mkdtemp(prefix="bench-startup-"))
    base = {**os.environ, **ONE_THREAD, "MEGALUT_CACHE": str(work / "cache")}
    base.pop("PYTHONPATH", None)
    now_env = base
    before_env = None
    if args.before:
        tree = work / "before"
        subprocess.run(
            ["git", "worktree", "add", "--detach", str(tree), args.before],
            cwd=ROOT,
            check=True,
            capture_output=True,
        )
        before_env = {**base, "PYTHONPATH": str(tree)}
    py = sys.executable
    cli = [py, "-m", "megalut_cli"]
    loops = [py, str(ROOT / "benchmarks" / "galsim_loops.py")]
    print(
        f"{datetime.datetime.now():%Y-%m-%d %H:%M}, {platform.node()}, {os.cpu_count()} cores, "
        f"load {os.getloadavg()[0]:.1f}; before = {args.before or '-'}"
    )

    def versions(cmd: list[str]) -> dict[str, tuple[list[str], dict[str, str]]]:
        out = {"now": (cmd, now_env)}
        if before_env:
            out["before"] = (cmd, before_env)
        return out

    def sim(n_cases: int, n_rea: int, j: int, name: str) -> list[str]:
        return [
            *cli,
            "simulate",
            TP,
            "--measure",
            "-j",
            str(j),
            "--n-cases",
            str(n_cases),
            "--n-realizations",
            str(n_rea),
            "-o",
            str(work / f"{name}.fits"),
            "--overwrite",
            "-q",
        ]

    floors: dict[str, float] = {}
    if args.floors:
        folder = work / "floors"
        folder.mkdir()
        (folder / "floor_kernel.py").write_text(FLOOR_KERNEL.format(module="numba"))
        (folder / "floor_light.py").write_text(FLOOR_KERNEL.format(module="megalut_cli.jit"))
        env = {**base, "PYTHONPATH": str(folder)}
        floors = compare(
            "floors: processes that only start what a command needs (nothing of megalut's)",
            {name: ([py, "-c", code], env) for name, code in FLOORS.items()},
            args.repeats,
        )
    medians: dict[str, dict[str, float]] = {}
    compare("megalut --version", versions([*cli, "--version"]), args.repeats)
    compare("megalut simulate --help", versions([*cli, "simulate", "--help"]), args.repeats)
    medians["1"] = compare(
        "simulate --measure -j 1, 1 stamp", versions(sim(1, 1, 1, "one")), args.repeats
    )
    for n_cases, label in ((30, "3000"),) + (() if args.skip_30k else ((300, "30 000"),)):
        n = n_cases * 100
        cmds = {
            "now": (sim(n_cases, 100, 1, f"s{n}"), now_env),
            "galsim": ([*loops, "simulate", str(n), "1"], base),
        }
        if before_env:
            cmds["before"] = (sim(n_cases, 100, 1, f"s{n}b"), before_env)
        medians[label] = compare(
            f"simulate --measure -j 1, {label} stamps, against the plain GalSim loop",
            cmds,
            args.repeats,
        )
    for n_cases in (40, 400) if args.large_j else (40,):
        for name, env in (("now", now_env), ("before", before_env)):
            if env is not None:
                times = compare(
                    f"-j 1 against -j 2, {n_cases * 100} stamps ({name})",
                    {
                        "-j 1": (sim(n_cases, 100, 1, "j1"), env),
                        "-j 2": (sim(n_cases, 100, 2, "j2"), env),
                    },
                    args.repeats,
                )
                if n_cases == 40:
                    medians[f"-j {name}"] = times
    grid = work / "grid.fits"
    subprocess.run(
        [
            *cli,
            "simulate",
            str(ROOT / "examples/fiducial/vo.toml"),
            "-o",
            str(work / "grid.cat.fits"),
            "--stamps",
            str(grid),
            "--n-cases",
            "4",
            "--n-realizations",
            "5000",
            "--seed",
            "3",
            "-j",
            "2",
            "-q",
        ],
        env=now_env,
        cwd=ROOT,
        check=True,
    )
    meas = [*cli, "measure", str(grid), "-o", str(work / "m.fits"), "-j", "1", "--overwrite", "-q"]
    cmds = {"now": (meas, now_env), "galsim": ([*loops, "measure", str(grid)], base)}
    if before_env:
        cmds["before"] = (meas, before_env)
    medians["measure"] = compare(
        "measure -j 1, 20 000 stamps, against a FindAdaptiveMom loop", cmds, args.repeats
    )
    if floors:
        print_target_arithmetic(floors, medians)
    if args.before:
        subprocess.run(
            ["git", "worktree", "remove", "--force", str(work / "before")], cwd=ROOT, check=False
        )


if __name__ == "__main__":
    main()
