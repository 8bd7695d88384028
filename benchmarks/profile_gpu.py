"""Where a device work unit's time goes, and how it moves with the batch sizes (benchmarks/gpu.md).

One ``simulate --measure`` work unit of fiducial TP stamps (``examples/fiducial/tp.toml``)
drawn by the device backend, with each stage timed to its end on the device
(``jax.block_until_ready``): rendering, placing the stamps, noise, the adaptive moments'
first steps and slow-stamp tails, the rest of the measurement, and the host (all else: cases,
plans, PSF k-images, features). Each ``--batch``/``--noise`` pair runs once to compile, then
``--repeats`` times; the flags and features are compared with the first pair's::

    python benchmarks/profile_gpu.py --cases 40 --realizations 2000 \\
        --batch 4096 16384 32768 --noise 32768 131072

``--platform cpu`` runs it on JAX's CPU mode (a check that the script runs).
"""

from __future__ import annotations

import os
import sys

if "--platform" in sys.argv and sys.argv[sys.argv.index("--platform") + 1] == "cpu":
    os.environ["MEGALUT_GPU_PLATFORM"] = "cpu"

import argparse  # noqa: E402
import collections  # noqa: E402
import itertools  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402
import numpy as np  # noqa: E402

from megalut_cli.gpu import adamom, jax_device  # noqa: E402
from megalut_cli.gpu import draw as gdraw  # noqa: E402
from megalut_cli.gpu import measure as gmeasure  # noqa: E402
from megalut_cli.gpu import render as grender  # noqa: E402
from megalut_cli.sim.config import load_config  # noqa: E402
from megalut_cli.sim.draw import WorkUnit, draw_unit  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SECONDS: collections.Counter = collections.Counter()
CALLS: collections.Counter = collections.Counter()


def timed(stage, fn):
    """``fn`` with its time to completion on the device added to ``SECONDS[stage]``
    (``stage``: a name, or a function of ``fn``'s arguments giving it)."""

    def wrapper(*args, **kwargs):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args, **kwargs))
        label = stage(*args) if callable(stage) else stage
        SECONDS[label] += time.perf_counter() - t0
        CALLS[label] += 1
        return out

    return wrapper


def moments_stage(*args) -> str:
    """The first steps every stamp takes (``max_steps``, the sixth argument, is
    ``FIRST_STEPS``), or the tail of the slow stamps."""
    first = args[5] == adamom.FIRST_STEPS
    return "moments: first steps" if first else "moments: slow stamps"


def instrument() -> None:
    """Wrap the stages where the device backend looks them up."""
    grender.render_batch = timed("render", grender.render_batch)
    gdraw.place_rows = timed("place", gdraw.place_rows)
    gdraw.add_gaussian_noise = timed("noise", gdraw.add_gaussian_noise)
    gdraw.measure_on_device = timed("measure", gdraw.measure_on_device)
    adamom.iterate_moments = timed(moments_stage, adamom.iterate_moments)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--cases", type=int, default=4)
    ap.add_argument("--realizations", type=int, default=256)
    ap.add_argument("--batch", type=int, nargs="+", default=[gmeasure.BATCH_STAMPS])
    ap.add_argument("--noise", type=int, nargs="+", default=[gdraw.NOISE_STAMPS])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--platform", choices=["gpu", "cpu"], default="gpu")
    a = ap.parse_args()
    print(f"device: {jax_device()}")
    cfg = load_config(
        ROOT / "examples" / "fiducial" / "tp.toml",
        n_cases=a.cases + 1,
        n_realizations=a.realizations,
    )
    unit = WorkUnit(
        cfg,
        1,
        1,
        a.cases + 1,
        cfg.structure.grid_nx,
        keep_stamps=False,
        measure=True,
        device="gpu",
    )
    n = a.cases * a.realizations
    instrument()
    reference = None
    for batch, noise in itertools.product(a.batch, a.noise):
        gmeasure.BATCH_STAMPS, gdraw.NOISE_STAMPS = batch, noise
        t0 = time.perf_counter()
        draw_unit(unit)  # compilation of this pair's shapes
        compile_s = time.perf_counter() - t0
        best, parts = np.inf, {}
        for _ in range(a.repeats):
            SECONDS.clear()
            CALLS.clear()
            t0 = time.perf_counter()
            res = draw_unit(unit)["columns"]
            total = time.perf_counter() - t0
            if total < best:
                best, parts, calls = total, dict(SECONDS), dict(CALLS)
        moments = sum(v for k, v in parts.items() if k.startswith("moments"))
        parts["measure: rest"] = parts.pop("measure", 0.0) - moments
        calls["measure: rest"] = calls.pop("measure", 0)
        parts["host"] = best - sum(parts.values())
        print(
            f"batch {batch}, noise {noise}: {n} stamps in {best:.3f} s, {n / best:.0f} stamps/s "
            f"(first call {compile_s:.1f} s)"
        )
        for name, s in sorted(parts.items(), key=lambda kv: -kv[1]):
            print(
                f"  {name:22s} {s:8.3f} s  {100 * s / best:5.1f} %  ({calls.get(name, '')} calls)"
            )
        if reference is None:
            reference = res
            continue
        differ = int(np.sum(res["flags"] != reference["flags"]))
        ok = np.isfinite(res["adamom_g1"]) & np.isfinite(reference["adamom_g1"])
        dg = np.max(np.abs(res["adamom_g1"][ok] - reference["adamom_g1"][ok]), initial=0.0)
        print(f"  against the first pair: flags differ on {differ}, max |adamom_g1| {dg:.1e}")


if __name__ == "__main__":
    main()
