"""`megalut predict`: shear estimates and weights for a feature catalog."""

from __future__ import annotations

import logging

import click

from megalut_cli.cli.commands import short_help
from megalut_cli.cli.console import flag_names, stdin_path, stdout_path
from megalut_cli.cli.options import (
    MODEL_FILE,
    execution_options,
    model_help,
    output_option,
    overwrite_option,
    progress,
    schema_option,
)
from megalut_cli.errors import ConfigError
from megalut_cli.shear.options import PREDICT

log = logging.getLogger(__name__)


def parse_column_map(items: tuple[str, ...] | list[str]) -> dict[str, str]:
    """``--col`` values ``["adamom_g1=E1", ...]`` -> ``{"adamom_g1": "E1"}`` (feature -> catalog
    column)."""
    out: dict[str, str] = {}
    for item in items:
        feat, sep, col = item.partition("=")
        feat, col = feat.strip(), col.strip()
        if not sep or not feat or not col:
            raise ConfigError(f"--col {item!r}: expected FEATURE=COLUMN, e.g. adamom_g1=E1")
        if feat in out and out[feat] != col:
            raise ConfigError(f"--col: feature {feat!r} mapped twice")
        out[feat] = col
    return out


@click.command("predict", short_help=short_help("predict"))
@click.argument("features", type=click.Path(exists=True, dir_okay=False, allow_dash=True))
@click.option(
    "--model",
    "model_path",
    required=True,
    type=MODEL_FILE,
    help=model_help("Trained model (HDF5 from train-point / train-weight)."),
)
@output_option("Output catalog: all input columns plus the predictions.", dash=True)
@click.option(
    "--col",
    "col",
    multiple=True,
    metavar="FEATURE=COLUMN",
    help="Read the model feature FEATURE from the catalog column COLUMN (repeatable), "
    "e.g. --col adamom_g1=E1.",
)
@schema_option(PREDICT["chunk_rows"], show_default=True)
@schema_option(PREDICT["strict"])
@execution_options
@overwrite_option
def command(
    features: str,
    model_path: str,
    output: str,
    col: tuple[str, ...],
    chunk_rows: int,
    strict: bool,
    nproc: int,
    scheduler: str | None,
    overwrite: bool,
) -> None:
    """Predict shear estimates for every row of FEATURES.fits with a trained model.

    Adds pre_g1, pre_g2 (committee means of the point estimators) and, when the model
    has weight committees, pre_g1_w, pre_g2_w. Rows whose features failed (flags != 0 or a
    non-finite feature) get NaN estimates, weight 0 and the BAD_FEATURES flag (128) in
    'flags'. The catalog is streamed in chunks; the header records the model's sha256
    (MODELSHA). FEATURES '-' reads the catalog from stdin, -o - writes to stdout.

    Before predicting, the catalog is compared with the model's training domain: a
    warning with the numbers for each of skymad, snr, adamom_sigma, adamom_flux and the
    PSF's psf_adamom_sigma, g1, g2 (usable rows; noshear columns of a metacal catalog)
    whose median lies outside the model's 1-99 % range or of which more than 10 % of the
    rows lie outside its 0.5-99.5 % range (a constant training PSF: its size within 1 %,
    its ellipticity within 2e-4), for rows in (size, flux) cells the model has no training
    rows in, for a stamp size (STAMPSZ, else MEDS box_size) other than the model's, for a
    catalog without PSF measurement or without usable row, for a model whose recorded m is
    outside the Stage IV requirement, and for every item of the recorded setup (PSF, noise,
    gain) that differs. A metacal model is judged on snr and the size relative to the PSF
    only (its response absorbs the PSF and the noise). --strict refuses such a catalog
    (exit 1, one line, nothing written). The model's training population, domain and
    recorded bias on real galaxies (when it carries one) are logged at info level. MODEL
    may name a shipped model (--model fiducial).

    \b
    Example:
      megalut predict vo.fits --model model.h5 -o shears.fits
      megalut predict survey.fits --model fiducial -o shears.fits --strict
      megalut predict mycat.fits --model model.h5 -o shears.fits \\
          --col adamom_g1=E1 --col adamom_g2=E2
      megalut measure stamps.fits cat.fits -o - \\
          | megalut predict - --model model.h5 -o - | megalut evaluate -
    """
    # fitsio, and ~40 ms of modules (the simulation config ones): not for --help
    from megalut_cli.nn.model import ShearModel
    from megalut_cli.nn.population import model_report
    from megalut_cli.shear.predict import predict_catalog

    column_map = parse_column_map(col)
    with stdin_path(features) as features_path, stdout_path(output) as output_path:
        report = predict_catalog(
            features_path,
            model_path,
            output_path,
            column_map=column_map,
            nproc=nproc,
            scheduler=scheduler,
            overwrite=overwrite,
            chunk_rows=chunk_rows,
            strict=strict,
            progress=progress,
            names=flag_names(column_map="--col"),
        )
    log.info(
        "wrote %s: %d rows, %s (%d with failed features)",
        "stdout" if output == "-" else report.output,
        report.n_rows,
        ", ".join(report.columns),
        report.n_failed,
    )
    for line in model_report(ShearModel.load(model_path)):  # what the model was trained on
        log.info("%s", line)
