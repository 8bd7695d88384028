"""Constants of stamp measurement and of its catalogs, in a module without imports (read by
option declarations, by the image and MEDS measurements, and by the device backend)."""

#: The smallest stamp, in pixels.
MIN_STAMP_SIZE = 3
#: Coordinates of the first pixel's centre a catalog may use: 1 (FITS), 0 (GREAT3).
ORIGINS = (0, 1)
#: Rescaling of the MAD into a Gaussian standard deviation (paper Eq. 7).
MAD_TO_SIGMA = 1.4826

#: Output format name of ``megalut measure`` catalogs.
FORMAT = "megalut.features"
FORMAT_VERSION = "1.0"
#: PSF feature columns (from the galaxy features of the PSF stamps).
PSF_COLUMNS: tuple[str, ...] = (
    "psf_adamom_g1",
    "psf_adamom_g2",
    "psf_adamom_sigma",
    "psf_adamom_rho4",
)

#: Output format name of ``megalut measure --metadetect`` catalogs.
MDET_FORMAT = "megalut.metadetect"
#: Format of a cells file (``megalut simulate --scene``; the input of ``measure --metadetect``).
CELLS_FORMAT = "megalut.scenes"
#: Header card of a cells file (and of the catalog): the width of the border (pixels) outside
#: each cell's inner region (overlapping cells, scenes); 0 or absent: the whole cell is inner.
INNER_CARD = "INNERBRD"
#: Stamp cut around each detection of ``--metadetect`` when no stamp size is given.
MDET_STAMP_SIZE = 48
#: ``--metadetect`` detection defaults (sep): threshold in noise sigmas, the fewest pixels,
#: deblending sub-thresholds and the minimum contrast of a deblended branch (Source
#: Extractor's defaults for the last two).
DETECT_THRESH = 5.0
DETECT_MINAREA = 4
DEBLEND_NTHRESH = 32
DEBLEND_CONT = 0.005
#: ``--metadetect``, ``--detect``: a detection whose unsheared position lies within this
#: many pixels of a masked pixel of its cell is flagged NEAR_MASK (docs/metadetect.md).
MASK_MARGIN = 10.0
#: ``--metadetect``, ``--detect``: detections whose adaptive-moment centroids lie within
#: this many pixels of each other measured the same light; all but one are flagged
#: DUPLICATE (docs/metadetect.md).
DUPLICATE_RADIUS = 0.25
#: ``--metadetect``, ``--detect``: what the masked pixels of a cell hold before the metacal
#: operation and detection: the harmonic interpolation of their good neighbours, or 0.
MASK_FILLS = ("interpolate", "zero")
#: ``--metadetect`` on a coadd image: the side of the cells it is cut into and the border
#: outside each cell's inner region (Rubin's cell coadds: 250-pixel cells, inner 150).
CELL_SIZE = 250
CELL_BORDER = 50
