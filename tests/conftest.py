"""Shared fixtures, and the strict-skips check (MEGALUT_STRICT_SKIPS=1, used by CI)."""

from __future__ import annotations

import fnmatch
import os
import shutil
import tempfile
from pathlib import Path

import pytest
from click.testing import CliRunner

#: Skips allowed under MEGALUT_STRICT_SKIPS=1: one per line, ``<nodeid or glob> # <reason>``.
EXPECTED_SKIPS = Path(__file__).resolve().with_name("expected_skips.txt")
STRICT_SKIPS_ENV = "MEGALUT_STRICT_SKIPS"


@pytest.fixture
def runner() -> CliRunner:
    """A click CliRunner (stderr kept apart from stdout)."""
    try:
        return CliRunner(mix_stderr=False)
    except TypeError:  # click >= 8.2 always separates them
        return CliRunner()


@pytest.fixture
def cli():
    """The megalut click group."""
    from megalut_cli.cli import main

    return main


@pytest.fixture(autouse=True)
def _one_process_by_default(monkeypatch):
    """-j defaults to all cores; tests run in one process unless they ask for more (spawning
    workers costs seconds on this shared machine). Results do not depend on -j."""
    monkeypatch.setenv("MEGALUT_NPROC", "1")


def read_expected_skips(path: Path) -> list[tuple[str, str]]:
    """``(pattern, reason)`` of each line ``<nodeid or fnmatch glob> # <reason>`` of ``path``
    (blank lines and lines starting with ``#`` are comments; a reason is required)."""
    entries = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        pattern, sep, reason = line.partition(" # ")
        if not sep or not pattern.strip() or not reason.strip():
            raise pytest.UsageError(
                f"{path}:{number}: expected '<nodeid or pattern> # <reason>', got {line!r}"
            )
        entries.append((pattern.strip(), reason.strip()))
    return entries


class StrictSkips:
    """Fails the session (exit status 1) on any skip that ``expected_skips.txt`` does not list:
    a skip in CI means a test that did not run, e.g. a test dependency missing."""

    def __init__(self, path: Path):
        self.path = path
        self.expected = read_expected_skips(path) if path.is_file() else []
        self.skipped: dict[str, str] = {}  # nodeid -> reason
        self.unexpected: list[tuple[str, str]] = []

    def _record(self, report) -> None:
        if not report.skipped or hasattr(report, "wasxfail"):  # xfail is not a skip
            return
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        self.skipped.setdefault(report.nodeid, reason.removeprefix("Skipped: "))

    def pytest_runtest_logreport(self, report) -> None:
        self._record(report)

    def pytest_collectreport(self, report) -> None:  # a module skipped whole (allow_module_level)
        self._record(report)

    def is_expected(self, nodeid: str) -> bool:
        return any(nodeid == p or fnmatch.fnmatchcase(nodeid, p) for p, _ in self.expected)

    @pytest.hookimpl(trylast=True)
    def pytest_sessionfinish(self, session) -> None:
        self.unexpected = [(n, r) for n, r in self.skipped.items() if not self.is_expected(n)]
        if self.unexpected and session.exitstatus == pytest.ExitCode.OK:
            session.exitstatus = pytest.ExitCode.TESTS_FAILED

    def pytest_terminal_summary(self, terminalreporter) -> None:
        if not self.unexpected:
            return
        terminalreporter.section(f"unexpected skips ({STRICT_SKIPS_ENV}=1)", red=True, bold=True)
        for nodeid, reason in self.unexpected:
            terminalreporter.line(f"SKIPPED {nodeid} - {reason}", red=True)
        terminalreporter.line(
            f"{len(self.unexpected)} skip(s) not listed in {self.path}: install what they need, "
            "or list them there with their reason if the skip is legitimate on this machine",
            red=True,
        )


def pytest_configure(config) -> None:
    # The disk cache (megalut_cli.cache) of this session: a fresh folder, not the user's,
    # unless MEGALUT_CACHE names one; the CLI's subprocesses inherit it.
    if "MEGALUT_CACHE" not in os.environ:
        folder = tempfile.mkdtemp(prefix="megalut-test-cache-")
        os.environ["MEGALUT_CACHE"] = folder
        config.add_cleanup(lambda: shutil.rmtree(folder, ignore_errors=True))
    if os.environ.get(STRICT_SKIPS_ENV) == "1":
        config.pluginmanager.register(StrictSkips(EXPECTED_SKIPS), "megalut-strict-skips")
