"""Turn a simulated grid of stamps into a MEDS file, as a survey would deliver it.

    python examples/your-data/make_meds.py stamps.fits truth.fits survey.toml -o survey.meds.fits

Each stamp of the ``megalut simulate --stamps`` grid becomes one object with one cutout (marked
as the coadd), a weight map of 1/sigma^2 from the config's ``[noise]``, the config's PSF drawn
by GalSim (with the pixel) as its PSF cutout, and, on 2 % of the objects, a cosmic ray: a
bright pixel off the galaxy's centre, flagged in the bad-pixel mask (``bmask``), so that
``measure`` must leave it out. The truth (``case``, ``rea``, ``tru_g1``, ``tru_g2``) rides
along as extra ``object_data`` columns, which ``megalut measure`` passes through, so that
``megalut evaluate`` can check the shears. See docs/your-data.md.
"""

from __future__ import annotations

import argparse

import fitsio
import galsim
import numpy as np

from megalut_cli.configfile import read_toml
from megalut_cli.measure.meds import write_meds

#: Truth columns carried into the MEDS file's object_data.
TRUTH = ("case", "rea", "tru_g1", "tru_g2")
#: Fraction of the objects given a masked cosmic ray.
COSMIC_FRACTION = 0.02


def psf_image(psf: dict, size: int) -> np.ndarray:
    """The config's Gaussian or Moffat PSF with the pixel, centred on a ``size``-pixel stamp."""
    if psf["type"] == "moffat":
        prof = galsim.Moffat(beta=psf["beta"], fwhm=psf["fwhm"])
    elif psf["type"] == "gaussian":
        prof = galsim.Gaussian(sigma=psf["sigma"])
    else:
        raise SystemExit(f"make_meds.py draws gaussian and moffat PSFs, not {psf['type']!r}")
    prof = prof.shear(g1=psf.get("g1", 0.0), g2=psf.get("g2", 0.0))
    return prof.drawImage(nx=size, ny=size, scale=1.0).array


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stamps")
    ap.add_argument("truth")
    ap.add_argument("config")
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--seed", type=int, default=7, help="seed of the cosmic rays")
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args()

    config, _ = read_toml(args.config)
    image, header = fitsio.read(args.stamps, header=True)
    size, nx, n = int(header["STAMPSZ"]), int(header["NSTAMPX"]), int(header["NSTAMPS"])
    k = np.arange(n)
    rows, cols = (k // nx)[:, None, None] * size, (k % nx)[:, None, None] * size
    iy, ix = np.indices((size, size))
    stamps = image[rows + iy, cols + ix].astype(np.float64)

    sigma = float(config["noise"]["sigma"])
    weights = np.full_like(stamps, 1.0 / sigma**2)
    bmasks = np.zeros(stamps.shape, dtype=np.int32)
    rng = np.random.default_rng(args.seed)
    hit = rng.choice(n, size=int(COSMIC_FRACTION * n), replace=False)
    for i in hit:  # a hot pixel 6-12 px from the centre
        r, phi = rng.uniform(6, 12), rng.uniform(0, 2 * np.pi)
        y, x = int(size / 2 + r * np.sin(phi)), int(size / 2 + r * np.cos(phi))
        stamps[i, y, x] += 500.0 * sigma
        bmasks[i, y, x] = 1
    psf = psf_image(config["psf"], size)
    truth = fitsio.read(args.truth, columns=list(TRUTH))
    write_meds(
        args.output,
        stamps,
        weights=weights,
        bmasks=bmasks,
        psfs=np.broadcast_to(psf, stamps.shape),
        extra={c: truth[c] for c in TRUTH},
        overwrite=args.overwrite,
    )
    print(f"wrote {args.output}: {n} objects of {size} px, {len(hit)} with a masked cosmic ray")


if __name__ == "__main__":
    main()
