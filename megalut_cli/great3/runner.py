"""Running a GREAT3 branch pipeline (:mod:`megalut_cli.great3.pipeline`) in a work folder.

Every subfield is one work unit (``-j``, Dask), run serially inside and written into a
temporary folder renamed into place when complete (``subfields/SSS/``, with its record
``subfield.json``); its point and weight committees are trained in memory
(:func:`megalut_cli.training.fit_point`, :func:`~megalut_cli.training.fit_weight`). Then
the branch products: ``shears.fits``, ``submission.txt``, ``evaluation.json`` (with a
truth folder) and ``manifest.json``.
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
from megalut_cli.errors import InputError, MegalutError
from megalut_cli.great3 import layout as L
from megalut_cli.great3.pipeline import (
    EVALUATION,
    MANIFEST,
    MANIFEST_FORMAT,
    SET_NAMES,
    SHEARS,
    SHEARS_FORMAT,
    SUBFIELDS_DIR,
    SUBMISSION,
    UNIT_PRODUCTS,
    UNIT_RECORD,
    BranchPipeline,
    component_features,
    set_config,
    subfield_seed,
    unit_params,
)
from megalut_cli.nn.model import ShearModel
from megalut_cli.progress import Progress, no_progress
from megalut_cli.steps import current_sha, fingerprint, sha_text

if TYPE_CHECKING:
    from megalut_cli.training import Columns

log = logging.getLogger("megalut")


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


def _up_to_date(folder: Path, key: str) -> dict[str, Any] | None:
    """The record of a finished subfield folder if its key is ``key`` and its products
    unchanged (the step engine's rule: :func:`megalut_cli.steps.current_sha`)."""
    try:
        rec = json.loads((folder / UNIT_RECORD).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(rec, dict) or rec.get("key") != key or not isinstance(rec.get("products"), dict):
        return None
    products = rec["products"]
    if any(isinstance(fp, dict) and "sha256" not in fp for fp in products.values()):
        log.info("%s: recorded by an older megalut without content hashes: redone", folder)
        return None
    if not all(current_sha(folder / name, fp) for name, fp in products.items()):
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


def as_shear_estimator(model: ShearModel, component: int) -> ShearModel:
    """The single point committee of ``model`` as the shear estimator of ``component``
    (relabelled in place when it was trained on the ellipticity)."""
    (comm,) = model.point.values()
    if comm.target != f"tru_g{component}":
        comm.training = {**comm.training, "estimates": f"tru_g{component}", "trained_on": comm.target,
                         "note": "ellipticity shortcut (paper Sects. 4.3, 8.2): the ellipticity estimate is the shear estimate"}
        comm.target = f"tru_g{component}"
    return ShearModel(point={comm.target: comm}, provenance=model.provenance)


def train_subfield(pipe: BranchPipeline, subfield: int, tp: Columns, tw: Columns,
                   sources: Mapping[str, str]) -> ShearModel:
    """Point committees (per component) on ``tp``, taken as shear estimators; weights on ``tw``; one model.

    ``sources``: the names of ``tp`` and ``tw`` for the logs and the model's provenance.
    """
    from megalut_cli.pipeline_config import key_names
    from megalut_cli.provenance import command_line, software_versions
    from megalut_cli.training import fit_point, fit_weight

    point, weight = {}, {}
    pt, pw = pipe.point, pipe.weight
    for i in (1, 2):
        estimator = fit_point(tp, features=component_features(pt.features, i), targets=[pt.targets[i - 1]],
                              hidden=pt.hidden, cost=pt.cost, select_cases=pt.select_cases, init_scheme=pt.init,
                              options=replace(pt.options, seed=subfield_seed(pt.options.seed, subfield, i)),
                              sources={"train": sources["tp"]}, names=key_names("train_point"))
        model = fit_weight(tw, as_shear_estimator(estimator, i), features=component_features(pw.features, i),
                           hidden=pw.hidden, select=pw.select,
                           options=replace(pw.options, seed=subfield_seed(pw.options.seed, subfield, i)),
                           sources={"train": sources["tw"]}, names=key_names("train_weight"))
        point.update(model.point)
        weight.update(model.weight)
    prov = {"command": "run (GREAT3 branch)", "argv": command_line(), "versions": software_versions(),
            "subfield": subfield, "inputs": dict(sources)}
    return ShearModel(point=point, weight=weight, provenance=prov)


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
    from megalut_cli.catalog import CatalogColumns, read_catalog
    from megalut_cli.measure.measure import measure_file
    from megalut_cli.provenance import sha256_file
    from megalut_cli.shear.predict import predict_catalog
    from megalut_cli.sim.simulate import simulate

    if s in pipe.problems:
        raise InputError(pipe.problems[s])
    files = L.subfield_files(pipe.branch_dir, s, pipe.epoch)
    params = unit_params(pipe, s)
    inputs = {k: {"name": p.name, "sha256": sha256_file(p)} for k, p in files.items()}
    key = sha_text({"params": params, "inputs": inputs, "megalut": __version__})
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
            model = train_subfield(pipe, s, CatalogColumns(set_paths["tp"]), CatalogColumns(set_paths["tw"]),
                                   {n: p.name for n, p in set_paths.items()})
            model.save(tmp / "model.h5")
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
                  "products": {n: fingerprint(tmp / n) for n in products}, "megalut": __version__}
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
        from megalut_cli.shear.report import format_table

        lines += [format_table(result.evaluation), ""]
    lines.append(f"{len(result.summaries)} subfield(s); products in {result.workdir}/: {', '.join(result.products)} "
                 f"(and {SUBFIELDS_DIR}/SSS/)")
    return "\n".join(lines)
