"""`megalut evaluate`: multiplicative and additive shear biases of a prediction catalog."""

from __future__ import annotations

import sys
from typing import TextIO

import click

from megalut_cli.atomic import check_output, write_json
from megalut_cli.cli.commands import short_help
from megalut_cli.cli.console import flag_names, is_stdio, stdin_path
from megalut_cli.cli.options import (
    overwrite_option,
    parse_list,
    plot_option,
    schema_option,
    seed_option,
)
from megalut_cli.shear.options import EVALUATE, EVALUATE_CLI

#: Exit code of ``--fail-above`` when the Stage IV requirement does not hold.
EXIT_OUT_OF_TOLERANCE = 3


@click.command(
    "evaluate",
    short_help=short_help("evaluate"),
)
@click.argument("shears", type=click.Path(exists=True, dir_okay=False, allow_dash=True))
@schema_option(EVALUATE["by"].with_default(None))
@schema_option(EVALUATE["bins"], show_default=True)
@schema_option(EVALUATE["select"])
@schema_option(EVALUATE["select_cases"])
@click.option(
    "--json",
    "json_path",
    type=click.Path(dir_okay=False, allow_dash=True),
    default=None,
    help="Write all results (and per-case averages) to this JSON file (layout: docs/evaluate.md); "
    "'-': stdout, the table then goes to stderr.",
)
@plot_option("residual and conditional-bias panels")
@schema_option(
    EVALUATE_CLI["fail_above"],
    help=EVALUATE_CLI["fail_above"].help.replace("EXIT", str(EXIT_OUT_OF_TOLERANCE)),
)
@click.option(
    "--great3-truth",
    "great3_truth",
    type=click.Path(exists=True, file_okay=False),
    default=None,
    help="Truth folder of a GREAT3 constant-shear branch (shear_params-SSS, "
    "starshape_parameters-SSS-0; truth/ of 'simulate --great3'): SHEARS is then a submission "
    "(subfield g1 g2 per line) or a predictions catalog with subfield or GREAT3 ID, and the "
    "cases are its subfields.",
)
@schema_option(EVALUATE_CLI["sigma2_min"], show_default=True)
@click.option(
    "--twin",
    "twin_path",
    type=click.Path(exists=True, dir_okay=False),
    default=None,
    help="Paired evaluation: SHEARS holds real galaxies and TWIN their Sersic twins, simulated "
    "from one config and seed; prints m, c of both and m_real - m_twin with paired-bootstrap "
    "errors over galaxies (--bootstrap resamples, --seed; docs/realgal.md).",
)
@schema_option(EVALUATE_CLI["errors"], show_default=True)
@schema_option(EVALUATE_CLI["bootstrap"], show_default=True)
@schema_option(EVALUATE_CLI["response"], show_default=True)
@schema_option(EVALUATE_CLI["failures"], show_default=True)
@seed_option(help="Seed of the bootstrap resampling.")
@overwrite_option
def command(
    shears: str,
    by: str | None,
    bins: int,
    select: str | None,
    select_cases: str | None,
    json_path: str | None,
    plot_path: str | None,
    fail_above: bool,
    great3_truth: str | None,
    sigma2_min: float,
    errors: str,
    bootstrap: int,
    response: str,
    failures: str,
    twin_path: str | None,
    seed: int,
    overwrite: bool,
) -> None:
    """Measure the shear biases of SHEARS.fits, a catalog with truth and predictions.

    SHEARS.fits needs the columns case, tru_g1, tru_g2 and pre_g1, pre_g2 (from
    'megalut predict'); with pre_g1_w, pre_g2_w a weighted analysis is added. Rows with
    flags != 0 or NaN estimates are left out. The estimates of each case are averaged
    (unweighted, and weighted), and a line fitted over cases, <g_est> - g = m g + c, gives
    m and c with 1-sigma errors from the scatter of the residuals (ordinary least squares,
    every case counting the same). With PSF ellipticity columns (tru_psf_g1/g2, else
    psf_adamom_g1/g2) the biases are also given in the PSF frame (plus, cross), as in
    GREAT3, with its Q_c metric.

    Common-random-number sets (simulated with structure.common = true, header CRN = T)
    share their galaxies between cases, so the cases are not independent: their errors
    come from a bootstrap over galaxies instead (--bootstrap resamples of the realization
    groups, a 90-degree pair together, across all cases; --seed). The report says which
    errors it quotes.

    A metacal catalog (predictions on 'measure --metacal' features) is evaluated on its
    noshear estimates calibrated by the metacal response plus the selection response of
    --select and the weights. Metacal's step composes with each case's shear, so the mean
    response over a few drawn shears carries their spin-4 moments into m (about 1e-3 for
    20 shears up to 0.1): common-random-number sets of 10 cases or more are calibrated by
    the response at zero shear instead, the intercept of a fit of each case's response
    against its true shear (--response; docs/evaluate.md).

    A metadetection catalog of simulated scenes (measure --metadetect, predicted or not;
    docs/metadetect.md) is evaluated by the responses of each version's means over the
    whole catalog, one estimate per image (field and sign), m and c from a fit against the
    images' tru_g1, tru_g2 (the ±g pairs' difference and mean), errors from a bootstrap
    over fields; --select applies to every version's rows.

    With --great3-truth, SHEARS is evaluated against a GREAT3 constant-shear branch:
    a submission file (one 'subfield g1 g2' line per subfield) or a predictions catalog
    whose rows carry a subfield (column subfield, or GREAT3 ID = 1e6 subfield + ...);
    the subfields are the cases, the truth's starshape parameters give the PSF frame.

    SHEARS '-' reads a FITS catalog from stdin. The table goes to stdout (to stderr with
    --json -); exit status 0, or 1 for bad input, 2 for bad options, and with --fail-above
    3 when the Stage IV requirement does not hold.

    \b
    Example:
      megalut evaluate shears.fits
      megalut evaluate shears.fits --by tru_rad,tru_sersicn,snr --bins 5 \\
          --plot biases.png
      megalut evaluate vp-shears.fits --select-cases "mean(snr) > 10" \\
          --by "mean(snr),tru_rad,tru_sersicn"
      megalut evaluate shears.fits \\
          --select "snr > 10 & adamom_sigma > 1.5" --json biases.json
      megalut evaluate shears.fits --fail-above \\
          || echo "biases out of tolerance"
      megalut evaluate crn-shears.fits --bootstrap 500 --seed 2
      megalut evaluate submission.txt --great3-truth branch/truth \\
          --sigma2-min 1
      megalut evaluate real-shears.fits --twin twin-shears.fits \\
          --by "tru_twin_rad/tru_psf_sigma,snr"
    """
    # SciPy, fitsio: not for --help
    from megalut_cli.shear.evaluate import (
        WARN_M,
        errors_na_note,
        evaluate_catalog,
        large_m,
        requirement_met,
    )
    from megalut_cli.shear.report import format_table

    by_cols = parse_list(by, "--by column list")
    json_to_stdout = is_stdio(json_path)
    for path in (json_path, plot_path):
        if path is not None and not is_stdio(path):
            check_output(path, overwrite)
    if json_path is not None and plot_path is not None and json_path == plot_path:
        raise click.UsageError("--json and --plot must name different files")
    if plot_path is not None:
        from megalut_cli.shear.plots import check_plot_output  # SciPy, fitsio: not for --help

        check_plot_output(plot_path)

    if twin_path is not None:
        _evaluate_twin(
            shears,
            twin_path,
            by_cols,
            bins,
            bootstrap,
            seed,
            json_path,
            overwrite,
            other=[
                name
                for name, v in (
                    ("--great3-truth", great3_truth),
                    ("--select", select),
                    ("--select-cases", select_cases),
                    ("--plot", plot_path),
                    ("--fail-above", fail_above),
                    ("--errors", errors != "auto"),
                    ("--response", response != "auto"),
                    ("--failures", failures != "exclude"),
                )
                if v
            ],
        )
        return
    from_stdin = is_stdio(shears)
    shears = click.get_current_context().with_resource(stdin_path(shears))
    from megalut_cli.shear.metadetect import is_metadetect_catalog  # fitsio: not for --help

    if great3_truth is None and is_metadetect_catalog(shears):
        _evaluate_metadetect(
            shears,
            select,
            bootstrap,
            seed,
            json_path,
            overwrite,
            fail_above,
            other=[
                name
                for name, v in (
                    ("--by", by_cols),
                    ("--select-cases", select_cases),
                    ("--plot", plot_path),
                    ("--errors fit", errors == "fit"),
                    ("--response", response != "auto"),
                    ("--failures", failures != "exclude"),
                )
                if v
            ],
        )
        return
    if great3_truth is not None:
        from megalut_cli.great3.evaluate import evaluate_branch  # astropy, SciPy: not for --help

        if errors == "bootstrap":
            raise click.UsageError(
                "--errors bootstrap does not apply to --great3-truth (subfields are independent)"
            )
        if response != "auto":
            raise click.UsageError("--response does not apply to --great3-truth")
        if failures != "exclude":
            raise click.UsageError("--failures does not apply to --great3-truth")
        result = evaluate_branch(
            shears,
            great3_truth,
            sigma2_min=sigma2_min,
            by=by_cols,
            bins=bins,
            select=select,
            select_cases=select_cases,
            names=flag_names(),
        )
    else:
        result = evaluate_catalog(
            shears,
            by=by_cols,
            bins=bins,
            select=select,
            select_cases=select_cases,
            sigma2_min=sigma2_min,
            errors=errors,
            n_bootstrap=bootstrap,
            seed=seed,
            names=flag_names(),
            response=response,
            failures=failures,
        )
    if from_stdin:
        result["input"] = "stdin"
    click.echo(format_table(result), err=json_to_stdout)
    note = errors_na_note(result)
    if note:
        click.echo(f"megalut: {note}", err=True)
    warnings = large_m(result)
    if warnings:
        click.echo(
            f"megalut: warning: |m| > {WARN_M:g} ({'; '.join(warnings)}): "
            "an untrained or mismatched model?",
            err=True,
        )
    if json_to_stdout:
        _dump_json(result, sys.stdout)
    elif json_path is not None:
        write_json(json_path, result, overwrite)
    if plot_path is not None:
        from megalut_cli.shear.plots import plot_evaluation  # SciPy, fitsio: not for --help

        plot_evaluation(result, plot_path, overwrite)
    if fail_above and not requirement_met(result):
        click.echo(
            f"megalut: bias out of tolerance ({'; '.join(result['requirement']['failures'])})",
            err=True,
        )
        click.get_current_context().exit(EXIT_OUT_OF_TOLERANCE)


def _evaluate_metadetect(
    shears: str,
    select: str | None,
    n_boot: int,
    seed: int,
    json_path: str | None,
    overwrite: bool,
    fail_above: bool,
    other: list[str],
) -> None:
    """A metadetection catalog of simulated scenes: m, c from the images' true shears."""
    from megalut_cli.shear.metadetect import evaluate_metadetect_file, format_metadetect

    if other:
        raise click.UsageError(f"{other[0]} does not apply to a metadetection catalog")
    result = evaluate_metadetect_file(
        shears, select=select, n_bootstrap=n_boot, seed=seed, names=flag_names()
    )
    click.echo(format_metadetect(result), err=is_stdio(json_path))
    if is_stdio(json_path):
        _dump_json(result, sys.stdout)
    elif json_path is not None:
        write_json(json_path, result, overwrite)
    if fail_above and not result["requirement"]["met"]:
        click.echo(
            f"megalut: bias out of tolerance ({'; '.join(result['requirement']['failures'])})",
            err=True,
        )
        click.get_current_context().exit(EXIT_OUT_OF_TOLERANCE)


def _evaluate_twin(
    shears: str,
    twin: str,
    by: list[str] | None,
    bins: int,
    n_boot: int,
    seed: int,
    json_path: str | None,
    overwrite: bool,
    other: list[str],
) -> None:
    """The paired real-vs-twin evaluation of ``--twin``."""
    from megalut_cli.shear.paired import (  # SciPy, fitsio: not for --help
        evaluate_paired_catalogs,
        format_paired,
    )

    if other:
        raise click.UsageError(f"{other[0]} does not apply with --twin")
    if is_stdio(shears):
        raise click.UsageError("--twin needs SHEARS as a file, not stdin")
    result = evaluate_paired_catalogs(
        shears, twin, by=by, n_bins=bins, n_boot=n_boot, seed=seed, names=flag_names()
    )
    click.echo(format_paired(result), nl=False, err=is_stdio(json_path))
    if is_stdio(json_path):
        _dump_json(result, sys.stdout)
    elif json_path is not None:
        write_json(json_path, result, overwrite)


def _dump_json(result: dict, stream: TextIO) -> None:
    import json

    stream.write(json.dumps(result, indent=1, allow_nan=False) + "\n")
    stream.flush()
