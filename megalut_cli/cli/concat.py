"""`megalut concat`: the catalogs of many tiles as one, their provenance checked."""

from __future__ import annotations

import click

from megalut_cli.cli.commands import short_help
from megalut_cli.cli.options import output_option, overwrite_option


@click.command("concat", short_help=short_help("concat"))
@click.argument("catalogs", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False))
@output_option("Concatenated catalog to write (FITS table, the inputs' format).")
@overwrite_option
def command(catalogs: tuple[str, ...], output: str, overwrite: bool) -> None:
    """Concatenate CATALOGS (features, predictions or metadetection catalogs of many tiles,
    or of many simulation runs) into one.

    The catalogs must make one catalog: the same format and columns, and the same MLFORMAT,
    MODELSHA (the model), MCALSTEP, MDETSTEP and MCALTARG (the metacal step and target),
    MENGINE and SHFRAME; otherwise the first card that differs is named and nothing is
    written (exit 1).
    Rows follow in the order given, each with its tile index in the column tile (from 0);
    the cards every catalog holds with one value are kept, NTILES is added, and one
    HISTORY line per tile records its name, rows and sha256. megalut calibrate then
    calibrates the whole catalog at once (objects are told apart by tile and id). A
    calibrated catalog (calibrate -o) is refused: its responses belong to its own catalog.

    megalut evaluate on a concatenation of metadetection catalogs of scenes counts each
    run's fields apart (tile and field).

    \b
    Examples:
      megalut concat shears-tile*.fits -o shears.fits
      megalut calibrate shears.fits --by tile
      megalut concat det-run*.fits -o det.fits
      megalut evaluate det.fits
    """
    from megalut_cli.concat import concat_catalogs

    concat_catalogs(list(catalogs), output, overwrite)
