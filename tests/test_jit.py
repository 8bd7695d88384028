"""megalut_cli/jit.py: cached kernels load without numba's target refresh, and compile as
before on a cache miss."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

#: A kernel module of the test's own, cached in the test's folder.
KERNEL = """
import numpy as np
from megalut_cli.jit import njit


@njit(cache=True)
def weighted_sum(values, weights):
    total = 0.0
    for i in range(values.shape[0]):
        total += values[i] * weights[i]
    return total


@njit(cache=True)
def cumulative(values):
    out = np.empty_like(values)
    total = 0.0
    for i in range(values.shape[0]):
        total += values[i]
        out[i] = total
    return out
"""

#: Calls the cached kernels, then compiles new code (numba's own njit with numpy.linalg,
#: and a cached kernel for a new argument type), and prints what it found.
SCRIPT = """
import json, sys
import numpy as np
import kernels

x = np.linspace(0.1, 1.0, 101)
result = {"sum": kernels.weighted_sum(x, x[::-1].copy()), "cum": kernels.cumulative(x).tolist()}
if len(sys.argv) > 1:
    from numba import njit

    @njit
    def determinant(a):
        return np.linalg.det(a)

    result["det"] = determinant(np.array([[2.0, 1.0], [1.0, 3.0]]))
    result["sum32"] = float(kernels.weighted_sum(x.astype(np.float32), x.astype(np.float32)))
result["refreshed"] = "numba.np.arraymath" in sys.modules
print(json.dumps(result))
"""


def _run(folder: Path, *args: str, full: bool = False) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "MEGALUT_NUMBA_FULL_SETUP"}
    env.update(PYTHONPATH=str(folder), NUMBA_CACHE_DIR=str(folder / "numba"))
    if full:
        env["MEGALUT_NUMBA_FULL_SETUP"] = "1"
    done = subprocess.run(
        [sys.executable, str(folder / "script.py"), *args],
        env=env,
        cwd=folder,
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_cached_kernels_load_without_the_target_refresh_and_compile_after(tmp_path):
    (tmp_path / "kernels.py").write_text(KERNEL)
    (tmp_path / "script.py").write_text(SCRIPT)
    first = _run(tmp_path)
    assert first["refreshed"]  # a cache miss: numba compiles, with its whole target
    light = _run(tmp_path)
    assert not light["refreshed"]  # from the cache: numba's runtime only
    full = _run(tmp_path, full=True)
    assert full["refreshed"]  # MEGALUT_NUMBA_FULL_SETUP=1: numba's own loading
    x = np.linspace(0.1, 1.0, 101)
    for found in (first, light, full):  # the same kernels: the same bits
        assert found["sum"] == first["sum"] and found["cum"] == first["cum"]
    assert abs(first["sum"] - float(np.dot(x, x[::-1]))) < 1e-12
    assert np.array_equal(first["cum"], np.cumsum(x))
    # after a light load, numba still compiles: new code using numpy.linalg (its target is
    # refreshed then) and a cached kernel for a new argument type
    compiled = _run(tmp_path, "compile")
    assert compiled["refreshed"]
    assert abs(compiled["det"] - 5.0) < 1e-12
    assert abs(compiled["sum32"] - float(np.dot(x, x))) < 1e-4


def test_a_failed_light_load_falls_back_on_numbas_loading(monkeypatch):
    """Should a cached kernel need what only numba's target refresh sets up, its light load
    fails and the loader refreshes the target and loads again (numba's own loading)."""
    import contextlib

    from megalut_cli import jit

    events = []

    class Context:
        def refresh(self):
            events.append("refresh")

    class Cache:
        @contextlib.contextmanager
        def _guard_against_spurious_io_errors(self):
            yield

        def _load_overload(self, sig, target_context):
            events.append("load")
            if "refresh" not in events:
                raise RuntimeError("symbol not found")
            return "compile result"

    class Runtime:
        def initialize(self, target_context):
            events.append("runtime")

    monkeypatch.setattr(jit, "rtsys", Runtime())
    assert jit.load_cached_overload(Cache(), (), Context()) == "compile result"
    assert events == ["runtime", "load", "refresh", "load"]


def test_prefetch_asks_the_cpu_for_the_line_and_changes_no_value():
    """``prefetch`` compiles to LLVM's prefetch of the element's address, for any 2-d array
    (a read-only memory map's uint32 view included), and leaves every value as it was."""
    import numba

    from megalut_cli.jit import prefetch

    @numba.njit
    def prefetched_sum(rows):
        total = 0.0
        for y in range(rows.shape[0]):
            prefetch(rows, y, rows.shape[1] - 1)
            for x in range(rows.shape[1]):
                total += rows[y, x]
        return total

    for rows in (
        np.arange(12.0).reshape(3, 4),
        np.arange(12, dtype=np.float32).reshape(4, 3),
        np.arange(12, dtype=np.uint32).reshape(2, 6)[:, ::2],
    ):
        rows.flags.writeable = False
        assert prefetched_sum(rows) == rows.sum()
        assert rows.tolist() == np.asarray(rows).tolist()
    ir = "".join(prefetched_sum.inspect_llvm().values())
    assert "@llvm.prefetch" in ir
