"""Catalog-level bias analysis on synthetic predictions with known injected biases."""

from __future__ import annotations

import re

import numpy as np
import pytest
from helpers import png_size, synthetic

from megalut_cli import flags
from megalut_cli.catalog import write_catalog
from megalut_cli.errors import ConfigError, InputError
from megalut_cli.pipeline.config import key_names
from megalut_cli.shear.evaluate import evaluate_catalog, evaluate_columns
from megalut_cli.shear.report import format_table


def test_recovers_injected_m_and_c_within_quoted_errors():
    m, c = (0.03, -0.02), (2e-3, -1e-3)
    r = evaluate_columns(synthetic(seed=11, m=m, c=c, sigma=0.05, weights=True))
    for scheme in ("unweighted", "weighted"):
        for i, comp in enumerate(("g1", "g2")):
            f = r[scheme][comp]
            assert abs(f["m"] - m[i]) < 3 * f["m_err"], (scheme, comp, f)
            assert abs(f["c"] - c[i]) < 3 * f["c_err"], (scheme, comp, f)
            assert f["m_err"] < 0.012 and f["c_err"] < 7e-4  # a real constraint, not a wide error
            assert f["n_cases"] == 100 and f["n_rows"] == 10_000
    assert "plus" not in r["unweighted"] and r["psf_frame"] is None


def test_quoted_errors_match_scatter_over_seeds():
    """Over 200 seeds, the std of the estimates agrees with the mean quoted error (15 %)."""
    m, c = (0.01, -0.005), (5e-4, 0.0)
    est = {k: [] for k in ("m", "m_err", "c", "c_err")}
    for seed in range(200):
        f = evaluate_columns(synthetic(seed=seed, n_cases=40, n_rea=25, m=m, c=c, sigma=0.3))[
            "unweighted"
        ]["g1"]
        for k in est:
            est[k].append(f[k])
    est = {k: np.array(v) for k, v in est.items()}
    assert np.std(est["m"], ddof=1) / np.mean(est["m_err"]) == pytest.approx(1.0, abs=0.15)
    assert np.std(est["c"], ddof=1) / np.mean(est["c_err"]) == pytest.approx(1.0, abs=0.15)
    # and the estimates are unbiased: the mean over seeds is within 3 standard errors.
    assert abs(np.mean(est["m"]) - m[0]) < 3 * np.std(est["m"]) / np.sqrt(200)
    assert abs(np.mean(est["c"]) - c[0]) < 3 * np.std(est["c"]) / np.sqrt(200)


def _append(d: dict[str, np.ndarray], extra: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: np.concatenate([d[k], np.asarray(extra[k], dtype=d[k].dtype)]) for k in d}


def test_zero_weights_remove_rows_exactly():
    base = synthetic(seed=5, n_cases=30, n_rea=40, m=(0.02, 0.0), weights=True)
    n = 500
    rng = np.random.default_rng(9)
    junk = {k: np.resize(base[k], n) for k in base}
    junk["pre_g1"] = rng.normal(5.0, 3.0, n)  # wild estimates ...
    junk["pre_g2"] = np.full(n, np.inf)
    junk["pre_g1_w"] = np.zeros(n)  # ... that carry no weight
    junk["pre_g2_w"] = np.zeros(n)
    junk["case"] = np.resize(np.append(base["case"][:3], 99_999), n)  # also a case with only junk
    junk["tru_g1"] = np.where(junk["case"] == 99_999, 0.3, junk["tru_g1"])
    with_junk = evaluate_columns(_append(base, junk))
    without = evaluate_columns(base)
    assert with_junk["weighted"] == without["weighted"]  # bit-identical, counts included


def test_failed_rows_are_excluded():
    base = synthetic(seed=6, n_cases=30, n_rea=40, m=(0.02, -0.01))
    n = 300
    bad = {k: np.resize(base[k], n) for k in base}
    bad["pre_g1"] = np.full(n, 3.0)
    bad["flags"] = np.full(n, flags.BAD_FEATURES)
    nan = {k: np.resize(base[k], n) for k in base}
    nan["pre_g1"] = np.full(n, np.nan)
    nan["pre_g2"] = np.full(n, np.nan)
    r = evaluate_columns(_append(_append(base, bad), nan))
    ref = evaluate_columns(base)
    assert r["unweighted"] == ref["unweighted"]
    assert r["n_rows"] == base["case"].size + 2 * n and r["n_valid"] == base["case"].size


def test_psf_frame_additive_bias_along_psf_lands_in_c_plus_only():
    d = synthetic(seed=2, n_cases=200, n_rea=20, sigma=0.002, psf=True)
    theta = 0.5 * np.arctan2(d["tru_psf_g2"], d["tru_psf_g1"])
    c0 = 3e-3
    d["pre_g1"] += c0 * np.cos(2 * theta)
    d["pre_g2"] += c0 * np.sin(2 * theta)
    r = evaluate_columns(d)["unweighted"]
    plus, cross = r["plus"], r["cross"]
    assert plus["c"] == pytest.approx(c0, abs=3 * plus["c_err"])
    assert abs(plus["c"] - c0) < 0.02 * c0  # achieved 0.49 % (0.43 sigma)
    assert (
        abs(cross["c"]) < 3 * cross["c_err"] and abs(cross["c"]) < 1e-3 * c0
    )  # achieved 3.0e-4 c0
    for comp in ("plus", "cross"):
        assert abs(r[comp]["m"]) < 3 * r[comp]["m_err"]
    # In the pixel frame the same bias is smeared over both components and the scatter.
    assert r["g1"]["c_err"] > 3 * plus["c_err"]


def test_psf_frame_falls_back_to_measured_psf_columns():
    d = synthetic(seed=3, n_cases=20, n_rea=10)
    d["psf_adamom_g1"] = np.full(d["case"].size, 0.1)
    d["psf_adamom_g2"] = np.zeros(d["case"].size)
    r = evaluate_columns(d)
    assert r["psf_frame"] == {"columns": ["psf_adamom_g1", "psf_adamom_g2"], "round": False}
    assert r["unweighted"]["plus"]["m"] == pytest.approx(r["unweighted"]["g1"]["m"])  # theta = 0


def test_conditional_biases_follow_injected_dependence():
    """m depends on a true parameter (per case) and c on a measured one (per row)."""
    d = synthetic(seed=4, n_cases=400, n_rea=50, sigma=0.03)
    m_true = np.where(d["tru_rad"] < 3.0, -0.05, 0.05)
    c_true = np.where(d["snr"] < 27.5, 2e-3, -2e-3)
    for comp in ("g1", "g2"):
        d[f"pre_{comp}"] += m_true * d[f"tru_{comp}"] + c_true
    r = evaluate_columns(d, by=["tru_rad", "snr"], bins=2)
    rad_bins = r["conditional"]["tru_rad"]["bins"]
    assert len(rad_bins) == 2
    for b, m in zip(rad_bins, (-0.05, 0.05)):
        f = b["unweighted"]["g1"]
        assert abs(f["m"] - m) < 3 * f["m_err"] and f["m_err"] < 0.01
        assert b["lo"] <= b["center"] <= b["hi"]
    snr_bins = r["conditional"]["snr"]["bins"]
    for b, c in zip(snr_bins, (2e-3, -2e-3)):
        f = b["unweighted"]["g2"]
        assert abs(f["c"] - c) < 3 * f["c_err"] and f["c_err"] < 5e-4
        assert f["n_cases"] == 400  # a per-row column: every case has rows in every bin
    assert abs(snr_bins[0]["n_rows"] - snr_bins[1]["n_rows"]) <= 1  # equal population


def test_conditional_biases_by_case_average_keep_whole_cases(tmp_path):
    """Binning by mean(snr) per case (paper Fig. 12) keeps each case, and its shape-noise
    cancellation, in one bin and finds an m that depends on the case's average S/N, which
    binning the noisy per-row snr blurs."""
    d = synthetic(seed=5, n_cases=400, n_rea=40, sigma=0.03)
    n = d["case"].size
    case_snr = np.random.default_rng(6).uniform(5.0, 50.0, 400)[d["case"] - 1000]
    d["snr"] = case_snr * np.random.default_rng(7).lognormal(0.0, 0.5, n)  # noisy per-row S/N
    m_true = np.where(case_snr < 27.5, -0.05, 0.05)
    for comp in ("g1", "g2"):
        d[f"pre_{comp}"] += m_true * d[f"tru_{comp}"]
    r = evaluate_columns(d, by=["mean(snr)", "snr"], bins=2)
    by_case = r["conditional"]["mean(snr)"]["bins"]
    assert [b["n_rows"] % 40 for b in by_case] == [0, 0]  # whole cases
    assert sum(b["unweighted"]["g1"]["n_cases"] for b in by_case) == 400
    for b, m in zip(by_case, (-0.05, 0.05)):
        f = b["unweighted"]["g1"]
        assert abs(f["m"] - m) < 3 * f["m_err"] and f["m_err"] < 0.01
    by_row = r["conditional"]["snr"]["bins"]
    assert by_row[1]["unweighted"]["g1"]["m"] - by_row[0]["unweighted"]["g1"]["m"] < 0.08  # blurred
    path = tmp_path / "shears.fits"
    write_catalog(path, d, fmt="megalut.shears")
    streamed = evaluate_catalog(path, by=["mean(snr)"], bins=2, chunk_rows=777)
    for a, b in zip(
        streamed["conditional"]["mean(snr)"]["bins"], by_case
    ):  # chunked sums: rounding only
        assert a["n_rows"] == b["n_rows"] and a["unweighted"]["g1"]["m"] == pytest.approx(
            b["unweighted"]["g1"]["m"]
        )


def test_conditional_biases_by_row_expression():
    d = synthetic(seed=9, n_cases=50, n_rea=20)
    rng = np.random.default_rng(3)
    d["tru_e1"], d["tru_e2"] = rng.normal(0, 0.2, (2, d["case"].size))
    r = evaluate_columns(d, by=["sqrt(tru_e1**2 + tru_e2**2)"], bins=4)
    bins = r["conditional"]["sqrt(tru_e1**2 + tru_e2**2)"]["bins"]
    e = np.hypot(d["tru_e1"], d["tru_e2"])
    assert (
        len(bins) == 4
        and bins[0]["lo"] == pytest.approx(e.min())
        and bins[-1]["hi"] == pytest.approx(e.max())
    )
    assert sum(b["n_rows"] for b in bins) == e.size


def test_row_selection_removes_selection_bias():
    d = synthetic(seed=8, n_cases=100, n_rea=60, sigma=0.1)
    low = d["snr"] < 10.0
    d["pre_g1"] = np.where(low, 0.5 * d["pre_g1"], d["pre_g1"])  # faint rows: strongly biased
    r_all = evaluate_columns(d)["unweighted"]["g1"]
    r_sel = evaluate_columns(d, select="snr > 10 & tru_rad > 0")
    f = r_sel["unweighted"]["g1"]
    assert r_all["m"] < -0.03
    assert abs(f["m"]) < 3 * f["m_err"]
    assert r_sel["n_selected"] == int((~low).sum()) and r_sel["select"] == "snr > 10 & tru_rad > 0"


def test_case_selection():
    d = synthetic(seed=8, n_cases=50, n_rea=10)
    r = evaluate_columns(d, select_cases="mean(tru_rad) > 3")
    assert r["unweighted"]["g1"]["n_cases"] == len(np.unique(d["case"][d["tru_rad"] > 3]))


def test_streamed_file_equals_in_memory(tmp_path):
    d = synthetic(seed=12, n_cases=37, n_rea=29, weights=True, psf=True, m=(0.01, 0.0))
    path = tmp_path / "shears.fits"
    write_catalog(path, d, fmt="megalut.predictions")
    ref = evaluate_columns(d, by=["tru_rad", "snr"], bins=4)
    got = evaluate_catalog(path, by=["tru_rad", "snr"], bins=4, chunk_rows=97)
    for scheme in ("unweighted", "weighted"):
        for comp, f in ref[scheme].items():
            for k, v in f.items():
                assert got[scheme][comp][k] == pytest.approx(v, rel=1e-9, abs=1e-15)
    for col in ("tru_rad", "snr"):
        for bref, bgot in zip(ref["conditional"][col]["bins"], got["conditional"][col]["bins"]):
            assert bgot["n_rows"] == bref["n_rows"]
            assert bgot["weighted"]["plus"]["m"] == pytest.approx(
                bref["weighted"]["plus"]["m"], rel=1e-9
            )
    assert got["input"] == str(path)


def test_requirement_and_table():
    good = evaluate_columns(synthetic(seed=1, sigma=0.0))  # exact estimates: m = c = 0
    assert good["requirement"]["met"] and good["requirement"]["applies_to"] == "unweighted"
    bad = evaluate_columns(synthetic(seed=1, sigma=0.0, m=(0.01, 0.0), weights=True))
    assert not bad["requirement"]["met"] and bad["requirement"]["applies_to"] == "weighted"
    assert any(f.startswith("g1: |m|") for f in bad["requirement"]["failures"])
    text = format_table(bad)
    assert "weighted" in text and "NOT met" in text and "OUT" in text


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d.pop("tru_g1"), "evaluate needs the true shear"),
        (lambda d: d["flags"].fill(1), "all 10000 rows failed"),
        (lambda d: d["case"].fill(7), "only one case"),
        (lambda d: (d["tru_g1"].fill(0.01), d["tru_g2"].fill(-0.02)), "no lever arm"),
        (lambda d: d["pre_g1_w"].__setitem__(3, -1.0), "negative weight"),
        (lambda d: (d["pre_g1_w"].fill(0.0), d["pre_g2_w"].fill(0.0)), "zero on every usable row"),
    ],
)
def test_bad_input_one_clear_error(mutate, message):
    d = synthetic(seed=0, weights=True)
    mutate(d)
    with pytest.raises(InputError, match=message):
        evaluate_columns(d)


def test_bad_options():
    d = synthetic(seed=0, n_cases=5, n_rea=5)
    with pytest.raises(ConfigError, match="no column nope"):
        evaluate_columns(d, by=["nope"])
    with pytest.raises(ConfigError, match="^by: .*unknown column"):
        evaluate_columns(d, by=["mean(nope)"])
    with pytest.raises(ConfigError, match="^by: .*is a condition"):
        evaluate_columns(d, by=["mean(snr) > 3"])
    with pytest.raises(ConfigError, match="unknown column"):
        evaluate_columns(d, select="nope > 1")
    with pytest.raises(InputError, match="no row passes"):
        evaluate_columns(d, select="snr > 1000")


def test_plot_renders(tmp_path):
    from megalut_cli.shear.plots import plot_evaluation

    r = evaluate_columns(
        synthetic(seed=3, weights=True, psf=True, m=(2e-3, 0)), by=["tru_rad", "snr"], bins=4
    )
    out = plot_evaluation(r, tmp_path / "ev.png")
    w, h = png_size(out)
    assert w >= 1000 and h >= 1000  # 4 columns x 4 rows of panels
    small = plot_evaluation(evaluate_columns(synthetic(seed=3)), tmp_path / "small.png")
    w2, h2 = png_size(small)
    assert 200 < h2 < h and w2 >= 600
    with pytest.raises(Exception, match="exists"):
        plot_evaluation(r, out)


def test_round_psf_is_flagged():
    d = synthetic(seed=4, n_cases=20, n_rea=10, psf=True)
    d["tru_psf_g1"][:] = 0.0
    d["tru_psf_g2"][:] = 0.0
    r = evaluate_columns(d)
    assert r["psf_frame"]["round"] is True
    assert r["unweighted"]["plus"] == r["unweighted"]["g1"]
    assert "round PSF" in format_table(r)


def test_messages_name_the_callers_words():
    d = synthetic(seed=1, n_cases=5, n_rea=5)
    for names, word in (
        (None, "select"),
        ({"select": "--select"}, "--select"),
        (key_names("evaluate"), "evaluate.select"),
    ):
        with pytest.raises(InputError, match=f"no row passes {re.escape(word)} 'tru_g1 > 5'"):
            evaluate_columns(d, select="tru_g1 > 5", names=names)
