"""The step engine (``steps.py``) with a toy pipeline: keys, skipping, what re-runs, copies."""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path

import pytest

from megalut_cli.errors import MegalutError
from megalut_cli.pipeline.steps import (
    MANIFEST,
    RunRecord,
    Step,
    check_workdir,
    failed_units,
    run_steps,
)

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
        Step(
            prefix + "b", [prefix + "b.txt"], [prefix + "a.txt"], {}, write_b, "doubles a", prefix
        ),
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
    assert _statuses(run_steps(toy_steps(calls, 1), tmp_path, RUN, skip_existing=True)) == [
        "skipped",
        "skipped",
    ]
    assert calls == []

    os.utime(tmp_path / "a.txt", ns=(0, 0))  # touched, same content: still up to date (sha256)
    assert _statuses(run_steps(toy_steps(calls, 1), tmp_path, RUN, skip_existing=True)) == [
        "skipped",
        "skipped",
    ]

    (tmp_path / "a.txt").write_text(
        "9"
    )  # changed by hand: a re-runs, b (same input content again) does not
    assert _statuses(run_steps(toy_steps(calls, 1), tmp_path, RUN, skip_existing=True)) == [
        "ran",
        "skipped",
    ]
    assert calls == ["a"] and (tmp_path / "a.txt").read_text() == "1"

    calls.clear()  # a parameter changed: the step and everything downstream
    assert _statuses(run_steps(toy_steps(calls, 2), tmp_path, RUN, skip_existing=True)) == [
        "ran",
        "ran",
    ]
    assert (tmp_path / "b.txt").read_text() == "22"


def test_same_work_in_a_named_pipeline_is_copied(tmp_path: Path) -> None:
    calls: list[str] = []
    run_steps(toy_steps(calls, 3), tmp_path, RUN)
    (tmp_path / "x").mkdir()
    calls.clear()
    named = RunRecord("x", "toy-x.toml", "1" * 64, (), {})
    assert _statuses(run_steps(toy_steps(calls, 3, "x/"), tmp_path, named, skip_existing=True)) == [
        "copied",
        "copied",
    ]
    assert calls == [] and (tmp_path / "x" / "b.txt").read_text() == "33"
    manifest = json.loads((tmp_path / MANIFEST).read_text())
    assert manifest["steps"]["x/b"]["copied_from"] == "b" and set(manifest["pipelines"]) == {
        "",
        "x",
    }


def test_check_workdir_refuses_products_without_a_flag(tmp_path: Path) -> None:
    steps = toy_steps([], 1)
    check_workdir(tmp_path, steps, False, False)  # empty: fine
    (tmp_path / "b.txt").write_text("old")
    with pytest.raises(
        MegalutError,
        match="b.txt exists; use skip_existing=True to reuse the up-to-date products or "
        "overwrite=True to redo",
    ):
        check_workdir(tmp_path, steps, False, False)
    check_workdir(tmp_path, steps, True, False)
    check_workdir(tmp_path, steps, False, True)
    (tmp_path / "file").write_text("")
    with pytest.raises(MegalutError, match="not a folder"):
        check_workdir(tmp_path / "file", steps, False, False)


# --------------------------------------------------------------------------- work units


def toy_units(tmp_path: Path, n: int = 4, factor: int = 10) -> list:
    """``n`` units (``u<i>.txt`` = source i x factor), then a step summing what finished."""
    from helpers import toy_unit

    from megalut_cli.pipeline.steps import Unit, Units

    src = tmp_path / "src"
    src.mkdir(exist_ok=True)
    units = []
    for i in range(n):
        if not (src / f"{i}.txt").exists():
            (src / f"{i}.txt").write_text(str(i + 1))
        job = {
            "i": i,
            "source": str(src / f"{i}.txt"),
            "factor": factor,
            "log": str(tmp_path / "calls.log"),
        }
        units.append(
            Unit(
                f"u-{i}",
                f"unit {i}",
                [f"u{i}.txt"],
                {"factor": factor, "i": i},
                {"source": src / f"{i}.txt"},
                toy_unit,
                job,
            )
        )

    def total(results):
        names = [f"u{r['i']}.txt" for r in results.values()]

        def write(wd: Path, overwrite: bool) -> None:
            (wd / "total.txt").write_text(str(sum(int((wd / n).read_text()) for n in names)))

        return [Step("total", ["total.txt"], names, {"units": sorted(results)}, write, "sum")]

    return [Units("units", units, "toy units", noun="unit"), total]


def _calls(tmp_path: Path) -> list[int]:
    log = tmp_path / "calls.log"
    calls = sorted(int(x) for x in log.read_text().split()) if log.exists() else []
    log.unlink(missing_ok=True)
    return calls


def _unit_statuses(reports) -> list[str]:
    return [u.status for r in reports for u in r.units]


def test_units_skip_and_rerun_by_content(tmp_path: Path) -> None:
    wd = tmp_path / "wd"
    wd.mkdir()
    reports = run_steps(toy_units(tmp_path), wd, RUN)
    assert _unit_statuses(reports) == ["ran"] * 4 and _calls(tmp_path) == [0, 1, 2, 3]
    assert (wd / "total.txt").read_text() == str(10 * (1 + 2 + 3 + 4))
    manifest = json.loads((wd / MANIFEST).read_text())
    assert manifest["format"] == "megalut.run-manifest" and manifest["failed"] == {}
    assert (
        manifest["steps"]["u-2"]["result"]["value"] == 30
        and manifest["steps"]["u-2"]["inputs"]["source"]["name"] == "2.txt"
    )
    # the unit function was handed the key the engine recorded
    assert manifest["steps"]["u-2"]["result"]["key"] == manifest["steps"]["u-2"]["key"]

    # nothing changed: every unit and the step after them skipped, results given back
    reports = run_steps(toy_units(tmp_path), wd, RUN, skip_existing=True)
    assert _unit_statuses(reports) == ["skipped"] * 4 and _calls(tmp_path) == []
    assert [r.status for r in reports] == ["skipped", "skipped"]
    assert [u.result["value"] for u in reports[0].units] == [10, 20, 30, 40]

    # one source changed: that unit re-runs, and the step downstream (its input changed)
    (tmp_path / "src" / "1.txt").write_text("7")
    reports = run_steps(toy_units(tmp_path), wd, RUN, skip_existing=True)
    assert _unit_statuses(reports) == ["skipped", "ran", "skipped", "skipped"] and _calls(
        tmp_path
    ) == [1]
    assert reports[1].status == "ran" and (wd / "total.txt").read_text() == str(
        10 * (1 + 7 + 3 + 4)
    )

    # a product changed by hand: that unit re-runs; a parameter changed: every unit
    (wd / "u3.txt").write_text("0")
    run_steps(toy_units(tmp_path), wd, RUN, skip_existing=True)
    assert _calls(tmp_path) == [3] and (wd / "u3.txt").read_text() == "40"
    run_steps(toy_units(tmp_path, factor=2), wd, RUN, skip_existing=True)
    assert _calls(tmp_path) == [0, 1, 2, 3] and (wd / "total.txt").read_text() == str(
        2 * (1 + 7 + 3 + 4)
    )

    # without skip_existing every unit runs again
    run_steps(toy_units(tmp_path, factor=2), wd, RUN, overwrite=True)
    assert _calls(tmp_path) == [0, 1, 2, 3]


def test_units_keep_going(tmp_path: Path) -> None:
    wd = tmp_path / "wd"
    wd.mkdir()
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "2.txt").write_text("bad")
    # without keep_going the first failure stops the run, naming the unit; earlier units are
    # recorded
    with pytest.raises(MegalutError, match=r"^unit 2: .*2.txt: bad content$"):
        run_steps(toy_units(tmp_path), wd, RUN)
    assert _calls(tmp_path) == [0, 1] and not (wd / "total.txt").exists()
    assert {"u-0", "u-1"} <= set(json.loads((wd / MANIFEST).read_text())["steps"])
    # with it the others complete (the recorded ones are skipped), the failure is reported
    reports = run_steps(toy_units(tmp_path), wd, RUN, skip_existing=True, keep_going=True)
    assert _unit_statuses(reports) == ["skipped", "skipped", "failed", "ran"] and _calls(
        tmp_path
    ) == [3]
    assert [u.name for u in failed_units(reports)] == ["u-2"] and "bad content" in failed_units(
        reports
    )[0].error
    assert (wd / "total.txt").read_text() == str(10 * (1 + 2 + 4))
    manifest = json.loads((wd / MANIFEST).read_text())
    assert list(manifest["failed"]) == ["u-2"] and "u-2" not in manifest["steps"]
    assert manifest["steps"]["total"]["params"]["units"] == ["u-0", "u-1", "u-3"]
    # fixed: only it runs; the failure is gone from the manifest
    (tmp_path / "src" / "2.txt").write_text("3")
    reports = run_steps(toy_units(tmp_path), wd, RUN, skip_existing=True, keep_going=True)
    assert _unit_statuses(reports) == ["skipped", "skipped", "ran", "skipped"] and _calls(
        tmp_path
    ) == [2]
    assert json.loads((wd / MANIFEST).read_text())["failed"] == {}
    # every unit failing is an error, even with keep_going
    for i in range(4):
        (tmp_path / "src" / f"{i}.txt").write_text("bad")
    with pytest.raises(MegalutError, match="every unit failed"):
        run_steps(toy_units(tmp_path), wd, RUN, overwrite=True, keep_going=True)


def test_units_do_not_depend_on_workers(tmp_path: Path) -> None:
    """The same products and records on 2 worker processes as in this one."""
    products = {}
    for nproc in (1, 2):
        base = tmp_path / f"j{nproc}"
        base.mkdir()
        (base / "wd").mkdir()
        bar: list[tuple[str, int, int]] = []

        @contextlib.contextmanager
        def progress(label, total, bar=bar):
            done: list[int] = []
            yield done.append
            bar.append((label, total, sum(done)))

        run_steps(toy_units(base, n=5), base / "wd", RUN, nproc=nproc, progress=progress)
        assert bar == [("units", 5, 5)]
        man = json.loads((base / "wd" / MANIFEST).read_text())
        products[nproc] = (
            {p.name: p.read_text() for p in (base / "wd").glob("*.txt")},
            {
                n: (r["key"], r["result"]["value"])
                for n, r in man["steps"].items()
                if n.startswith("u-")
            },
        )
    assert products[1] == products[2]


def test_old_manifest_format_is_refused_with_skip_existing(tmp_path: Path) -> None:
    (tmp_path / MANIFEST).write_text(json.dumps({"format": "megalut.great3-run", "subfields": {}}))
    with pytest.raises(
        MegalutError,
        match=r"older megalut \(format megalut.great3-run\).*use overwrite=True to redo",
    ):
        run_steps(toy_units(tmp_path), tmp_path, RUN, skip_existing=True)
    run_steps(toy_units(tmp_path), tmp_path, RUN, overwrite=True)  # --overwrite replaces it
    assert json.loads((tmp_path / MANIFEST).read_text())["format"] == "megalut.run-manifest"


def test_made_workdir_leaves_no_empty_folder(tmp_path: Path) -> None:
    from megalut_cli.pipeline.steps import made_workdir

    wd = tmp_path / "a" / "wd"
    with pytest.raises(RuntimeError), made_workdir(wd, "sub"):
        assert (wd / "sub").is_dir()
        raise RuntimeError
    assert not wd.exists()
    with made_workdir(wd, "sub"):
        pass
    assert (wd / "sub").is_dir()
