"""Noiseless fiducial stamps: the batched renderer against GalSim's drawImage loop.

Galaxies of ``examples/fiducial/tp.toml`` (Sersic n gridded by 0.1 in [1, 4], half-light
radius U(2, 8) px, flux = sb pi hlr^2 with sb U(1, 15), |e| Rayleigh of mode 0.2 cut at
0.6, g U(-0.1, 0.1), offsets U(-0.5, 0.5) px), one independent galaxy per stamp, Gaussian
PSF of sigma 2 px, 64x64 stamps. Measured in ONE run, interleaved, order alternated every
repeat (the machine is shared):

* ``galsim``: ``galsim.Convolve(shaped(Sersic), psf).drawImage(ImageF(64, 64), offset=...)``
  per stamp, as ``megalut_cli/sim/draw.py`` does (GalSim's Sersic cache warm);
* ``render``: ``StampRenderer(64).draw(psf, key, "auto", ...)`` on all stamps at once
  (radial tables and PSF k-images warm, as in a long run).

Both CPU time (``time.process_time``) and wall clock are reported; the ratio uses CPU
time. Then a cProfile of one ``render`` call splits its time into the k-image fill (numba),
the inverse FFTs and the rest, and a table gives the FFT floor per grid size.

Run::

    python benchmarks/bench_render.py [--stamps 400 --repeats 3 --seed 1]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import collections  # noqa: E402
import cProfile  # noqa: E402
import math  # noqa: E402
import pstats  # noqa: E402
import time  # noqa: E402

import galsim  # noqa: E402
import numpy as np  # noqa: E402

from megalut_cli.sim.galaxies import base_profile, shaped  # noqa: E402
from megalut_cli.sim.render import BATCH_BYTES, StampRenderer, inverse_fft_window  # noqa: E402

STAMP = 64


def fiducial_galaxies(m: int, seed: int) -> dict:
    """Noiseless fiducial TP galaxies (independent per stamp)."""
    rng = np.random.default_rng(seed)
    rad = rng.uniform(2.0, 8.0, m)
    e = np.empty(m)
    filled = 0
    while filled < m:  # Rayleigh of mode 0.2, truncated to [0, 0.6]
        draw = rng.rayleigh(0.2, m)
        draw = draw[draw <= 0.6][: m - filled]
        e[filled : filled + len(draw)] = draw
        filled += len(draw)
    theta = rng.uniform(0.0, np.pi, m)
    return {
        "profile": "sersic",
        "rad": rad,
        "flux": rng.uniform(1.0, 15.0, m) * np.pi * rad**2,
        "sersicn": np.round(rng.integers(10, 41, m) * 0.1, 1),
        "e1": e * np.cos(2 * theta),
        "e2": e * np.sin(2 * theta),
        "g1": rng.uniform(-0.1, 0.1, m),
        "g2": rng.uniform(-0.1, 0.1, m),
        "dx": rng.uniform(-0.5, 0.5, m),
        "dy": rng.uniform(-0.5, 0.5, m),
    }


def galsim_loop(gals: dict, psf: galsim.GSObject) -> np.ndarray:
    """The stamps as draw.py draws them, one at a time."""
    m = len(gals["rad"])
    out = np.empty((m, STAMP, STAMP), dtype=np.float32)
    image = galsim.ImageF(STAMP, STAMP, scale=1.0)
    for k in range(m):
        gal = shaped(
            base_profile("sersic", gals["rad"][k], gals["flux"][k], gals["sersicn"][k]),
            gals["e1"][k],
            gals["e2"][k],
            gals["g1"][k],
            gals["g2"][k],
        )
        galsim.Convolve(gal, psf).drawImage(
            image=image, offset=(gals["dx"][k], gals["dy"][k]), method="auto"
        )
        out[k] = image.array
    return out


def timed(fn, *args):
    c0, w0 = time.process_time(), time.perf_counter()
    result = fn(*args)
    return result, time.process_time() - c0, time.perf_counter() - w0


def fft_floor(sizes: collections.Counter, stamp: int) -> None:
    """FLOPs and bytes per stamp of the pruned inverse FFT, and its measured time."""
    print("\nFFT floor per stamp (pruned inverse FFT: N/2+1 complex y-transforms of length N, then")
    print(
        f"{stamp} real x-transforms; 5 N log2 N flops per complex transform, "
        "2.5 N log2 N per real one;"
    )
    print(
        "bytes: complex64 k-image written by the fill, read and written by the y-FFT, "
        "S rows read by the x-FFT)"
    )
    print(f"{'N':>6} {'share':>6} {'Mflop':>8} {'MB':>7} {'ms measured':>12}")
    total_ms = 0.0
    total = sum(sizes.values())
    for n, count in sorted(sizes.items()):
        flops = (n // 2 + 1) * 5 * n * math.log2(n) + stamp * 2.5 * n * math.log2(n)
        nbytes = n * (n // 2 + 1) * 8 * 3 + stamp * (n // 2 + 1) * 8 + stamp * n * 8
        batch = max(1, min(64, BATCH_BYTES // (n * (n // 2 + 1) * 8)))  # as the renderer batches
        k0 = (np.random.default_rng(0).standard_normal((batch, n, n // 2 + 1)) + 0j).astype(
            np.complex64
        )
        inverse_fft_window(k0.copy(), n, stamp)
        reps, spent = 3, 0.0
        for _ in range(reps):
            k = k0.copy()  # the transform overwrites its input
            t0 = time.process_time()
            inverse_fft_window(k, n, stamp)
            spent += time.process_time() - t0
        ms = spent / reps / batch * 1e3
        total_ms += ms * count / total
        print(f"{n:>6} {count / total:>6.1%} {flops / 1e6:>8.2f} {nbytes / 1e6:>7.2f} {ms:>12.3f}")
    print(f"mean FFT time per stamp over this mix: {total_ms:.3f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stamps", type=int, default=400)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    galsim.set_omp_threads(1)
    psf = galsim.Gaussian(sigma=2.0)
    renderer = StampRenderer(STAMP)
    gals = fiducial_galaxies(args.stamps, args.seed)
    # Warm-up: numba compilation, radial tables, PSF k-images, GalSim's Sersic cache.
    warm = fiducial_galaxies(args.stamps, args.seed + 1000)
    renderer.draw(psf, "psf", "auto", **gals)
    renderer.draw(psf, "psf", "auto", **warm)
    galsim_loop({k: (v if k == "profile" else v[:40]) for k, v in warm.items()}, psf)
    for n in np.unique(gals["sersicn"]):
        base_profile("sersic", 1.0, 1.0, float(n)).maxk  # noqa: B018 (fills GalSim's cache)

    times = {"galsim": [], "render": []}
    for rep in range(args.repeats):
        order = ("galsim", "render") if rep % 2 == 0 else ("render", "galsim")
        for name in order:
            if name == "galsim":
                ref, cpu, wall = timed(galsim_loop, gals, psf)
            else:
                out, cpu, wall = timed(
                    renderer.draw,
                    psf,
                    "psf",
                    "auto",
                    "sersic",
                    gals["rad"],
                    gals["flux"],
                    gals["sersicn"],
                    gals["e1"],
                    gals["e2"],
                    gals["g1"],
                    gals["g2"],
                    gals["dx"],
                    gals["dy"],
                )
            times[name].append((cpu, wall))
    err = np.abs(out - ref).max(axis=(1, 2)) / ref.max(axis=(1, 2))
    m = args.stamps
    print(
        f"{m} noiseless fiducial stamps of {STAMP}x{STAMP}, {args.repeats} interleaved repeats; "
        f"max |render - galsim| / peak = {err.max():.2e}"
    )
    print(f"{'':8} {'cpu ms/stamp (min, median)':>28} {'wall ms/stamp (min)':>20}")
    for name, ts in times.items():
        cpus = sorted(c for c, _ in ts)
        print(
            f"{name:8} {cpus[0] / m * 1e3:>13.3f} {np.median(cpus) / m * 1e3:>13.3f} "
            f"{min(w for _, w in ts) / m * 1e3:>20.3f}"
        )
    ratio = [g[0] / r[0] for g, r in zip(times["galsim"], times["render"])]
    print(f"speed-up (galsim cpu / render cpu, per repeat): {', '.join(f'{x:.2f}' for x in ratio)}")

    n_fft, n_k = renderer.grid_sizes(
        psf,
        "psf",
        "auto",
        "sersic",
        gals["rad"],
        gals["sersicn"],
        gals["e1"],
        gals["e2"],
        gals["g1"],
        gals["g2"],
        gals["dx"],
        gals["dy"],
    )
    sizes = collections.Counter(int(n) for n in n_fft)
    print(
        f"grid sizes N (Nk = N for all: {bool((n_k == n_fft).all())}): "
        f"{dict(sorted(sizes.items()))}"
    )

    prof = cProfile.Profile(time.process_time)  # CPU time: the machine is shared
    prof.enable()
    renderer.draw(psf, "psf", "auto", **gals)
    prof.disable()
    stats = pstats.Stats(prof)
    total = stats.total_tt
    parts = collections.defaultdict(float)
    for (filename, _, func), (_, _, tottime, _, _) in stats.stats.items():
        if func == "fill_kimages":
            parts["k-image fill (numba)"] += tottime
        elif "numpy/fft" in filename:
            parts["inverse FFTs (numpy pocketfft)"] += tottime
    parts["overhead (geometry, grouping, copies)"] = total - sum(parts.values())
    print(f"\nCPU profile of one render call ({total / m * 1e3:.3f} ms/stamp under cProfile):")
    for name, t in parts.items():
        print(f"  {name:40} {t / m * 1e3:8.3f} ms/stamp  {t / total:6.1%}")
    fft_floor(sizes, STAMP)
    print(f"\nnumpy {np.__version__}, galsim {galsim.__version__}")


if __name__ == "__main__":
    main()
