"""`megalut draft`: a pipeline file whose PSF, noise and stamp size come from your data."""

from __future__ import annotations

import logging

import click

from megalut_cli.atomic import atomic_output, check_output
from megalut_cli.cli.commands import short_help
from megalut_cli.cli.console import is_stdio
from megalut_cli.cli.options import output_option, overwrite_option, schema_option
from megalut_cli.draft import STARS_OPTION, draft_setup, render_pipeline, toml_value

log = logging.getLogger(__name__)


@click.command("draft", short_help=short_help("draft"))
@click.argument("features", type=click.Path(exists=True, dir_okay=False), metavar="FEATURES.fits")
@output_option("Output pipeline file (TOML).", dash=True)
@schema_option(STARS_OPTION)
@overwrite_option
def command(features: str, output: str, stars: str | None, overwrite: bool) -> None:
    """Draft a pipeline file for `megalut run` that trains networks for the setup of
    FEATURES.fits, a catalog measured on your own stamps (`megalut measure`).

    The draft is the default pipeline (`megalut run --print-default`, docs/pipeline.md)
    with the stamp size (the STAMPSZ card, or MEDS box_size), the PSF (median
    psf_adamom_* of the catalog's rows, measured with --psf or --psf-model, or of the
    stars of --stars; a Moffat when psf_adamom_rho4 shows wings, sheared when the PSF is
    elliptical) and the pixel noise (median noise_weight of weight maps, else skymad)
    measured on the data. Every drafted value carries a comment with the numbers it
    comes from; comments above the tables (and log lines) report what the draft did not
    decide: the data's snr, adamom_sigma and adamom_flux, a PSF varying across the field
    (see examples/varpsf), a galaxy size range widened to cover the data's. Check them,
    then run the file. -o - prints it.

    \b
    Examples:
      megalut measure stamps.fits cat.fits --psf psf.fits -o features.fits
      megalut draft features.fits -o my-pipeline.toml
      megalut run my-pipeline.toml --dry-run
      # the PSF from the stars of a star field instead
      megalut measure starfield.fits -o stars.fits --stars
      megalut draft features.fits --stars stars.fits -o -
    """
    from megalut_cli.catalog import read_catalog_columns  # fitsio: not for --help

    to_stdout = is_stdio(output)
    if not to_stdout:
        check_output(output, overwrite)  # before reading anything
    columns, header = read_catalog_columns(features)
    star_columns = read_catalog_columns(stars)[0] if stars is not None else None
    draft = draft_setup(
        columns, header, star_columns, features_name=features, stars_name=stars or "stars"
    )
    for v in draft.values:
        log.info("[%s] %s = %s: %s", v.table, v.key, toml_value(v.value), v.source)
    for note in draft.notes:
        (log.warning if note.warning else log.info)("[%s] %s", note.table, note.text)
    text = render_pipeline(draft)
    if to_stdout:
        click.echo(text, nl=False)
        return
    with atomic_output(output, overwrite) as tmp:
        tmp.write_text(text)
    log.info("wrote %s; check it with: megalut run %s --dry-run", output, output)
