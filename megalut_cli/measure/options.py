"""The options of ``megalut measure``, declared once: its click options, the defaults of
:func:`megalut_cli.measure.measure.measure_file` and the table of ``docs/catalogs.md``.

The choices and ranges come from the modules that implement them (:mod:`.stamps`,
:mod:`megalut_cli.engine`); ``--engine``, ``--device``, ``-j``, ``--scheduler`` and
``--overwrite`` are the shared declarations of :mod:`megalut_cli.engine`,
:mod:`megalut_cli.parallel` and :mod:`megalut_cli.atomic`.
"""

from __future__ import annotations

from dataclasses import replace

from megalut_cli.atomic import OVERWRITE_OPTION
from megalut_cli.engine import DEVICE_OPTION, ENGINE_OPTION
from megalut_cli.measure.defaults import (
    CELL_BORDER,
    CELL_SIZE,
    DEBLEND_CONT,
    DEBLEND_NTHRESH,
    DETECT_MINAREA,
    DETECT_THRESH,
    DUPLICATE_RADIUS,
    MASK_FILLS,
    MASK_MARGIN,
    MDET_STAMP_SIZE,
    MIN_STAMP_SIZE,
    ORIGINS,
)
from megalut_cli.measure.feature_sets import set_options
from megalut_cli.measure.metacal_defaults import DEFAULT_STEP, MAX_STEP
from megalut_cli.parallel import NPROC_OPTION, SCHEDULER_OPTION
from megalut_cli.schema import DEFAULT_MARK, Option
from megalut_cli.seeding import SEED_OPTION

#: The options of ``megalut measure`` that only it has, in the order of ``--help``.
MEASURE_OPTIONS: tuple[Option, ...] = (
    Option(
        "stamp_size",
        "int",
        None,
        f"Stamp size in pixels{DEFAULT_MARK}.",
        minimum=MIN_STAMP_SIZE,
        default_text="the image's STAMPSZ header card",
    ),
    Option(
        "origin",
        "choice",
        "1",
        "Coordinate of the first pixel's centre in the catalog's x, y (1: FITS, 0: GREAT3).",
        choices=tuple(str(o) for o in ORIGINS),
    ),
    Option(
        "gain",
        "float",
        None,
        f"Gain in e-/ADU: S/N from the CCD equation (paper Eq. 8){DEFAULT_MARK}.",
        minimum=0,
        min_open=True,
        default_text="none, sky-limited S/N of Eq. 10",
    ),
    Option(
        "cutout",
        "int",
        0,
        "MEDS input: the cutout of each object to measure (0: the coadd when the file "
        "has one, else the first epoch; k: the k-th cutout; objects with fewer cutouts are "
        "flagged NO_CUTOUT).",
        minimum=0,
        metavar="INDEX",
    ),
    Option(
        "epochs",
        "bool",
        False,
        "MEDS input: measure every single-epoch cutout of each object instead of one "
        "(all but the coadd when the file has one), each with its own PSF, weight map and "
        "Jacobian: one row per object and epoch, its index in the column cutout; megalut "
        "calibrate combines them in the world frame.",
    ),
    Option(
        "stars",
        "bool",
        None,
        "STAMPS is a star field: one row per star with psf_adamom_flux, psf_adamom_g1, "
        "psf_adamom_g2, psf_adamom_sigma, psf_adamom_rho4, psf_adamom_x, psf_adamom_y, "
        f"flags{DEFAULT_MARK}.",
        flag="--stars/--no-stars",
        default_text="for files named starfield_image-*; a square one without "
        "--stamp-size or STAMPSZ card is a 3x3 grid",
    ),
    *set_options(),  # --morphology and every other optional feature set
    Option(
        "metacal",
        "bool",
        False,
        "Also measure the five metacalibration versions of each stamp (noshear, "
        "1p, 1m, 2p, 2m: deconvolved by the PSF, sheared by +-step along g1 and g2, reconvolved "
        "with a round target PSF, with fixnoise at the stamp's noise: skymad, or a MEDS file's "
        "noise_weight): every feature column X again as X_noshear, X_1p, X_1m, X_2p, X_2m, "
        "every version's skymad and snr on the noshear version's sky noise "
        "(docs/metacal.md). Needs --psf or --psf-model (a MEDS file may use its PSF cutouts).",
    ),
    Option(
        "metacal_step",
        "float",
        DEFAULT_STEP,
        "Shear step of --metacal.",
        minimum=0,
        min_open=True,
        maximum=MAX_STEP,
    ),
    Option(
        "moments_retry",
        "float",
        0.0,
        "Step factor of a damped second adaptive-moments iteration on the stamps whose "
        "first fails by itself (too many iterations, moments out of range, NaN): it "
        "converges to the same moments where HSM's iteration oscillates (about 6 in 10 of "
        "the failures of fiducial stamps at 0.5; docs/catalogs.md). 0: none, GalSim's failures.",
        minimum=0,
        maximum=1,
        max_open=True,
    ),
    Option(
        "metadetect",
        "bool",
        False,
        "STAMPS is a cells file (docs/metadetect.md: SCI, WGT, MSK, PSF cubes), or a coadd "
        "image with --weight and --psf or --psf-model, cut into cells: per cell, the "
        "five metacal versions of the whole cell (fixnoise from the weight map), detection on "
        "each version with sep, and the features of a stamp cut around each detection, "
        "neighbours left in (stamp size --stamp-size, default "
        f"{MDET_STAMP_SIZE}): one row per detection per version, format megalut.metadetect.",
    ),
    Option(
        "detect",
        "bool",
        False,
        "Like --metadetect, but detection on each cell itself (no sheared versions): one row "
        "per detection with the features of its stamp and the cell's PSF, format "
        "megalut.features; with --metacal, each stamp's metacal versions (the stamp route on "
        "the same cells, for comparison).",
    ),
    Option(
        "detect_thresh",
        "float",
        DETECT_THRESH,
        "--metadetect: detection threshold, in units of the noise of each version (from the "
        "weight map, through the metacal operation and fixnoise).",
        minimum=0,
        min_open=True,
    ),
    Option(
        "detect_minarea",
        "int",
        DETECT_MINAREA,
        "--metadetect: the fewest connected pixels above the threshold that make a detection.",
        minimum=1,
    ),
    Option(
        "deblend_nthresh",
        "int",
        DEBLEND_NTHRESH,
        "--metadetect: number of deblending sub-thresholds.",
        minimum=1,
        maximum=256,
    ),
    Option(
        "deblend_cont",
        "float",
        DEBLEND_CONT,
        "--metadetect: minimum flux fraction of a deblended branch (1: no deblending).",
        minimum=0,
        maximum=1,
    ),
    Option(
        "no_clean",
        "bool",
        False,
        "--metadetect: switch off sep's cleaning (Source Extractor's CLEAN, which merges "
        "detections it takes for spurious wings of brighter ones; on blended scenes it also "
        "removes real neighbours, docs/metadetect.md).",
    ),
    Option(
        "mask_neighbours",
        "bool",
        False,
        "--metadetect, --detect: mask the pixels of the other detections (sep's segmentation "
        "of the version) in each detection's stamp: on blends, fewer HSM failures and "
        "centroid shifts (docs/metadetect.md).",
    ),
    Option(
        "mask_margin",
        "float",
        MASK_MARGIN,
        "Flag NEAR_MASK (NaN features) on objects within this many pixels of a masked pixel: "
        "of the cell for --metadetect and --detect (from the detection's unsheared position), "
        "of the stamp for MEDS input; the column mask_dist holds that distance; 0: no flag "
        "(docs/metadetect.md, docs/catalogs.md).",
        minimum=0,
    ),
    Option(
        "duplicate_radius",
        "float",
        DUPLICATE_RADIUS,
        "--metadetect, --detect: flag DUPLICATE (NaN features) on a detection whose "
        "adaptive-moment centroid lies within this many pixels of another detection's in the "
        "same version: the same light measured twice (a galaxy split by the deblending, or a "
        "neighbour's light taken over); the detection nearest that centroid is kept; 0: no "
        "flag (docs/metadetect.md).",
        minimum=0,
    ),
    Option(
        "mask_fill",
        "choice",
        MASK_FILLS[0],
        "--metadetect, --detect: what the cell's masked pixels hold before the metacal "
        "operation and detection: 'interpolate' (each the mean of its neighbours: a smooth "
        "fill from the good pixels around) or 'zero' (docs/metadetect.md).",
        choices=MASK_FILLS,
    ),
    Option(
        "cell_size",
        "int",
        CELL_SIZE,
        "--metadetect on a coadd image: side of the square cells it is cut into (pixels).",
        minimum=32,
        maximum=4096,
    ),
    Option(
        "cell_border",
        "int",
        CELL_BORDER,
        "--metadetect on a coadd image: the border outside each cell's inner region "
        "(pixels); cells overlap by twice this and their inner regions tile the image, so "
        "each object counts in one cell (inner = 1).",
        minimum=0,
    ),
    replace(
        SEED_OPTION,
        help="Seed of the fixnoise fields of --metacal (one field per stamp; per realization "
        "in a common-random-number set) and of --metadetect (one per field of cells).",
    ),
)
MEASURE = {o.name: o for o in MEASURE_OPTIONS}

#: Every option of ``megalut measure`` with a value (not its files), for the docs table.
ALL_MEASURE_OPTIONS: tuple[Option, ...] = (
    *MEASURE_OPTIONS,
    ENGINE_OPTION,
    DEVICE_OPTION,
    NPROC_OPTION,
    SCHEDULER_OPTION,
    OVERWRITE_OPTION,
)
