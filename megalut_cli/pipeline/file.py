"""``megalut run``: a whole shear-calibration pipeline from one TOML file.

A pipeline file (reference: ``docs/pipeline.md``) names three simulation sets — ``tp``
(point-estimator training, Fig. 4 structure), ``tw`` (weight training, Fig. 5) and ``vo``
(overall validation) — and optionally ``pretrain`` (low-noise ellipticity pretraining,
Fig. 6 structure, paper Sect. 6) and ``vp`` (point-estimator validation, Fig. 4
structure), with the settings of the training, prediction and evaluation steps.
:func:`megalut_cli.pipeline.run.run_pipeline` runs, in a work folder:

====================  ==================================  =========================
step                  does                                writes
====================  ==================================  =========================
``simulate-<set>``    simulate + measure a set            ``<set>.fits``
``pretrain-point``    point committees on ``pretrain``    ``pretrain.h5``
                      (targets ``tru_e1, tru_e2``)
``train-point``       point committees (MSB) on TP,       ``point.h5``
                      continuing ``pretrain.h5`` if any
``predict-vp``        point estimates on VP               ``vp-shears.fits``
``evaluate-vp``       m, c of the point estimates         ``evaluation-vp.json``
``train-weight``      weight committees (MSWB) on TW      ``trained.h5``
``predict``           estimates and weights on VO         ``vo-shears.fits``
``evaluate``          m, c unweighted and weighted        ``evaluation.json`` (+ ``.png``)
``model``             ``trained.h5`` with its validation  ``model.h5``
                      recorded (``predict`` reports it)
====================  ==================================  =========================

A pipeline with a ``name`` writes the products of every step after the simulations to
the subfolder ``<name>/`` of the work folder (steps ``<name>/train-point``...), so that
several pipelines sharing the same sets (the feature setups of Sect. 6, the selections of
Sect. 7) run in one work folder and simulate the sets once. ``extends = "base.toml"``
makes a pipeline file a set of changes to another.

``manifest.json`` in the work folder records, for every finished step, a key (sha256 of
its parameters, the sha256 of its input files and the megalut version) and the sha256,
size and modification time of its outputs. With ``skip_existing`` a step is skipped when
its key is unchanged and its outputs are still those recorded; any change (a config
value, a seed, an upstream product) re-runs the step and, through the input hashes,
everything downstream. A step whose key is that of a finished step of another pipeline
in the same folder copies that step's products instead of redoing the work. The
execution engine (``-j``, Dask) is not part of the key: the results do not depend on it.
"""

from __future__ import annotations

import copy
import importlib.resources
import json
import logging
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from megalut_cli.engine import DEFAULT_DEVICE, DEFAULT_ENGINE
from megalut_cli.errors import ConfigError, InputError, MegalutError
from megalut_cli.expr import check_expression
from megalut_cli.nn.options import PointSpec, WeightSpec
from megalut_cli.nn.shipped import SHIPPED_MODELS, shipped_model
from megalut_cli.pipeline.config import (
    DEFAULT_PIPELINE,
    DEFAULT_SET_SEEDS,
    MAX_NAME,
    PATH_TABLES,
    PIPELINE,
    PLOT_OPTION,
    REFERENCE_OPTION,
    SCALE_BY,
    SET_OPTION,
    TRAIN_POINT_KEYS,
    TRAIN_TABLE_DEFAULTS,
    TRAIN_WEIGHT_KEYS,
    EvaluateSpec,
    merge_tables,
    read_spec,
    selection_expression,
)
from megalut_cli.pipeline.steps import sha_text
from megalut_cli.provenance import sha256_file
from megalut_cli.schema import Table, resolve_path
from megalut_cli.shear.options import EVALUATE
from megalut_cli.sim.config import SimConfig, apply_overrides, read_toml, validate_config

log = logging.getLogger(__name__)

DEFAULT_WORKDIR = "megalut-run"
EVALUATION_JSON = "evaluation.json"
#: The weight step's model, validated on VO; then the pipeline's product, the same networks
#: with that validation recorded (``predict`` reports it, ``--strict`` refuses a bias).
TRAINED_MODEL = "trained.h5"
MODEL = "model.h5"
EVALUATION_PNG = "evaluation.png"
EVALUATION_VP_JSON = "evaluation-vp.json"
EVALUATION_VP_PNG = "evaluation-vp.png"
REFERENCE_SHEARS = "reference-shears.fits"
EVALUATION_REFERENCE_JSON = "evaluation-reference.json"
EVALUATION_REFERENCE_PNG = "evaluation-reference.png"
#: The sets every pipeline has.
SET_NAMES = ("tp", "tw", "vo")
#: Optional sets: ellipticity pretraining (Sect. 6) and point-estimator validation.
OPTIONAL_SETS = ("pretrain", "vp")
#: Every set, in the order of the simulation steps.
ALL_SETS = ("pretrain", "tp", "tw", "vo", "vp")
#: Case selection of the VP evaluation unless the file says otherwise (paper Figs. 12, 10).
VP_SELECT_CASES = "mean(snr) > 10"
#: How deep ``extends`` chains may go.
MAX_EXTENDS = 8
_NAME_RE = re.compile(
    rf"[A-Za-z0-9][A-Za-z0-9_-]{{0,{MAX_NAME - 1}}}"
)  # no ".": never a product's name

#: Top-level keys a parsed pipeline may have (``extends`` is read with the file).
_TOP_KEYS = set(PIPELINE) - {"extends"}
#: Pretraining continues into train_point: same features and architecture.
_PRETRAIN_KEYS = TRAIN_POINT_KEYS - {"features", "hidden"}
_EVALUATE_KEYS = {*EVALUATE, PLOT_OPTION.name}

# --------------------------------------------------------------------------- specification


@dataclass(frozen=True)
class SetSpec:
    """One simulated set: its validated config and seed."""

    name: str
    config: SimConfig
    seed: int
    source: str  # where the config comes from, for the logs

    @property
    def product(self) -> str:
        return f"{self.name}.fits"


@dataclass(frozen=True)
class ReferenceSpec:
    """A fixed model validated beside the trained one, on one of the pipeline's sets."""

    model: Path
    label: str  # how the summary names it
    set: str
    sha256: str  # of the model file, hashed once: part of the prediction step's key


@dataclass(frozen=True)
class Pipeline:
    """A validated pipeline file (overrides and scale applied)."""

    path: str
    sha256: str
    overrides: tuple[str, ...]
    raw: dict[str, Any]
    description: str
    scale: float
    sets: dict[str, SetSpec]
    train_point: PointSpec
    train_weight: WeightSpec
    evaluate: EvaluateSpec
    columns: dict[str, list[str]] = field(default_factory=dict)  # set -> columns it will have
    name: str = ""  # products of the steps after the simulations go to <workdir>/<name>/
    pretrain: PointSpec | None = None  # with the set "pretrain" (features, hidden: train_point's)
    evaluate_vp: EvaluateSpec | None = None  # with the set "vp"
    engine: str = DEFAULT_ENGINE  # stamp engine of the simulations (megalut_cli.engine)
    device: str = DEFAULT_DEVICE  # where simulations and trainings run; not in the steps' keys
    reference: ReferenceSpec | None = None  # [reference]: a fixed model evaluated on a set
    metacal: bool = False  # the validation sets measured in metacal mode too (docs/metacal.md)
    moments_retry: float = 0.0  # the moments' damped retry of every set's measurement (0: none)

    def product(self, base: str) -> str:
        """Where a product of a training, prediction or evaluation step goes in the work folder."""
        return f"{self.name}/{base}" if self.name else base


def scaled_size(n: int, factor: float, minimum: int, even: bool = False) -> int:
    """``n`` times ``factor``, rounded, at least ``minimum`` (and even when ``even``)."""
    m = max(minimum, round(n * factor))
    if even:
        m = max(2, 2 * round(m / 2))
    return int(m)


def _load_set(
    name: str,
    raw: Mapping[str, Any],
    base_sim: Mapping[str, Any] | None,
    scale: float,
    pipeline_path: str,
    base_dir: Path | None,
    pipeline_sha: str,
) -> SetSpec:
    t = Table(raw.get(name), f"sets.{name}", set(SET_OPTION))
    if "config" in t.data:
        cfg_path = resolve_path(t.option(SET_OPTION["config"]), t.key("config"), base_dir)
        try:
            sim_raw, sha = read_toml(cfg_path)
        except MegalutError as err:
            raise type(err)(f"{t.key('config')}: {err}") from None
        where, source = str(cfg_path), str(cfg_path)
    elif base_sim is not None:
        sim_raw, sha = copy.deepcopy(dict(base_sim)), pipeline_sha
        where, source = f"{pipeline_path}#sets.{name}", "[simulation]"
    else:
        raise ConfigError(
            f"sets.{name}.config: missing (a simulation config file, or a [simulation] table)"
        )
    over = t.option(SET_OPTION["simulation"])
    if over is not None:
        sim_raw = merge_tables(sim_raw, over)
        source += f" + sets.{name}.simulation"
    structure = sim_raw.get("structure")
    if structure is None:
        structure = sim_raw["structure"] = {}
    if not isinstance(structure, dict):
        raise ConfigError(f"sets.{name}: structure: expected a table")
    for k in ("n_cases", "n_realizations"):
        v = t.option(SET_OPTION[k])
        if v is not None:
            structure[k] = v
    seed = t.option(SET_OPTION["seed"], DEFAULT_SET_SEEDS[name])
    scale_by = t.option(SET_OPTION["scale_by"])
    try:
        config = validate_config(sim_raw, path=where, sha256=sha)
    except MegalutError as err:
        raise type(err)(f"sets.{name}: {err}") from None
    if scale != 1.0:
        s = config.structure
        a, b = SCALE_BY[scale_by]
        sizes = {
            "n_cases": scaled_size(s.n_cases, scale**a, 2),
            "n_realizations": scaled_size(s.n_realizations, scale**b, 1, even=s.snc == "pairs"),
        }
        raw_scaled = copy.deepcopy(config.raw)
        raw_scaled["structure"].update(sizes)
        config = replace(config.with_structure(**sizes), raw=raw_scaled)
    if config.structure.n_cases < 2:
        raise ConfigError(
            f"sets.{name}.n_cases: at least 2 cases are needed, got {config.structure.n_cases}"
        )
    return SetSpec(name, config, int(seed), source)


def _evaluate_spec(t: Table, select_cases: str | None) -> EvaluateSpec:
    return EvaluateSpec(
        by=t.option(EVALUATE["by"]),
        bins=t.option(EVALUATE["bins"]),
        select=selection_expression(t, EVALUATE["select"], False),
        select_cases=selection_expression(t, EVALUATE["select_cases"], True, select_cases),
        plot=t.option(PLOT_OPTION),
    )


def _pretrain_spec(top: Table, has_set: bool) -> PointSpec | None:
    """The ``[pretrain]`` table (its features and hidden layers: the defaults, until
    :func:`parse_pipeline` sets those of ``[train_point]``)."""
    if not has_set:
        if top.data.get("pretrain") is not None:
            raise ConfigError(
                "pretrain: there is no set to pretrain on: add a [sets.pretrain] table"
            )
        return None
    t = Table(top.data.get("pretrain"), "pretrain")
    for k in ("features", "hidden"):
        if k in t.data:
            raise ConfigError(
                f"pretrain.{k}: the pretraining uses the features and hidden layers of "
                "[train_point], which continues from it; set them there"
            )
    table = Table(t.data, "pretrain", _PRETRAIN_KEYS)
    return read_spec(PointSpec, table, **TRAIN_TABLE_DEFAULTS["pretrain"])


def parse_pipeline(
    raw: Mapping[str, Any],
    path: str = "<pipeline>",
    sha256: str = "",
    overrides: Sequence[str] = (),
    base_dir: Path | None = None,
) -> Pipeline:
    """Validate a parsed pipeline mapping (after ``key=value`` overrides)."""
    raw = apply_overrides(dict(raw), overrides)
    if "extends" in raw:
        raise ConfigError(
            "extends: only a pipeline file can extend another (not an override or a mapping)"
        )
    top = Table(raw, "", _TOP_KEYS)
    description = top.option(PIPELINE["description"])
    name = top.data.get("name", PIPELINE["name"].default)
    if not isinstance(name, str) or (name and not _NAME_RE.fullmatch(name)):
        raise ConfigError(
            f"name: expected a folder name (letters, digits, '_', '-'; at most {MAX_NAME}), got "
            f"{name!r}"
        )
    scale = top.option(PIPELINE["scale"])
    engine = top.option(PIPELINE["engine"])
    device = top.option(PIPELINE["device"])
    metacal = top.option(PIPELINE["metacal"])
    moments_retry = top.option(PIPELINE["moments_retry"])
    base_sim = top.option(PIPELINE["simulation"])
    sets_t = Table(top.option(PIPELINE["sets"]), "sets", set(ALL_SETS))
    missing = [n for n in SET_NAMES if n not in sets_t.data]
    if missing:
        raise ConfigError(
            f"sets.{missing[0]}: missing (a pipeline needs the sets {', '.join(SET_NAMES)})"
        )
    sets = {
        n: _load_set(n, sets_t.data, base_sim, scale, path, base_dir, sha256)
        for n in ALL_SETS
        if n in sets_t.data
    }
    seen: dict[int, str] = {}
    for n, s in sets.items():
        if s.seed in seen:
            raise ConfigError(
                f"sets.{n}.seed: {s.seed} is also the seed of sets.{seen[s.seed]}; "
                "every set needs its own seed (the paper draws them independently)"
            )
        seen[s.seed] = n

    pretrain = _pretrain_spec(top, "pretrain" in sets)
    point_table = Table(top.data.get("train_point"), "train_point", TRAIN_POINT_KEYS)
    point = read_spec(PointSpec, point_table, **TRAIN_TABLE_DEFAULTS["train_point"])
    overlap = sorted(set(point.features) & set(point.targets))
    if overlap:
        raise ConfigError(f"train_point.features: {overlap[0]!r} is also a target")
    if pretrain is not None:
        pretrain = replace(pretrain, features=point.features, hidden=point.hidden)
        _check_pretrain(pretrain, point, sets["pretrain"])
    weight_table = Table(top.data.get("train_weight"), "train_weight", TRAIN_WEIGHT_KEYS)
    weight = read_spec(WeightSpec, weight_table, **TRAIN_TABLE_DEFAULTS["train_weight"])
    evaluate = _evaluate_spec(Table(top.data.get("evaluate"), "evaluate", _EVALUATE_KEYS), None)
    evaluate_vp = None
    if "vp" in sets:
        evaluate_vp = _evaluate_spec(
            Table(top.data.get("evaluate_vp"), "evaluate_vp", _EVALUATE_KEYS), VP_SELECT_CASES
        )
    elif top.data.get("evaluate_vp") is not None:
        raise ConfigError("evaluate_vp: there is no set to evaluate: add a [sets.vp] table")
    pipe = Pipeline(
        path=path,
        sha256=sha256,
        overrides=tuple(overrides),
        raw=json.loads(json.dumps(raw, default=str)),
        description=description,
        scale=scale,
        sets=sets,
        train_point=point,
        train_weight=weight,
        evaluate=evaluate,
        name=name,
        pretrain=pretrain,
        evaluate_vp=evaluate_vp,
        engine=engine,
        device=device,
        reference=_reference_spec(top, sets, base_dir),
        metacal=bool(metacal),
        moments_retry=float(moments_retry),
    )
    _check_columns(pipe)
    return pipe


def _reference_spec(
    top: Table, sets: Mapping[str, SetSpec], base_dir: Path | None
) -> ReferenceSpec | None:
    """``[reference]``: ``model`` (a model file, or the name of a shipped model) and ``set``."""
    if top.data.get("reference") is None:
        return None
    t = Table(top.data["reference"], "reference", set(REFERENCE_OPTION))
    if t.data.get("model") is None:
        raise ConfigError(
            "reference.model: missing (a model file, or a shipped model: "
            f"{', '.join(SHIPPED_MODELS)})"
        )
    text = t.option(REFERENCE_OPTION["model"])
    if text in SHIPPED_MODELS:
        model, label = (
            shipped_model(text),
            f"the shipped model {text} (models/{SHIPPED_MODELS[text]})",
        )
    else:
        model, label = resolve_path(text, "reference.model", base_dir), text
    default_set = REFERENCE_OPTION["set"].default
    set_name = t.get_str("set", default_set, [n for n in ALL_SETS if n in sets]) or default_set
    return ReferenceSpec(model, label, set_name, sha256_file(model))


def _check_pretrain(pre: PointSpec, point: PointSpec, spec: SetSpec) -> None:
    """The pretrained committees must fit train_point, which starts from them (by name, else by
    position)."""
    for i, t in enumerate(point.targets):
        if t not in pre.targets and i >= len(pre.targets):
            raise ConfigError(
                f"pretrain.targets: no committee to start train_point's {t} from "
                f"({len(pre.targets)} pretraining target(s) for {len(point.targets)})"
            )
    overlap = sorted(set(point.features) & set(pre.targets))
    if overlap:
        raise ConfigError(f"pretrain.targets: {overlap[0]!r} is also a feature of train_point")
    s = spec.config.structure
    varying = [
        t for t in pre.targets if t in ("tru_e1", "tru_e2", "tru_theta")
    ]  # change with the angle
    if pre.cost == "msb" and varying and (s.varies("angle") or s.snc != "none"):
        raise ConfigError(
            f"sets.pretrain: the target {varying[0]} changes within a case (rotated realizations) "
            "but the MSB cost needs one value per case: use per_realization = [] and "
            'snc = "none" (Fig. 6 structure)'
        )


def _probe_columns(spec: SetSpec) -> list[str]:
    """The columns the set's catalog will have: draw and measure its first case once."""
    from megalut_cli.sim.draw import WorkUnit, draw_unit  # numba, SciPy: when a pipeline is checked

    s = spec.config.structure
    small = spec.config.with_structure(n_cases=1, n_realizations=2 if s.snc == "pairs" else 1)
    try:
        cols = draw_unit(WorkUnit(small, spec.seed, 0, 1, 1, False, True))["columns"]
    except MegalutError as err:
        raise type(err)(f"sets.{spec.name}: {err}") from None
    return ["x", "y", *cols]


def _require(names: Sequence[str], available: Sequence[str], key: str, where: str) -> None:
    missing = [n for n in names if n not in available]
    if missing:
        raise ConfigError(
            f"{key}: no column {', '.join(map(repr, missing))} in the {where} catalog"
        )


def _check_columns(pipe: Pipeline) -> None:
    """Check every column the steps use against what the simulations will produce."""
    from megalut_cli.shear.evaluate import check_by  # scipy: only when a pipeline is checked

    cols = {n: _probe_columns(s) for n, s in pipe.sets.items()}
    pipe.columns.update(cols)
    tp, tw, ev = pipe.train_point, pipe.train_weight, pipe.evaluate
    if not {"tru_g1", "tru_g2"} <= set(tp.targets):
        raise ConfigError(
            "train_point.targets: the pipeline evaluates shear: the targets must include "
            "tru_g1, tru_g2"
        )
    needs = [  # (key, columns, the sets that must have them)
        (
            "train_point.features",
            tp.features,
            ("tp", "tw", "vo"),
        ),  # trained on tp, predicted on tw, vo
        ("train_point.targets", tp.targets, ("tp", "tw")),
        ("train_weight.features", tw.features or [], ("tw", "vo")),
        ("sets.vo", ["case", "tru_g1", "tru_g2"], ("vo",)),
    ]
    pre, evp = pipe.pretrain, pipe.evaluate_vp
    if pre is not None:
        needs += [
            ("train_point.features", tp.features, ("pretrain",)),
            ("pretrain.targets", pre.targets, ("pretrain",)),
        ]
    if evp is not None:
        needs += [
            ("train_point.features", tp.features, ("vp",)),
            ("sets.vp", ["case", "tru_g1", "tru_g2"], ("vp",)),
        ]
    for key, names, where in needs:
        for name in where:
            _require(names, cols[name], key, name)
    predicted = cols["vo"] + ["pre_g1", "pre_g2", "pre_g1_w", "pre_g2_w"]
    check_by(ev.by, predicted, "evaluate.by", "the vo catalog")
    checks = [
        (tp.select_cases, cols["tp"], True, "train_point.select_cases"),
        (tw.select, cols["tw"], False, "train_weight.select"),
        (ev.select, predicted, False, "evaluate.select"),
        (ev.select_cases, predicted, True, "evaluate.select_cases"),
    ]
    if pre is not None:
        checks.append((pre.select_cases, cols["pretrain"], True, "pretrain.select_cases"))
    if evp is not None:
        vp_predicted = cols["vp"] + ["pre_g1", "pre_g2"]  # point estimates only: no weights on VP
        check_by(evp.by, vp_predicted, "evaluate_vp.by", "the vp catalog")
        checks += [
            (evp.select, vp_predicted, False, "evaluate_vp.select"),
            (evp.select_cases, vp_predicted, True, "evaluate_vp.select_cases"),
        ]
    for expr, available, case_mode, key in checks:
        if expr is not None:
            try:
                check_expression(expr, available, case_mode=case_mode)
            except MegalutError as err:
                raise ConfigError(f"{key}: {err}") from None


def _tables_at(raw: Mapping[str, Any], where: Sequence[str]) -> list[dict[str, Any]]:
    """The tables of ``raw`` at the dotted position ``where`` (``"*"``: every sub-table)."""
    found: list[Any] = [raw]
    for part in where:
        found = [sub for t in found for sub in (t.values() if part == "*" else [t.get(part)])]
        found = [t for t in found if isinstance(t, dict)]
    return found


def _rebase_paths(raw: dict[str, Any], base_dir: Path) -> None:
    """Make the relative ``path`` options (:data:`PATH_TABLES`) of an extended file absolute
    where they name a file beside it; others (a shipped model's name, a file relative to the
    current folder) stay as written."""
    for where, options in PATH_TABLES:
        for table in _tables_at(raw, where):
            for option in options:
                text = table.get(option.name)
                if option.kind != "path" or not isinstance(text, str) or not text.strip():
                    continue
                path = Path(text).expanduser()
                if not path.is_absolute() and (base_dir / path).exists():
                    table[option.name] = str(base_dir / path)


def read_pipeline_file(
    path: str | os.PathLike, _chain: tuple[Path, ...] = ()
) -> tuple[dict[str, Any], str]:
    """Parse a pipeline file, merged over the file it ``extends`` (recursively); return
    (raw, sha256).

    The sha256 covers every file of the chain. Relative set configs of an extended file
    stay relative to that file.
    """
    p = Path(path).resolve()
    raw, sha = read_toml(p)
    base = raw.pop("extends", None)
    if base is None:
        return raw, sha
    if not isinstance(base, str) or not base.strip():
        raise ConfigError(f"{path}: extends: expected the path of a pipeline file, got {base!r}")
    base_path = (p.parent / Path(base).expanduser()).resolve()
    if base_path == p or base_path in _chain:
        cycle = " -> ".join(x.name for x in (*_chain, p, base_path))
        raise ConfigError(f"{path}: extends: {base!r} makes a cycle ({cycle})")
    if len(_chain) >= MAX_EXTENDS:
        raise ConfigError(f"{path}: extends: more than {MAX_EXTENDS} files in the chain")
    if not base_path.is_file():
        raise InputError(f"{path}: extends: no such file {str(base_path)!r}")
    base_raw, base_sha = read_pipeline_file(base_path, (*_chain, p))
    _rebase_paths(base_raw, base_path.parent)
    return merge_tables(base_raw, raw), sha_text([base_sha, sha])


def load_pipeline(path: str | os.PathLike | None = None, overrides: Sequence[str] = ()) -> Pipeline:
    """Read and validate a pipeline file (``None``: the embedded default)."""
    if path is None:
        ref = importlib.resources.files("megalut_cli").joinpath("data", DEFAULT_PIPELINE)
        with importlib.resources.as_file(ref) as p:
            raw, sha = read_toml(p)
        return parse_pipeline(raw, f"<default {DEFAULT_PIPELINE}>", sha, overrides, None)
    raw, sha = read_pipeline_file(path)
    return parse_pipeline(raw, str(path), sha, overrides, Path(path).resolve().parent)
