"""Plain GalSim loops, the reference of the speed benchmarks; also runnable as a whole process.

Only GalSim and numpy are imported, so that a loop timed as a process pays GalSim's start-up
and nothing of megalut's::

    python benchmarks/galsim_loops.py simulate N SEED   # draw + noise + HSM, fiducial stamps
    python benchmarks/galsim_loops.py measure GRID.fits  # FindAdaptiveMom on every stamp
"""

from __future__ import annotations

import math
import sys

import galsim
import numpy as np

#: The plain loop's parameter distributions: those of examples/fiducial/tp.toml (Table 1).
STAMP_SIZE = 64
PSF_SIGMA = 2.0
NOISE_SIGMA = 1.0
SERSIC_N = np.round(np.arange(1.0, 4.0 + 1e-9, 0.1), 1)  # grid, step 0.1 (GalSim's cache)
RAD = (2.0, 8.0)  # half-light radius, pixels, uniform
SB = (1.0, 15.0)  # surface brightness, flux = sb * pi * rad^2, uniform
ELL_MODE, ELL_MAX = 0.2, 0.6  # Rayleigh of mode 0.2 truncated to [0, 0.6]
SHEAR_MAX = 0.1  # g1, g2 uniform in [-0.1, 0.1]
OFFSET = 0.5  # sub-pixel offset uniform in [-0.5, 0.5] px


def truncated_rayleigh(rng: np.random.Generator, n: int, mode: float, hi: float) -> np.ndarray:
    """Rayleigh of ``mode`` truncated to [0, hi] (inverse CDF)."""
    q_hi = math.exp(-(hi**2) / (2 * mode**2))
    q = 1.0 - rng.random(n) * (1.0 - q_hi)
    return np.sqrt(-2 * mode**2 * np.log(q))


def plain_loop(n: int, seed: int) -> np.ndarray:
    """Draw, noise and measure ``n`` fiducial stamps with plain GalSim calls; adamom sigmas."""
    rng = np.random.default_rng(seed)
    sersicn = rng.choice(SERSIC_N, n)
    rad = rng.uniform(*RAD, n)
    flux = rng.uniform(*SB, n) * np.pi * rad**2
    ell = truncated_rayleigh(rng, n, ELL_MODE, ELL_MAX)
    theta = rng.uniform(0.0, np.pi, n)
    e1, e2 = ell * np.cos(2 * theta), ell * np.sin(2 * theta)
    g1, g2 = rng.uniform(-SHEAR_MAX, SHEAR_MAX, (2, n))
    dx, dy = rng.uniform(-OFFSET, OFFSET, (2, n))
    noise_seeds = rng.integers(1, 2**31 - 1, n)
    psf = galsim.Gaussian(sigma=PSF_SIGMA)
    sigma = np.full(n, np.nan)
    for i in range(n):
        gal = galsim.Sersic(n=sersicn[i], half_light_radius=rad[i], flux=flux[i])
        gal = gal.shear(g1=e1[i], g2=e2[i]).shear(g1=g1[i], g2=g2[i])
        image = galsim.Convolve(gal, psf).drawImage(
            nx=STAMP_SIZE, ny=STAMP_SIZE, scale=1.0, offset=(dx[i], dy[i])
        )
        noise = galsim.GaussianNoise(galsim.BaseDeviate(int(noise_seeds[i])), sigma=NOISE_SIGMA)
        image.addNoise(noise)
        res = galsim.hsm.FindAdaptiveMom(image, strict=False)
        if res.moments_status == 0:
            sigma[i] = res.moments_sigma
    return sigma


def measure_loop(stamps: np.ndarray) -> None:
    """``FindAdaptiveMom`` on every stamp of ``stamps`` (n, S, S)."""
    for stamp in stamps:
        galsim.hsm.FindAdaptiveMom(galsim.ImageD(stamp), guess_sig=5.0, strict=False)


def read_grid_stamps(path: str) -> np.ndarray:
    """Every stamp of a ``megalut simulate --stamps`` grid image (``STAMPSZ``, ``NSTAMPS``
    cards), read with GalSim's FITS reader and cut with numpy."""
    image = galsim.fits.read(path)
    header = galsim.fits.FitsHeader(path)
    size = int(header["STAMPSZ"])
    arr = image.array
    n_y, n_x = arr.shape[0] // size, arr.shape[1] // size
    stamps = (
        arr[: n_y * size, : n_x * size]
        .reshape(n_y, size, n_x, size)
        .swapaxes(1, 2)
        .reshape(-1, size, size)
    )
    return stamps[: int(header.get("NSTAMPS", n_y * n_x))]


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "simulate":
        plain_loop(int(sys.argv[2]), int(sys.argv[3]))
    elif len(sys.argv) == 3 and sys.argv[1] == "measure":
        measure_loop(read_grid_stamps(sys.argv[2]))
    else:
        sys.exit(__doc__)
