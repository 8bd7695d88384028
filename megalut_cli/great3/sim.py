"""Simulated branches in the GREAT3 layout (``megalut simulate CONFIG -o CAT --great3 DIR``).

Every *case* of the simulation becomes a *subfield* ``SSS`` (= case index) and its
``n_realizations`` realizations the ``n_x`` x ``n_y`` stamps of its image, realization
``k`` at grid column ``k mod n_x`` and row ``k div n_x`` (``n_x`` = ``structure.n_x``,
default ``sqrt(n_realizations)``; the grid must be full). So a constant-shear branch is a
config with one shear per case, the galaxies drawn per realization and ``snc =
"pairs"`` (GREAT3's 90-degree pairs)::

    [structure]
    n_cases = 200                 # subfields
    n_realizations = 10000        # a 100 x 100 grid
    per_realization = ["galaxy"]
    snc = "pairs"
    stamp_size = 48

The branch folder gets, per subfield, ``image-SSS-0.fits``, ``galaxy_catalog-SSS.fits``
and ``.txt`` (0-indexed GREAT3 centres and IDs), ``starfield_image-SSS-0.fits`` (the
case's PSF drawn noiselessly on a 3 x 3 grid, the lower-left star exactly centred, the
others offset by up to ``STAR_SHIFT`` pixels), ``star_catalog-SSS.fits`` / ``.txt``, and
in ``truth/`` the GREAT3 truth files ``shear_params-SSS`` and
``starshape_parameters-SSS-0`` (PSF ellipticity: HSM adaptive moments of the centred
star, as GREAT3 measured its star shapes). The ``-o`` catalog is the usual
``megalut.simulation`` catalog (one row per stamp, all truth) with ``subfield``, ``ID``
and ``x, y`` = 1-based centres in the subfield image: with ``--measure`` its features
equal those of ``megalut measure image-SSS-0.fits galaxy_catalog-SSS.txt --origin 0``.

Subfields are work units (seeded per case as every simulation); files appear in a
temporary folder beside ``DIR`` that is renamed to ``DIR`` only when every subfield is
written, so a failed or interrupted run leaves nothing half-written.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import galsim
import numpy as np

from megalut_cli.atomic import atomic_output, check_output, move_into_folder
from megalut_cli.catalog import write_catalog, write_image, write_text_catalog
from megalut_cli.engine import DEFAULT_ENGINE
from megalut_cli.errors import ConfigError, MegalutError, Names, namer
from megalut_cli.great3 import layout as L
from megalut_cli.measure.features import measure_stamps
from megalut_cli.parallel import executor, map_units
from megalut_cli.progress import Progress, no_progress
from megalut_cli.seeding import STREAM_SIMULATE, rng_for
from megalut_cli.sim.config import SimConfig
from megalut_cli.sim.draw import WorkUnit, draw_unit, get_psf, psf_includes_pixel
from megalut_cli.sim.simulate import (
    expected_workers,
    log_engine_fallback,
    order_columns,
    simulation_cards,
    warn_hst_noise,
    write_simulation_catalog,
)
from megalut_cli.sim.structure import draw_case

log = logging.getLogger(__name__)

#: Largest offset (pixels, each axis) of the stars other than the lower-left one (GREAT3: 1).
STAR_SHIFT = 1.0
#: Sub-key of ``rng_for(seed, STREAM_SIMULATE, case, KEY)`` for the star offsets (0-2: structure).
_STAR_KEY = 3
#: Name of the truth sub-folder of a simulated branch.
TRUTH_DIR = "truth"
#: Bytes of subfield images held in memory at once (beyond one per worker).
_BATCH_BYTES = 1 << 30


@dataclass
class BranchResult:
    n_subfields: int
    n_x: int
    n_y: int
    seconds: float
    branch_dir: Path
    catalog: Path


def grid_shape(config: SimConfig) -> tuple[int, int]:
    """``(n_x, n_y)`` of the subfield grid; a ConfigError if the grid is not full."""
    s = config.structure
    n = s.n_realizations
    n_x = s.n_x if s.n_x else math.isqrt(n)
    if n_x * n_x != n and not s.n_x:
        raise ConfigError(
            f"structure.n_x: the GREAT3 layout puts the {n} realizations of a case on a full grid; "
            "give n_x (stamps per row) or a square number of realizations"
        )
    if n % n_x:
        raise ConfigError(
            f"structure.n_x: {n_x} does not divide n_realizations = {n} (the grid must be full)"
        )
    n_y = n // n_x
    if max(n_x, n_y) > L.MAX_GRID:
        raise ConfigError(
            f"structure.n_x: a {n_x}x{n_y} grid is too large for GREAT3 IDs "
            f"(at most {L.MAX_GRID} per side)"
        )
    return n_x, n_y


def check_config(config: SimConfig) -> tuple[int, int]:
    """Check that ``config`` maps onto GREAT3 subfields; return the grid ``(n_x, n_y)``."""
    s = config.structure
    if s.n_cases > L.MAX_SUBFIELD + 1:
        raise ConfigError(
            f"structure.n_cases: at most {L.MAX_SUBFIELD + 1} subfields in the GREAT3 layout, "
            f"got {s.n_cases}"
        )
    for group, what in (("shear", "one shear"), ("psf", "one PSF")):
        if group in s.per_realization:
            raise ConfigError(
                f"structure.per_realization: the GREAT3 layout needs {what} per subfield (case); "
                f"remove {group!r}"
            )
    if config.psf_varies:
        raise ConfigError(
            "psf.type: the GREAT3 constant-PSF layout needs a PSF that does not vary over the field"
        )
    return grid_shape(config)


def _star_field(
    config: SimConfig, seed: int, case: int, size: int
) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    """The case's PSF drawn on a 3x3 grid: ``(image, offsets (9, 2), (psf_g1, psf_g2))``."""
    d = draw_case(config, seed, case)
    spec, fx, fy = d.psf_specs[0]
    psf, truth = get_psf(spec, fx, fy, config.psf_varies, config.gsparams)
    method = "no_pixel" if psf_includes_pixel(spec) else "auto"
    n = L.STARFIELD_GRID
    rng = rng_for(seed, STREAM_SIMULATE, case, _STAR_KEY)
    offsets = rng.uniform(-STAR_SHIFT, STAR_SHIFT, (n * n, 2))
    offsets[0] = 0.0  # the lower-left star is exactly centred
    image = np.zeros((n * size, n * size), dtype=np.float32)
    stamp = galsim.ImageF(size, size, scale=1.0)
    for k in range(n * n):
        row, col = divmod(k, n)
        psf.drawImage(image=stamp, offset=(offsets[k, 0], offsets[k, 1]), method=method)
        image[row * size : (row + 1) * size, col * size : (col + 1) * size] = stamp.array
    res = galsim.hsm.FindAdaptiveMom(
        galsim.ImageF(np.ascontiguousarray(image[:size, :size])), strict=False
    )
    if res.moments_status == 0:
        shape = (float(res.observed_shape.g1), float(res.observed_shape.g2))
    else:  # fall back on the PSF truth
        shape = (float(truth["tru_psf_g1"]), float(truth["tru_psf_g2"]))
    return image, offsets, shape


def _draw_subfield(job: dict[str, Any]) -> dict[str, Any]:
    """Worker: the image, star field and catalog columns of one subfield (case)."""
    unit: WorkUnit = job["unit"]
    n_x, n_y, size = job["n_x"], job["n_y"], unit.config.structure.stamp_size
    res = draw_unit(unit)
    stamps = res["stamps"]
    image = (
        stamps.reshape(n_y, n_x, size, size).transpose(0, 2, 1, 3).reshape(n_y * size, n_x * size)
    )
    cols = res["columns"]
    g = L.grid_centres(n_x, n_y, size)
    origins = np.column_stack([g["column"] * size + 1, g["row"] * size + 1]).astype(float)
    if job["measure"]:
        cols.update(
            measure_stamps(stamps, origins=origins, gain=unit.config.gain, engine=unit.engine)
        )
    stars, offsets, psf_shape = _star_field(unit.config, unit.seed, unit.case_start, size)
    return {
        "image": np.ascontiguousarray(image),
        "stars": stars,
        "star_offsets": offsets,
        "psf_shape": psf_shape,
        "columns": cols,
    }


def _subfield_cards(
    config: SimConfig, seed: int, subfield: int, size: int, n: int, n_x: int
) -> dict[str, Any]:
    return {
        "SUBFIELD": (subfield, "GREAT3 subfield index (megalut case)"),
        "STAMPSZ": (size, "stamp size in pixels"),
        "NSTAMPX": (n_x, "stamps per row of the grid"),
        "NSTAMPS": (n, "number of stamps in the grid"),
        "SEED": (seed, "seed of every random draw (megalut simulate --seed)"),
        "CFGFILE": (Path(config.path).name, "simulation config file"),
        "CFGSHA": (config.sha256, "sha256 of the config file"),
    }


def _write_subfield(
    tmp_dir: Path, config: SimConfig, seed: int, case: int, res: dict[str, Any], n_x: int, n_y: int
) -> None:
    size = config.structure.stamp_size
    cards = _subfield_cards(config, seed, case, size, n_x * n_y, n_x)
    write_image(tmp_dir / L.image_name(case), res["image"], fmt=L.IMAGE_FORMAT, cards=cards)
    cat = L.galaxy_catalog(case, n_x, n_y, size)
    write_catalog(
        tmp_dir / L.galaxy_catalog_name(case, "fits"),
        cat,
        fmt=L.CATALOG_FORMAT,
        cards={
            "SUBFIELD": cards["SUBFIELD"],
            "STAMPSZ": cards["STAMPSZ"],
            "XYORIGIN": (0, "coordinate of the first pixel in x, y"),
        },
    )
    write_text_catalog(tmp_dir / L.galaxy_catalog_name(case, "txt"), cat)
    n = L.STARFIELD_GRID
    star_cards = dict(cards, NSTAMPX=(n, "stars per row"), NSTAMPS=(n * n, "number of stars"))
    write_image(
        tmp_dir / L.starfield_name(case), res["stars"], fmt=L.STARFIELD_FORMAT, cards=star_cards
    )
    stars = L.grid_centres(n, n, size)
    star_cat = {"x": stars["x"], "y": stars["y"]}
    write_catalog(
        tmp_dir / L.star_catalog_name(case, "fits"),
        star_cat,
        fmt=L.CATALOG_FORMAT,
        cards={"SUBFIELD": cards["SUBFIELD"], "STAMPSZ": cards["STAMPSZ"]},
    )
    write_text_catalog(tmp_dir / L.star_catalog_name(case, "txt"), star_cat)


def check_branch_output(
    branch_dir: str | os.PathLike, overwrite: bool, names: Names | None = None
) -> Path:
    """Fail early if ``branch_dir`` is a file, a non-empty folder without ``overwrite``, or
    its parent folder is missing (messages name the arguments by ``names``)."""
    name = namer(names)
    d = Path(branch_dir)
    key = f"{name('branch_dir')} {d}"
    if d.exists() and not d.is_dir():
        raise MegalutError(f"{key}: exists and is not a folder")
    if d.is_dir() and any(d.iterdir()) and not overwrite:
        raise MegalutError(
            f"{key}: the folder exists and is not empty; use {name('overwrite')} to replace "
            "its files"
        )
    parent = d.resolve().parent
    if not parent.is_dir():
        raise MegalutError(f"{key}: the parent folder {parent} does not exist")
    return d


def simulate_branch(
    config: SimConfig,
    branch_dir: str | os.PathLike,
    output: str | os.PathLike,
    measure: bool = False,
    seed: int = 1,
    nproc: int = 1,
    scheduler: str | None = None,
    overwrite: bool = False,
    progress: Progress | None = None,
    engine: str = DEFAULT_ENGINE,
    names: Names | None = None,
) -> BranchResult:
    """Simulate ``config`` into the GREAT3 branch folder ``branch_dir`` and the catalog ``output``.

    ``progress`` counts the subfields as they are drawn (``n_cases`` in all); messages name
    the arguments by ``names``.
    """
    out = check_output(output, overwrite)
    final = check_branch_output(branch_dir, overwrite, names)
    n_x, n_y = check_config(config)
    s = config.structure
    size = s.stamp_size
    workers = expected_workers(nproc, scheduler)
    jobs = [
        {
            "unit": WorkUnit(
                config, seed, c, c + 1, n_x, keep_stamps=True, measure=False, engine=engine
            ),
            "n_x": n_x,
            "n_y": n_y,
            "measure": measure,
        }
        for c in range(s.n_cases)
    ]
    bytes_per = 4 * n_x * n_y * size * size * 2  # stamps and image
    batch = max(1, workers, min(4 * workers, _BATCH_BYTES // max(bytes_per, 1)))
    log.info(
        "simulating a GREAT3-layout branch: %d subfield(s) of %dx%d stamps of %d px into %s",
        s.n_cases,
        n_x,
        n_y,
        size,
        final,
    )
    log_engine_fallback(config, engine, True)
    t0 = time.perf_counter()
    tmp_dir = Path(
        tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".tmp", dir=final.resolve().parent)
    )
    try:
        parts: list[dict[str, np.ndarray]] = []
        shapes = np.zeros((s.n_cases, 2))
        with (
            executor(nproc, scheduler) as pool,
            (progress or no_progress)("simulate", s.n_cases) as update,
        ):
            for i in range(0, len(jobs), batch):
                results = map_units(_draw_subfield, jobs[i : i + batch], pool, update)
                for job, res in zip(jobs[i : i + batch], results):
                    case = job["unit"].case_start
                    _write_subfield(tmp_dir, config, seed, case, res, n_x, n_y)
                    shapes[case] = res["psf_shape"]
                    parts.append(res["columns"])
        seconds = time.perf_counter() - t0
        columns = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        warn_hst_noise(columns)
        g = L.grid_centres(n_x, n_y, size)
        n_sub = s.n_cases
        columns["x"] = np.tile(g["column"] * size + (size + 1) / 2.0, n_sub)  # 1-based true centres
        columns["y"] = np.tile(g["row"] * size + (size + 1) / 2.0, n_sub)
        columns["subfield"] = columns["case"].copy()
        columns["ID"] = L.galaxy_ids(
            columns["case"], np.tile(g["column"], n_sub), np.tile(g["row"], n_sub)
        )
        columns = order_columns(columns)
        first = {c: columns.pop(c) for c in ("case", "rea", "subfield", "ID", "x", "y")}
        columns = {**first, **columns}
        g1 = columns["tru_g1"].reshape(n_sub, -1)[:, 0]
        g2 = columns["tru_g2"].reshape(n_sub, -1)[:, 0]
        L.write_truth(tmp_dir / TRUTH_DIR, np.arange(n_sub), g1, g2, shapes[:, 0], shapes[:, 1])
        cards = simulation_cards(config, seed, measure, engine)
        cards["NSTAMPX"] = (n_x, "stamps per row of each subfield image")
        cards["LAYOUT"] = ("great3", "files written by --great3")
        with atomic_output(out, overwrite) as tmp_cat:
            write_simulation_catalog(tmp_cat, columns, config, cards)
            check_branch_output(final, overwrite, names)  # appeared while we worked?
            move_into_folder(tmp_dir, final)
    finally:
        with contextlib.suppress(FileNotFoundError):
            shutil.rmtree(tmp_dir)
    n = n_x * n_y * s.n_cases
    log.info(
        "%d subfield(s), %d stamps in %.1f s (%.1f stamps/s)",
        s.n_cases,
        n,
        seconds,
        n / seconds if seconds else math.inf,
    )
    return BranchResult(s.n_cases, n_x, n_y, seconds, final, out)
