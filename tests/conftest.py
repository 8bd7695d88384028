"""Shared fixtures."""

from __future__ import annotations

import pytest
from click.testing import CliRunner


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
