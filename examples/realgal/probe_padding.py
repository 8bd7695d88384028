"""Noiseless probe of the real-galaxy drawing (issue 39): does a noise-padded real galaxy
respond to g1 as it does to g2, and as the same galaxy without padding?

For each galaxy of the catalog: rings of 4 orientations (45 degrees apart, a ring angle and
sub-pixel offsets per ring), each under the four shears (+-g, 0) and (0, +-g) with common
random numbers; no added noise, no symmetrization, no metacal. The adaptive-moment
ellipticity's response A_i = d<e_i>/dg_i is fitted from the CRN differences, and A1/A2 - 1
is printed per galaxy and drawing method, with the time per draw:

- ``unpadded``: the galaxy without noise padding (the reference: A1/A2 - 1 ~ 0);
- ``stamp``: padded as the simulator padded it before issue 39 (1.5 S + 4 px, GalSim's
  default ``pad_factor``), drawn straight into the S x S stamp (the FFT period follows the
  unpadded cutout);
- ``zeros``: padded as now (the interpolated image zero-padded to 4 times the noise
  padding), drawn straight into the stamp;
- ``big:N``: the old padded galaxy drawn into an N x N image and the centre S x S cut out;
- ``fixed``: the simulator's drawing now (``real_profile`` with its zero padding,
  ``draw_wide`` at ``wide_draw_size``).

Usage::

    python examples/realgal/probe_padding.py --stamp 64 --rings 10 --galaxies 0,5,19,37 \
        --methods unpadded,stamp,fixed -j 2
    python examples/realgal/probe_padding.py --stamp 64 --rings 6 --galaxies all -j 2

(The catalog and setup are those of ``fiducial.toml``: 0.06"/px, Gaussian PSF sigma = 2 px.)
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
import time
from pathlib import Path

import galsim
import numpy as np

from megalut_cli.sim.draw import draw_wide, wide_draw_size
from megalut_cli.sim.galaxies import (
    real_galaxy_catalog,
    real_padded_side,
    real_profile,
    rotated,
)

HERE = Path(__file__).resolve().parent
REAL = {
    "catalog": str(HERE.parent / "data/cosmos/real_galaxy_catalog_26_extension_example.fits"),
    "dir": str(HERE.parent / "data/cosmos"),
    "pixel_scale": 0.06,
}
SHEAR = 0.02
SHEARS = ((SHEAR, 0.0), (-SHEAR, 0.0), (0.0, SHEAR), (0.0, -SHEAR))


def ellipticity(image: galsim.Image) -> tuple[float, float]:
    """HSM adaptive-moment shape (g1, g2) of ``image``; NaN when it fails."""
    try:
        res = galsim.hsm.FindAdaptiveMom(image, strict=True)
    except galsim.GalSimHSMError:
        return np.nan, np.nan
    return res.observed_shape.g1, res.observed_shape.g2


def old_padded(index: int, stamp: int) -> galsim.GSObject:
    """Real galaxy ``index`` padded as the simulator padded it before issue 39."""
    rgc = real_galaxy_catalog(REAL["catalog"], REAL["dir"])
    gal = galsim.RealGalaxy(
        rgc,
        index=index,
        noise_pad_size=(1.5 * stamp + 4.0) * REAL["pixel_scale"],
        rng=galsim.BaseDeviate(271828 + index),
    )
    return gal.withFlux(1000.0).dilate(1.0 / REAL["pixel_scale"])


def draw(base, psf, theta, g1, g2, offset, stamp: int, method: str, padded: float):
    """One noiseless stamp of ``base`` by drawing ``method``."""
    obj = galsim.Convolve(rotated(base, theta, g1, g2), psf)
    if method in ("unpadded", "stamp", "zeros"):
        return obj.drawImage(nx=stamp, ny=stamp, scale=1.0, offset=offset)
    if method == "fixed":
        image = galsim.ImageF(stamp, stamp, scale=1.0)
        size = wide_draw_size(stamp, padded, float(np.hypot(g1, g2)), psf)
        return draw_wide(obj, image, offset, "auto", size)
    n = int(method.split(":")[1])
    big = obj.drawImage(nx=n, ny=n, scale=1.0, offset=offset)
    a = (n - stamp) // 2
    return galsim.Image(big.array[a : a + stamp, a : a + stamp].copy(), scale=1.0)


def probe(args: tuple[int, int, int, str, int]) -> tuple[int, str, float, ...]:
    """(index, method, A1, A2, sigma(A1), sigma(A2), seconds per draw) of one galaxy."""
    index, stamp, rings, method, seed = args
    pad = 0.0 if method == "unpadded" else 1.5 * stamp + 4.0
    if method in ("unpadded", "zeros", "fixed"):
        base = real_profile(REAL, index, 1000.0, pad_pixels=pad)
    else:
        base = old_padded(index, stamp)
    padded = real_padded_side(REAL, index, pad)
    psf = galsim.Gaussian(sigma=2.0)
    rng = np.random.default_rng([seed, index])
    d1, d2 = [], []
    t0 = time.perf_counter()
    for _ in range(rings):
        theta0 = rng.uniform(0.0, 45.0)
        for j in range(4):
            offset = tuple(rng.uniform(-0.5, 0.5, 2))
            e = [
                ellipticity(
                    draw(base, psf, theta0 + 45.0 * j, g1, g2, offset, stamp, method, padded)
                )
                for g1, g2 in SHEARS
            ]
            d1.append((e[0][0] - e[1][0]) / (2 * SHEAR))
            d2.append((e[2][1] - e[3][1]) / (2 * SHEAR))
    dt = (time.perf_counter() - t0) / (rings * 16)
    d1a, d2a = np.asarray(d1), np.asarray(d2)
    d1a, d2a = d1a[np.isfinite(d1a)], d2a[np.isfinite(d2a)]
    # rings are the independent units: errors from the scatter of the ring means
    r1 = np.nanmean(np.asarray(d1).reshape(rings, 4), axis=1)
    r2 = np.nanmean(np.asarray(d2).reshape(rings, 4), axis=1)
    s1 = float(np.nanstd(r1, ddof=1) / np.sqrt(rings)) if rings > 1 else np.nan
    s2 = float(np.nanstd(r2, ddof=1) / np.sqrt(rings)) if rings > 1 else np.nan
    return index, method, float(d1a.mean()), float(d2a.mean()), s1, s2, dt


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--stamp", type=int, default=64)
    p.add_argument("--rings", type=int, default=10)
    p.add_argument("--galaxies", default="0,5,19,37", help="comma list, or 'all'")
    p.add_argument("--methods", default="unpadded,stamp,fixed")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("-j", type=int, default=1)
    a = p.parse_args(argv)
    n_cat = galsim.RealGalaxyCatalog(REAL["catalog"], dir=REAL["dir"]).nobjects
    gals = range(n_cat) if a.galaxies == "all" else [int(g) for g in a.galaxies.split(",")]
    methods = a.methods.split(",")
    jobs = [(g, a.stamp, a.rings, m, a.seed) for g in gals for m in methods]
    with multiprocessing.Pool(a.j) as pool:
        results = pool.map(probe, jobs, chunksize=1)
    table: dict[int, dict[str, tuple]] = {}
    for r in results:
        table.setdefault(r[0], {})[r[1]] = r[2:]
    print(f"# stamp {a.stamp} px, {a.rings} rings x 4 orientations x 4 shears, seed {a.seed}")
    print("# A1/A2 - 1 in % (+- from the rings); ms per draw")
    print("galaxy " + " ".join(f"{m:>22}" for m in methods))
    ratios: dict[str, list[float]] = {m: [] for m in methods}
    times: dict[str, list[float]] = {m: [] for m in methods}
    for g in gals:
        cells = []
        for m in methods:
            a1, a2, s1, s2, dt = table[g][m]
            q = a1 / a2 - 1.0
            sq = abs(a1 / a2) * np.hypot(s1 / a1, s2 / a2)
            ratios[m].append(q)
            times[m].append(dt)
            cells.append(f"{100 * q:+7.2f} ± {100 * sq:4.2f} {1e3 * dt:6.1f}")
        print(f"{g:6d} " + " ".join(f"{c:>22}" for c in cells))
    print("summary: method, median |A1/A2 - 1| %, max |A1/A2 - 1| %, rms %, mean ms per draw")
    for m in methods:
        q = np.abs(np.asarray(ratios[m]))
        print(
            f"  {m:10s} {100 * np.median(q):6.2f} {100 * q.max():6.2f} "
            f"{100 * np.sqrt(np.mean(q**2)):6.2f} {1e3 * np.mean(times[m]):7.2f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
