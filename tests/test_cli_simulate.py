"""`megalut simulate`: help, outputs, overrides, exit codes, determinism across engines."""

from __future__ import annotations

from pathlib import Path

import fitsio
import numpy as np
import pytest
from sim_configs import write

from megalut_cli.catalog import read_catalog

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _err(result) -> str:
    return (getattr(result, "stderr", "") or "") + (result.output or "")


def test_help(runner, cli):
    result = runner.invoke(cli, ["simulate", "--help"])
    assert result.exit_code == 0
    for opt in (
        "--stamps",
        "--measure",
        "--n-cases",
        "--n-realizations",
        "--seed",
        "--nproc",
        "--scheduler",
        "--overwrite",
        "KEY=VALUE",
    ):
        assert opt in result.output
    assert "megalut simulate examples/fiducial/tp.toml" in result.output


def test_simulate_measure(runner, cli, tmp_path):
    out = tmp_path / "cat.fits"
    result = runner.invoke(
        cli,
        [
            "simulate",
            str(write(tmp_path)),
            "-o",
            str(out),
            "--measure",
            "--n-cases",
            "2",
            "--n-realizations",
            "6",
            "--seed",
            "4",
        ],
    )
    assert result.exit_code == 0, _err(result)
    t = read_catalog(out)
    assert len(t) == 12 and t.meta["SEED"] == 4 and t.meta["NCASES"] == 2
    assert {"adamom_g1", "adamom_sigma", "skymad", "snr", "flags"} <= set(t.colnames)
    assert t.meta["HISTORY"]  # the command line is recorded


def test_key_value_overrides(runner, cli, tmp_path):
    out = tmp_path / "cat.fits"
    result = runner.invoke(
        cli,
        [
            "simulate",
            str(write(tmp_path)),
            "-o",
            str(out),
            "noise.sigma=0.5",
            "galaxy.rad=2.0",
            "--n-cases",
            "1",
        ],
    )
    assert result.exit_code == 0, _err(result)
    t = read_catalog(out)
    assert np.all(t["tru_sky_sigma"] == 0.5) and np.all(t["tru_rad"] == 2.0)
    assert "noise.sigma=0.5" in t.meta["CFGOVR"]


@pytest.mark.parametrize(
    "replace, args, message",
    [
        ({"n_cases = 3\n": ""}, [], "[structure] n_cases: missing"),
        ({"sigma = 1.5": "sigma = nan"}, [], "[psf] sigma"),
        ({'rad = {type = "uniform", min = 1.5, max = 3.0}': "rad = -1.0"}, [], "[galaxy] rad"),
        (
            {
                'rad = {type = "uniform", min = 1.5, max = 3.0}': (
                    'rad = {type = "lognormal", mean = 1}'
                )
            },
            [],
            "[galaxy] rad.type: unknown distribution",
        ),
        (
            {'type = "gaussian"\nsigma = 1.5': 'type = "airy"'},
            [],
            "[psf] type: unknown PSF type 'airy'",
        ),
        ({"[structure]": "[structure"}, [], "invalid TOML"),
        ({}, ["noise.sigma"], "expected KEY=VALUE"),
        ({}, ["noise.sigma=-1"], "noise.sigma"),
    ],
)
def test_config_errors_exit_2(runner, cli, tmp_path, replace, args, message):
    out = tmp_path / "cat.fits"
    cfg = write(tmp_path, replace=replace)
    result = runner.invoke(cli, ["simulate", str(cfg), "-o", str(out), "--measure", *args])
    assert result.exit_code == 2, _err(result)
    assert message in _err(result)
    assert "Traceback" not in _err(result)
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sim.toml"]


def test_usage_errors(runner, cli, tmp_path):
    cfg = str(write(tmp_path))
    out = str(tmp_path / "c.fits")
    assert runner.invoke(cli, ["simulate", str(tmp_path / "nope.toml"), "-o", out]).exit_code == 2
    assert runner.invoke(cli, ["simulate", cfg]).exit_code == 2  # -o missing
    assert runner.invoke(cli, ["simulate", cfg, "-o", out, "--n-cases", "0"]).exit_code == 2
    r = runner.invoke(cli, ["simulate", cfg, "-o", out, "-j", "2", "--scheduler", "tcp://x:1"])
    assert r.exit_code == 2 and "mutually exclusive" in _err(r)
    assert not Path(out).exists()


def test_refuses_overwrite(runner, cli, tmp_path):
    cfg = str(write(tmp_path))
    out = tmp_path / "c.fits"
    out.write_bytes(b"precious")
    r = runner.invoke(cli, ["simulate", cfg, "-o", str(out), "--measure"])
    assert r.exit_code == 1 and "--overwrite" in _err(r)
    assert out.read_bytes() == b"precious"
    st = tmp_path / "s.fits"
    st.write_bytes(b"precious")
    r = runner.invoke(cli, ["simulate", cfg, "-o", str(tmp_path / "new.fits"), "--stamps", str(st)])
    assert (
        r.exit_code == 1 and st.read_bytes() == b"precious" and not (tmp_path / "new.fits").exists()
    )
    r = runner.invoke(cli, ["simulate", cfg, "-o", str(out), "--measure", "--overwrite"])
    assert r.exit_code == 0, _err(r)
    assert len(read_catalog(out)) == 12


def test_missing_catalog_file_exit_1(runner, cli, tmp_path):
    text = (EXAMPLES / "euclid" / "vo.toml").read_text().replace("../data/cosmos/", "nowhere/")
    cfg = write(tmp_path, text, name="vo.toml")
    r = runner.invoke(cli, ["simulate", str(cfg), "-o", str(tmp_path / "c.fits"), "--n-cases", "1"])
    assert r.exit_code == 1 and "vo.toml: [catalog] path" in _err(r)


def _table_bytes(path: Path) -> tuple[bytes, bytes, dict]:
    with fitsio.FITS(str(path)) as f:
        data = f[1].read().tobytes()
        cfg = f["CONFIG"].read().tobytes()
        hdr = {
            r["name"]: r["value"] for r in f[1].read_header().records() if r["name"] != "HISTORY"
        }
    return data, cfg, hdr


@pytest.mark.parametrize("stamp_engine", ["fast", "galsim"])
def test_identical_for_any_engine(runner, cli, tmp_path, monkeypatch, stamp_engine):
    """Same seed: byte-identical catalogs with -j 1, -j 2 and a Dask LocalCluster, with
    either stamp engine (docs/engines.md)."""
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    cfg = str(
        write(
            tmp_path,
            replace={
                'per_realization = ["angle"]': 'per_realization = ["galaxy"]',
                'snc = "ring"': 'snc = "pairs"',
            },
        )
    )
    common = [
        "--measure",
        "--engine",
        stamp_engine,
        "--n-cases",
        "9",
        "--n-realizations",
        "4",
        "--seed",
        "21",
    ]
    outs = {}
    for name, extra in (("j1", ["-j", "1"]), ("j2", ["-j", "2"])):
        outs[name] = tmp_path / f"{name}.fits"
        r = runner.invoke(cli, ["simulate", cfg, "-o", str(outs[name]), *common, *extra])
        assert r.exit_code == 0, _err(r)
    import distributed

    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        outs["dask"] = tmp_path / "dask.fits"
        r = runner.invoke(
            cli,
            [
                "simulate",
                cfg,
                "-o",
                str(outs["dask"]),
                *common,
                "--scheduler",
                cluster.scheduler_address,
            ],
        )
        assert r.exit_code == 0, _err(r)
    ref = _table_bytes(outs["j1"])
    assert len(read_catalog(outs["j1"])) == 36
    for name in ("j2", "dask"):
        assert _table_bytes(outs[name]) == ref, name
    # a different seed changes the data
    other = tmp_path / "other.fits"
    r = runner.invoke(cli, ["simulate", cfg, "-o", str(other), *common[:-1], "22"])
    assert r.exit_code == 0 and _table_bytes(other)[0] != ref[0]


def test_n_cases_override_keeps_first_cases(runner, cli, tmp_path):
    cfg = str(write(tmp_path))
    a, b = tmp_path / "a.fits", tmp_path / "b.fits"
    assert runner.invoke(cli, ["simulate", cfg, "-o", str(a), "--n-cases", "2"]).exit_code == 0
    assert runner.invoke(cli, ["simulate", cfg, "-o", str(b), "--n-cases", "5"]).exit_code == 0
    ta, tb = read_catalog(a), read_catalog(b)
    assert len(ta) == 8 and len(tb) == 20 and tb.meta["NCASES"] == 5
    for col in ("case", "rea", "tru_g1", "tru_rad", "tru_e1", "tru_dx"):
        assert np.array_equal(np.asarray(ta[col]), np.asarray(tb[col])[:8]), col


SIM_EXAMPLES = sorted(
    p.relative_to(EXAMPLES) for p in EXAMPLES.glob("*/*.toml") if not p.name.startswith("pipeline")
)


@pytest.mark.parametrize("path", SIM_EXAMPLES, ids=str)
def test_examples_are_valid(path, monkeypatch):
    """Every example simulation config (not pipeline files) loads at its paper size
    (realgal/ and metacal/: the real-galaxy experiments, which have no paper size: their
    galaxies are the 100 COSMOS ones; your-data/: the worked example's stand-in survey;
    scenes/: fields of galaxies, no stamps)."""
    from megalut_cli.sim.config import load_config

    monkeypatch.chdir(EXAMPLES.parent)
    if path.parts[0] == "scenes":
        assert load_config(Path("examples") / path, scene=True).scene is not None
        return
    cfg = load_config(Path("examples") / path)
    assert cfg.structure.n_stamps >= {"realgal": 10**2, "metacal": 10**2, "your-data": 10**4}.get(
        path.parts[0], 10**6
    )


def test_varpsf_example_runs(runner, cli, tmp_path, monkeypatch):
    monkeypatch.chdir(EXAMPLES.parent)
    out = tmp_path / "tw.fits"
    r = runner.invoke(
        cli,
        [
            "simulate",
            "examples/varpsf/tw.toml",
            "-o",
            str(out),
            "--measure",
            "--n-cases",
            "2",
            "--n-realizations",
            "4",
        ],
    )
    assert r.exit_code == 0, _err(r)
    t = read_catalog(out)
    assert t.meta["SNC"] == "pairs"
    for col in ("tru_field_x", "tru_field_y", "tru_psf_g1", "tru_psf_g2", "tru_psf_sigma"):
        per_case = [np.unique(np.asarray(t[col])[np.asarray(t["case"]) == c]) for c in (0, 1)]
        assert all(len(u) == 1 for u in per_case) and per_case[0][0] != per_case[1][0], col
    np.testing.assert_allclose(t["tru_psf_g1"], -0.25 + 0.5 * np.asarray(t["tru_field_x"]))
    np.testing.assert_allclose(
        t["tru_psf_sigma"], 2 + 0.25 * (np.asarray(t["tru_field_x"]) + t["tru_field_y"] - 1)
    )


def test_moments_retry_as_measure_has_it(runner, cli, tmp_path):
    """``simulate --measure --moments-retry`` gives measure's columns on the same stamps, with
    fewer HSM failures than without it; it needs --measure."""
    from megalut_cli import flags as fl

    cfg = str(Path(__file__).parent.parent / "examples" / "fiducial" / "vo.toml")
    sim = ["simulate", cfg, "--n-cases", "2", "--n-realizations", "300", "--seed", "3"]
    retry = ["--moments-retry", "0.5"]
    for args in (
        ["-o", str(tmp_path / "m.fits"), "--measure", *retry],
        ["-o", str(tmp_path / "p.fits"), "--measure"],
        ["-o", str(tmp_path / "c.fits"), "--stamps", str(tmp_path / "s.fits")],
        [
            "measure",
            str(tmp_path / "s.fits"),
            str(tmp_path / "c.fits"),
            "-o",
            str(tmp_path / "f.fits"),
            *retry,
        ],
    ):
        result = runner.invoke(cli, args if args[0] == "measure" else [*sim, *args])
        assert result.exit_code == 0, _err(result)
    m, p, f = (read_catalog(tmp_path / f"{k}.fits") for k in "mpf")
    np.testing.assert_array_equal(m["flags"], f["flags"])
    np.testing.assert_array_equal(m["adamom_g1"], f["adamom_g1"])
    assert m.meta["HSMRETRY"] == 0.5 and "HSMRETRY" not in p.meta
    n_p, n_m = (int(((t["flags"] & fl.HSM_FAILED) != 0).sum()) for t in (p, m))
    assert n_m < n_p, (n_m, n_p)
    r = runner.invoke(cli, [*sim, "-o", str(tmp_path / "x.fits"), *retry])
    assert r.exit_code == 2 and "--moments-retry needs --measure" in _err(r)
