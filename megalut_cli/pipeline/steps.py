"""The step engine of ``megalut run``: a work folder, a list of steps, a manifest.

A pipeline (``pipeline/run.py``, ``pipeline/great3_run.py``) declares its work as :class:`Step`
objects — products, inputs (products of earlier steps), parameters and an action — and
:class:`Units`, a step made of independent work units (each with its own key and
products, run in parallel on the executor of ``-j``/``--scheduler``); a
:data:`StepBuilder` in the list declares steps once the units before it finished.
:func:`run_steps` runs them in order in a work folder, recording in :class:`Manifest`
(``manifest.json``) each finished step's and unit's key (sha256 of its parameters, the
sha256 of its inputs and the megalut version) and the sha256, size and modification time
of its products. With ``skip_existing`` a step or unit whose key is unchanged and whose
products are still those recorded is skipped; a step whose key is that of a finished
step elsewhere in the folder (another named pipeline) copies that step's products. With
``keep_going`` a failing unit is reported and the others complete. The execution engine
(``-j``, Dask) is not part of a key: the results do not depend on it.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from megalut_cli import __version__
from megalut_cli.atomic import atomic_output, write_json
from megalut_cli.errors import ArgumentError, HintError, MegalutError, braces_escaped
from megalut_cli.parallel import executor, map_units
from megalut_cli.progress import Progress, no_progress
from megalut_cli.provenance import sha256_file, utc_now

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
MANIFEST_FORMAT = "megalut.run-manifest"
MANIFEST_VERSION = "1.0"


@dataclass
class Step:
    """One step: products in the work folder, inputs (upstream products), parameters.

    ``action(workdir, overwrite)`` writes the products. ``prefix`` (``"<name>/"`` of a
    named pipeline, else ``""``) starts the step's name and its products; the step's key
    is computed without it, so that the same work gets the same key in any pipeline.
    """

    name: str
    outputs: list[str]
    inputs: list[str]
    params: dict[str, Any]
    action: Callable[[Path, bool], None]  # (workdir, overwrite)
    summary: str = ""
    prefix: str = ""


@dataclass(frozen=True)
class UnitWork:
    """What the engine hands a unit's function: the work folder, the key it computed, the
    hashed sources (``{name: {"name": file name, "sha256": ...}}``), whether to overwrite."""

    workdir: Path
    key: str
    inputs: dict[str, dict[str, str]]
    overwrite: bool


@dataclass
class Unit:
    """One independent work unit of :class:`Units`: its products, parameters and sources.

    ``func(job, work)`` (a top-level function and a picklable ``job``: it may run in a
    worker process) writes ``outputs`` and returns a JSON-able result, recorded in the
    manifest and given back when the unit is skipped as up to date. ``sources``: files
    outside the work folder whose contents enter the key. ``label`` names the unit in
    messages ("subfield 3").
    """

    name: str
    label: str
    outputs: list[str]
    params: dict[str, Any]
    sources: dict[str, Path]
    func: Callable[[Any, UnitWork], Any]
    job: Any


@dataclass
class Units:
    """A step made of independent :class:`Unit` s, run in parallel where ``-j``/``--scheduler``
    allow; ``noun`` names a unit in the progress bar and the messages ("subfield")."""

    name: str
    units: list[Unit]
    summary: str = ""
    noun: str = "unit"


@dataclass
class UnitReport:
    name: str
    label: str
    status: str  # "ran", "skipped" or "failed"
    seconds: float
    result: Any = None
    error: str = ""


@dataclass
class StepReport:
    name: str
    status: str  # "ran", "skipped" or "copied" (the products of the same work in another pipeline)
    seconds: float
    units: list[UnitReport] = field(default_factory=list)  # of a :class:`Units` step, in unit order


#: Steps declared once the units before them finished: given ``{unit name: result}`` of
#: every finished unit so far (in order), the steps to run next.
StepBuilder = Callable[[Mapping[str, Any]], Sequence[Step]]
Entry = Step | Units | StepBuilder


@dataclass(frozen=True)
class RunRecord:
    """What the manifest records of the pipeline file that declared the steps."""

    name: str  # "" for an unnamed pipeline
    path: str
    sha256: str
    overrides: tuple[str, ...]
    effective: dict[str, Any]  # the validated file, overrides applied

    def as_dict(self) -> dict[str, Any]:
        return {
            "path": self.path,
            "sha256": self.sha256,
            "overrides": list(self.overrides),
            "effective": self.effective,
        }


def sha_text(obj: Any) -> str:
    """The sha256 of ``obj`` as sorted JSON (``str`` for what JSON cannot hold)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def fingerprint(path: Path) -> dict[str, Any]:
    """What the manifest records of a product: sha256, size, modification time."""
    st = path.stat()
    return {"sha256": sha256_file(path), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def current_sha(path: Path, record: Any) -> str | None:
    """The sha256 of ``path`` if it is still the product ``record`` (a :func:`fingerprint`)
    describes.

    Size and modification time unchanged count as unchanged (as make and git assume);
    otherwise the content is hashed again.
    """
    if not path.is_file() or not isinstance(record, dict) or "sha256" not in record:
        return None
    st = path.stat()
    if record.get("size") == st.st_size and record.get("mtime_ns") == st.st_mtime_ns:
        return record.get("sha256")
    sha = sha256_file(path)
    return sha if sha == record.get("sha256") else None


class Manifest:
    """``manifest.json``: the key and output fingerprints of every finished step."""

    def __init__(self, path: Path, run: RunRecord, skip_existing: bool = False) -> None:
        self.path = path
        self.run = run
        self.steps: dict[str, Any] = {}
        self.pipelines: dict[
            str, Any
        ] = {}  # name ("" unnamed) -> the last pipeline of that name run here
        self.failed: dict[str, str] | None = None  # unit name -> error, of the last run with units
        if path.is_file():
            try:
                data = json.loads(path.read_text())
            except (OSError, UnicodeDecodeError, json.JSONDecodeError):
                log.warning("%s: unreadable, every step will run", path)
                data = {}
            fmt = data.get("format") if isinstance(data, dict) else None
            if skip_existing and isinstance(fmt, str) and fmt != MANIFEST_FORMAT:
                raise HintError(
                    f"{braces_escaped(path)}: written by an older megalut (format "
                    f"{braces_escaped(fmt)}), its records cannot be reused; use {{overwrite}} to "
                    "redo the work",
                    "overwrite",
                )
            if (
                isinstance(data, dict)
                and fmt == MANIFEST_FORMAT
                and isinstance(data.get("steps"), dict)
            ):
                self.steps = data["steps"]
                if isinstance(data.get("pipelines"), dict):
                    self.pipelines = data["pipelines"]

    def current_sha(self, step: str, workdir: Path, name: str) -> str | None:
        """The sha256 of product ``name`` if it is still what ``step`` recorded, else None."""
        return current_sha(
            workdir / name, (self.steps.get(step) or {}).get("outputs", {}).get(name)
        )

    def same_work(self, step: Step, key: str, workdir: Path) -> tuple[str, dict[str, str]] | None:
        """Another step with this key whose products are intact: (its name, our product -> its
        product)."""
        for other, rec in self.steps.items():
            if other == step.name or not isinstance(rec, dict) or rec.get("key") != key:
                continue
            theirs = list(rec.get("outputs") or {})
            if len(theirs) == len(step.outputs) and all(
                self.current_sha(other, workdir, o) for o in theirs
            ):
                return other, dict(zip(step.outputs, theirs))
        return None

    def up_to_date(self, step: Step, key: str, workdir: Path) -> dict[str, str] | None:
        """The sha256 of each product of ``step`` if its record has ``key`` and its products
        are intact (what ``--skip-existing`` skips), else None."""
        rec = self.steps.get(step.name) or {}
        current = {o: self.current_sha(step.name, workdir, o) for o in step.outputs}
        if rec.get("key") != key or not all(current.values()):
            return None
        return {o: s for o, s in current.items() if s}

    def record(
        self,
        step: Step,
        key: str,
        inputs: Mapping[str, str],
        outputs: Mapping[str, dict[str, Any]],
        seconds: float,
        copied_from: str | None = None,
    ) -> None:
        self.steps[step.name] = {
            "key": key,
            "params": step.params,
            "inputs": dict(inputs),
            "outputs": dict(outputs),
            "seconds": round(seconds, 3),
            "finished": utc_now(),
        }
        if copied_from is not None:
            self.steps[step.name]["copied_from"] = copied_from
        self.save()

    def save(self) -> None:
        this = self.run.as_dict()
        self.pipelines[self.run.name] = this
        data = {
            "format": MANIFEST_FORMAT,
            "format_version": MANIFEST_VERSION,
            "megalut": __version__,
            "pipeline": this,  # the last one run here
            "pipelines": self.pipelines,
            "steps": self.steps,
        }
        if self.failed is not None:
            data["failed"] = self.failed
        write_json(self.path, json.loads(json.dumps(data, default=str)), overwrite=True)


def _unprefix(name: str, prefix: str) -> str:
    return name[len(prefix) :] if prefix and name.startswith(prefix) else name


def step_key(step: Step, input_shas: Mapping[str, str]) -> str:
    """The identity of a step's work: parameters, input contents, megalut version (no pipeline
    name)."""
    inputs = {_unprefix(n, step.prefix): s for n, s in input_shas.items()}
    return sha_text(
        {
            "step": _unprefix(step.name, step.prefix),
            "params": step.params,
            "inputs": inputs,
            "megalut": __version__,
        }
    )


def products(steps: Sequence[Entry]) -> list[str]:
    """Every product of ``steps`` (units' included, builders' not known yet), in order."""
    out: list[str] = []
    for entry in steps:
        if isinstance(entry, Step):
            out += entry.outputs
        elif isinstance(entry, Units):
            out += [o for u in entry.units for o in u.outputs]
    return out


def check_workdir(
    workdir: Path,
    steps: Sequence[Entry],
    skip_existing: bool,
    overwrite: bool,
    also: Sequence[str] = (),
) -> None:
    """Fail early: a file where the folder should be, an unwritable place, or products
    (or the files named in ``also``) there without ``skip_existing`` or ``overwrite``."""
    if workdir.exists() and not workdir.is_dir():
        raise ArgumentError("workdir", f" {workdir}: exists and is not a folder")
    existing = next((p for p in (workdir, *workdir.absolute().parents) if p.exists()), Path("."))
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        where = "" if existing == workdir else f" (its folder {existing})"
        raise ArgumentError("workdir", f" {workdir}: not writable{where}")
    if skip_existing or overwrite:
        return
    for name in dict.fromkeys([*products(steps), *also, MANIFEST]):
        if (workdir / name).exists():
            raise HintError(
                f"{braces_escaped(workdir / name)} exists; use {{skip_existing}} to reuse the "
                "up-to-date products or {overwrite} to redo every step",
                "skip_existing",
                "overwrite",
            )


@contextlib.contextmanager
def made_workdir(workdir: Path, *folders: str) -> Iterator[Path]:
    """Create ``workdir`` and its ``folders``; if the body fails, remove those of them it
    created that are still empty (no empty folder left behind a failed start)."""
    created = [p for p in (workdir, *(workdir / f for f in folders)) if not p.exists()]
    for p in (workdir, *(workdir / f for f in folders)):
        p.mkdir(parents=True, exist_ok=True)
    try:
        yield workdir
    except BaseException:
        for p in reversed(created):
            with contextlib.suppress(OSError):
                p.rmdir()
        raise


def _copy_products(wd: Path, mapping: Mapping[str, str]) -> None:
    for ours, theirs in mapping.items():
        with atomic_output(wd / ours, overwrite=True) as tmp:
            shutil.copyfile(wd / theirs, tmp)


def about(label: str, message: str) -> str:
    """``message`` prefixed with ``label`` ("subfield 3: ...") unless it names it already."""
    return message if f"{label}:" in message else f"{label}: {message}"


def unit_key(params: Any, inputs: Mapping[str, Any]) -> str:
    """The identity of a unit's work: parameters, hashed sources, megalut version."""
    return sha_text({"params": params, "inputs": dict(inputs), "megalut": __version__})


def run_unit(task: Mapping[str, Any]) -> dict[str, Any]:
    """Bring one :class:`Unit` up to date (top level: it runs in a worker process too).

    ``task``: ``unit``, ``workdir``, ``prior`` (its manifest record when up-to-date units
    are skipped, else None), ``overwrite``, ``keep_going``. Returns ``{"status": "skipped"}``,
    the record of a unit that ran (``status`` "ran"), or, with ``keep_going``,
    ``{"status": "failed", "error": ...}`` instead of raising.
    """
    unit: Unit = task["unit"]
    wd = Path(task["workdir"])
    prior = task.get("prior")
    t0 = time.perf_counter()
    try:
        inputs = {
            k: {"name": Path(p).name, "sha256": sha256_file(p)} for k, p in unit.sources.items()
        }
        key = unit_key(unit.params, inputs)
        if (
            isinstance(prior, dict)
            and prior.get("key") == key
            and all(current_sha(wd / o, (prior.get("outputs") or {}).get(o)) for o in unit.outputs)
        ):
            return {"status": "skipped"}
        result = unit.func(unit.job, UnitWork(wd, key, inputs, bool(task["overwrite"])))
        outputs = {o: fingerprint(wd / o) for o in unit.outputs}
    except Exception as err:
        if not task["keep_going"]:
            if isinstance(err, MegalutError):
                raise type(err)(about(unit.label, str(err))) from None
            raise
        text = (
            str(err)
            if isinstance(err, MegalutError)
            else f"internal error ({type(err).__name__}: {err})"
        )
        return {"status": "failed", "error": text}
    return {
        "status": "ran",
        "key": key,
        "params": unit.params,
        "inputs": inputs,
        "outputs": outputs,
        "result": result,
        "seconds": round(time.perf_counter() - t0, 3),
        "finished": utc_now(),
    }


def _run_units(
    group: Units,
    wd: Path,
    manifest: Manifest,
    *,
    skip_existing: bool,
    overwrite: bool,
    keep_going: bool,
    nproc: int,
    scheduler: str | None,
    progress: Progress | None,
) -> list[UnitReport]:
    """Run the units of ``group`` not up to date, on the executor; record each as it finishes."""
    n = len(group.units)
    tasks = [
        {
            "unit": u,
            "workdir": str(wd.resolve()),
            "prior": manifest.steps.get(u.name) if skip_existing else None,
            "overwrite": overwrite or skip_existing,
            "keep_going": keep_going,
        }
        for u in group.units
    ]
    reports: list[UnitReport | None] = [None] * n
    failed = manifest.failed if manifest.failed is not None else {}
    manifest.failed = failed

    def finished(i: int, out: Mapping[str, Any]) -> None:
        unit = group.units[i]
        failed.pop(unit.name, None)
        if out["status"] == "skipped":
            rec = manifest.steps[unit.name]
            reports[i] = UnitReport(unit.name, unit.label, "skipped", 0.0, rec.get("result"))
            return
        manifest.steps.pop(unit.name, None)
        if out["status"] == "failed":
            failed[unit.name] = out["error"]
            log.error("%s failed: %s", unit.label, out["error"])
            reports[i] = UnitReport(unit.name, unit.label, "failed", 0.0, error=out["error"])
        else:
            manifest.steps[unit.name] = {k: v for k, v in out.items() if k != "status"}
            reports[i] = UnitReport(unit.name, unit.label, "ran", out["seconds"], out["result"])
        manifest.save()

    with (
        executor(nproc, scheduler, n_units=n) as pool,
        (progress or no_progress)(f"{group.noun}s", n) as update,
    ):
        map_units(run_unit, tasks, pool, update, finished)
    manifest.save()
    done = [r for r in reports if r is not None]
    if done and all(r.status == "failed" for r in done):
        first = done[0]
        raise MegalutError(f"every {group.noun} failed (first: {first.label}: {first.error})")
    return done


def run_steps(
    steps: Sequence[Entry],
    workdir: Path,
    run: RunRecord,
    *,
    skip_existing: bool = False,
    overwrite: bool = False,
    keep_going: bool = False,
    nproc: int = 1,
    scheduler: str | None = None,
    progress: Progress | None = None,
) -> list[StepReport]:
    """Run (or bring up to date) ``steps`` in order in ``workdir`` (which exists), recording
    each in ``manifest.json``; return what happened to each.

    ``keep_going``: a failing unit is reported (:func:`failed_units`) and the others
    complete; without it the first failure stops the run. ``nproc``, ``scheduler``: the
    executor of the units; ``progress``: a bar per :class:`Units` step.
    """
    wd = workdir
    manifest = Manifest(wd / MANIFEST, run, skip_existing)
    entries = list(steps)
    if not skip_existing:  # every step of this pipeline runs; other pipelines' records stay
        for entry in entries:
            if isinstance(entry, Step):
                manifest.steps.pop(entry.name, None)
            elif isinstance(entry, Units):
                for unit in entry.units:
                    manifest.steps.pop(unit.name, None)
    shas: dict[str, str] = {}
    results: dict[str, Any] = {}  # unit name -> result, of every finished unit
    reports: list[StepReport] = []
    numbered = not any(callable(e) and not isinstance(e, (Step, Units)) for e in entries)
    i = 0
    while entries:
        entry = entries.pop(0)
        if not isinstance(entry, (Step, Units)):  # a StepBuilder: the steps it declares come next
            entries[:0] = list(entry(dict(results)))
            continue
        i += 1
        label = f"[{i}/{i + len(entries)}] {entry.name}" if numbered else f"[{i}] {entry.name}"
        if isinstance(entry, Units):
            log.info(
                "%s: %d %s(s)%s",
                label,
                len(entry.units),
                entry.noun,
                f": {entry.summary}" if entry.summary else "",
            )
            t0 = time.perf_counter()
            units = _run_units(
                entry,
                wd,
                manifest,
                skip_existing=skip_existing,
                overwrite=overwrite,
                keep_going=keep_going,
                nproc=nproc,
                scheduler=scheduler,
                progress=progress,
            )
            for u in units:
                if u.status != "failed":
                    results[u.name] = u.result
                    rec = manifest.steps[u.name]
                    shas.update({o: f["sha256"] for o, f in rec["outputs"].items()})
            seconds = time.perf_counter() - t0
            counts = {s: sum(u.status == s for u in units) for s in ("ran", "skipped", "failed")}
            log.info(
                "%s: %d ran, %d up to date, %d failed in %.1f s",
                label,
                counts["ran"],
                counts["skipped"],
                counts["failed"],
                seconds,
            )
            reports.append(
                StepReport(entry.name, "ran" if counts["ran"] else "skipped", seconds, units)
            )
            continue
        step = entry
        inputs = {name: shas[name] for name in step.inputs}
        key = step_key(step, inputs)
        donor = None
        if skip_existing:
            rec = manifest.steps.get(step.name) or {}
            current = manifest.up_to_date(step, key, wd)
            if current is not None:
                shas.update(current)
                log.info("%s: up to date, skipped", label)
                reports.append(StepReport(step.name, "skipped", 0.0))
                continue
            donor = manifest.same_work(step, key, wd)
            reason = (
                "parameters or inputs changed"
                if rec.get("key") not in (None, key)
                else ("not run yet" if not rec else "products missing or changed")
            )
            if donor is None:
                log.info("%s: %s: %s", label, reason, step.summary)
        else:
            log.info("%s: %s", label, step.summary)
        manifest.steps.pop(step.name, None)
        t0 = time.perf_counter()
        if donor is not None:
            log.info("%s: the same work as %s: copying its products", label, donor[0])
            _copy_products(wd, donor[1])
        else:
            step.action(wd, overwrite or skip_existing)
        seconds = time.perf_counter() - t0
        outputs = {o: fingerprint(wd / o) for o in step.outputs}
        shas.update({o: f["sha256"] for o, f in outputs.items()})
        manifest.record(step, key, inputs, outputs, seconds, donor[0] if donor else None)
        log.info("%s: done in %.1f s", label, seconds)
        reports.append(StepReport(step.name, "copied" if donor else "ran", seconds))
    return reports


def failed_units(reports: Sequence[StepReport]) -> list[UnitReport]:
    """The units that failed (under ``keep_going``), in order."""
    return [u for r in reports for u in r.units if u.status == "failed"]


def finished_units(reports: Sequence[StepReport]) -> list[UnitReport]:
    """The units that ran or were up to date, in order."""
    return [u for r in reports for u in r.units if u.status != "failed"]


def timing_line(reports: Sequence[StepReport]) -> str:
    """``name 12 s, name skipped, ...``: what each step took."""
    return ", ".join(
        f"{r.name} {r.seconds:.0f} s" if r.status == "ran" else f"{r.name} {r.status}"
        for r in reports
    )
