"""--device without the GPU extra: ``auto`` falls back to the CPU silently, ``gpu`` is one line."""

from __future__ import annotations

import sys

import pytest

from megalut_cli import gpu
from megalut_cli.engine import resolve_device
from megalut_cli.errors import ConfigError, MegalutError


@pytest.fixture
def no_jax(monkeypatch):
    """As if the 'gpu' extra were not installed (import jax fails)."""
    monkeypatch.setitem(sys.modules, "jax", None)
    gpu._problem.cache_clear()
    yield
    gpu._problem.cache_clear()


def test_resolution_without_the_extra(no_jax) -> None:
    assert resolve_device("cpu") == "cpu"
    assert resolve_device("auto") == "cpu"
    with pytest.raises(
        MegalutError, match=r"^device gpu: the GPU backend is not installed \(pip install"
    ):
        resolve_device("gpu")
    with pytest.raises(ConfigError, match="device: unknown value 'tpu'"):
        resolve_device("tpu")


def test_cli_without_the_extra(no_jax, tmp_path, runner, cli) -> None:
    from sim_configs import write

    cfg = str(write(tmp_path))
    res = runner.invoke(
        cli, ["simulate", cfg, "-o", str(tmp_path / "a.fits"), "--measure", "--device", "gpu"]
    )
    assert res.exit_code == 1
    assert res.stderr.strip().splitlines()[-1].endswith("pip install 'megalut-cli[gpu]')")
    assert not (tmp_path / "a.fits").exists()
    res = runner.invoke(
        cli, ["simulate", cfg, "-o", str(tmp_path / "a.fits"), "--measure", "--device", "auto"]
    )
    assert res.exit_code == 0, res.stderr
    res = runner.invoke(cli, ["simulate", cfg, "-o", str(tmp_path / "b.fits"), "--device", "tpu"])
    assert res.exit_code == 2 and "'tpu' is not one of" in res.stderr


def test_pipeline_device_key(tmp_path) -> None:
    from megalut_cli.pipeline.file import load_pipeline

    default = load_pipeline(None)
    assert default.device == "cpu"
    assert load_pipeline(None, ['device="auto"']).device == "auto"
    with pytest.raises(ConfigError, match="device.*tpu"):
        load_pipeline(None, ['device="tpu"'])
