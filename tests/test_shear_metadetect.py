"""m and c of metadetection catalogs of simulated scenes (``shear/metadetect.py``,
``megalut evaluate`` on them): an injected bias is recovered, the ±g pairs cancel the
shape noise, the bootstrap errors match the spread of independent sets, and bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import invoke_fails

from megalut_cli.catalog import write_catalog
from megalut_cli.measure.metacal_defaults import TYPES
from megalut_cli.shear.metadetect import evaluate_metadetect

STEP = 0.01
SHEARS = {"noshear": (0, 0), "1p": (1, 0), "1m": (-1, 0), "2p": (0, 1), "2m": (0, -1)}


def scenes(seed: int, m: float = 0.0, c: float = 0.0, n_fields: int = 100, per: int = 60):
    """A synthetic metadetection catalog of paired fields (g1 = ±0.02): each object's
    estimate in a version is ``e + R (s + (1 + m) g) + c`` (the metacal versions' shears
    ``s`` answered with R, the true shear with (1 + m) R: a bias metacal cannot see), and a
    version keeps the objects it detects, ``u + |estimate|^2 > 0.4``."""
    rng = np.random.default_rng(seed)
    n = n_fields * per
    e = rng.normal(0.0, 0.25, (2, n))
    r = rng.uniform(0.5, 0.9, n)
    u = rng.uniform(0.0, 1.0, n)
    field = np.repeat(np.arange(n_fields), per)
    parts: dict[str, list] = {
        k: []
        for k in (
            "mdet_step",
            "field",
            "pair_sign",
            "tru_g1",
            "tru_g2",
            "adamom_g1",
            "adamom_g2",
            "flags",
            "inner",
        )
    }
    for sign in (1, -1):
        g = np.array([0.02 * sign, 0.0])
        for kind, s in SHEARS.items():
            est = e + r * (np.asarray(s)[:, None] * STEP + (1 + m) * g[:, None]) + c
            det = u + (est**2).sum(axis=0) > 0.4
            k = int(det.sum())
            parts["mdet_step"].append(np.full(k, kind))
            parts["field"].append(field[det])
            parts["pair_sign"].append(np.full(k, sign))
            parts["tru_g1"].append(np.full(k, g[0]))
            parts["tru_g2"].append(np.full(k, g[1]))
            parts["adamom_g1"].append(est[0][det])
            parts["adamom_g2"].append(est[1][det])
            parts["flags"].append(np.zeros(k, np.int32))
            parts["inner"].append(np.ones(k, np.int16))
    return {k: np.concatenate(v) for k, v in parts.items()}


def test_an_injected_bias_is_recovered_and_pairs_cancel_shape_noise():
    base = evaluate_metadetect(scenes(1, per=200), STEP, n_bootstrap=50)["unweighted"]
    biased = evaluate_metadetect(scenes(1, m=0.03, per=200), STEP, n_bootstrap=50)["unweighted"]
    added = evaluate_metadetect(scenes(1, c=0.002, per=200), STEP, n_bootstrap=50)["unweighted"]
    g1 = base["g1"]
    assert abs(g1["m"]) < 3 * g1["m_err"] and g1["m_err"] < 0.02  # 20 000 objects, paired
    assert biased["g1"]["m"] - g1["m"] == pytest.approx(0.03, abs=4e-3)  # on the same noise
    assert added["g1"]["c"] - g1["c"] == pytest.approx(0.002 / g1["R"], rel=0.2)
    assert base["g2"]["m"] is None  # no lever arm in g2 (tru_g2 = 0 everywhere)
    assert base["g1"]["R"] > 0.7 + 0.05  # <r> = 0.7, plus the detection's response


def test_the_bootstrap_errors_match_the_spread_of_independent_sets():
    results = [
        evaluate_metadetect(scenes(s), STEP, n_bootstrap=100)["unweighted"] for s in range(12)
    ]
    m = np.array([r["g1"]["m"] for r in results])
    quoted = np.median([r["g1"]["m_err"] for r in results])
    assert 0.6 < m.std(ddof=1) / quoted < 1.6


def test_evaluate_command_and_bad_input(runner, cli, tmp_path):
    cols = scenes(3)
    path = tmp_path / "det.fits"
    write_catalog(path, cols, fmt="megalut.metadetect", cards={"MDETSTEP": STEP})
    result = runner.invoke(cli, ["evaluate", str(path), "--json", str(tmp_path / "e.json")])
    assert result.exit_code == 0, result.output
    assert "metadetection" in result.output and "unweighted" in result.output
    invoke_fails(runner, cli, ["evaluate", str(path), "--by", "tru_g1"], 2, "--by")
    nocard = tmp_path / "nocard.fits"
    write_catalog(nocard, cols, fmt="megalut.metadetect")
    invoke_fails(runner, cli, ["evaluate", str(nocard)], 1, "MDETSTEP")
    notruth = tmp_path / "notruth.fits"
    write_catalog(
        notruth,
        {k: v for k, v in cols.items() if not k.startswith("tru_")},
        fmt="megalut.metadetect",
        cards={"MDETSTEP": STEP},
    )
    invoke_fails(runner, cli, ["evaluate", str(notruth)], 1, "tru_g1")
    assert set(TYPES) == set(SHEARS)


def test_runs_concatenated_count_their_fields_apart(runner, cli, tmp_path):
    """``megalut concat`` joins the metadetection catalogs of several runs (whose fields are
    numbered from 0 in each); ``evaluate`` then takes (tile, field) as the field: the same m,
    c and errors as one catalog whose second run's fields are renumbered. A run measured at
    another metacal step is refused."""
    a, b = scenes(5, n_fields=40), scenes(6, n_fields=40)
    paths = [tmp_path / "a.fits", tmp_path / "b.fits"]
    for path, cols in zip(paths, (a, b)):
        write_catalog(path, cols, fmt="megalut.metadetect", cards={"MDETSTEP": STEP})
    joined = tmp_path / "ab.fits"
    result = runner.invoke(cli, ["concat", *map(str, paths), "-o", str(joined)])
    assert result.exit_code == 0, result.output
    renumbered = {k: np.concatenate([a[k], b[k]]) for k in a}
    renumbered["field"][len(a["field"]) :] += 40
    ref = evaluate_metadetect(renumbered, STEP, n_bootstrap=50)["unweighted"]["g1"]
    result = runner.invoke(cli, ["evaluate", str(joined), "--json", str(tmp_path / "e.json")])
    assert result.exit_code == 0, result.output
    got = json.loads((tmp_path / "e.json").read_text())
    g1 = got["unweighted"]["g1"]
    assert got["n_fields"] == 80
    assert g1["m"] == pytest.approx(ref["m"], rel=1e-9) and g1["R"] == pytest.approx(ref["R"])
    assert g1["m_err"] == pytest.approx(ref["m_err"], rel=0.5)  # bootstrap draws differ
    other = tmp_path / "c.fits"
    write_catalog(other, a, fmt="megalut.metadetect", cards={"MDETSTEP": 2 * STEP})
    invoke_fails(
        runner,
        cli,
        ["concat", str(paths[0]), str(other), "-o", str(tmp_path / "x.fits")],
        1,
        "MDETSTEP",
    )
