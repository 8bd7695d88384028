"""m, c (pixel and PSF frames) and Q_c of GREAT3 constant-shear submissions against truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from megalut_cli.catalog import write_catalog
from megalut_cli.errors import InputError
from megalut_cli.great3 import layout as L
from megalut_cli.great3.evaluate import evaluate_branch
from megalut_cli.shear.bias import q_c

N = 60


@pytest.fixture
def truth(tmp_path):
    rng = np.random.default_rng(42)
    g1, g2 = rng.uniform(-0.05, 0.05, (2, N))
    ang = rng.uniform(0, np.pi, N)
    psf = 0.05 * np.exp(2j * ang)
    d = tmp_path / "truth"
    L.write_truth(d, np.arange(N), g1, g2, psf.real, psf.imag)
    return d, g1, g2, psf


def test_m_c_and_psf_leakage_recovered(truth, tmp_path):
    d, g1, g2, psf = truth
    rng = np.random.default_rng(7)
    m, c1, alpha, sig = 0.02, 3e-4, 0.01, 2e-4
    e1 = (1 + m) * g1 + c1 + alpha * psf.real + rng.normal(0, sig, N)
    e2 = (1 + m) * g2 + alpha * psf.imag + rng.normal(0, sig, N)
    sub = tmp_path / "sub.txt"
    L.write_submission(sub, np.arange(N), e1, e2)
    res = evaluate_branch(sub, d)
    u = res["unweighted"]
    for comp in ("g1", "g2", "plus", "cross"):
        assert u[comp]["n_cases"] == N
        assert abs(u[comp]["m"] - m) < 4 * u[comp]["m_err"], comp
    assert abs(u["g1"]["c"] - c1) < 4 * u["g1"]["c_err"]
    # the PSF leakage is a constant +alpha |e_psf| along the PSF: c_plus, not c_cross
    assert abs(u["plus"]["c"] - alpha * 0.05) < 4 * u["plus"]["c_err"] + abs(c1)
    assert abs(u["cross"]["c"]) < 4 * u["cross"]["c_err"] + abs(c1)
    assert u["plus"]["c"] > 10 * u["plus"]["c_err"]
    assert res["q_c"]["frame"] == "psf" and res["q_c"]["sigma2_min"] == 4.0
    assert res["q_c"]["unweighted"] == pytest.approx(
        q_c(u["plus"]["m"], u["plus"]["c"], u["cross"]["m"], u["cross"]["c"], sigma2_min=4.0)
    )
    space = evaluate_branch(sub, d, sigma2_min=1.0)["q_c"]
    assert space["sigma2_min"] == 1.0 and space["unweighted"] > res["q_c"]["unweighted"]


def test_perfect_submission_scores_the_great3_maximum(truth, tmp_path):
    d, g1, g2, _ = truth
    sub = tmp_path / "sub.txt"
    L.write_submission(sub, np.arange(N), g1, g2)
    res = evaluate_branch(sub, d)
    assert res["q_c"]["unweighted"] == pytest.approx(
        2000 * 1.232 / 2, rel=1e-6
    )  # sqrt(sigma2_min = 4)


def test_per_galaxy_catalog_equals_its_submission(truth, tmp_path, runner, cli):
    d, g1, g2, _ = truth
    rng = np.random.default_rng(3)
    n_gal = 20
    sub_of = np.repeat(np.arange(N), n_gal)
    ids = L.galaxy_ids(sub_of, np.tile(np.arange(n_gal) % 5, N), np.tile(np.arange(n_gal) // 5, N))
    pre1 = g1[sub_of] + rng.normal(0, 0.2, sub_of.size)
    pre2 = g2[sub_of] + rng.normal(0, 0.2, sub_of.size)
    w = rng.uniform(0.1, 1.0, sub_of.size)
    flags = (rng.random(sub_of.size) < 0.05).astype(np.int32)
    cat = tmp_path / "shears.fits"
    write_catalog(
        cat,
        {"ID": ids, "pre_g1": pre1, "pre_g2": pre2, "pre_g1_w": w, "pre_g2_w": w, "flags": flags},
        fmt="megalut.predictions",
    )
    r = runner.invoke(
        cli, ["evaluate", str(cat), "--great3-truth", str(d), "--json", str(tmp_path / "c.json")]
    )
    assert r.exit_code == 0, r.output
    rc = json.loads((tmp_path / "c.json").read_text())
    for weighted, scheme in ((False, "unweighted"), (True, "weighted")):
        s, a1, a2, _ = L.submission_from_catalog(write_and_read(cat), weighted=weighted)
        sub = tmp_path / f"{scheme}.txt"
        L.write_submission(sub, s, a1, a2)
        rs = evaluate_branch(sub, d)
        for comp in ("g1", "g2", "plus", "cross"):
            assert rc[scheme][comp]["m"] == pytest.approx(rs["unweighted"][comp]["m"], abs=1e-10)
            assert rc[scheme][comp]["c"] == pytest.approx(rs["unweighted"][comp]["c"], abs=1e-12)


def write_and_read(path):
    from megalut_cli.catalog import read_catalog

    return read_catalog(path)


def test_bad_inputs(truth, tmp_path, runner, cli):
    d, g1, g2, _ = truth
    sub = tmp_path / "sub.txt"
    L.write_submission(sub, [0, 1, N + 5], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    with pytest.raises(InputError, match=f"subfield {N + 5}"):
        evaluate_branch(sub, d)
    r = runner.invoke(cli, ["evaluate", str(sub), "--great3-truth", str(d)])
    assert r.exit_code == 1 and f"subfield {N + 5}" in (r.stderr or r.output)
    one = tmp_path / "one.txt"
    L.write_submission(one, [3], [0.0], [0.0])
    with pytest.raises(InputError, match="fewer than 2 subfields"):
        evaluate_branch(one, d)
    nocol = tmp_path / "nocol.fits"
    write_catalog(nocol, {"pre_g1": np.zeros(3), "pre_g2": np.zeros(3)}, fmt="test")
    r = runner.invoke(cli, ["evaluate", str(nocol), "--great3-truth", str(d)])
    assert r.exit_code == 1 and "subfield" in (r.stderr or r.output)
    r = runner.invoke(cli, ["evaluate", str(sub), "--great3-truth", str(tmp_path / "nope")])
    assert r.exit_code == 2
