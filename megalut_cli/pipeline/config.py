"""Pipeline-file validation shared by the standard and GREAT3 pipelines of ``megalut run``.

The declarations of the top-level keys (:data:`PIPELINE_OPTIONS`) and of the ``[sets.X]``
keys (:data:`SET_OPTIONS`) of a pipeline file, read with :class:`~megalut_cli.schema.Table`
and shown in ``docs/pipeline.md``; :func:`merge_tables` (``extends`` and
``[sets.X.simulation]`` overrides); the training tables, read into the specs of
:mod:`megalut_cli.nn.options` (:func:`read_spec`), and the evaluation tables; the embedded
default pipeline.
"""

from __future__ import annotations

import copy
import importlib.resources
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from megalut_cli.configfile import (
    ConfigSource,
    config_source,
    has_key,
    message_keys,
    override_for,
    parse_override,
    table_key,
    tomllib,
    written_at,
)
from megalut_cli.configfile import where_written as config_where_written
from megalut_cli.engine import DEVICE_OPTION, ENGINE_OPTION
from megalut_cli.errors import ConfigError, MegalutError
from megalut_cli.expr import check_expression
from megalut_cli.measure.options import MEASURE
from megalut_cli.nn.options import OPTION as TRAIN_OPTION
from megalut_cli.nn.options import SELECTIONS, PointSpec, TrainSpec, WeightSpec
from megalut_cli.schema import Option, Table
from megalut_cli.sim.config import STRUCTURE

#: The embedded default pipeline (package data).
DEFAULT_PIPELINE = "default_pipeline.toml"
#: Seeds of the sets when the file gives none (all different).
DEFAULT_SET_SEEDS = {"tp": 1, "tw": 2, "vo": 3, "pretrain": 4, "vp": 5}
#: The defaults of the training tables that are the pipeline's own (the others: those of
#: ``megalut train-point``/``train-weight``): each training its own seed; the pretraining
#: learns the ellipticity (paper Sects. 4.4 and 6).
TRAIN_TABLE_DEFAULTS: dict[str, dict[str, Any]] = {
    "pretrain": {"targets": ["tru_e1", "tru_e2"], "seed": 3},
    "train_point": {},
    "train_weight": {"seed": 2},
}
#: How ``scale`` shrinks a set: the exponents of ``scale`` for (n_cases, n_realizations).
SCALE_BY = {"both": (0.5, 0.5), "cases": (1.0, 0.0), "realizations": (0.0, 1.0)}
#: Most characters of a pipeline's ``name``.
MAX_NAME = 64

#: The top-level keys of a pipeline file (``docs/pipeline.md``, "Top level"). ``extends`` is
#: read with the file (:func:`megalut_cli.pipeline.file.read_pipeline_file`), the tables by their
#: own readers.
PIPELINE_OPTIONS: tuple[Option, ...] = (
    Option("description", "str", "", "free text", empty_ok=True),
    Option(
        "name",
        "str",
        "",
        "a subfolder of the work folder for the products of the steps after the "
        "simulations; see above",
        empty_ok=True,
        allowed_text=f"letters, digits, `_`, `-` (at most {MAX_NAME})",
    ),
    Option(
        "extends",
        "path",
        None,
        "a pipeline file this one changes; see above (in a file only, not as an override)",
    ),
    Option(
        "scale",
        "float",
        1.0,
        "fraction of the stamps to simulate: shrinks (or grows) every set, see `scale_by`",
        minimum=0,
        min_open=True,
    ),
    replace(
        ENGINE_OPTION,
        help='stamp engine of the simulations: `"fast"` (batched rendering, compiled '
        'adaptive moments) or `"galsim"` (the reference); see [engines.md](engines.md). Part of '
        "the simulation steps' keys: changing it re-runs them",
    ),
    replace(
        DEVICE_OPTION,
        help='where the simulations and trainings run: `"cpu"`, `"gpu"` (the optional '
        'JAX backend; one clear error if none is usable) or `"auto"` (gpu when found); see '
        "[gpu.md](gpu.md). Not part of the steps' keys (results agree within the tolerances of "
        "gpu.md), like `-j`",
    ),
    Option(
        "metacal",
        "bool",
        False,
        "measure every set in metacal mode too (each stamp deconvolved by its PSF, "
        "sheared by ±0.01, reconvolved; docs/metacal.md): the networks train on the features of "
        "the noshear versions (a metacal model), the predictions get the responses "
        "`mcal_r11`..`mcal_r22` and `evaluate` reports the response-calibrated biases; a "
        "`[reference]` model must then be a metacal one "
        '(`"fiducial-metacal"`). Part of the simulation steps\' keys',
    ),
    replace(
        MEASURE["moments_retry"],
        help="step factor of the adaptive moments' damped retry on the stamps whose iteration "
        "fails (`measure --moments-retry`, [catalogs.md](catalogs.md)); 0: none. Part of the "
        "simulation steps' keys when set",
    ),
    Option(
        "simulation",
        "table",
        None,
        "a simulation config (any table of docs/config.md) shared by the sets without `config`",
    ),
    Option(
        "sets",
        "table",
        None,
        "the simulated sets: `[sets.tp]`, `[sets.tw]`, `[sets.vo]` (required), "
        "`[sets.pretrain]` (enables `pretrain-point`) and `[sets.vp]` (enables `predict-vp`, "
        "`evaluate-vp`)",
        default_text="required",
    ),
    Option(
        "pretrain",
        "table",
        None,
        "pretraining of the point estimators (needs `[sets.pretrain]`)",
        default_text="see below",
    ),
    Option("train_point", "table", None, "point-estimator training", default_text="see below"),
    Option("train_weight", "table", None, "weight training", default_text="see below"),
    Option("evaluate", "table", None, "bias analysis on `vo`", default_text="see below"),
    Option(
        "evaluate_vp",
        "table",
        None,
        "bias analysis of the point estimates on `vp` (needs `[sets.vp]`)",
        default_text="see below",
    ),
    Option(
        "reference",
        "table",
        None,
        "a fixed model validated beside the one trained here (needs `model`)",
        default_text="see below",
    ),
)
PIPELINE = {o.name: o for o in PIPELINE_OPTIONS}

#: The keys of a ``[sets.X]`` table.
SET_OPTIONS: tuple[Option, ...] = (
    Option(
        "config",
        "path",
        None,
        "a simulation config file (docs/config.md), relative to the pipeline file; "
        "without it the top-level `[simulation]` table is the base",
    ),
    Option(
        "simulation",
        "table",
        None,
        'a table merged over the base config, e.g. `{structure = {snc = "pairs"}}`',
    ),
    replace(
        STRUCTURE["n_cases"], help="overrides `structure.n_cases`", default_text="the config's"
    ),
    replace(
        STRUCTURE["n_realizations"],
        help="overrides `structure.n_realizations`",
        default_text="the config's",
    ),
    Option(
        "seed",
        "int",
        None,
        "seed of every random draw of the set; **the seeds of the sets must differ**",
        minimum=0,
        default_text=", ".join(f"{k} {v}" for k, v in DEFAULT_SET_SEEDS.items()),
    ),
    Option(
        "scale_by",
        "choice",
        "both",
        'how `scale` shrinks the set: `"both"` multiplies n_cases and '
        'n_realizations by sqrt(scale), `"cases"` n_cases by scale, `"realizations"` '
        "n_realizations by scale",
        choices=tuple(SCALE_BY),
    ),
)
SET_OPTION = {o.name: o for o in SET_OPTIONS}

#: The keys of the ``[reference]`` table.
REFERENCE_OPTIONS: tuple[Option, ...] = (
    Option(
        "model",
        "path",
        None,
        "a model file (relative to the pipeline file), or the name of a model shipped "
        'with megalut: `"fiducial"` (`models/fiducial.h5`, the paper-size model) or '
        '`"fiducial-1e6"` (`models/fiducial-1e6.h5`, the model shipped before it; '
        '[models/README.md](../models/README.md)), or `"fiducial-metacal"` (the networks of '
        "`fiducial` for metacal catalogs, [metacal.md](metacal.md)), or "
        '`"fiducial-metacal-d4"` and `"fiducial-d4"` (those networks averaged over the '
        "stamp's rotations and reflections: no additive bias of their own)",
        default_text="required",
        allowed_text="a path, or a shipped model's name",
    ),
    Option(
        "set",
        "str",
        "vo",
        "the set it is evaluated on, with the options of `[evaluate]`",
        allowed_text="a set of the pipeline",
    ),
)
REFERENCE_OPTION = {o.name: o for o in REFERENCE_OPTIONS}

#: The tables whose ``path`` options name files relative to the pipeline file: where they sit
#: in the file (``"*"``: every sub-table) and their declarations.
PATH_TABLES: tuple[tuple[tuple[str, ...], tuple[Option, ...]], ...] = (
    (("sets", "*"), SET_OPTIONS),
    (("reference",), REFERENCE_OPTIONS),
)


@dataclass(frozen=True)
class EvaluateSpec:
    by: list[str]
    bins: int
    select: str | None
    select_cases: str | None
    plot: bool


def merge_tables(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """Deep-merge ``over`` into a copy of ``base``; a table with a ``type`` key replaces, not
    merges."""
    out = copy.deepcopy(dict(base))
    for k, v in over.items():
        if isinstance(v, Mapping) and "type" not in v and isinstance(out.get(k), Mapping):
            out[k] = merge_tables(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


#: The keys of a ``[train_point]`` and a ``[train_weight]`` table (standard and GREAT3 pipelines).
TRAIN_POINT_KEYS = {o.name for o in PointSpec.OPTIONS}
TRAIN_WEIGHT_KEYS = {o.name for o in WeightSpec.OPTIONS}
#: ``plot`` of an ``[evaluate]`` table (its other keys: the options of ``megalut evaluate``).
PLOT_OPTION = Option(
    "plot", "bool", True, "draw the evaluation's figure (when matplotlib is installed)"
)


def read_spec(spec_class: type[TrainSpec], t: Table, **defaults: Any) -> Any:
    """The training spec of the table ``t``, read with the declarations of ``spec_class``
    (:mod:`megalut_cli.nn.options`); ``defaults`` (by key) are the pipeline's own. Selections
    are syntax-checked (their columns later), ``""`` meaning none."""
    values = {}
    for o in spec_class.OPTIONS:
        if o.name in SELECTIONS:
            values[o.name] = selection_expression(t, o, SELECTIONS[o.name], defaults.get(o.name))
        elif o.name not in TRAIN_OPTION:  # those: checked together, by from_values
            values[o.name] = t.option(o, defaults.get(o.name))
    shared = {k: v for k, v in t.data.items() if k in TRAIN_OPTION}
    return spec_class.from_values({**values, **shared}, t.where, defaults)


def key_names(table: str) -> dict[str, str]:
    """How library messages name their arguments: keys of the table ``table`` of the pipeline
    file."""
    return {
        arg: f"{table}.{arg}"
        for arg in ("select_cases", "select", "hidden", "valid_fraction", "by")
    }


def selection_expression(
    t: Table, option: Option, case_mode: bool, default: str | None = None
) -> str | None:
    """The selection expression of the declared ``option``, syntax-checked (columns are
    checked later); ``""`` means none."""
    if t.data.get(option.name) == "":
        return None
    expr = t.option(option, default)
    if expr is not None:
        try:
            check_expression(expr, None, case_mode=case_mode)
        except MegalutError as err:
            raise ConfigError(f"{t.key(option.name)}: {err}") from None
    return expr


def default_pipeline_text() -> str:
    """The text of the embedded default pipeline."""
    return importlib.resources.files("megalut_cli").joinpath("data", DEFAULT_PIPELINE).read_text()


# --------------------------------------------------------------------------- where a key is written
#: Set keys that the pipeline copies into the set's ``structure``.
_SET_STRUCTURE_KEYS = ("n_cases", "n_realizations")


def _display(path: Path) -> str:
    try:
        return os.path.relpath(path)
    except ValueError:  # pragma: no cover - another drive on Windows
        return str(path)


def _chain(path: str | os.PathLike | None) -> list[ConfigSource]:
    """The files of a pipeline, the given one first, then those it ``extends``; the embedded
    default for ``None``."""
    if path is None:
        text = default_pipeline_text()
        return [ConfigSource("the default pipeline", tomllib.loads(text), text)]
    out: list[ConfigSource] = []
    p, name = Path(path), str(path)
    seen: set[Path] = set()
    while p.is_file() and p.resolve() not in seen and len(out) < 32:
        seen.add(p.resolve())
        src = config_source(p, name)
        if src is None:
            break
        out.append(src)
        base = src.raw.get("extends")
        if not isinstance(base, str) or not base.strip():
            break
        p = (p.resolve().parent / Path(base).expanduser()).resolve()
        name = _display(p)
    return out


def _get(raw: Any, parts: Sequence[str]) -> Any:
    return (
        raw
        if not parts
        else (_get(raw.get(parts[0]), parts[1:]) if isinstance(raw, Mapping) else None)
    )


def _set_key(
    name: str, key: list[str], chain: Sequence[ConfigSource], overrides: Sequence[str]
) -> str | None:
    """Where the simulation key ``key`` of the set ``name`` comes from: an override, the
    set's ``simulation`` table (or its ``n_cases``/``n_realizations``), its ``config``
    file, or the top-level ``[simulation]``."""
    if len(key) == 2 and key[0] == "structure" and key[1] in _SET_STRUCTURE_KEYS:
        found = written_at(["sets", name, key[1]], chain, overrides)
        if found:
            return found
    found = written_at(["sets", name, "simulation", *key], chain, overrides)
    if found:
        return found
    config = written_at(["sets", name, "config"], chain, overrides)
    if config is not None:
        override = override_for(["sets", name, "config"], overrides)
        if override is not None:  # a path given on the command line: from the current folder
            okey, value = parse_override(override)
            value, base = (
                _get({"v": value}, ["v", *["sets", name, "config"][len(okey) :]]),
                Path.cwd(),
            )
        else:
            src = next(s for s in chain if has_key(s.raw, ["sets", name, "config"]))
            value, base = _get(src.raw, ["sets", name, "config"]), Path(src.name).resolve().parent
        if isinstance(value, str):
            for candidate in (
                base / Path(value).expanduser(),
                Path.cwd() / Path(value).expanduser(),
            ):
                if candidate.is_file():
                    try:
                        return f"{_display(candidate)}: {table_key(candidate.read_text(), key)}"
                    except (OSError, UnicodeDecodeError):
                        break
        return None
    return written_at(["simulation", *key], chain, overrides)


def where_written(
    message: str, path: str | os.PathLike | None, overrides: Sequence[str] = ()
) -> str:
    """A pipeline-file error ``message`` (``sets.tp: noise.sigam: unknown key``) naming the
    key where the user wrote it: the file and its table (``pipeline.toml: [simulation.noise]
    sigam: unknown key``), a set's simulation config file, or the dotted key of a ``KEY=VALUE``
    override (:func:`megalut_cli.configfile.where_written` for the keys outside the sets).
    ``message`` is returned as it is when its key is not found."""
    chain = _chain(path)
    if not chain:
        return message
    top = {*chain[0].raw, *PIPELINE, "branch"}
    keys, rest = message_keys(message, top, [s.name for s in chain])
    first = keys[0].split(".") if keys else []
    if first[:1] == ["sets"] and len(first) == 2 and len(keys) > 1:
        found = _set_key(first[1], ".".join(keys[1:]).split("."), chain, overrides)
        return message if found is None else f"{found}: {rest}"
    return config_where_written(message, chain, overrides, top)
