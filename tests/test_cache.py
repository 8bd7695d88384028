"""The disk cache of arrays (megalut_cli.cache) and the Sersic tables kept in it."""

from __future__ import annotations

import multiprocessing

import galsim
import numpy as np
import pytest

from megalut_cli import cache
from megalut_cli.sim import render


@pytest.fixture
def folder(tmp_path, monkeypatch):
    monkeypatch.setenv(cache.CACHE_ENV, str(tmp_path / "cache"))
    return tmp_path / "cache"


def test_round_trip_is_exact_and_keyed(folder):
    arrays = {
        "a": np.array([0.1, np.nan, -np.inf]),
        "b": np.arange(6, dtype=np.int64).reshape(2, 3),
    }
    assert cache.load_arrays("t", "key 1") is None
    cache.store_arrays("t", "key 1", arrays)
    back = cache.load_arrays("t", "key 1")
    assert back.keys() == arrays.keys()
    for name in arrays:
        assert back[name].dtype == arrays[name].dtype
        np.testing.assert_array_equal(back[name], arrays[name])
    assert cache.load_arrays("t", "key 2") is None
    assert [p.suffix for p in folder.iterdir()] == [".npz"]  # no temporary file left


def test_damaged_or_foreign_entries_are_recomputed(folder):
    cache.store_arrays("t", "k", {"a": np.ones(3)})
    path = cache.entry_path("t", "k", folder)
    path.write_bytes(path.read_bytes()[:40])  # truncated
    assert cache.load_arrays("t", "k") is None
    cache.store_arrays("t", "other", {"a": np.ones(3)})
    cache.entry_path("t", "other", folder).replace(path)  # another key under this name
    assert cache.load_arrays("t", "k") is None


def test_off_and_unwritable(tmp_path, monkeypatch):
    for off in ("none", ""):
        monkeypatch.setenv(cache.CACHE_ENV, off)
        assert cache.cache_dir() is None
        cache.store_arrays("t", "k", {"a": np.ones(2)})
        assert cache.load_arrays("t", "k") is None
    blocker = tmp_path / "file"
    blocker.write_text("x")
    monkeypatch.setenv(cache.CACHE_ENV, str(blocker / "sub"))  # cannot be created
    cache.store_arrays("t", "k", {"a": np.ones(2)})  # no error: only the recomputation is lost
    assert cache.load_arrays("t", "k") is None


def test_default_folder_follows_xdg(tmp_path, monkeypatch):
    monkeypatch.delenv(cache.CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert cache.cache_dir() == tmp_path / "megalut"


def test_size_bound_drops_least_recently_used(folder):
    big = {"a": np.zeros(10_000)}  # 80 kB each
    for k in range(4):
        cache.store_arrays("t", f"k{k}", big)
    cache.load_arrays("t", "k0")  # used again: now the most recent
    cache.store_arrays("t", "k4", big, max_bytes=3 * 81_000)
    kept = {k for k in range(5) if cache.load_arrays("t", f"k{k}") is not None}
    assert kept == {0, 3, 4}


def _writer(args: tuple[str, int]) -> bool:
    folder, k = args
    import os

    os.environ[cache.CACHE_ENV] = folder
    value = {"a": np.full(50_000, 7.0)}
    for _ in range(20):
        cache.store_arrays("t", "shared", value)
        got = cache.load_arrays("t", "shared")
        if got is not None and not np.array_equal(got["a"], value["a"]):
            return False
    return True


def test_concurrent_writers_and_readers_see_whole_entries(folder):
    with multiprocessing.get_context("spawn").Pool(4) as pool:
        assert all(pool.map(_writer, [(str(folder), k) for k in range(8)]))
    assert sorted(p.name for p in folder.iterdir()) == [
        cache.entry_path("t", "shared", folder).name
    ]


def test_sersic_table_from_disk_equals_the_built_one(folder, monkeypatch):
    gsp = galsim.GSParams()
    render._SERSIC_TABLES.clear()
    built = render.sersic_table(2.7, gsp)
    assert cache.load_arrays("sersic", render.sersic_table_key(2.7, gsp)) is not None
    render._SERSIC_TABLES.clear()

    def no_build(*args):
        raise AssertionError("rebuilt although cached")

    monkeypatch.setattr(render, "_build_sersic_table", no_build)
    loaded = render.sersic_table(2.7, gsp)
    for name in ("params", "coef", "fast"):
        a, b = getattr(built, name), getattr(loaded, name)
        assert a.dtype == b.dtype and a.flags.c_contiguous and b.flags.c_contiguous
        np.testing.assert_array_equal(a, b)  # NaN where the fast form falls back, in both
    assert (built.kind, built.octaves, built.stepk, built.maxk, built.hlr_factor) == (
        loaded.kind,
        loaded.octaves,
        loaded.stepk,
        loaded.maxk,
        loaded.hlr_factor,
    )
    render._SERSIC_TABLES.clear()


def test_continuous_sersic_indices_stay_in_memory(folder):
    render._SERSIC_TABLES.clear()
    render.sersic_table(2.7182818, galsim.GSParams())  # a fitted or continuous n
    assert not folder.exists() or not any(folder.iterdir())
    key = render.sersic_table_key(1.5, galsim.GSParams(folding_threshold=1e-2))
    assert key != render.sersic_table_key(1.5, galsim.GSParams()) and galsim.__version__ in key
    render._SERSIC_TABLES.clear()
