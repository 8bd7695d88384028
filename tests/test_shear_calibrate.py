"""shear/calibrate.py: the calibrated mean shear of a catalog without truth, against hand
computations and known shears, PSF leakage, and errors against the scatter of realizations."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import metacal_predictions, with_failures

from megalut_cli.errors import ConfigError, InputError
from megalut_cli.shear.calibrate import (
    calibrate_columns,
    calibrated_catalog,
    format_calibration,
    plan_calibration,
    sky_patches,
)

STEP = 0.01
TYPES = ("noshear", "1p", "1m", "2p", "2m")


def hand_metacal(cat, select=None, weighted=False):
    """``(<R> + R_sel)^-1 <g>`` written out from Sheldon & Huff (2017), Sect. 5."""
    n = cat["pre_g1"].size

    def sel(kind):
        return cat[f"size_{kind}"] > 0.5 if select else np.ones(n, dtype=bool)

    def w(i, kind):
        return cat[f"pre_g{i}_w_{kind}"] if weighted else np.ones(n)

    m0 = sel("noshear")
    mean_r = np.array(
        [
            [
                np.sum((w(i, "noshear") * m0) * cat[f"mcal_r{i}{j}"]) / np.sum(w(i, "noshear") * m0)
                for j in (1, 2)
            ]
            for i in (1, 2)
        ]
    )
    g_raw = np.array(
        [
            np.sum(w(i, "noshear") * m0 * cat[f"pre_g{i}_noshear"]) / np.sum(w(i, "noshear") * m0)
            for i in (1, 2)
        ]
    )

    def avg(i, kind):
        ww = w(i, kind) * sel(kind)
        return np.sum(ww * cat[f"pre_g{i}_noshear"]) / np.sum(ww)

    r_sel = np.array(
        [[(avg(i, f"{j}p") - avg(i, f"{j}m")) / (2 * STEP) for j in (1, 2)] for i in (1, 2)]
    )
    return np.linalg.solve(mean_r + r_sel, g_raw), mean_r, r_sel, int(m0.sum())


@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("select", [None, "size > 0.5"])
def test_metacal_is_the_hand_computation(weighted, select):
    cat = metacal_predictions(n=3000, weights=weighted, seed=2, ring=1)
    res = calibrate_columns(
        cat, select=select, unweighted=not weighted, n_patches=20, failures="exclude"
    ).result
    g, mean_r, r_sel, n_used = hand_metacal(cat, select, weighted)
    a = res["all"]
    assert a["scheme"] == ("weighted" if weighted else "unweighted")
    assert res["calibration"] == "metacal" and a["n_objects"] == n_used
    np.testing.assert_allclose([a["g1"], a["g2"]], g, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(a["response"], mean_r, rtol=1e-10)
    if select is None and not weighted:
        assert a["selection_response"] is None  # no selection, no weights: none to take
        np.testing.assert_allclose(r_sel, 0.0, atol=1e-12)
    else:
        np.testing.assert_allclose(a["selection_response"], r_sel, rtol=1e-9, atol=1e-12)
        assert abs(r_sel[0][0]) > 0.05  # the set is built so that it matters


@pytest.mark.parametrize("weighted", [False, True])
def test_the_selection_response_recovers_the_shear(weighted):
    """A cut on a measured size and shear-dependent weights bias <g>/<R> by ~20 %; with the
    selection response the known shear (0.02, -0.01) comes back to 1e-3 (100 000 objects in
    90-degree pairs)."""
    cat = metacal_predictions(n=100_000, weights=weighted, seed=1, positions=False)
    a = calibrate_columns(
        cat,
        select="size > 0.5",
        unweighted=not weighted,
        errors="bootstrap",
        n_bootstrap=10,
        failures="exclude",
    ).result["all"]
    g = np.array([a["g1"], a["g2"]])
    total = np.array(a["response"]) + np.array(a["selection_response"])
    mean_only = np.linalg.solve(np.array(a["response"]), total @ g)
    assert np.all(np.abs(g - (0.02, -0.01)) < 1e-3), g
    assert abs(mean_only[0] - 0.02) > 3e-3, mean_only


def test_without_selection_the_mean_response_is_exact():
    cat = metacal_predictions(n=2000, seed=3)  # pairs, linear: <e> = 0 exactly
    for failures in ("exclude", "selection"):
        a = calibrate_columns(cat, unweighted=True, failures=failures).result["all"]
        assert a["selection_response"] is None
        np.testing.assert_allclose([a["g1"], a["g2"]], (0.02, -0.01), atol=1e-12)


def simulation_catalog(n=4000, g=(0.01, -0.02), seed=0, alpha=0.0, sigma=0.25, psf=True):
    """A simulation-calibrated prediction catalog: pre_g = g + alpha e_psf + noise."""
    rng = np.random.default_rng(seed)
    e_psf = rng.uniform(-0.05, 0.05, (2, n))
    cat = {
        "id": np.arange(n),
        "ra": rng.uniform(10.0, 12.0, n),
        "dec": rng.uniform(-1.0, 1.0, n),
        "pre_g1": g[0] + alpha * e_psf[0] + rng.normal(0, sigma, n),
        "pre_g2": g[1] + alpha * e_psf[1] + rng.normal(0, sigma, n),
        "pre_g1_w": rng.uniform(0.2, 1.0, n),
        "pre_g2_w": rng.uniform(0.2, 1.0, n),
        "flags": np.zeros(n, dtype=np.int32),
    }
    if psf:
        cat["psf_adamom_g1"], cat["psf_adamom_g2"] = e_psf
    return cat


def test_simulation_route_weighted_means():
    cat = simulation_catalog(psf=False)
    cat["flags"][:10] = 1
    cat["pre_g2"][10:20] = np.nan
    res = calibrate_columns(cat).result
    a = res["all"]
    assert res["calibration"] == "simulation" and res["metacal_step"] is None
    for i, bad in ((1, slice(0, 10)), (2, slice(0, 20))):
        w = cat[f"pre_g{i}_w"].copy()
        w[bad] = 0.0
        expect = np.sum(w * np.nan_to_num(cat[f"pre_g{i}"])) / np.sum(w)
        assert a[f"g{i}"] == pytest.approx(expect, rel=1e-12)
    assert a["response"] == [[1.0, 0.0], [0.0, 1.0]] and a["selection_response"] is None
    assert a["n_objects"] == 3990 and "alpha" not in a
    plain = calibrate_columns(cat, unweighted=True).result["all"]
    assert plain["g1"] == pytest.approx(np.mean(cat["pre_g1"][10:]), rel=1e-12)
    assert plain["scheme"] == "unweighted"


def test_psf_leakage_recovered():
    """g_est = g + 0.1 e_psf + noise: alpha = 0.1 within 3 sigma, the additive term g."""
    a = calibrate_columns(simulation_catalog(n=40_000, alpha=0.1, sigma=0.1)).result["all"]
    for i, g in ((0, 0.01), (1, -0.02)):
        assert abs(a["alpha"][i] - 0.1) < 3 * a["alpha_err"][i], a
        assert a["alpha_err"][i] < 0.03
        assert abs(a["additive"][i] - g) < 3 * a["additive_err"][i]
    # metacal: no leakage in the model, alpha consistent with 0 (calibrated estimates)
    cat = metacal_predictions(n=20_000, seed=4, ring=1)
    rng = np.random.default_rng(5)
    cat["psf_adamom_g1"], cat["psf_adamom_g2"] = rng.uniform(-0.05, 0.05, (2, 20_000))
    m = calibrate_columns(cat, unweighted=True).result["all"]
    assert all(abs(x) < 3 * e for x, e in zip(m["alpha"], m["alpha_err"])), m


@pytest.mark.parametrize("errors", ["jackknife", "bootstrap"])
def test_errors_follow_the_scatter_of_realizations(errors):
    """30 independent realizations: the mean quoted error matches the standard deviation of
    the estimates within 35 % (the scatter of a standard deviation over 30 draws is ~13 %),
    simulation-calibrated and metacal with failures that depend on the shear (counted as a
    selection, the default, and excluded)."""
    found: dict[str, tuple[list, list]] = {k: ([], []) for k in ("sim", "selection", "exclude")}
    for seed in range(30):
        kw = {"errors": errors, "n_patches": 25, "n_bootstrap": 50, "seed": seed}
        runs = [("sim", simulation_catalog(n=1000, seed=seed), {})]
        cat = with_failures(metacal_predictions(n=1000, seed=100 + seed, weights=True, ring=1))
        for failures in ("selection", "exclude"):
            runs.append((failures, cat, {"select": "size > 0.5", "failures": failures}))
        for key, columns, extra in runs:
            a = calibrate_columns(columns, **kw, **extra).result["all"]
            found[key][0].append((a["g1"], a["g2"]))
            found[key][1].append((a["g1_err"], a["g2_err"]))
    for key, (values, quoted) in found.items():
        ratio = np.mean(quoted, axis=0) / np.std(values, axis=0, ddof=1)
        assert np.all((ratio > 0.65) & (ratio < 1.35)), (key, ratio)


def test_bins_of_an_integer_column_and_of_quantiles():
    rng = np.random.default_rng(1)
    parts = []
    for tomo, g in enumerate(((0.01, 0.0), (0.03, -0.02), (-0.02, 0.04))):
        c = simulation_catalog(n=3000, g=g, seed=tomo, sigma=0.02, psf=False)
        c["tomo"] = np.full(3000, tomo + 1, dtype=np.int16)
        c["snr"] = rng.uniform(5, 50, 3000)
        parts.append(c)
    cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    res = calibrate_columns(cat, by="tomo", bins=7).result
    assert res["by"] == {"quantity": "tomo", "binning": "value"}
    assert [b["value"] for b in res["bins"]] == [1, 2, 3]  # value by value: --bins ignored
    for b, g in zip(res["bins"], ((0.01, 0.0), (0.03, -0.02), (-0.02, 0.04))):
        assert b["n_objects"] == 3000
        assert abs(b["g1"] - g[0]) < 3 * b["g1_err"] and abs(b["g2"] - g[1]) < 3 * b["g2_err"]
    res = calibrate_columns(cat, by="snr", bins=3).result
    assert res["by"]["binning"] == "quantile" and len(res["bins"]) == 3
    assert [b["n_objects"] for b in res["bins"]] == [3000, 3000, 3000]
    assert res["bins"][0]["lo"] < res["bins"][0]["center"] < res["bins"][0]["hi"]
    table = format_calibration(res)
    assert "all" in table.splitlines()[2] and len(table.splitlines()) == 8
    assert table.splitlines()[-1].startswith("frame: pixel")


def test_metacal_bins_of_a_measured_column_have_a_selection_response():
    cat = metacal_predictions(n=4000, seed=6, ring=1)
    cat["tomo"] = np.arange(4000) % 3
    kw = {"unweighted": True, "failures": "exclude"}
    res = calibrate_columns(cat, by="size", bins=2, **kw).result
    assert res["all"]["selection_response"] is None
    assert all(b["selection_response"] is not None for b in res["bins"])
    assert abs(res["bins"][1]["selection_response"][0][0]) > 0.05
    res = calibrate_columns(cat, by="tomo", **kw).result  # no sheared versions
    assert all(b["selection_response"] is None for b in res["bins"])


def test_sky_patches():
    rng = np.random.default_rng(0)
    ra = rng.uniform(-2.0, 2.0, 5000) % 360.0  # across RA = 0
    dec = rng.uniform(-3.0, 3.0, 5000)
    patches = sky_patches(ra, dec, 24)
    counts = np.bincount(patches)
    assert 18 <= counts.size <= 30 and counts.min() > 100  # one footprint, not two
    dec_far = dec + 60.0  # cos(dec) shrinks RA: the grid stays about square on the sky
    assert 18 <= np.unique(sky_patches(ra, dec_far, 24)).size <= 30
    x = np.array([0.0, 0.5, np.nan, 2.0])
    assert sky_patches(x, np.zeros(4), 2, sky=False).tolist() == [0, 0, -1, 1]


def test_per_object_catalog():
    cat = metacal_predictions(n=3000, seed=7, ring=1)
    cal = calibrate_columns(cat, unweighted=True, failures="exclude")
    table, cards = calibrated_catalog(cat, cal)
    a = cal.result["all"]
    assert set(table) >= {"id", "ra", "dec", "g1", "g2", "weight", "bin", "R11", "R22"}
    assert np.mean(table["g1"]) == pytest.approx(a["g1"], rel=1e-10)  # averages hold
    assert np.mean(table["g2"]) == pytest.approx(a["g2"], rel=1e-10)
    assert cards["CALR11"][0] == pytest.approx(a["response"][0][0])
    cal = calibrate_columns(cat, by="size", bins=2, unweighted=True, failures="exclude")
    table, cards = calibrated_catalog(cat, cal)
    for k, b in enumerate(cal.result["bins"]):
        total = np.array(b["response"]) + np.array(b["selection_response"])
        inside = table["bin"] == k
        assert inside.sum() == b["n_objects"]
        assert np.allclose(table["R11"][inside], total[0, 0])
        assert cards[f"R11B{k}"][0] == pytest.approx(total[0, 0])
        assert np.mean(table["g1"][inside]) == pytest.approx(b["g1"], rel=1e-9)


def test_bad_inputs():
    cat = metacal_predictions(n=500, seed=8)
    with pytest.raises(InputError, match="missing: pre_g1, pre_g2"):
        plan_calibration(["ra", "dec", "snr"])
    partial = [c for c in cat if c != "pre_g2_1m"]
    with pytest.raises(InputError, match="lacks pre_g2_1m"):
        plan_calibration(partial)
    with pytest.raises(InputError, match="no row passes select"):
        calibrate_columns(cat, select="size > 100")
    with pytest.raises(ConfigError, match="no column nosuch"):
        calibrate_columns(cat, by="nosuch")
    with pytest.raises(ConfigError, match="per-case"):
        calibrate_columns(cat, by="mean(size)")
    with pytest.raises(ConfigError, match="not a numeric column"):
        calibrate_columns(dict(cat, name=np.array(["a"] * 500)), by="name")
    no_pos = {k: v for k, v in cat.items() if k not in ("ra", "dec")}
    with pytest.raises(InputError, match="needs positions"):
        calibrate_columns(no_pos, errors="jackknife")
    assert calibrate_columns(no_pos).result["errors"]["method"] == "bootstrap"
    flagged = dict(cat, flags_noshear=np.ones(500, dtype=np.int32))
    with pytest.raises(InputError, match="nothing to calibrate"):
        calibrate_columns(flagged)


def test_psf_profile_follows_the_leakage():
    """The binned calibrated shear against the PSF ellipticity (``psf_profile``, what
    ``--plot`` draws) rises with the slope of a known leakage alpha = 0.5, and is flat
    without leakage."""
    for alpha in (0.5, 0.0):
        cat = simulation_catalog(n=40_000, alpha=alpha, sigma=0.05, seed=4)
        prof = calibrate_columns(cat).result["psf_profile"]
        for comp in ("g1", "g2"):
            e, g = np.array(prof[comp]["e_psf"]), np.array(prof[comp]["g"])
            assert len(e) == 8 and sum(prof[comp]["n"]) == 40_000
            slope = np.polyfit(e, g, 1)[0]
            assert abs(slope - alpha) < 0.05, (alpha, comp, slope)
            assert np.all(np.array(prof[comp]["g_err"]) < 1e-3)
    assert "psf_profile" not in calibrate_columns(simulation_catalog(psf=False)).result


def test_bins_of_sky_patches():
    """``--by patch``: about --bins patches of the sky, each with its bootstrap error and
    its median position; every patch's shear within 4 sigma of the truth; a jackknife or a
    catalog without positions refused."""
    cat = metacal_predictions(n=20_000, seed=8, ring=1)
    res = calibrate_columns(cat, by="patch", bins=4, n_bootstrap=50).result
    assert res["by"]["binning"] == "patch" and res["errors"]["method"] == "bootstrap"
    assert len(res["bins"]) == 4 and sum(b["n_objects"] for b in res["bins"]) == 20_000
    for b in res["bins"]:
        assert {"value", "ra", "dec"} <= set(b)
        assert abs(b["g1"] - 0.02) < 4 * b["g1_err"] and abs(b["g2"] + 0.01) < 4 * b["g2_err"]
    assert "patch 0 (" in format_calibration(res)
    with pytest.raises(ConfigError, match="jackknife"):
        calibrate_columns(cat, by="patch", errors="jackknife")
    nopos = {k: v for k, v in cat.items() if k not in ("ra", "dec")}
    with pytest.raises(InputError, match="positions"):
        calibrate_columns(nopos, by="patch")


def test_metadetection_catalog_is_calibrated_by_its_detections_response():
    """A metadetection catalog (one row per detection per version, ``mdet_step``): the
    response from each version's own detections, detection included, gives the shear back
    to 1e-3; the noshear detections' mean over the objects' response alone does not (the
    detection is a selection); errors by field (jackknife)."""
    from helpers import metadetect_predictions

    cat = metadetect_predictions(n=200_000, seed=2)
    res = calibrate_columns(cat, header={"MDETSTEP": 0.01}).result
    a = res["all"]
    assert res["calibration"] == "metadetect" and a["selection_response"] is None
    assert res["errors"]["method"] == "jackknife" and res["errors"]["units"] == "field"
    g = np.array([a["g1"], a["g2"]])
    assert np.all(np.abs(g - (0.02, -0.01)) < 1e-3), g
    assert np.all(np.abs(g - (0.02, -0.01)) < 4 * np.array([a["g1_err"], a["g2_err"]]))
    noshear = cat["mdet_step"] == "noshear"
    naive = cat["pre_g1"][noshear].mean() / 0.8  # the objects' mean response
    assert abs(naive - 0.02) > 3e-3, naive
    assert "metadetection" in format_calibration(res)
    with pytest.raises(InputError, match="MDETSTEP"):
        calibrate_columns(cat)
    bad = dict(cat, mdet_step=np.where(noshear, "noshear", "3p"))
    with pytest.raises(InputError, match="3p"):
        calibrate_columns(bad, header={"MDETSTEP": 0.01})


@pytest.mark.parametrize("angle, flip", [(30.0, False), (-75.0, True)])
def test_metadetection_shears_come_out_in_the_world_frame(angle, flip):
    """A coadd's metadetection catalog with the image's local Jacobian (``dudcol`` ...,
    written by ``measure IMAGE --metadetect`` for a celestial WCS), its pixels turned by
    ``angle`` degrees from the sky (and flipped): the galaxies' world shear, seen in the
    pixel frame as Q^T g, is calibrated back to the world frame to 1e-3."""
    from helpers import metadetect_predictions

    from megalut_cli.shear.frame import jacobian_frames

    phi = np.deg2rad(angle)
    jac = 0.2 * np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
    if flip:
        jac = jac @ np.diag([-1.0, 1.0])
    q = jacobian_frames(*(np.array([v]) for v in jac.ravel())).rotation[0]
    g_world = np.array([0.02, -0.01])
    cat = metadetect_predictions(n=200_000, seed=3, g=tuple(q.T @ g_world))
    n = len(cat["pre_g1"])
    for name, value in zip(("dudcol", "dudrow", "dvdcol", "dvdrow"), jac.ravel()):
        cat[name] = np.full(n, value)
    res = calibrate_columns(cat, header={"MDETSTEP": 0.01}).result
    a = res["all"]
    assert res["frame"] == "world"
    g = np.array([a["g1"], a["g2"]])
    assert np.all(np.abs(g - g_world) < 1e-3), g
    pixel = calibrate_columns(
        {k: v for k, v in cat.items() if not k.startswith("dud") and not k.startswith("dvd")},
        header={"MDETSTEP": 0.01},
    ).result["all"]
    assert abs(pixel["g1"] - g_world[0]) > 5e-3  # the pixel frame is another frame here


@pytest.mark.parametrize("jacobians", [False, True])
def test_failures_as_a_selection_recover_the_shear(jacobians):
    """Failures that depend on the shear bias the objects with every version measured (g1
    0.0165 and 0.0179 for 0.02, unweighted and weighted); counted as each version's selection
    (``failures="selection"``, the default: the response of the versions' means) the shear
    comes back within 3 sigma, in the pixel frame and through each object's Jacobian in the
    world frame (achieved within 0.2 sigma)."""
    g = np.array([0.02, -0.01])
    cat = with_failures(
        metacal_predictions(n=200_000, g=tuple(g), seed=4, weights=True, jacobians=jacobians)
    )
    header = {"MCALSTEP": 0.01}
    for unweighted in (False, True):
        kw = {"header": header, "unweighted": unweighted}
        excluded = calibrate_columns(cat, failures="exclude", **kw).result
        selected = calibrate_columns(cat, **kw).result
        assert excluded["failures"] == "exclude" and selected["failures"] == "selection"
        assert selected["frame"] == ("world" if jacobians else "pixel")
        a, b = excluded["all"], selected["all"]
        assert a["g1"] < 0.019 and a["g1"] + 2 * a["g1_err"] < g[0]  # the failures' bias
        for i in (1, 2):
            assert abs(b[f"g{i}"] - g[i - 1]) < 3 * b[f"g{i}_err"], (unweighted, b)
        assert b["selection_response"] is None  # the versions' means hold the selection
        assert b["n_objects"] > a["n_objects"]  # the noshear-measured objects, all of them
    # without failures the two agree (the same objects; the same response to rounding here,
    # where every object has every version)
    clean = metacal_predictions(n=4000, seed=5, jacobians=jacobians)
    a = calibrate_columns(clean, header=header, failures="exclude")
    b = calibrate_columns(clean, header=header)
    for i in (1, 2):
        assert b.result["all"][f"g{i}"] == pytest.approx(a.result["all"][f"g{i}"], abs=1e-6)


def test_failures_option_is_checked():
    cat = simulation_catalog(n=400)
    with pytest.raises(InputError, match="metacal catalog of stamps"):
        calibrate_columns(cat, failures="selection")
    with pytest.raises(ConfigError, match="failures"):
        calibrate_columns(metacal_predictions(n=400), failures="drop")
