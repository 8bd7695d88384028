"""`megalut train-point`: train committees of point estimators with the MSB cost."""

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

_DEFAULT_FEATURES = "adamom_g1, adamom_g2, adamom_sigma, adamom_flux, adamom_rho4"


@click.command(
    "train-point",
    short_help="Train point-estimate committees (MSB cost).",
    context_settings={"show_default": True},
)
@click.argument("train", type=click.Path(exists=True, dir_okay=False))
@output_option("Output model file (HDF5).")
@click.option(
    "--features",
    default=None,
    metavar="A,B,...",
    help=f"Input feature columns. [default: {_DEFAULT_FEATURES}, or those of --init-from]",
)
@click.option("--targets", default="tru_g1,tru_g2", metavar="A,B", help="Target columns, one committee each.")
@click.option(
    "--valid",
    type=click.Path(exists=True, dir_okay=False),
    default=None,
    help="Validation catalog (monitoring and member selection). Default: hold out --valid-fraction of the cases.",
)
@click.option(
    "--valid-fraction",
    type=click.FloatRange(0.0, 1.0, max_open=True),
    default=0.2,
    help="Fraction of the training cases held out for validation when no --valid is given (0: none).",
)
@click.option("--hidden", default=None, metavar="N,N", help="Hidden layer sizes. [default: 5,5, or those of --init-from]")
@click.option("--members", type=click.IntRange(1), default=8, help="Networks per committee.")
@click.option("--keep", type=click.IntRange(1), default=None, help="Members kept (lowest validation cost). [default: half]")
@click.option("--iterations", type=click.IntRange(1), default=1000, help="Optimizer iterations per member.")
@click.option(
    "--batch-fraction",
    type=click.FloatRange(0.0, 1.0, min_open=True),
    default=0.25,
    help="Fraction of the training cases in each mini-batch (1: full batch).",
)
@click.option("--batch-iterations", type=click.IntRange(1), default=30, help="Iterations on each mini-batch.")
@click.option("--cost", type=click.Choice(["msb", "mse"]), default="msb", help="Cost function (MSE only for comparison).")
@click.option(
    "--select-cases",
    metavar="EXPR",
    default=None,
    help='Keep only the cases for which EXPR holds, on aggregates over their valid realizations, '
    'e.g. "mean(snr) > 10" (also applied to --valid).',
)
@click.option(
    "--init-from",
    type=click.Path(exists=True, dir_okay=False),
    default=None,
    help="Continue from the point committees of this model (e.g. pretrained on ellipticity).",
)
@click.option(
    "--init",
    "init_scheme",
    type=click.Choice(["normal", "identity"]),
    default="normal",
    help="Starting parameters: N(0, 0.1), or near-identity on the matching feature (adamom_g1 for tru_g1).",
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
    output: str,
    features: str | None,
    targets: str,
    valid: str | None,
    valid_fraction: float,
    hidden: str | None,
    members: int,
    keep: int | None,
    iterations: int,
    batch_fraction: float,
    batch_iterations: int,
    cost: str,
    select_cases: str | None,
    init_from: str | None,
    init_scheme: str,
    normalization: str,
    optimizer: str,
    precision: str,
    seed: int,
    nproc: int,
    scheduler: str | None,
    overwrite: bool,
) -> None:
    """Train committees of neural networks predicting TARGETS from FEATURES.

    TRAIN is a catalog with one row per realization, grouped into cases by its `case`
    column; within a case all realizations share the target value. Each committee member
    minimises the mean square bias (paper Eq. 3) with BFGS on random mini-batches of cases,
    is monitored on the validation cases after every iteration, and keeps its parameters of
    lowest validation cost; the best half of the members form the committee. Rows with
    flags != 0 or non-finite features are masked; cases without any valid row are dropped.

    \b
    Examples:
      megalut train-point tp.fits -o model.h5 --select-cases "mean(snr) > 10" -j 4
      megalut train-point pre.fits -o pre.h5 --targets tru_e1,tru_e2
      megalut train-point tp.fits -o model.h5 --init-from pre.h5 --iterations 300
      megalut train-point toy.fits -o toy.h5 --features d --targets tru_theta --hidden 5
    """
    from megalut_cli.training import TrainOptions, train_point

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
    train_point(
        train,
        output,
        features=parse_list(features, "--features"),
        targets=parse_list(targets, "--targets"),
        valid=valid,
        hidden=parse_int_list(hidden, "--hidden"),
        cost=cost,
        select_cases=select_cases,
        init_from=init_from,
        init_scheme=init_scheme,
        options=opts,
        nproc=nproc,
        scheduler=scheduler,
        overwrite=overwrite,
        progress=progress,
    )
