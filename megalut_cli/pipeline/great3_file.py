"""The per-subfield pipeline of a GREAT3 constant-shear branch (paper Sect. 8), run by
``megalut run``.

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
only, so results do not depend on ``-j`` or the cluster. This module reads and checks the
file (a :class:`BranchPipeline`); :mod:`megalut_cli.pipeline.great3_run` runs it.
"""

from __future__ import annotations

import copy
import json
import logging
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from megalut_cli.engine import DEFAULT_ENGINE, ENGINE_OPTION
from megalut_cli.errors import ConfigError, InputError, MegalutError
from megalut_cli.great3 import layout as L
from megalut_cli.measure.defaults import MIN_STAMP_SIZE
from megalut_cli.measure.features import FEATURE_COLUMNS
from megalut_cli.nn.options import OPTION as TRAIN_OPTION
from megalut_cli.nn.options import POINT_OPTION, PointSpec, WeightSpec
from megalut_cli.pipeline.config import (
    PIPELINE,
    TRAIN_POINT_KEYS,
    TRAIN_WEIGHT_KEYS,
    merge_tables,
    read_spec,
)
from megalut_cli.pipeline.config import SET_OPTIONS as PIPELINE_SET_OPTIONS
from megalut_cli.pipeline.steps import MANIFEST as MANIFEST  # the step engine's manifest.json
from megalut_cli.pipeline.steps import sha_text
from megalut_cli.schema import Option, Table, resolve_path
from megalut_cli.seeding import STREAM_SUBFIELD, int_seed_for
from megalut_cli.shear.bias import GREAT3_SIGMA2_MIN_GROUND, GREAT3_SIGMA2_MIN_SPACE
from megalut_cli.sim.config import apply_overrides, is_measured, read_toml, validate_config

log = logging.getLogger(__name__)

KINDS = ("ground", "space")
SET_NAMES = ("tp", "tw")
#: Pipeline seeds when the file gives none (all different).
DEFAULT_SEEDS = {"tp": 1, "tw": 2, "train_point": 3, "train_weight": 4}
#: The paper's four features per component (Sect. 8.2); ``{i}`` is the component, 1 or 2.
FEATURE_TEMPLATES = ["adamom_g{i}", "adamom_sigma", "adamom_flux", "adamom_rho4"]
#: Targets of the point committees: the ellipticity shortcut, or a shear-structured ``tp``.
TARGET_CHOICES = (("tru_e1", "tru_e2"), ("tru_g1", "tru_g2"))
#: Hidden layers of the weight networks: those of the point networks, "for all estimators
#: ... two hidden layers" (Sect. 8.2).
WEIGHT_HIDDEN = POINT_OPTION["hidden"].default

SUBFIELDS_DIR = "subfields"
SHEARS_FILE = "shears.fits"
SUBMISSION = "submission.txt"
EVALUATION = "evaluation.json"
UNIT_RECORD = "subfield.json"
#: ``format`` of a subfield's own record ``subfield.json`` (the manifest is the step engine's).
UNIT_RECORD_FORMAT = "megalut.great3-run"
#: Products of a subfield folder (``tp.fits``, ``tw.fits`` too with ``keep_sets``).
UNIT_PRODUCTS = ("features.fits", "stars.fits", "model.h5", "shears.fits")
SHEARS_FORMAT = "megalut.predictions"


def _by_kind(values: Mapping[str, Any]) -> str:
    return "by `kind` (" + ", ".join(f"{k} {v:g}" for k, v in values.items()) + ")"


#: ``Q_c``'s sigma^2_min by kind of branch (the GREAT3 metric).
SIGMA2_MIN = {"ground": GREAT3_SIGMA2_MIN_GROUND, "space": GREAT3_SIGMA2_MIN_SPACE}

#: The keys of the ``[branch]`` table (``docs/great3.md``); ``subfields`` and ``truth`` have
#: readers of their own (:func:`parse_subfields`, a folder or a flag).
BRANCH_OPTIONS: tuple[Option, ...] = (
    Option("path", "path", None, "the branch folder", default_text="required"),
    Option(
        "kind",
        "choice",
        KINDS[0],
        '`"ground"` (48-pixel stamps, Table 3 ground distributions, `sigma2_min` 4) '
        'or `"space"` (96, space, 1)',
        choices=KINDS,
    ),
    Option(
        "stamp_size",
        "int",
        None,
        "stamp size in pixels",
        minimum=MIN_STAMP_SIZE,
        default_text=_by_kind(L.STAMP_SIZES),
    ),
    Option(
        "subfields",
        "str",
        "all",
        'every `image-SSS-E.fits` of the folder, or a list (`[0, 5]`), or a text (`"0-19,25"`)',
        allowed_text='`"all"`, indices, a text of ranges',
    ),
    Option("epoch", "int", 0, "the `E` of the file names", minimum=0),
    Option(
        "strict",
        "bool",
        True,
        "off-image centres and NaN pixels are errors (false: flagged stamps)",
    ),
    Option(
        "truth",
        "bool",
        True,
        "the truth folder to evaluate against: true = the branch's `truth/` if any, a "
        "path, or false",
        allowed_text="true, false, a folder",
    ),
    Option(
        "sigma2_min",
        "float",
        None,
        "`Q_c`'s σ²_min",
        minimum=0,
        min_open=True,
        default_text=_by_kind(SIGMA2_MIN),
    ),
)
BRANCH = {o.name: o for o in BRANCH_OPTIONS}
#: The keys of the ``[tp]`` and ``[tw]`` tables: those of a standard pipeline's ``[sets.X]``
#: but ``scale_by`` (a branch pipeline has no ``scale``).
_SET_CHANGES = {
    "config": {
        "help": "a simulation config file replacing the default set (below), relative to the "
        "pipeline file",
        "default_text": "the paper's",
    },
    "seed": {"default_text": "tp 1, tw 2"},
}
SET_OPTIONS: tuple[Option, ...] = tuple(
    replace(o, **_SET_CHANGES.get(o.name, {})) for o in PIPELINE_SET_OPTIONS if o.name != "scale_by"
)
SET_OPTION = {o.name: o for o in SET_OPTIONS}
#: The keys of the ``[output]`` table.
OUTPUT_OPTIONS: tuple[Option, ...] = (
    Option("weighted", "bool", True, "the submission from weighted means (false: plain means)"),
    Option(
        "keep_sets",
        "bool",
        False,
        "keep `tp.fits`, `tw.fits` per subfield (200 × ~50 MB at the paper's sizes)",
    ),
)
OUTPUT = {o.name: o for o in OUTPUT_OPTIONS}
#: The top-level keys of a branch pipeline file.
TOP_OPTIONS: tuple[Option, ...] = (
    PIPELINE["description"],
    replace(
        ENGINE_OPTION,
        help="stamp engine of `measure` and the training simulations, as in "
        "[pipeline.md](pipeline.md) ([engines.md](engines.md))",
    ),
    Option(
        "metacal",
        "bool",
        False,
        "self-calibrated mode ([metacal.md](metacal.md)): the subfield's galaxies "
        "are measured with `--metacal` (deconvolved by the star field's first star), the training "
        "sets in metacal mode (the networks train on the noshear versions' features), and each "
        "subfield's shear is its mean noshear estimate divided by its mean response",
    ),
    replace(
        PIPELINE["moments_retry"],
        help="step factor of the adaptive moments' damped retry on the stamps whose iteration "
        "fails (`measure --moments-retry`, [catalogs.md](catalogs.md)) in every measurement "
        "of a subfield (its galaxies and stars, the training sets); 0: none. Part of the "
        "subfields' keys when set",
    ),
    Option(
        "branch", "table", None, "the branch and how to read it (above)", default_text="required"
    ),
    Option(
        "tp",
        "table",
        None,
        "the per-subfield point-training set (below)",
        default_text="the paper's",
    ),
    Option(
        "tw",
        "table",
        None,
        "the per-subfield weight-training set (below); its seed must differ from tp's",
        default_text="the paper's",
    ),
    Option(
        "train_point",
        "table",
        None,
        "as in [pipeline.md](pipeline.md): `features` (default "
        '`["adamom_g{i}", "adamom_sigma", "adamom_flux", "adamom_rho4"]`, `{i}` = the component), '
        '`targets` (`["tru_e1", "tru_e2"]`, or `["tru_g1", "tru_g2"]` with a sheared `tp`), '
        f"`hidden` ({POINT_OPTION['hidden'].default}), "
        f"`members` ({TRAIN_OPTION['members'].default}), `keep`, "
        f"`iterations` ({PointSpec().iterations}), `cost`, `select_cases`, `init`, "
        "`normalization`, `optimizer`, `precision`, `valid_fraction`, `batch_fraction`, "
        f"`batch_iterations`, `seed` ({DEFAULT_SEEDS['train_point']})",
        default_text="see meaning",
    ),
    Option(
        "train_weight",
        "table",
        None,
        "the same keys (no `targets`, `cost`, `select_cases`, `init`), plus "
        f"`select`; `features` default those of `train_point`, `hidden` {WEIGHT_HIDDEN} (the "
        "paper's choice for all its GREAT3 estimators), "
        f"`iterations` {WeightSpec().iterations}, "
        f"`seed` {DEFAULT_SEEDS['train_weight']}",
        default_text="see meaning",
    ),
    Option("output", "table", None, "what the run writes (below)", default_text="see below"),
)
TOP = {o.name: o for o in TOP_OPTIONS}

# --------------------------------------------------------------------------- Table 3

_RAYLEIGH = {"type": "rayleigh", "mode": 0.2, "min": 0.0, "max": 0.7}
_ANGLE = {"type": "uniform", "min": 0.0, "max": 180.0}


def _sersic(lo: float, hi: float) -> dict[str, Any]:
    return {
        "type": "grid",
        "min": lo,
        "max": hi,
        "step": 0.1,
    }  # gridded, as the paper (Table 3, note a)


#: Galaxy distributions of the paper's Table 3: (kind, "uniform" | "mock") -> [galaxy] table.
TABLE3: dict[tuple[str, str], dict[str, Any]] = {
    ("ground", "uniform"): {
        "sersicn": _sersic(0.5, 4.0),
        "rad": {"type": "uniform", "min": 0.75, "max": 3.0},
        "flux": {"type": "uniform", "min": 10.0, "max": 100.0},
    },
    ("ground", "mock"): {
        "sersicn": _sersic(0.5, 2.5),
        "rad": {"type": "normal", "mean": 1.0, "sigma": 0.8, "min": 0.75, "max": 3.0},
        "flux": {"type": "normal", "mean": 15.0, "sigma": 20.0, "min": 10.0, "max": 200.0},
    },
    ("space", "uniform"): {
        "sersicn": _sersic(0.5, 4.0),
        "rad": {"type": "uniform", "min": 1.25, "max": 10.0},
        "flux": {"type": "uniform", "min": 10.0, "max": 100.0},
    },
    ("space", "mock"): {
        "sersicn": _sersic(0.5, 4.0),
        "rad": {"type": "normal", "mean": 2.5, "sigma": 3.5, "min": 1.25, "max": 10.0},
        "flux": {"type": "normal", "mean": 0.0, "sigma": 30.0, "min": 10.0, "max": 200.0},
    },
}


def default_set(name: str, kind: str, stamp_size: int) -> dict[str, Any]:
    """The default simulation config of set ``tp`` or ``tw`` for one subfield (paper Sect. 8.2).

    ``psf.path`` (the star field) and ``noise.sigma.path`` (the features) are filled in
    per subfield.
    """
    star_psf = {"type": "stamp", "path": "", "stamp_size": stamp_size, "index": "random"}
    galaxy = {
        "profile": "sersic",
        **copy.deepcopy(TABLE3[(kind, "uniform" if name == "tp" else "mock")]),
        "ellipticity": dict(_RAYLEIGH),
        "angle": dict(_ANGLE),
    }
    if name == "tp":
        return {
            "description": (
                f"GREAT3 {kind} subfield: point-estimate training set "
                "(ellipticity shortcut, Table 3 uniform)"
            ),
            "structure": {
                "n_cases": 1000,
                "n_realizations": 10,
                "per_realization": [],
                "snc": "none",
                "stamp_size": stamp_size,
                "offset": 0.5,
            },
            "galaxy": galaxy,
            "psf": star_psf,
            "noise": {"type": "none"},
        }
    return {
        "description": (
            f"GREAT3 {kind} subfield: weight training set (90-degree pairs, Table 3 mock)"
        ),
        "structure": {
            "n_cases": 200,
            "n_realizations": 1000,
            "per_realization": ["galaxy"],
            "snc": "pairs",
            "stamp_size": stamp_size,
            "offset": 0.5,
        },
        "shear": {
            "g1": {"type": "uniform", "min": -0.1, "max": 0.1},
            "g2": {"type": "uniform", "min": -0.1, "max": 0.1},
        },
        "galaxy": galaxy,
        "psf": star_psf,
        "noise": {
            "type": "gaussian",
            "sigma": {"type": "measured", "path": "", "column": "skymad", "statistic": "median"},
        },
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
    point: PointSpec  # features are templates: "{i}" -> 1, 2
    weight: WeightSpec
    weighted: bool
    keep_sets: bool
    problems: dict[int, str] = field(default_factory=dict)  # subfields with missing files
    engine: str = DEFAULT_ENGINE  # stamp engine of measure and simulate (megalut_cli.engine)
    metacal: bool = False  # the self-calibrated mode (docs/metacal.md)
    moments_retry: float = 0.0  # the moments' damped retry of every measurement (0: none)


def is_branch_pipeline(path: str | os.PathLike) -> bool:
    """Whether the TOML file ``path`` is a branch pipeline (has a top-level ``[branch]``)."""
    raw, _ = read_toml(path)
    return "branch" in raw


def component_features(templates: Sequence[str], i: int) -> list[str]:
    """Feature names of component ``i`` (1 or 2): ``{i}`` replaced, duplicates dropped."""
    return list(dict.fromkeys(t.replace("{i}", str(i)) for t in templates))


def subfield_seed(seed: int, subfield: int, *keys: int) -> int:
    """The seed of a subfield's draw (``keys`` name the draw): independent of the workers."""
    return int_seed_for(seed, STREAM_SUBFIELD, subfield, *keys)


def parse_subfields(value: Any, key: str = "branch.subfields") -> list[int] | None:
    """``"all"`` -> None; a list of indices, an index, or a text like ``"0-19,25"`` -> sorted
    indices."""
    if value is None or value == "all":
        return None
    items: list[int] = []
    if isinstance(value, int) and not isinstance(value, bool):
        items = [value]
    elif (
        isinstance(value, list)
        and value
        and all(isinstance(v, int) and not isinstance(v, bool) for v in value)
    ):
        items = list(value)
    elif isinstance(value, str) and value.strip():
        for part in value.split(","):
            m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", part)
            if not m:
                raise ConfigError(f'{key}: cannot read {part.strip()!r} (expected e.g. "0-19,25")')
            a, b = int(m.group(1)), int(m.group(2) if m.group(2) is not None else m.group(1))
            if b < a:
                raise ConfigError(f"{key}: empty range {part.strip()!r}")
            items += range(a, b + 1)
    else:
        raise ConfigError(
            f'{key}: expected "all", a list of subfield indices or a text like "0-19", '
            f"got {value!r}"
        )
    if any(v < 0 for v in items):
        raise ConfigError(f"{key}: subfield indices must be >= 0")
    return sorted(set(items))


def _find_path(text: str, key: str, base_dir: Path | None, want_dir: bool) -> Path:
    """A path from the pipeline file (:func:`megalut_cli.schema.resolve_path`)."""
    return resolve_path(text, key, base_dir, folder=want_dir)


def _load_set(
    name: str, top: Any, kind: str, size: int, base_dir: Path | None, pipe_path: str
) -> SetTemplate:
    t = Table(top.data.get(name), name, set(SET_OPTION))
    if "config" in t.data:
        cfg = _find_path(t.option(SET_OPTION["config"]), t.key("config"), base_dir, want_dir=False)
        raw, _ = read_toml(cfg)
        config_path, source = str(cfg), str(cfg)
    else:
        raw, config_path, source = (
            default_set(name, kind, size),
            pipe_path,
            f"default {kind} {name}",
        )
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
        v = t.option(SET_OPTION[k]) if k in t.data else None
        if v is not None:
            structure[k] = v
    seed = t.option(SET_OPTION["seed"], DEFAULT_SEEDS[name])
    return SetTemplate(name, raw, int(seed or 0), config_path, source)


def set_config(
    tpl: SetTemplate, starfield: str | os.PathLike, features: str | os.PathLike | None
) -> Any:
    """The validated simulation config of ``tpl`` for one subfield: a ``stamp`` PSF takes
    the subfield's star field, a ``measured`` noise its features catalog (``None``: a
    stand-in value of 1, to check the config before anything is measured)."""
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
        return validate_config(raw, path=tpl.config_path, sha256=sha_text(raw))
    except MegalutError as err:
        raise type(err)(f"{tpl.name} ({tpl.source}): {err}") from None


def _check_features(names: Sequence[str], key: str) -> None:
    allowed = [c for c in FEATURE_COLUMNS if c != "flags"]
    for i in (1, 2):
        bad = [f for f in component_features(names, i) if f not in allowed]
        if bad:
            raise ConfigError(
                f"{key}: {bad[0]!r} is not a measured feature (allowed: {', '.join(allowed)}; "
                "'{i}' stands for the component, e.g. adamom_g{i})"
            )


def parse_branch_pipeline(
    raw: Mapping[str, Any],
    path: str = "<pipeline>",
    sha256: str = "",
    overrides: Sequence[str] = (),
    base_dir: Path | None = None,
) -> BranchPipeline:
    """Validate a parsed branch pipeline (after ``key=value`` overrides); check the branch
    folder."""
    raw = apply_overrides(dict(raw), overrides)
    top = Table(raw, "", set(TOP))
    description = top.option(TOP["description"])
    b = Table(top.data.get("branch"), "branch", set(BRANCH))
    if "path" not in b.data:
        raise ConfigError("branch.path: missing (the branch folder, in the GREAT3 layout)")
    branch_dir = _find_path(b.option(BRANCH["path"]), "branch.path", base_dir, want_dir=True)
    kind = b.option(BRANCH["kind"])
    size = b.option(BRANCH["stamp_size"], L.STAMP_SIZES[kind])
    epoch = b.option(BRANCH["epoch"])
    strict = b.option(BRANCH["strict"])
    sigma2_min = b.option(BRANCH["sigma2_min"], SIGMA2_MIN[kind])
    truth_value = b.data.get("truth", BRANCH["truth"].default)
    truth: Path | None = None
    if truth_value is True:
        truth = branch_dir / "truth" if (branch_dir / "truth").is_dir() else None
    elif isinstance(truth_value, str) and truth_value:
        truth = _find_path(truth_value, "branch.truth", base_dir, want_dir=True)
    elif truth_value is not False:
        raise ConfigError(
            "branch.truth: expected a folder, true (the branch's truth/ if any) or false, "
            f"got {truth_value!r}"
        )

    available = L.find_subfields(branch_dir, epoch)
    wanted = parse_subfields(b.data.get("subfields", BRANCH["subfields"].default))
    if wanted is None:
        if not available:
            raise InputError(
                f"{branch_dir}: no {L.image_name(0, epoch).replace('000', 'SSS')} file: "
                "not a GREAT3 branch folder"
            )
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
        raise ConfigError(
            f"tw.seed: {sets['tw'].seed} is also the seed of tp; every set needs its own seed"
        )

    point_table = Table(top.data.get("train_point"), "train_point", TRAIN_POINT_KEYS)
    point = read_spec(
        PointSpec,
        point_table,
        seed=DEFAULT_SEEDS["train_point"],
        targets=list(TARGET_CHOICES[0]),
        features=FEATURE_TEMPLATES,
    )
    targets = point.targets
    if tuple(targets) not in TARGET_CHOICES:
        raise ConfigError(
            'train_point.targets: expected ["tru_e1", "tru_e2"] (the ellipticity shortcut) or '
            f'["tru_g1", "tru_g2"], got {targets!r}'
        )
    _check_features(point.features, "train_point.features")
    weight_table = Table(top.data.get("train_weight"), "train_weight", TRAIN_WEIGHT_KEYS)
    weight = read_spec(
        WeightSpec,
        weight_table,
        seed=DEFAULT_SEEDS["train_weight"],
        features=point.features,
        hidden=WEIGHT_HIDDEN,
    )
    _check_features(weight.features, "train_weight.features")
    out = Table(top.data.get("output"), "output", set(OUTPUT))
    pipe = BranchPipeline(
        path=path,
        sha256=sha256,
        overrides=tuple(overrides),
        raw=json.loads(json.dumps(raw, default=str)),
        description=description,
        branch_dir=branch_dir,
        kind=kind,
        stamp_size=int(size),
        epoch=int(epoch),
        subfields=subfields,
        strict=strict,
        truth=truth,
        sigma2_min=sigma2_min,
        sets=sets,
        point=point,
        weight=weight,
        weighted=out.option(OUTPUT["weighted"]),
        keep_sets=out.option(OUTPUT["keep_sets"]),
        problems=problems,
        engine=top.option(TOP["engine"]),
        metacal=bool(top.option(TOP["metacal"])),
        moments_retry=float(top.option(TOP["moments_retry"])),
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
            raise ConfigError(
                f"{name}: structure.stamp_size {s.stamp_size} differs from the branch's "
                f"{pipe.stamp_size}"
            )
        if s.n_cases < 2:
            raise ConfigError(f"{name}.n_cases: at least 2 cases are needed, got {s.n_cases}")
    tw_raw = pipe.sets["tw"].raw
    if not tw_raw.get("shear"):
        raise ConfigError(
            "tw: the weight-training set needs a [shear] distribution (MSWB learns the shear)"
        )
    if pipe.point.targets[0] == "tru_g1" and not pipe.sets["tp"].raw.get("shear"):
        raise ConfigError(
            "train_point.targets: tru_g1, tru_g2 need a [shear] in tp (or use tru_e1, tru_e2)"
        )


def load_branch_pipeline(path: str | os.PathLike, overrides: Sequence[str] = ()) -> BranchPipeline:
    """Read and validate a branch pipeline file."""
    raw, sha = read_toml(path)
    return parse_branch_pipeline(raw, str(path), sha, overrides, Path(path).resolve().parent)


def unit_params(pipe: BranchPipeline, subfield: int) -> dict[str, Any]:
    """Everything that determines a subfield's products (its key, with the input hashes)."""
    return {
        "subfield": subfield,
        "kind": pipe.kind,
        "stamp_size": pipe.stamp_size,
        "epoch": pipe.epoch,
        "strict": pipe.strict,
        "keep_sets": pipe.keep_sets,
        "sets": {
            n: {"raw": t.raw, "seed": subfield_seed(t.seed, subfield)} for n, t in pipe.sets.items()
        },
        "train_point": asdict(pipe.point),
        "train_weight": asdict(pipe.weight),
        "engine": pipe.engine,
        **({"metacal": True} if pipe.metacal else {}),
        # absent when unset: the keys of earlier runs stay valid
        **({"moments_retry": pipe.moments_retry} if pipe.moments_retry > 0 else {}),
    }
