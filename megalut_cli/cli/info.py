"""`megalut info`: what is inside a catalog, a stamp image, a model, an evaluation or a run
manifest."""

from __future__ import annotations

import click

from megalut_cli.cli.commands import short_help
from megalut_cli.cli.console import is_stdio, stdin_path
from megalut_cli.cli.options import MODEL_FILE_OR_STDIN


@click.command("info", short_help=short_help("info"))
@click.argument("file", type=MODEL_FILE_OR_STDIN, required=False)
@click.option(
    "--json", "as_json", is_flag=True, help="Print the summary as JSON (layout: docs/catalogs.md)."
)
@click.option(
    "--models",
    "list_models",
    is_flag=True,
    help="List the shipped models (name, shear mode, what they were trained on, file) "
    "instead of FILE.",
)
def command(file: str | None, as_json: bool, list_models: bool) -> None:
    """Show what FILE holds, as fitsinfo and rio info do for theirs.

    A FITS catalog of any megalut format: its format, rows, columns with their units
    and descriptions, how many rows each flag bit marks, header cards, the stored
    simulation config and the provenance chain (the command of every step that made
    it, the model and config hashes). A stamp image: its shape, stamp size and grid.
    An HDF5 model (a file, or a shipped model by name: megalut info fiducial): its
    targets, features, committees (networks selected, architecture, cost,
    normalisation, training settings), what it was trained on in plain words (galaxy
    profile and ranges, PSF, noise, stamp size) and its domain (the 1-99 % ranges of
    skymad, snr, sizes and flux over its training rows, which predict compares
    catalogs with), the training data of every training step (file names and sha256),
    software versions. --models lists the shipped models. An evaluation
    (evaluate --json, a run's evaluation.json): its input, m and c of each fit, the
    requirement. A run's manifest.json: the pipeline file and overrides, every finished
    step with its time and products. A text catalog (GREAT3's galaxy_catalog-SSS.txt,
    star_catalog-SSS.txt; '# name' header lines): rows, columns, subfields, x/y ranges.
    A MEDS file: checked as measure reads it (every cutout inside its extensions), with
    its objects, cutouts per object, box and PSF sizes, maps, and its Jacobians (turned,
    flipped, residual shear: the frame calibrate will give). FILE '-' reads stdin.

    \b
    Example:
      megalut info shears.fits
      megalut info model.h5 --json | python -m json.tool
      megalut info fiducial
      megalut info --models
      megalut info stamps.fits
      megalut info megalut-run/manifest.json
      megalut info megalut-run/evaluation.json
      megalut info galaxy_catalog-000.txt
      megalut info objects.meds.fits
      megalut measure stamps.fits cat.fits -o - | megalut info -
    """
    import json

    from megalut_cli.info import (  # fitsio: not for --help
        describe_file,
        describe_shipped_models,
        format_info,
        format_shipped_models,
    )

    if list_models == (file is not None):
        raise click.UsageError("give FILE or --models (one of them)")
    if list_models:
        models = describe_shipped_models()
        click.echo(json.dumps(models, indent=1) if as_json else format_shipped_models(models))
        return
    with stdin_path(file, "file") as path:
        assert path is not None
        info = describe_file(path)
    if is_stdio(file):
        info["path"] = "stdin"
    click.echo(json.dumps(info, indent=1, default=str) if as_json else format_info(info))
