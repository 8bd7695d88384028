"""The device backend against one CPU core, side by side in one run (benchmarks/gpu.md).

1. ``simulate --measure`` work: fiducial TP stamps (``examples/fiducial/tp.toml``, 64x64,
   Gaussian noise) drawn, noised and measured by ``draw_unit`` with ``device="cpu"`` (the
   fast engine: numba and numpy, one core) and ``device="gpu"`` (JAX; compiled first, on a
   warm-up unit). Stamps per second of each, and their ratio.
2. Training: one MSB cost + gradient evaluation of a 5-input, (5, 5)-hidden network on N
   rows, ``Objective`` (analytic gradient, numpy, one core) against ``DeviceObjective``
   (autodiff on the device). Rows per second of each, and their ratio.

On a GPU machine::

    pip install -e ".[gpu]" "jax[cuda12]"
    python benchmarks/bench_gpu.py --cases 40 --realizations 2000 --rows 10000000

Without one, ``--platform cpu`` runs the device path on JAX's CPU mode, limited to one
thread (``XLA_FLAGS``) for a one-core against one-core comparison: a check that the script
runs and a CPU-mode figure, not a GPU one.
"""

from __future__ import annotations

import os
import sys

for _v in (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "NUMBA_NUM_THREADS",
):
    os.environ[_v] = "1"

if "--platform" in sys.argv and sys.argv[sys.argv.index("--platform") + 1] == "cpu":
    os.environ["MEGALUT_GPU_PLATFORM"] = "cpu"
    os.environ["XLA_FLAGS"] = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from megalut_cli.sim.config import load_config  # noqa: E402
from megalut_cli.sim.draw import WorkUnit, draw_unit  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def time_unit(unit: WorkUnit, repeats: int) -> tuple[float, dict]:
    """Best wall time of ``repeats`` runs of ``draw_unit(unit)``, and its result."""
    best, res = np.inf, {}
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = draw_unit(unit)
        best = min(best, time.perf_counter() - t0)
    return best, res


def bench_simulate(cases: int, realizations: int, repeats: int) -> None:
    cfg = load_config(
        ROOT / "examples" / "fiducial" / "tp.toml", n_cases=cases + 1, n_realizations=realizations
    )
    nx = cfg.structure.grid_nx
    cpu_unit = WorkUnit(
        cfg, 1, 1, cases + 1, nx, keep_stamps=False, measure=True, engine="fast", device="cpu"
    )
    gpu_unit = dataclasses.replace(cpu_unit, device="gpu")
    draw_unit(dataclasses.replace(cpu_unit, case_start=0, case_stop=1))  # numba, GalSim tables
    t0 = time.perf_counter()
    draw_unit(
        dataclasses.replace(gpu_unit, case_start=0, case_stop=cases + 1)
    )  # compilation (same shapes)
    compile_s = time.perf_counter() - t0
    t_cpu, r_cpu = time_unit(cpu_unit, repeats)
    t_gpu, r_gpu = time_unit(gpu_unit, repeats)
    n = cases * realizations
    f_cpu, f_gpu = r_cpu["columns"]["flags"], r_gpu["columns"]["flags"]
    differ = np.flatnonzero(f_cpu != f_gpu)
    flag_diff = f"{len(differ)} of {len(f_cpu)} stamps" + (
        f" (bits {sorted(set(np.bitwise_xor(f_cpu[differ], f_gpu[differ]).tolist()))})"
        if len(differ)
        else ""
    )
    dg = np.nanmax(np.abs(r_cpu["columns"]["adamom_g1"] - r_gpu["columns"]["adamom_g1"]))
    print(
        f"simulate --measure, {n} fiducial stamps ({cases} cases x {realizations}), "
        f"best of {repeats}:"
    )
    print(f"  cpu (fast engine, 1 core): {t_cpu:8.3f} s  {n / t_cpu:12.0f} stamps/s")
    print(
        f"  device                   : {t_gpu:8.3f} s  {n / t_gpu:12.0f} stamps/s  "
        f"(x{t_cpu / t_gpu:.2f}; first call with compilation {compile_s:.1f} s)"
    )
    print(f"  flags differ on {flag_diff}; max |adamom_g1 difference| {dg:.2e}")


def bench_training(rows: int, repeats: int) -> None:
    from megalut_cli.gpu.train import DeviceObjective
    from megalut_cli.nn.data import CaseData
    from megalut_cli.nn.network import Network
    from megalut_cli.nn.train import Objective

    rng = np.random.default_rng(1)
    n_rea = 200
    nc = max(1, rows // n_rea)
    x = rng.normal(size=(nc, n_rea, 5))
    data = CaseData.from_padded(x, np.ones((nc, n_rea), bool), rng.uniform(-0.1, 0.1, nc))
    net = Network(5, (5, 5), "identity", 0.0, 0.05)
    params = net.init_normal(rng, 0.1)
    args = (net, "msb", data, 0, np.zeros(5), np.ones(5), 0.05)
    out = {}
    for name, cls in (("cpu (numpy, 1 core)", Objective), ("device", DeviceObjective)):
        obj = cls(*args)
        obj.value_and_grad(params)  # warm-up (compilation)
        best = np.inf
        for _ in range(repeats):
            t0 = time.perf_counter()
            c, g = obj.value_and_grad(params)
            best = min(best, time.perf_counter() - t0)
        out[name] = (best, c, g)
    n = nc * n_rea
    print(
        f"training: one MSB cost + gradient on {n} rows (5 inputs, hidden 5,5), best of {repeats}:"
    )
    (t_c, c_c, g_c), (t_d, c_d, g_d) = out.values()
    print(f"  cpu (numpy, 1 core): {t_c * 1e3:9.2f} ms  {n / t_c:14.0f} rows/s")
    print(f"  device             : {t_d * 1e3:9.2f} ms  {n / t_d:14.0f} rows/s  (x{t_c / t_d:.2f})")
    print(
        f"  relative differences: cost {abs(c_d - c_c) / abs(c_c):.1e}, "
        f"gradient {np.abs(g_d - g_c).max() / np.abs(g_c).max():.1e}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--cases", type=int, default=4)
    ap.add_argument("--realizations", type=int, default=256)
    ap.add_argument("--rows", type=int, default=200_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument(
        "--platform",
        choices=["gpu", "cpu"],
        default="gpu",
        help="JAX platform of the device path (cpu: JAX's CPU mode, one thread)",
    )
    a = ap.parse_args()
    from megalut_cli.gpu import device_problem, jax_device

    problem = device_problem()
    if problem:
        sys.exit(f"bench_gpu: {problem}")
    print(f"device: {jax_device()} (platform {a.platform})")
    bench_simulate(a.cases, a.realizations, a.repeats)
    bench_training(a.rows, a.repeats)


if __name__ == "__main__":
    main()
