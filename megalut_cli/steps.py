"""The step engine of ``megalut run``: a work folder, a list of steps, a manifest.

A pipeline (``pipeline.py``, ``great3/pipeline.py``) declares its work as :class:`Step`
objects — products, inputs (products of earlier steps), parameters and an action — and
:func:`run_steps` runs them in order in a work folder, recording in :class:`Manifest`
(``manifest.json``) each finished step's key (sha256 of its parameters, the sha256 of
its inputs and the megalut version) and the sha256, size and modification time of its
products. With ``skip_existing`` a step whose key is unchanged and whose products are
still those recorded is skipped; a step whose key is that of a finished step elsewhere
in the folder (another named pipeline) copies that step's products. The execution
engine (``-j``, Dask) is not part of a key: the results do not depend on it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from megalut_cli import __version__
from megalut_cli.atomic import atomic_output, write_json
from megalut_cli.errors import MegalutError
from megalut_cli.provenance import sha256_file, utc_now

log = logging.getLogger("megalut")

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


@dataclass
class StepReport:
    name: str
    status: str  # "ran", "skipped" or "copied" (the products of the same work in another pipeline)
    seconds: float


@dataclass(frozen=True)
class RunRecord:
    """What the manifest records of the pipeline file that declared the steps."""

    name: str  # "" for an unnamed pipeline
    path: str
    sha256: str
    overrides: tuple[str, ...]
    effective: dict[str, Any]  # the validated file, overrides applied

    def as_dict(self) -> dict[str, Any]:
        return {"path": self.path, "sha256": self.sha256, "overrides": list(self.overrides),
                "effective": self.effective}


def sha_text(obj: Any) -> str:
    """The sha256 of ``obj`` as sorted JSON (``str`` for what JSON cannot hold)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def fingerprint(path: Path) -> dict[str, Any]:
    """What the manifest records of a product: sha256, size, modification time."""
    st = path.stat()
    return {"sha256": sha256_file(path), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def current_sha(path: Path, record: Any) -> str | None:
    """The sha256 of ``path`` if it is still the product ``record`` (a :func:`fingerprint`) describes.

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

    def __init__(self, path: Path, run: RunRecord) -> None:
        self.path = path
        self.run = run
        self.steps: dict[str, Any] = {}
        self.pipelines: dict[str, Any] = {}  # name ("" unnamed) -> the last pipeline of that name run here
        if path.is_file():
            try:
                data = json.loads(path.read_text())
            except (OSError, UnicodeDecodeError, json.JSONDecodeError):
                log.warning("%s: unreadable, every step will run", path)
                data = {}
            if isinstance(data, dict) and data.get("format") == MANIFEST_FORMAT and isinstance(data.get("steps"), dict):
                self.steps = data["steps"]
                if isinstance(data.get("pipelines"), dict):
                    self.pipelines = data["pipelines"]

    def current_sha(self, step: str, workdir: Path, name: str) -> str | None:
        """The sha256 of product ``name`` if it is still what ``step`` recorded, else None."""
        return current_sha(workdir / name, (self.steps.get(step) or {}).get("outputs", {}).get(name))

    def same_work(self, step: Step, key: str, workdir: Path) -> tuple[str, dict[str, str]] | None:
        """Another step with this key whose products are intact: (its name, our product -> its product)."""
        for other, rec in self.steps.items():
            if other == step.name or not isinstance(rec, dict) or rec.get("key") != key:
                continue
            theirs = list(rec.get("outputs") or {})
            if len(theirs) == len(step.outputs) and all(self.current_sha(other, workdir, o) for o in theirs):
                return other, dict(zip(step.outputs, theirs))
        return None

    def record(self, step: Step, key: str, inputs: Mapping[str, str], outputs: Mapping[str, dict[str, Any]],
               seconds: float, copied_from: str | None = None) -> None:
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
        write_json(self.path, data, overwrite=True)


def _unprefix(name: str, prefix: str) -> str:
    return name[len(prefix):] if prefix and name.startswith(prefix) else name


def step_key(step: Step, input_shas: Mapping[str, str]) -> str:
    """The identity of a step's work: parameters, input contents, megalut version (no pipeline name)."""
    inputs = {_unprefix(n, step.prefix): s for n, s in input_shas.items()}
    return sha_text({"step": _unprefix(step.name, step.prefix), "params": step.params, "inputs": inputs,
                     "megalut": __version__})


def products(steps: Sequence[Step]) -> list[str]:
    """Every product of ``steps``, in order."""
    return [o for s in steps for o in s.outputs]


def check_workdir(workdir: Path, steps: Sequence[Step], skip_existing: bool, overwrite: bool,
                  also: Sequence[str] = ()) -> None:
    """Fail early: a file where the folder should be, an unwritable place, or products
    (or the files named in ``also``) there without ``skip_existing`` or ``overwrite``."""
    if workdir.exists() and not workdir.is_dir():
        raise MegalutError(f"--workdir {workdir}: exists and is not a folder")
    existing = next((p for p in (workdir, *workdir.absolute().parents) if p.exists()), Path("."))
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        where = "" if existing == workdir else f" (its folder {existing})"
        raise MegalutError(f"--workdir {workdir}: not writable{where}")
    if skip_existing or overwrite:
        return
    for name in dict.fromkeys([*products(steps), *also, MANIFEST]):
        if (workdir / name).exists():
            raise MegalutError(
                f"{workdir / name} exists; use --skip-existing to reuse the up-to-date products "
                "or --overwrite to redo every step"
            )


def _copy_products(wd: Path, mapping: Mapping[str, str]) -> None:
    for ours, theirs in mapping.items():
        with atomic_output(wd / ours, overwrite=True) as tmp:
            shutil.copyfile(wd / theirs, tmp)


def run_steps(steps: Sequence[Step], workdir: Path, run: RunRecord, *, skip_existing: bool = False,
              overwrite: bool = False) -> list[StepReport]:
    """Run (or bring up to date) ``steps`` in order in ``workdir`` (which exists), recording
    each in ``manifest.json``; return what happened to each."""
    wd = workdir
    manifest = Manifest(wd / MANIFEST, run)
    if not skip_existing:  # every step of this pipeline runs; other pipelines' records stay
        for step in steps:
            manifest.steps.pop(step.name, None)
    shas: dict[str, str] = {}
    reports: list[StepReport] = []
    for i, step in enumerate(steps, 1):
        label = f"[{i}/{len(steps)}] {step.name}"
        inputs = {name: shas[name] for name in step.inputs}
        key = step_key(step, inputs)
        donor = None
        if skip_existing:
            rec = manifest.steps.get(step.name) or {}
            current = {o: manifest.current_sha(step.name, wd, o) for o in step.outputs}
            if rec.get("key") == key and all(current.values()):
                shas.update({o: s for o, s in current.items() if s})
                log.info("%s: up to date, skipped", label)
                reports.append(StepReport(step.name, "skipped", 0.0))
                continue
            donor = manifest.same_work(step, key, wd)
            reason = "parameters or inputs changed" if rec.get("key") not in (None, key) else (
                "not run yet" if not rec else "products missing or changed")
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


def timing_line(reports: Sequence[StepReport]) -> str:
    """``name 12 s, name skipped, ...``: what each step took."""
    return ", ".join(f"{r.name} {r.seconds:.0f} s" if r.status == "ran" else f"{r.name} {r.status}"
                     for r in reports)
