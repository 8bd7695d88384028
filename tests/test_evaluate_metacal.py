"""The metacal calibration of ``evaluate`` (shear/evaluate.py, shear/paired.py) on synthetic
catalogs."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import with_failures

from megalut_cli.errors import InputError
from megalut_cli.shear.evaluate import BootstrapSpec, evaluate_columns
from megalut_cli.shear.paired import paired_evaluation

STEP = 0.01
SHEARS = np.array(
    [[-0.04, 0.03], [-0.02, -0.03], [0.0, 0.01], [0.02, -0.01], [0.04, 0.02], [0.03, 0.04]]
)


def _catalog(n_rea: int = 20000, response: float = 0.6, seed: int = 1) -> dict[str, np.ndarray]:
    """An estimator ``e = e_int + R g`` with a per-row response scattered around ``response``
    (noisy, like a network's finite difference), intrinsic shapes in 90-degree pairs (their mean is
    zero), the sheared versions ``e(+-step)`` and a spin-0 quantity ``q = |e|`` measured on every
    version (a cut on it prefers galaxies aligned with the shear: a selection bias)."""
    rng = np.random.default_rng(seed)
    n_cases = len(SHEARS)
    case = np.repeat(np.arange(n_cases), n_rea)
    rea = np.tile(np.arange(n_rea), n_cases)
    half = rng.normal(0.0, 0.25, (n_rea // 2, 2))
    e_int = np.tile(
        np.stack([half, -half], axis=1).reshape(-1, 2), (n_cases, 1)
    )  # common random numbers
    r_row = np.tile(response + rng.normal(0.0, 0.3, n_rea), n_cases)
    g = SHEARS[case]
    cols: dict[str, np.ndarray] = {
        "case": case,
        "rea": rea,
        "tru_g1": g[:, 0],
        "tru_g2": g[:, 1],
        "tru_real_index": rea // 2,
    }
    for kind, (s1, s2) in {
        "noshear": (0, 0),
        "1p": (1, 0),
        "1m": (-1, 0),
        "2p": (0, 1),
        "2m": (0, -1),
    }.items():
        e = e_int + r_row[:, None] * (g + STEP * np.array([s1, s2]))
        cols[f"pre_g1_{kind}"], cols[f"pre_g2_{kind}"] = e[:, 0], e[:, 1]
        cols[f"q_{kind}"] = np.hypot(e[:, 0], e[:, 1])
        cols[f"flags_{kind}"] = np.zeros(len(case), dtype=np.int32)
    cols["q"] = cols["q_noshear"]
    cols["pre_g1"], cols["pre_g2"] = cols["pre_g1_noshear"], cols["pre_g2_noshear"]
    cols["flags"] = np.zeros(len(case), dtype=np.int32)
    for i in "12":
        for j in "12":
            cols[f"mcal_r{i}{j}"] = (cols[f"pre_g{i}_{j}p"] - cols[f"pre_g{i}_{j}m"]) / (2 * STEP)
    return cols


def test_mean_response_calibrates_the_estimates():
    """Raw m = R - 1 = -0.4; calibrated by the rows' mean response, m and c vanish (to rounding:
    the synthetic response is exactly linear and the shapes cancel in pairs). Achieved < 1e-12."""
    cols = _catalog()
    plain = {k: v for k, v in cols.items() if not k.startswith("mcal_r")}
    raw = evaluate_columns(plain)
    assert raw["unweighted"]["g1"]["m"] == pytest.approx(-0.4, abs=0.02)
    res = evaluate_columns(cols, metacal_step=STEP)
    r = np.array(res["metacal"]["response"]["unweighted"])
    assert r[0, 0] == pytest.approx(np.mean(cols["mcal_r11"]), rel=1e-12)
    assert abs(r[0, 1]) < 1e-12 and abs(r[1, 0]) < 1e-12
    for comp in ("g1", "g2"):
        assert abs(res["unweighted"][comp]["m"]) < 1e-9, res["unweighted"][comp]
        assert abs(res["unweighted"][comp]["c"]) < 1e-9
    assert res["metacal"]["selection_response"]["unweighted"] is None


def test_selection_response_removes_the_selection_bias():
    """A cut on ``|e| > 0.2`` keeps more of the galaxies aligned with the shear: calibrated by
    the mean response alone, m is about +0.3; with the selection response from the same cut on
    the sheared versions, |m| < 1e-2 (achieved +2.1e-3 +- 1.6e-3, +2.0e-3 +- 3.0e-3: the
    finite-difference noise of the selection response limits it at this size)."""
    cols = _catalog(40000)
    res = evaluate_columns(cols, select="q > 0.2", metacal_step=STEP)
    sel = np.array(res["metacal"]["selection_response"]["unweighted"])
    mean = np.array(res["metacal"]["response"]["unweighted"])
    assert sel[0, 0] > 0.05 and sel[1, 1] > 0.05  # a positive selection response on the diagonal
    for i, comp in enumerate(("g1", "g2")):
        m = res["unweighted"][comp]["m"]
        assert abs(m) < 1e-2, res["unweighted"][comp]
        # the mean response alone leaves the selection bias
        assert (1 + m) * (mean[i, i] + sel[i, i]) / mean[i, i] - 1 > 0.05


def test_failures_as_a_selection_remove_their_bias():
    """Versions fail where ``|e| > 0.6``: which rows a case keeps depends on its shear. With
    the rows that have every version measured (``failures="exclude"``), m is about -0.16;
    with each version's mean over its own measured rows (``"selection"``: the response of the
    means, selection included), |m| < 0.02 (achieved +3.7e-3 +- 5.0e-3, +1.2e-3 +- 2.4e-3)."""
    cols = with_failures(_catalog(40000))
    excluded = evaluate_columns(cols, metacal_step=STEP)
    selected = evaluate_columns(cols, metacal_step=STEP, failures="selection")
    assert excluded["metacal"]["failures"] == "exclude"
    assert selected["metacal"]["failures"] == "selection"
    assert selected["metacal"]["selection_response"]["unweighted"] is None
    for comp in ("g1", "g2"):
        assert excluded["unweighted"][comp]["m"] < -0.1, excluded["unweighted"][comp]
        assert abs(selected["unweighted"][comp]["m"]) < 0.02, selected["unweighted"][comp]
    # bins of the measured q (a selection of their own) and the weights' selection: each
    # version's mean over its own bin and with its own weights. The failures are in the top
    # bin: there m is -0.15 to -0.23 with them excluded, |m| < 0.02 as a selection (achieved
    # 0.001 to 0.005); every bin within 3 sigma (+ 0.01) of zero
    weighted = _weighted(dict(cols))
    runs = {
        f: evaluate_columns(weighted, by=["q"], bins=3, metacal_step=STEP, failures=f)
        for f in ("exclude", "selection")
    }
    top = {f: r["conditional"]["q"]["bins"][-1] for f, r in runs.items()}
    for scheme in ("unweighted", "weighted"):
        for comp in ("g1", "g2"):
            assert top["exclude"][scheme][comp]["m"] < -0.1, top["exclude"][scheme][comp]
            assert abs(top["selection"][scheme][comp]["m"]) < 0.02, top["selection"][scheme]
            assert abs(runs["selection"][scheme][comp]["m"]) < 0.02, runs["selection"][scheme]
            for entry in runs["selection"]["conditional"]["q"]["bins"]:
                fit = entry[scheme][comp]
                assert abs(fit["m"]) < 3 * fit["m_err"] + 0.01, (scheme, comp, fit)
    # without failures the two agree to rounding (the same rows, the same response)
    clean = _catalog(4000)
    a = evaluate_columns(clean, metacal_step=STEP)
    b = evaluate_columns(clean, metacal_step=STEP, failures="selection")
    for comp in ("g1", "g2"):
        assert b["unweighted"][comp]["m"] == pytest.approx(a["unweighted"][comp]["m"], abs=1e-9)
    with pytest.raises(InputError, match="metacal catalog"):
        plain = {k: v for k, v in clean.items() if not k.startswith("mcal_r")}
        evaluate_columns(plain, failures="selection")


def test_paired_evaluation_calibrates_each_set():
    """Two sets of different responses (0.6 and 0.9) are each calibrated by their own mean
    response: m_a, m_b and m_a - m_b all vanish (achieved < 1e-9)."""
    a, b = _catalog(4000, 0.6), _catalog(4000, 0.9)
    res = paired_evaluation(a, b, n_boot=50)
    assert res["metacal"] is True
    for comp in ("g1", "g2"):
        r = res["overall"]["unweighted"][comp]
        assert abs(r["m_a"]) < 1e-9 and abs(r["m_b"]) < 1e-9 and abs(r["dm"]) < 1e-9, r


def _weighted(cols: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Weights computed on each version's shape, ``1 / (0.3^2 + |e|^2)``: they depend on the
    shear (a selection by weights)."""
    for kind in ("noshear", "1p", "1m", "2p", "2m"):
        w = 1.0 / (0.09 + cols[f"pre_g1_{kind}"] ** 2 + cols[f"pre_g2_{kind}"] ** 2)
        cols[f"pre_g1_w_{kind}"] = cols[f"pre_g2_w_{kind}"] = w
    cols["pre_g1_w"], cols["pre_g2_w"] = cols["pre_g1_w_noshear"], cols["pre_g2_w_noshear"]
    return cols


def test_paired_weighted_has_the_weights_selection_response():
    """With weights that depend on the shear, the paired evaluation gives exactly the m and c of
    the single-set evaluation of each set (both calibrate by the full 2x2 mean response plus
    the weights' 2x2 selection response; achieved 4e-15), unweighted and weighted; without
    the weights' selection response m would be off by about 0.4."""
    a = _weighted(_catalog(4000, 0.6, seed=2))
    single = evaluate_columns(a, metacal_step=STEP)
    paired = paired_evaluation(a, _weighted(_catalog(4000, 0.9, seed=2)), n_boot=20)
    sel = np.array(single["metacal"]["selection_response"]["weighted"])
    mean = np.array(single["metacal"]["response"]["weighted"])
    for scheme in ("unweighted", "weighted"):
        for comp in ("g1", "g2"):
            got = paired["overall"][scheme][comp]
            assert got["m_a"] == pytest.approx(single[scheme][comp]["m"], abs=1e-12)
            assert got["c_a"] == pytest.approx(single[scheme][comp]["c"], abs=1e-12)
    for i, comp in enumerate(("g1", "g2")):
        m_single = single["weighted"][comp]["m"]
        assert abs((1 + m_single) * (mean[i, i] + sel[i, i]) / mean[i, i] - 1 - m_single) > 1e-2


def test_by_bins_of_a_measured_quantity_get_their_selection_response():
    """Bins of ``q = |e|`` measured on the noshear version are a selection: galaxies aligned
    with the shear move to higher bins. With each bin's selection response from the same bin
    edges applied to the sheared versions' ``q``, every bin's |m| < 5e-2 (achieved: 0.010 to
    0.039, within 2 sigma of the fit errors, 0.006-0.033); with the mean response alone the
    bins are off by -0.77 to -0.79, -0.29 and +1.06 to +1.08."""
    cols = _catalog(40000)
    res = evaluate_columns(cols, by=["q"], bins=3, metacal_step=STEP)
    bins = res["conditional"]["q"]["bins"]
    assert len(bins) == 3
    for k, entry in enumerate(bins):
        mean = np.array(entry["metacal"]["response"]["unweighted"])
        sel = np.array(entry["metacal"]["selection_response"]["unweighted"])
        for i, comp in enumerate(("g1", "g2")):
            m = entry["unweighted"][comp]["m"]
            assert abs(m) < 5e-2, (k, comp, entry["unweighted"][comp])
            assert abs((1 + m) * (mean[i, i] + sel[i, i]) / mean[i, i] - 1) > 0.2
    # a per-case entry bins whole cases: no selection on the sheared versions
    res = evaluate_columns(cols, by=["tru_g1"], bins=2, metacal_step=STEP)
    for entry in res["conditional"]["tru_g1"]["bins"]:
        sel = np.array(entry["metacal"]["selection_response"]["unweighted"])
        assert np.all(sel == 0.0)
    # without a binned selection, the overall result has no selection response
    assert res["metacal"]["selection_response"]["unweighted"] is None


def _composed_catalog(
    shears: np.ndarray, n_rea: int = 2000, seed: int = 3
) -> dict[str, np.ndarray]:
    """As :func:`_catalog`, but each sheared version sees metacal's step composed with the
    case's shear as on an image, ``Shear(step) + Shear(g)`` (GalSim): its response is
    ``R (1 - S4(g))``, not ``R``."""
    import galsim

    rng = np.random.default_rng(seed)
    n_cases = len(shears)
    case = np.repeat(np.arange(n_cases), n_rea)
    half = rng.normal(0.0, 0.25, (n_rea // 2, 2))
    e_int = np.tile(np.stack([half, -half], axis=1).reshape(-1, 2), (n_cases, 1))
    r_row = np.tile(0.8 + rng.normal(0.0, 0.2, n_rea), n_cases)
    cols: dict[str, np.ndarray] = {
        "case": case,
        "rea": np.tile(np.arange(n_rea), n_cases),
        "tru_g1": shears[case, 0],
        "tru_g2": shears[case, 1],
    }
    steps = {"noshear": (0, 0), "1p": (1, 0), "1m": (-1, 0), "2p": (0, 1), "2m": (0, -1)}
    for kind, (s1, s2) in steps.items():
        seen = np.array(
            [
                (galsim.Shear(g1=STEP * s1, g2=STEP * s2) + galsim.Shear(g1=g1, g2=g2)).g1
                for g1, g2 in shears
            ]
        )
        seen2 = np.array(
            [
                (galsim.Shear(g1=STEP * s1, g2=STEP * s2) + galsim.Shear(g1=g1, g2=g2)).g2
                for g1, g2 in shears
            ]
        )
        e = e_int + r_row[:, None] * np.stack([seen[case], seen2[case]], axis=1)
        cols[f"pre_g1_{kind}"], cols[f"pre_g2_{kind}"] = e[:, 0], e[:, 1]
        cols[f"flags_{kind}"] = np.zeros(len(case), dtype=np.int32)
    cols["pre_g1"], cols["pre_g2"] = cols["pre_g1_noshear"], cols["pre_g2_noshear"]
    for i in "12":
        for j in "12":
            cols[f"mcal_r{i}{j}"] = (cols[f"pre_g{i}_{j}p"] - cols[f"pre_g{i}_{j}m"]) / (2 * STEP)
    return cols


def test_zero_shear_response_removes_the_drawn_shears_spin4_term():
    """20 shears drawn uniformly in |g_i| < 0.1: the mean response over the cases is
    ``R (1 - <S4(g)>)``, so calibrated by it the cases read ``(1 - <S4>)^-1 g``, and m takes
    the draw's <g1^2 - g2^2> (here -1.7e-3) and <2 g1 g2>: m = -0.68e-3 and +2.41e-3, as
    predicted to 1e-4 of their values; the response at zero shear (the default for a CRN
    set) calibrates |m| < 1e-7 (achieved 4e-9) and |c| < 1e-9."""
    shears = np.random.default_rng(5).uniform(-0.1, 0.1, (20, 2))
    g1, g2 = shears[:, 0], shears[:, 1]
    d, e = np.mean(g1**2 - g2**2), np.mean(2 * g1 * g2)
    s4 = np.array([[d, e], [e, -d]])
    assert abs(d) > 1e-3  # a draw that shows the effect
    predicted = np.linalg.solve(np.eye(2) - s4, shears.T).T
    cols = _composed_catalog(shears)
    mean = evaluate_columns(cols, metacal_step=STEP, response="mean")
    assert mean["metacal"]["response_at"] == "mean"
    for i, comp in enumerate(("g1", "g2")):
        m_predicted = np.polyfit(shears[:, i], predicted[:, i], 1)[0] - 1
        assert abs(m_predicted) > 5e-4
        assert mean["unweighted"][comp]["m"] == pytest.approx(m_predicted, rel=1e-3)
    zero = evaluate_columns(cols, metacal_step=STEP, crn=True)  # auto: zero shear
    assert zero["metacal"]["response_at"] == "zero-shear"
    r0 = np.array(zero["metacal"]["calibration_response"]["unweighted"])
    assert r0 == pytest.approx(np.diag([np.mean(cols["mcal_r11"][:2000])] * 2), abs=2e-4)
    for comp in ("g1", "g2"):
        assert abs(zero["unweighted"][comp]["m"]) < 1e-7, zero["unweighted"][comp]
        assert abs(zero["unweighted"][comp]["c"]) < 1e-9
    # the bootstrap redoes the fit in every resample: its errors stay finite
    boot = evaluate_columns(
        cols, metacal_step=STEP, crn=True, bootstrap=BootstrapSpec(2, 20, 1, True)
    )
    assert boot["unweighted"]["g1"]["m"] == pytest.approx(zero["unweighted"]["g1"]["m"])
    assert np.isfinite(boot["unweighted"]["g1"]["m_err"])


def test_zero_shear_response_needs_enough_cases():
    """Fewer than 10 cases: 'auto' falls back to the mean response, 'zero-shear' refuses."""
    cols = _catalog(200)
    assert evaluate_columns(cols, metacal_step=STEP, crn=True)["metacal"]["response_at"] == "mean"
    with pytest.raises(InputError, match="at least 10 cases"):
        evaluate_columns(cols, metacal_step=STEP, response="zero-shear")
    plain = {k: v for k, v in cols.items() if not k.startswith("mcal_r")}
    with pytest.raises(InputError, match="metacal catalog"):
        evaluate_columns(plain, response="zero-shear")
