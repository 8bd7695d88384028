"""Cost of the realistic galaxy models and correlated noise relative to the fiducial set.

Runs ``simulate(config, out, measure=True)`` (one process) on ``examples/fiducial/tp.toml``
and on every ``examples/realgal/*.toml``, scaled down to the same number of stamps,
interleaved and repeated in ONE run because the machine is shared; prints the median
stamps per second of each and its ratio to the fiducial Sersic set. A warm-up run of each
config comes first (imports, GalSim's profile caches, the correlated-noise model).
Run::

    python benchmarks/bench_models.py [--n-cases 4 --n-realizations 50 --repeats 3]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from megalut_cli.sim.config import load_config  # noqa: E402
from megalut_cli.sim.simulate import simulate  # noqa: E402

ROOT = Path(__file__).resolve().parents[1] / "examples"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-cases", type=int, default=4)
    parser.add_argument("--n-realizations", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    paths = [ROOT / "fiducial" / "tp.toml", *sorted((ROOT / "realgal").glob("*.toml"))]
    configs = {
        p.relative_to(ROOT).as_posix(): load_config(
            p, n_cases=args.n_cases, n_realizations=args.n_realizations
        )
        for p in paths
    }
    rates: dict[str, list[float]] = {name: [] for name in configs}
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out.fits"
        for cfg in configs.values():  # warm-up
            simulate(
                cfg.with_structure(n_cases=1, n_realizations=4), out, measure=True, overwrite=True
            )
        for _ in range(args.repeats):
            for name, cfg in configs.items():
                t0 = time.perf_counter()
                simulate(cfg, out, measure=True, seed=3, overwrite=True)
                rates[name].append(cfg.structure.n_stamps / (time.perf_counter() - t0))
    ref = statistics.median(rates["fiducial/tp.toml"])
    n = args.n_cases * args.n_realizations
    print(f"{n} stamps per run, median of {args.repeats} interleaved runs, one process")
    print(f"{'config':28s} {'stamps/s':>9s} {'ratio to fiducial':>18s}")
    for name, r in rates.items():
        m = statistics.median(r)
        print(f"{name:28s} {m:9.1f} {m / ref:18.2f}")


if __name__ == "__main__":
    main()
