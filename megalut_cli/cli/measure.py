"""`megalut measure`: adaptive-moment features of every stamp of a FITS image."""

from __future__ import annotations

import click

from megalut_cli.cli.commands import short_help
from megalut_cli.cli.console import flag_names, is_stdio, stdin_path, stdout_path
from megalut_cli.cli.options import (
    F,
    device_option,
    engine_option,
    execution_options,
    feature_set_options,
    output_option,
    overwrite_option,
    progress,
    schema_option,
)
from megalut_cli.engine import resolve_device
from megalut_cli.measure.feature_sets import requested_sets
from megalut_cli.measure.options import MEASURE

#: The images given with a coadd image (--metadetect): flag, library argument (the name of
#: the command's parameter, so that messages name it by its flag) and what it is.
COADD_IMAGE_OPTIONS: tuple[tuple[str, str, str], ...] = (
    (
        "--weight",
        "weight_path",
        "its weight map (inverse noise variance per pixel, 0 where bad), an image of the same "
        "shape.",
    ),
    ("--mask", "mask_path", "its mask (integer bits, non-zero bad), an image of the same shape."),
    (
        "--noise-image",
        "noise_path",
        "a realization of its noise (same shape, same correlations), whose correlation "
        "colours the fixnoise instead of white noise from the weight map.",
    ),
)


def coadd_image_options(command: F) -> F:
    """The options of :data:`COADD_IMAGE_OPTIONS`, in that order: each an existing file."""
    for flag, name, what in reversed(COADD_IMAGE_OPTIONS):
        command = click.option(
            flag,
            name,
            type=click.Path(exists=True, dir_okay=False),
            default=None,
            help=f"--metadetect on a coadd image: {what}",
        )(command)
    return command


@click.command(
    "measure",
    short_help=short_help("measure"),
)
@click.argument("stamps", type=click.Path(exists=True, dir_okay=False, allow_dash=True))
@click.argument(
    "catalog", required=False, type=click.Path(exists=True, dir_okay=False, allow_dash=True)
)
@output_option("Features catalog to write (FITS table, format megalut.features).", dash=True)
@schema_option(MEASURE["stamp_size"])
@schema_option(MEASURE["origin"], show_default=True)
@schema_option(MEASURE["gain"])
@click.option(
    "--psf",
    "psf",
    type=click.Path(exists=True, dir_okay=False),
    default=None,
    help="FITS image of PSF stamps: a grid like STAMPS (one PSF per row), or one PSF "
    "(single stamp, or the lower-left star of a star grid such as GREAT3's starfield_image); "
    "adds psf_adamom_g1, psf_adamom_g2, psf_adamom_sigma, psf_adamom_rho4.",
)
@click.option(
    "--psf-model",
    "psf_model",
    type=click.Path(exists=True, dir_okay=False),
    default=None,
    help="PSF model of the exposure the stamps are cut from, instead of --psf: a PSFEx .psf file "
    "or a Piff model (pip install 'megalut-cli[piff]'); each row's PSF is the model's at its "
    "position (CATALOG's x, y; without CATALOG the stamp centre in STAMPS), for psf_adamom_* "
    "and --metacal.",
)
@coadd_image_options
@schema_option(MEASURE["cell_size"], show_default=True)
@schema_option(MEASURE["cell_border"], show_default=True)
@schema_option(MEASURE["cutout"], show_default=True)
@schema_option(MEASURE["epochs"])
@schema_option(MEASURE["stars"])
@feature_set_options(MEASURE)
@schema_option(MEASURE["metacal"])
@schema_option(MEASURE["metacal_step"], show_default=True)
@schema_option(MEASURE["moments_retry"], show_default=True)
@schema_option(MEASURE["metadetect"])
@schema_option(MEASURE["detect"])
@schema_option(MEASURE["detect_thresh"], show_default=True)
@schema_option(MEASURE["detect_minarea"], show_default=True)
@schema_option(MEASURE["deblend_nthresh"], show_default=True)
@schema_option(MEASURE["deblend_cont"], show_default=True)
@schema_option(MEASURE["no_clean"])
@schema_option(MEASURE["mask_neighbours"])
@schema_option(MEASURE["mask_margin"], show_default=True)
@schema_option(MEASURE["mask_fill"], show_default=True)
@schema_option(MEASURE["duplicate_radius"], show_default=True)
@schema_option(MEASURE["seed"], show_default=True)
@engine_option("the adaptive moments are measured")
@device_option("the fast engine measures")
@execution_options
@overwrite_option
def command(
    stamps: str,
    catalog: str | None,
    output: str,
    stamp_size: int | None,
    origin: str,
    gain: float | None,
    psf: str | None,
    psf_model: str | None,
    weight_path: str | None,
    mask_path: str | None,
    noise_path: str | None,
    cell_size: int,
    cell_border: int,
    cutout: int,
    epochs: bool,
    stars: bool | None,
    metacal: bool,
    metacal_step: float,
    moments_retry: float,
    metadetect: bool,
    detect: bool,
    detect_thresh: float,
    detect_minarea: int,
    deblend_nthresh: int,
    deblend_cont: float,
    no_clean: bool,
    mask_neighbours: bool,
    mask_margin: float,
    mask_fill: str,
    duplicate_radius: float,
    seed: int,
    engine: str,
    device: str,
    nproc: int,
    scheduler: str | None,
    overwrite: bool,
    **feature_flags: bool,
) -> None:
    """Measure the paper's features (Sect. 4) on each stamp of STAMPS.

    Stamps are located by the centres x, y of CATALOG (FITS 1-based unless --origin 0),
    a FITS table or a text file with '# name' header lines (GREAT3's galaxy_catalog-SSS.txt),
    whose columns are all passed through; without CATALOG, stamp k is taken in grid order
    (column k mod n_x, row k div n_x from the lower-left pixel; as many stamps as the
    header card NSTAMPS says, else the whole grid) and gets one output row with its
    centre x, y. Adds adamom_flux, adamom_g1, adamom_g2, adamom_sigma,
    adamom_rho4, adamom_x, adamom_y (HSM adaptive moments: GalSim's FindAdaptiveMom
    or its compiled batched twin, --engine), adamom_logflux, skymad
    (1.4826 MAD of the stamp-edge pixels), snr (Eq. 8 with --gain, else Eq. 10) and a
    flags bitmask; flagged stamps (HSM failure, centroid more than min(10, S/4) pixels
    from the stamp centre, non-positive flux, stamp off the image, NaN pixels) have NaN
    features. A CATALOG whose provenance cards (SEED, CFGSHA, NCASES, NREA, NSTAMPX, STAMPSZ)
    disagree with the image's, or a --stamp-size that contradicts its STAMPSZ card, is
    refused. CATALOG '-' reads a FITS catalog from stdin (or STAMPS '-' a stamp image or a
    MEDS file); -o - writes to stdout. With --morphology,
    morph_conc, morph_conc_inner and morph_size_ratio are added. With --psf-model (a PSFEx
    .psf file or a Piff model of the exposure STAMPS is, or is cut from, pixel for pixel),
    each row's PSF is the model's at its position, drawn in the exposure's pixels on a stamp
    like the galaxy's and measured as a --psf grid stamp would be; the header records it
    (PSFMODEL, PSFMSHA, PSFMTYPE). With --metacal (and --psf or --psf-model),
    each stamp is also deconvolved by its PSF, sheared by +-step along g1 and g2 and
    reconvolved with a round target PSF, with fixnoise (docs/metacal.md): every feature
    column X (and psf_adamom_*, of the target PSF) is written again as X_noshear, X_1p,
    X_1m, X_2p, X_2m, and the header gets MCALSTEP, MCALSEED; in an image of stamps, a stamp
    with NaN pixels is then an error (a MEDS object with masked or NaN pixels is flagged).

    A MEDS cutout file as STAMPS (recognised by its object_data and image_cutouts
    extensions; no CATALOG) gives one row per object: its id, number, box_size,
    ncutout, ra, dec, orig_row, orig_col, and the features of its cutout --cutout (0:
    the coadd when the file marks one, else the first cutout; the log says which).
    Masked pixels (bmask != 0 or weight 0) are left out of the moments (as GalSim's
    badpix) and counted in n_masked; too many, or one near the centre, flag
    MASKED_PIXELS; noise_weight = 1/sqrt(median weight) gives the snr when the file
    has weight maps. The PSF: --psf (one for all objects), --psf-model (at each
    object's orig_col + 1, orig_row + 1), else the file's PSF cutouts
    (docs/catalogs.md, MEDS input). The Jacobian of the measured cutout (dudcol, dudrow,
    dvdcol, dvdrow) is passed through, so that megalut calibrate gives world-frame shears;
    --epochs measures every single-epoch cutout, one row per object and epoch.

    A cells file as STAMPS (SCI, WGT, MSK and PSF cubes, what megalut simulate --scene
    writes; docs/metadetect.md) is measured with --metadetect: per cell, the five metacal
    versions of the whole cell (fixnoise from the weight map), detection with sep on each
    version (--detect-thresh, --detect-minarea, --deblend-nthresh, --deblend-cont,
    --no-clean), and the
    features of a stamp (--stamp-size, default 48) cut around each detection, neighbours
    left in (--mask-neighbours: their segments masked): one row per detection per version
    (mdet_step, image, field, pair_sign, x, y, inner, the features, psf_adamom_* of the
    target PSF), format megalut.metadetect.
    A plain coadd image as STAMPS with --metadetect needs --weight and one PSF (--psf, one
    PSF image in the image's pixels, or --psf-model, drawn at each cell's centre); it is cut
    into cells of --cell-size pixels overlapping by twice --cell-border, whose inner regions
    tile the image (each object is inner in one cell), with --mask and --noise-image
    optional: rows get cell, x, y in the image's pixels and ra, dec from a celestial WCS.
    --detect instead detects on the cells themselves (no sheared versions): one row per
    detection with the features of its stamp and the cell's PSF (format megalut.features);
    with --metacal, each stamp's metacal versions, the stamp route on the same cells.

    \b
    Example (200 stamps):
      megalut simulate examples/fiducial/vp.toml -o cat.fits \\
          --stamps stamps.fits --n-cases 2 --n-realizations 100
      megalut measure stamps.fits cat.fits -o features.fits
      megalut measure stamps.fits cat.fits -o - \\
          | megalut predict - --model model.h5 -o shears.fits
      megalut measure image-000-0.fits galaxy_catalog-000.txt -o f.fits \\
          --stamp-size 48 --origin 0 --psf starfield_image-000-0.fits
      megalut measure stamps.fits cat.fits -o mcal.fits \\
          --psf psf.fits --metacal
      megalut measure exposure.fits objects.fits -o f.fits \\
          --psf-model exposure_psfcat.psf
      megalut measure starfield_image-000-0.fits -o stars.fits \\
          --stamp-size 48
      megalut measure objects.meds.fits -o f.fits
      megalut measure scenes.fits --metadetect -o det.fits
      megalut measure coadd.fits --weight weight.fits --psf psf.fits \\
          --metadetect -o det.fits
    """
    # fitsio: not for --help; measure_file_columns: no astropy Table (~0.4 s less)
    from megalut_cli.measure.measure import measure_file_columns

    device = resolve_device(device)

    if is_stdio(stamps) and is_stdio(catalog):
        raise click.UsageError("STAMPS and CATALOG cannot both be read from stdin ('-')")
    with (
        stdin_path(stamps, "stamps file") as stamps_path,
        stdin_path(catalog) as catalog_path,
        stdout_path(output) as output_path,
    ):
        assert stamps_path is not None
        measure_file_columns(
            stamps_path,
            catalog_path,
            output_path,
            stamp_size=stamp_size,
            origin=int(origin),
            gain=gain,
            psf_path=psf,
            nproc=nproc,
            scheduler=scheduler,
            overwrite=overwrite,
            progress=progress,
            stars=stars,
            engine=engine,
            feature_sets=requested_sets(feature_flags),
            device=device,
            names=flag_names(
                psf_path="--psf",
                psf_model_path="--psf-model",
            ),
            metacal=metacal,
            metacal_step=metacal_step,
            moments_retry=moments_retry,
            seed=seed,
            cutout=cutout,
            epochs=epochs,
            psf_model_path=psf_model,
            metadetect=metadetect,
            detect=detect,
            detect_thresh=detect_thresh,
            detect_minarea=detect_minarea,
            deblend_nthresh=deblend_nthresh,
            deblend_cont=deblend_cont,
            no_clean=no_clean,
            mask_neighbours=mask_neighbours,
            mask_margin=mask_margin,
            mask_fill=mask_fill,
            duplicate_radius=duplicate_radius,
            weight_path=weight_path,
            mask_path=mask_path,
            noise_path=noise_path,
            cell_size=cell_size,
            cell_border=cell_border,
        )
