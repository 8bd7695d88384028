"""Training of shear estimators: in memory (:func:`fit_point`, :func:`fit_weight`) and
file to file (:func:`train_point`, :func:`train_weight`, ``megalut train-point/-weight``).

What a training is, is one spec (:data:`megalut_cli.nn.options.PointSpec`,
:data:`~megalut_cli.nn.options.WeightSpec`), which the command line and the pipelines build
and pass whole. :func:`fit_point` trains one committee of point estimators per target with
the MSB cost (paper Sect. 5.1) on a table of columns, optionally continuing from an earlier
model (pretraining, Sect. 6), and returns a :class:`ShearModel`. :func:`fit_weight` predicts
the point estimates of a model on a weight-training table and trains one committee of weight
networks per target with the MSWB cost (Sect. 5.2); the model it returns holds both. The
file functions read the catalogs, add the provenance of the files and write the model.
Messages name the options (``select_cases``...) or, given ``names``, the caller's words
for them (``--select-cases`` of the command line, ``train_point.select_cases`` of a
pipeline file). Nothing here needs GalSim or click.

Masked realizations: rows with ``flags != 0`` (when the column exists), with a non-finite
feature, (for weights) with a non-finite point estimate or outside ``select``. Cases left
without any valid realization are dropped (a warning, or an info line when a selection
removed them); an error is raised when fewer than two cases remain.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from megalut_cli.atomic import check_output
from megalut_cli.catalog import (
    CatalogColumns,
    VersionColumns,
    catalog_info,
    read_setup,
    require_columns,
)
from megalut_cli.errors import ConfigError, InputError, namer
from megalut_cli.expr import check_expression, columns_used, evaluate_cases, evaluate_rows
from megalut_cli.measure.metacal_defaults import STEP_CARD
from megalut_cli.nn import normalization as norm
from megalut_cli.nn.committee import CommitteeSpec, train_committees
from megalut_cli.nn.data import CaseData, build_cases, split_cases, valid_rows
from megalut_cli.nn.defaults import DEFAULT_FEATURES, INIT_SCHEMES, POINT_COSTS, WEIGHT_COST
from megalut_cli.nn.domain import (
    DOMAIN_COLUMNS,
    DOMAIN_KEY,
    DOMAIN_PSF_COLUMNS,
    PSF_G_TOLERANCE,
    PSF_SIZE_TOLERANCE,
    domain_record,
    with_constant_column,
)
from megalut_cli.nn.model import Committee, ShearModel, component_name
from megalut_cli.nn.network import Network
from megalut_cli.nn.options import POINT_OPTION, WEIGHT_OPTION, PointSpec, TrainSpec, WeightSpec
from megalut_cli.nn.population import training_population
from megalut_cli.nn.symmetry import predict_with_symmetry
from megalut_cli.nn.train import TrainSettings
from megalut_cli.parallel import executor
from megalut_cli.progress import Progress, no_progress
from megalut_cli.provenance import command_line, recorded_path, sha256_file, software_versions
from megalut_cli.seeding import STREAM_SPLIT, rng_for

log = logging.getLogger(__name__)

#: The declared defaults of a point training's features, targets and hidden layers and of a
#: weight training's hidden layers.
DEFAULT_TARGETS = list(POINT_OPTION["targets"].default)
DEFAULT_POINT_HIDDEN = tuple(POINT_OPTION["hidden"].default)
DEFAULT_WEIGHT_HIDDEN = tuple(WEIGHT_OPTION["hidden"].default)
#: How a committee's training record names a training option it knew by another name.
RECORDED_NAMES = {"precision": "dtype"}
#: A table of columns: a dict of column name to array, an astropy Table, or a
#: :class:`megalut_cli.catalog.CatalogColumns` reading a catalog's columns on demand.
Columns = Mapping[str, Any]


def training_columns(path: str | os.PathLike) -> tuple[Columns, str]:
    """The columns a model trains on, and its shear mode: a metacal catalog (``MCALSTEP``
    card, ``measure``/``simulate --metacal``) trains on the ``noshear`` version's features."""
    columns = CatalogColumns(path)
    if catalog_info(path)[2].get(STEP_CARD) is None:
        return columns, "simulation"
    log.info(
        "%s: a metacal catalog: training on the features of its noshear versions (a metacal model)",
        path,
    )
    return VersionColumns(columns, "noshear"), "metacal"


def _validation_columns(
    train: str | os.PathLike, valid: str | os.PathLike | None, mode: str, name: Callable[[str], str]
) -> Columns | None:
    """The columns of the validation catalog, which must have the training catalog's mode."""
    if valid is None:
        return None
    columns, valid_mode = training_columns(valid)
    if valid_mode != mode:
        raise InputError(
            f"{name('valid')} {valid} and {name('train')} {train}: one is a metacal catalog, the "
            "other not"
        )
    return columns


def _unique(items: Sequence[str], what: str) -> list[str]:
    items = [str(i) for i in items]
    dup = sorted({i for i in items if items.count(i) > 1})
    if dup:
        raise ConfigError(f"duplicate {what}: {', '.join(dup)}")
    if not items:
        raise ConfigError(f"no {what} given")
    return items


def column_names(table: Columns) -> list[str]:
    """The column names of a table (an astropy Table iterates over rows, a mapping over names)."""
    return list(table.colnames) if hasattr(table, "colnames") else list(table)


def _take_columns(
    table: Columns, where: str, required: Sequence[str], optional: Sequence[str] = ()
) -> dict[str, np.ndarray]:
    names = column_names(table)
    require_columns(names, required, where)
    use = list(dict.fromkeys([*required, *(c for c in optional if c in names)]))
    if isinstance(table, (CatalogColumns, VersionColumns)):
        table.load(use)  # one pass over the file
    return {c: np.asarray(table[c]) for c in use}


def _select_cases(
    columns: Mapping[str, np.ndarray], ok: np.ndarray, expr: str, where: str, name: str
) -> np.ndarray:
    """Restrict ``ok`` to the cases selected by a case expression (evaluated on valid rows)."""
    if not ok.any():
        return ok
    sub = {c: np.asarray(columns[c])[ok] for c in columns_used(expr)}
    ids, sel = evaluate_cases(expr, sub, np.asarray(columns["case"])[ok])
    if not sel.any():
        raise ConfigError(f"{name} {expr!r} selects no case of {where}")
    log.info("%s: %s keeps %d of %d cases", where, name, int(sel.sum()), len(ids))
    return ok & np.isin(columns["case"], ids[sel])


def _load_cases(
    table: Columns,
    where: str,
    features: Sequence[str],
    targets: Sequence[str],
    *,
    constant_targets: bool,
    select_cases: str | None = None,
    select_rows: str | None = None,
    point_model: ShearModel | None = None,
    name: Callable[[str], str] | None = None,
    with_domain: bool = True,
) -> tuple[CaseData, dict[str, Any] | None]:
    """Group a table's rows into cases (see the module docstring for masking); and the
    domain of its usable rows (:func:`megalut_cli.nn.domain.domain_record`; ``None``
    without ``with_domain``)."""
    name = name or namer(None)
    names = column_names(table)
    extra = []
    for expr, case_mode in ((select_cases, True), (select_rows, False)):
        if expr:
            check_expression(expr, names, case_mode=case_mode)
            extra += columns_used(expr)
    point_features = point_model.features if point_model is not None else []
    required = list(dict.fromkeys(["case", *features, *point_features, *targets]))
    domain_columns = DOMAIN_COLUMNS if with_domain else ()
    columns = _take_columns(table, where, required, ["flags", *extra, *domain_columns])
    n = len(columns["case"])
    ok = valid_rows(columns, list(dict.fromkeys([*features, *point_features])), n)
    point = None
    if point_model is not None:
        point = {}
        for t in targets:
            comm = point_model.point[t]
            x = np.column_stack([np.asarray(columns[f], dtype=np.float64) for f in comm.features])
            # the point estimates the weights will multiply, as predict makes them
            point[t] = predict_with_symmetry(
                point_model.symmetry, comm.predict, x, comm.features, t, "point"
            )
            ok &= np.isfinite(point[t])
    measured = ok.copy()
    if select_rows:
        sel = evaluate_rows(select_rows, {c: columns[c] for c in columns_used(select_rows)}, n)
        if not sel.any():
            raise ConfigError(f"{name('select')} {select_rows!r} selects no row of {where}")
        log.info("%s: %s keeps %d of %d rows", where, name("select"), int(sel.sum()), n)
        ok &= sel
    if select_cases:
        ok = _select_cases(columns, ok, select_cases, where, name("select_cases"))
    data = build_cases(
        columns,
        features,
        targets,
        ok,
        where=where,
        constant_targets=constant_targets,
        point=point,
        measured=measured,
    )
    in_cases = np.isin(columns["case"], data.case_ids)
    log.info(
        "%s: %d cases, %d valid realizations (%d masked)",
        where,
        data.n_cases,
        data.n_rows,
        int(in_cases.sum()) - data.n_rows,
    )
    return data, domain_record(columns, ok & in_cases) if with_domain else None


def _load_split(
    train: Columns,
    train_name: str,
    valid: Columns | None,
    valid_name: str,
    spec: TrainSpec,
    features: Sequence[str],
    targets: Sequence[str],
    **load: Any,
) -> tuple[CaseData, CaseData | None, str, dict[str, Any]]:
    """Training and validation cases: from ``valid``, or a held-out fraction of ``train``;
    a description of the validation set; the domain of ``train`` (all its usable rows).
    ``load`` goes to :func:`_load_cases`."""
    name = load.get("name", namer(None))
    data, domain = _load_cases(train, train_name, features, targets, **load)
    if valid is not None:
        return (
            data,
            _load_cases(valid, valid_name, features, targets, with_domain=False, **load)[0],
            valid_name,
            domain,
        )
    if spec.valid_fraction <= 0:
        log.warning(
            "no validation set (%s 0): members are monitored and selected on the training set",
            name("valid_fraction"),
        )
        return data, None, "training set", domain
    tr, va = split_cases(data.n_cases, spec.valid_fraction, rng_for(spec.seed, STREAM_SPLIT))
    if len(tr) < 2:
        raise InputError(
            f"only {data.n_cases} cases: too few to hold out a validation fraction; "
            f"use {name('valid')} or {name('valid_fraction')} 0"
        )
    log.info(
        "holding out %d of %d cases for validation (%s %g)",
        len(va),
        data.n_cases,
        name("valid_fraction"),
        spec.valid_fraction,
    )
    return data.subset(tr), data.subset(va), f"held-out fraction {spec.valid_fraction:g}", domain


def _identity_feature(target: str, features: Sequence[str]) -> int:
    comp = component_name(target)
    candidates = [comp] + (["g" + comp[1:]] if comp.startswith("e") else [])
    for c in candidates:
        for i, f in enumerate(features):
            if f == c or f.endswith("_" + c):
                return i
    return 0


def _input(path: str | os.PathLike, sha256: str | None = None) -> dict[str, str]:
    """How a model records an input file: its name and sha256 (its identity) and, for
    information only, a path never absolute (:func:`megalut_cli.provenance.recorded_path`)."""
    return {
        "name": Path(path).name,
        "path": recorded_path(path),
        "sha256": sha256 or sha256_file(path),
    }


def _spread(values: np.ndarray) -> float:
    s = float(np.std(values))
    return s if np.isfinite(s) and s > 0 else 1.0


def _training_record(
    spec: TrainSpec,
    device: str,
    command: str,
    cost: str,
    valid_desc: str,
    tdata: CaseData,
    vdata: CaseData | None,
    **extra: Any,
) -> dict[str, Any]:
    """What a committee records of its training: the training options (named as
    :data:`RECORDED_NAMES` says) and the device, the data sizes and ``extra``."""
    return {
        **{RECORDED_NAMES.get(name, name): value for name, value in spec.train_values().items()},
        "device": device,
        "command": command,
        "cost": cost,
        **extra,
        "validation": valid_desc,
        "n_train_cases": tdata.n_cases,
        "n_train_rows": tdata.n_rows,
        "n_valid_cases": vdata.n_cases if vdata is not None else 0,
        "n_valid_rows": vdata.n_rows if vdata is not None else 0,
    }


def _check_architecture(
    features: Sequence[str],
    targets: Sequence[str],
    hidden: Sequence[int],
    name: Callable[[str], str],
) -> None:
    overlap = sorted(set(features) & set(targets))
    if overlap:
        raise ConfigError(f"column(s) {', '.join(overlap)} cannot be both a feature and a target")
    if any(h < 1 for h in hidden):
        raise ConfigError(f"{name('hidden')} sizes must be positive integers")


def _provenance(
    command: str,
    inputs: dict[str, Any],
    seed: int,
    parent: Mapping[str, Any] | None = None,
    setup: Mapping[str, Any] | None = None,
    population: Mapping[str, Any] | None = None,
    domain: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The provenance of a trained model: command line, versions, inputs, seed, the training
    catalog's observing setup (:func:`megalut_cli.catalog.read_setup`), population (read
    from the training catalog itself, never from a recorded path), domain
    (:mod:`megalut_cli.nn.domain`) and parent model."""
    prov: dict[str, Any] = {
        "command": command,
        "argv": command_line(),
        "versions": software_versions(),
        "inputs": inputs,
        "seed": seed,
    }
    if setup:
        prov["setup"] = dict(setup)
    if population is not None:
        prov["population"] = dict(population)
    if domain:
        prov[DOMAIN_KEY] = dict(domain)
    if parent is not None:
        prov["parent"] = parent
    return prov


def _file_domain(
    prov: Mapping[str, Any],
    train: str | os.PathLike,
    setup: Mapping[str, Any],
    mode: str,
    population: Mapping[str, Any] | None,
) -> dict[str, Any]:
    """The domain :func:`fit_point`/:func:`fit_weight` recorded, with the training catalog's
    stamp size (``STAMPSZ`` card) and file name, for a metacal model the version its
    columns are of (``noshear``), and the PSF size of its ``population``'s constant PSF."""
    domain = dict(prov.get(DOMAIN_KEY) or {})
    if domain:
        domain["stamp_size"] = setup.get("stamp_size")
        domain["source"] = Path(train).name
        if mode == "metacal":
            domain["version"] = "noshear"
        domain = config_psf_domain(domain, (population or {}).get("psf"))
    return domain


def config_psf_domain(domain: Mapping[str, Any], psf: Any) -> dict[str, Any]:
    """``domain`` with the ``psf_adamom_sigma, psf_adamom_g1, psf_adamom_g2`` of a constant
    training PSF (the ``[psf]`` table drawn as ``measure --psf`` sees it on a stamp of the
    domain's ``stamp_size``), for those the training rows do not measure; ``domain`` as it is
    without a stamp size, without a ``psf`` table, or when it records them all."""
    stamp_size = domain.get("stamp_size")
    recorded = domain.get("columns", {})
    if not stamp_size or not isinstance(psf, Mapping) or not psf:
        return dict(domain)
    if all(c in recorded for c in DOMAIN_PSF_COLUMNS):
        return dict(domain)
    from megalut_cli.sim.psf import measured_psf_shape  # GalSim: only when a PSF must be drawn

    shape = measured_psf_shape(psf, int(stamp_size))
    if shape is None:
        return dict(domain)
    source = "the training config's [psf], drawn with the pixel on the stamp and measured"
    out = with_constant_column(domain, "psf_adamom_sigma", shape[0], PSF_SIZE_TOLERANCE, source)
    for column, value in zip(("psf_adamom_g1", "psf_adamom_g2"), shape[1:]):
        out = with_constant_column(out, column, value, PSF_G_TOLERANCE, source, absolute=True)
    return out


def fit_point(
    train: Columns,
    spec: PointSpec | None = None,
    *,
    valid: Columns | None = None,
    init_model: ShearModel | None = None,
    device: str = "cpu",
    nproc: int = 1,
    scheduler: str | None = None,
    progress: Progress | None = None,
    sources: Mapping[str, str] | None = None,
    names: Mapping[str, str] | None = None,
) -> ShearModel:
    """Train point-estimate committees (one per target) on the table ``train`` as ``spec``
    says (default: every option's declared default).

    ``init_model``: continue its point committees (by target, else by position); the
    spec's ``features`` and ``hidden`` ``None`` are then those of the model (else the
    defaults). ``device``: where the costs and gradients run (a resolved one: ``cpu`` or
    ``gpu``). ``sources`` names the tables and the initial model in logs and records (keys
    ``train``, ``valid``, ``init_model``); ``names`` how messages name the options. The
    model's provenance holds the command, versions and seed (the file functions add their
    inputs).
    """
    spec = spec or PointSpec()
    name = namer(names)
    src_names = {"train": "train", "valid": "valid", "init_model": "init_model", **(sources or {})}
    init_from = src_names["init_model"]
    spec.check()
    _check_point_arguments(spec)
    targets = _unique(spec.targets or DEFAULT_TARGETS, "targets")
    init_comms: dict[str, Committee] = {}
    if init_model is not None:
        available = list(init_model.point.values())
        if not available:
            raise InputError(f"{init_from}: the model has no point committee to start from")
        for i, t in enumerate(targets):
            src = init_model.point.get(t) or (available[i] if i < len(available) else None)
            if src is None:
                raise InputError(f"{init_from}: no committee to initialise target {t} from")
            if src.target != t:
                log.info("initialising %s from the %s committee of %s", t, src.target, init_from)
            init_comms[t] = src
    features = spec.features
    if features is None:
        features = (
            next(iter(init_comms.values())).features if init_comms else list(DEFAULT_FEATURES)
        )
    features = _unique(features, "features")
    for src in init_comms.values():
        if src.features != features:
            raise InputError(
                f"{init_from}: the {src.target} committee's features ({', '.join(src.features)}) "
                f"do not match the features ({', '.join(features)})"
            )
        if spec.hidden is not None and tuple(spec.hidden) != src.hidden:
            raise ConfigError(
                f"{name('hidden')} {','.join(map(str, spec.hidden))} differs from the architecture "
                f"of {init_from} ({','.join(map(str, src.hidden))}); leave {name('hidden')} out to "
                "continue that model"
            )
    hidden = (
        tuple(spec.hidden)
        if spec.hidden is not None
        else (next(iter(init_comms.values())).hidden if init_comms else DEFAULT_POINT_HIDDEN)
    )
    _check_architecture(features, targets, hidden, name)

    tdata, vdata, valid_desc, domain = _load_split(
        train,
        src_names["train"],
        valid,
        src_names["valid"],
        spec,
        features,
        targets,
        constant_targets=spec.cost != "mse",
        select_cases=spec.select_cases,
        name=name,
    )

    committee_specs = []
    for j, t in enumerate(targets):
        src = init_comms.get(t)
        if src is not None:
            in_loc, in_scale, out_loc, out_scale = (
                src.in_loc,
                src.in_scale,
                src.out_loc,
                src.out_scale,
            )
            method = src.normalization
            ranked = sorted(range(len(src.members)), key=lambda k: (not src.members[k].selected, k))
            init_members = [src.members[k] for k in ranked]
        else:
            in_loc, in_scale = norm.fit(tdata.x, spec.normalization, features)
            method = spec.normalization
            out_loc = float(np.mean(tdata.targets[:, j]))
            out_scale = _spread(tdata.targets[:, j])
            init_members = None
        net = Network(len(features), hidden, "identity", out_loc, out_scale)
        training = _training_record(
            spec,
            device,
            "train-point",
            spec.cost,
            valid_desc,
            tdata,
            vdata,
            select_cases=spec.select_cases,
            init_from=init_from if init_model is not None else None,
            init_scheme="model" if src is not None else spec.init,
        )
        committee_specs.append(
            CommitteeSpec(
                kind="point",
                target=t,
                j=j,
                net=net,
                in_loc=in_loc,
                in_scale=in_scale,
                train=tdata,
                valid=vdata,
                members=spec.members,
                keep=spec.keep,
                cost_scale=out_scale,
                init_scheme=spec.init,
                identity_feature=_identity_feature(t, features),
                init_members=init_members,
                normalization=method,
                training=training,
            )
        )
    settings = TrainSettings.of(spec, spec.cost, device)
    committees = _run(committee_specs, settings, spec.seed, nproc, scheduler, progress)
    parent = init_model.provenance if init_model is not None else None
    domain.update(source=src_names["train"], selection=spec.select_cases)
    prov = _provenance("train-point", {}, spec.seed, parent, domain=domain)
    return ShearModel(point=committees, provenance=prov)


def _check_point_arguments(spec: PointSpec) -> None:
    """Check the cost, the initialisation and the case selection's syntax of a point training."""
    if spec.cost not in POINT_COSTS:
        raise ConfigError(f"unknown cost {spec.cost!r} for point estimates (choose msb or mse)")
    if spec.init not in INIT_SCHEMES:
        raise ConfigError(f"unknown initialisation {spec.init!r}")
    if spec.select_cases is not None:
        check_expression(spec.select_cases, None, case_mode=True)


def train_point(
    train: str | os.PathLike,
    output: str | os.PathLike,
    spec: PointSpec | None = None,
    *,
    valid: str | os.PathLike | None = None,
    init_from: str | os.PathLike | None = None,
    device: str = "cpu",
    nproc: int = 1,
    scheduler: str | None = None,
    overwrite: bool = False,
    progress: Progress | None = None,
    names: Mapping[str, str] | None = None,
) -> ShearModel:
    """:func:`fit_point` on the catalog ``train`` (continuing the model file ``init_from``
    when given); write the model to ``output``."""
    spec = spec or PointSpec()
    spec.check()
    out = check_output(output, overwrite)
    _check_point_arguments(spec)
    init_model = ShearModel.load(init_from) if init_from is not None else None
    sources = {"train": str(train), "valid": str(valid), "init_model": str(init_from)}
    train_columns, mode = training_columns(train)
    model = fit_point(
        train_columns,
        spec,
        valid=_validation_columns(train, valid, mode, namer(names)),
        init_model=init_model,
        device=device,
        nproc=nproc,
        scheduler=scheduler,
        progress=progress,
        sources=sources,
        names=names,
    )
    inputs = {"train": _input(train)}
    if valid is not None:
        inputs["valid"] = _input(valid)
    if init_model is not None:
        inputs["init_from"] = _input(init_from, init_model.sha256)
    setup, population = read_setup(train), training_population(train)
    model.provenance = _provenance(
        "train-point",
        inputs,
        model.provenance["seed"],
        init_model.provenance if init_model is not None else None,
        setup,
        population,
        _file_domain(model.provenance, train, setup, mode, population),
    )
    model.shear_mode = mode
    model.save(out, overwrite=overwrite)
    log.info("wrote %s (sha256 %s)", out, model.sha256[:12])
    return model


def _run(
    specs: Sequence[CommitteeSpec],
    settings: TrainSettings,
    seed: int,
    nproc: int,
    scheduler: str | None,
    progress: Progress | None,
) -> dict[str, Committee]:
    n_units = sum(s.members for s in specs)
    if settings.device == "gpu" and not scheduler:
        nproc = 1  # one process feeds the device
    log.info(
        "training %d committee(s) x %d members, %d iterations each (%s, batches of %g of the "
        "cases x %d iterations)",
        len(specs),
        specs[0].members,
        settings.iterations,
        settings.cost,
        settings.batch_fraction,
        settings.batch_iterations,
    )
    with (
        executor(nproc, scheduler, n_units) as pool,
        (progress or no_progress)("members trained", n_units) as update,
    ):
        return train_committees(specs, settings, seed, pool, update)


def fit_weight(
    train: Columns,
    point_model: ShearModel,
    spec: WeightSpec | None = None,
    *,
    valid: Columns | None = None,
    device: str = "cpu",
    nproc: int = 1,
    scheduler: str | None = None,
    progress: Progress | None = None,
    sources: Mapping[str, str] | None = None,
    names: Mapping[str, str] | None = None,
) -> ShearModel:
    """Train weight committees (MSWB) on the table ``train`` for every point committee of
    ``point_model`` as ``spec`` says (default: every option's declared default; ``features``
    ``None``: those of the point model); return a model with both (provenance: command,
    versions, seed, parent).

    ``device``: where the costs and gradients run (``cpu`` or ``gpu``). ``sources`` names
    the tables and the point model (keys ``train``, ``valid``, ``model``); ``names`` how
    messages name the options.
    """
    spec = spec or WeightSpec()
    name = namer(names)
    src_names = {"train": "train", "valid": "valid", "model": "model", **(sources or {})}
    spec.check()
    if spec.select is not None:
        check_expression(spec.select, None, case_mode=False)
    if not point_model.point:
        raise InputError(f"{src_names['model']}: the model has no point committee")
    targets = list(point_model.point)
    features = _unique(point_model.features if spec.features is None else spec.features, "features")
    hidden = tuple(spec.hidden) if spec.hidden is not None else DEFAULT_WEIGHT_HIDDEN
    _check_architecture(features, targets, hidden, name)

    tdata, vdata, valid_desc, domain = _load_split(
        train,
        src_names["train"],
        valid,
        src_names["valid"],
        spec,
        features,
        targets,
        constant_targets=True,
        select_rows=spec.select,
        point_model=point_model,
        name=name,
    )
    in_loc, in_scale = norm.fit(tdata.x, spec.normalization, features)
    committee_specs = []
    for j, t in enumerate(targets):
        net = Network(len(features), hidden, "sigmoid4")
        training = _training_record(
            spec,
            device,
            "train-weight",
            WEIGHT_COST,
            valid_desc,
            tdata,
            vdata,
            select=spec.select,
            point_model_sha256=point_model.sha256 or None,
        )
        committee_specs.append(
            CommitteeSpec(
                kind="weight",
                target=t,
                j=j,
                net=net,
                in_loc=in_loc,
                in_scale=in_scale,
                train=tdata,
                valid=vdata,
                members=spec.members,
                keep=spec.keep,
                cost_scale=_spread(tdata.targets[:, j]),
                normalization=spec.normalization,
                training=training,
            )
        )
    settings = TrainSettings.of(spec, WEIGHT_COST, device)
    committees = _run(committee_specs, settings, spec.seed, nproc, scheduler, progress)
    domain.update(source=src_names["train"], selection=spec.select)
    prov = _provenance("train-weight", {}, spec.seed, point_model.provenance, domain=domain)
    out = ShearModel(point=point_model.point, weight=committees, provenance=prov)
    out.symmetry = point_model.symmetry  # the weights are trained for these point estimates
    return out


def train_weight(
    train: str | os.PathLike,
    model: str | os.PathLike,
    output: str | os.PathLike,
    spec: WeightSpec | None = None,
    *,
    valid: str | os.PathLike | None = None,
    device: str = "cpu",
    nproc: int = 1,
    scheduler: str | None = None,
    overwrite: bool = False,
    progress: Progress | None = None,
    names: Mapping[str, str] | None = None,
) -> ShearModel:
    """:func:`fit_weight` on the catalog ``train`` and the model file ``model``; write the
    model with both kinds of committees to ``output``."""
    spec = spec or WeightSpec()
    spec.check()
    out = check_output(output, overwrite)
    if Path(out).resolve() == Path(model).resolve():
        raise ConfigError(
            f"{namer(names)('output')} {output} would replace the input model; choose another "
            "output file"
        )
    if spec.select is not None:
        check_expression(spec.select, None, case_mode=False)
    point_model = ShearModel.load(model)
    train_columns, mode = training_columns(train)
    valid_columns = _validation_columns(train, valid, mode, namer(names))
    if point_model.shear_mode != mode:
        raise InputError(
            f"{model} is a {point_model.shear_mode} model and {train} "
            f"{'a metacal' if mode == 'metacal' else 'a plain'} "
            "catalog: train the weights on a catalog of the point model's mode"
        )
    result = fit_weight(
        train_columns,
        point_model,
        spec,
        valid=valid_columns,
        device=device,
        nproc=nproc,
        scheduler=scheduler,
        progress=progress,
        sources={"train": str(train), "valid": str(valid), "model": str(model)},
        names=names,
    )
    inputs = {"train": _input(train), "model": _input(model, point_model.sha256)}
    if valid is not None:
        inputs["valid"] = _input(valid)
    setup, population = read_setup(train), training_population(train)
    result.provenance = _provenance(
        "train-weight",
        inputs,
        result.provenance["seed"],
        point_model.provenance,
        setup,
        population,
        _file_domain(result.provenance, train, setup, mode, population),
    )
    result.shear_mode = mode
    result.save(out, overwrite=overwrite)
    log.info("wrote %s (sha256 %s)", out, result.sha256[:12])
    return result
