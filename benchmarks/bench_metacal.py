"""Throughput of the metacal route: the ``measure --metacal`` commands on the stamps a user
measures, side by side with another tree, and the batched engine against GalSim's, per core.

The stamps are the fiducial population as ``megalut simulate`` draws it
(``examples/fiducial/vo.toml``, 64-px stamps; ``--n-cases`` x ``--n-realizations``, seed 5)
with a 64-px Gaussian PSF image of sigma 2 px, and a MEDS file of the same stamps, each
object with its own PSF image (48 px, Gaussian sigma 1.9-2.1 px, |g| < 0.03). Timed, one core
(BLAS and numba on one thread), CPU seconds (the machine may be busy; interleaved, repeated):

* ``measure``: ``megalut measure stamps.fits cat.fits -o f.fits --psf psf.fits --metacal -j 1``
  and ``megalut measure meds.fits -o m.fits --metacal -j 1``, each tree in its own
  subprocess (its own numba cache, warmed first), with ``--before DIR`` also that tree's,
  interleaved; the CPU of the command and its logged per-stamp line;
* in this process, on the first ``--n`` stamps: ``fast`` (``metacal_versions(...,
  engine="fast")`` with fixnoise), ``fast+measure`` (``metacal_features``: the same plus the
  features of the five versions), ``operation`` (``fft_versions_fixnoise`` on the stamps and
  their rotated fields), ``galsim`` (the reference on ``--ref-n`` stamps);

then where the operation's time goes (each stage of ``metacal_fft._run``), the floor
(matrix-product FLOPs at this machine's sgemm rate, interpolation FMAs, bytes) and the
first-call costs in fresh processes (numba cache cold and warm). Run::

    PYTHONPATH=. python benchmarks/bench_metacal.py [--n 1024] [--repeat 3] [--ref-n N] \
        [--n-cases 10 --n-realizations 300] [--before DIR]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import platform  # noqa: E402
import re  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402
from pathlib import Path  # noqa: E402

import galsim  # noqa: E402
import numba  # noqa: E402
import numpy as np  # noqa: E402

from megalut_cli.measure import metacal_fft as mf  # noqa: E402
from megalut_cli.measure import metacal_fft_nb as mf_nb  # noqa: E402
from megalut_cli.measure.features import measure_stamps  # noqa: E402
from megalut_cli.measure.metacal import (  # noqa: E402
    DEFAULT_STEP,
    fixnoise_seeds,
    metacal_features,
    metacal_versions,
    noise_field,
    target_psf_sigma,
)
from megalut_cli.measure.metacal_targets.gauss import GaussTarget  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
SIZE, PSF_SIGMA = 64, 2.0


def megalut(tree: Path, args: list[str], cwd: Path, cache: Path) -> tuple[float, str]:
    """Run ``python -m megalut_cli ARGS`` with ``tree``'s code, one thread: (CPU seconds of
    the command, its stderr)."""
    env = dict(os.environ, PYTHONPATH=str(tree), NUMBA_CACHE_DIR=str(cache))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run(
        [sys.executable, "-m", "megalut_cli", *args], cwd=cwd, env=env, capture_output=True,
        text=True, check=True,
    )  # fmt: skip
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return cpu, done.stderr


def fiducial_inputs(work: Path, n_cases: int, n_rea: int) -> tuple[np.ndarray, np.ndarray]:
    """``megalut simulate`` of the fiducial population (stamps.fits, cat.fits), psf.fits
    (Gaussian sigma 2 px, 64 px) and meds.fits (the stamps, each with its own PSF) in
    ``work``: ``(stamps (n, 64, 64) float64, psf image)``."""
    from astropy.io import fits

    from megalut_cli.measure.meds import write_meds

    subprocess.run(
        [
            sys.executable, "-m", "megalut_cli", "simulate",
            str(ROOT / "examples/fiducial/vo.toml"), "-o", "cat.fits", "--stamps",
            "stamps.fits", "--n-cases", str(n_cases), "--n-realizations", str(n_rea),
            "--seed", "5",
        ],
        cwd=work, env=dict(os.environ, PYTHONPATH=str(ROOT)), check=True, capture_output=True,
    )  # fmt: skip
    psf = galsim.Gaussian(sigma=PSF_SIGMA).drawImage(nx=SIZE, ny=SIZE, scale=1.0).array
    fits.writeto(work / "psf.fits", psf, overwrite=True)
    grid = fits.getdata(work / "stamps.fits").astype(np.float64)
    side = grid.shape[1] // SIZE
    stamps = grid.reshape(-1, SIZE, side, SIZE).transpose(0, 2, 1, 3).reshape(-1, SIZE, SIZE)
    stamps = stamps[: n_cases * n_rea]
    rng = np.random.default_rng(7)
    psfs = np.array(
        [
            galsim.Gaussian(sigma=rng.uniform(1.9, 2.1))
            .shear(g1=rng.uniform(-0.02, 0.02), g2=rng.uniform(-0.02, 0.02))
            .drawImage(nx=48, ny=48, scale=1.0)
            .array
            for _ in range(len(stamps))
        ]
    )
    write_meds(work / "meds.fits", stamps, weights=np.ones_like(stamps), psfs=psfs)
    return stamps, psf.astype(np.float64)


def logged_ms(stderr: str) -> float:
    """The per-stamp milliseconds of the command's ``measured N stamps in T s`` line."""
    m = re.search(r"measured (\d+) (?:stamps|objects) in ([\d.]+) s", stderr)
    return float(m.group(2)) / int(m.group(1)) * 1e3 if m else float("nan")


def command_times(work: Path, trees: dict[str, Path], n: int, repeat: int) -> None:
    """The two ``measure --metacal`` commands, each tree interleaved, best and median CPU."""
    commands = {
        "grid, one PSF": ["measure", "stamps.fits", "cat.fits", "-o", "f.fits", "--psf",
                          "psf.fits", "--metacal", "-j", "1", "--overwrite"],
        "MEDS, per-object PSFs": ["measure", "meds.fits", "-o", "m.fits", "--metacal", "-j",
                                  "1", "--overwrite"],
    }  # fmt: skip
    caches = {label: work / f"numba-{label}" for label in trees}
    for label, tree in trees.items():  # compile or load each tree's kernels once
        megalut(tree, commands["grid, one PSF"], work, caches[label])
        megalut(tree, commands["MEDS, per-object PSFs"], work, caches[label])
    print(f"\nmeasure --metacal, {n} stamps, CPU ms per stamp (best / median of {repeat}; "
          "the command's logged ms per stamp, wall, best):")  # fmt: skip
    for name, cmd in commands.items():
        cpu: dict[str, list[float]] = {label: [] for label in trees}
        logged: dict[str, list[float]] = {label: [] for label in trees}
        for _ in range(repeat):
            for label, tree in trees.items():
                t, err = megalut(tree, cmd, work, caches[label])
                cpu[label].append(t / n * 1e3)
                logged[label].append(logged_ms(err))
        for label in trees:
            print(
                f"  {name:22s} {label:6s} {min(cpu[label]):6.2f} / {np.median(cpu[label]):6.2f}"
                f"   (logged {min(logged[label]):.2f})"
            )
        if len(trees) == 2:
            ratios = np.array(cpu["before"]) / np.array(cpu["after"])
            print(
                f"  {name:22s} before / after: median of per-repeat ratios {np.median(ratios):.2f}x"
            )


def cpu_time(func) -> float:
    t0 = time.process_time()
    func()
    return time.process_time() - t0


def stage_times(plan: mf.Plan, images: np.ndarray) -> dict[str, float]:
    """CPU seconds of each stage of ``metacal_fft._run`` (mirrored here, stage by stage) over
    ``images`` in blocks of ``metacal_fft.BLOCK``."""
    acc: dict[str, float] = defaultdict(float)
    m = mf.BLOCK
    ws = mf.Workspace(plan, m)
    size, h = plan.size, plan.size // 2 + 1
    ky1, kx1 = plan.ky + 1, plan.kx + 1
    out = np.empty((len(mf.TYPES), m, size, size))
    clock = time.process_time
    for b in range(0, len(images) - m + 1, m):
        t = clock()

        def lap(name: str) -> None:
            nonlocal t
            t1 = clock()
            acc[name] += t1 - t
            t = t1

        mf_nb.fold_x(images[b : b + m], ws.ex, ws.dx)
        lap("fold x (stamps, f64 -> f32)")
        np.matmul(ws.ex.reshape(m * size, h), plan.in_xc, out=ws.gc)
        np.matmul(ws.dx.reshape(m * size, h), plan.in_xs, out=ws.gs)
        lap("GEMM in, x")
        mf_nb.fold_y(ws.gc, ws.gs, size, ws.ey, ws.dy)
        lap("fold y")
        np.matmul(plan.in_yc, ws.ey.reshape(h, -1), out=ws.top.reshape(plan.ry + 1, -1))
        np.matmul(plan.in_ys, ws.dy.reshape(h, -1), out=ws.bottom.reshape(plan.ry + 1, -1))
        lap("GEMM in, y")
        mf_nb.padded_dft(ws.top, ws.bottom, ws.f)
        lap("assemble padded DFT")
        a2, b2 = ws.a.reshape(h * m, -1), ws.b.reshape(h * m, -1)
        for v, ver in enumerate(plan.versions):
            if ver.sep:
                mf_nb.slots_sep(ws.f, ver.p0, ver.wx, ver.r0, ver.wy, ver.wr, ver.wi, ws.q, ws.work)
            else:
                mf_nb.slots_full(ws.f, ver.p0, ver.wx, ver.r0, ver.wy, None, ver.wr, ver.wi, ws.q)
            lap(f"Quintic taps x weights, {mf.TYPES[v]}")
            np.matmul(plan.out_yc, ws.q[:ky1].reshape(ky1, -1), out=ws.a.reshape(h, -1))
            np.matmul(plan.out_ys, ws.q[ky1:].reshape(ky1, -1), out=ws.b.reshape(h, -1))
            lap("GEMM out, y (5 versions)")
            for k, (src, mat) in enumerate(
                ((a2, plan.out_xc), (b2, plan.out_xc), (a2, plan.out_xs), (b2, plan.out_xs))
            ):
                cols = slice(None, kx1) if k < 2 else slice(kx1, None)
                np.matmul(src[:, cols], mat, out=ws.u[k].reshape(h * m, h))
            lap("GEMM out, x (5 versions)")
            mf_nb.unfold(ws.u[0], ws.u[1], ws.u[2], ws.u[3], out[v])
            lap("unfold (f32 -> f64 stamps)")
    return acc


def gemm_rate(dtype: str, repeat: int) -> float:
    """This machine's sgemm / dgemm rate (FLOP/s) on products of the engine's shapes."""
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(84, 33)).astype(dtype), rng.normal(size=(33, 16 * 162)).astype(dtype)
    c, d = rng.normal(size=(33 * 16, 38)).astype(dtype), rng.normal(size=(38, 33)).astype(dtype)
    ab, cd = a @ b, c @ d

    def products() -> None:
        for _ in range(200):
            np.matmul(a, b, out=ab)
            np.matmul(c, d, out=cd)

    best = min(cpu_time(products) for _ in range(repeat))
    return (
        200
        * 2
        * (a.shape[0] * a.shape[1] * b.shape[1] + c.shape[0] * c.shape[1] * d.shape[1])
        / best
    )


def floor(plan: mf.Plan, rate: float) -> None:
    """FLOPs of the matrix products and of the Quintic taps per stamp, bytes per stamp."""
    size, h, n = plan.size, plan.size // 2 + 1, plan.np_
    ky1, kx1 = plan.ky + 1, plan.kx + 1
    macs = {
        "GEMM in, x": 2 * size * h * n,
        "GEMM in, y": 2 * (plan.ry + 1) * h * 2 * n,
        "GEMM out, y": 5 * 2 * h * ky1 * 2 * kx1,
        "GEMM out, x": 5 * 4 * h * kx1 * h,
    }
    taps = 0
    for ver in plan.versions:
        pts = int(np.count_nonzero((ver.wr != 0) | (ver.wi != 0)))
        if ver.sep:
            rows = int(ver.r0.max() + ver.wy.shape[1] - ver.r0.min())
            taps += (
                rows * kx1 * ver.wx.shape[1] if ver.wx.shape[1] > 1 else 0
            ) + pts * ver.wy.shape[1]
        else:
            taps += pts * 36
    total = sum(macs.values())
    print(
        f"\nfloor per stamp (plan: padded DFT {2 * plan.ry + 1} x {n} nodes, "
        f"k box {2 * plan.ky + 1} x {kx1}):"
    )
    for name, v in macs.items():
        print(f"  {name:14s} {v / 1e6:6.2f} M multiply-adds")
    print(
        f"  matrix products: {total / 1e6:.2f} M multiply-adds = {2 * total / 1e6:.1f} MFLOP, "
        f"at this machine's sgemm rate on these shapes ({rate / 1e9:.0f} GFLOP/s): "
        f"{2 * total / rate * 1e6:.0f} us"
    )
    print(
        f"  Quintic taps: {taps / 1e3:.0f} k complex taps = {2 * taps / 1e3:.0f} k real FMAs"
        f" (AVX2, 8 float32 lanes, 2 FMA/cycle: {2 * taps / 16 / 2.0e3:.0f} us at 2 GHz)"
    )
    ws = mf.Workspace(plan, mf.BLOCK)
    work = sum(a.nbytes for a in vars(ws).values() if isinstance(a, np.ndarray)) / mf.BLOCK
    print(
        f"  bytes: work arrays {work / 1e3:.0f} kB per stamp (in cache, blocks of {mf.BLOCK}); "
        f"input {size * size * 8 / 1e3:.0f} kB + output {5 * size * size * 8 / 1e3:.0f} kB "
        "float64 per stamp"
    )


FIRST_CALL = """
import resource, time
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime
c0 = cpu()
import numpy as np
from megalut_cli.measure.metacal import metacal_versions
import galsim
psf = galsim.Gaussian(sigma=2.0).drawImage(nx=64, ny=64, scale=1.0).array
c1 = cpu()
metacal_versions(
    np.random.default_rng(0).normal(size=(2, 64, 64)), psf, noise_sigma=[1, 1], engine="fast"
)
c2 = cpu()
metacal_versions(
    np.random.default_rng(1).normal(size=(2, 64, 64)), psf, noise_sigma=[1, 1], engine="fast"
)
print(c1 - c0, c2 - c1, cpu() - c2)
"""


def first_call_costs(repeat: int) -> None:
    """CPU seconds to import, then of the first call and of a second call, fresh processes."""
    print(
        "\nfresh process, CPU seconds (import / first call (compile or load, "
        "PSF plan) / second call):"
    )
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
                print(f"  {label}: {float(out[0]):.2f} / {float(out[1]):.2f} / {float(out[2]):.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1024, help="stamps timed in this process")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument(
        "--ref-n", type=int, default=None, help="stamps for the GalSim reference (default all)"
    )
    ap.add_argument("--n-cases", type=int, default=10, help="megalut simulate --n-cases")
    ap.add_argument("--n-realizations", type=int, default=300, help="--n-realizations")
    ap.add_argument(
        "--before", type=Path, default=None, help="another source tree, timed side by side"
    )
    ap.add_argument("--no-commands", action="store_true", help="skip the commands' timings")
    ap.add_argument("--first-call-only", action="store_true", help="only the compile/cache costs")
    args = ap.parse_args()
    if args.first_call_only:
        first_call_costs(args.repeat)
        return

    t0 = time.perf_counter()
    work = Path(tempfile.mkdtemp(prefix="bench-metacal-"))
    stamps, psf = fiducial_inputs(work, args.n_cases, args.n_realizations)
    print(
        f"{platform.machine()} {platform.python_version()}, numpy {np.__version__}, "
        f"numba {numba.__version__}, galsim {galsim.__version__}; {len(stamps)} fiducial "
        f"stamps of {SIZE} px (simulated in {time.perf_counter() - t0:.0f} s, in {work})"
    )
    if not args.no_commands:
        trees = {"after": ROOT} | ({"before": args.before.resolve()} if args.before else {})
        command_times(work, trees, len(stamps), args.repeat)

    stamps = stamps[: args.n]
    n, ref_n = len(stamps), min(args.ref_n or args.n, len(stamps))
    origins = np.ones((n, 2))
    noise = measure_stamps(stamps, origins)["skymad"]  # the command's fixnoise level
    seeds = fixnoise_seeds(5, np.arange(n))
    sigma = target_psf_sigma(psf, DEFAULT_STEP)
    fields = np.array(
        [np.rot90(noise_field(noise[i], seeds[i], (SIZE, SIZE)), 1) for i in range(n)]
    )
    stack = np.concatenate([stamps, fields])
    buf = np.empty((5, n, SIZE, SIZE))
    c0 = time.process_time()
    metacal_features(stamps[:4], psf, noise_sigma=noise[:4], metacal_engine="fast")
    print(
        f"\nfirst call (numba cache load or compile, PSF plan): {time.process_time() - c0:.2f} s "
        "CPU"
    )
    kw = {"noise_sigma": noise, "seeds": seeds}
    runs = {
        "fast": lambda: metacal_versions(stamps, psf, engine="fast", **kw),
        "fast+measure": lambda: metacal_features(
            stamps, psf, metacal_engine="fast", origins=origins, engine="fast", **kw
        ),
        "operation": lambda: mf.fft_versions_fixnoise(
            stack, n, np.arange(n), psf, DEFAULT_STEP, sigma, out=buf
        ),
        "galsim": lambda: metacal_versions(
            stamps[:ref_n], psf, noise_sigma=noise[:ref_n], seeds=seeds[:ref_n], engine="galsim"
        ),
    }
    per = {"fast": n, "fast+measure": n, "operation": n, "galsim": ref_n}  # per input stamp
    times: dict[str, list[float]] = {k: [] for k in runs}
    for _ in range(args.repeat):
        for name, func in runs.items():  # interleaved
            times[name].append(cpu_time(func) / per[name])
    print(
        f"\nCPU per input stamp (best / median of {args.repeat}, interleaved; operation: the "
        "stamp and its field):"
    )
    for name, ts in times.items():
        print(f"  {name:13s} {min(ts) * 1e6:9.1f} us  {np.median(ts) * 1e6:9.1f} us")
    ratios = np.array(times["galsim"]) / np.array(times["fast"])
    print(
        f"  speed-up fast vs galsim: best-of {min(times['galsim']) / min(times['fast']):.0f}x, "
        f"median of per-repeat ratios {np.median(ratios):.0f}x"
    )

    # Where fft_versions's time goes, on the same stack of 2n images.
    target = GaussTarget(float(sigma))
    plan = mf._plan(psf.tobytes(), SIZE, SIZE, 128, float(DEFAULT_STEP), target, "float32")
    stages = None
    for _ in range(args.repeat):
        st = stage_times(plan, stack)
        if stages is None or sum(st.values()) < sum(stages.values()):
            stages = st
    assert stages is not None
    total = sum(stages.values())
    print(f"\nfft_versions stages, best of {args.repeat}, CPU per image (stamp or field):")
    for name, t in stages.items():
        print(f"  {name:38s} {t / len(stack) * 1e6:6.1f} us  {t / total:5.1%}")
    print(f"  {'sum':38s} {total / len(stack) * 1e6:6.1f} us")
    fast, lin, meas = min(times["fast"]), min(times["operation"]), min(times["fast+measure"])
    print(
        "  the operation's call (grid sizes, blocks, the fields' rotated adds): "
        f"{lin / 2 * 1e6:.1f} us per image"
    )
    print(
        "  metacal.py around it (noise fields, the stack, output pages): "
        f"{(fast - lin) * 1e6:.1f} us per stamp"
    )
    print(f"  measure_stamps of the five versions: {(meas - fast) * 1e6:.1f} us per stamp")
    floor(plan, gemm_rate("float32", args.repeat))
    first_call_costs(2)


if __name__ == "__main__":
    main()
