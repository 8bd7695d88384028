"""Running a GREAT3 branch pipeline (:mod:`megalut_cli.pipeline.great3_file`): its steps over
the step engine (:mod:`megalut_cli.pipeline.steps`).

Every subfield is one :class:`~megalut_cli.pipeline.steps.Unit` (``-j``, Dask, ``--keep-going``,
skipped when up to date: the engine decides and records), run serially inside and written
into a temporary folder renamed into place when complete (``subfields/SSS/``, with its
record ``subfield.json``). Its data pass in memory and files are only its products: the
galaxies and stars measured into ``features.fits`` and ``stars.fits``, the training sets
simulated as tables (:func:`~megalut_cli.sim.simulate.simulate_table`; ``tp.fits``,
``tw.fits`` written with ``output.keep_sets``), the point and weight committees trained on
them (:func:`megalut_cli.nn.fit.fit_point`, :func:`~megalut_cli.nn.fit.fit_weight`) and
saved as ``model.h5``, the galaxies' estimates predicted from the tables
(:func:`~megalut_cli.shear.predict.predict_columns`) into ``shears.fits``. Then
the branch steps, declared once the subfields finished: ``shears.fits``,
``submission.txt``, ``evaluation.json`` (with a truth folder); the engine's
``manifest.json`` records them all.

The functions import the library modules that load GalSim, numba, SciPy and fitsio where they
are called (the units, the steps' actions, the summary): importing this module loads none of
them.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import shutil
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from megalut_cli import __version__
from megalut_cli import flags as fl
from megalut_cli.atomic import replace_folder, write_json
from megalut_cli.errors import InputError, MegalutError
from megalut_cli.great3 import layout as L
from megalut_cli.measure.measurer import metacal_cards, retry_cards
from megalut_cli.measure.metacal_defaults import DEFAULT_STEP
from megalut_cli.nn.model import ShearModel
from megalut_cli.nn.options import PointSpec, WeightSpec
from megalut_cli.pipeline.config import key_names
from megalut_cli.pipeline.great3_file import (
    EVALUATION,
    MANIFEST,
    SET_NAMES,
    SHEARS_FILE,
    SHEARS_FORMAT,
    SUBFIELDS_DIR,
    SUBMISSION,
    UNIT_PRODUCTS,
    UNIT_RECORD,
    UNIT_RECORD_FORMAT,
    BranchPipeline,
    component_features,
    set_config,
    subfield_seed,
    unit_params,
)
from megalut_cli.pipeline.steps import (
    Entry,
    RunRecord,
    Step,
    Unit,
    Units,
    UnitWork,
    about,
    check_workdir,
    failed_units,
    fingerprint,
    finished_units,
    made_workdir,
    run_steps,
)
from megalut_cli.progress import Progress
from megalut_cli.provenance import command_line, sha256_file, software_versions
from megalut_cli.shear.response import header_step

if TYPE_CHECKING:
    from megalut_cli.nn.fit import Columns

log = logging.getLogger(__name__)


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """Hide the INFO lines of the inner steps (kept with -v)."""
    package = logging.getLogger("megalut_cli")  # the parent of every module's logger
    if package.getEffectiveLevel() < logging.INFO:
        yield
        return
    old = package.level
    package.setLevel(logging.WARNING)
    try:
        yield
    finally:
        package.setLevel(old)


def _check_measurement(feats: Any, files: Mapping[str, Path], strict: bool) -> None:
    """Errors naming the file for off-image centres and bad pixels (``strict``) and an
    unmeasurable subfield."""
    flags = np.asarray(feats["flags"])
    n = len(flags)
    off = int(np.count_nonzero(flags & fl.STAMP_OFF_IMAGE))
    bad = int(np.count_nonzero(flags & fl.BAD_PIXELS))
    if strict and off:
        raise InputError(
            f"{files['catalog']}: {off} of {n} galaxy centre(s) fall off {files['image'].name} "
            "(wrong stamp size or centres?)"
        )
    if strict and bad:
        raise InputError(
            f"{files['image']}: {bad} of {n} galaxy stamp(s) have NaN or infinite pixels"
        )
    if not np.any(flags == 0):
        raise InputError(
            f"{files['image']}: no galaxy of the subfield could be measured ({n} flagged)"
        )
    for what, k in (("off the image", off), ("with NaN or infinite pixels", bad)):
        if k:
            log.warning("%s: %d galaxy stamp(s) %s: flagged, left out", files["image"], k, what)


def as_shear_estimator(model: ShearModel, component: int) -> ShearModel:
    """The single point committee of ``model`` as the shear estimator of ``component``
    (relabelled in place when it was trained on the ellipticity)."""
    (comm,) = model.point.values()
    if comm.target != f"tru_g{component}":
        comm.training = {
            **comm.training,
            "estimates": f"tru_g{component}",
            "trained_on": comm.target,
            "note": "ellipticity shortcut (paper Sects. 4.3, 8.2): the ellipticity estimate is "
            "the shear estimate",
        }
        comm.target = f"tru_g{component}"
    return ShearModel(point={comm.target: comm}, provenance=model.provenance)


def train_subfield(
    pt: PointSpec,
    pw: WeightSpec,
    subfield: int,
    tp: Columns,
    tw: Columns,
    sources: Mapping[str, str],
) -> ShearModel:
    """Point committees (per component) on ``tp`` as ``pt`` says (features are templates,
    ``{i}`` the component), taken as shear estimators; weights on ``tw`` as ``pw`` says; one
    model. Each component's trainings draw with the subfield's seeds.

    ``sources``: the names of ``tp`` and ``tw`` for the logs and the model's provenance.
    """
    from megalut_cli.nn.fit import fit_point, fit_weight

    point, weight = {}, {}
    for i in (1, 2):
        point_spec = replace(
            pt,
            features=component_features(pt.features, i),
            targets=[pt.targets[i - 1]],
            seed=subfield_seed(pt.seed, subfield, i),
        )
        estimator = fit_point(
            tp, point_spec, sources={"train": sources["tp"]}, names=key_names("train_point")
        )
        weight_spec = replace(
            pw,
            features=component_features(pw.features, i),
            seed=subfield_seed(pw.seed, subfield, i),
        )
        model = fit_weight(
            tw,
            as_shear_estimator(estimator, i),
            weight_spec,
            sources={"train": sources["tw"]},
            names=key_names("train_weight"),
        )
        point.update(model.point)
        weight.update(model.weight)
    prov = {
        "command": "run (GREAT3 branch)",
        "argv": command_line(),
        "versions": software_versions(),
        "subfield": subfield,
        "inputs": dict(sources),
    }
    return ShearModel(point=point, weight=weight, provenance=prov)


def simulate_set(
    cfg: Any,
    seed: int,
    engine: str,
    metacal: bool,
    kept: Path | None,
    moments_retry: float = 0.0,
) -> dict[str, np.ndarray]:
    """A training set of one subfield, simulated and measured in memory (``metacal``: in
    metacal mode; ``moments_retry``: the moments' damped retry); written to ``kept`` too
    (``output.keep_sets``) as ``megalut simulate --measure`` (``--metacal``,
    ``--moments-retry``) writes it."""
    from megalut_cli.sim.simulate import simulate_table, simulation_cards, write_simulation_catalog

    t0 = time.perf_counter()
    columns, _ = simulate_table(
        cfg,
        seed,
        measure=True,
        engine=engine,
        metacal_step=float(DEFAULT_STEP) if metacal else None,
        moments_retry=moments_retry,
    )
    if kept is not None:
        cards = simulation_cards(cfg, seed, True, engine)
        cards.update(retry_cards(moments_retry))
        if metacal:
            cards.update(metacal_cards(DEFAULT_STEP, seed, "simulate"))
        write_simulation_catalog(kept, columns, cfg, cards)
    n, seconds = len(columns["case"]), time.perf_counter() - t0
    log.info(
        "%d stamps in %.1f s (%.1f stamps/s)", n, seconds, n / seconds if seconds else math.inf
    )
    return columns


def predict_subfield(
    feats: Any, model: ShearModel, features: Path, model_path: Path, output: Path
) -> dict[str, np.ndarray]:
    """The subfield's galaxies (``feats``, the table measured into ``features``) with the
    estimates of ``model`` (saved as ``model_path``), predicted in memory and written to
    ``output`` as ``megalut predict`` writes them: the features catalog's header, carried
    HDUs and history, after the same check against the model's training domain."""
    from megalut_cli.catalog import catalog_info, catalog_writer, read_cards, read_carried_hdus
    from megalut_cli.shear.predict import (
        FORMAT,
        FORMAT_VERSION,
        check_domain,
        predict_columns,
        prediction_cards,
    )

    n_rows, colnames, header = catalog_info(features)
    step = header_step(header)
    check_domain(
        model,
        model_path,
        features,
        colnames=colnames,
        header=header,
        metacal=step is not None,
        n_rows=n_rows,
    )
    columns = {c: np.asarray(feats[c]) for c in feats.colnames}
    columns.update(predict_columns(model, feats, metacal_step=step))
    cards = prediction_cards(read_cards(features), model, model_path, step)
    extra_hdus = read_carried_hdus(features)
    with catalog_writer(
        output,
        fmt=FORMAT,
        fmt_version=FORMAT_VERSION,
        cards=cards,
        history=header.get("HISTORY"),
        extra_hdus=extra_hdus,
    ) as writer:
        writer.append(columns)
    return columns


def subfield_folder(subfield: int) -> str:
    """``subfields/SSS``: where a subfield's products are, relative to the work folder."""
    return f"{SUBFIELDS_DIR}/{subfield:03d}"


def subfield_unit(pipe: BranchPipeline, subfield: int) -> Unit:
    """The work unit of one subfield: its products, parameters and input files (image,
    galaxy catalog, star field; none for a subfield with missing files: it fails)."""
    folder = subfield_folder(subfield)
    names = [
        *UNIT_PRODUCTS,
        *([f"{n}.fits" for n in SET_NAMES] if pipe.keep_sets else []),
        UNIT_RECORD,
    ]
    sources = (
        {} if subfield in pipe.problems else L.subfield_files(pipe.branch_dir, subfield, pipe.epoch)
    )
    return Unit(
        f"subfield-{subfield:03d}",
        f"subfield {subfield}",
        [f"{folder}/{n}" for n in names],
        unit_params(pipe, subfield),
        dict(sources),
        run_subfield,
        {"pipe": pipe, "subfield": subfield},
    )


def run_subfield(job: Mapping[str, Any], work: UnitWork) -> dict[str, Any]:
    """Work unit: the whole pipeline of one subfield (``job``: ``pipe``, ``subfield``), written
    into ``subfields/SSS/`` with its record; returns its summary (means, galaxies, noise)."""
    from megalut_cli.catalog import VersionColumns
    from megalut_cli.measure.measure import measure_file

    pipe: BranchPipeline = job["pipe"]
    s = int(job["subfield"])

    if s in pipe.problems:
        raise InputError(pipe.problems[s])
    files = L.subfield_files(pipe.branch_dir, s, pipe.epoch)
    params = unit_params(pipe, s)
    final = work.workdir / subfield_folder(s)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{s:03d}.", suffix=".tmp", dir=final.parent))
    tmp.chmod(0o755)  # mkdtemp's 0700 would follow the folder into place
    t0 = time.perf_counter()
    timings: dict[str, float] = {}

    def lap(name: str, t: float) -> None:
        timings[name] = round(time.perf_counter() - t, 3)

    try:
        with _quiet():
            t = time.perf_counter()
            feats = measure_file(
                files["image"],
                files["catalog"],
                tmp / "features.fits",
                stamp_size=pipe.stamp_size,
                origin=0,
                psf_path=files["starfield"],
                engine=pipe.engine,
                metacal=pipe.metacal,
                moments_retry=pipe.moments_retry,
            )
            _check_measurement(feats, files, pipe.strict)
            measure_file(
                files["starfield"],
                None,
                tmp / "stars.fits",
                stamp_size=pipe.stamp_size,
                stars=True,
                engine=pipe.engine,
                moments_retry=pipe.moments_retry,
            )
            lap("measure", t)
            sets, noise_sigma = {}, None
            for name, tpl in pipe.sets.items():
                t = time.perf_counter()
                cfg = set_config(tpl, files["starfield"], tmp / "features.fits")
                kept = tmp / f"{name}.fits" if pipe.keep_sets else None
                seed = params["sets"][name]["seed"]
                sets[name] = simulate_set(
                    cfg, seed, pipe.engine, pipe.metacal, kept, pipe.moments_retry
                )
                if name == "tw":
                    noise_sigma = (
                        float(cfg.noise.params["sigma"].bounds()[0])
                        if "sigma" in cfg.noise.params
                        else None
                    )
                lap(f"simulate-{name}", t)
            t = time.perf_counter()
            tp, tw = sets["tp"], sets["tw"]
            if pipe.metacal:  # the networks train on the noshear versions' features
                tp, tw = VersionColumns(tp, "noshear"), VersionColumns(tw, "noshear")
            specs = PointSpec(**params["train_point"]), WeightSpec(**params["train_weight"])
            model = train_subfield(*specs, s, tp, tw, {n: f"{n}.fits" for n in sets})
            model.shear_mode = "metacal" if pipe.metacal else model.shear_mode
            model.save(tmp / "model.h5")
            lap("train", t)
            t = time.perf_counter()
            shears = predict_subfield(
                feats, model, tmp / "features.fits", tmp / "model.h5", tmp / "shears.fits"
            )
            lap("predict", t)
        means = {}
        for scheme, weighted in (("unweighted", False), ("weighted", True)):
            _, g1, g2, n_used = L.submission_from_catalog(
                shears, weighted=weighted, where=str(files["image"])
            )
            means[scheme] = {"g1": float(g1[0]), "g2": float(g2[0]), "n_used": int(n_used[0])}
        use = means["weighted" if pipe.weighted else "unweighted"]
        if not (math.isfinite(use["g1"]) and math.isfinite(use["g2"])):
            raise InputError(f"{files['image']}: no galaxy with a usable shear estimate")
        summary = {
            "subfield": s,
            "n_galaxies": len(shears["flags"]),
            "n_flagged": int(np.count_nonzero(shears["flags"])),
            "noise_sigma": noise_sigma,
            "psf_adamom_sigma": float(np.asarray(feats["psf_adamom_sigma"])[0]),
            "means": means,
            "g1": use["g1"],
            "g2": use["g2"],
            "seconds": round(time.perf_counter() - t0, 3),
            "timings": timings,
            "status": "ran",
        }
        products = list(UNIT_PRODUCTS) + (
            [f"{n}.fits" for n in SET_NAMES] if pipe.keep_sets else []
        )
        record = {
            "format": UNIT_RECORD_FORMAT,
            "key": work.key,
            "params": params,
            "inputs": work.inputs,
            "summary": summary,
            "products": {n: fingerprint(tmp / n) for n in products},
            "megalut": __version__,
        }
        (tmp / UNIT_RECORD).write_text(json.dumps(record, indent=1, allow_nan=False) + "\n")
        replace_folder(tmp, final)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    log.info(
        "subfield %d: g1 = %+.5f, g2 = %+.5f (%d galaxies, noise sigma %.4g) in %.0f s",
        s,
        summary["g1"],
        summary["g2"],
        summary["n_galaxies"],
        noise_sigma or 0.0,
        summary["seconds"],
    )
    return summary


# --------------------------------------------------------------------------- the branch


@dataclass
class BranchRunResult:
    workdir: Path
    summaries: list[dict[str, Any]]
    failures: list[dict[str, Any]]  # {"subfield", "error"}
    evaluation: dict[str, Any] | None
    seconds: float
    products: list[str]
    n_skipped: int = 0  # subfields up to date


def build_steps(pipe: BranchPipeline, workdir: Path) -> list[Entry]:
    """The steps of ``pipe``: the subfields (units), then the branch steps they allow."""
    units = Units("subfields", [subfield_unit(pipe, s) for s in pipe.subfields], noun="subfield")

    def branch(results: Mapping[str, Any]) -> list[Step]:
        return branch_steps(
            pipe, workdir, [results[u.name] for u in units.units if u.name in results]
        )

    return [units, branch]


def branch_steps(
    pipe: BranchPipeline, workdir: Path, done: Sequence[Mapping[str, Any]]
) -> list[Step]:
    """``shears.fits``, ``submission.txt`` and (truth, 2 subfields or more) ``evaluation.json``
    of the finished subfields (their summaries ``done``)."""
    done = sorted(done, key=lambda r: r["subfield"])
    subs = [int(r["subfield"]) for r in done]
    their_shears = [f"{subfield_folder(s)}/shears.fits" for s in subs]
    scheme = "weighted" if pipe.weighted else "unweighted"

    def write_shears(wd: Path, overwrite: bool) -> None:
        _write_shears(wd / SHEARS_FILE, wd, subs, overwrite=True)

    def write_submission(wd: Path, overwrite: bool) -> None:
        L.write_submission(
            wd / SUBMISSION,
            subs,
            [r["means"][scheme]["g1"] for r in done],
            [r["means"][scheme]["g2"] for r in done],
            overwrite=True,
        )

    steps = [
        Step(
            "shears",
            [SHEARS_FILE],
            their_shears,
            {"subfields": subs},
            write_shears,
            f"the {len(subs)} subfield(s)' galaxies with a subfield column",
        ),
        Step(
            "submission",
            [SUBMISSION],
            their_shears,
            {"subfields": subs, "weighted": pipe.weighted},
            write_submission,
            f"subfield g1 g2 ({scheme} means)",
        ),
    ]
    if pipe.truth is None:
        return steps
    if len(done) < 2:
        log.warning(
            "%s: one subfield only: m and c cannot be fitted, no %s", pipe.truth, EVALUATION
        )
        (workdir / EVALUATION).unlink(
            missing_ok=True
        )  # none of an earlier run left beside these products
        return steps
    truth = pipe.truth

    def evaluate(wd: Path, overwrite: bool) -> None:
        from megalut_cli.great3.evaluate import evaluate_branch

        with _quiet():
            evaluation = evaluate_branch(wd / SHEARS_FILE, truth, sigma2_min=pipe.sigma2_min)
        evaluation["submission"] = {"weighted": pipe.weighted, "path": SUBMISSION}
        write_json(wd / EVALUATION, evaluation, overwrite=True)

    truth_files = {p.name: sha256_file(p) for p in sorted(truth.iterdir()) if p.is_file()}
    return steps + [
        Step(
            "evaluation",
            [EVALUATION],
            [SHEARS_FILE],
            {
                "truth": str(truth),
                "truth_sha256": truth_files,
                "sigma2_min": pipe.sigma2_min,
                "weighted": pipe.weighted,
            },
            evaluate,
            f"m, c and Q_c against {truth}",
        )
    ]


def _write_shears(path: Path, workdir: Path, subfields: Sequence[int], overwrite: bool) -> int:
    """Concatenate the subfields' predictions into one catalog with a ``subfield`` column
    (streamed, :func:`megalut_cli.catalog.catalog_writer`)."""
    from megalut_cli.catalog import catalog_info, catalog_writer, read_catalog

    n = 0
    dtype = None
    _, _, header = catalog_info(workdir / SUBFIELDS_DIR / f"{subfields[0]:03d}" / "shears.fits")
    cards = {
        k: v
        for k, v in header.items()
        if k not in ("HISTORY", "MODEL", "MODELSHA", "SUBFIELD", "TEXTCAT")
    }
    cards["NSUBFLD"] = (len(subfields), "subfields in this catalog")
    history = header.get("HISTORY")
    with catalog_writer(
        path,
        fmt=SHEARS_FORMAT,
        fmt_version="1.0",
        overwrite=overwrite,
        cards=cards,
        history=history,
    ) as writer:
        for s in subfields:
            src = workdir / SUBFIELDS_DIR / f"{s:03d}" / "shears.fits"
            t = read_catalog(src)
            cols = {"subfield": np.full(len(t), s, dtype=np.int64)}
            cols.update({c: np.asarray(t[c]) for c in t.colnames if c != "subfield"})
            if dtype is None:
                dtype = np.dtype(
                    [
                        (c, v.dtype.str, v.shape[1:]) if v.ndim > 1 else (c, v.dtype.str)
                        for c, v in cols.items()
                    ]
                )
            elif set(cols) != set(dtype.names):
                raise InputError(f"{src}: its columns differ from those of subfield {subfields[0]}")
            arr = np.zeros(len(t), dtype=dtype)
            for c in dtype.names:
                arr[c] = cols[c]
            writer.append(arr)
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
    """Run (or bring up to date) every subfield of ``pipe`` (work units), then write the
    per-galaxy catalog, the submission and (with a truth folder) the evaluation.

    Without ``keep_going`` the first failing subfield stops the run (no branch product is
    written; the subfields already finished stay in ``subfields/``). With it, the others
    complete and the products hold them; ``result.failures`` lists the failed ones (see
    :func:`failure_error`). Every subfield failing is an error.
    """
    wd = Path(workdir)
    steps = build_steps(pipe, wd)
    check_workdir(wd, steps, skip_existing, overwrite, [SHEARS_FILE, SUBMISSION, EVALUATION])
    if pipe.problems and not keep_going:
        s = next(iter(pipe.problems))
        raise InputError(about(f"subfield {s}", pipe.problems[s]))
    t0 = time.perf_counter()
    log.info(
        "branch %s (%s, %d-pixel stamps): %d subfield(s) -> %s",
        pipe.branch_dir,
        pipe.kind,
        pipe.stamp_size,
        len(pipe.subfields),
        wd,
    )
    tp, tw = (pipe.sets[k].raw.get("structure", {}) for k in SET_NAMES)
    log.info(
        "per subfield: tp %s x %s stamps, tw %s x %s stamps; %d + %d members per component",
        tp.get("n_cases"),
        tp.get("n_realizations"),
        tw.get("n_cases"),
        tw.get("n_realizations"),
        pipe.point.members,
        pipe.weight.members,
    )
    run = RunRecord("", pipe.path, pipe.sha256, pipe.overrides, pipe.raw)
    with made_workdir(wd, SUBFIELDS_DIR):
        reports = run_steps(
            steps,
            wd,
            run,
            skip_existing=skip_existing,
            overwrite=overwrite,
            keep_going=keep_going,
            nproc=nproc,
            scheduler=scheduler,
            progress=progress,
        )
    done = sorted((u.result for u in finished_units(reports)), key=lambda r: r["subfield"])
    failures = [
        {"subfield": int(u.name.rsplit("-", 1)[1]), "error": u.error} for u in failed_units(reports)
    ]
    n_skipped = sum(u.status == "skipped" for u in finished_units(reports))
    ran = {r.name for r in reports}
    evaluation = None
    products = [SHEARS_FILE, SUBMISSION]
    if "evaluation" in ran and (wd / EVALUATION).is_file():
        evaluation = json.loads((wd / EVALUATION).read_text())
        products.append(EVALUATION)
    products.append(MANIFEST)
    seconds = time.perf_counter() - t0
    log.info(
        "%d subfield(s) done (%d skipped as up to date), %d failed; %d galaxies in %s; %.0f s",
        len(done),
        n_skipped,
        len(failures),
        sum(r["n_galaxies"] for r in done),
        SHEARS_FILE,
        seconds,
    )
    return BranchRunResult(wd, done, failures, evaluation, seconds, products, n_skipped)


def failure_error(result: BranchRunResult) -> MegalutError | None:
    """The error to report (exit 1) when subfields failed under ``keep_going``, else None."""
    if not result.failures:
        return None
    f = result.failures
    listed = "; ".join(f"{r['subfield']}: {r['error']}" for r in f[:3]) + (
        " ..." if len(f) > 3 else ""
    )
    return MegalutError(
        f"{len(f)} of {len(f) + len(result.summaries)} subfield(s) failed ({listed}); "
        f"{result.workdir / SUBMISSION} holds the other {len(result.summaries)}"
    )


def format_summary(result: BranchRunResult) -> str:
    """What was written and, with a truth folder, the m, c and Q_c table."""
    lines = []
    if result.evaluation is not None:
        from megalut_cli.shear.report import format_table

        lines += [format_table(result.evaluation), ""]
    lines.append(
        f"{len(result.summaries)} subfield(s); products in {result.workdir}/: "
        f"{', '.join(result.products)} (and {SUBFIELDS_DIR}/SSS/)"
    )
    return "\n".join(lines)
