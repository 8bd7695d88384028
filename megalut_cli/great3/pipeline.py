"""The per-subfield pipeline of a GREAT3 constant-shear branch (paper Sect. 8), run by ``megalut run``.

A *branch pipeline file* is a TOML file with a top-level ``[branch]`` table (reference:
``docs/great3.md``). As the paper does, every subfield is processed on its own, with its
own PSF and noise, and no PSF features; a subfield is one work unit (``-j``, Dask), run
serially inside:

1. measure the subfield (``image-SSS-E.fits`` at the centres of ``galaxy_catalog-SSS``,
   0-indexed) and its star field (``starfield_image-SSS-E.fits``, star by star);
2. simulate the point-training set ``tp`` (the ellipticity shortcut: no shear, noiseless,
   10 realizations per case differing by their sub-pixel offset, Table 3 "uniform") and
   the weight-training set ``tw`` (90-degree pairs, Table 3 "mock", Gaussian noise of the
   median ``skymad`` of the subfield), both with a random star of the subfield's star
   field per case as the PSF (``psf.type = "stamp"``);
3. train one point committee per component with MSB on ``tp`` (features with ``{i}``
   replaced by the component, so ``adamom_g1`` for g1: the paper's four features), taken
   as the shear estimator (the ellipticity shortcut), then one weight committee per
   component with MSWB on ``tw``;
4. predict the subfield's galaxies and average them (weighted, by default) into the
   subfield's line of the submission.

The work folder gets ``subfields/SSS/`` per subfield (``features.fits``, ``stars.fits``,
``model.h5``, ``shears.fits``, ``subfield.json``; ``tp.fits`` and ``tw.fits`` with
``output.keep_sets``), then ``shears.fits`` (every galaxy of the branch with its
estimates, weights and a ``subfield`` column), ``submission.txt`` (``subfield g1 g2``),
``manifest.json`` and, when the branch has a truth folder, ``evaluation.json`` (m, c in
both frames and ``Q_c``). Each subfield is written into a temporary folder renamed into
place when complete; its seeds derive from the pipeline's seeds and the subfield index
only, so results do not depend on ``-j`` or the cluster.
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import logging
import math
import os
import re
import shutil
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from megalut_cli import __version__
from megalut_cli import flags as fl
from megalut_cli.engine import DEFAULT_ENGINE, ENGINES
from megalut_cli.errors import ConfigError, InputError, MegalutError
from megalut_cli.great3 import layout as L
from megalut_cli.nn.options import OPTION as TRAIN_OPTION
from megalut_cli.nn.train import POINT_ITERATIONS, WEIGHT_ITERATIONS
from megalut_cli.pipeline_config import TrainPointSpec, TrainWeightSpec
from megalut_cli.progress import Progress, no_progress
from megalut_cli.schema import Table, resolve_path
from megalut_cli.seeding import STREAM_SUBFIELD, int_seed_for

log = logging.getLogger("megalut")

KINDS = ("ground", "space")
SET_NAMES = ("tp", "tw")
#: Pipeline seeds when the file gives none (all different).
DEFAULT_SEEDS = {"tp": 1, "tw": 2, "train_point": 3, "train_weight": 4}
#: The paper's four features per component (Sect. 8.2); ``{i}`` is the component, 1 or 2.
DEFAULT_FEATURES = ["adamom_g{i}", "adamom_sigma", "adamom_flux", "adamom_rho4"]
#: Targets of the point committees: the ellipticity shortcut, or a shear-structured ``tp``.
TARGET_CHOICES = (("tru_e1", "tru_e2"), ("tru_g1", "tru_g2"))

SUBFIELDS_DIR = "subfields"
SHEARS = "shears.fits"
SUBMISSION = "submission.txt"
MANIFEST = "manifest.json"
EVALUATION = "evaluation.json"
UNIT_RECORD = "subfield.json"
MANIFEST_FORMAT = "megalut.great3-run"
#: Products of a subfield folder (``tp.fits``, ``tw.fits`` too with ``keep_sets``).
UNIT_PRODUCTS = ("features.fits", "stars.fits", "model.h5", "shears.fits")
SHEARS_FORMAT = "megalut.predictions"

_TOP_KEYS = {"description", "engine", "branch", "tp", "tw", "train_point", "train_weight", "output"}
_BRANCH_KEYS = {"path", "kind", "stamp_size", "epoch", "subfields", "strict", "truth", "sigma2_min"}
_SET_KEYS = {"config", "simulation", "n_cases", "n_realizations", "seed"}
_COMMON_TRAIN = {"features", "hidden", *TRAIN_OPTION}
_POINT_KEYS = _COMMON_TRAIN | {"targets", "cost", "select_cases", "init"}
_WEIGHT_KEYS = _COMMON_TRAIN | {"select"}
_OUTPUT_KEYS = {"weighted", "keep_sets"}

# --------------------------------------------------------------------------- Table 3

_RAYLEIGH = {"type": "rayleigh", "mode": 0.2, "min": 0.0, "max": 0.7}
_ANGLE = {"type": "uniform", "min": 0.0, "max": 180.0}


def _sersic(lo: float, hi: float) -> dict[str, Any]:
    return {"type": "grid", "min": lo, "max": hi, "step": 0.1}  # gridded, as the paper (Table 3, note a)


#: Galaxy distributions of the paper's Table 3: (kind, "uniform" | "mock") -> [galaxy] table.
TABLE3: dict[tuple[str, str], dict[str, Any]] = {
    ("ground", "uniform"): {
        "sersicn": _sersic(0.5, 4.0), "rad": {"type": "uniform", "min": 0.75, "max": 3.0},
        "flux": {"type": "uniform", "min": 10.0, "max": 100.0},
    },
    ("ground", "mock"): {
        "sersicn": _sersic(0.5, 2.5), "rad": {"type": "normal", "mean": 1.0, "sigma": 0.8, "min": 0.75, "max": 3.0},
        "flux": {"type": "normal", "mean": 15.0, "sigma": 20.0, "min": 10.0, "max": 200.0},
    },
    ("space", "uniform"): {
        "sersicn": _sersic(0.5, 4.0), "rad": {"type": "uniform", "min": 1.25, "max": 10.0},
        "flux": {"type": "uniform", "min": 10.0, "max": 100.0},
    },
    ("space", "mock"): {
        "sersicn": _sersic(0.5, 4.0), "rad": {"type": "normal", "mean": 2.5, "sigma": 3.5, "min": 1.25, "max": 10.0},
        "flux": {"type": "normal", "mean": 0.0, "sigma": 30.0, "min": 10.0, "max": 200.0},
    },
}


def default_set(name: str, kind: str, stamp_size: int) -> dict[str, Any]:
    """The default simulation config of set ``tp`` or ``tw`` for one subfield (paper Sect. 8.2).

    ``psf.path`` (the star field) and ``noise.sigma.path`` (the features) are filled in
    per subfield.
    """
    star_psf = {"type": "stamp", "path": "", "stamp_size": stamp_size, "index": "random"}
    galaxy = {"profile": "sersic", **copy.deepcopy(TABLE3[(kind, "uniform" if name == "tp" else "mock")]),
              "ellipticity": dict(_RAYLEIGH), "angle": dict(_ANGLE)}
    if name == "tp":
        return {
            "description": f"GREAT3 {kind} subfield: point-estimate training set (ellipticity shortcut, Table 3 uniform)",
            "structure": {"n_cases": 1000, "n_realizations": 10, "per_realization": [], "snc": "none",
                          "stamp_size": stamp_size, "offset": 0.5},
            "galaxy": galaxy, "psf": star_psf, "noise": {"type": "none"},
        }
    return {
        "description": f"GREAT3 {kind} subfield: weight training set (90-degree pairs, Table 3 mock)",
        "structure": {"n_cases": 200, "n_realizations": 1000, "per_realization": ["galaxy"], "snc": "pairs",
                      "stamp_size": stamp_size, "offset": 0.5},
        "shear": {"g1": {"type": "uniform", "min": -0.1, "max": 0.1}, "g2": {"type": "uniform", "min": -0.1, "max": 0.1}},
        "galaxy": galaxy, "psf": star_psf,
        "noise": {"type": "gaussian", "sigma": {"type": "measured", "path": "", "column": "skymad",
                                                "statistic": "median"}},
    }


# --------------------------------------------------------------------------- specification


@dataclass(frozen=True)
class SetTemplate:
    """A per-subfield simulation: its config (paths filled in per subfield) and base seed."""

    name: str
    raw: dict[str, Any]
    seed: int
    config_path: str  # where relative paths of the config are resolved
    source: str


@dataclass(frozen=True)
class BranchPipeline:
    """A validated branch pipeline file (overrides applied)."""

    path: str
    sha256: str
    overrides: tuple[str, ...]
    raw: dict[str, Any]
    description: str
    branch_dir: Path
    kind: str
    stamp_size: int
    epoch: int
    subfields: list[int]
    strict: bool
    truth: Path | None
    sigma2_min: float
    sets: dict[str, SetTemplate]
    point: TrainPointSpec  # features are templates: "{i}" -> 1, 2
    weight: TrainWeightSpec
    weighted: bool
    keep_sets: bool
    problems: dict[int, str] = field(default_factory=dict)  # subfields with missing files
    engine: str = DEFAULT_ENGINE  # stamp engine of measure and simulate (megalut_cli.engine)


def is_branch_pipeline(path: str | os.PathLike) -> bool:
    """Whether the TOML file ``path`` is a branch pipeline (has a top-level ``[branch]``)."""
    from megalut_cli.sim.config import read_toml

    raw, _ = read_toml(path)
    return "branch" in raw


def component_features(templates: Sequence[str], i: int) -> list[str]:
    """Feature names of component ``i`` (1 or 2): ``{i}`` replaced, duplicates dropped."""
    return list(dict.fromkeys(t.replace("{i}", str(i)) for t in templates))


def subfield_seed(seed: int, subfield: int, *keys: int) -> int:
    """The seed of a subfield's draw (``keys`` name the draw): independent of the workers."""
    return int_seed_for(seed, STREAM_SUBFIELD, subfield, *keys)


def parse_subfields(value: Any, key: str = "branch.subfields") -> list[int] | None:
    """``"all"`` -> None; a list of indices, an index, or a text like ``"0-19,25"`` -> sorted indices."""
    if value is None or value == "all":
        return None
    items: list[int] = []
    if isinstance(value, int) and not isinstance(value, bool):
        items = [value]
    elif isinstance(value, list) and value and all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        items = list(value)
    elif isinstance(value, str) and value.strip():
        for part in value.split(","):
            m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", part)
            if not m:
                raise ConfigError(f"{key}: cannot read {part.strip()!r} (expected e.g. \"0-19,25\")")
            a, b = int(m.group(1)), int(m.group(2) if m.group(2) is not None else m.group(1))
            if b < a:
                raise ConfigError(f"{key}: empty range {part.strip()!r}")
            items += range(a, b + 1)
    else:
        raise ConfigError(f"{key}: expected \"all\", a list of subfield indices or a text like \"0-19\", got {value!r}")
    if any(v < 0 for v in items):
        raise ConfigError(f"{key}: subfield indices must be >= 0")
    return sorted(set(items))


def _find_path(text: str, key: str, base_dir: Path | None, want_dir: bool) -> Path:
    """A path from the pipeline file (:func:`megalut_cli.schema.resolve_path`)."""
    return resolve_path(text, key, base_dir, folder=want_dir)


def _load_set(name: str, top: Any, kind: str, size: int, base_dir: Path | None, pipe_path: str) -> SetTemplate:
    from megalut_cli.pipeline_config import merge_tables
    from megalut_cli.sim.config import read_toml

    t = Table(top.data.get(name), name, _SET_KEYS)
    if "config" in t.data:
        cfg = _find_path(t.get_str("config", None) or "", t.key("config"), base_dir, want_dir=False)
        raw, _ = read_toml(cfg)
        config_path, source = str(cfg), str(cfg)
    else:
        raw, config_path, source = default_set(name, kind, size), pipe_path, f"default {kind} {name}"
    over = t.data.get("simulation")
    if over is not None:
        if not isinstance(over, Mapping):
            raise ConfigError(f"{t.key('simulation')}: expected a table")
        raw = merge_tables(raw, over)
        source += f" + {name}.simulation"
    structure = raw.setdefault("structure", {})
    if not isinstance(structure, dict):
        raise ConfigError(f"{name}: structure: expected a table")
    for k in ("n_cases", "n_realizations"):
        v = t.get_int(k, None, 1)
        if v is not None:
            structure[k] = v
    seed = t.get_int("seed", DEFAULT_SEEDS[name], 0)
    return SetTemplate(name, raw, int(seed or 0), config_path, source)


def set_config(tpl: SetTemplate, starfield: str | os.PathLike, features: str | os.PathLike | None) -> Any:
    """The validated simulation config of ``tpl`` for one subfield: a ``stamp`` PSF takes
    the subfield's star field, a ``measured`` noise its features catalog (``None``: a
    stand-in value of 1, to check the config before anything is measured)."""
    from megalut_cli.sim.config import is_measured, validate_config

    raw = copy.deepcopy(tpl.raw)
    psf = raw.get("psf")
    if isinstance(psf, dict) and psf.get("type") == "stamp":
        psf["path"] = str(starfield)
    noise = raw.get("noise")
    if isinstance(noise, dict) and is_measured(noise.get("sigma")):
        if features is None:
            noise["sigma"] = 1.0
        else:
            noise["sigma"]["path"] = str(features)
    try:
        return validate_config(raw, path=tpl.config_path, sha256=hashlib.sha256(
            json.dumps(raw, sort_keys=True, default=str).encode()).hexdigest())
    except MegalutError as err:
        raise type(err)(f"{tpl.name} ({tpl.source}): {err}") from None


def _check_features(names: Sequence[str], key: str) -> None:
    from megalut_cli.measure.features import FEATURE_COLUMNS

    allowed = [c for c in FEATURE_COLUMNS if c != "flags"]
    for i in (1, 2):
        bad = [f for f in component_features(names, i) if f not in allowed]
        if bad:
            raise ConfigError(
                f"{key}: {bad[0]!r} is not a measured feature (allowed: {', '.join(allowed)}; "
                "'{i}' stands for the component, e.g. adamom_g{i})"
            )


def parse_branch_pipeline(raw: Mapping[str, Any], path: str = "<pipeline>", sha256: str = "",
                          overrides: Sequence[str] = (), base_dir: Path | None = None) -> BranchPipeline:
    """Validate a parsed branch pipeline (after ``key=value`` overrides); check the branch folder."""
    from megalut_cli.pipeline_config import selection_expression, train_options_from
    from megalut_cli.shear.bias import GREAT3_SIGMA2_MIN_GROUND, GREAT3_SIGMA2_MIN_SPACE
    from megalut_cli.sim.config import apply_overrides

    raw = apply_overrides(dict(raw), overrides)
    top = Table(raw, "", _TOP_KEYS)
    description = top.data.get("description", "")
    if not isinstance(description, str):
        raise ConfigError("description: expected a string")
    b = Table(top.data.get("branch"), "branch", _BRANCH_KEYS)
    if "path" not in b.data:
        raise ConfigError("branch.path: missing (the branch folder, in the GREAT3 layout)")
    branch_dir = _find_path(b.get_str("path", None) or "", "branch.path", base_dir, want_dir=True)
    kind = b.get_str("kind", "ground", KINDS) or "ground"
    size = b.get_int("stamp_size", L.STAMP_SIZES[kind], 3) or L.STAMP_SIZES[kind]
    epoch = b.get_int("epoch", 0, 0) or 0
    strict = b.get_bool("strict", True)
    sigma2_min = b.get_float("sigma2_min", GREAT3_SIGMA2_MIN_GROUND if kind == "ground" else GREAT3_SIGMA2_MIN_SPACE,
                             0.0, math.inf, lo_open=True)
    truth_value = b.data.get("truth", True)
    truth: Path | None = None
    if truth_value is True:
        truth = branch_dir / "truth" if (branch_dir / "truth").is_dir() else None
    elif isinstance(truth_value, str) and truth_value:
        truth = _find_path(truth_value, "branch.truth", base_dir, want_dir=True)
    elif truth_value is not False:
        raise ConfigError(f"branch.truth: expected a folder, true (the branch's truth/ if any) or false, got {truth_value!r}")

    available = L.find_subfields(branch_dir, epoch)
    wanted = parse_subfields(b.data.get("subfields", "all"))
    if wanted is None:
        if not available:
            raise InputError(f"{branch_dir}: no {L.image_name(0, epoch).replace('000', 'SSS')} file: not a GREAT3 branch folder")
        subfields = available
    else:
        subfields = wanted
    problems: dict[int, str] = {}
    for s in subfields:
        try:
            L.subfield_files(branch_dir, s, epoch)
        except InputError as err:
            problems[s] = str(err)

    sets = {n: _load_set(n, top, kind, size, base_dir, path) for n in SET_NAMES}
    if sets["tp"].seed == sets["tw"].seed:
        raise ConfigError(f"tw.seed: {sets['tw'].seed} is also the seed of tp; every set needs its own seed")

    tp = Table(top.data.get("train_point"), "train_point", _POINT_KEYS)
    targets = tp.get_str_list("targets", list(TARGET_CHOICES[0])) or []
    if tuple(targets) not in TARGET_CHOICES:
        raise ConfigError(
            "train_point.targets: expected [\"tru_e1\", \"tru_e2\"] (the ellipticity shortcut) or "
            f"[\"tru_g1\", \"tru_g2\"], got {targets!r}"
        )
    point = TrainPointSpec(
        features=tp.get_str_list("features", DEFAULT_FEATURES) or [],
        targets=targets,
        hidden=tp.get_int_list("hidden", [5, 5]),
        cost=tp.get_str("cost", "msb", ("msb", "mse")) or "msb",
        select_cases=selection_expression(tp, "select_cases", True),
        init=tp.get_str("init", "normal", ("normal", "identity")) or "normal",
        options=train_options_from(tp, POINT_ITERATIONS, DEFAULT_SEEDS["train_point"]),
    )
    _check_features(point.features, "train_point.features")
    tw = Table(top.data.get("train_weight"), "train_weight", _WEIGHT_KEYS)
    weight = TrainWeightSpec(
        features=tw.get_str_list("features", point.features) or [],
        hidden=tw.get_int_list("hidden", [5, 5]),  # "for all estimators ... two hidden layers" (Sect. 8.2)
        select=selection_expression(tw, "select", False),
        options=train_options_from(tw, WEIGHT_ITERATIONS, DEFAULT_SEEDS["train_weight"]),
    )
    _check_features(weight.features, "train_weight.features")
    out = Table(top.data.get("output"), "output", _OUTPUT_KEYS)
    pipe = BranchPipeline(
        path=path, sha256=sha256, overrides=tuple(overrides), raw=json.loads(json.dumps(raw, default=str)),
        description=description, branch_dir=branch_dir, kind=kind, stamp_size=int(size), epoch=int(epoch),
        subfields=subfields, strict=strict, truth=truth, sigma2_min=sigma2_min, sets=sets, point=point,
        weight=weight, weighted=out.get_bool("weighted", True), keep_sets=out.get_bool("keep_sets", False),
        problems=problems, engine=top.get_str("engine", DEFAULT_ENGINE, tuple(ENGINES)) or DEFAULT_ENGINE,
    )
    _check_templates(pipe)
    return pipe


def _check_templates(pipe: BranchPipeline) -> None:
    """Validate both simulation configs with the star field of a subfield (exit 2 on errors)."""
    ok = [s for s in pipe.subfields if s not in pipe.problems]
    if not ok:
        return  # every subfield is missing files: reported when running
    starfield = L.subfield_files(pipe.branch_dir, ok[0], pipe.epoch)["starfield"]
    for name, tpl in pipe.sets.items():
        try:
            cfg = set_config(tpl, starfield, None)
        except InputError:
            continue  # a bad star field: that subfield fails when it runs
        s = cfg.structure
        if s.stamp_size != pipe.stamp_size:
            raise ConfigError(f"{name}: structure.stamp_size {s.stamp_size} differs from the branch's {pipe.stamp_size}")
        if s.n_cases < 2:
            raise ConfigError(f"{name}.n_cases: at least 2 cases are needed, got {s.n_cases}")
    tw_raw = pipe.sets["tw"].raw
    if not tw_raw.get("shear"):
        raise ConfigError("tw: the weight-training set needs a [shear] distribution (MSWB learns the shear)")
    if pipe.point.targets[0] == "tru_g1" and not pipe.sets["tp"].raw.get("shear"):
        raise ConfigError("train_point.targets: tru_g1, tru_g2 need a [shear] in tp (or use tru_e1, tru_e2)")


def load_branch_pipeline(path: str | os.PathLike, overrides: Sequence[str] = ()) -> BranchPipeline:
    """Read and validate a branch pipeline file."""
    from megalut_cli.sim.config import read_toml

    raw, sha = read_toml(path)
    return parse_branch_pipeline(raw, str(path), sha, overrides, Path(path).resolve().parent)


# --------------------------------------------------------------------------- one subfield


def _sha_text(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def unit_params(pipe: BranchPipeline, subfield: int) -> dict[str, Any]:
    """Everything that determines a subfield's products (its key, with the input hashes)."""
    return {
        "subfield": subfield,
        "kind": pipe.kind,
        "stamp_size": pipe.stamp_size,
        "epoch": pipe.epoch,
        "strict": pipe.strict,
        "keep_sets": pipe.keep_sets,
        "sets": {n: {"raw": t.raw, "seed": subfield_seed(t.seed, subfield)} for n, t in pipe.sets.items()},
        "train_point": asdict(pipe.point),
        "train_weight": asdict(pipe.weight),
        "engine": pipe.engine,
    }


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """Hide the INFO lines of the inner steps (kept with -v)."""
    loggers = [logging.getLogger(n) for n in ("megalut", "megalut_cli")]
    if logging.getLogger("megalut").getEffectiveLevel() < logging.INFO:
        yield
        return
    old = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.WARNING)
    try:
        yield
    finally:
        for lg, lv in zip(loggers, old):
            lg.setLevel(lv)


def _fingerprints(folder: Path, names: Sequence[str]) -> dict[str, dict[str, int]]:
    out = {}
    for n in names:
        st = (folder / n).stat()
        out[n] = {"size": st.st_size, "mtime_ns": st.st_mtime_ns}
    return out


def _up_to_date(folder: Path, key: str) -> dict[str, Any] | None:
    """The record of a finished subfield folder if its key is ``key`` and its products unchanged."""
    try:
        rec = json.loads((folder / UNIT_RECORD).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(rec, dict) or rec.get("key") != key or not isinstance(rec.get("products"), dict):
        return None
    for name, fp in rec["products"].items():
        p = folder / name
        if not p.is_file() or not isinstance(fp, dict):
            return None
        st = p.stat()
        if fp.get("size") != st.st_size or fp.get("mtime_ns") != st.st_mtime_ns:
            return None
    return rec


def _check_measurement(feats: Any, files: Mapping[str, Path], strict: bool) -> None:
    """Errors naming the file for off-image centres and bad pixels (``strict``) and an
    unmeasurable subfield."""
    flags = np.asarray(feats["flags"])
    n = len(flags)
    off = int(np.count_nonzero(flags & fl.STAMP_OFF_IMAGE))
    bad = int(np.count_nonzero(flags & fl.BAD_PIXELS))
    if strict and off:
        raise InputError(f"{files['catalog']}: {off} of {n} galaxy centre(s) fall off {files['image'].name} "
                         "(wrong stamp size or centres?)")
    if strict and bad:
        raise InputError(f"{files['image']}: {bad} of {n} galaxy stamp(s) have NaN or infinite pixels")
    if not np.any(flags == 0):
        raise InputError(f"{files['image']}: no galaxy of the subfield could be measured ({n} flagged)")
    for what, k in (("off the image", off), ("with NaN or infinite pixels", bad)):
        if k:
            log.warning("%s: %d galaxy stamp(s) %s: flagged, left out", files["image"], k, what)


def _relabel(path: Path, component: int) -> Any:
    """The single point committee of ``path`` as the shear estimator of ``component``."""
    from megalut_cli.nn.model import ShearModel

    model = ShearModel.load(path)
    (comm,) = model.point.values()
    if comm.target != f"tru_g{component}":
        comm.training = {**comm.training, "estimates": f"tru_g{component}", "trained_on": comm.target,
                         "note": "ellipticity shortcut (paper Sects. 4.3, 8.2): the ellipticity estimate is the shear estimate"}
        comm.target = f"tru_g{component}"
    return ShearModel(point={comm.target: comm}, provenance=model.provenance)


def _train(pipe: BranchPipeline, subfield: int, tp_path: Path, tw_path: Path, scratch: Path, model_path: Path) -> None:
    """Point committees (per component) on tp, relabelled as shear estimators; weights on tw; one model."""
    from megalut_cli.nn.model import ShearModel
    from megalut_cli.provenance import command_line, software_versions
    from megalut_cli.training import train_point, train_weight

    point, weight = {}, {}
    for i in (1, 2):
        pt, pw = pipe.point, pipe.weight
        e_path, g_path, w_path = scratch / f"point-{i}.h5", scratch / f"point-g{i}.h5", scratch / f"weight-{i}.h5"
        train_point(tp_path, e_path, features=component_features(pt.features, i), targets=[pt.targets[i - 1]],
                    hidden=pt.hidden, cost=pt.cost, select_cases=pt.select_cases, init_scheme=pt.init,
                    options=replace(pt.options, seed=subfield_seed(pt.options.seed, subfield, i)))
        _relabel(e_path, i).save(g_path, overwrite=True)
        model = train_weight(tw_path, g_path, w_path, features=component_features(pw.features, i), hidden=pw.hidden,
                             select=pw.select, options=replace(pw.options, seed=subfield_seed(pw.options.seed, subfield, i)))
        point.update(model.point)
        weight.update(model.weight)
    prov = {"command": "run (GREAT3 branch)", "argv": command_line(), "versions": software_versions(),
            "subfield": subfield, "inputs": {"tp": str(tp_path.name), "tw": str(tw_path.name)}}
    ShearModel(point=point, weight=weight, provenance=prov).save(model_path, overwrite=True)


def run_subfield(job: Mapping[str, Any]) -> dict[str, Any]:
    """Work unit: the whole pipeline of one subfield; returns its summary (see :func:`run_branch`).

    ``job``: ``pipe``, ``subfield``, ``workdir``, ``skip_existing``, ``keep_going``. With
    ``keep_going`` an error is returned (``{"subfield", "error"}``) instead of raised.
    """
    try:
        return _run_subfield(job["pipe"], int(job["subfield"]), Path(job["workdir"]), bool(job["skip_existing"]))
    except Exception as err:
        if not job.get("keep_going"):
            if isinstance(err, MegalutError):
                raise type(err)(_about(job["subfield"], str(err))) from None
            raise
        text = str(err) if isinstance(err, MegalutError) else f"internal error ({type(err).__name__}: {err})"
        return {"subfield": int(job["subfield"]), "error": text}


def _about(subfield: int, message: str) -> str:
    """``message`` prefixed with the subfield unless it names it already."""
    return message if f"subfield {subfield}:" in message else f"subfield {subfield}: {message}"


def _run_subfield(pipe: BranchPipeline, s: int, workdir: Path, skip_existing: bool) -> dict[str, Any]:
    from megalut_cli.atomic import replace_folder
    from megalut_cli.catalog import read_catalog
    from megalut_cli.measure.measure import measure_file
    from megalut_cli.provenance import sha256_file
    from megalut_cli.shear.predict import predict_catalog
    from megalut_cli.sim.simulate import simulate

    if s in pipe.problems:
        raise InputError(pipe.problems[s])
    files = L.subfield_files(pipe.branch_dir, s, pipe.epoch)
    params = unit_params(pipe, s)
    inputs = {k: {"name": p.name, "sha256": sha256_file(p)} for k, p in files.items()}
    key = _sha_text({"params": params, "inputs": inputs, "megalut": __version__})
    final = workdir / SUBFIELDS_DIR / f"{s:03d}"
    if skip_existing:
        rec = _up_to_date(final, key)
        if rec is not None:
            return {**rec["summary"], "status": "skipped"}
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{s:03d}.", suffix=".tmp", dir=final.parent))
    tmp.chmod(0o755)  # mkdtemp's 0700 would follow the folder into place
    t0 = time.perf_counter()
    timings: dict[str, float] = {}

    def lap(name: str, t: float) -> None:
        timings[name] = round(time.perf_counter() - t, 3)

    try:
        scratch = tmp / "scratch"
        scratch.mkdir()
        with _quiet():
            t = time.perf_counter()
            feats = measure_file(files["image"], files["catalog"], tmp / "features.fits", stamp_size=pipe.stamp_size,
                                 origin=0, psf_path=files["starfield"], engine=pipe.engine)
            _check_measurement(feats, files, pipe.strict)
            measure_file(files["starfield"], None, tmp / "stars.fits", stamp_size=pipe.stamp_size, stars=True,
                         engine=pipe.engine)
            lap("measure", t)
            set_paths, noise_sigma = {}, None
            for name, tpl in pipe.sets.items():
                t = time.perf_counter()
                cfg = set_config(tpl, files["starfield"], tmp / "features.fits")
                set_paths[name] = (tmp if pipe.keep_sets else scratch) / f"{name}.fits"
                simulate(cfg, set_paths[name], measure=True, seed=params["sets"][name]["seed"], engine=pipe.engine)
                if name == "tw":
                    noise_sigma = float(cfg.noise.params["sigma"].bounds()[0]) if "sigma" in cfg.noise.params else None
                lap(f"simulate-{name}", t)
            t = time.perf_counter()
            _train(pipe, s, set_paths["tp"], set_paths["tw"], scratch, tmp / "model.h5")
            lap("train", t)
            t = time.perf_counter()
            predict_catalog(tmp / "features.fits", tmp / "model.h5", tmp / "shears.fits")
            lap("predict", t)
        shears = read_catalog(tmp / "shears.fits")
        means = {}
        for scheme, weighted in (("unweighted", False), ("weighted", True)):
            _, g1, g2, n_used = L.submission_from_catalog(shears, weighted=weighted, where=str(files["image"]))
            means[scheme] = {"g1": float(g1[0]), "g2": float(g2[0]), "n_used": int(n_used[0])}
        use = means["weighted" if pipe.weighted else "unweighted"]
        if not (math.isfinite(use["g1"]) and math.isfinite(use["g2"])):
            raise InputError(f"{files['image']}: no galaxy with a usable shear estimate")
        shutil.rmtree(scratch)
        summary = {
            "subfield": s, "n_galaxies": len(shears), "n_flagged": int(np.count_nonzero(np.asarray(shears["flags"]))),
            "noise_sigma": noise_sigma, "psf_adamom_sigma": float(np.asarray(feats["psf_adamom_sigma"])[0]),
            "means": means, "g1": use["g1"], "g2": use["g2"], "seconds": round(time.perf_counter() - t0, 3),
            "timings": timings, "status": "ran",
        }
        products = list(UNIT_PRODUCTS) + ([f"{n}.fits" for n in SET_NAMES] if pipe.keep_sets else [])
        record = {"format": MANIFEST_FORMAT, "key": key, "params": params, "inputs": inputs, "summary": summary,
                  "products": _fingerprints(tmp, products), "megalut": __version__}
        (tmp / UNIT_RECORD).write_text(json.dumps(record, indent=1, allow_nan=False) + "\n")
        replace_folder(tmp, final)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    log.info("subfield %d: g1 = %+.5f, g2 = %+.5f (%d galaxies, noise sigma %.4g) in %.0f s", s, summary["g1"],
             summary["g2"], summary["n_galaxies"], noise_sigma or 0.0, summary["seconds"])
    return summary


# --------------------------------------------------------------------------- the branch


@dataclass
class BranchRunResult:
    workdir: Path
    summaries: list[dict[str, Any]]
    failures: list[dict[str, Any]]
    evaluation: dict[str, Any] | None
    seconds: float
    products: list[str]


def _final_products(pipe: BranchPipeline) -> list[str]:
    return [SHEARS, SUBMISSION, MANIFEST] + ([EVALUATION] if pipe.truth is not None else [])


def check_workdir(pipe: BranchPipeline, workdir: Path, skip_existing: bool, overwrite: bool) -> None:
    """Fail early: a file where the folder should be, or products there without a flag."""
    if workdir.exists() and not workdir.is_dir():
        raise MegalutError(f"--workdir {workdir}: exists and is not a folder")
    if skip_existing or overwrite:
        return
    names = _final_products(pipe) + [f"{SUBFIELDS_DIR}/{s:03d}" for s in pipe.subfields]
    for name in names:
        if (workdir / name).exists():
            raise MegalutError(
                f"{workdir / name} exists; use --skip-existing to reuse the up-to-date subfields "
                "or --overwrite to redo every one"
            )


def _write_shears(path: Path, workdir: Path, subfields: Sequence[int], overwrite: bool) -> int:
    """Concatenate the subfields' predictions into one catalog with a ``subfield`` column (streamed)."""
    import fitsio

    from megalut_cli.atomic import atomic_output
    from megalut_cli.catalog import catalog_info, header_cards, read_catalog, write_table_hdu

    n = 0
    dtype = None
    _, _, header = catalog_info(workdir / SUBFIELDS_DIR / f"{subfields[0]:03d}" / "shears.fits")
    cards = {k: v for k, v in header.items() if k not in ("HISTORY", "MODEL", "MODELSHA", "SUBFIELD", "TEXTCAT")}
    cards["NSUBFLD"] = (len(subfields), "subfields in this catalog")
    history = header.get("HISTORY")
    with atomic_output(path, overwrite) as tmp, fitsio.FITS(str(tmp), "rw", clobber=True) as fits:
        for s in subfields:
            src = workdir / SUBFIELDS_DIR / f"{s:03d}" / "shears.fits"
            t = read_catalog(src)
            cols = {"subfield": np.full(len(t), s, dtype=np.int64)}
            cols.update({c: np.asarray(t[c]) for c in t.colnames if c != "subfield"})
            if dtype is None:
                dtype = np.dtype([(c, v.dtype.str, v.shape[1:]) if v.ndim > 1 else (c, v.dtype.str) for c, v in cols.items()])
            elif set(cols) != set(dtype.names):
                raise InputError(f"{src}: its columns differ from those of subfield {subfields[0]}")
            arr = np.zeros(len(t), dtype=dtype)
            for c in dtype.names:
                arr[c] = cols[c]
            if len(fits) < 2:
                write_table_hdu(fits, arr, header_cards(SHEARS_FORMAT, "1.0", cards, history, columns=dtype.names))
            else:
                fits[-1].append(arr)
            n += len(t)
    return n


def run_branch(
    pipe: BranchPipeline,
    workdir: str | os.PathLike,
    *,
    skip_existing: bool = False,
    overwrite: bool = False,
    keep_going: bool = False,
    nproc: int = 1,
    scheduler: str | None = None,
    progress: Progress | None = None,
) -> BranchRunResult:
    """Run every subfield of ``pipe`` (work units), then write the per-galaxy catalog, the
    submission, the manifest and (with a truth folder) the evaluation.

    Without ``keep_going`` the first failing subfield stops the run (no branch product is
    written; the subfields already finished stay in ``subfields/``). With it, the others
    complete and the products hold them; ``result.failures`` lists the failed ones (see
    :func:`failure_error`). Every subfield failing is an error.
    """
    wd = Path(workdir)
    check_workdir(pipe, wd, skip_existing, overwrite)
    if pipe.problems and not keep_going:
        s = next(iter(pipe.problems))
        raise InputError(_about(s, pipe.problems[s]))
    created = not wd.exists()
    wd.mkdir(parents=True, exist_ok=True)
    try:
        return _run_units(pipe, wd, skip_existing, keep_going, nproc, scheduler, progress)
    except BaseException:
        with contextlib.suppress(OSError):  # leave no empty folder behind a failed start
            (wd / SUBFIELDS_DIR).rmdir()
            if created:
                wd.rmdir()
        raise


def _run_units(pipe: BranchPipeline, wd: Path, skip_existing: bool, keep_going: bool, nproc: int,
               scheduler: str | None, progress: Progress | None) -> BranchRunResult:
    from megalut_cli.parallel import executor, map_units

    t0 = time.perf_counter()
    n = len(pipe.subfields)
    log.info("branch %s (%s, %d-pixel stamps): %d subfield(s) -> %s", pipe.branch_dir, pipe.kind, pipe.stamp_size, n, wd)
    tp, tw = (pipe.sets[k].raw.get("structure", {}) for k in SET_NAMES)
    log.info("per subfield: tp %s x %s stamps, tw %s x %s stamps; %d + %d members per component",
             tp.get("n_cases"), tp.get("n_realizations"), tw.get("n_cases"), tw.get("n_realizations"),
             pipe.point.options.members, pipe.weight.options.members)
    jobs = [{"pipe": pipe, "subfield": s, "workdir": str(wd.resolve()), "skip_existing": skip_existing,
             "keep_going": keep_going} for s in pipe.subfields]
    prog = progress or no_progress
    with executor(nproc, scheduler) as pool, prog("subfields", n) as update:
        results = map_units(run_subfield, jobs, pool, update)
    failures = [r for r in results if "error" in r]
    done = sorted((r for r in results if "error" not in r), key=lambda r: r["subfield"])
    for f in failures:
        log.error("subfield %d failed: %s", f["subfield"], f["error"])
    if not done:
        raise MegalutError(f"every subfield failed (first: subfield {failures[0]['subfield']}: {failures[0]['error']})")
    subs = [r["subfield"] for r in done]
    n_rows = _write_shears(wd / SHEARS, wd, subs, overwrite=True)
    L.write_submission(wd / SUBMISSION, subs, [r["g1"] for r in done], [r["g2"] for r in done], overwrite=True)
    evaluation = None
    products = [SHEARS, SUBMISSION]
    if pipe.truth is not None:
        from megalut_cli.atomic import write_json
        from megalut_cli.great3.evaluate import evaluate_branch

        if len(done) >= 2:
            with _quiet():
                evaluation = evaluate_branch(wd / SHEARS, pipe.truth, sigma2_min=pipe.sigma2_min)
            evaluation["submission"] = {"weighted": pipe.weighted, "path": SUBMISSION}
            write_json(wd / EVALUATION, evaluation, overwrite=True)
            products.append(EVALUATION)
        else:
            log.warning("%s: one subfield only: m and c cannot be fitted, no %s", pipe.truth, EVALUATION)
            (wd / EVALUATION).unlink(missing_ok=True)
    seconds = time.perf_counter() - t0
    _write_manifest(pipe, wd, done, failures, seconds)
    products.append(MANIFEST)
    log.info("%d subfield(s) done (%d skipped as up to date), %d failed; %d galaxies in %s; %.0f s",
             len(done), sum(r["status"] == "skipped" for r in done), len(failures), n_rows, SHEARS, seconds)
    return BranchRunResult(wd, done, failures, evaluation, seconds, products)


def failure_error(result: BranchRunResult) -> MegalutError | None:
    """The error to report (exit 1) when subfields failed under ``keep_going``, else None."""
    if not result.failures:
        return None
    f = result.failures
    listed = "; ".join(f"{r['subfield']}: {r['error']}" for r in f[:3]) + (" ..." if len(f) > 3 else "")
    return MegalutError(
        f"{len(f)} of {len(f) + len(result.summaries)} subfield(s) failed ({listed}); "
        f"{result.workdir / SUBMISSION} holds the other {len(result.summaries)}"
    )


def _write_manifest(pipe: BranchPipeline, wd: Path, done: Sequence[Mapping[str, Any]],
                    failures: Sequence[Mapping[str, Any]], seconds: float) -> None:
    from megalut_cli.atomic import write_json
    from megalut_cli.provenance import utc_now

    data = {
        "format": MANIFEST_FORMAT,
        "format_version": "1.0",
        "megalut": __version__,
        "finished": utc_now(),
        "pipeline": {"path": pipe.path, "sha256": pipe.sha256, "overrides": list(pipe.overrides), "effective": pipe.raw},
        "branch": {"path": str(pipe.branch_dir), "kind": pipe.kind, "stamp_size": pipe.stamp_size,
                   "truth": str(pipe.truth) if pipe.truth else None},
        "submission": {"path": SUBMISSION, "weighted": pipe.weighted, "n_subfields": len(done)},
        "seconds": round(seconds, 3),
        "subfields": {f"{r['subfield']:03d}": r for r in done},
        "failed": {f"{r['subfield']:03d}": r["error"] for r in failures},
    }
    write_json(wd / MANIFEST, json.loads(json.dumps(data, default=str)), overwrite=True)


def format_summary(result: BranchRunResult) -> str:
    """What was written and, with a truth folder, the m, c and Q_c table."""
    lines = []
    if result.evaluation is not None:
        from megalut_cli.shear.evaluate import format_table

        lines += [format_table(result.evaluation), ""]
    lines.append(f"{len(result.summaries)} subfield(s); products in {result.workdir}/: {', '.join(result.products)} "
                 f"(and {SUBFIELDS_DIR}/SSS/)")
    return "\n".join(lines)
