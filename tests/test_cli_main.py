"""The megalut group: version, help, verbosity, man pages."""

from __future__ import annotations

import pytest

from megalut_cli import __version__

COMMANDS = ["simulate", "measure", "train-point", "train-weight", "predict", "evaluate", "run"]


def test_version(runner, cli):
    result = runner.invoke(cli, ["--version"])
    assert result.exit_code == 0
    assert __version__ in result.output


def test_help_lists_commands_in_pipeline_order(runner, cli):
    result = runner.invoke(cli, ["--help"])
    assert result.exit_code == 0
    positions = [result.output.index(f"  {c} ") for c in COMMANDS]
    assert positions == sorted(positions)


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_has_help_with_example(runner, cli, command):
    result = runner.invoke(cli, [command, "--help"])
    assert result.exit_code == 0
    assert "megalut " + command in result.output
    assert "Example" in result.output


def test_unknown_command_is_usage_error(runner, cli):
    result = runner.invoke(cli, ["frobnicate"])
    assert result.exit_code == 2


def test_man_pages_are_current(tmp_path):
    """man/ must be regenerated (python -m megalut_cli.cli.manpages) when the help changes."""
    from pathlib import Path

    import click_man  # noqa: F401  (the test extra: a missing click-man must fail, not skip)

    from megalut_cli.cli.manpages import generate

    shipped = Path(__file__).resolve().parents[1] / "man"
    fresh = generate(tmp_path)
    assert sorted(p.name for p in fresh) == sorted(p.name for p in shipped.glob("*.1"))
    for page in fresh:
        assert page.read_text() == (shipped / page.name).read_text(), (
            f"man/{page.name} is stale: run python -m megalut_cli.cli.manpages"
        )
