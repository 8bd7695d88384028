"""`megalut calibrate`: the calibrated mean shear of a catalog without truth."""

from __future__ import annotations

import json
import sys

import click

from megalut_cli.atomic import check_output, write_json
from megalut_cli.cli.commands import short_help
from megalut_cli.cli.console import flag_names, is_stdio, stdin_path
from megalut_cli.cli.options import (
    given_on_command_line,
    overwrite_option,
    plot_option,
    schema_option,
    seed_option,
)
from megalut_cli.shear.options import CALIBRATE


@click.command("calibrate", short_help=short_help("calibrate"))
@click.argument("predictions", type=click.Path(exists=True, dir_okay=False, allow_dash=True))
@schema_option(CALIBRATE["select"])
@schema_option(CALIBRATE["by"])
@schema_option(CALIBRATE["bins"], show_default=True)
@schema_option(CALIBRATE["unweighted"])
@schema_option(CALIBRATE["errors"], show_default=True)
@schema_option(CALIBRATE["patches"], show_default=True)
@schema_option(CALIBRATE["bootstrap"], show_default=True)
@schema_option(CALIBRATE["failures"], show_default=True)
@seed_option(help="Seed of the bootstrap resampling.")
@click.option(
    "--json",
    "json_path",
    type=click.Path(dir_okay=False, allow_dash=True),
    default=None,
    help="Write the results (whole catalog, each bin, provenance) to this JSON file "
    "(layout: docs/calibrate.md); '-': stdout, the table then goes to stderr.",
)
@click.option(
    "-o",
    "--output",
    "output",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write a per-object catalog (FITS) for downstream tools: id and position columns, "
    "calibrated g1, g2, weight, bin and its response R11 .. R22 (valid for averages, "
    "not for one object).",
)
@plot_option(
    "the diagnostics: the calibrated shear in bins of the PSF ellipticity with the fitted "
    "leakage, and the mean shear of each --by bin"
)
@overwrite_option
def command(
    predictions: str,
    select: str | None,
    by: str | None,
    bins: int,
    unweighted: bool,
    errors: str,
    patches: int,
    bootstrap: int,
    failures: str,
    seed: int,
    json_path: str | None,
    output: str | None,
    plot_path: str | None,
    overwrite: bool,
) -> None:
    """The calibrated mean shear of PREDICTIONS.fits, a catalog without truth.

    PREDICTIONS.fits is the output of 'megalut predict'. On a metacal catalog (pre_g1_noshear
    ..., mcal_r11 .. mcal_r22 and the sheared versions' pre_*_<type>) the mean noshear
    estimate is calibrated by the response of the versions' means,
    R = (<g>_jp - <g>_jm) / (2 step), each version's estimates averaged over the objects that
    version measured, with the selection (--select), the weights and a --by bin of a measured
    column taken on that version: failures that depend on the shear are a selection like
    any other (--failures selection, the default). --failures exclude keeps the objects with
    every version measured and calibrates by the mean response plus the selection response,
    g = (<R> + R_sel)^-1 <g> (biased where failures depend on the shear). On a
    simulation-calibrated catalog the estimates are averaged. Weighted by pre_g1_w, pre_g2_w
    when the catalog has them (metacal: every version's), unless --unweighted. Rows with
    flags != 0 (metacal: the noshear version's) or NaN estimates are left out.

    Errors: a delete-one jackknife over patches of the sky (ra, dec; else the image x, y),
    or a bootstrap over objects when the catalog has no positions; the response is
    recomputed in every sample. With the PSF ellipticity columns psf_adamom_g1,
    psf_adamom_g2 the PSF leakage alpha is fitted too: calibrated g_i = alpha_i e_psf,i + c_i
    (--plot draws it). With each object's Jacobian (dudcol, dudrow, dvdcol, dvdrow: a MEDS
    file's, or an image's celestial WCS) every estimate, response, weight and PSF ellipticity
    is first turned to the world frame (u west, v north; header card SHFRAME); rows that are
    epochs of one object (id and cutout: measure --epochs) are combined.

    The table goes to stdout (to stderr with --json -); -o writes the per-object catalog,
    each estimate calibrated by the response of its bin: valid for averages, not for one
    object. Exit status 0, or 1 for bad input, 2 for bad options; nothing is written on
    failure.

    \b
    Example:
      megalut calibrate shears.fits
      megalut calibrate shears.fits --by snr --bins 3 --json cal.json
      megalut calibrate shears.fits --by tomo_bin -o cal.fits --plot cal.png
      megalut calibrate shears.fits --select "snr > 10" \\
          --errors bootstrap --seed 2
    """
    from megalut_cli.catalog import catalog_info, read_cards, read_catalog_columns, write_catalog
    from megalut_cli.measure.metacal_defaults import STEP_CARD
    from megalut_cli.shear.calibrate import (
        CATALOG_FORMAT,
        calibrate_columns,
        calibrated_catalog,
        format_calibration,
        plan_calibration,
    )
    from megalut_cli.shear.evaluate import evaluation_provenance

    if output == "-":
        raise click.BadParameter(
            "the catalog cannot go to stdout ('-'); name a file", param_hint="-o"
        )
    for path in (json_path, output, plot_path):
        if path is not None and not is_stdio(path):
            check_output(path, overwrite)
    named = [p for p in (json_path, output, plot_path) if p is not None]
    if len(set(named)) < len(named):
        raise click.UsageError("--json, -o and --plot must name different files")
    if plot_path is not None:
        from megalut_cli.shear.plots import check_plot_output  # matplotlib: checked up front

        check_plot_output(plot_path)
    from_stdin = is_stdio(predictions)
    path = click.get_current_context().with_resource(stdin_path(predictions))
    names = flag_names()
    _, colnames, header = catalog_info(path)
    options = {
        "select": select,
        "by": by,
        "unweighted": unweighted,
        "errors": errors,
        # not given: None, the metacal route's default (refused elsewhere only when asked)
        "failures": failures if given_on_command_line("failures") else None,
    }
    plan = plan_calibration(colnames, header, source=predictions, names=names, **options)
    columns, _ = read_catalog_columns(path, list(plan.columns))
    cal = calibrate_columns(
        columns,
        header=header,
        bins=bins,
        n_patches=patches,
        n_bootstrap=bootstrap,
        seed=seed,
        source=predictions,
        names=names,
        **options,
    )
    result = cal.result
    result["provenance"] = evaluation_provenance(path)
    if from_stdin:
        result["input"] = "stdin"
        result["provenance"]["input"]["path"] = "stdin"
    to_stdout = is_stdio(json_path)
    click.echo(format_calibration(result), err=to_stdout)
    if to_stdout:
        sys.stdout.write(json.dumps(result, indent=1, allow_nan=False) + "\n")
        sys.stdout.flush()
    elif json_path is not None:
        write_json(json_path, result, overwrite)
    if plot_path is not None:
        from megalut_cli.shear.plots import plot_calibration

        plot_calibration(result, plot_path, overwrite)
    if output is not None:
        table, cards = calibrated_catalog(columns, cal)
        carried = {k: v for k, v in read_cards(path).items() if k != STEP_CARD}
        write_catalog(
            output,
            table,
            fmt=CATALOG_FORMAT,
            overwrite=overwrite,
            cards={**carried, **cards},
            history=header.get("HISTORY"),
        )
