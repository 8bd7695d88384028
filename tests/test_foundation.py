"""Foundation: catalogs, safe writes, provenance, seeds, executors, expressions."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from astropy.table import Table

from megalut_cli import catalog, expr, flags, parallel, seeding
from megalut_cli.atomic import atomic_output
from megalut_cli.errors import ConfigError, InputError, MegalutError


def _table(n: int = 7) -> Table:
    rng = np.random.default_rng(0)
    return Table({"case": np.arange(n) // 2, "x": rng.normal(size=n), "v": rng.normal(size=(n, 3))})


def test_catalog_round_trip_with_provenance(tmp_path):
    path = tmp_path / "c.fits"
    catalog.write_catalog(
        path, _table(), fmt="megalut.test", cards={"SEED": (42, "seed")}, history=["step one"]
    )
    back = catalog.read_catalog(path)
    np.testing.assert_array_equal(back["x"], _table()["x"])
    np.testing.assert_array_equal(back["v"], _table()["v"])
    assert back.meta["MLFORMAT"] == "megalut.test"
    assert back.meta["SEED"] == 42
    assert back.meta["CREATOR"].startswith("megalut ")
    assert back.meta["HISTORY"][0] == "step one" and len(back.meta["HISTORY"]) >= 2
    assert "TTYPE1" not in back.meta


def test_catalog_chunks_and_columns(tmp_path):
    path = tmp_path / "c.fits"
    catalog.write_catalog(path, _table(7), fmt="megalut.test")
    chunks = list(catalog.iter_catalog(path, 3, columns=["x"]))
    assert [len(c) for c in chunks] == [3, 3, 1]
    np.testing.assert_array_equal(np.concatenate([c["x"] for c in chunks]), _table(7)["x"])
    with pytest.raises(InputError, match="missing column.*zz, yy"):
        catalog.read_catalog(path, columns=["x", "zz", "yy"])


def test_columns_read_by_rows_are_those_read_one_by_one(tmp_path, monkeypatch):
    """read_columns_by_rows (CatalogColumns.load) gives the arrays of the one-column reads:
    every column type, several blocks of rows, a metacal catalog's version names."""
    import fitsio

    n = 23
    rng = np.random.default_rng(5)
    data = np.zeros(
        n,
        dtype=[
            ("case", "i8"),
            ("flags", "i4"),
            ("small", "i2"),
            ("byte", "u1"),
            ("big", "u4"),
            ("ok", "?"),
            ("f32", "f4"),
            ("x", "f8"),
            ("x_noshear", "f8"),
            ("v", "f8", (3,)),
            ("name", "S5"),
        ],
    )
    for name in data.dtype.names:
        data[name] = rng.integers(0, 200, size=data[name].shape).astype(data.dtype[name].base)
    data["big"][0] = 4_000_000_000
    data["x"] = rng.normal(size=n)
    path = tmp_path / "c.fits"
    fitsio.write(str(path), data)
    monkeypatch.setattr(catalog, "ROW_BLOCK_BYTES", 5 * data.dtype.itemsize)  # 5 blocks
    names = list(data.dtype.names)
    by_rows = catalog.read_columns_by_rows(path, names)
    for name in names:
        one = catalog.read_catalog_columns(path, [name])[0][name]
        assert by_rows[name].dtype == one.dtype and by_rows[name].shape == one.shape
        assert by_rows[name].tobytes() == one.tobytes(), name
    columns = catalog.CatalogColumns(path)
    columns.load(["x", "case", "nope"])
    assert set(columns._read) == {"x", "case"}
    with pytest.raises(KeyError):
        columns["nope"]
    version = catalog.VersionColumns(catalog.CatalogColumns(path), "noshear")
    version.load(["x", "flags"])
    assert set(version.columns._read) == {"x_noshear", "flags"}
    np.testing.assert_array_equal(version["x"], data["x_noshear"])
    with pytest.raises(InputError, match="missing column.*zz"):
        catalog.read_columns_by_rows(path, ["x", "zz"])


def test_catalog_refuses_overwrite_and_bad_files(tmp_path):
    path = tmp_path / "c.fits"
    catalog.write_catalog(path, _table(), fmt="megalut.test")
    with pytest.raises(MegalutError, match="exists; pass overwrite=True to replace it"):
        catalog.write_catalog(path, _table(), fmt="megalut.test")
    bad = tmp_path / "bad.fits"
    bad.write_bytes(path.read_bytes()[:4000])
    with pytest.raises(InputError, match="not a readable FITS"):
        catalog.read_catalog(bad)
    with pytest.raises(InputError, match="no such file"):
        catalog.read_catalog(tmp_path / "nope.fits")


def test_write_errors_name_the_users_file_not_the_temporary_one(tmp_path):
    """A failed write (disk full) names the output the user asked for; the temp file is removed."""
    target = tmp_path / "out.fits"
    with pytest.raises(MegalutError) as err:
        with atomic_output(target) as tmp:
            tmp.write_bytes(b"partial")
            raise OSError(28, "No space left on device", str(tmp))
    assert str(err.value) == f"{target}: cannot write (No space left on device)"
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(MegalutError, match=r"out.fits: cannot write \(.*out.fits: write failed\)"):
        with atomic_output(target) as tmp:
            raise OSError(f"{tmp}: write failed")  # as cfitsio says it: no filename attribute
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(MegalutError, match="output folder .* does not exist"):
        with atomic_output(tmp_path / "missing" / "out.fits"):
            pass


def test_atomic_output_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.fits"
    with pytest.raises(RuntimeError):
        with atomic_output(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []


def test_seeds_depend_on_keys_only():
    a = seeding.rng_for(3, 1, 5).normal(size=4)
    b = seeding.rng_for(3, 1, 5).normal(size=4)
    c = seeding.rng_for(3, 1, 6).normal(size=4)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    assert 0 < seeding.int_seed_for(3, 1, 5) < 2**31


def _square(x: int) -> int:
    return x * x


def test_process_pool_gives_ordered_results():
    with parallel.executor(nproc=2) as pool:
        assert pool is not None
        assert parallel.map_units(_square, list(range(9)), pool) == [i * i for i in range(9)]
    with parallel.executor(nproc=1) as pool:
        assert pool is None
    with parallel.executor(nproc=2, n_units=1) as pool:  # one unit: no workers to start
        assert pool is None


def _pid_and_blas_threads(_: int) -> tuple[int, str | None]:
    import os
    import time

    time.sleep(0.02)  # long enough for the worker to take some units
    return os.getpid(), os.environ.get("OPENBLAS_NUM_THREADS")


def test_workers_start_with_one_blas_thread(monkeypatch):
    """The pool starts its workers on the first submit: they must still see one BLAS thread
    (they did not: the variables were restored before any worker started)."""
    import os

    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    with parallel.executor(nproc=2) as pool:
        found = parallel.map_units(_pid_and_blas_threads, list(range(8)), pool)
    on_workers = [threads for pid, threads in found if pid != os.getpid()]
    assert on_workers and set(on_workers) == {"1"}
    assert "OPENBLAS_NUM_THREADS" not in os.environ


def _slow_pid(x: int) -> tuple[int, int]:
    import os
    import time

    time.sleep(0.01 * (x % 3))
    if x == 13:
        raise ValueError("unit 13 failed")
    return x * x, os.getpid()


def test_local_pool_shares_the_units_with_this_process():
    """``-j 2`` is this process and one worker: both run units (the worker its first at
    once, this process the next), results in unit order either way; the pool's size."""
    import os

    with parallel.executor(nproc=2) as pool:
        assert isinstance(pool, parallel.LocalPool) and pool.workers == 1
        found = parallel.map_units(_slow_pid, list(range(12)), pool)
        assert [v for v, _ in found] == [i * i for i in range(12)]
        pids = [pid for _, pid in found]
        assert pids[0] != os.getpid() and pids[1] == os.getpid()  # worker first, then here
        streamed = list(parallel.map_ordered(_slow_pid, ((f"k{i}", i) for i in range(12)), pool, 3))
        assert [(k, v) for k, (v, _) in streamed] == [(f"k{i}", i * i) for i in range(12)]
        assert len({pid for _, (_, pid) in streamed}) == 2
    with parallel.executor(nproc=3) as pool:
        assert pool.workers == 2
        assert [v for v, _ in parallel.map_units(_slow_pid, list(range(7)), pool)] == [
            i * i for i in range(7)
        ]


@pytest.mark.parametrize("ordered", [False, True])
def test_a_failed_unit_fails_the_map_here_or_on_a_worker(ordered):
    """Unit 13 fails wherever it runs; the error reaches the caller and the pool ends."""
    with pytest.raises(ValueError, match="unit 13"), parallel.executor(nproc=2) as pool:
        if ordered:
            list(parallel.map_ordered(_slow_pid, ((i, i) for i in range(20)), pool, 4))
        else:
            parallel.map_units(_slow_pid, list(range(20)), pool)


def test_local_pool_takes_at_most_a_window_of_units_ahead():
    """map_ordered on a local pool takes units from its iterator at most ``window`` ahead of
    the first result not yet delivered (a stream of bounded memory)."""
    taken = []

    def units():
        for i in range(30):
            taken.append(i)
            yield i, 100 + i

    with parallel.executor(nproc=2) as pool:
        for n_delivered, (key, (value, _)) in enumerate(
            parallel.map_ordered(_slow_pid, units(), pool, window=4)
        ):
            assert value == (100 + key) ** 2
            assert len(taken) <= n_delivered + 4
    assert len(taken) == 30


_PROBE = """
import os, signal, sys, time


def state(name):
    time.sleep(0.02)  # long enough for the worker to take some units
    return os.getpid(), name in sys.modules, signal.getsignal(signal.SIGINT) is signal.SIG_IGN


def on_workers(states):  # the units run by the workers (this process runs some too)
    return sorted({tuple(s[1:]) for s in states if s[0] != os.getpid()})
"""

_WARM_SCRIPT = """
import sys
sys.path.insert(0, {folder!r})
from megalut_cli import parallel
parallel.start_worker_server(["json.tool"])  # imported by nothing else here
import probe
with parallel.executor(nproc=2) as pool:
    print(probe.on_workers(parallel.map_units(probe.state, ["json.tool"] * 4, pool)))
"""


def test_workers_are_forked_warm_from_one_server(tmp_path):
    """Local workers come from a server that imported the command's modules once (so each
    worker does not import them again) and ignore Ctrl-C; a fresh process, since the server
    is one per process."""
    import subprocess
    import sys

    if parallel.START_METHOD != "forkserver":
        pytest.skip("no fork server on this platform")  # not on Linux, where CI runs
    (tmp_path / "probe.py").write_text(_PROBE)
    out = subprocess.run(
        [sys.executable, "-c", _WARM_SCRIPT.format(folder=str(tmp_path))],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[(True, True)]"


_TEARDOWN_PROBE = """
import os

MARKER = os.environ["TEARDOWN_MARKER"]


class Teardown:  # Python's teardown would call this; the server skips it
    def __del__(self, write=open):
        write(MARKER, "w").write("torn down")


kept = Teardown()
"""

_SERVER_EXIT_SCRIPT = """
from megalut_cli import parallel
parallel.start_worker_server(["teardown_probe"])  # the server only: this process exits as usual
import probe
with parallel.executor(nproc=2) as pool:
    print(probe.on_workers(parallel.map_units(probe.state, ["teardown_probe"] * 4, pool)))
"""


def test_the_worker_server_leaves_without_teardown(tmp_path):
    """Once the command has gone, the server leaves without Python's teardown of what it
    preloaded (0.15-0.25 s during which a reader of the command's output, which the server
    holds open too, waited); ``capture_output`` reads until the server has closed it."""
    import os
    import subprocess
    import sys

    if parallel.START_METHOD != "forkserver":
        pytest.skip("no fork server on this platform")  # not on Linux, where CI runs
    (tmp_path / "teardown_probe.py").write_text(_TEARDOWN_PROBE)
    (tmp_path / "probe.py").write_text(_PROBE)
    marker = tmp_path / "server.teardown"
    out = subprocess.run(
        [sys.executable, "-c", _SERVER_EXIT_SCRIPT],  # the server finds the probes on PYTHONPATH
        env={**os.environ, "TEARDOWN_MARKER": str(marker), "PYTHONPATH": str(tmp_path)},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[(True, True)]"  # the workers came from that server
    assert not marker.exists()


def test_every_command_with_workers_names_their_modules():
    import importlib

    from megalut_cli.cli import main
    from megalut_cli.cli.commands import COMMANDS, WORKER_MODULES

    for name in COMMANDS:
        command = main.get_command(None, name)
        has_workers = any(p.name == "nproc" for p in command.params)
        assert (name in WORKER_MODULES) == has_workers, name
    for modules in WORKER_MODULES.values():
        for module in modules:
            importlib.import_module(module)


def test_bad_scheduler_is_config_error(tmp_path):
    import distributed  # noqa: F401  (the test extra: a missing dask must fail, not skip)

    with pytest.raises(ConfigError, match="neither an address"):
        with parallel.executor(scheduler=str(tmp_path / "missing.json")):
            pass


def test_chunk_ranges_cover_everything():
    assert parallel.chunk_ranges(10, 3) == [(0, 3), (3, 7), (7, 10)]
    assert parallel.chunk_ranges(2, 5) == [(0, 1), (1, 2)]


COLS = {
    "snr": np.array([5.0, 12, 20, np.nan, 30]),
    "s": np.array([1.0, 2, 2, 1, 3]),
    "case": np.array([0, 0, 1, 1, 2]),
    "tru": np.array([1.0, 1, 2, 2, 3]),
}


def test_row_expressions_with_ampersand_precedence():
    np.testing.assert_array_equal(
        expr.evaluate_rows("snr > 10 & s > 1.5", COLS), [False, True, True, False, True]
    )
    np.testing.assert_array_equal(
        expr.evaluate_rows("~(snr > 10) | s >= 3", COLS), [True, False, False, True, True]
    )
    assert expr.columns_used("log10(snr) > 1 & s < 2") == ["snr", "s"]


def test_case_expressions():
    ids, sel = expr.evaluate_cases("mean(snr) > 10 & tru < 3", COLS, COLS["case"])
    np.testing.assert_array_equal(ids, [0, 1, 2])
    np.testing.assert_array_equal(sel, [False, True, False])
    _, sel = expr.evaluate_cases("median(snr) >= 12", COLS, COLS["case"])
    np.testing.assert_array_equal(sel, [False, True, True])
    _, sel = expr.evaluate_cases("count(snr) == 2", COLS, COLS["case"])
    np.testing.assert_array_equal(sel, [True, False, False])


@pytest.mark.parametrize(
    "bad, message",
    [
        ("snr >", "cannot be read"),
        ("__import__('os').system('true')", "not allowed|unknown function"),
        ("snr.real > 1", "attribute access"),
        ("mean(snr) > 1", "only allowed in case"),
        ("foo > 1", "unknown column"),
        ("snr + 1", "not a condition"),
    ],
)
def test_bad_expressions_are_config_errors(bad, message):
    with pytest.raises(ConfigError, match=message):
        expr.evaluate_rows(bad, COLS)


@pytest.mark.parametrize(
    "bad, words",
    [
        ("snr = 10", ["cannot be read", "==", "snr > 10"]),
        ("snr[0] > 1", ["indexing", "is not allowed", "comparisons", "sqrt"]),
        ("snr >> 1", ["'>>' is not allowed"]),
        ("snr in 3", ["'in' is not allowed"]),
        (
            "sn > 1 & tru < 3",
            ["unknown column(s) sn", "did you mean snr?", "the catalog has: case, s, snr, tru"],
        ),
    ],
)
def test_expression_errors_are_plain_words_with_existing_columns(bad, words):
    """Never the parser's tree; the columns that exist, and the closest one, for a typo."""
    for check in (
        lambda: expr.evaluate_rows(bad, COLS),
        lambda: expr.check_expression(bad, list(COLS)),
    ):
        with pytest.raises(ConfigError) as err:
            check()
        text = str(err.value)
        assert "ast." not in text and "Name(" not in text and "ctx=" not in text
        for w in words:
            if w.startswith("the catalog") and "unknown" not in text:
                continue
            assert w in text, text


def test_case_expression_rejects_varying_bare_column():
    with pytest.raises(ConfigError, match="varies within cases"):
        expr.evaluate_cases("s > 1", COLS, COLS["case"])


def test_flags_explain():
    assert flags.explain(flags.HSM_FAILED | flags.BAD_PIXELS) == ["HSM_FAILED", "BAD_PIXELS"]
    assert flags.explain(0) == []


def test_an_existing_output_is_named_by_the_library_argument_and_by_the_cli_flag(
    tmp_path, runner, cli
):
    """The library says ``overwrite=True``; the command line maps it to ``--overwrite``."""
    from megalut_cli.atomic import check_output
    from megalut_cli.errors import OutputExistsError

    out = tmp_path / "x.fits"
    out.write_text("x")
    with pytest.raises(OutputExistsError) as err:
        check_output(out, overwrite=False)
    assert str(err.value) == f"{out} exists; pass overwrite=True to replace it"
    result = runner.invoke(cli, ["evaluate", str(out), "--json", str(out)])
    assert result.exit_code == 1 and f"{out} exists; use --overwrite to replace it" in result.stderr


def test_argument_errors_name_the_argument_and_the_cli_names_the_flag(tmp_path, runner, cli):
    """Library messages about --workdir, --scheduler, --device name the argument; the command
    line maps it to the running command's flag, exit codes unchanged."""
    from pipeline_configs import write_pipeline

    from megalut_cli.errors import ArgumentError, ConfigError
    from megalut_cli.parallel import executor
    from megalut_cli.pipeline.steps import check_workdir

    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(ArgumentError) as err:
        check_workdir(blocker, [], False, False)
    assert str(err.value) == f"workdir {blocker}: exists and is not a folder"
    with pytest.raises(ConfigError, match=r"^scheduler 'nowhere' is neither an address"):
        with executor(1, "nowhere"):
            pass
    result = runner.invoke(
        cli,
        [
            "run",
            str(write_pipeline(tmp_path)),
            "--workdir",
            str(tmp_path / "wd"),
            "--scheduler",
            "nowhere",
            "-q",
        ],
    )
    assert result.exit_code == 2, result.stderr
    assert "--scheduler 'nowhere' is neither an address" in result.stderr


def test_ordered_window_bounds_work_in_flight():
    active, peak, lock = 0, 0, threading.Lock()

    def work(x: int) -> int:
        nonlocal active, peak
        with lock:
            active += 1
            peak = max(peak, active)
        time.sleep(0.002)
        with lock:
            active -= 1
        return x * x

    consumed = []
    with ThreadPoolExecutor(8) as pool:
        for key, res in parallel.map_ordered(work, ((i, i) for i in range(60)), pool, window=3):
            consumed.append((key, res))
    assert consumed == [(i, i * i) for i in range(60)]
    assert peak <= 3


@pytest.mark.parametrize("block_bytes", [catalog.CatalogWriter.BLOCK_BYTES, 3000])
def test_catalog_written_in_chunks_equals_one_write(tmp_path, monkeypatch, block_bytes):
    """Chunks held and appended in blocks (one block, or one per ~3000 bytes) give the file
    one write gives."""
    monkeypatch.setattr(catalog.CatalogWriter, "BLOCK_BYTES", block_bytes)
    rng = np.random.default_rng(2)
    cols = {
        "a": rng.normal(size=1000),
        "b": np.arange(1000, dtype=np.int32),
        "flags": np.zeros(1000, np.int32),
    }
    extra = {"CONFIG": np.array([(b"{}",)], dtype=[("json", "S2")])}
    catalog.write_catalog(
        tmp_path / "one.fits", cols, fmt="megalut.features", cards={"SEED": 3}, extra_hdus=extra
    )
    with catalog.catalog_writer(
        tmp_path / "chunks.fits", fmt="megalut.features", cards={"SEED": 3}, extra_hdus=extra
    ) as writer:
        for start in range(0, 1000, 300):
            writer.append(
                {
                    k: v[start : start + 300].astype(np.int64)
                    if k == "b" and start
                    else v[start : start + 300]
                    for k, v in cols.items()
                }
            )  # a later chunk in another dtype is cast
        assert writer.n_rows == 1000
    import fitsio

    with (
        fitsio.FITS(str(tmp_path / "one.fits")) as a,
        fitsio.FITS(str(tmp_path / "chunks.fits")) as b,
    ):
        assert len(a) == len(b) == 3
        for ha, hb in zip(a, b):
            assert np.array_equal(ha.read(), hb.read()) if ha.has_data() else not hb.has_data()
            cards = [
                (r["name"], r.get("value"))
                for r in ha.read_header().records()
                if r["name"] != "DATE"
            ]
            assert cards == [
                (r["name"], r.get("value"))
                for r in hb.read_header().records()
                if r["name"] != "DATE"
            ]


def test_catalog_writer_leaves_nothing_on_failure(tmp_path):
    with (
        pytest.raises(RuntimeError),
        catalog.catalog_writer(tmp_path / "c.fits", fmt="megalut.features") as writer,
    ):
        writer.append({"a": np.arange(3.0)})
        raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []


_VERSIONS_SCRIPT = """
import sys
from megalut_cli.provenance import software_versions
versions = software_versions()
loaded = [name for name in ("galsim", "astropy", "scipy") if name in sys.modules]
import astropy, fitsio, galsim, h5py, numpy, scipy
modules = {"astropy": astropy, "fitsio": fitsio, "galsim": galsim, \
"h5py": h5py, "numpy": numpy, "scipy": scipy}
print(loaded, all(versions[name] == m.__version__ for name, m in modules.items()))
"""


def test_software_versions_are_the_modules_without_importing_them():
    """Provenance records the libraries' versions without importing them (GalSim and its
    astropy cost 0.5 s of every training command), and they are the modules' own."""
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-c", _VERSIONS_SCRIPT], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[] True"


def test_a_record_is_the_models_own_else_its_parents():
    """own_or_parent: the record a model's own training made, else its parent's (a weight
    training's point training); an empty or non-mapping record is none."""
    from megalut_cli.provenance import own_or_parent

    parent = {"setup": {"stamp_size": 48}, "domain": {"columns": {}}, "population": {"a": 1}}
    prov = {"setup": {}, "domain": {"source": "own"}, "population": "?", "parent": parent}
    assert own_or_parent(prov, "domain") == {"source": "own"}
    assert own_or_parent(prov, "setup") == {"stamp_size": 48}
    assert own_or_parent(prov, "population") == {"a": 1}
    assert own_or_parent(prov, "nothing") is None
    assert own_or_parent({"setup": {"gain": 2}, "parent": "not a record"}, "setup") == {"gain": 2}
    assert own_or_parent({"parent": {"setup": {}}}, "setup") is None
