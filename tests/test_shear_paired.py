"""Paired real-vs-twin biases: a known injected m difference is recovered, with the right error."""

from __future__ import annotations

import numpy as np
import pytest

from megalut_cli.errors import InputError
from megalut_cli.shear.paired import (
    check_pairing,
    format_paired,
    group_bins,
    paired_bias,
    paired_evaluation,
)


def synthetic_pair(
    seed: int,
    n_gal: int = 60,
    n_shear: int = 20,
    dm: float = -0.02,
    spread: float = 0.03,
    noise: float = 0.05,
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Twin estimates g (1 + m_t) + e + noise; real ones g (1 + m_t + dm + delta_i) + e + noise,
    with a per-galaxy response delta_i ~ N(0, spread) (real morphologies differ), 90-degree
    pairs, every galaxy under every shear; common shears, shapes and part of the noise."""
    rng = np.random.default_rng(seed)
    g = rng.uniform(-0.1, 0.1, (n_shear, 2))
    e = rng.rayleigh(0.2, n_gal)
    phi = rng.uniform(0, np.pi, n_gal)
    delta = rng.normal(0.0, spread, n_gal)
    case = np.repeat(np.arange(n_shear), 2 * n_gal)
    gal = np.tile(np.repeat(np.arange(n_gal), 2), n_shear)
    rea = np.tile(np.arange(2 * n_gal), n_shear)
    rot = np.tile([0.0, np.pi / 2], n_gal * n_shear)
    ang = 2 * (phi[gal] + rot)
    e_rows = np.stack([e[gal] * np.cos(ang), e[gal] * np.sin(ang)], axis=1)
    common = rng.normal(0, noise, (case.size, 2))
    m_t = 0.01
    a = {"case": case, "rea": rea, "gal": gal}
    b = dict(a)
    for i, comp in enumerate(("g1", "g2")):
        gt = g[case, i]
        a[f"tru_{comp}"] = b[f"tru_{comp}"] = gt
        b[f"pre_{comp}"] = gt * (1 + m_t) + e_rows[:, i] + common[:, i]
        a[f"pre_{comp}"] = (
            gt * (1 + m_t + dm + delta[gal])
            + e_rows[:, i]
            + common[:, i]
            + rng.normal(0, 0.3 * noise, case.size)
        )
        a[f"pre_{comp}_w"] = b[f"pre_{comp}_w"] = np.full(case.size, 0.5)
    return a, b


def test_recovers_injected_difference_and_its_error():
    """Over independent draws of the galaxies, the paired estimate of m_real - m_twin is
    unbiased and its bootstrap error matches its scatter (within 25 %)."""
    dms, errs, dms_sample = [], [], []
    for seed in range(40):
        a, b = synthetic_pair(seed)
        r = paired_bias(
            a["gal"], a["case"], a["tru_g1"], a["pre_g1"], b["pre_g1"], n_boot=400, seed=seed
        )
        dms.append(r["dm"])
        errs.append(r["dm_err"])
        dms_sample.append(r["m_a"] - r["m_b"])
    dms, errs = np.array(dms), np.array(errs)
    assert np.allclose(dms, dms_sample)
    scatter = dms.std(ddof=1)
    # expected: the galaxies' response spread over 60 galaxies, and the unpaired noise
    # (sigma 0.015 on 2400 rows with shears uniform in +-0.1)
    expected = np.hypot(0.03 / np.sqrt(60), 0.015 / np.sqrt(2400 * 0.2**2 / 12))
    assert scatter == pytest.approx(expected, rel=0.3)
    assert abs(dms.mean() - (-0.02)) < 3 * scatter / np.sqrt(len(dms))
    assert np.mean(errs) == pytest.approx(scatter, rel=0.25)


def test_pairing_makes_the_difference_more_precise_than_either_bias():
    """Shape noise is common to both sets: the error of the difference is far below the
    errors of m_real and m_twin themselves."""
    a, b = synthetic_pair(1, spread=0.0, noise=0.05)
    r = paired_bias(a["gal"], a["case"], a["tru_g2"], a["pre_g2"], b["pre_g2"], n_boot=300)
    assert r["dm"] == pytest.approx(-0.02, abs=4 * r["dm_err"])
    assert r["dm_err"] < 0.3 * r["m_b_err"]
    assert r["m_b"] == pytest.approx(0.01, abs=4 * r["m_b_err"])


def test_evaluation_weighted_bins_and_table():
    a, b = synthetic_pair(3)
    size = np.linspace(1, 3, 60)[a["gal"]]
    res = paired_evaluation(
        a, b, galaxy_column="gal", by={"size": size}, n_bins=2, n_boot=200, seed=4
    )
    assert set(res["overall"]) == {"unweighted", "weighted"}
    # uniform weights: the weighted analysis equals the unweighted one
    for comp in ("g1", "g2"):
        assert res["overall"]["weighted"][comp]["dm"] == pytest.approx(
            res["overall"]["unweighted"][comp]["dm"]
        )
    bins = res["by"]["size"]["bins"]
    assert [x["unweighted"]["g1"]["n_galaxies"] for x in bins] == [30, 30]
    assert "m_real - m_twin" in format_paired(res)


def test_group_bins_keep_pairs_together():
    gal = np.array([0, 0, 1, 1, 0, 0, 1, 1])
    case = np.array([0, 0, 0, 0, 1, 1, 1, 1])
    v = np.array([1.0, 9.0, 2.0, 2.0, 1.0, 1.0, 8.0, 8.0])
    idx, edges = group_bins(v, gal, case, 2)
    assert idx[0] == idx[1] and idx[2] == idx[3] and idx[6] == idx[7]
    assert len(edges) == 3


def test_mismatched_catalogs_one_line():
    a, b = synthetic_pair(0, n_gal=4, n_shear=3)
    b = dict(b, tru_g1=b["tru_g1"].copy())
    b["tru_g1"][5] += 0.01
    with pytest.raises(InputError, match="column tru_g1 differs at row 5"):
        check_pairing(a, b, ("real.fits", "twin.fits"), "gal")
    with pytest.raises(InputError, match="24 rows against 6"):
        check_pairing(a, {k: v[:6] for k, v in b.items()}, ("real.fits", "twin.fits"), "gal")


def test_cli_twin(tmp_path, runner, cli):
    """evaluate --twin prints the paired table and JSON; mismatched catalogs and options
    that do not apply give one error line."""
    import json

    from megalut_cli.catalog import write_catalog

    a, b = synthetic_pair(2, n_gal=20, n_shear=8)
    for t in (a, b):
        t["tru_real_index"] = t.pop("gal")
    write_catalog(tmp_path / "real.fits", a, fmt="test")
    write_catalog(tmp_path / "twin.fits", b, fmt="test")
    args = [
        "evaluate",
        str(tmp_path / "real.fits"),
        "--twin",
        str(tmp_path / "twin.fits"),
        "--bootstrap",
        "100",
    ]
    res = runner.invoke(
        cli, [*args, "--json", str(tmp_path / "p.json"), "--by", "abs(tru_g1)", "--bins", "2"]
    )
    assert res.exit_code == 0, res.output
    assert "m_real - m_twin" in res.output and "abs(tru_g1) in [" in res.output
    out = json.loads((tmp_path / "p.json").read_text())
    assert out["overall"]["weighted"]["g1"]["n_galaxies"] == 20
    assert len(out["by"]["abs(tru_g1)"]["bins"]) == 2
    bad = dict(b, rea=b["rea"][::-1].copy())
    write_catalog(tmp_path / "bad.fits", bad, fmt="test")
    res = runner.invoke(
        cli, ["evaluate", str(tmp_path / "real.fits"), "--twin", str(tmp_path / "bad.fits")]
    )
    assert res.exit_code == 1
    lines = (
        (res.stderr if hasattr(res, "stderr") and res.stderr else res.output).strip().splitlines()
    )
    assert len(lines) == 1 and "not paired: column rea differs at row 0" in lines[0]
    res = runner.invoke(cli, [*args, "--plot", str(tmp_path / "x.png")])
    assert res.exit_code == 2 and "--plot does not apply with --twin" in res.output
    res = runner.invoke(cli, [*args, "--by", "mean(snr)"])
    assert res.exit_code == 2


def test_paired_evaluation_of_a_set_with_itself_is_the_single_set_bootstrap():
    """One core for both evaluations: a set paired with itself gets the single-set m, c and
    bootstrap errors (the same draw of the same galaxies: groups = 90-degree pairs), plain and
    metacal (mean and selection response of each resample), unweighted and weighted; the
    differences vanish. Both default to the same number of resamples."""
    import inspect

    from helpers import crn_synthetic
    from test_evaluate_metacal import _catalog, _weighted

    from megalut_cli.shear.evaluate import BootstrapSpec, evaluate_columns
    from megalut_cli.shear.options import EVALUATE_CLI

    plain = crn_synthetic(2, True, n_cases=6, n_groups=50)
    plain["pre_g1_w"] = plain["pre_g2_w"] = np.linspace(0.5, 1.0, plain["case"].size)
    metacal = _weighted(_catalog(400, 0.7, seed=3))
    metacal["mcal_r11"] = metacal["mcal_r11"] + np.linspace(-0.1, 0.1, metacal["case"].size)
    for cols, step in ((plain, None), (metacal, 0.01)):
        cols["gal"] = cols["rea"] // 2
        single = evaluate_columns(cols, bootstrap=BootstrapSpec(2, 40, 5), metacal_step=step)
        paired = paired_evaluation(
            cols, cols, galaxy_column="gal", n_boot=40, seed=5, metacal_step=step or 0.01
        )
        assert paired["metacal"] is (step is not None)
        for scheme in ("unweighted", "weighted"):
            for comp in ("g1", "g2"):
                s, p = single[scheme][comp], paired["overall"][scheme][comp]
                for key in ("m", "c", "m_err", "c_err"):
                    assert p[f"{key[0]}_a{key[1:]}"] == pytest.approx(s[key], rel=1e-9), key
                assert p["dm"] == 0.0 and p["dm_err"] == 0.0
    defaults = {
        inspect.signature(f).parameters["n_boot"].default for f in (paired_bias, paired_evaluation)
    }
    assert defaults == {EVALUATE_CLI["bootstrap"].default}
