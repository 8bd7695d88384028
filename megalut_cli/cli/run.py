"""`megalut run`: the whole pipeline (simulate, train, predict, evaluate) from one TOML file."""

from __future__ import annotations

from pathlib import Path

import click

from megalut_cli.cli.options import execution_options, overwrite_option


@click.command(
    "run",
    short_help="Run a whole pipeline: simulate, train, predict, evaluate.",
    context_settings={"show_default": True},
)
@click.argument("pipeline", required=False, metavar="[PIPELINE.toml]")
@click.argument("overrides", nargs=-1, metavar="[KEY=VALUE]...")
@click.option(
    "--workdir",
    type=click.Path(file_okay=False),
    default="megalut-run",
    help="Folder for every intermediate product, the manifest and evaluation.json.",
)
@click.option(
    "--skip-existing",
    is_flag=True,
    help="Skip the steps whose products are there and up to date (same parameters, same inputs); "
    "re-run the others, replacing their products.",
)
@click.option(
    "--print-default", is_flag=True, help="Print the embedded default pipeline (to copy and edit) and exit."
)
@execution_options
@overwrite_option
def command(
    pipeline: str | None,
    overrides: tuple[str, ...],
    workdir: str,
    skip_existing: bool,
    print_default: bool,
    nproc: int,
    scheduler: str | None,
    overwrite: bool,
) -> None:
    """Run the pipeline of PIPELINE.toml, or the embedded default without one.

    The steps: simulate and measure the point-training (tp), weight-training (tw) and
    validation (vo) sets, train-point on tp, train-weight on tw, predict on vo, evaluate.
    Optional sets add steps: "pretrain" (low-noise ellipticity pretraining, which
    train-point continues, paper Sect. 6) and "vp" (point estimates of point.h5 on it,
    evaluated unweighted into evaluation-vp.json). Every product goes to --workdir
    (tp.fits, tw.fits, vo.fits, point.h5, model.h5, vo-shears.fits, evaluation.json,
    evaluation.png with matplotlib) with a manifest.json recording each step's
    parameters and input hashes, which --skip-existing uses to redo only what changed
    (--overwrite redoes every step). A pipeline with a `name` puts its training and
    evaluation products in that subfolder, so that pipelines sharing their sets run in
    one --workdir and simulate them once. The m, c table (unweighted and weighted) is
    printed at the end; logs and step timings go to stderr.

    The default is the paper's fiducial setup (Sect. 5) scaled down to about 10 minutes on
    2 cores. KEY=VALUE arguments override pipeline keys (dotted names, TOML values), e.g.
    scale=0.01 (the fraction of the stamps of every set), sets.vo.seed=7 or
    train_point.iterations=300. The file format is in docs/pipeline.md.

    \b
    Examples:
      megalut run -j 2
      megalut run --print-default > my-pipeline.toml
      megalut run examples/fiducial/pipeline.toml scale=0.001 --workdir fid -j 4
      megalut run examples/fiducial/pipeline.toml scale=0.001 --workdir fid --skip-existing train_weight.iterations=500
      megalut run examples/varpsf/pipeline-field.toml scale=0.001 --workdir varpsf --skip-existing
    """
    from megalut_cli import pipeline as pl
    from megalut_cli.cli.options import progress

    if print_default:
        click.echo(pl.default_pipeline_text(), nl=False)
        return
    if pipeline is not None and "=" in pipeline and not Path(pipeline).exists():
        overrides, pipeline = (pipeline, *overrides), None  # `megalut run scale=0.5`
    if pipeline is not None and not Path(pipeline).is_file():
        raise click.BadParameter(f"{pipeline!r}: no such file", param_hint="PIPELINE.toml")
    pipe = pl.load_pipeline(pipeline, overrides)
    result = pl.run_pipeline(
        pipe,
        workdir,
        skip_existing=skip_existing,
        overwrite=overwrite,
        nproc=nproc,
        scheduler=scheduler,
        progress=progress,
    )
    click.echo(pl.format_summary(result))
