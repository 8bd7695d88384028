"""Two first-contact papercuts of issue 24: `simulate CONFIG` errors name the key as the file
writes it (as pipeline errors do), and Ctrl-C is one line and exit 130 at any moment, also
while the command's packages are still being imported."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from helpers import error_text, one_line
from sim_configs import write as write_sim_config

ROOT = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------- simulate CONFIG errors
@pytest.mark.parametrize(
    ("replace", "overrides", "expected"),
    [
        (
            {
                'rad = {type = "uniform", min = 1.5, max = 3.0}': (
                    'rad = {type = "uniform", min = -1.5, max = 3.0}'
                )
            },
            [],
            "{file}: [galaxy] rad: the half-light radius must be > 0.0, but values reach -1.5",
        ),
        (
            {'[noise]\ntype = "gaussian"\nsigma': '[noise]\ntype = "gaussian"\nsigam'},
            [],
            "{file}: [noise] sigam: unknown key",
        ),
        ({"mode = 0.2, min": "mode = 0.2, mn"}, [], "{file}: [galaxy] ellipticity.mn: unknown key"),
        ({"n_cases = 3\n": ""}, [], "{file}: [structure] n_cases: missing"),
        ({"[shear]": "[shaer]"}, [], "{file}: [shaer]: unknown table or key"),
        (
            {},
            ["galaxy.rad.min=-1"],
            "galaxy.rad: the half-light radius must be > 0.0",
        ),  # as the override writes it
        ({}, ["noise.sigam=1"], "noise.sigam: unknown key"),
    ],
)
def test_simulate_config_errors_name_the_file_and_table_as_written(
    runner, cli, tmp_path, replace, overrides, expected
) -> None:
    path = write_sim_config(tmp_path, replace=replace)
    result = runner.invoke(
        cli, ["simulate", str(path), *overrides, "-o", str(tmp_path / "out.fits"), "--dry-run"]
    )
    assert result.exit_code == 2, error_text(result)
    assert one_line(result).startswith("Error: " + expected.format(file=path)), error_text(result)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sim.toml"]


def test_simulate_structure_flags_are_not_blamed_on_the_file(runner, cli, tmp_path) -> None:
    """--n-realizations 3 with snc = 'pairs': the file does not say 3, the command line does."""
    path = write_sim_config(tmp_path, replace={'snc = "ring"': 'snc = "pairs"'})
    result = runner.invoke(
        cli, ["simulate", str(path), "-o", str(tmp_path / "o.fits"), "--n-realizations", "3"]
    )
    assert result.exit_code == 2
    assert (
        one_line(result)
        == "Error: structure.n_realizations: snc = 'pairs' needs an even number, got 3"
    )


def test_the_library_keeps_dotted_keys_and_the_helper_is_shared(tmp_path) -> None:
    """load_config names keys dotted (its callers name them their way); one helper
    (configfile.where_written) names them as written, for simulation and pipeline files."""
    from megalut_cli.configfile import config_source, where_written
    from megalut_cli.errors import ConfigError
    from megalut_cli.sim.config import keys_as_written, load_config

    path = write_sim_config(tmp_path, replace={"sigma = 1.5": "sigma = -1.5"})
    with pytest.raises(ConfigError, match=r"^psf\.sigma: must be > 0"):
        load_config(path)
    with (
        pytest.raises(ConfigError, match=r"sim\.toml: \[psf\] sigma: must be > 0"),
        keys_as_written(path),
    ):
        load_config(path)
    src = config_source(path, "F")
    assert where_written("psf.sigma: bad", [src]) == "F: [psf] sigma: bad"
    assert where_written("F: psf: no", [src]) == "F: psf: no"  # a message naming the file already
    assert where_written("override 'x': bad key", [src]) == "override 'x': bad key"
    assert where_written("psf.sigma: bad", [src], ["psf.sigma=2"]) == "psf.sigma: bad"


# --------------------------------------------------------------------------- Ctrl-C at any moment
#: Runs the console script's entry point and sends this process SIGINT when it first imports
#: MODULE (while megalut's packages are being imported, before the group exists).
_INTERRUPT_ON_IMPORT = """
import builtins, os, signal, sys
module, entry, args = sys.argv[1], sys.argv[2], sys.argv[3:]
real_import = builtins.__import__
def interrupting_import(name, *a, **k):
    if name == module:
        builtins.__import__ = real_import
        os.kill(os.getpid(), signal.SIGINT)
    return real_import(name, *a, **k)
builtins.__import__ = interrupting_import
sys.argv = ["megalut", *args]
if entry == "run":
    from megalut_cli.__main__ import run
    run()
else:  # the entry point before: the group itself
    from megalut_cli.cli import main
    main()
"""


def _interrupted_run(module: str, entry: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", _INTERRUPT_ON_IMPORT, module, entry, *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )


@pytest.mark.parametrize("module", ["click", "megalut_cli.cli.console"])
def test_ctrl_c_while_importing_is_one_line_and_130(module) -> None:
    done = _interrupted_run(module, "run", "simulate", "--help")
    assert done.returncode == 130 and done.stderr == "megalut: interrupted\n", done.stderr
    assert done.stdout == ""
    before = _interrupted_run(module, "main", "simulate", "--help")  # what the group alone did
    assert "Traceback" in before.stderr and "KeyboardInterrupt" in before.stderr


def test_ctrl_c_while_the_group_reads_its_options_is_one_line_and_130() -> None:
    """--help is printed while the group's own options are read, outside its command's handling."""
    code = (
        "import os, signal, sys\nfrom megalut_cli import cli\n"
        "def format_commands(self, ctx, formatter):\n    os.kill(os.getpid(), signal.SIGINT)\n"
        "cli.MegalutGroup.format_commands = format_commands\nsys.argv = ['megalut', '--help']\n"
        "from megalut_cli.__main__ import run\nrun()\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 130 and done.stderr == "megalut: interrupted\n", done.stderr


def test_the_console_script_is_the_interrupt_safe_entry_point() -> None:
    from megalut_cli.configfile import tomllib

    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["megalut"] == "megalut_cli.__main__:run"
    done = subprocess.run(
        [sys.executable, "-m", "megalut_cli", "--version"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0 and "megalut" in done.stdout
