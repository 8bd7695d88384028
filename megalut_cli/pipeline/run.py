"""The steps of the standard ``megalut run`` pipeline: :func:`build_steps` turns a
:class:`~megalut_cli.pipeline.file.Pipeline` (the file, :mod:`megalut_cli.pipeline.file`) into the
steps of the engine (:mod:`megalut_cli.pipeline.steps`); :func:`plan_pipeline` and
:func:`run_pipeline` check the work folder and run them; :func:`format_summary` reports.

The functions import the library modules that load GalSim, numba, SciPy and fitsio where they
are called (the steps and their actions, the planning, the summary): importing this module
(``megalut run --help``) loads none of them.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from megalut_cli.atomic import write_json
from megalut_cli.engine import resolve_device
from megalut_cli.measure.metacal_defaults import DEFAULT_STEP
from megalut_cli.pipeline.config import (
    EvaluateSpec,
    key_names,
)
from megalut_cli.pipeline.file import (
    ALL_SETS,
    DEFAULT_WORKDIR,
    EVALUATION_JSON,
    EVALUATION_PNG,
    EVALUATION_REFERENCE_JSON,
    EVALUATION_REFERENCE_PNG,
    EVALUATION_VP_JSON,
    EVALUATION_VP_PNG,
    MODEL,
    REFERENCE_SHEARS,
    TRAINED_MODEL,
    Pipeline,
    ReferenceSpec,
    SetSpec,
)
from megalut_cli.pipeline.steps import (
    MANIFEST,
    Manifest,
    RunRecord,
    Step,
    StepReport,
    check_workdir,
    run_steps,
    step_key,
    timing_line,
)
from megalut_cli.progress import Progress, relabelled
from megalut_cli.provenance import sha256_file

log = logging.getLogger(__name__)

#: The sets that ``metacal = true`` measures in metacal mode: all (the networks then train on
#: the noshear versions' features: a metacal model).
METACAL_SETS = ("tp", "tw", "vo", "vp", "pretrain")


@dataclass
class RunResult:
    """What :func:`run_pipeline` did and the evaluation it ends with."""

    workdir: Path
    evaluation: dict[str, Any]
    steps: list[StepReport]
    seconds: float
    evaluation_vp: dict[str, Any] | None = None
    prefix: str = ""  # where the step products are, relative to workdir ("" or "<name>/")
    evaluation_reference: dict[str, Any] | None = None
    reference: ReferenceSpec | None = None


def build_steps(
    pipe: Pipeline, nproc: int = 1, scheduler: str | None = None, progress: Progress | None = None
) -> list[Step]:
    """The steps of ``pipe`` in execution order."""
    prefix = f"{pipe.name}/" if pipe.name else ""
    out = pipe.product
    steps: list[Step] = []

    def add(
        name: str,
        outputs: list[str],
        inputs: list[str],
        params: dict[str, Any],
        action: Callable[[Path, bool], None],
        summary: str,
    ) -> None:
        steps.append(Step(prefix + name, outputs, inputs, params, action, summary, prefix))

    def sim_step(spec: SetSpec) -> Step:
        from megalut_cli.sim.simulate import simulate

        metacal = pipe.metacal and spec.name in METACAL_SETS

        def action(wd: Path, overwrite: bool) -> None:
            simulate(
                spec.config,
                wd / spec.product,
                measure=True,
                seed=spec.seed,
                nproc=nproc,
                scheduler=scheduler,
                overwrite=overwrite,
                progress=relabelled(progress, f"simulate {spec.name}"),
                engine=pipe.engine,
                device=pipe.device,
                metacal=metacal,
                moments_retry=pipe.moments_retry,
            )

        s = spec.config.structure
        extra: dict[str, Any] = {"metacal": True} if metacal else {}
        if pipe.moments_retry > 0:  # absent when unset: the keys of earlier runs stay valid
            extra["moments_retry"] = pipe.moments_retry
        if spec.config.catalog_path:
            extra["catalog_sha256"] = sha256_file(spec.config.catalog_path)
        psf_path = spec.config.psf.get("path")
        if isinstance(psf_path, str) and Path(psf_path).is_file():
            extra["psf_sha256"] = sha256_file(psf_path)
        return Step(  # shared by every pipeline of the work folder: no prefix
            f"simulate-{spec.name}",
            [spec.product],
            [],
            {
                "config": json.loads(spec.config.to_json()),
                "seed": spec.seed,
                "measure": True,
                "engine": pipe.engine,
                **extra,
            },
            action,
            f"{s.n_cases} cases x {s.n_realizations} realizations = {s.n_stamps} stamps, "
            f"seed {spec.seed}, snc {s.snc} ({spec.source})",
        )

    for name in ALL_SETS:
        if name in pipe.sets:
            steps.append(sim_step(pipe.sets[name]))

    # A training step's parameters are its spec's dict (its key); the step trains with that
    # spec. Where it runs (the device, like -j) is not a parameter: the results agree
    # within the tolerances of docs/gpu.md.
    tp, pre = pipe.train_point, pipe.pretrain
    if pre is not None:
        pre_params = asdict(pre)

        def pretrain_action(wd: Path, overwrite: bool) -> None:
            from megalut_cli.nn.fit import train_point

            train_point(
                wd / "pretrain.fits",
                wd / out("pretrain.h5"),
                pre,
                device=resolve_device(pipe.device),
                nproc=nproc,
                scheduler=scheduler,
                overwrite=overwrite,
                progress=progress,
                names=key_names("pretrain"),
            )

        add(
            "pretrain-point",
            [out("pretrain.h5")],
            ["pretrain.fits"],
            pre_params,
            pretrain_action,
            f"{pre.members} members x {len(pre.targets)} targets ({', '.join(pre.targets)}), "
            f"hidden {tp.hidden}, {pre.iterations} iterations, select_cases {pre.select_cases!r}, "
            f"seed {pre.seed}",
        )

    tp_params = asdict(tp)

    def train_point_action(wd: Path, overwrite: bool) -> None:
        from megalut_cli.nn.fit import train_point

        init_from = wd / out("pretrain.h5") if pre is not None else None
        train_point(
            wd / "tp.fits",
            wd / out("point.h5"),
            tp,
            init_from=init_from,
            device=resolve_device(pipe.device),
            nproc=nproc,
            scheduler=scheduler,
            overwrite=overwrite,
            progress=progress,
            names=key_names("train_point"),
        )

    add(
        "train-point",
        [out("point.h5")],
        ["tp.fits"] + ([out("pretrain.h5")] if pre is not None else []),
        tp_params,
        train_point_action,
        f"{tp.members} members x {len(tp.targets)} targets, hidden {tp.hidden}, "
        f"{tp.iterations} iterations, select_cases {tp.select_cases!r}, seed {tp.seed}"
        + (", starting from pretrain.h5" if pre is not None else ""),
    )

    def predict_step(name: str, catalog: str, model: str, shears: str, summary: str) -> None:
        def action(wd: Path, overwrite: bool) -> None:
            from megalut_cli.shear.predict import predict_catalog

            predict_catalog(
                wd / catalog,
                wd / out(model),
                wd / out(shears),
                nproc=nproc,
                scheduler=scheduler,
                overwrite=overwrite,
                progress=relabelled(progress, name),
            )

        add(name, [out(shears)], [catalog, out(model)], {}, action, summary)

    def evaluate_step(
        name: str,
        table: str,
        ev: EvaluateSpec,
        shears: str,
        json_name: str,
        png_name: str,
        what: str,
    ) -> None:
        """A step evaluating ``shears`` with the options ``ev`` of the pipeline table ``table``."""
        plot = ev.plot and _have_matplotlib()
        if ev.plot and not plot:
            from megalut_cli.shear.plots import MATPLOTLIB_HINT

            log.info("matplotlib is not installed: no %s (%s)", png_name, MATPLOTLIB_HINT)

        def action(wd: Path, overwrite: bool) -> None:
            from megalut_cli.shear.evaluate import evaluate_catalog

            result = evaluate_catalog(
                wd / out(shears),
                by=ev.by or None,
                bins=ev.bins,
                select=ev.select,
                select_cases=ev.select_cases,
                names=key_names(table),
            )
            write_json(wd / out(json_name), result, overwrite)
            if plot:
                from megalut_cli.shear.plots import plot_evaluation

                plot_evaluation(result, wd / out(png_name), overwrite)
            else:  # no figure of an earlier run left beside this evaluation
                (wd / out(png_name)).unlink(missing_ok=True)

        add(
            name,
            [out(json_name)] + ([out(png_name)] if plot else []),
            [out(shears)],
            {
                "by": ev.by,
                "bins": ev.bins,
                "select": ev.select,
                "select_cases": ev.select_cases,
                "plot": plot,
            },
            action,
            f"{what} on {shears}{f' by {ev.by}' if ev.by else ''}"
            f"{f', select {ev.select!r}' if ev.select else ''}"
            f"{f', select_cases {ev.select_cases!r}' if ev.select_cases else ''}",
        )

    if pipe.evaluate_vp is not None:
        predict_step(
            "predict-vp", "vp.fits", "point.h5", "vp-shears.fits", "point estimates on vp.fits"
        )
        evaluate_step(
            "evaluate-vp",
            "evaluate_vp",
            pipe.evaluate_vp,
            "vp-shears.fits",
            EVALUATION_VP_JSON,
            EVALUATION_VP_PNG,
            "m, c of the point estimates (unweighted)",
        )

    tw = pipe.train_weight
    tw_params = asdict(tw)

    def train_weight_action(wd: Path, overwrite: bool) -> None:
        from megalut_cli.nn.fit import train_weight

        train_weight(
            wd / "tw.fits",
            wd / out("point.h5"),
            wd / out(TRAINED_MODEL),
            tw,
            device=resolve_device(pipe.device),
            nproc=nproc,
            scheduler=scheduler,
            overwrite=overwrite,
            progress=progress,
            names=key_names("train_weight"),
        )

    add(
        "train-weight",
        [out(TRAINED_MODEL)],
        ["tw.fits", out("point.h5")],
        tw_params,
        train_weight_action,
        f"{tw.members} members, hidden {tw.hidden}, {tw.iterations} iterations, "
        f"select {tw.select!r}, seed {tw.seed}",
    )
    predict_step(
        "predict",
        "vo.fits",
        TRAINED_MODEL,
        "vo-shears.fits",
        "point estimates and weights on vo.fits",
    )
    evaluate_step(
        "evaluate",
        "evaluate",
        pipe.evaluate,
        "vo-shears.fits",
        EVALUATION_JSON,
        EVALUATION_PNG,
        "m, c",
    )

    def model_action(wd: Path, overwrite: bool) -> None:
        from megalut_cli.nn.population import record_validated_model

        evaluation = json.loads((wd / out(EVALUATION_JSON)).read_text())
        record_validated_model(wd / out(TRAINED_MODEL), evaluation, wd / out(MODEL), overwrite)

    add(
        "model",
        [out(MODEL)],
        [out(TRAINED_MODEL), out(EVALUATION_JSON)],
        {},
        model_action,
        f"{TRAINED_MODEL} with its own validation recorded ({EVALUATION_JSON}, weighted m, c)",
    )
    ref = pipe.reference
    if ref is not None:
        catalog = pipe.sets[ref.set].product

        def reference_action(wd: Path, overwrite: bool) -> None:
            from megalut_cli.shear.predict import predict_catalog

            predict_catalog(
                wd / catalog,
                ref.model,
                wd / out(REFERENCE_SHEARS),
                nproc=nproc,
                scheduler=scheduler,
                overwrite=overwrite,
                progress=relabelled(progress, "predict-reference"),
            )

        add(
            "predict-reference",
            [out(REFERENCE_SHEARS)],
            [catalog],
            {"model_sha256": ref.sha256},
            reference_action,
            f"{ref.label} on {catalog}",
        )
        evaluate_step(
            "evaluate-reference",
            "evaluate",
            pipe.evaluate,
            REFERENCE_SHEARS,
            EVALUATION_REFERENCE_JSON,
            EVALUATION_REFERENCE_PNG,
            f"m, c of {ref.label}",
        )
    return steps


def _have_matplotlib() -> bool:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


# --------------------------------------------------------------------------- running


def _evaluation_pngs(pipe: Pipeline) -> list[str]:
    """Figures a run may leave (even when this one draws none): a product to refuse to overwrite."""
    return [
        pipe.product(EVALUATION_PNG),
        pipe.product(EVALUATION_VP_PNG),
        pipe.product(EVALUATION_REFERENCE_PNG),
    ]


def plan_pipeline(
    pipe: Pipeline,
    workdir: str | os.PathLike = DEFAULT_WORKDIR,
    *,
    skip_existing: bool = False,
    overwrite: bool = False,
    nproc: int = 1,
    scheduler: str | None = None,
    estimate: bool | None = None,
) -> list[str]:
    """Pre-flight of :func:`run_pipeline`: check the work folder; one line per step saying
    what it will do, the simulations with a time estimated from a tiny calibration draw
    (``estimate``: as :func:`~megalut_cli.sim.simulate.plan_message`)."""
    from megalut_cli.sim.simulate import plan_message

    wd = Path(workdir)
    steps = build_steps(pipe, nproc, scheduler)
    check_workdir(wd, steps, skip_existing, overwrite, _evaluation_pngs(pipe))
    lines = [
        f"pipeline {pipe.path} -> {wd / pipe.name if pipe.name else wd}: {len(steps)} steps"
        + (" (up-to-date steps will be skipped)" if skip_existing else "")
    ]
    sims = {f"simulate-{name}": spec for name, spec in pipe.sets.items()}
    manifest = (
        Manifest(
            wd / MANIFEST, RunRecord(pipe.name, pipe.path, pipe.sha256, pipe.overrides, pipe.raw)
        )
        if skip_existing
        else None
    )
    for i, step in enumerate(steps, 1):
        spec = sims.get(step.name)
        if (
            spec
            and manifest is not None
            and not step.inputs
            and manifest.up_to_date(step, step_key(step, {}), wd)
        ):
            what = "up to date, will be skipped"
        elif spec:
            metacal = pipe.metacal and spec.name in METACAL_SETS
            what = plan_message(
                spec.config,
                spec.seed,
                True,
                False,
                nproc,
                scheduler,
                pipe.engine,
                metacal_step=DEFAULT_STEP if metacal else None,
                estimate=estimate,
            )
        else:
            what = step.summary
        lines.append(f"[{i}/{len(steps)}] {step.name}: {what}")
    return lines


def run_pipeline(
    pipe: Pipeline,
    workdir: str | os.PathLike = DEFAULT_WORKDIR,
    *,
    skip_existing: bool = False,
    overwrite: bool = False,
    nproc: int = 1,
    scheduler: str | None = None,
    progress: Progress | None = None,
) -> RunResult:
    """Run (or bring up to date) every step of ``pipe`` in ``workdir``; return the evaluation."""
    wd = Path(workdir)
    steps = build_steps(pipe, nproc, scheduler, progress)
    check_workdir(wd, steps, skip_existing, overwrite, _evaluation_pngs(pipe))
    wd.mkdir(parents=True, exist_ok=True)
    if pipe.name:
        (wd / pipe.name).mkdir(exist_ok=True)
    log.info("pipeline %s -> %s", pipe.path, wd / pipe.name if pipe.name else wd)
    t_start = time.perf_counter()
    run = RunRecord(pipe.name, pipe.path, pipe.sha256, pipe.overrides, pipe.raw)
    reports = run_steps(steps, wd, run, skip_existing=skip_existing, overwrite=overwrite)
    total = time.perf_counter() - t_start
    evaluation = json.loads((wd / pipe.product(EVALUATION_JSON)).read_text())
    evaluation_vp = evaluation_reference = None
    if pipe.evaluate_vp is not None:
        evaluation_vp = json.loads((wd / pipe.product(EVALUATION_VP_JSON)).read_text())
    if pipe.reference is not None:
        evaluation_reference = json.loads(
            (wd / pipe.product(EVALUATION_REFERENCE_JSON)).read_text()
        )
    log.info("pipeline finished in %.1f s (%s)", total, timing_line(reports))
    return RunResult(
        wd,
        evaluation,
        reports,
        total,
        evaluation_vp,
        f"{pipe.name}/" if pipe.name else "",
        evaluation_reference,
        pipe.reference,
    )


def format_summary(result: RunResult) -> str:
    """The evaluation table(s), then where the products are."""
    from megalut_cli.shear.report import format_table

    lines = []
    ref = result.reference
    if result.evaluation_vp is not None:
        lines += [
            f"== VP: point estimates ({result.prefix}{EVALUATION_VP_JSON}) ==",
            format_table(result.evaluation_vp),
            "",
        ]
    if result.evaluation_vp is not None or result.evaluation_reference is not None:
        lines.append(f"== VO: overall validation ({result.prefix}{EVALUATION_JSON}) ==")
    lines += [format_table(result.evaluation), ""]
    if result.evaluation_reference is not None and ref is not None:
        lines += [
            f"== {ref.label} on {ref.set} ({result.prefix}{EVALUATION_REFERENCE_JSON}) ==",
            format_table(result.evaluation_reference),
            "",
        ]
    names = [EVALUATION_JSON, EVALUATION_PNG]
    if result.evaluation_vp is not None:
        names += [EVALUATION_VP_JSON, EVALUATION_VP_PNG]
    if result.evaluation_reference is not None:
        names += [EVALUATION_REFERENCE_JSON, EVALUATION_REFERENCE_PNG]
    files = [result.prefix + n for n in names if (result.workdir / (result.prefix + n)).is_file()]
    lines.append(
        f"products in {result.workdir}/: {', '.join(files)}, {MANIFEST} "
        "(and the catalogs and models)"
    )
    return "\n".join(lines)
