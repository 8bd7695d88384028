"""Make ``psfex_moffat.psf``: a PSFEx model fit by PSFEx itself to a simulated star field of
a known PSF (a Moffat of beta 3.5, FWHM 3.8 px, sheared by g = (0.02, -0.05), convolved with
the pixel: :data:`PSF_PROFILE` of ``tests/test_psf_model.py``).

Needs Source Extractor and PSFEx on the PATH (Debian: ``apt install source-extractor psfex``;
not megalut dependencies, not run by the tests): 1 500 stars at uniform sub-pixel positions
on a 2000² image, fluxes log-uniform 2e4 to 3e5, Gaussian noise of sigma 5 (seeds 5 and 7);
a FITS_LDAC catalog with 35² vignets; PSFEx with its automatic sampling (0.979 px here),
35² basis pixels, a degree-1 polynomial (GalSim reads no degree-0 file).

    python tests/data/make_psfex_moffat.py      # writes tests/data/psfex_moffat.psf
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

import fitsio
import galsim
import numpy as np

HERE = Path(__file__).resolve().parent
PARAMS = "VIGNET(35,35) X_IMAGE Y_IMAGE XWIN_IMAGE YWIN_IMAGE FLUX_APER(1) FLUXERR_APER(1) "
PARAMS += "FLUX_RADIUS ELONGATION FLAGS SNR_WIN FLUX_MAX"


def star_field(path: Path) -> None:
    """The simulated star field, written to ``path``."""
    rng = np.random.default_rng(5)
    n, count = 2000, 1500
    image = galsim.ImageF(n, n, scale=1.0)
    psf = galsim.Moffat(beta=3.5, fwhm=3.8).shear(g1=0.02, g2=-0.05)
    xs, ys = rng.uniform(40, n - 40, count), rng.uniform(40, n - 40, count)
    fluxes = np.exp(rng.uniform(np.log(2e4), np.log(3e5), count))
    for x, y, flux in zip(xs, ys, fluxes):
        stamp = psf.withFlux(flux).drawImage(nx=41, ny=41, scale=1.0, center=galsim.PositionD(x, y))
        bounds = stamp.bounds & image.bounds
        image[bounds] += stamp[bounds]
    image.addNoise(galsim.GaussianNoise(galsim.BaseDeviate(7), sigma=5.0))
    fitsio.write(str(path), image.array, clobber=True)


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        star_field(work / "stars.fits")
        (work / "psfex.param").write_text("\n".join(PARAMS.split()) + "\n")
        run = {"cwd": work, "check": True}
        with open(work / "default.sex", "w") as f:
            subprocess.run(["source-extractor", "-dd"], stdout=f, **run)
        with open(work / "default.psfex", "w") as f:
            subprocess.run(["psfex", "-dd"], stdout=f, **run)
        subprocess.run(
            ["source-extractor", "stars.fits", "-c", "default.sex", "-CATALOG_NAME", "stars.cat",
             "-CATALOG_TYPE", "FITS_LDAC", "-PARAMETERS_NAME", "psfex.param",
             "-FILTER_NAME", "/usr/share/source-extractor/default.conv", "-PHOT_APERTURES",
             "10", "-SATUR_LEVEL", "1e9", "-DETECT_THRESH", "20", "-VERBOSE_TYPE", "QUIET"],
            **run,
        )  # fmt: skip
        subprocess.run(
            ["psfex", "stars.cat", "-c", "default.psfex", "-PSF_SAMPLING", "0.0",
             "-PSFVAR_DEGREES", "1", "-PSF_SIZE", "35,35", "-CHECKPLOT_DEV", "NULL",
             "-CHECKIMAGE_TYPE", "NONE", "-WRITE_XML", "N", "-PSF_DIR", ".",
             "-VERBOSE_TYPE", "QUIET", "-SAMPLE_FWHMRANGE", "1,10", "-SAMPLE_MINSN", "20"],
            **run,
        )  # fmt: skip
        shutil.copy(work / "stars.psf", HERE / "psfex_moffat.psf")


if __name__ == "__main__":
    main()
