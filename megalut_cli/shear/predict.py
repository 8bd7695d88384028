"""Applying a trained shear model to a feature catalog (``megalut predict``).

For every point committee of the model (target ``tru_X``) the output gains ``pre_X``, the
committee mean, and for every weight committee ``pre_X_w``. Rows whose features failed
(``flags != 0``, or any model feature not finite) get NaN estimates, weight 0, and
:data:`megalut_cli.flags.BAD_FEATURES` OR-ed into ``flags`` (created when absent). All input
columns pass through unchanged.

The catalog is streamed in row chunks: the main process reads a chunk, sends the feature
matrix to a worker (or evaluates it itself), and appends the chunk with its predictions to
a temporary FITS file, renamed into place at the end. At most a few chunks are in flight,
so memory is bounded by the chunk size, not by the catalog. Workers (``-j``, Dask) load
the model once per process from its path (which must be readable there).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from megalut_cli import flags as _flags
from megalut_cli.atomic import check_output
from megalut_cli.catalog import (
    catalog_info,
    catalog_writer,
    iter_catalog,
    read_cards,
    read_carried_hdus,
    read_setup,
    setup_differences,
)
from megalut_cli.errors import ConfigError, InputError, Names, namer
from megalut_cli.measure.metacal_defaults import MDET_COLUMN, MDET_STEP_CARD, STEP_CARD, TYPES
from megalut_cli.nn.domain import (
    DOMAIN_PSF_COLUMNS,
    METACAL_ITEMS,
    UNITS,
    Finding,
    domain_findings,
    mode_domain,
    model_domain,
    shown,
    usable_rows,
)
from megalut_cli.nn.model import ShearModel, prediction_column
from megalut_cli.nn.population import REAL_BIAS_ATTR, SIMULATED_BIAS_ATTR
from megalut_cli.nn.symmetry import predict_with_symmetry
from megalut_cli.parallel import executor, map_ordered, resolve_nproc
from megalut_cli.progress import Progress, no_progress
from megalut_cli.provenance import own_or_parent
from megalut_cli.shear.bias import STAGE_IV_M
from megalut_cli.shear.options import PREDICT
from megalut_cli.shear.response import header_step

log = logging.getLogger(__name__)

#: Rows per chunk (work unit).
CHUNK_ROWS: int = PREDICT["chunk_rows"].default
FORMAT = "megalut.predictions"
FORMAT_VERSION = "1.0"


def resolve_columns(
    features: Sequence[str],
    available: Sequence[str],
    column_map: Mapping[str, str] | None,
    where: str,
    names: Names | None = None,
) -> dict[str, str]:
    """Catalog column of every model feature, checking everything at once.

    Raises :class:`ConfigError` for a ``column_map`` entry that is not a feature, and
    :class:`InputError` listing every feature without a column. Messages name
    ``column_map`` by ``names``.
    """
    key = namer(names)("column_map")
    column_map = dict(column_map or {})
    unknown = [f for f in column_map if f not in features]
    if unknown:
        raise ConfigError(
            f"{key} {', '.join(unknown)}: not a feature of the model "
            f"(its features: {', '.join(features)})"
        )
    have = set(available)
    resolved = {f: column_map.get(f, f) for f in features}
    missing = [
        f if resolved[f] == f else f"{f} ({key} {f}={resolved[f]})"
        for f in features
        if resolved[f] not in have
    ]
    if missing:
        raise InputError(
            f"{where}: missing column(s) for model feature(s) {', '.join(missing)}; "
            f"map differently named columns with {key} FEATURE=COLUMN"
        )
    return resolved


# --------------------------------------------------------------------------- core


def predict_arrays(
    model: ShearModel, x: np.ndarray, flags_in: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Predictions for a feature matrix ``x`` (rows x ``model.features``, in that order).

    Returns the ``pre_*`` columns (float64) and ``flags`` (input flags, or zeros, with
    ``BAD_FEATURES`` set on failed rows).
    """
    x = np.asarray(x, dtype=np.float64)
    n = x.shape[0]
    good = np.all(np.isfinite(x), axis=1)
    if flags_in is None:
        flags_out = np.zeros(n, dtype=np.int32)
    else:  # at least 16 bits, so that BAD_FEATURES (128) fits
        flags_out = np.asarray(flags_in).astype(
            np.promote_types(np.asarray(flags_in).dtype, np.int16)
        )
    if flags_in is not None:
        good &= flags_out == 0
    flags_out[~good] |= _flags.BAD_FEATURES
    xg = x[good] if not good.all() else x
    index = {f: i for i, f in enumerate(model.features)}
    out: dict[str, np.ndarray] = {}
    for is_weight, committees in ((False, model.point), (True, model.weight)):
        for committee in committees.values():
            cols = [index[f] for f in committee.features]
            sub = xg if cols == list(range(x.shape[1])) else xg[:, cols]
            values = np.full(n, 0.0 if is_weight else np.nan)
            pred = predict_with_symmetry(
                model.symmetry,
                committee.predict,
                sub,
                committee.features,
                committee.target,
                "weight" if is_weight else "point",
            )
            if is_weight:
                pred = np.where(np.isfinite(pred), pred, 0.0)
            values[good] = pred
            out[prediction_column(committee.target, "weight" if is_weight else "point")] = values
    out["flags"] = flags_out
    return out


def metacal_response_columns(
    preds: Mapping[str, Mapping[str, np.ndarray]], step: float
) -> dict[str, np.ndarray]:
    """``mcal_r<i><j> = (pre_g<i>_<j>p - pre_g<i>_<j>m) / (2 step)`` from the predictions of
    each metacal type (``preds[type]["pre_g1"]``...), for the components present."""
    out = {}
    for i in ("1", "2"):
        for j in ("1", "2"):
            col = f"pre_g{i}"
            if col in preds["noshear"]:
                out[f"mcal_r{i}{j}"] = (preds[f"{j}p"][col] - preds[f"{j}m"][col]) / (2.0 * step)
    return out


def predict_metacal(
    model: ShearModel,
    x_by_type: Mapping[str, np.ndarray],
    flags_by_type: Mapping[str, np.ndarray | None],
    step: float,
) -> dict[str, np.ndarray]:
    """Predictions for the five metacal versions: ``pre_*_<type>`` for every prediction column
    of :func:`predict_arrays`, ``flags_<type>`` (with ``BAD_FEATURES`` where the type's
    features failed) and the per-row responses ``mcal_r11, mcal_r12, mcal_r21, mcal_r22``."""
    preds = {
        kind: predict_arrays(model, x_by_type[kind], flags_by_type.get(kind)) for kind in TYPES
    }
    out: dict[str, np.ndarray] = {}
    for kind, pred in preds.items():
        for col, values in pred.items():
            out[f"{col}_{kind}"] = values
    out.update(metacal_response_columns(preds, step))
    return out


#: The metacal versions of rows, as :func:`predict_rows` takes them: ``(step, {type: X},
#: {type: flags})``.
MetacalInputs = tuple[float, Mapping[str, np.ndarray], Mapping[str, np.ndarray | None]]


def predict_columns(
    model: ShearModel,
    columns: Mapping[str, np.ndarray],
    column_map: Mapping[str, str] | None = None,
    metacal_step: float | None = None,
) -> dict[str, np.ndarray]:
    """In-memory prediction: the new columns (``pre_*`` and ``flags``) for a dict/Table of columns.

    With ``metacal_step`` (a metacal catalog: ``X_<type>`` columns), the columns ``predict``
    writes for one: also those of every metacal version and the responses
    (:func:`predict_rows`), in the catalog's order (:func:`prediction_columns`, then the flags).
    """
    names = list(columns.colnames) if hasattr(columns, "colnames") else list(columns)
    resolved = resolve_columns(model.features, names, column_map, "catalog")
    feature_cols = [resolved[f] for f in model.features]
    flags = np.asarray(columns["flags"]) if "flags" in names else None
    if metacal_step is None:
        return predict_arrays(model, _matrix(columns, feature_cols), flags)
    metacal = _metacal_inputs(columns, names, feature_cols, metacal_step)
    pred = predict_rows(model, None, flags, metacal)
    order = [*prediction_columns(model, True), *(c for c in pred if c.startswith("flags"))]
    return {c: pred[c] for c in order}


def prediction_columns(model: ShearModel, metacal: bool) -> list[str]:
    """The estimate columns ``predict`` adds for ``model``: ``pre_X`` per point committee,
    ``pre_X_w`` per weight committee, and for a ``metacal`` catalog those of every version
    (``pre_X_<type>``...) and the responses ``mcal_r<i><j>``."""
    cols = [prediction_column(c.target, c.kind) for c in model.point.values()]
    cols += [prediction_column(c.target, c.kind) for c in model.weight.values()]
    if not metacal:
        return cols
    plain = list(cols)  # in metacal mode: the noshear estimates, uncalibrated
    cols += [f"{c}_{kind}" for kind in TYPES for c in plain]
    cols += [f"mcal_r{i}{j}" for i in "12" for j in "12" if f"pre_g{i}" in plain]
    return cols


def prediction_cards(
    cards: Mapping[str, Any], model: ShearModel, model_path: str | os.PathLike, step: float | None
) -> dict[str, Any]:
    """The header cards of a predictions catalog: the features catalog's ``cards``, the
    model file's sha256 and name, and the metacal step of the responses (``step``)."""
    out = dict(cards)
    out["MODELSHA"] = (model.sha256, "sha256 of the model file")
    out["MODEL"] = (Path(model_path).name[:68], "model file")
    if step is not None:
        out[STEP_CARD] = (step, "metacal shear step of the mcal_r* responses")
    return out


_MODELS: dict[str, ShearModel] = {}


def _load_model(path: str, sha256: str | None = None) -> ShearModel:
    """The model at ``path``, loaded once per process (and checked against ``sha256``)."""
    model = _MODELS.get(str(path))
    if model is None or (sha256 and model.sha256 != sha256):
        model = ShearModel.load(path)
        if sha256 and model.sha256 != sha256:
            raise InputError(f"{path}: the model changed during the run (sha256 differs)")
        _MODELS.clear()
        _MODELS[str(path)] = model
    return model


def _predict_unit(unit: tuple[Any, ...]) -> dict[str, np.ndarray]:
    """Work unit: ``(model_path, model_sha256, X, flags, metacal)`` -> prediction columns
    (:func:`predict_rows`)."""
    path, sha, x, flg, metacal = unit
    return predict_rows(_load_model(path, sha), x, flg, metacal)


def predict_rows(
    model: Any,
    x: np.ndarray | None,
    flg: np.ndarray | None,
    metacal: MetacalInputs | None,
) -> dict[str, np.ndarray]:
    """The prediction columns of rows with features ``x`` (rows x ``model.features``) and
    ``flg``: :func:`predict_arrays`; or, for a metacal catalog (``metacal``: ``(step, {type:
    X}, {type: flags})``, ``x`` unused: None), :func:`predict_metacal` plus ``pre_X`` (the
    noshear estimate, uncalibrated) and ``flags`` (``flg`` with ``BAD_FEATURES`` where the
    noshear version failed)."""
    if metacal is None:
        return predict_arrays(model, x, flg)
    step, xs, flgs = metacal
    out = predict_metacal(model, xs, flgs, step)
    # pre_X: the (uncalibrated) noshear estimate; flags: the catalog's, and BAD_FEATURES where it
    # failed
    for col in list(out):
        if col.endswith("_noshear") and col.startswith("pre_"):
            out[col[: -len("_noshear")]] = out[col]
    failed = (np.asarray(out["flags_noshear"]) & _flags.BAD_FEATURES) != 0
    base = np.zeros(len(failed), dtype=np.int32) if flg is None else np.asarray(flg)
    base = base.astype(np.promote_types(base.dtype, np.int16))
    out["flags"] = base | np.where(failed, _flags.BAD_FEATURES, 0).astype(base.dtype)
    return out


def _matrix(table: Any, cols: Sequence[str]) -> np.ndarray:
    """The float64 matrix (rows x ``cols``) of a table chunk."""
    if not len(table):
        return np.zeros((0, len(cols)))
    return np.column_stack([np.asarray(table[c], dtype=np.float64) for c in cols])


def _metacal_inputs(
    table: Any, colnames: Sequence[str], feature_cols: Sequence[str], step: float
) -> MetacalInputs:
    """The ``metacal`` argument of :func:`predict_rows` for the rows of a metacal table."""
    xs = {kind: _matrix(table, [f"{c}_{kind}" for c in feature_cols]) for kind in TYPES}
    flgs = {
        kind: np.asarray(table[f"flags_{kind}"]) if f"flags_{kind}" in colnames else None
        for kind in TYPES
    }
    return step, xs, flgs


def _check_mode(
    model: ShearModel,
    step: float | None,
    model_path: Any,
    features_path: Any,
    metadetect: bool = False,
) -> None:
    """Refuse a metacal model on a plain catalog and a simulation-calibrated one on a metacal
    or metadetection catalog (whose rows a metacal model predicts one by one)."""
    if metadetect:
        if model.shear_mode != "metacal":
            raise InputError(
                f"{model_path} is a simulation-calibrated model and {features_path} a "
                f"metadetection catalog ({MDET_STEP_CARD} card): use a metacal model "
                f"({METACAL_MODEL_HINT})"
            )
        return
    if model.shear_mode == "metacal" and step is None:
        raise InputError(
            f"{model_path} is a metacal model and {features_path} a plain catalog "
            f"(no {STEP_CARD} card): measure with --metacal (and --psf), or use a "
            "simulation-calibrated model"
        )
    if model.shear_mode != "metacal" and step is not None:
        raise InputError(
            f"{model_path} is a simulation-calibrated model and {features_path} a metacal catalog "
            f"({STEP_CARD} card): use a metacal model ({METACAL_MODEL_HINT}), or measure without "
            "--metacal"
        )


#: Where the messages send users for a metacal model.
METACAL_MODEL_HINT = (
    "megalut info MODEL says its mode; the shipped one is megalut_cli/data/fiducial-metacal.h5"
)


def _metacal_step(header: Mapping[str, Any], path: str | os.PathLike) -> float | None:
    """The metacal step of a catalog (its ``MCALSTEP`` card), or None for a plain catalog."""
    if header.get(STEP_CARD) is None:
        return None
    step = header_step(header)
    if step is None or not 0 < step < 1:
        raise InputError(
            f"{path}: bad {STEP_CARD} card {header[STEP_CARD]!r}: expected the metacal shear step, "
            "e.g. 0.01"
        )
    return step


@dataclass
class PredictReport:
    """What ``predict_catalog`` did."""

    output: Path
    n_rows: int
    n_failed: int
    columns: list[str]
    model_sha256: str
    #: How the catalog lies outside the model's domain (:func:`domain_report`).
    findings: list[Finding] = field(default_factory=list)


def _fits_field(name: str, col: np.ndarray) -> tuple:
    """Field of a column as FITS stores it back (unicode as ASCII bytes, booleans as int16)."""
    base = col.dtype
    if base.kind == "U":
        base = np.dtype(f"S{max(base.itemsize // 4, 1)}")
    elif base.kind == "b":
        base = np.dtype(np.int16)
    return (name, base, col.shape[1:]) if col.ndim > 1 else (name, base)


def _output_dtype(table: Any, new_cols: Sequence[str]) -> np.dtype:
    """Input columns (as FITS stores them), prediction columns as float64, then ``flags``."""
    fields = [
        (c, np.float64) if c in new_cols else _fits_field(c, np.asarray(table[c]))
        for c in table.colnames
    ]
    fields += [(c, np.float64) for c in new_cols if c not in table.colnames]
    if "flags" not in table.colnames:
        fields.append(("flags", np.int32))
    else:  # as predict_arrays: at least 16 bits for BAD_FEATURES
        fields = [
            (c, np.promote_types(f[0], np.int16)) if c == "flags" else (c, *f) for c, *f in fields
        ]
    return np.dtype(fields)


def _trained_setup(model: ShearModel) -> dict[str, Any]:
    """The setup the model records (its own training set's, else its point training set's)."""
    return dict(own_or_parent(model.provenance, "setup") or {})


def setup_findings(trained: Mapping[str, Any], applied: Mapping[str, Any]) -> list[Finding]:
    """One :class:`Finding` (item ``setup``) naming every item of the recorded setups (PSF,
    noise, stamp size, gain: a model's ``trained``, a catalog's ``applied``) that both record
    and that differ; none when they agree."""
    diffs = setup_differences(trained, applied)
    if not diffs:
        return []
    return [
        Finding(
            "setup",
            f"recorded setup differs from the model's training set (trained vs here): "
            f"{'; '.join(diffs)}",
        )
    ]


def applied_domain(model: ShearModel) -> tuple[dict[str, Any] | None, list[str]]:
    """The domain ``predict`` compares catalogs with, and the recorded items it leaves out:
    the model's (:func:`megalut_cli.nn.domain.model_domain`), with the stamp size of its setup
    when the domain has none and, for a simulation-calibrated model trained on a constant PSF,
    that PSF's measured size and ellipticity when the domain does not record them (models
    recorded before); restricted to the items of the model's shear mode
    (:func:`megalut_cli.nn.domain.mode_domain`)."""
    domain = model_domain(model.provenance)
    if domain is None:
        return None, []
    trained = _trained_setup(model)
    if domain.get("stamp_size") is None and trained.get("stamp_size") is not None:
        domain["stamp_size"] = trained["stamp_size"]
    if model.shear_mode != "metacal":
        from megalut_cli.nn.fit import config_psf_domain  # GalSim: only to draw the PSF

        population = own_or_parent(model.provenance, "population") or {}
        domain = config_psf_domain(domain, population.get("psf"))
    return mode_domain(domain, model.shear_mode)


def _all_nan(columns: Mapping[str, np.ndarray], names: Sequence[str], rows: np.ndarray) -> bool:
    """Whether none of ``names`` has a finite value in the rows ``rows`` (absent: none)."""
    return not any(
        np.isfinite(np.asarray(columns[c], dtype=np.float64)[rows]).any()
        for c in names
        if c in columns
    )


def catalog_column(
    name: str, colnames: Sequence[str], resolved: Mapping[str, str] | None, metacal: bool
) -> str | None:
    """The catalog column of a domain item or model feature ``name``: through its
    ``resolved`` column, the ``noshear`` version's in a metacal catalog; None when absent."""
    base = (resolved or {}).get(name, name)
    column = f"{base}_noshear" if metacal and f"{base}_noshear" in colnames else base
    return column if column in colnames else None


#: Most rows the domain check keeps: of a larger catalog, every k-th row (a systematic
#: sample; memory stays bounded as predict's own).
MAX_DOMAIN_ROWS = 1_000_000


#: Rows per chunk of :func:`domain_rows` (a few columns: small chunks keep its memory below
#: predict's own).
DOMAIN_CHUNK_ROWS = 10_000


@dataclass
class RowCounts:
    """How many rows a catalog has, how many are flagged and how many usable (unflagged, every
    model feature finite); the features not finite in any unflagged row."""

    n_rows: int
    n_flagged: int
    n_usable: int
    never_finite: list[str]


@dataclass
class DomainRows:
    """What the domain check reads of a catalog (:func:`domain_rows`): the counts of its rows
    and its columns of the model's domain, by their domain names (empty without a domain)."""

    counts: RowCounts
    columns: dict[str, np.ndarray]


def domain_rows(
    features_path: str | os.PathLike,
    features: Sequence[str],
    colnames: Sequence[str],
    resolved: Mapping[str, str] | None = None,
    metacal: bool = False,
    domain: Mapping[str, Any] | None = None,
    n_rows: int | None = None,
    extra: Sequence[str] = (),
) -> DomainRows:
    """The catalog's rows as the domain check sees them, in one pass chunk by chunk over the
    columns it needs: the :class:`RowCounts` of every row (``flags`` and the model's
    ``features``) and, with a ``domain``, the columns of the domain, ``flags`` and ``extra``
    (every row; every k-th of a catalog of more than :data:`MAX_DOMAIN_ROWS` rows ``n_rows``).
    A model feature is read through its ``resolved`` column, and for a metacal catalog the
    ``noshear`` version's column where there is one."""
    flags = catalog_column("flags", colnames, None, metacal)
    cols = {f: catalog_column(f, colnames, resolved, metacal) for f in features}
    wanted: dict[str, str] = {}
    if domain is not None:
        for c in dict.fromkeys([*domain.get("columns", {}), "flags", *extra]):
            column = catalog_column(c, colnames, None if c == "flags" else resolved, metacal)
            if column is not None:
                wanted[c] = column
    kept = list(dict.fromkeys(wanted.values()))
    counted = [*(c for c in cols.values() if c), *([flags] if flags else [])]
    read = list(dict.fromkeys([*counted, *kept]))
    step = 1 if n_rows is None or n_rows <= MAX_DOMAIN_ROWS else -(-n_rows // MAX_DOMAIN_ROWS)
    parts: dict[str, list[np.ndarray]] = {column: [] for column in kept}
    n = flagged = usable = 0
    seen = dict.fromkeys(features, False)
    for table in iter_catalog(features_path, DOMAIN_CHUNK_ROWS, columns=read or None):
        m = len(table)
        bad = np.asarray(table[flags]) != 0 if flags else np.zeros(m, dtype=bool)
        good = ~bad
        for f, c in cols.items():
            finite = np.isfinite(np.asarray(table[c], dtype=np.float64)) if c else np.zeros(m, bool)
            seen[f] |= bool((finite & ~bad).any())
            good &= finite
        first = (-n) % step  # the chunk's first row whose index is a multiple of step
        for column in kept:
            parts[column].append(np.asarray(table[column])[first::step])
        n, flagged, usable = n + m, flagged + int(bad.sum()), usable + int(good.sum())
    never = [f for f, ok in seen.items() if not ok] if n > flagged else []
    columns = {c: np.concatenate(parts[column]) for c, column in wanted.items()}
    return DomainRows(RowCounts(n, flagged, usable, never), columns)


def usable_findings(counts: RowCounts) -> list[Finding]:
    """The finding (item ``rows``) of a catalog without a usable row, saying why: its flagged
    rows, and the model features not finite in any unflagged row (a model that needs PSF
    measurements given a catalog measured without a PSF); none when a row is usable."""
    if counts.n_usable:
        return []
    if not counts.n_rows:
        return [Finding("rows", "no usable row: the catalog has no row")]
    why = f"{counts.n_flagged} flagged (flags != 0)"
    rest = counts.n_rows - counts.n_flagged
    if rest:
        why += f", {rest} with a non-finite model feature"
    if counts.never_finite:
        why += f" ({', '.join(counts.never_finite)} not finite in any unflagged row"
        if any(f in DOMAIN_PSF_COLUMNS for f in counts.never_finite):
            why += ": measure with a PSF"
        why += ")"
    return [
        Finding("rows", f"no usable row: of all {counts.n_rows} rows, {why}; nothing to estimate")
    ]


def _usable(columns: Mapping[str, np.ndarray], features: Sequence[str]) -> np.ndarray:
    """``flags == 0`` and every model feature finite, over the (sampled) domain columns."""
    good = usable_rows(columns, len(next(iter(columns.values()))) if columns else 0)
    for f in features:
        if f in columns:
            good &= np.isfinite(np.asarray(columns[f], dtype=np.float64))
    return good


def setup_psf_columns(
    domain: Mapping[str, Any],
    columns: Mapping[str, np.ndarray],
    rows: np.ndarray,
    setup: Mapping[str, Any],
) -> dict[str, np.ndarray]:
    """For a catalog without PSF measurements whose setup records a constant PSF (a simulated
    catalog's ``[psf]``): that PSF's ``psf_adamom_sigma, _g1, _g2`` as ``measure --psf`` would
    find them on its stamp (every row), so that they are compared with the model's as measured
    ones would be (the setup comparison ignores a key one side leaves to its default, such as
    the ellipticity of a PSF sheared by ``g2``). Empty when the catalog measures its PSF, the
    model records none or the setup has no drawable PSF."""
    psf, stamp = setup.get("psf"), setup.get("stamp_size")
    recorded = [c for c in DOMAIN_PSF_COLUMNS if c in domain.get("columns", {})]
    if not recorded or not isinstance(psf, Mapping) or not stamp:
        return {}
    if not _all_nan(columns, DOMAIN_PSF_COLUMNS, rows):
        return {}
    from megalut_cli.sim.psf import measured_psf_shape  # GalSim: only to draw the PSF

    shape = measured_psf_shape(psf, int(stamp))
    if shape is None:
        return {}
    n = len(rows)
    return {c: np.full(n, value) for c, value in zip(DOMAIN_PSF_COLUMNS, shape)}


def psf_findings(
    domain: Mapping[str, Any],
    columns: Mapping[str, np.ndarray],
    rows: np.ndarray,
    setup: Mapping[str, Any],
) -> list[Finding]:
    """One finding (item ``psf``) when the model's domain records the training PSF but the
    catalog carries no PSF measurement (no finite ``psf_adamom_*`` in its usable rows) and
    records no PSF in its setup: nothing shows that its PSF is the model's."""
    recorded = [c for c in DOMAIN_PSF_COLUMNS if c in domain.get("columns", {})]
    if not recorded or "psf" in setup or not _all_nan(columns, DOMAIN_PSF_COLUMNS, rows):
        return []
    trained = ", ".join(
        f"{c} {shown(domain['columns'][c], domain['columns'][c]['q'][3])}{UNITS.get(c, '')}"
        for c in recorded
    )
    return [
        Finding(
            "psf",
            f"no PSF measurement ({', '.join(DOMAIN_PSF_COLUMNS)} missing or NaN) and no "
            f"recorded PSF: nothing shows the PSF is the model's (trained at {trained}); "
            "measure with a PSF (--psf, --psf-model or the MEDS file's PSF cutouts)",
        )
    ]


def validation_findings(validation: Mapping[str, Any]) -> list[Finding]:
    """One finding (item ``validation``) per record of the model's own bias (its simulated
    validation, :data:`megalut_cli.nn.population.SIMULATED_BIAS_ATTR`; a real-galaxy record
    of the model's m, quantity ``m_real``) whose |m| of a component exceeds the Stage IV
    requirement :data:`megalut_cli.shear.bias.STAGE_IV_M` (a real-galaxy record of ``m_real -
    m_twin`` is a difference, not the model's m: not judged here, ``info`` tells it)."""
    out = []
    sim = validation.get(SIMULATED_BIAS_ATTR)
    if isinstance(sim, Mapping):
        m = {g: (sim.get(f"m_{g}"), sim.get(f"m_{g}_err")) for g in ("g1", "g2")}
        what = f"simulated validation ({sim.get('scheme')}, {sim.get('input')})"
        out += _stage_iv(m, what)
    real = validation.get(REAL_BIAS_ATTR)
    if isinstance(real, Mapping) and real.get("quantity") == "m_real":
        m = {g: (real.get(f"dm_{g}"), real.get(f"dm_{g}_err")) for g in ("g1", "g2")}
        out += _stage_iv(m, f"real galaxies ({real.get('scheme')})")
    return out


def _stage_iv(m: Mapping[str, tuple[Any, Any]], what: str) -> list[Finding]:
    values = {
        g: (float(v), float(e) if e is not None else float("nan"))
        for g, (v, e) in m.items()
        if isinstance(v, (int, float))
    }
    if not any(abs(v) > STAGE_IV_M for v, _ in values.values()):
        return []
    parts = ", ".join(f"m{g[1]} = {v:+.2e} ± {e:.1e}" for g, (v, e) in values.items())
    return [
        Finding(
            "validation",
            f"the model's recorded bias on its {what}: {parts}, outside the Stage IV "
            f"requirement |m| < {STAGE_IV_M:.0e}",
        )
    ]


def domain_report(
    model: ShearModel,
    features_path: str | os.PathLike,
    *,
    colnames: Sequence[str],
    header: Mapping[str, Any],
    resolved: Mapping[str, str] | None = None,
    metacal: bool = False,
    n_rows: int | None = None,
    applied: tuple[dict[str, Any] | None, list[str]] | None = None,
) -> list[Finding]:
    """How the catalog ``features_path`` lies outside ``model``'s domain
    (:func:`applied_domain`, the items of its shear mode; ``applied`` when already known):
    no usable row (``flags == 0`` and finite model features; the ``noshear`` columns of a
    metacal catalog) is one finding and
    the only one of the catalog; else the findings of
    :func:`megalut_cli.nn.domain.domain_findings` on its usable rows and stamp size
    (``STAMPSZ``, else the ``box_size`` column), a missing PSF (:func:`psf_findings`) and,
    for a simulation-calibrated model, those of :func:`setup_findings` on the setups both
    record (the stamp size once). The model's own recorded bias
    (:func:`validation_findings`) is judged in any case."""
    trained = _trained_setup(model)
    domain, _ = applied if applied is not None else applied_domain(model)
    extra = [*model.features, "box_size", *DOMAIN_PSF_COLUMNS]
    read = domain_rows(
        features_path, model.features, colnames, resolved, metacal, domain, n_rows, extra
    )
    findings = usable_findings(read.counts)
    if findings:  # nothing to compare
        return findings + validation_findings(model.validation)
    setup = read_setup(features_path) if model.shear_mode != "metacal" else {}
    if domain is not None:
        columns = read.columns
        rows = _usable(columns, model.features)
        if model.shear_mode != "metacal":
            columns = {**columns, **setup_psf_columns(domain, columns, rows, setup)}
        if rows.any():  # (a sample of a large catalog may hold none)
            stamp = header.get("STAMPSZ")
            findings += domain_findings(
                domain,
                columns,
                int(stamp) if isinstance(stamp, (int, np.integer)) else None,
                usable=rows,
            )
            findings += psf_findings(domain, columns, rows, setup)
        trained.pop("stamp_size", None)
    if trained and model.shear_mode != "metacal":
        findings += setup_findings(trained, setup)
    return findings + validation_findings(model.validation)


def check_domain(
    model: ShearModel,
    model_path: str | os.PathLike,
    features_path: str | os.PathLike,
    *,
    colnames: Sequence[str],
    header: Mapping[str, Any],
    resolved: Mapping[str, str] | None = None,
    metacal: bool = False,
    n_rows: int | None = None,
    strict: bool = False,
    names: Names | None = None,
) -> list[Finding]:
    """:func:`domain_report`, told: a warning per finding and one saying what they mean, or
    with ``strict`` an :class:`InputError` listing them (before anything is written)."""
    name = Path(model_path).name
    applied = applied_domain(model)  # once: it may draw the training PSF
    findings = domain_report(
        model,
        features_path,
        colnames=colnames,
        header=header,
        resolved=resolved,
        metacal=metacal,
        n_rows=n_rows,
        applied=applied,
    )
    if findings and strict:
        raise InputError(
            f"{features_path} lies outside the domain of {name} ({namer(names)('strict')}): "
            + "; ".join(map(str, findings))
        )
    if model_domain(model.provenance) is None:
        log.info(
            "%s records no domain (quantiles of its training rows): only its recorded setup is "
            "compared with %s",
            name,
            features_path,
        )
    dropped = applied[1]
    if dropped:
        log.info(
            "%s is a metacal model: its response absorbs the PSF and the noise to first order, "
            "so only %s are compared (not %s, nor the stamp size and the recorded setup)",
            name,
            " and ".join(METACAL_ITEMS),
            ", ".join(d for d in dropped if d != "stamp_size"),
        )
    for f in findings:
        log.warning("%s: %s", features_path, f)
    if findings:
        log.warning(
            "%s: %d finding(s) against the training domain of %s: the estimates may be biased "
            "(megalut info shows what the model was trained on)",
            features_path,
            len(findings),
            name,
        )
    return findings


def predict_catalog(
    features_path: str | os.PathLike,
    model_path: str | os.PathLike,
    output: str | os.PathLike,
    *,
    column_map: Mapping[str, str] | None = None,
    nproc: int = 1,
    scheduler: str | None = None,
    overwrite: bool = False,
    chunk_rows: int = CHUNK_ROWS,
    strict: bool = PREDICT["strict"].default,
    progress: Progress | None = None,
    names: Names | None = None,
) -> PredictReport:
    """Predict shears for every row of ``features_path`` into ``output`` (see module doc).

    The catalog is first compared with the model's domain (:func:`check_domain`): warnings,
    or with ``strict`` an error and nothing written. ``progress`` counts the rows as they
    are written (all of the catalog's); messages name the arguments by ``names``.
    """
    check_output(output, overwrite)
    if Path(output).resolve() == Path(features_path).resolve():
        raise ConfigError("the output must not be the input catalog")
    n_rows, colnames, header = catalog_info(features_path)
    abs_model = str(Path(model_path).resolve())
    model = ShearModel.load(abs_model)  # always fresh here; workers reuse it by hash
    _MODELS.clear()
    _MODELS[abs_model] = model
    resolved = resolve_columns(model.features, colnames, column_map, str(features_path), names)
    has_flags = "flags" in colnames
    step = _metacal_step(header, features_path)
    metadetect = header.get(MDET_STEP_CARD) is not None or MDET_COLUMN in colnames
    if metadetect and step is not None:
        raise InputError(
            f"{features_path}: both a metacal ({STEP_CARD}) and a metadetection "
            f"({MDET_STEP_CARD}) catalog"
        )
    _check_mode(model, step, model_path, features_path, metadetect)
    if step is not None:
        missing = [
            f"{c}_{kind}"
            for kind in TYPES
            for c in [*(resolved[f] for f in model.features), "flags"]
            if f"{c}_{kind}" not in colnames
        ]
        if missing:
            raise InputError(
                f"{features_path}: a metacal catalog ({STEP_CARD} card) without the metacal "
                f"column(s) {', '.join(missing)}"
            )
    findings = check_domain(
        model,
        model_path,
        features_path,
        colnames=colnames,
        header=header,
        resolved=resolved,
        metacal=step is not None,
        n_rows=n_rows,
        strict=strict,
        names=names,
    )
    new_cols = prediction_columns(model, step is not None)
    replaced = [c for c in new_cols if c in colnames]
    if replaced:
        log.warning("%s: replacing existing column(s) %s", features_path, ", ".join(replaced))
    cards = prediction_cards(read_cards(features_path), model, model_path, step)  # with comments
    extra_hdus = read_carried_hdus(features_path)
    feature_cols = [resolved[f] for f in model.features]
    n_failed = 0

    def units() -> Iterator[tuple[Any, tuple]]:
        for table in iter_catalog(features_path, chunk_rows):
            x = _matrix(table, feature_cols) if step is None else None
            flg = np.asarray(table["flags"]) if has_flags else None
            metacal = (
                None if step is None else _metacal_inputs(table, table.colnames, feature_cols, step)
            )
            yield table, (abs_model, model.sha256, x, flg, metacal)

    with (
        executor(nproc, scheduler, -(-n_rows // chunk_rows)) as pool,
        (progress or no_progress)("predict", n_rows) as update,
    ):
        window = 2 * resolve_nproc(nproc) if scheduler is None else 16
        with catalog_writer(
            output,
            fmt=FORMAT,
            fmt_version=FORMAT_VERSION,
            overwrite=overwrite,
            cards=cards,
            history=header.get("HISTORY"),
            extra_hdus=extra_hdus,
        ) as writer:
            dtype = None
            for table, pred in map_ordered(_predict_unit, units(), pool, window):
                if dtype is None:
                    dtype = _output_dtype(table, new_cols)
                arr = np.zeros(len(table), dtype=dtype)
                for c in table.colnames:
                    if c not in pred:
                        col = np.asarray(table[c])
                        arr[c] = np.char.encode(col, "ascii") if col.dtype.kind == "U" else col
                for c, v in pred.items():
                    arr[c] = v
                n_failed += int(np.count_nonzero(pred["flags"] & _flags.BAD_FEATURES))
                writer.append(arr)
                update(len(table))
    if n_failed:
        log.info(
            "%d of %d rows have failed features (NaN estimates, flag BAD_FEATURES)",
            n_failed,
            n_rows,
        )
    return PredictReport(Path(output), n_rows, n_failed, new_cols, model.sha256, findings)
