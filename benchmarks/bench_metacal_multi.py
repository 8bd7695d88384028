"""Time per object of ``metacal_versions(..., engine="fast")`` (fixnoise on, one core) on
stacks where every object has its own PSF image: the per-PSF path (one plan per PSF, as
before benchmarks/metacal.md's "One PSF per object") against the batched pass
(measure/metacal_fft_multi.py), interleaved, best of ``--repeat``; caches cleared before
each timing (the batched pass's PSF-independent geometry is kept warm: once per process).

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 NUMBA_NUM_THREADS=1 \\
        PYTHONPATH=. python benchmarks/bench_metacal_multi.py --n 64 --repeat 3
"""

from __future__ import annotations

import argparse
import time

import galsim
import numpy as np

from megalut_cli.measure import metacal_fft as mf
from megalut_cli.measure import metacal_fft_multi as mm
from megalut_cli.measure.metacal import metacal_versions


def make_stack(n: int, size: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exponential galaxies through Moffat PSFs (FWHM 2.5-4 px, |g| < 0.05, with the pixel),
    one PSF per stamp, noise 1e-3: ``(stamps, psfs, noise sigmas)``."""
    rng = np.random.default_rng(seed)
    stamps, psfs = np.empty((n, size, size)), np.empty((n, size, size))
    for k in range(n):
        psf = galsim.Moffat(beta=3.0, fwhm=rng.uniform(2.5, 4.0)).shear(
            g1=rng.uniform(-0.05, 0.05), g2=rng.uniform(-0.05, 0.05)
        )
        psf = galsim.Convolve(psf, galsim.Pixel(1.0))
        psfs[k] = psf.drawImage(nx=size, ny=size, scale=1.0, method="no_pixel").array
        gal = galsim.Exponential(half_light_radius=rng.uniform(1.0, 3.0)).shear(
            g1=rng.uniform(-0.3, 0.3), g2=rng.uniform(-0.3, 0.3)
        )
        img = (
            galsim.Convolve(gal, psf)
            .drawImage(nx=size, ny=size, scale=1.0, method="no_pixel")
            .array
        )
        stamps[k] = img + rng.normal(0.0, 1e-3, img.shape)
    return stamps, psfs, np.full(n, 1e-3)


def per_psf(stamps: np.ndarray, psfs: np.ndarray, sigma: np.ndarray) -> None:
    """The per-PSF path: metacal_versions one PSF at a time (what it did before)."""
    for j in range(len(stamps)):
        metacal_versions(
            stamps[j : j + 1], psfs[j], noise_sigma=sigma[j : j + 1], seeds=[j], engine="fast"
        )


def batched(stamps: np.ndarray, psfs: np.ndarray, sigma: np.ndarray) -> None:
    """The batched pass: metacal_versions with one PSF per stamp."""
    metacal_versions(stamps, psfs, noise_sigma=sigma, engine="fast")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    for size in (48, 64):
        stamps, psfs, sigma = make_stack(args.n, size, seed=size)
        for f in (per_psf, batched):  # numba, the geometry
            f(stamps[:2], psfs[:2], sigma[:2])
        best = {}
        for _ in range(args.repeat):
            for f in (per_psf, batched):
                mf._plan.cache_clear()
                mf.psf_params.cache_clear()
                mm._trig.cache_clear()
                t = time.process_time()
                f(stamps, psfs, sigma)
                best[f.__name__] = min(
                    best.get(f.__name__, np.inf), (time.process_time() - t) / args.n * 1e3
                )
        line = "  ".join(f"{k} {v:.2f} ms" for k, v in best.items())
        print(
            f"{size} px, {args.n} objects each with its own PSF, fixnoise: {line} per object "
            f"(speed-up {best['per_psf'] / best['batched']:.1f}x)"
        )


if __name__ == "__main__":
    main()
