"""The megalut group: version, help, verbosity, man pages."""

from __future__ import annotations

import pytest

from megalut_cli import __version__

COMMANDS = [
    "simulate",
    "measure",
    "train-point",
    "train-weight",
    "predict",
    "evaluate",
    "run",
    "draft",
]


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


#: Packages whose import takes most of a second (issue 26): no help or version needs them.
HEAVY = ("astropy", "galsim", "scipy", "numba", "fitsio", "h5py", "matplotlib", "jax", "dask")


def _modules_after(args: list[str], all_names: bool = False) -> set[str]:
    """Top-level packages and megalut_cli.cli modules imported by ``megalut ARGS`` (a fresh
    process; ``all_names``: every module)."""
    import json
    import subprocess
    import sys

    code = (
        "import json, sys\nfrom megalut_cli.cli import main\n"
        f"try:\n    main({args!r}, prog_name='megalut')\nexcept SystemExit:\n    pass\n"
        "print(json.dumps(sorted(sys.modules)), file=sys.stderr)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    names = json.loads(done.stderr.strip().splitlines()[-1])
    if all_names:
        return set(names)
    return {n.split(".")[0] for n in names} | {n for n in names if n.startswith("megalut_cli.cli.")}


def test_version_and_group_help_load_no_subcommand():
    for args in (["--version"], ["--help"]):
        loaded = _modules_after(args)
        assert not loaded & set(HEAVY), (args, loaded & set(HEAVY))
        assert (
            not {f"megalut_cli.cli.{m}" for m in ("simulate", "measure", "predict", "run")} & loaded
        )


@pytest.mark.parametrize("command", [*COMMANDS, "info"])
def test_command_help_needs_no_heavy_package(command):
    loaded = _modules_after([command, "--help"])
    assert not loaded & set(HEAVY), loaded & set(HEAVY)


#: What a plain (non-metacal) fast-engine simulate or measure does not use (issue 26): GalSim
#: with astropy (the Sersic tables and the fixed PSF's k-images come from the disk cache), the
#: metacal modules, and numba's CPU-target refresh.
NOT_ON_THE_PLAIN_PATH = (
    "galsim",
    "astropy",
    "megalut_cli.measure.metacal",
    "numba.np.arraymath",  # numba's target refresh: cached kernels load lightly (jit.py)
    "scipy.linalg",  # which that refresh imports
)


def test_plain_simulate_and_measure_load_neither_galsim_nor_metacal(tmp_path, monkeypatch):
    """After a first run has filled the disk cache, ``simulate --measure`` and ``measure``
    of the fiducial configuration import no GalSim, astropy or metacal module, and load their
    cached kernels without numba's target refresh."""
    from pathlib import Path

    monkeypatch.setenv("MEGALUT_CACHE", str(tmp_path / "cache"))
    tp = str(Path(__file__).resolve().parent.parent / "examples" / "fiducial" / "tp.toml")
    grid = str(tmp_path / "grid.fits")
    simulate = ["simulate", tp, "--n-cases", "2", "--n-realizations", "4", "--measure", "-q"]
    first = _modules_after([*simulate, "-o", str(tmp_path / "a.fits"), "--stamps", grid], True)
    assert "galsim" in first  # the cold cache: GalSim builds the tables and the PSF
    _modules_after(["measure", grid, "-o", str(tmp_path / "w.fits"), "-q"])  # its kernels cached
    for args in (
        [*simulate, "-o", str(tmp_path / "b.fits")],
        ["measure", grid, "-o", str(tmp_path / "m.fits"), "-q"],
    ):
        loaded = _modules_after(args, True)
        assert "megalut_cli.sim.draw" in loaded or "megalut_cli.measure.measure" in loaded
        assert not loaded & set(NOT_ON_THE_PLAIN_PATH), (args, loaded & set(NOT_ON_THE_PLAIN_PATH))
    assert (tmp_path / "b.fits").is_file() and (tmp_path / "m.fits").is_file()


def test_registry_names_each_module_command(cli):
    from megalut_cli.cli.commands import COMMANDS as REGISTRY

    assert list(REGISTRY) == cli.list_commands(None) and set(COMMANDS) < set(REGISTRY)
    for name, (_, short) in REGISTRY.items():
        command = cli.get_command(None, name)
        assert command.name == name and command.short_help == short
        assert [p.name for p in command.params][-2:] == ["verbose", "quiet"]  # added once
        assert cli.get_command(None, name) is command


_EXIT_SCRIPT = """
import atexit, sys
from megalut_cli import cli

invoke = cli.MegalutGroup.invoke
marker = sys.argv[1]


class Teardown:  # Python's teardown would call this; the shell command skips it
    def __del__(self):
        open(marker + ".teardown", "w").write("torn down")


kept = Teardown()


def invoke_registering(self, ctx):  # as a library imported by the command would
    atexit.register(lambda: open(marker, "w").write("ran"))
    return invoke(self, ctx)


cli.MegalutGroup.invoke = invoke_registering
sys.argv = ["megalut", *sys.argv[2:]]
cli.main()
"""


@pytest.mark.parametrize(
    ("args", "status"),
    [
        (["info", "models/fiducial.h5"], 0),
        (["simulate", "/nonexistent.toml"], 2),
        (["train-point", "/dev/null", "-o", "/sys/megalut-test.h5"], 1),
    ],
)
def test_the_shell_command_exits_without_teardown_keeping_status_and_exit_handlers(
    tmp_path, args, status
):
    """`megalut` as the shell runs it leaves through os._exit once the exit handlers have run
    (Python's teardown of GalSim, numba and astropy took 0.3-0.8 s); its status and the
    handlers of the libraries it imported are kept."""
    import subprocess
    import sys
    from pathlib import Path

    marker = tmp_path / "marker"
    root = Path(__file__).resolve().parent.parent
    out = subprocess.run(
        [sys.executable, "-c", _EXIT_SCRIPT, str(marker), *args],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == status, out.stderr
    assert marker.read_text() == "ran"
    assert not (tmp_path / "marker.teardown").exists()
    if status == 0:
        assert out.stdout.startswith("models/fiducial.h5: megalut.model")
