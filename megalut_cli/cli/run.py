"""`megalut run`: the whole pipeline (simulate, train, predict, evaluate) from one TOML file."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from pathlib import Path

import click

from megalut_cli.cli.commands import short_help
from megalut_cli.cli.options import execution_options, overwrite_option, progress
from megalut_cli.errors import ConfigError, InputError

log = logging.getLogger(__name__)


@click.command(
    "run",
    short_help=short_help("run"),
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
    "--keep-going",
    is_flag=True,
    help="GREAT3 branch pipelines: when a subfield fails, report it and complete the others "
    "(the products hold them; the exit status is still 1).",
)
@click.option(
    "--dry-run",
    is_flag=True,
    help="Check the pipeline and the work folder, list the steps with the simulations' estimated "
    "times (from tiny calibration draws), and stop.",
)
@click.option(
    "--print-default",
    is_flag=True,
    help="Print the embedded default pipeline (to copy and edit) and exit.",
)
@execution_options
@overwrite_option
def command(
    pipeline: str | None,
    overrides: tuple[str, ...],
    workdir: str,
    skip_existing: bool,
    keep_going: bool,
    dry_run: bool,
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

    The default is the paper's fiducial setup (Sect. 5) scaled down to under 10 minutes on
    2 cores. Before the first step, every step is logged with its size, the simulations with
    a time estimated from a tiny calibration draw; --dry-run stops there. KEY=VALUE arguments
    override pipeline keys (dotted names, TOML values), e.g.
    scale=0.01 (the fraction of the stamps of every set), sets.vo.seed=7 or
    train_point.iterations=300. The file format is in docs/pipeline.md.

    A pipeline file with a [branch] table runs a GREAT3-layout branch instead (paper
    Sect. 8; docs/great3.md): per subfield (the work units of -j/--scheduler), measure
    the galaxies and stars, simulate point- and weight-training sets with the subfield's
    stars and noise, train, predict; then write the per-galaxy catalog shears.fits, the
    constant-shear submission submission.txt (subfield g1 g2) and, with the branch's
    truth, evaluation.json (m, c, Q_c). --keep-going completes the other subfields
    when one fails.

    \b
    Examples:
      # the default pipeline: 1.45e6 stamps (all cores used)
      megalut run
      megalut run --print-default > my-pipeline.toml
      # each step's size and simulation time (10^5 stamps here); no run
      megalut run examples/fiducial/pipeline.toml scale=0.001 \\
          --workdir fid --dry-run
      megalut run examples/fiducial/pipeline.toml scale=0.001 --workdir fid
      megalut run examples/fiducial/pipeline.toml scale=0.001 \\
          --workdir fid --skip-existing train_weight.iterations=500
      megalut run examples/varpsf/pipeline-field.toml scale=0.001 \\
          --workdir varpsf --skip-existing
      megalut run examples/great3/pipeline.toml branch.path=rgc \\
          --workdir rgc-run --keep-going
    """
    # the pipeline and simulation config modules, ~60 ms: not for --help
    from megalut_cli.pipeline import file as pl
    from megalut_cli.pipeline import run as pipeline_run
    from megalut_cli.pipeline.config import default_pipeline_text

    if print_default:
        click.echo(default_pipeline_text(), nl=False)
        return
    if pipeline is not None and "=" in pipeline and not Path(pipeline).exists():
        overrides, pipeline = (pipeline, *overrides), None  # `megalut run scale=0.5`
    if pipeline is not None and not Path(pipeline).is_file():
        raise click.BadParameter(f"{pipeline!r}: no such file", param_hint="PIPELINE.toml")
    if dry_run and pipeline is not None and _is_branch(pipeline):
        raise click.UsageError(
            "--dry-run applies to simulate/train pipelines, not GREAT3 branch pipelines"
        )
    if pipeline is not None and _branch_pipeline(
        pipeline, workdir, overrides, skip_existing, overwrite, keep_going, nproc, scheduler
    ):
        return
    if keep_going:
        log.info("--keep-going applies to GREAT3 branch pipelines only: ignored")
    with _keys_as_written(pipeline, overrides):
        pipe = pl.load_pipeline(pipeline, overrides)
    plan = pipeline_run.plan_pipeline(
        pipe,
        workdir,
        skip_existing=skip_existing,
        overwrite=overwrite,
        nproc=nproc,
        scheduler=scheduler,
        estimate=True if dry_run else None,
    )
    for line in plan:
        log.info("%s", line)
    if dry_run:
        return
    result = pipeline_run.run_pipeline(
        pipe,
        workdir,
        skip_existing=skip_existing,
        overwrite=overwrite,
        nproc=nproc,
        scheduler=scheduler,
        progress=progress,
    )
    click.echo(pipeline_run.format_summary(result))


@contextlib.contextmanager
def _keys_as_written(pipeline: str | None, overrides: tuple[str, ...]) -> Iterator[None]:
    """Errors of the pipeline file name its keys where the user wrote them: the file and
    its table (``pipeline.toml: [simulation.noise] sigam: unknown key``) or the override."""
    from megalut_cli.pipeline.config import where_written  # as in command: not for --help

    try:
        yield
    except (ConfigError, InputError) as err:
        if type(err) not in (ConfigError, InputError):  # errors with their own fields
            raise
        raise type(err)(where_written(str(err), pipeline, overrides)) from None


def _is_branch(pipeline: str) -> bool:
    from megalut_cli.pipeline import great3_file as g3  # astropy: not for --help

    return bool(g3.is_branch_pipeline(pipeline))


def _branch_pipeline(
    pipeline: str,
    workdir: str,
    overrides: tuple[str, ...],
    skip_existing: bool,
    overwrite: bool,
    keep_going: bool,
    nproc: int,
    scheduler: str | None,
) -> bool:
    """Run ``pipeline`` if it is a GREAT3 branch pipeline (a [branch] table); False otherwise."""
    # astropy: not for --help
    from megalut_cli.pipeline import great3_file as g3
    from megalut_cli.pipeline import great3_run as runner

    if not g3.is_branch_pipeline(pipeline):
        return False
    with _keys_as_written(pipeline, overrides):
        pipe = g3.load_branch_pipeline(pipeline, overrides)
    result = runner.run_branch(
        pipe,
        workdir,
        skip_existing=skip_existing,
        overwrite=overwrite,
        keep_going=keep_going,
        nproc=nproc,
        scheduler=scheduler,
        progress=progress,
    )
    click.echo(runner.format_summary(result))
    error = runner.failure_error(result)
    if error is not None:
        raise error
    return True
