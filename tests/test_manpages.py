"""Man pages: examples that fit an 80-column terminal, roff escaping, installed by pip."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from megalut_cli.cli import main

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib
from megalut_cli.cli.manpages import MAX_EXAMPLE_WIDTH, example_blocks, help_to_roff, iter_commands

ROOT = Path(__file__).resolve().parents[1]
MAN = ROOT / "man"


def test_every_command_has_a_page_and_examples():
    names = {ctx.command_path.replace(" ", "-") + ".1" for ctx in iter_commands(main)}
    assert names == {p.name for p in MAN.glob("*.1")}
    assert "megalut-info.1" in names
    for ctx in iter_commands(main):
        assert list(example_blocks(ctx.command.help)), f"{ctx.command_path}: no example"


def test_example_lines_fit_a_terminal():
    """Long example commands continue after a backslash instead of wrapping mid-option."""
    for ctx in iter_commands(main):
        for line in example_blocks(ctx.command.help):
            assert len(line) <= MAX_EXAMPLE_WIDTH, f"{ctx.command_path}: {line!r}"


def test_roff_escaping():
    roff = help_to_roff(
        "Intro text, --opt.\n'quoted' start\n.dot start\n\n\b\nExample:\n  a \\\n      --b c\n"
    )
    lines = roff.split("\n")
    assert r"\&'quoted' start" in lines and r"\&.dot start" in lines  # not roff requests
    assert ".nf" in lines and ".fi" in lines  # examples not refilled
    assert r"  a \e" in lines and r"      \-\-b c" in lines
    assert "\b" not in roff


@pytest.mark.skipif(shutil.which("man") is None, reason="no man command")
def test_rendered_examples_are_whole_lines():
    env = {**os.environ, "MANWIDTH": "80", "MAN_KEEP_FORMATTING": ""}
    for ctx in iter_commands(main):
        page = MAN / (ctx.command_path.replace(" ", "-") + ".1")
        text = subprocess.run(
            ["man", "-l", str(page)], capture_output=True, text=True, env=env, check=True
        ).stdout
        rendered = {line.strip() for line in text.splitlines()}
        for line in example_blocks(ctx.command.help):
            assert line.strip() in rendered, f"{page.name}: {line!r} not rendered whole"
        assert "\b" not in text


def test_pyproject_installs_every_page():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    patterns = cfg["tool"]["setuptools"]["data-files"]["share/man/man1"]
    installed = {p.name for pat in patterns for p in ROOT.glob(pat)}
    assert installed == {p.name for p in MAN.glob("*.1")}


def test_wheel_contains_the_man_pages(tmp_path):
    """`pip wheel` on a copy of the source puts man/*.1 under <env>/share/man/man1. Offline:
    the installed setuptools (the test extra's) builds it, nothing is downloaded."""
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for name in ("megalut_cli", "man"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__"))
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "--no-index",
            "-q",
            "-w",
            str(tmp_path / "dist"),
            str(src),
        ],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    (wheel,) = (tmp_path / "dist").glob("megalut_cli-*.whl")
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
        pages = {Path(n).name: n for n in names if "/data/share/man/man1/" in n}
        assert set(pages) == {p.name for p in MAN.glob("*.1")}
        assert (
            z.read(pages["megalut-simulate.1"]).decode() == (MAN / "megalut-simulate.1").read_text()
        )
