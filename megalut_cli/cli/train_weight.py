"""`megalut train-weight`: train committees of weight networks with the MSWB cost."""

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
from megalut_cli.nn.options import WEIGHT_OPTION, WeightSpec


@click.command(
    "train-weight",
    short_help=short_help("train-weight"),
    context_settings={"show_default": True},
)
@click.argument("train", type=click.Path(exists=True, dir_okay=False, allow_dash=True))
@click.option(
    "--model",
    required=True,
    type=MODEL_FILE,
    help=model_help("Model with the point-estimate committees (from train-point)."),
)
@output_option("Output model file (HDF5): the point and the new weight committees.")
@schema_option(WEIGHT_OPTION["features"])
@schema_option(WEIGHT_OPTION["hidden"])
@committee_options("weight")
@schema_option(WEIGHT_OPTION["select"])
@validation_options("Validation catalog. Default: hold out --valid-fraction of the cases.")
@optimizer_options
@execution_options
@overwrite_option
@pass_spec(WeightSpec)
def command(
    train: str,
    model: str,
    output: str,
    valid: str | None,
    spec: WeightSpec,
    device: str,
    nproc: int,
    scheduler: str | None,
    overwrite: bool,
) -> None:
    """Train weight committees for the point estimates of MODEL on TRAIN.

    The point committees of MODEL predict their estimates on TRAIN; then, for each target,
    a committee of networks with outputs in (0, 1) learns weights minimising the mean
    square weighted bias (paper Eq. 5) of every case. TRAIN (FITS; '-': stdin) should mimic
    the survey's population (many different galaxies per case, no shape-noise cancellation).
    Rows with flags != 0, non-finite features or estimates, or outside --select are masked
    (weight 0 at prediction time is the user's selection). The output model holds the point
    and the weight committees.

    \b
    Example:
      megalut train-weight tw.fits --model model.h5 -o model_w.h5 \\
          --select "snr > 10" -j 4
    """
    from megalut_cli.nn.fit import train_weight  # fitsio: not for --help

    train = click.get_current_context().with_resource(stdin_path(train))  # '-': stdin

    train_weight(
        train,
        model,
        output,
        spec,
        valid=valid,
        device=device,
        nproc=nproc,
        scheduler=scheduler,
        overwrite=overwrite,
        progress=progress,
        names=flag_names(valid="--valid FILE"),
    )
