"""`megalut simulate`: draw galaxy stamps with known shear from a TOML config."""

from __future__ import annotations

import click

from megalut_cli.cli.options import (
    execution_options,
    output_option,
    overwrite_option,
    progress,
    seed_option,
)


@click.command(
    "simulate",
    short_help="Simulate galaxy stamps with known shear (truth and feature catalog).",
)
@click.argument("config", type=click.Path(exists=True, dir_okay=False))
@click.argument("overrides", nargs=-1, metavar="[KEY=VALUE]...")
@output_option("Output catalog (FITS table, one row per stamp).")
@click.option(
    "--stamps",
    type=click.Path(dir_okay=False),
    default=None,
    help="Also write the stamps as a FITS image grid (stamp k at column k mod n_x, row k div n_x).",
)
@click.option(
    "--measure",
    is_flag=True,
    help="Measure the features right after drawing (no image kept): the way to make large training sets.",
)
@click.option("--n-cases", type=click.IntRange(min=1), default=None, help="Override structure.n_cases.")
@click.option(
    "--n-realizations", type=click.IntRange(min=1), default=None, help="Override structure.n_realizations."
)
@seed_option(1, "Seed of every random draw; the output is identical for any -j or cluster.")
@execution_options
@overwrite_option
def command(
    config: str,
    overrides: tuple[str, ...],
    output: str,
    stamps: str | None,
    measure: bool,
    n_cases: int | None,
    n_realizations: int | None,
    seed: int,
    nproc: int,
    scheduler: str | None,
    overwrite: bool,
) -> None:
    """Simulate the stamps described by CONFIG (a TOML file, see docs/config.md).

    The catalog has one row per stamp (ordered by case, then realization) with `case`,
    `rea`, the stamp centre `x, y` (FITS 1-based, in the --stamps grid) and every true
    parameter `tru_*`; with --measure it also holds the features (`adamom_*`, `skymad`,
    `snr`, `flags`) measured exactly as `megalut measure` would on the --stamps image.
    Without --stamps or --measure only the truth is written (nothing is drawn).

    KEY=VALUE arguments override config keys (dotted names, TOML values), e.g.
    `noise.sigma=0.1` or `galaxy.rad='{type="uniform", min=1, max=4}'`.
    --n-cases and --n-realizations scale a paper-sized config down.

    \b
    Examples:
      megalut simulate examples/fiducial/tp.toml -o tp.fits --measure --n-cases 50 --n-realizations 200 -j 4
      megalut simulate examples/fiducial/vo.toml -o vo.fits --stamps vo-stamps.fits --n-cases 2 --n-realizations 100
      megalut simulate examples/varpsf/pretrain.toml -o pre.fits --measure noise.sigma=0.2 --n-cases 100
    """
    from megalut_cli.sim.config import load_config
    from megalut_cli.sim.simulate import n_work_units, simulate

    cfg = load_config(config, overrides, n_cases=n_cases, n_realizations=n_realizations)
    with progress("simulate", n_work_units(cfg, nproc, scheduler)) as update:
        simulate(
            cfg,
            output,
            stamps=stamps,
            measure=measure,
            seed=seed,
            nproc=nproc,
            scheduler=scheduler,
            overwrite=overwrite,
            progress=update,
        )
