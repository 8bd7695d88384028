"""The step engine (``steps.py``) with a toy pipeline: keys, skipping, what re-runs, copies."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from megalut_cli.errors import MegalutError
from megalut_cli.steps import MANIFEST, RunRecord, Step, check_workdir, run_steps

RUN = RunRecord("", "toy.toml", "0" * 64, (), {"value": 1})


def toy_steps(calls: list[str], value: int, prefix: str = "") -> list[Step]:
    """``a`` writes ``value``; ``b`` writes ``a`` twice (so it depends on ``a``'s content)."""

    def write_a(wd: Path, overwrite: bool) -> None:
        calls.append(prefix + "a")
        (wd / f"{prefix}a.txt").write_text(str(value))

    def write_b(wd: Path, overwrite: bool) -> None:
        calls.append(prefix + "b")
        (wd / f"{prefix}b.txt").write_text((wd / f"{prefix}a.txt").read_text() * 2)

    return [
        Step(prefix + "a", [prefix + "a.txt"], [], {"value": value}, write_a, "writes a", prefix),
        Step(prefix + "b", [prefix + "b.txt"], [prefix + "a.txt"], {}, write_b, "doubles a", prefix),
    ]


def _statuses(reports) -> list[str]:
    return [r.status for r in reports]


def test_skip_and_rerun_by_content(tmp_path: Path) -> None:
    calls: list[str] = []
    assert _statuses(run_steps(toy_steps(calls, 1), tmp_path, RUN)) == ["ran", "ran"]
    assert calls == ["a", "b"] and (tmp_path / "b.txt").read_text() == "11"
    manifest = json.loads((tmp_path / MANIFEST).read_text())
    assert manifest["format"] == "megalut.run-manifest" and set(manifest["steps"]) == {"a", "b"}
    assert manifest["pipeline"]["effective"] == {"value": 1}

    calls.clear()  # nothing changed: everything skipped
    assert _statuses(run_steps(toy_steps(calls, 1), tmp_path, RUN, skip_existing=True)) == ["skipped", "skipped"]
    assert calls == []

    os.utime(tmp_path / "a.txt", ns=(0, 0))  # touched, same content: still up to date (sha256)
    assert _statuses(run_steps(toy_steps(calls, 1), tmp_path, RUN, skip_existing=True)) == ["skipped", "skipped"]

    (tmp_path / "a.txt").write_text("9")  # changed by hand: a re-runs, b (same input content again) does not
    assert _statuses(run_steps(toy_steps(calls, 1), tmp_path, RUN, skip_existing=True)) == ["ran", "skipped"]
    assert calls == ["a"] and (tmp_path / "a.txt").read_text() == "1"

    calls.clear()  # a parameter changed: the step and everything downstream
    assert _statuses(run_steps(toy_steps(calls, 2), tmp_path, RUN, skip_existing=True)) == ["ran", "ran"]
    assert (tmp_path / "b.txt").read_text() == "22"


def test_same_work_in_a_named_pipeline_is_copied(tmp_path: Path) -> None:
    calls: list[str] = []
    run_steps(toy_steps(calls, 3), tmp_path, RUN)
    (tmp_path / "x").mkdir()
    calls.clear()
    named = RunRecord("x", "toy-x.toml", "1" * 64, (), {})
    assert _statuses(run_steps(toy_steps(calls, 3, "x/"), tmp_path, named, skip_existing=True)) == ["copied", "copied"]
    assert calls == [] and (tmp_path / "x" / "b.txt").read_text() == "33"
    manifest = json.loads((tmp_path / MANIFEST).read_text())
    assert manifest["steps"]["x/b"]["copied_from"] == "b" and set(manifest["pipelines"]) == {"", "x"}


def test_check_workdir_refuses_products_without_a_flag(tmp_path: Path) -> None:
    steps = toy_steps([], 1)
    check_workdir(tmp_path, steps, False, False)  # empty: fine
    (tmp_path / "b.txt").write_text("old")
    with pytest.raises(MegalutError, match="b.txt exists; use --skip-existing"):
        check_workdir(tmp_path, steps, False, False)
    check_workdir(tmp_path, steps, True, False)
    check_workdir(tmp_path, steps, False, True)
    (tmp_path / "file").write_text("")
    with pytest.raises(MegalutError, match="not a folder"):
        check_workdir(tmp_path / "file", steps, False, False)
