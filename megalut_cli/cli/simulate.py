"""`megalut simulate`: draw galaxy stamps with known shear from a TOML config."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import click

from megalut_cli.cli.commands import short_help
from megalut_cli.cli.console import flag_names, stdout_path
from megalut_cli.cli.options import (
    device_option,
    engine_option,
    execution_options,
    feature_set_options,
    output_option,
    overwrite_option,
    progress,
    schema_option,
)
from megalut_cli.engine import resolve_device
from megalut_cli.measure.feature_sets import requested_sets
from megalut_cli.sim.config import keys_as_written, load_config
from megalut_cli.sim.options import SIMULATE

if TYPE_CHECKING:
    from megalut_cli.sim.config import SimConfig
    from megalut_cli.sim.scene import Scenes

log = logging.getLogger(__name__)


@click.command(
    "simulate",
    short_help=short_help("simulate"),
)
@click.argument("config", type=click.Path(exists=True, dir_okay=False))
@click.argument("overrides", nargs=-1, metavar="[KEY=VALUE]...")
@output_option("Output catalog (FITS table, one row per stamp).", dash=True)
@click.option(
    "--stamps",
    type=click.Path(dir_okay=False),
    default=None,
    help="Also write the stamps as a FITS image grid (stamp k at column k mod n_x, row k div n_x).",
)
@click.option(
    "--scene",
    "scene_path",
    type=click.Path(dir_okay=False),
    default=None,
    help="Draw scenes instead of stamps: fields of galaxies at random positions "
    "([scene] of CONFIG; docs/scenes.md), written here as cubes (SCI, WGT, MSK, PSF and an "
    "IMAGES table); -o then gets the truth, one row per galaxy per image. Not with --stamps, "
    "--measure, --great3, --n-cases, --n-realizations.",
)
@schema_option(SIMULATE["pairs"])
@schema_option(SIMULATE["measure"])
@feature_set_options(SIMULATE)
@schema_option(SIMULATE["metacal"])
@schema_option(SIMULATE["metacal_step"], show_default=True)
@schema_option(SIMULATE["moments_retry"], show_default=True)
@click.option(
    "--great3",
    "great3_dir",
    type=click.Path(file_okay=False),
    default=None,
    help="Also write a GREAT3-layout branch into this folder: each case is a subfield "
    "(image-SSS-0.fits, galaxy_catalog-SSS.fits/.txt, starfield_image-SSS-0.fits, truth/); "
    "see docs/great3.md. Not with --stamps.",
)
@schema_option(SIMULATE["n_cases"])
@schema_option(SIMULATE["n_realizations"])
@schema_option(SIMULATE["dry_run"])
@schema_option(SIMULATE["seed"], show_default=True)
@engine_option("stamps (and scene galaxies) are drawn, noised and measured")
@device_option("the fast engine draws, noises and measures")
@execution_options
@overwrite_option
def command(
    config: str,
    overrides: tuple[str, ...],
    output: str,
    stamps: str | None,
    scene_path: str | None,
    pairs: bool,
    measure: bool,
    metacal: bool,
    metacal_step: float,
    moments_retry: float,
    great3_dir: str | None,
    n_cases: int | None,
    n_realizations: int | None,
    dry_run: bool,
    seed: int,
    engine: str,
    device: str,
    nproc: int,
    scheduler: str | None,
    overwrite: bool,
    **feature_flags: bool,
) -> None:
    """Simulate the stamps described by CONFIG (a TOML file, see docs/config.md).

    The catalog has one row per stamp (ordered by case, then realization) with `case`,
    `rea`, the stamp centre `x, y` (FITS 1-based, in the --stamps grid) and every true
    parameter `tru_*`; with --measure it also holds the features (`adamom_*`, `skymad`,
    `snr`, `flags`) measured exactly as `megalut measure` would on the --stamps image.
    Without --stamps or --measure only the truth is written (nothing is drawn). -o - writes
    the catalog to stdout. Before drawing, the plan (cases, stamps, a time estimated from a
    tiny calibration draw) is logged; --dry-run stops there.

    With --great3 DIR, every case becomes a GREAT3 subfield whose realizations fill the
    grid of its image (n_x per row, default sqrt(n_realizations)); the catalog then also
    has `subfield` and the GREAT3 `ID`, and `x, y` are centres in the subfield images.

    With --scene SCENES.fits, fields of galaxies at random positions are drawn instead
    ([scene] of CONFIG: density per arcmin², size, pixel scale, number of fields; one shear
    per field; docs/scenes.md): the images go to SCENES.fits, their truth (one row per galaxy
    per image, `x, y` FITS 1-based) to -o; --pairs draws each field at +g and -g with the
    same galaxies and noise.

    KEY=VALUE arguments override config keys (dotted names, TOML values), e.g.
    `noise.sigma=0.1` or `galaxy.rad='{type="uniform", min=1, max=4}'`.
    --n-cases and --n-realizations scale a paper-sized config down.

    The fast engine (default) gives the same noiseless pixels and features as GalSim
    (docs/engines.md); its noise realizations differ from the galsim engine's, both drawn
    from the same per-stamp seeds. Galaxies it cannot draw (profile "real", knots) go
    through GalSim whatever the engine; with --scene it draws the galaxies (the noise is
    GalSim's for both).

    \b
    Examples (sizes as given; times measured on a busy 2-core machine):
      # 10 000 stamps drawn and measured, no image kept (40 s)
      megalut simulate examples/fiducial/tp.toml -o tp.fits --measure \\
          --n-cases 50 --n-realizations 200
      # 200 stamps kept as a grid image of 64x64-pixel stamps (25 s)
      megalut simulate examples/fiducial/vo.toml -o vo.fits \\
          --stamps vo-stamps.fits --n-cases 2 --n-realizations 100
      # 5000 low-noise stamps for the ellipticity pretraining (30 s)
      megalut simulate examples/varpsf/pretrain.toml -o pre.fits --measure \\
          noise.sigma=0.2 --n-cases 100 --n-realizations 50
      # a GREAT3-layout branch: 4 subfields of 10x10 stamps (30 s)
      megalut simulate examples/great3/branch.toml -o branch.fits \\
          --great3 branch/ --n-cases 4 --n-realizations 100
      # 10 fields of 250x250 px at +g and -g, 166 galaxies (3 s)
      megalut simulate examples/scenes/metadetect.toml -o truth.fits \\
          --scene scenes.fits
      # what the paper-sized config (10^7 stamps) would do, and how long
      megalut simulate examples/fiducial/tp.toml -o tp.fits --measure \\
          --dry-run
    """
    # GalSim, numba, SciPy, astropy, fitsio: not for --help
    from megalut_cli.sim.simulate import check_outputs, plan_message, simulate

    output = click.get_current_context().with_resource(
        stdout_path(output)
    )  # -o -: to stdout at the end
    if scene_path is not None or pairs:
        given = {
            "--stamps": stamps is not None,
            "--measure": measure,
            "--metacal": metacal,
            "--great3": great3_dir is not None,
            "--n-cases": n_cases is not None,
            "--n-realizations": n_realizations is not None,
        }
        if scene_path is None:
            raise click.UsageError("--pairs needs --scene (the pairs are scene fields)")
        clash = [flag for flag, on in given.items() if on] + [
            SIMULATE[name].cli_flag for name in requested_sets(feature_flags)
        ]
        if clash:
            raise click.UsageError(f"--scene draws fields, not stamps: do not give {clash[0]}")
        simulate_scenes(
            config,
            overrides,
            output,
            scene_path,
            pairs,
            dry_run,
            seed,
            nproc,
            scheduler,
            overwrite,
            engine,
        )
        return
    device = resolve_device(device)
    with keys_as_written(
        config, overrides, n_cases=n_cases, n_realizations=n_realizations
    ):  # [table] key of FILE
        cfg = load_config(config, overrides, n_cases=n_cases, n_realizations=n_realizations)
    feature_sets = requested_sets(feature_flags)
    if feature_sets and (not measure or great3_dir is not None):
        flag = SIMULATE[feature_sets[0]].cli_flag
        raise click.UsageError(f"{flag} needs --measure (and not --great3)")
    if metacal and (not measure or great3_dir is not None):
        raise click.UsageError("--metacal needs --measure (and not --great3)")
    if moments_retry and (not measure or great3_dir is not None):
        raise click.UsageError("--moments-retry needs --measure (and not --great3)")
    if great3_dir is not None and stamps is not None:
        raise click.UsageError("--great3 writes the subfield images itself: do not give --stamps")
    names = flag_names(branch_dir="--great3")
    check_outputs(cfg, output, stamps, overwrite, names)
    if great3_dir is not None:
        from megalut_cli.great3.sim import check_branch_output  # GalSim: not for --help

        check_branch_output(great3_dir, overwrite, names)
    log.info(
        "about to simulate %s",
        plan_message(
            cfg,
            seed,
            measure,
            stamps is not None or great3_dir is not None,
            nproc,
            scheduler,
            engine,
            device,
            metacal_step if metacal and measure else None,
            estimate=True if dry_run else None,
        ),
    )
    if dry_run:
        return
    if great3_dir is not None:
        from megalut_cli.great3.sim import simulate_branch  # GalSim: not for --help

        branch = simulate_branch(
            cfg,
            great3_dir,
            output,
            measure=measure,
            seed=seed,
            nproc=nproc,
            scheduler=scheduler,
            overwrite=overwrite,
            progress=progress,
            engine=engine,
            names=names,
        )
        log.info(
            "wrote %s (%d subfields) and %s", branch.branch_dir, branch.n_subfields, branch.catalog
        )
        return
    result = simulate(
        cfg,
        output,
        stamps=stamps,
        measure=measure,
        feature_sets=feature_sets,
        seed=seed,
        nproc=nproc,
        scheduler=scheduler,
        overwrite=overwrite,
        progress=progress,
        engine=engine,
        device=device,
        names=names,
        metacal=metacal,
        metacal_step=metacal_step,
        moments_retry=moments_retry,
    )
    log.info(
        "wrote %s (%d rows)%s",
        result.catalog,
        result.n_stamps,
        f" and {result.stamps}" if result.stamps is not None else "",
    )


def simulate_scenes(
    config: str,
    overrides: tuple[str, ...],
    output: str,
    scene_path: str,
    pairs: bool,
    dry_run: bool,
    seed: int,
    nproc: int,
    scheduler: str | None,
    overwrite: bool,
    engine: str,
) -> None:
    """``simulate --scene``: draw the fields of CONFIG's ``[scene]`` with ``engine``, write
    the images to ``scene_path`` and the truth to ``output`` (both or neither)."""
    import time  # noqa: I001

    from megalut_cli.atomic import check_output
    from megalut_cli.errors import MegalutError
    from megalut_cli.sim.scene import check_scene_size, draw_scenes, plan_text

    if pairs:
        overrides = (*overrides, "scene.pairs=true")
    with keys_as_written(config, overrides):
        cfg = load_config(config, overrides, scene=True)
    out = check_output(output, overwrite)
    images = check_output(scene_path, overwrite)
    if images.resolve() == out.resolve():
        raise MegalutError("--scene and --output must be different files")
    check_scene_size(cfg)
    log.info("about to simulate %s", plan_text(cfg, seed))
    if dry_run:
        return
    t0 = time.perf_counter()
    scenes = draw_scenes(cfg, seed, nproc, scheduler, engine)
    write_scenes(cfg, seed, scenes, out, images, overwrite, engine)
    log.info(
        "wrote %s (%d images) and %s (%d rows) in %.1f s",
        images,
        len(scenes.images),
        out,
        len(scenes.truth["image"]),
        time.perf_counter() - t0,
    )


def write_scenes(
    cfg: SimConfig,
    seed: int,
    scenes: Scenes,
    truth_path: Path,
    images_path: Path,
    overwrite: bool,
    engine: str,
) -> None:
    """The scene products, each written whole or not at all: the images (``SCI``, ``WGT``,
    ``MSK``, ``PSF`` cubes, ``NOISE`` for correlated noise, and the ``IMAGES`` table) and the
    truth table (``CONFIG`` HDU; ``STARS`` with stars)."""
    import contextlib

    import fitsio

    from megalut_cli.atomic import atomic_output
    from megalut_cli.catalog import catalog_writer, header_cards, to_structured, write_table_hdu
    from megalut_cli.sim.scene import SCENE_TRUTH_FORMAT, SCENES_FORMAT, scene_cards
    from megalut_cli.sim.simulate import config_table

    cards = scene_cards(cfg, seed, engine)
    rows = to_structured(scenes.image_table)
    with contextlib.ExitStack() as stack:
        writer = stack.enter_context(
            catalog_writer(
                truth_path,
                fmt=SCENE_TRUTH_FORMAT,
                cards=cards,
                overwrite=overwrite,
                extra_hdus={
                    "CONFIG": config_table(cfg),
                    **({} if scenes.stars is None else {"STARS": to_structured(scenes.stars)}),
                },
            )
        )
        writer.append(scenes.truth)
        tmp = stack.enter_context(atomic_output(images_path, overwrite))
        with fitsio.FITS(str(tmp), "rw", clobber=True) as fits:
            fits.write(
                scenes.images, header=header_cards(SCENES_FORMAT, cards=cards), extname="SCI"
            )
            fits.write(scenes.weights, extname="WGT")
            fits.write(scenes.masks, extname="MSK")
            fits.write(scenes.psfs, extname="PSF")
            if scenes.noise is not None:
                fits.write(scenes.noise, extname="NOISE")
            recs = header_cards(SCENES_FORMAT, cards=cards, columns=rows.dtype.names)
            write_table_hdu(fits, rows, recs, "IMAGES")
