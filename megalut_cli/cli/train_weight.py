"""`megalut train-weight`: train committees of weight networks with the MSWB cost."""

from __future__ import annotations

import click

from megalut_cli.cli.options import (
    execution_options,
    output_option,
    overwrite_option,
    parse_int_list,
    parse_list,
    progress,
    seed_option,
)


@click.command(
    "train-weight",
    short_help="Train weight committees (MSWB cost) for a point model.",
    context_settings={"show_default": True},
)
@click.argument("train", type=click.Path(exists=True, dir_okay=False))
@click.option(
    "--model",
    required=True,
    type=click.Path(exists=True, dir_okay=False),
    help="Model with the point-estimate committees (from train-point).",
)
@output_option("Output model file (HDF5): the point and the new weight committees.")
@click.option(
    "--features",
    default=None,
    metavar="A,B,...",
    help="Input feature columns of the weight networks. [default: all features of the point model]",
)
@click.option("--hidden", default="5", metavar="N,N", help="Hidden layer sizes.")
@click.option("--members", type=click.IntRange(1), default=8, help="Networks per committee.")
@click.option("--keep", type=click.IntRange(1), default=None, help="Members kept (lowest validation cost). [default: half]")
@click.option("--iterations", type=click.IntRange(1), default=300, help="Optimizer iterations per member.")
@click.option(
    "--batch-fraction",
    type=click.FloatRange(0.0, 1.0, min_open=True),
    default=0.25,
    help="Fraction of the training cases in each mini-batch (1: full batch).",
)
@click.option("--batch-iterations", type=click.IntRange(1), default=30, help="Iterations on each mini-batch.")
@click.option(
    "--select",
    metavar="EXPR",
    default=None,
    help='Selection function on realizations; rows outside get no weight, e.g. "snr > 10 & adamom_sigma > 1.5".',
)
@click.option(
    "--valid",
    type=click.Path(exists=True, dir_okay=False),
    default=None,
    help="Validation catalog. Default: hold out --valid-fraction of the cases.",
)
@click.option(
    "--valid-fraction",
    type=click.FloatRange(0.0, 1.0, max_open=True),
    default=0.2,
    help="Fraction of the training cases held out for validation when no --valid is given (0: none).",
)
@click.option(
    "--normalization",
    type=click.Choice(["minmax", "robust"]),
    default="minmax",
    help="Input scaling: training range to [-1, 1] (paper), or 1st-99th percentile to [-1, 1].",
)
@click.option("--optimizer", type=click.Choice(["bfgs", "lbfgs"]), default="bfgs", help="scipy optimizer.")
@click.option(
    "--precision",
    type=click.Choice(["float64", "float32"]),
    default="float64",
    help="Arithmetic of the network passes during training (float32 is about twice as fast).",
)
@seed_option(1, "Seed of the random draws (initial parameters, mini-batches, validation split).")
@execution_options
@overwrite_option
def command(
    train: str,
    model: str,
    output: str,
    features: str | None,
    hidden: str,
    members: int,
    keep: int | None,
    iterations: int,
    batch_fraction: float,
    batch_iterations: int,
    select: str | None,
    valid: str | None,
    valid_fraction: float,
    normalization: str,
    optimizer: str,
    precision: str,
    seed: int,
    nproc: int,
    scheduler: str | None,
    overwrite: bool,
) -> None:
    """Train weight committees for the point estimates of MODEL on TRAIN.

    The point committees of MODEL predict their estimates on TRAIN; then, for each target,
    a committee of networks with outputs in (0, 1) learns weights minimising the mean
    square weighted bias (paper Eq. 5) of every case. TRAIN should mimic the survey's
    population (many different galaxies per case, no shape-noise cancellation). Rows with
    flags != 0, non-finite features or estimates, or outside --select are masked (weight 0
    at prediction time is the user's selection). The output model holds the point and
    the weight committees.

    \b
    Example:
      megalut train-weight tw.fits --model model.h5 -o model_w.h5 --select "snr > 10" -j 4
    """
    from megalut_cli.training import TrainOptions, train_weight

    opts = TrainOptions(
        members=members,
        iterations=iterations,
        batch_fraction=batch_fraction,
        batch_iterations=batch_iterations,
        optimizer=optimizer,
        normalization=normalization,
        valid_fraction=valid_fraction,
        seed=seed,
        dtype=precision,
        keep=keep,
    )
    train_weight(
        train,
        model,
        output,
        features=parse_list(features, "--features"),
        hidden=parse_int_list(hidden, "--hidden"),
        select=select,
        valid=valid,
        options=opts,
        nproc=nproc,
        scheduler=scheduler,
        overwrite=overwrite,
        progress=progress,
    )
