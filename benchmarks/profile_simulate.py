"""CPU time per stamp of each component of ``simulate(cfg, out, measure=True)`` (fast engine, -j 1).

Profiles one call on the fiducial TP config (``examples/fiducial/tp.toml``, default 50
cases x 40 realizations = 2000 stamps) with cProfile on the process CPU clock, after a
warm-up call (numba caches, GalSim's Sersic cache, the renderer's tables), and prints the
cumulative time of the k-image fill, the two inverse FFTs, the adaptive moments, the noise
and the rest. cProfile adds a few microseconds per Python call, so "rest" is inflated;
compare runs side by side (e.g. two source trees, alternated). Run from the worktree root::

    PYTHONPATH=. python benchmarks/profile_simulate.py [--n-cases 50 --n-realizations 40]
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import tempfile
import time
from pathlib import Path

from megalut_cli.sim.config import load_config
from megalut_cli.sim.simulate import simulate

CONFIG = Path(__file__).resolve().parent.parent / "examples" / "fiducial" / "tp.toml"

#: Component name -> predicate on a cProfile (file, line, function) key.
COMPONENTS = {
    "k-image fill": lambda k: k[2] == "fill_kimages",
    "inverse FFTs": lambda k: "numpy/fft" in k[0] and k[2] == "_raw_fft",
    "cut, sky MAD, adaptive moments": lambda k: (
        k[2] in ("adaptive_moments_stack", "cut_measure_stack")
    ),
    "noise": lambda k: k[2] == "add_batch",
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-cases", type=int, default=50)
    parser.add_argument("--n-realizations", type=int, default=40)
    parser.add_argument(
        "--top", type=int, default=0, help="also list the N functions of most own time"
    )
    args = parser.parse_args()
    cfg = load_config(CONFIG, n_cases=args.n_cases, n_realizations=args.n_realizations)
    n = args.n_cases * args.n_realizations
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "sim.fits"
        simulate(cfg, out, measure=True, seed=1, nproc=1, overwrite=True)  # warm-up
        prof = cProfile.Profile(time.process_time)
        prof.enable()
        simulate(cfg, out, measure=True, seed=1, nproc=1, overwrite=True)
        prof.disable()
    stats = pstats.Stats(prof).stats  # key -> (calls, primitive calls, tottime, cumtime, callers)
    total = max(v[3] for k, v in stats.items() if k[2] == "simulate")
    parts = {
        name: sum(v[3] for k, v in stats.items() if pred(k)) for name, pred in COMPONENTS.items()
    }
    parts["rest (Python, geometry, catalog)"] = total - sum(parts.values())
    print(
        f"simulate --measure, {n} fiducial stamps, -j 1, under cProfile: "
        f"{total / n * 1e3:.3f} CPU ms/stamp"
    )
    for name, seconds in parts.items():
        print(f"  {name:<34} {seconds / n * 1e3:7.3f} ms/stamp  {seconds / total:6.1%}")
    if args.top:
        print(f"the {args.top} functions of most own time:")
        for k, v in sorted(stats.items(), key=lambda kv: -kv[1][2])[: args.top]:
            where = f"{k[2]} ({Path(k[0]).name}:{k[1]})"
            print(f"  {v[2] / n * 1e3:7.4f} ms/stamp  {v[0]:7d} calls  {where}")


if __name__ == "__main__":
    main()
