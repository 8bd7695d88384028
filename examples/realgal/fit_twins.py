"""Fit the Sérsic twin of every real galaxy of a RealGalaxyCatalog and write the twin catalog.

    python examples/realgal/fit_twins.py \
        examples/data/cosmos/real_galaxy_catalog_26_extension_example.fits \
        examples/data/cosmos/real_galaxy_catalog_26_extension_sersic_twins.fits

Each galaxy's HST image is fitted by a Sérsic convolved with its HST PSF
(``megalut_cli.sim.twins.fit_sersic``): one twin per galaxy, no population is fitted.
"""

from __future__ import annotations

import logging
import os
import sys

import galsim

from megalut_cli.catalog import write_catalog
from megalut_cli.sim.twins import TWIN_FORMAT, fit_real_catalog


def main(catalog: str, output: str) -> None:
    """Fit every row of ``catalog`` (images beside it) and write ``output``."""
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    galsim.set_omp_threads(1)
    path = os.path.abspath(catalog)
    rgc = galsim.RealGalaxyCatalog(path, dir=os.path.dirname(path))
    rgc.preload()
    cols = fit_real_catalog(rgc)
    cards = {
        "REALCAT": (os.path.basename(path), "RealGalaxyCatalog fitted"),
        "UNITS": ("arcsec", "hlr, dx, dy in arcsec of the HST frame"),
    }
    write_catalog(output, cols, fmt=TWIN_FORMAT, cards=cards, overwrite=True, extname="TWINS")


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: fit_twins.py REAL_CATALOG.fits OUTPUT.fits")
    main(sys.argv[1], sys.argv[2])
