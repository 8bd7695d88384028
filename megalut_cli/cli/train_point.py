"""`megalut train-point`: train committees of point estimators with the MSB cost."""

from __future__ import annotations

import click

from megalut_cli.cli.commands import short_help
from megalut_cli.cli.console import flag_names, stdin_path
from megalut_cli.cli.options import (
    MODEL_FILE,
    committee_options,
    execution_options,
    model_help,
    optimizer_options,
    output_option,
    overwrite_option,
    pass_spec,
    progress,
    schema_option,
    validation_options,
)
from megalut_cli.nn.options import POINT_OPTION, PointSpec

#: Without --features or --hidden, those of --init-from (else the declared defaults).
_FEATURES = POINT_OPTION["features"].with_default(
    None, f"{', '.join(POINT_OPTION['features'].default)}, or those of --init-from"
)
_HIDDEN = POINT_OPTION["hidden"].with_default(
    None, f"{','.join(str(n) for n in POINT_OPTION['hidden'].default)}, or those of --init-from"
)


@click.command(
    "train-point",
    short_help=short_help("train-point"),
    context_settings={"show_default": True},
)
@click.argument("train", type=click.Path(exists=True, dir_okay=False, allow_dash=True))
@output_option("Output model file (HDF5).")
@schema_option(_FEATURES)
@schema_option(POINT_OPTION["targets"])
@validation_options(
    "Validation catalog (monitoring and member selection). Default: hold out --valid-fraction "
    "of the cases."
)
@schema_option(_HIDDEN)
@committee_options("point")
@schema_option(POINT_OPTION["cost"])
@schema_option(POINT_OPTION["select_cases"])
@click.option(
    "--init-from",
    type=MODEL_FILE,
    default=None,
    help=model_help(
        "Continue from the point committees of this model (e.g. pretrained on ellipticity)."
    ),
)
@schema_option(POINT_OPTION["init"])
@optimizer_options
@execution_options
@overwrite_option
@pass_spec(PointSpec)
def command(
    train: str,
    output: str,
    valid: str | None,
    init_from: str | None,
    spec: PointSpec,
    device: str,
    nproc: int,
    scheduler: str | None,
    overwrite: bool,
) -> None:
    """Train committees of neural networks predicting TARGETS from FEATURES.

    TRAIN is a catalog (FITS; '-': stdin) with one row per realization, grouped into cases by
    its `case` column; within a case all realizations share the target value. Each committee member
    minimises the mean square bias (paper Eq. 3) with BFGS on random mini-batches of cases,
    is monitored on the validation cases after every iteration, and keeps its parameters of
    lowest validation cost; the best half of the members form the committee. Rows with
    flags != 0 or non-finite features are masked; cases without any valid row are dropped.

    \b
    Examples:
      megalut train-point tp.fits -o model.h5 \\
          --select-cases "mean(snr) > 10" -j 4
      megalut train-point pre.fits -o pre.h5 --targets tru_e1,tru_e2
      megalut train-point tp.fits -o model.h5 --init-from pre.h5 \\
          --iterations 300
      megalut train-point toy.fits -o toy.h5 --features d \\
          --targets tru_theta --hidden 5
    """
    from megalut_cli.nn.fit import train_point  # fitsio: not for --help

    train = click.get_current_context().with_resource(stdin_path(train))  # '-': stdin

    train_point(
        train,
        output,
        spec,
        valid=valid,
        init_from=init_from,
        device=device,
        nproc=nproc,
        scheduler=scheduler,
        overwrite=overwrite,
        progress=progress,
        names=flag_names(valid="--valid FILE"),
    )
