"""Cost of bootstrap errors in ``megalut evaluate``, against fit errors, side by side.

A synthetic common-random-number catalog (K cases x N realizations in 90-degree pairs,
weights and PSF columns, so both schemes and the PSF frame are fitted) is evaluated in
memory (``evaluate_columns``) with errors from the fit and with a bootstrap of B
resamples over the galaxy pairs; also with ``--by snr`` in 5 bins. One core (BLAS
limited to one thread). Prints the best of ``--repeat`` CPU times of this process (on a
shared machine the wall clock mostly measures the other jobs) and their ratio. Run::

    python benchmarks/bench_bootstrap.py [--cases 20] [--rea 50000] [--resamples 200] [--repeat 3]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from megalut_cli.shear.evaluate import BootstrapSpec, evaluate_columns  # noqa: E402


def catalog(n_cases: int, n_rea: int, seed: int = 1) -> dict[str, np.ndarray]:
    """Estimates of the same galaxy pairs under ``n_cases`` shears (no simulation)."""
    rng = np.random.default_rng(seed)
    n = n_cases * n_rea
    e = np.repeat(rng.normal(0, 0.25, (2, n_rea // 2)), 2, axis=1) * np.tile(
        [1.0, -1.0], n_rea // 2
    )
    g = rng.uniform(-0.1, 0.1, (2, n_cases))
    cols = {"case": np.repeat(np.arange(n_cases), n_rea), "rea": np.tile(np.arange(n_rea), n_cases)}
    for i in (0, 1):
        t = np.repeat(g[i], n_rea)
        cols[f"tru_g{i + 1}"] = t
        cols[f"pre_g{i + 1}"] = (
            np.tile(e[i], n_cases) + t * (1 + rng.normal(0, 0.2, n)) + rng.normal(0, 0.05, n)
        )
        cols[f"pre_g{i + 1}_w"] = rng.uniform(0.1, 1.0, n)
        cols[f"tru_psf_g{i + 1}"] = np.full(n, 0.01 * (i + 1))
    cols["snr"] = rng.uniform(5, 50, n)
    return cols


def best_time(fn, repeat: int) -> float:
    """Best CPU time (s) of ``repeat`` calls."""
    times = []
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        times.append(time.process_time() - t0)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=20)
    ap.add_argument("--rea", type=int, default=50000)
    ap.add_argument("--resamples", type=int, default=200)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    cols = catalog(args.cases, args.rea)
    spec = BootstrapSpec(2, args.resamples, 1, True)
    print(
        f"{args.cases} cases x {args.rea} realizations = {args.cases * args.rea} rows, "
        f"{args.rea // 2} pairs, {args.resamples} resamples, best of {args.repeat}"
    )
    for by in (None, ["snr"]):
        fit = best_time(lambda by=by: evaluate_columns(cols, by=by), args.repeat)
        boot = best_time(lambda by=by: evaluate_columns(cols, by=by, bootstrap=spec), args.repeat)
        what = "overall" if by is None else "overall + --by snr (5 bins)"
        print(
            f"{what:30} fit {fit:6.2f} s   bootstrap {boot:6.2f} s   ratio {boot / fit:5.1f}  (CPU)"
        )


if __name__ == "__main__":
    main()
