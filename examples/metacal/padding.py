"""GalSim's padding of the metacal operation against the response (docs/metacal.md).

The reference operation (``measure/metacal.py``) interpolates each stamp's transform at the
sheared frequencies from the stamp padded 4 times; this runs it with 4- and 16-fold padding
on the same stamps (no fixnoise; GalSim's adaptive moments at the stamp's centre) and prints
the mean responses R11, R22 and their paired difference.

    megalut simulate examples/fiducial/vo.toml -o cat.fits --stamps stamps.fits \\
        --n-cases 20 --n-realizations 40 --seed 5
    python examples/metacal/padding.py stamps.fits --n 600
"""

from __future__ import annotations

import argparse

import fitsio
import galsim
import numpy as np

from megalut_cli.measure.metacal_defaults import INTERPOLANT, SHEARS
from megalut_cli.measure.metacal_targets import metacal_target


def responses(
    stamp: np.ndarray, psf: galsim.GSObject, target: galsim.GSObject, pad: float, step: float
) -> tuple[float, float]:
    """R11, R22 of one stamp by GalSim's operation with ``pad``-fold padding."""
    size = stamp.shape[0]
    obj = galsim.InterpolatedImage(
        galsim.ImageD(stamp, scale=1.0), x_interpolant=INTERPOLANT, pad_factor=pad
    )
    deconvolved = galsim.Convolve(obj, galsim.Deconvolve(psf))
    g = {}
    for kind in ("1p", "1m", "2p", "2m"):
        s1, s2 = SHEARS[kind]
        image = galsim.Convolve(deconvolved.shear(g1=s1 * step, g2=s2 * step), target)
        drawn = image.drawImage(nx=size, ny=size, scale=1.0, method="no_pixel")
        res = galsim.hsm.FindAdaptiveMom(drawn, strict=False)
        ok = res.error_message == ""
        g[kind] = (res.observed_shape.g1, res.observed_shape.g2) if ok else (np.nan, np.nan)
    return (g["1p"][0] - g["1m"][0]) / (2 * step), (g["2p"][1] - g["2m"][1]) / (2 * step)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stamps", help="a grid of stamps (megalut simulate --stamps)")
    ap.add_argument("--n", type=int, default=600, help="stamps used")
    ap.add_argument("--size", type=int, default=64, help="stamp side (pixels)")
    ap.add_argument("--psf-sigma", type=float, default=2.0, help="the Gaussian PSF's sigma")
    ap.add_argument("--step", type=float, default=0.01)
    args = ap.parse_args()
    grid, s = fitsio.read(args.stamps), args.size
    stamps = [
        grid[j * s : (j + 1) * s, i * s : (i + 1) * s].astype(np.float64)
        for j in range(grid.shape[0] // s)
        for i in range(grid.shape[1] // s)
    ][: args.n]
    pixelized = galsim.Convolve(galsim.Gaussian(sigma=args.psf_sigma), galsim.Pixel(1.0))
    psf_image = pixelized.drawImage(nx=33, ny=33, scale=1.0, method="no_pixel").array
    psf = galsim.InterpolatedImage(
        galsim.ImageD(psf_image / psf_image.sum(), scale=1.0), x_interpolant=INTERPOLANT
    )
    target = galsim.Gaussian(sigma=metacal_target("gauss", psf_image, args.step).sigma)
    r = {
        pad: np.array([responses(st, psf, target, pad, args.step) for st in stamps])
        for pad in (4, 16)
    }
    ok = np.isfinite(r[4]).all(axis=1) & np.isfinite(r[16]).all(axis=1)
    d = r[4][ok] - r[16][ok]
    print(
        f"{ok.sum()} stamps; R11, R22 with 4-fold padding {r[4][ok].mean(axis=0)}, "
        f"16-fold {r[16][ok].mean(axis=0)}"
    )
    print(f"4-fold - 16-fold: {d.mean(axis=0)} +- {d.std(axis=0) / np.sqrt(ok.sum())}")


if __name__ == "__main__":
    main()
