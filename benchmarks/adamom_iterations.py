"""Where the adaptive moments' time goes: HSM's iterations per stamp on the fiducial stamps.

The stamps of ``benchmarks/bench_metacal.py`` (its ``fiducial_inputs``: ``megalut simulate
examples/fiducial/vo.toml --stamps ... --n-cases 10 --n-realizations 300 --seed 5``, 3000
fiducial 64-px stamps, noise sigma 1), measured by ``measure.adamom.adaptive_moments``
(GalSim's ``FindAdaptiveMom``, compiled) on one core: CPU per stamp (best of 3), the
iterations per stamp, the share of all iterations spent on stamps that take more than 100,
and what a lower iteration cap than GalSim's 400 (``HSMParams(max_mom2_iter=...)``) would
save and cost (stamps whose status changes, failures); then, at GalSim's cap, the damped
retry of the failed iterations (``adaptive_moments(..., retry_step=...)``, ``measure
--moments-retry``): the failures it leaves, by status, and what it costs. Run::

    PYTHONPATH=. python benchmarks/adamom_iterations.py [--caps 400 200 100 60] [--retry 0.5]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import galsim  # noqa: E402
import numpy as np  # noqa: E402

from benchmarks.bench_metacal import fiducial_inputs  # noqa: E402
from megalut_cli.measure.adamom import STATUS_NAMES, adaptive_moments  # noqa: E402
from megalut_cli.measure.adamom_nb import TOO_MANY_ITERATIONS  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--caps", type=int, nargs="+", default=[400, 200, 100, 60])
    ap.add_argument("--retry", type=float, nargs="*", default=[0.5, 0.7, 0.3])
    ap.add_argument("--n-realizations", type=int, default=300, help="per case, 10 cases")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        stamps = fiducial_inputs(Path(tmp), 10, args.n_realizations)[0]
    adaptive_moments(stamps[:8])  # compile / load the cache
    reference = None
    for cap in args.caps:
        params = galsim.hsm.HSMParams(max_mom2_iter=cap)
        spent = []
        for _ in range(3):
            t0 = time.process_time()
            result = adaptive_moments(stamps, params=params)
            spent.append(time.process_time() - t0)
        reference = result if reference is None else reference
        it, ok = result.n_iter, result.status == 0
        long_share = 100 * it[it > 100].sum() / it.sum()
        capped = 100 * (result.status == TOO_MANY_ITERATIONS).mean()
        print(
            f"cap {cap}: {1e6 * min(spent) / len(stamps):.1f} us per stamp, "
            f"{1e6 * min(spent) / it.sum():.2f} us per iteration; iterations mean "
            f"{it.mean():.1f}, median {np.median(it):.0f}, {long_share:.0f} % in stamps of "
            f"> 100; failures {100 * (~ok).mean():.2f} % "
            f"({capped:.2f} % at the cap); status changed from "
            f"cap {args.caps[0]}: {int((result.status != reference.status).sum())} of "
            f"{len(stamps)}; successes' most iterations {it[ok].max()}"
        )
    plain = adaptive_moments(stamps)
    for step in args.retry:
        spent = []
        for _ in range(3):
            t0 = time.process_time()
            result = adaptive_moments(stamps, retry_step=step)
            spent.append(time.process_time() - t0)
        failed, before = result.status != 0, plain.status != 0
        kinds = ", ".join(
            f"{STATUS_NAMES[k]} {int((result.status == k).sum())}"
            for k in np.unique(result.status[failed])
        )
        print(
            f"retry {step}: {1e6 * min(spent) / len(stamps):.1f} us per stamp, iterations mean "
            f"{result.n_iter.mean():.1f}; failures {int(failed.sum())} of {len(stamps)} "
            f"({100 * failed.mean():.2f} %; {kinds}) against {int(before.sum())}: "
            f"{int((before & ~failed).sum())} settled by the retry"
        )


if __name__ == "__main__":
    main()
