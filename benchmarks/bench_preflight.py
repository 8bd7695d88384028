"""Cost and accuracy of ``simulate``'s pre-flight time estimate, side by side with the run.

Before drawing, ``megalut simulate`` (and ``megalut run``, per set) times a tiny calibration
draw (``stamps_per_second``: 32 stamps of the first case, after a warm-up draw of the same)
and logs the estimated time. This script measures, in one process on ONE worker (``-j 1``),
for each repeat and each engine:

* ``calibration``: seconds spent in ``stamps_per_second``;
* ``estimate``: the predicted seconds of the run (stamps / calibrated rate);
* ``run``: seconds of ``simulate`` itself (same config, all stamps, measured);

and reports ``calibration / run`` (the overhead) and ``estimate / run`` (the accuracy).
Run::

    python benchmarks/bench_preflight.py [--cases 60] [--realizations 50] [--repeat 3]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import platform  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from megalut_cli.engine import ENGINES  # noqa: E402
from megalut_cli.sim.config import load_config  # noqa: E402
from megalut_cli.sim.simulate import simulate, stamps_per_second  # noqa: E402

CONFIG = Path(__file__).resolve().parents[1] / "examples" / "fiducial" / "tp.toml"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=60)
    parser.add_argument("--realizations", type=int, default=50)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    cfg = load_config(CONFIG, (), n_cases=args.cases, n_realizations=args.realizations)
    n = cfg.structure.n_stamps
    print(
        f"{CONFIG.name}: {args.cases} cases x {args.realizations} realizations = {n} stamps, "
        f"measured, -j 1; python {platform.python_version()}, {os.cpu_count()} cores, "
        f"load {os.getloadavg()[0]:.1f}"
    )
    rows = {e: [] for e in ENGINES}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeat):
            for engine in ENGINES:
                t0 = time.perf_counter()
                rate = stamps_per_second(cfg, 1, True, False, engine=engine)
                calibration = time.perf_counter() - t0
                t0 = time.perf_counter()
                simulate(
                    cfg,
                    Path(tmp) / f"{engine}.fits",
                    measure=True,
                    seed=1,
                    nproc=1,
                    overwrite=True,
                    engine=engine,
                )
                run = time.perf_counter() - t0
                estimate = n / rate
                rows[engine].append((calibration, estimate, run))
                print(
                    f"repeat {r + 1}/{args.repeat} {engine:7s} calibration {calibration:5.2f} s, "
                    f"estimate {estimate:6.1f} s, run {run:6.1f} s, load {os.getloadavg()[0]:.1f}"
                )
    print("\n| engine | calibration / run | estimate / run |\n|---|---|---|")
    for engine, values in rows.items():
        v = np.asarray(values)
        over, acc = v[:, 0] / v[:, 2], v[:, 1] / v[:, 2]
        print(
            f"| {engine} | {np.median(over):.3f} ({over.min():.3f}-{over.max():.3f}) "
            f"| {np.median(acc):.2f} ({acc.min():.2f}-{acc.max():.2f}) |"
        )


if __name__ == "__main__":
    main()
