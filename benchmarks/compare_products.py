"""Products comparison: does a refactoring or a speed change leave every command's outputs
identical?

Runs one fixed, small workflow (every subcommand and its main modes: ``simulate`` with the fast
engine, the galsim engine, a stamp grid and metacal; ``measure`` plain, ``--psf`` and
``--metacal``, a GREAT3 subfield and star field, MEDS files with and without PSF cutouts
and ``--metacal``; ``train-point``; ``train-weight``; ``predict`` plain and metacal; ``evaluate``;
``megalut run`` on a tiny pipeline; ``info``) with ``python -m megalut_cli`` in two trees, a
``git worktree`` of ``--before`` and the current working tree (or ``--after``), then compares
every product: FITS HDUs (data exactly, header cards but the provenance ones), HDF5 datasets
and attributes, JSON and text outputs (stdout of ``evaluate``, ``run``, ``info``). It prints
one line per product and each step's wall time per tree; exit status 0 when every product
is identical, 1 otherwise, 2 for bad usage. Page: benchmarks/products.md.

    python benchmarks/compare_products.py --before HEAD                 # HEAD vs working tree
    python benchmarks/compare_products.py --before HEAD~3 --after HEAD --keep /tmp/cmp
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent

# --------------------------------------------------------------------------- the workflow

#: A tiny `megalut run` pipeline (tests/pipeline_configs.py's TINY_PIPELINE and PRETRAIN_VP:
#: pretraining, vp set, 24x24 stamps, 2-member committees).
PIPELINE = """
description = "products comparison: tiny pipeline"

[simulation.structure]
stamp_size = 24

[simulation.shear]
g1 = {type = "uniform", min = -0.1, max = 0.1}
g2 = {type = "uniform", min = -0.1, max = 0.1}

[simulation.galaxy]
profile = "gaussian"
rad = {type = "uniform", min = 1.5, max = 3.0}
flux = {type = "uniform", min = 150.0, max = 500.0}
ellipticity = {type = "rayleigh", mode = 0.2, min = 0.0, max = 0.6}

[simulation.psf]
type = "gaussian"
sigma = 1.5

[simulation.noise]
type = "gaussian"
sigma = 1.0

[sets.tp]
n_cases = 24
n_realizations = 8
seed = 1
simulation = {structure = {per_realization = ["angle"], snc = "ring"}}

[sets.tw]
n_cases = 8
n_realizations = 30
seed = 2
simulation = {structure = {per_realization = ["galaxy"], snc = "pairs"}}

[sets.vo]
n_cases = 8
n_realizations = 30
seed = 3
simulation = {structure = {per_realization = ["galaxy"], snc = "pairs"}}

[sets.pretrain]
n_cases = 40
n_realizations = 2
seed = 4
simulation = {structure = {per_realization = [], snc = "none"}, noise = {sigma = 0.1}, \
shear = {g1 = {type = "constant", value = 0.0}, g2 = {type = "constant", value = 0.0}}}

[sets.vp]
simulation = {structure = {per_realization = ["angle"], snc = "ring"}}
seed = 5
n_cases = 10
n_realizations = 16

[pretrain]
members = 2
iterations = 15
seed = 10

[train_point]
members = 2
iterations = 15
seed = 11

[train_weight]
members = 2
iterations = 10
seed = 12

[evaluate_vp]
by = ["tru_rad"]
bins = 2
plot = false

[evaluate]
plot = false
"""

#: Inputs copied from each tree into its run folder (so that every command line, and so every
#: HISTORY card, is the same in both trees): (source in the tree, name in the run folder).
TREE_INPUTS = [
    ("examples/fiducial/tp.toml", "in/tp.toml"),
    ("examples/fiducial/tw.toml", "in/tw.toml"),
    ("examples/fiducial/vo.toml", "in/vo.toml"),
    ("examples/fiducial/vo-crn.toml", "in/vo-crn.toml"),
    ("examples/great3/branch.toml", "in/branch.toml"),
    ("megalut_cli/data/fiducial-metacal.h5", "in/fiducial-metacal.h5"),
    ("tests/data/DECam_00154912_12_psfcat.psf", "in/decam.psf"),
    ("examples/scenes/isolated.toml", "in/isolated.toml"),
]


@dataclass
class Step:
    """One command: ``python -m megalut_cli ARGS`` in the run folder; ``stdout`` names the
    file its standard output is kept in (a product) when it is one."""

    name: str
    args: list[str]
    stdout: str | None = None


def _sim(
    config: str, out: str, cases: int, rea: int, seed: int, *extra: str, j: int = 1
) -> list[str]:
    return [
        "simulate",
        f"in/{config}",
        "-o",
        out,
        "--n-cases",
        str(cases),
        "--n-realizations",
        str(rea),
        "--seed",
        str(seed),
        "-j",
        str(j),
        *extra,
    ]


def _grid(out: str, *extra: str) -> list[str]:
    """``measure`` of the simulated stamp grid into ``out``, one process."""
    return ["measure", "stamps.fits", "cat.fits", "-o", out, *extra, "-j", "1"]


WORKFLOW: list[Step] = [
    Step("simulate tp (fast, --measure)", _sim("tp.toml", "tp.fits", 40, 20, 1, "--measure")),
    Step(
        "simulate tw (fast, --measure --morphology, -j 2)",
        _sim("tw.toml", "tw.fits", 10, 40, 2, "--measure", "--morphology", j=2),
    ),
    Step("simulate vo (fast, --measure)", _sim("vo.toml", "vo.fits", 10, 120, 3, "--measure")),
    Step(
        "simulate vo (galsim, --measure)",
        _sim("vo.toml", "vo-galsim.fits", 2, 10, 4, "--measure", "--engine", "galsim"),
    ),
    Step(
        "simulate vo (--stamps)", _sim("vo.toml", "cat.fits", 2, 10, 5, "--stamps", "stamps.fits")
    ),
    Step(
        "simulate vo-crn (--measure --metacal)",
        _sim("vo-crn.toml", "mcal.fits", 2, 10, 6, "--measure", "--metacal"),
    ),
    Step("measure", _grid("features.fits")),
    Step("measure --psf", _grid("features-psf.fits", "--psf", "in/psf.fits")),
    Step(
        "measure --metacal --psf",
        _grid("features-mcal.fits", "--psf", "in/psf.fits", "--metacal", "--seed", "7"),
    ),
    Step(
        "measure --metacal --psf-model (PSFEx, even stamps)",
        _grid("features-model.fits", "--psf-model", "in/decam.psf", "--metacal", "--seed", "7"),
    ),
    Step(
        "simulate scenes (isolated, --scene)",
        [
            "simulate",
            "in/isolated.toml",
            "-o",
            "scene-truth.fits",
            "--scene",
            "scenes.fits",
            "scene.n_fields=4",
            "--seed",
            "3",
            "-j",
            "1",
        ],
    ),
    Step("measure --metadetect", ["measure", "scenes.fits", "--metadetect", "-o", "mdet.fits"]),
    Step(
        "simulate GREAT3 branch (--great3)",
        _sim("branch.toml", "g3.fits", 2, 100, 8, "--great3", "g3"),
    ),
    Step(
        "measure GREAT3 subfield (--origin 0, star field PSF)",
        [
            "measure",
            "g3/image-001-0.fits",
            "g3/galaxy_catalog-001.txt",
            "-o",
            "g3-features.fits",
            "--stamp-size",
            "48",
            "--origin",
            "0",
            "--psf",
            "g3/starfield_image-001-0.fits",
            "-j",
            "1",
        ],
    ),
    Step(
        "measure GREAT3 star field",
        ["measure", "g3/starfield_image-001-0.fits", "-o", "g3-stars.fits", "-j", "1"],
    ),
    Step(
        "measure MEDS (PSF cutouts, masks, weights)",
        ["measure", "in/objects.meds.fits", "-o", "meds.fits", "-j", "1"],
    ),
    Step(
        "measure MEDS --metacal --morphology (odd PSF cutouts)",
        [
            "measure",
            "in/objects.meds.fits",
            "-o",
            "meds-mcal.fits",
            "--metacal",
            "--morphology",
            "--seed",
            "9",
            "-j",
            "2",
        ],
    ),
    Step(
        "measure MEDS --psf --metacal (one PSF)",
        [
            "measure",
            "in/nopsf.meds.fits",
            "-o",
            "meds-psf.fits",
            "--psf",
            "in/psf.fits",
            "--metacal",
            "-j",
            "1",
        ],
    ),
    Step(
        "train-point",
        [
            "train-point",
            "tp.fits",
            "-o",
            "point.h5",
            "--members",
            "2",
            "--iterations",
            "8",
            "--batch-iterations",
            "4",
            "--select-cases",
            "mean(snr) > 10",
            "--seed",
            "11",
            "-j",
            "1",
        ],
    ),
    Step(
        "train-weight",
        [
            "train-weight",
            "tw.fits",
            "--model",
            "point.h5",
            "-o",
            "model.h5",
            "--members",
            "2",
            "--iterations",
            "6",
            "--batch-iterations",
            "3",
            "--seed",
            "12",
            "-j",
            "1",
        ],
    ),
    Step(
        "predict (2 chunks)",
        [
            "predict",
            "vo.fits",
            "--model",
            "model.h5",
            "-o",
            "vo-shears.fits",
            "--chunk-rows",
            "1000",
            "-j",
            "1",
        ],
    ),
    Step(
        "predict (metacal)",
        [
            "predict",
            "mcal.fits",
            "--model",
            "in/fiducial-metacal.h5",
            "-o",
            "mcal-shears.fits",
            "-j",
            "1",
        ],
    ),
    Step(
        "evaluate",
        [
            "evaluate",
            "vo-shears.fits",
            "--by",
            "tru_rad,snr",
            "--bins",
            "2",
            "--json",
            "evaluation.json",
            "--plot",
            "evaluation.png",
        ],
        stdout="evaluate.txt",
    ),
    Step(
        "evaluate (metacal)",
        ["evaluate", "mcal-shears.fits", "--json", "evaluation-mcal.json"],
        stdout="evaluate-mcal.txt",
    ),
    Step(
        "evaluate (bootstrap)",
        [
            "evaluate",
            "vo-shears.fits",
            "--errors",
            "bootstrap",
            "--bootstrap",
            "20",
            "--seed",
            "3",
            "--json",
            "evaluation-bootstrap.json",
        ],
        stdout="evaluate-bootstrap.txt",
    ),
    Step(
        "run (tiny pipeline)",
        ["run", "in/pipeline.toml", "--workdir", "run", "-j", "1"],
        stdout="run.txt",
    ),
    Step("info catalog", ["info", "vo-shears.fits"], stdout="info-catalog.txt"),
    Step("info stamps", ["info", "stamps.fits", "--json"], stdout="info-stamps.json"),
    Step("info model", ["info", "model.h5", "--json"], stdout="info-model.json"),
]

#: Products not compared (figures embed the plotting library's version and are drawn from
#: the compared JSON).
NOT_COMPARED = re.compile(r"\.(png|pdf|svg)$")

# --------------------------------------------------------------------------- provenance

#: FITS header cards that legitimately change between runs: the creation date, the software
#: (version), the sha256 of the model file (which holds a random uuid and its date), checksums.
IGNORED_CARDS = {"DATE", "CREATOR", "MODELSHA", "CHECKSUM", "DATASUM"}
#: Keys of JSON documents and HDF5 attributes (JSON-valued ones too) that do: dates, run
#: times, software versions, model uuids.
IGNORED_KEYS = {"created", "creator", "finished", "seconds", "versions", "megalut", "uuid"}
#: Every sha256 digest in JSON, HDF5 attributes and text is masked: they hash files (the
#: products, compared themselves, and the inputs, compared above them), and a model file holds
#: a random uuid, so every digest downstream of a training differs between two runs. The same
#: holds for the manifest's step keys (digests of parameters and input digests) and its file
#: fingerprints (sha256, size, mtime).
_DIGEST = re.compile(r"\b[0-9a-f]{64}\b")
_UUID = re.compile(r"\b[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}\b")
_FINGERPRINT = {"sha256", "size", "mtime_ns"}
#: Text lines that legitimately change: dates and times, durations, versions.
_TEXT_DROP = re.compile(
    r"\d{4}-\d\d-\d\d[T ]\d\d:\d\d|\bversions?\b|\b\d+(\.\d+)?\s*(s|ms|min|sec|seconds)\b",
    re.IGNORECASE,
)


def _ignored_key(key: str) -> bool:
    return key in IGNORED_KEYS


# --------------------------------------------------------------------------- running


@dataclass
class Tree:
    """A source tree the workflow runs in, with its run folder and step times."""

    label: str
    path: Path
    run: Path
    worktree: bool
    times: dict[str, float] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)


def _git(*args: str, cwd: Path = REPO) -> str:
    return subprocess.run(
        ["git", *args], cwd=cwd, check=True, capture_output=True, text=True
    ).stdout.strip()


def _environment(tree: Tree, cache: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MEGALUT_")}
    env.update(
        {
            "PYTHONPATH": str(tree.path),
            "MEGALUT_CACHE": str(cache / "megalut"),
            # both trees compile their kernels cold: fair times
            "NUMBA_CACHE_DIR": str(cache / "numba"),
            # same DATE cards where honoured (they are ignored anyway)
            "SOURCE_DATE_EPOCH": "1700000000",
            "OMP_NUM_THREADS": "1",
            "OPENBLAS_NUM_THREADS": "1",
            "MKL_NUM_THREADS": "1",
            "VECLIB_MAXIMUM_THREADS": "1",
            "NUMEXPR_NUM_THREADS": "1",
            "PYTHONDONTWRITEBYTECODE": "1",
        }
    )
    return env


def _write_psf(path: Path, size: int = 64) -> None:
    """The PSF image of the ``--psf`` steps: the fiducial Gaussian (sigma 2 px) with its pixel."""
    import galsim

    galsim.Gaussian(sigma=2.0).drawImage(nx=size, ny=size, scale=1.0).write(str(path))


def _write_meds(folder: Path) -> None:
    """The MEDS files of the MEDS steps (written once, by this tree, copied into both runs):
    120 noisy Sersic galaxies in 48-px boxes with weights, a few masked pixels and per-object
    PSF cutouts of 25 px (two PSFs, as two CCDs; odd, so redrawn for metacal), and the same
    galaxies without PSF cutouts."""
    import galsim

    from megalut_cli.measure.meds import write_meds

    rng = np.random.default_rng(2026)
    n, size = 120, 48
    psfs = [
        galsim.Moffat(beta=3.0, fwhm=fwhm).shear(g1=g1) for fwhm, g1 in ((4.0, 0.0), (4.6, 0.03))
    ]
    images = np.empty((n, size, size), np.float32)
    psf_images = np.empty((n, 25, 25), np.float32)
    for i in range(n):
        psf = psfs[i % 2]
        gal = galsim.Sersic(n=1.0 + 2.0 * rng.random(), half_light_radius=2.0 + 2.0 * rng.random())
        gal = gal.withFlux(2000.0 + 4000.0 * rng.random()).shear(
            g1=0.3 * rng.random() - 0.15, g2=0.3 * rng.random() - 0.15
        )
        img = galsim.Convolve(gal, psf).drawImage(
            nx=size, ny=size, scale=1.0, offset=rng.uniform(-0.5, 0.5, 2)
        )
        images[i] = img.array + rng.normal(0.0, 1.5, (size, size))
        psf_images[i] = psf.drawImage(nx=25, ny=25, scale=1.0).array
    weights = np.full_like(images, 1.0 / 1.5**2)
    bmasks = np.zeros(images.shape, np.int32)
    bmasks[::7, 3:6, 30:33] = 1  # a small defect off centre
    bmasks[5, 20:28, 20:28] = 1  # one masked at the centre: MASKED_PIXELS
    write_meds(folder / "objects.meds.fits", images, weights, bmasks, psf_images)
    write_meds(folder / "nopsf.meds.fits", images, weights, bmasks)


def _prepare(tree: Tree, psf: Path) -> None:
    (tree.run / "in").mkdir(parents=True)
    (tree.run / "logs").mkdir()
    for src, dst in TREE_INPUTS:
        if (tree.path / src).is_file():
            shutil.copyfile(tree.path / src, tree.run / dst)
    shutil.copyfile(psf, tree.run / "in" / "psf.fits")
    for name in ("objects.meds.fits", "nopsf.meds.fits"):
        shutil.copyfile(psf.parent / name, tree.run / "in" / name)
    (tree.run / "in" / "pipeline.toml").write_text(PIPELINE)


def run_workflow(tree: Tree, cache: Path, timeout: float) -> None:
    """Run every step of :data:`WORKFLOW` in ``tree.run``; failures are recorded, not raised."""
    env = _environment(tree, cache)
    where = subprocess.run(
        [sys.executable, "-c", "import megalut_cli; print(megalut_cli.__file__)"],
        cwd=tree.run,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    if not Path(where).resolve().is_relative_to(tree.path.resolve()):
        raise SystemExit(
            f"{tree.label}: python imports megalut_cli from {where}, not from {tree.path}"
        )
    print(f"[{tree.label}] {tree.path} (megalut_cli from {where})", flush=True)
    for i, step in enumerate(WORKFLOW):
        log = tree.run / "logs" / f"{i:02d}.stderr.txt"
        out = tree.run / step.stdout if step.stdout else tree.run / "logs" / f"{i:02d}.stdout.txt"
        t0 = time.perf_counter()
        with open(out, "wb") as fo, open(log, "wb") as fe:
            try:
                rc = subprocess.run(
                    [sys.executable, "-m", "megalut_cli", *step.args],
                    cwd=tree.run,
                    env=env,
                    stdout=fo,
                    stderr=fe,
                    timeout=timeout,
                ).returncode
            except subprocess.TimeoutExpired:
                rc = -1
        tree.times[step.name] = time.perf_counter() - t0
        status = "ok" if rc == 0 else f"FAILED (exit {rc}, log {log})"
        if rc != 0:
            tail = log.read_text(errors="replace").strip().splitlines()[-1:] or [""]
            tree.failed[step.name] = f"exit {rc}: {tail[0][:200]}"
        print(
            f"[{tree.label}] {step.name:<50} {tree.times[step.name]:7.1f} s  {status}", flush=True
        )


# --------------------------------------------------------------------------- comparing


def _fmt(v: Any) -> str:
    text = repr(v.item() if isinstance(v, np.generic) else v)
    return text if len(text) <= 80 else text[:77] + "..."


def _first_array_difference(a: np.ndarray, b: np.ndarray, table: bool = False) -> str | None:
    """``None`` when ``a`` and ``b`` are exactly equal (NaNs equal, the sign of zero counts),
    else where they first differ: 'row R: A != B' (``table``: a column, with the element of a
    vector cell), 'at (i, j): A != B' (an array)."""
    if a.dtype != b.dtype:
        return f"dtype {a.dtype} != {b.dtype}"
    if a.shape != b.shape:
        return f"shape {a.shape} != {b.shape}"
    if a.dtype.kind in "fc":
        same = (a == b) | (np.isnan(a) & np.isnan(b))
        same &= np.signbit(a.real) == np.signbit(b.real)
    else:
        same = a == b
    same = np.asarray(same)
    if same.all():
        return None
    idx = tuple(int(i) for i in np.argwhere(~same)[0]) if same.ndim else ()
    n_bad = int((~same).sum())
    if not idx:
        where = "value"
    elif table:
        where = f"row {idx[0]}" + (f" element {list(idx[1:])}" if len(idx) > 1 else "")
    else:
        where = f"at {idx if len(idx) > 1 else idx[0]}"
    return f"{where}: {_fmt(a[idx])} != {_fmt(b[idx])} ({n_bad} of {same.size} differ)"


def _normalise(value: Any, roots: Sequence[tuple[str, str]]) -> Any:
    """``value`` with provenance keys dropped and the trees' and run folders' paths replaced."""
    if isinstance(value, dict):
        if set(value) == _FINGERPRINT:
            return "<file fingerprint>"
        return {k: _normalise(v, roots) for k, v in value.items() if not _ignored_key(str(k))}
    if isinstance(value, list):
        return [_normalise(v, roots) for v in value]
    if isinstance(value, str):
        return _UUID.sub("<uuid>", _DIGEST.sub("<sha256>", _paths(value, roots)))
    return value


def _paths(text: str, roots: Sequence[tuple[str, str]]) -> str:
    """``text`` with the trees' and run folders' paths replaced (FITS cards: nothing else)."""
    for root, name in roots:
        text = text.replace(root, name)
    return text


def _first_json_difference(a: Any, b: Any, where: str = "") -> str | None:
    if type(a) is not type(b):
        return f"{where or '/'}: {_fmt(a)} != {_fmt(b)}"
    if isinstance(a, dict):
        for key in sorted(set(a) | set(b), key=str):
            if key not in a or key not in b:
                return f"{where}/{key}: only in {'after' if key not in a else 'before'}"
            diff = _first_json_difference(a[key], b[key], f"{where}/{key}")
            if diff:
                return diff
        return None
    if isinstance(a, list):
        if len(a) != len(b):
            return f"{where or '/'}: length {len(a)} != {len(b)}"
        for i, (x, y) in enumerate(zip(a, b)):
            diff = _first_json_difference(x, y, f"{where}[{i}]")
            if diff:
                return diff
        return None
    if isinstance(a, float) and math.isnan(a) and math.isnan(b):
        return None
    return None if a == b else f"{where or '/'}: {_fmt(a)} != {_fmt(b)}"


def _json_or_text(value: Any) -> Any:
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    if isinstance(value, str) and value[:1] in "{[":
        try:
            return json.loads(value)
        except ValueError:
            return value
    return value


def compare_fits(a: Path, b: Path, roots: Sequence[tuple[str, str]]) -> str | None:
    from astropy.io import fits

    with fits.open(a, memmap=False) as fa, fits.open(b, memmap=False) as fb:
        if len(fa) != len(fb):
            return f"{len(fa)} HDUs != {len(fb)}"
        for i, (ha, hb) in enumerate(zip(fa, fb)):
            cards = []
            for h in (ha.header, hb.header):
                cards.append(
                    [
                        (
                            c.keyword,
                            _paths(c.value, roots) if isinstance(c.value, str) else c.value,
                            c.comment,
                        )
                        for c in h.cards
                        if c.keyword not in IGNORED_CARDS
                    ]
                )
            for k, (ca, cb) in enumerate(zip(*cards)):
                if ca != cb:
                    return (
                        f"HDU {i} header card {k}: {ca[0]} = {_fmt(ca[1])} / {ca[2]!r} != "
                        f"{cb[0]} = {_fmt(cb[1])} / {cb[2]!r}"
                    )
            if len(cards[0]) != len(cards[1]):
                return f"HDU {i}: {len(cards[0])} header cards != {len(cards[1])}"
            da, db = ha.data, hb.data
            if (da is None) != (db is None):
                return f"HDU {i}: data in one file only"
            if da is None:
                continue
            if isinstance(ha, (fits.BinTableHDU, fits.TableHDU)):
                if da.columns.names != db.columns.names:
                    return f"HDU {i}: columns {da.columns.names} != {db.columns.names}"
                if len(da) != len(db):
                    return f"HDU {i}: {len(da)} rows != {len(db)}"
                for name in da.columns.names:
                    diff = _first_array_difference(
                        np.asarray(da[name]), np.asarray(db[name]), table=True
                    )
                    if diff:
                        return f"HDU {i} column {name} {diff}"
            else:
                diff = _first_array_difference(np.asarray(da), np.asarray(db))
                if diff:
                    return f"HDU {i} image (numpy order) {diff}"
    return None


def _h5_attrs(obj: Any, roots: Sequence[tuple[str, str]]) -> dict[str, Any]:
    out = {}
    for key, val in obj.attrs.items():
        if _ignored_key(key):
            continue
        val = _json_or_text(val)
        if isinstance(val, np.ndarray):
            val = val.tolist()
        elif isinstance(val, np.generic):
            val = val.item()
        out[key] = _normalise(val, roots)
    return out


def compare_hdf5(a: Path, b: Path, roots: Sequence[tuple[str, str]]) -> str | None:
    import h5py

    with h5py.File(a, "r") as fa, h5py.File(b, "r") as fb:
        names: list[list[str]] = [[], []]
        fa.visit(names[0].append)
        fb.visit(names[1].append)
        if names[0] != names[1]:
            only = sorted(set(names[0]) ^ set(names[1]))
            return f"objects differ: {only[:5] if only else 'order'}"
        for name in ["/", *names[0]]:
            oa, ob = fa[name], fb[name]
            if isinstance(oa, h5py.Dataset) != isinstance(ob, h5py.Dataset):
                return f"{name}: dataset in one file, group in the other"
            if isinstance(oa, h5py.Dataset):
                diff = _first_array_difference(np.asarray(oa[()]), np.asarray(ob[()]))
                if diff:
                    return f"dataset {name} {diff}"
            diff = _first_json_difference(
                _h5_attrs(oa, roots), _h5_attrs(ob, roots), f"{name} attrs"
            )
            if diff:
                return diff
    return None


def compare_json(a: Path, b: Path, roots: Sequence[tuple[str, str]]) -> str | None:
    return _first_json_difference(
        _normalise(json.loads(a.read_text()), roots), _normalise(json.loads(b.read_text()), roots)
    )


def _text_lines(path: Path, roots: Sequence[tuple[str, str]]) -> list[str]:
    text = _normalise(path.read_text(errors="replace"), roots)
    return [line for line in text.splitlines() if not _TEXT_DROP.search(line)]


def compare_text(a: Path, b: Path, roots: Sequence[tuple[str, str]]) -> str | None:
    la, lb = _text_lines(a, roots), _text_lines(b, roots)
    for i, (x, y) in enumerate(zip(la, lb)):
        if x != y:
            return f"line {i + 1} (of the kept lines): {x.strip()!r} != {y.strip()!r}"
    if len(la) != len(lb):
        return f"{len(la)} lines != {len(lb)}"
    return None


def _kind(path: Path) -> Callable[[Path, Path, Sequence[tuple[str, str]]], str | None]:
    with open(path, "rb") as f:
        magic = f.read(9)
    if magic == b"SIMPLE  =":
        return compare_fits
    if magic[:8] == b"\x89HDF\r\n\x1a\n":
        return compare_hdf5
    if path.suffix == ".json":
        return compare_json
    return compare_text


def _products(run: Path) -> Iterator[str]:
    for p in sorted(run.rglob("*")):
        rel = p.relative_to(run).as_posix()
        if p.is_file() and not rel.startswith(("in/", "logs/")):
            yield rel


def compare_trees(before: Tree, after: Tree) -> bool:
    """Print one line per product; True when all are identical."""
    roots = [(str(t.run), "<RUN>") for t in (before, after)] + [
        (str(t.path), "<TREE>") for t in (before, after)
    ]
    ok = True
    print("\n== inputs (copied from each tree)")
    for src, name in TREE_INPUTS:
        pa, pb = before.run / name, after.run / name
        if not pa.is_file() or not pb.is_file():
            status = f"MISSING in {'before' if not pa.is_file() else 'after'} ({src})"
        elif pa.read_bytes() == pb.read_bytes():
            status = "same"
        else:
            status = "CHANGED between the trees (differences below may come from it)"
        print(f"  {name:<40} {status}")
    print("\n== products")
    names = sorted(set(_products(before.run)) | set(_products(after.run)))
    width = max((len(n) for n in names), default=10)
    for name in names:
        pa, pb = before.run / name, after.run / name
        if NOT_COMPARED.search(name):
            print(f"  {name:<{width}}  not compared (figure)")
            continue
        if not pa.exists() or not pb.exists():
            ok = False
            print(
                f"  {name:<{width}}  DIFFERENT: only in {'after' if not pa.exists() else 'before'}"
            )
            continue
        try:
            diff = _kind(pa)(pa, pb, roots)
        except Exception as exc:  # an unreadable product counts as a difference
            diff = f"cannot compare: {type(exc).__name__}: {exc}"
        ok &= diff is None
        print(f"  {name:<{width}}  {'identical' if diff is None else 'DIFFERENT: ' + diff}")
    for tree in (before, after):
        for step, why in tree.failed.items():
            ok = False
            print(f"  step {step!r} FAILED in {tree.label}: {why}")
    return ok


def print_times(before: Tree, after: Tree) -> None:
    w = max(len(step.name) for step in WORKFLOW)
    print(f"\n== wall time per step (s)\n  {'step':<{w}} {'before':>8} {'after':>8}")
    for step in WORKFLOW:
        t0, t1 = before.times.get(step.name, math.nan), after.times.get(step.name, math.nan)
        print(f"  {step.name:<{w}} {t0:8.1f} {t1:8.1f}")
    print(f"  {'total':<{w}} {sum(before.times.values()):8.1f} {sum(after.times.values()):8.1f}")


# --------------------------------------------------------------------------- main


def _describe(ref: str) -> str:
    try:
        return _git("rev-parse", "--short", f"{ref}^{{commit}}")
    except subprocess.CalledProcessError:
        raise SystemExit(f"not a commit of {REPO}: {ref}") from None


def _make_tree(label: str, ref: str | None, root: Path) -> Tree:
    run = root / f"run-{label}"
    if ref is None:
        return Tree(label, REPO, run, worktree=False)
    if Path(ref).is_dir():
        return Tree(label, Path(ref).resolve(), run, worktree=False)
    commit = _describe(ref)
    path = root / f"tree-{label}"
    _git("worktree", "add", "--detach", str(path), commit)
    return Tree(label, path, run, worktree=True)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=(
            "Run one small workflow of every megalut subcommand in two source trees and check "
            "that every product is identical (FITS, HDF5, JSON, text; provenance cards such as "
            "dates, versions and model uuids/sha256 excepted). Exit 0: all identical; 1: some "
            "differ."
        ),
        epilog=(
            "Example: python benchmarks/compare_products.py --before HEAD  "
            "(HEAD against the working tree)"
        ),
    )
    parser.add_argument(
        "--before",
        required=True,
        metavar="COMMIT",
        help="commit of the reference tree (checked out with git worktree add --detach)",
    )
    parser.add_argument(
        "--after",
        metavar="COMMIT_OR_WORKTREE",
        help="commit (checked out as a worktree) or an existing source folder to compare; "
        f"default: the working tree {REPO}",
    )
    parser.add_argument(
        "--keep",
        metavar="DIR",
        type=Path,
        help="keep the run folders (products, logs) in this new folder; default: a temporary "
        "folder, removed at the end",
    )
    parser.add_argument(
        "--step-timeout",
        type=float,
        default=600.0,
        metavar="S",
        help="seconds after which a step is stopped and counted as failed (default: 600)",
    )
    args = parser.parse_args(argv)
    for ref in (args.before, args.after):
        if ref is not None and not Path(ref).is_dir():
            try:
                _git("rev-parse", "--verify", "--quiet", f"{ref}^{{commit}}")
            except subprocess.CalledProcessError:
                parser.error(f"not a commit of {REPO} (nor a folder): {ref}")

    if args.keep is not None:
        if args.keep.exists() and any(args.keep.iterdir()):
            parser.error(f"--keep {args.keep}: folder exists and is not empty")
        args.keep.mkdir(parents=True, exist_ok=True)
        root = args.keep.resolve()
    else:
        root = Path(tempfile.mkdtemp(prefix="megalut-products-"))
    trees: list[Tree] = []
    try:
        psf = root / "psf.fits"
        _write_psf(psf)
        _write_meds(root)
        for label, ref in (("before", args.before), ("after", args.after)):
            trees.append(_make_tree(label, ref, root))
        before, after = trees
        print(f"before: {args.before} ({_describe(args.before)}) in {before.path}")
        after_name = args.after
        if args.after is None:
            changed = _git("status", "--short", "--untracked-files=normal").splitlines()
            after_name = f"working tree ({len(changed)} files modified or untracked against HEAD)"
        print(f"after:  {after_name} in {after.path}\nrun folders under {root}\n", flush=True)
        for tree in trees:
            _prepare(tree, psf)
            cache = root / f"cache-{tree.label}"
            (cache / "megalut").mkdir(parents=True)
            run_workflow(tree, cache, args.step_timeout)
        identical = compare_trees(before, after)
        print_times(before, after)
        print(f"\n{'ALL IDENTICAL' if identical else 'SOME PRODUCTS DIFFER'}")
        return 0 if identical else 1
    finally:
        for tree in trees:
            if (
                tree.worktree
                and subprocess.run(
                    ["git", "worktree", "remove", "--force", str(tree.path)],
                    cwd=REPO,
                    capture_output=True,
                ).returncode
                != 0
            ):
                shutil.rmtree(tree.path, ignore_errors=True)
                subprocess.run(["git", "worktree", "prune"], cwd=REPO, capture_output=True)
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)
        else:
            print(f"kept: {root}")


if __name__ == "__main__":
    sys.exit(main())
