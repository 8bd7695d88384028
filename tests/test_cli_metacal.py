"""Metacalibration through the command line (issue 23): `measure --metacal`, `predict` and
`evaluate` (plain and `--twin`) on metacal catalogs, and the one-line errors on bad input.

One small fiducial set (4 cases x 8 realizations = 32 stamps of 64 px, Gaussian PSF sigma
2 px) is simulated and measured once per module; the metacal image operation runs with
``--engine galsim`` (the reference), unless noted.
"""

from __future__ import annotations

import json
from pathlib import Path

import galsim
import numpy as np
import pytest
from astropy.io import fits
from click.testing import CliRunner

from megalut_cli.catalog import read_catalog
from megalut_cli.cli import main as megalut
from megalut_cli.measure.defaults import PSF_COLUMNS
from megalut_cli.measure.features import FEATURE_COLUMNS
from megalut_cli.measure.metacal_defaults import TYPES
from megalut_cli.measure.morphology import MORPHOLOGY_COLUMNS

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "examples" / "fiducial" / "vo.toml"
#: The shipped models: simulation-calibrated (plain catalogs) and metacal (metacal catalogs).
MODEL = ROOT / "megalut_cli" / "data" / "fiducial.h5"
MCAL_MODEL = ROOT / "megalut_cli" / "data" / "fiducial-metacal.h5"
N_CASES, N_REA, SIZE = 4, 8, 64
ENV = {"MEGALUT_NPROC": "1"}  # module fixtures run before conftest's autouse monkeypatch
GALSIM = ["--engine", "galsim"]


def _runner() -> CliRunner:
    try:
        return CliRunner(mix_stderr=False)
    except TypeError:  # click >= 8.2 always separates them
        return CliRunner()


def _ok(*args: str):
    """Run ``megalut ARGS`` and require exit status 0."""
    result = _runner().invoke(megalut, [str(a) for a in args], env=ENV)
    assert result.exit_code == 0, (result.output, result.stderr, result.exception)
    return result


def _column(table, name: str) -> np.ndarray:
    return np.asarray(table[name])


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and np.array_equal(a, b, equal_nan=a.dtype.kind == "f")


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> Path:
    """The simulated stamps, their catalog and the PSF image (Gaussian sigma 2, with pixel)."""
    d = tmp_path_factory.mktemp("mcal_sim")
    _ok(
        "simulate",
        CONFIG,
        "-o",
        d / "cat.fits",
        "--stamps",
        d / "stamps.fits",
        "--n-cases",
        N_CASES,
        "--n-realizations",
        N_REA,
        "-q",
    )
    galsim.Gaussian(sigma=2.0).drawImage(nx=SIZE, ny=SIZE, scale=1.0).write(str(d / "psf.fits"))
    return d


@pytest.fixture(scope="module")
def measured(sim) -> Path:
    """Features: plain, metacal (seed 5, twice), metacal seed 6, metacal with --morphology and
    step 0.02 (seed 5); predictions of each but the repeated one."""
    d = sim
    base = ["measure", d / "stamps.fits", d / "cat.fits", "--psf", d / "psf.fits", *GALSIM, "-q"]
    _ok(*base, "-o", d / "plain.fits")
    _ok(*base, "-o", d / "mc5.fits", "--metacal", "--seed", "5")
    _ok(*base, "-o", d / "mc5b.fits", "--metacal", "--seed", "5")
    _ok(*base, "-o", d / "mc6.fits", "--metacal", "--seed", "6")
    _ok(
        *base,
        "-o",
        d / "morph.fits",
        "--metacal",
        "--metacal-step",
        "0.02",
        "--morphology",
        "--seed",
        "5",
    )
    _ok("predict", d / "plain.fits", "--model", MODEL, "-o", d / "s_plain.fits", "-q")
    for name in ("mc5", "mc6", "morph"):
        _ok("predict", d / f"{name}.fits", "--model", MCAL_MODEL, "-o", d / f"s_{name}.fits", "-q")
    return d


# --------------------------------------------------------------------------- measure


def test_help_mentions_metacal():
    result = _runner().invoke(megalut, ["measure", "--help"])
    assert result.exit_code == 0
    for word in ("--metacal", "--metacal-step", "--seed", "MCALSTEP"):
        assert word in result.output


def test_measure_metacal_columns_and_cards(measured):
    t = read_catalog(measured / "mc5.fits")
    names = list(FEATURE_COLUMNS)
    for kind in TYPES:
        for c in names:
            assert f"{c}_{kind}" in t.colnames, (c, kind)
        for c in PSF_COLUMNS:
            assert f"{c}_{kind}" in t.colnames, (c, kind)
    assert not any(c.startswith("morph_") for c in t.colnames)
    assert t.meta["MCALSTEP"] == 0.01 and t.meta["MCALSEED"] == 5
    assert len(t) == N_CASES * N_REA
    # the target PSF is round, slightly wider than the PSF, the same for every row and type
    for kind in TYPES:
        np.testing.assert_allclose(_column(t, f"psf_adamom_g1_{kind}"), 0.0, atol=1e-4)
        np.testing.assert_allclose(_column(t, f"psf_adamom_g2_{kind}"), 0.0, atol=1e-4)
        sigma = _column(t, f"psf_adamom_sigma_{kind}")
        assert np.all(sigma > _column(t, "psf_adamom_sigma")) and np.ptp(sigma) == 0
    np.testing.assert_allclose(
        _column(t, "psf_adamom_sigma_noshear"), _column(t, "psf_adamom_sigma") * 1.02, rtol=2e-3
    )
    for kind in TYPES:  # most sheared versions are measured
        assert np.mean(_column(t, f"flags_{kind}") == 0) > 0.8, kind


def test_metacal_keeps_todays_columns_bit_identical(measured):
    plain, mc = read_catalog(measured / "plain.fits"), read_catalog(measured / "mc5.fits")
    assert [c for c in mc.colnames if c in plain.colnames] == plain.colnames
    for c in plain.colnames:
        assert _same(plain[c], mc[c]), c
    assert "MCALSTEP" not in plain.meta and "MCALSEED" not in plain.meta
    for key in ("STAMPSZ", "MENGINE", "SEED", "NCASES", "NREA"):
        assert plain.meta[key] == mc.meta[key], key


def test_seed_reproducible_and_only_metacal_columns_change(measured):
    a, b, c = (read_catalog(measured / f"{n}.fits") for n in ("mc5", "mc5b", "mc6"))
    assert a.colnames == b.colnames == c.colnames
    for name in a.colnames:
        assert _same(a[name], b[name]), name
    assert c.meta["MCALSEED"] == 6
    plain = read_catalog(measured / "plain.fits").colnames
    for name in plain:
        assert _same(a[name], c[name]), name
    for kind in TYPES:  # another fixnoise field: other metacal features
        x, y = _column(a, f"adamom_g1_{kind}"), _column(c, f"adamom_g1_{kind}")
        ok = np.isfinite(x) & np.isfinite(y)
        assert ok.sum() > 20 and not np.array_equal(x[ok], y[ok]), kind
        assert not np.array_equal(_column(a, f"skymad_{kind}"), _column(c, f"skymad_{kind}")), kind


def test_versions_share_the_noshear_sky_noise(measured):
    """Every version's skymad is the noshear version's, and its snr Eq. 10 on it: the S/N
    then moves between 1p and 1m by what the shear does (~0.3 %), not by the resampled
    noise along each version's edges (their own edge MADs differ by ~7 %: the median
    |snr_1p - snr_1m| / snr was 5.7 % on a 10^6-stamp set), so an S/N cut's selection
    response is not noise."""
    t = read_catalog(measured / "mc5.fits")
    sky = _column(t, "skymad_noshear")
    assert np.all(np.isfinite(sky)) and np.all(sky > 0)
    for kind in TYPES:
        assert _same(_column(t, f"skymad_{kind}"), sky), kind
        flux, sigma = _column(t, f"adamom_flux_{kind}"), _column(t, f"adamom_sigma_{kind}")
        area = np.pi * (3 * sigma * np.sqrt(2 * np.log(2))) ** 2
        np.testing.assert_allclose(_column(t, f"snr_{kind}"), flux / (sky * np.sqrt(area)))
    for a, b in (("1p", "1m"), ("2p", "2m")):
        rel = np.abs(_column(t, f"snr_{a}") - _column(t, f"snr_{b}")) / _column(t, "snr_noshear")
        rel = rel[np.isfinite(rel)]
        assert len(rel) > 20 and np.median(rel) < 0.015, (a, b, np.median(rel))


def test_applied_shear_is_seen(measured):
    """adamom_g1_1p - adamom_g1_1m ~ 2 step R with R ~ 0.3-0.7 for adaptive moments; the
    same R with a step twice as large and the same fixnoise fields (the response is first
    order)."""
    responses = {}
    for name, step in (("mc5", 0.01), ("morph", 0.02)):
        t = read_catalog(measured / f"{name}.fits")
        assert t.meta["MCALSTEP"] == step
        for i in (1, 2):
            diff = _column(t, f"adamom_g{i}_{i}p") - _column(t, f"adamom_g{i}_{i}m")
            diff = diff[np.isfinite(diff)]
            assert diff.size > 20 and np.mean(diff > 0) > 0.8
            responses[(name, i)] = r = float(np.mean(diff)) / (2 * step)
            assert 0.25 < r < 0.9, (name, i, r)
        # the noshear version sits between the two sheared ones
        mid = _column(t, "adamom_g1_noshear")
        half = 0.5 * (_column(t, "adamom_g1_1p") + _column(t, "adamom_g1_1m"))
        ok = np.isfinite(mid) & np.isfinite(half)
        assert np.median(np.abs(mid - half)[ok]) < 1e-3
    for i in (1, 2):
        assert abs(responses[("mc5", i)] - responses[("morph", i)]) < 0.03, responses


def test_morphology_metacal_columns(measured):
    t = read_catalog(measured / "morph.fits")
    assert MORPHOLOGY_COLUMNS
    for c in MORPHOLOGY_COLUMNS:
        assert c in t.colnames
        for kind in TYPES:
            col = f"{c}_{kind}"
            assert col in t.colnames, col
            assert np.isfinite(_column(t, col)).sum() > 20, col
    assert t.meta["MCALSTEP"] == 0.02


def _first_rows(src: Path, dst: Path, n: int) -> Path:
    """A copy of a catalog with its first ``n`` rows (header cards kept)."""
    with fits.open(src) as h:
        h[1].data = h[1].data[:n]
        h.writeto(dst)
    return dst


def test_workers_and_psf_grid_give_the_same_metacal_features(measured, tmp_path):
    """-j 2 (fixnoise seeds follow the rows, not the work units) and a PSF grid like the
    stamps image (one PSF stamp per row, all the same here) give the features of the
    single-process, single-PSF run (mc5: the same seed, the same first 8 rows)."""
    d = measured
    cat = _first_rows(d / "cat.fits", tmp_path / "cat8.fits", 8)
    with fits.open(d / "stamps.fits") as h:
        ny, nx = h[0].data.shape
    psf = galsim.Gaussian(sigma=2.0).drawImage(nx=SIZE, ny=SIZE, scale=1.0).array
    grid = tmp_path / "psfgrid.fits"
    fits.PrimaryHDU(np.tile(psf, (ny // SIZE, nx // SIZE))).writeto(grid)
    base = ["measure", d / "stamps.fits", cat, "--metacal", "--seed", "5", *GALSIM, "-q"]
    _ok(*base, "--psf", d / "psf.fits", "-j", "2", "-o", tmp_path / "j2.fits")
    _ok(*base, "--psf", grid, "-o", tmp_path / "grid.fits")
    ref = read_catalog(d / "mc5.fits")[:8]
    j2, per_row = read_catalog(tmp_path / "j2.fits"), read_catalog(tmp_path / "grid.fits")
    assert j2.colnames == ref.colnames == per_row.colnames
    for name in ref.colnames:
        assert _same(j2[name], ref[name]), name
        if name.startswith("psf_adamom_") and name.endswith(
            TYPES
        ):  # the target from the PSF stamps' sigma
            np.testing.assert_allclose(
                _column(per_row, name), _column(ref, name), rtol=1e-5, atol=1e-6
            )
        elif np.asarray(ref[name]).dtype.kind == "f":
            np.testing.assert_allclose(
                _column(per_row, name), _column(ref, name), rtol=1e-9, atol=1e-12, err_msg=name
            )
        else:
            assert _same(per_row[name], ref[name]), name


def test_fast_and_galsim_metacal_engines_agree(measured, tmp_path):
    """The fast engine (FFTs over the stack, measure/metacal_fft.py) against the GalSim
    reference on 8 stamps: the same flags, shapes within 1e-4."""
    d = measured
    cat = _first_rows(d / "cat.fits", tmp_path / "cat8.fits", 8)
    out = {}
    for engine in ("galsim", "fast"):
        out[engine] = tmp_path / f"{engine}.fits"
        _ok(
            "measure",
            d / "stamps.fits",
            cat,
            "--psf",
            d / "psf.fits",
            "--metacal",
            "--engine",
            engine,
            "-o",
            out[engine],
            "-q",
        )
    a, b = read_catalog(out["galsim"]), read_catalog(out["fast"])
    assert a.colnames == b.colnames and str(b.meta["MENGINE"]).strip() == "fast"
    for kind in TYPES:
        assert _same(a[f"flags_{kind}"], b[f"flags_{kind}"]), kind
        for c in ("adamom_g1", "adamom_g2"):
            x, y = _column(a, f"{c}_{kind}"), _column(b, f"{c}_{kind}")
            ok = np.isfinite(x) & np.isfinite(y)
            assert ok.sum() >= 6 and np.array_equal(np.isfinite(x), np.isfinite(y))
            assert np.max(np.abs(x[ok] - y[ok])) < 1e-4, (c, kind)
        np.testing.assert_allclose(
            _column(b, f"adamom_sigma_{kind}"), _column(a, f"adamom_sigma_{kind}"), rtol=1e-4
        )


# --------------------------------------------------------------------------- predict


def test_predict_metacal_columns_and_responses(measured):
    s = read_catalog(measured / "s_mc5.fits")
    step = 0.01
    assert s.meta["MCALSTEP"] == step
    for kind in TYPES:
        for c in ("pre_g1", "pre_g2", "pre_g1_w", "pre_g2_w"):
            assert f"{c}_{kind}" in s.colnames, (c, kind)
    for i in (1, 2):
        for j in (1, 2):
            expected = (_column(s, f"pre_g{i}_{j}p") - _column(s, f"pre_g{i}_{j}m")) / (2.0 * step)
            assert np.array_equal(_column(s, f"mcal_r{i}{j}"), expected, equal_nan=True), (i, j)
    for c in ("mcal_r11", "mcal_r22"):
        r = _column(s, c)
        assert np.isfinite(r).sum() > 20
        assert 0.5 < np.nanmean(r) < 1.5, (c, np.nanmean(r))
    for c in ("mcal_r12", "mcal_r21"):
        assert abs(np.nanmean(_column(s, c))) < 0.3
    # a step of 0.02 (same fixnoise fields): its card, its finite differences, about the same
    # response
    s2 = read_catalog(measured / "s_morph.fits")
    assert s2.meta["MCALSTEP"] == 0.02
    expected = (_column(s2, "pre_g1_1p") - _column(s2, "pre_g1_1m")) / (2.0 * 0.02)
    assert np.array_equal(_column(s2, "mcal_r11"), expected, equal_nan=True)
    for c in ("mcal_r11", "mcal_r22"):
        assert abs(np.nanmean(_column(s2, c)) - np.nanmean(_column(s, c))) < 0.1, c
    plain = read_catalog(measured / "s_plain.fits")
    assert "MCALSTEP" not in plain.meta and not any(c.startswith("mcal_") for c in plain.colnames)


def test_predict_columns_of_a_metacal_catalog_in_memory(measured):
    """predict_columns with the catalog's metacal step gives the columns predict writes, in
    its order (the GREAT3 branch pipeline predicts its subfields this way)."""
    from megalut_cli.nn.model import ShearModel
    from megalut_cli.shear.predict import predict_columns

    features, written = read_catalog(measured / "mc5.fits"), read_catalog(measured / "s_mc5.fits")
    pred = predict_columns(
        ShearModel.load(MCAL_MODEL), features, metacal_step=features.meta["MCALSTEP"]
    )
    assert [c for c in written.colnames if c in pred and c not in features.colnames] == [
        c for c in pred if c not in features.colnames
    ]
    for c, values in pred.items():
        assert _same(values, written[c]), c


def test_predict_refuses_a_model_of_the_other_mode(measured, tmp_path):
    """A simulation-calibrated model on a metacal catalog, a metacal model on a plain one."""
    _refused(
        ["predict", measured / "mc5.fits", "--model", MODEL],
        1,
        tmp_path / "a.fits",
        "fiducial.h5",
        "MCALSTEP",
    )
    _refused(
        ["predict", measured / "plain.fits", "--model", MCAL_MODEL],
        1,
        tmp_path / "b.fits",
        "fiducial-metacal.h5",
        "--metacal",
    )


def test_predict_metacal_catalog_without_type_flags(measured, tmp_path):
    """An external metacal catalog (MCALSTEP, X_<type> features) without flags_<type>: the
    estimates are written (predict_metacal's flags_<type>), or one clear error, not a crash."""
    src = tmp_path / "noflags.fits"
    with fits.open(measured / "mc5.fits") as h:
        cols = [c for c in h[1].columns if not c.name.startswith("flags_")]
        fits.HDUList([h[0], fits.BinTableHDU.from_columns(cols, header=h[1].header)]).writeto(src)
    out = tmp_path / "s.fits"
    result = _runner().invoke(
        megalut, ["predict", str(src), "--model", str(MCAL_MODEL), "-o", str(out), "-q"], env=ENV
    )
    assert "internal error" not in result.stderr and "Traceback" not in result.stderr
    assert result.exit_code in (0, 1)
    if result.exit_code == 0:
        assert "mcal_r11" in read_catalog(out).colnames


# --------------------------------------------------------------------------- evaluate


def _usable(s, comp: int) -> np.ndarray:
    ok = _column(s, "flags_noshear") == 0
    ok &= np.isfinite(_column(s, f"tru_g{comp}")) & np.isfinite(_column(s, f"pre_g{comp}_noshear"))
    for j in (1, 2):
        ok &= np.isfinite(_column(s, f"mcal_r{comp}{j}"))
    return ok


def test_evaluate_metacal(measured, tmp_path):
    js = tmp_path / "e.json"
    result = _runner().invoke(
        megalut, ["evaluate", str(measured / "s_mc5.fits"), "--json", str(js)], env=ENV
    )
    assert result.exit_code == 0, (result.output, result.stderr)
    e = json.loads(js.read_text())
    mc = e["metacal"]
    assert mc["step"] == 0.01
    assert set(mc["response"]) == {"unweighted", "weighted"}
    assert mc["selection_response"]["unweighted"] is None  # no selection
    weighted_rs = np.array(mc["selection_response"]["weighted"], dtype=float)  # the weights select
    assert weighted_rs.shape == (2, 2) and np.all(np.isfinite(weighted_rs))

    s = read_catalog(measured / "s_mc5.fits")
    r = np.array(mc["response"]["unweighted"], dtype=float)
    for i in (1, 2):
        ok = _usable(s, i)
        assert ok.sum() > 20
        for j in (1, 2):
            np.testing.assert_allclose(
                r[i - 1, j - 1], np.mean(_column(s, f"mcal_r{i}{j}")[ok]), rtol=1e-10
            )

    # per case: the mean of pre_g*_noshear calibrated by the inverse of the mean response
    case = _column(s, "case")
    per_case = e["per_case"]
    means = {}
    for i in (1, 2):
        ok = _usable(s, i)
        means[i] = np.array(
            [np.mean(_column(s, f"pre_g{i}_noshear")[ok & (case == k)]) for k in per_case["case"]]
        )
    det = r[0, 0] * r[1, 1] - r[0, 1] * r[1, 0]
    g1 = (r[1, 1] * means[1] - r[0, 1] * means[2]) / det
    g2 = (r[0, 0] * means[2] - r[1, 0] * means[1]) / det
    np.testing.assert_allclose(per_case["unweighted"]["g1"]["pre"], g1, rtol=1e-9)
    np.testing.assert_allclose(per_case["unweighted"]["g2"]["pre"], g2, rtol=1e-9)
    # and m, c of those against the truth (ordinary least squares over the cases)
    for comp, est in (("g1", g1), ("g2", g2)):
        tru = np.array(per_case["unweighted"][comp]["tru"])
        m, c = np.polyfit(tru, est - tru, 1)
        assert e["unweighted"][comp]["m"] == pytest.approx(m, rel=1e-6, abs=1e-9)
        assert e["unweighted"][comp]["c"] == pytest.approx(c, rel=1e-6, abs=1e-9)

    # the same command with --fail-above: the documented exit status 3 (biases of 32 stamps)
    result = _runner().invoke(
        megalut, ["evaluate", str(measured / "s_mc5.fits"), "--fail-above", "-q"], env=ENV
    )
    assert result.exit_code == 3 and "bias out of tolerance" in result.stderr


def test_evaluate_metacal_selection_response(measured, tmp_path):
    js = tmp_path / "sel.json"
    result = _runner().invoke(
        megalut,
        ["evaluate", str(measured / "s_mc5.fits"), "--select", "snr > 10", "--json", str(js), "-q"],
        env=ENV,
    )
    assert result.exit_code == 0, result.stderr
    e = json.loads(js.read_text())
    assert e["select"] == "snr > 10" and 0 < e["n_selected"] < e["n_rows"]
    rs = e["metacal"]["selection_response"]
    for scheme in ("unweighted", "weighted"):
        a = np.array(rs[scheme], dtype=float)
        assert a.shape == (2, 2) and np.all(np.isfinite(a)), scheme


def test_evaluate_metacal_step_from_the_header(measured, tmp_path):
    js = tmp_path / "e.json"
    result = _runner().invoke(
        megalut, ["evaluate", str(measured / "s_morph.fits"), "--json", str(js), "-q"], env=ENV
    )
    assert result.exit_code == 0, result.stderr
    assert json.loads(js.read_text())["metacal"]["step"] == 0.02


def test_evaluate_metacal_selects_on_noshear_columns(measured, tmp_path):
    js = tmp_path / "sel.json"
    result = _runner().invoke(
        megalut,
        ["evaluate", str(measured / "s_mc5.fits"), "--select", "snr > 10", "--json", str(js), "-q"],
        env=ENV,
    )
    assert result.exit_code == 0, result.stderr
    s = read_catalog(measured / "s_mc5.fits")
    noshear = _column(s, "snr_noshear")
    assert np.sum(noshear > 10) != np.sum(_column(s, "snr") > 10)  # the two selections differ here
    assert json.loads(js.read_text())["n_selected"] == int(np.sum(noshear > 10))


def test_evaluate_metacal_catalog_without_type_flags(measured, tmp_path):
    src = tmp_path / "noflags.fits"
    with fits.open(measured / "s_mc5.fits") as h:
        cols = [c for c in h[1].columns if not c.name.startswith("flags_")]
        fits.HDUList([h[0], fits.BinTableHDU.from_columns(cols, header=h[1].header)]).writeto(src)
    result = _runner().invoke(megalut, ["evaluate", str(src), "-q"], env=ENV)
    assert "internal error" not in result.stderr and "Traceback" not in result.stderr
    assert result.exit_code in (0, 1)


def _with_galaxy_column(src: Path, dst: Path) -> Path:
    """A copy of a prediction catalog with tru_real_index (the galaxy id --twin pairs by)."""
    with fits.open(src) as h:
        rea = np.asarray(h[1].data["rea"], dtype=np.int64)
        col = fits.Column(name="tru_real_index", format="K", array=rea)
        table = fits.BinTableHDU.from_columns(
            h[1].columns + fits.ColDefs([col]), header=h[1].header
        )
        fits.HDUList([h[0], table]).writeto(dst)
    return dst


def test_evaluate_twin_on_metacal_catalogs(measured, tmp_path):
    a = _with_galaxy_column(measured / "s_mc5.fits", tmp_path / "a.fits")
    b = _with_galaxy_column(measured / "s_mc6.fits", tmp_path / "b.fits")
    js = tmp_path / "twin.json"
    result = _runner().invoke(
        megalut,
        ["evaluate", str(a), "--twin", str(b), "--bootstrap", "50", "--json", str(js), "-q"],
        env=ENV,
    )
    assert result.exit_code == 0, (result.output, result.stderr)
    e = json.loads(js.read_text())
    assert e["metacal"] is True
    for scheme in ("unweighted", "weighted"):
        for comp in ("g1", "g2"):
            r = e["overall"][scheme][comp]
            assert r["m_a"] is not None and r["m_b"] is not None and r["dm_err"] is not None, (
                scheme,
                comp,
            )
            assert r["n_cases"] == N_CASES and r["n_galaxies"] == N_REA
    # a catalog paired with itself: no difference
    js2 = tmp_path / "self.json"
    result = _runner().invoke(
        megalut,
        ["evaluate", str(a), "--twin", str(a), "--bootstrap", "20", "--json", str(js2), "-q"],
        env=ENV,
    )
    assert result.exit_code == 0, result.stderr
    self_pair = json.loads(js2.read_text())["overall"]["unweighted"]["g1"]
    assert self_pair["dm"] == 0.0 and self_pair["m_a"] == e["overall"]["unweighted"]["g1"]["m_a"]


# --------------------------------------------------------------------------- bad input


def _copy_image(
    src: Path, dst: Path, cards: dict | None = None, nan_at: tuple[int, int] | None = None
) -> Path:
    with fits.open(src) as h:
        for k, v in (cards or {}).items():
            h[0].header[k] = v
        if nan_at is not None:
            data = h[0].data.copy()
            data[nan_at] = np.nan
            h[0].data = data
        h.writeto(dst)
    return dst


def _refused(args: list, code: int, out: Path, *words: str) -> str:
    """``megalut ARGS -q`` exits with ``code``, one stderr line 'Error: ...', no output file."""
    result = _runner().invoke(megalut, [*(str(a) for a in args), "-o", str(out), "-q"], env=ENV)
    assert result.exit_code == code, (result.output, result.stderr)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    if lines and lines[0].startswith("Usage:"):  # click's own usage errors: usage, hint, error line
        lines = lines[2:]
    assert len(lines) == 1 and lines[0].startswith("Error:"), result.stderr
    assert "Traceback" not in result.stderr + result.output and "internal error" not in lines[0]
    for w in words:
        assert w in lines[0], lines[0]
    assert not out.exists()
    assert [
        p.name for p in out.parent.iterdir() if p.name.startswith(".")
    ] == []  # no temporary files
    return lines[0]


def test_metacal_without_psf_is_a_usage_error(sim, tmp_path):
    _refused(
        ["measure", sim / "stamps.fits", sim / "cat.fits", "--metacal", *GALSIM],
        2,
        tmp_path / "o.fits",
        "--psf",
        "--metacal",
    )


@pytest.mark.parametrize("step", ["0", "0.5", "-0.01"])
def test_metacal_step_out_of_range(sim, tmp_path, step):
    _refused(
        [
            "measure",
            sim / "stamps.fits",
            sim / "cat.fits",
            "--psf",
            sim / "psf.fits",
            "--metacal",
            "--metacal-step",
            step,
            *GALSIM,
        ],
        2,
        tmp_path / "o.fits",
        "--metacal-step",
    )


def test_psf_at_another_pixel_scale(sim, tmp_path):
    stamps = _copy_image(sim / "stamps.fits", tmp_path / "stamps.fits", {"PIXSCALE": 0.2})
    psf = _copy_image(sim / "psf.fits", tmp_path / "psf.fits", {"PIXSCALE": 0.1})
    out = tmp_path / "o.fits"
    _refused(
        ["measure", stamps, sim / "cat.fits", "--psf", psf, "--metacal", *GALSIM],
        1,
        out,
        "psf.fits",
        "0.1",
        "0.2",
    )
    # the same pixel scale is fine (4 rows, to be quick); without --metacal the scale is not checked
    cat = _first_rows(sim / "cat.fits", tmp_path / "cat4.fits", 4)
    same = _copy_image(sim / "psf.fits", tmp_path / "psf02.fits", {"PIXSCALE": 0.2})
    _ok(
        "measure",
        stamps,
        cat,
        "--psf",
        same,
        "--metacal",
        *GALSIM,
        "-o",
        tmp_path / "ok.fits",
        "-q",
    )
    assert len(read_catalog(tmp_path / "ok.fits")) == 4
    _ok("measure", stamps, cat, "--psf", psf, *GALSIM, "-o", tmp_path / "plain.fits", "-q")


def test_psf_of_the_other_parity(sim, tmp_path):
    psf = tmp_path / "psf63.fits"
    galsim.Gaussian(sigma=2.0).drawImage(nx=SIZE - 1, ny=SIZE - 1, scale=1.0).write(str(psf))
    _refused(
        ["measure", sim / "stamps.fits", sim / "cat.fits", "--psf", psf, "--metacal", *GALSIM],
        1,
        tmp_path / "o.fits",
        "psf63.fits",
        "63",
    )


def test_psf_with_nan_pixels(sim, tmp_path):
    psf = _copy_image(sim / "psf.fits", tmp_path / "psfnan.fits", nan_at=(32, 32))
    _refused(
        ["measure", sim / "stamps.fits", sim / "cat.fits", "--psf", psf, "--metacal", *GALSIM],
        1,
        tmp_path / "o.fits",
        "psfnan.fits",
    )


def test_stamp_with_nan_pixels(sim, tmp_path):
    stamps = _copy_image(
        sim / "stamps.fits", tmp_path / "stamps.fits", nan_at=(10, 10)
    )  # the first stamp
    _refused(
        ["measure", stamps, sim / "cat.fits", "--psf", sim / "psf.fits", "--metacal", *GALSIM],
        1,
        tmp_path / "o.fits",
        "NaN",
    )
    # without --metacal, the stamp is flagged and the rest measured
    _ok(
        "measure",
        stamps,
        sim / "cat.fits",
        "--psf",
        sim / "psf.fits",
        *GALSIM,
        "-o",
        tmp_path / "plain.fits",
        "-q",
    )
    flags = _column(read_catalog(tmp_path / "plain.fits"), "flags")
    assert flags[0] != 0 and np.sum(flags != 0) < 5


def test_metacal_on_a_star_field_is_a_usage_error(sim, tmp_path):
    stars = _copy_image(sim / "psf.fits", tmp_path / "starfield_image-000-0.fits")
    _refused(
        ["measure", stars, "--psf", sim / "psf.fits", "--metacal", "--stamp-size", SIZE, *GALSIM],
        2,
        tmp_path / "o.fits",
        "--metacal",
    )


def test_simulate_metacal_equals_measure_on_the_written_stamps(tmp_path):
    """simulate --measure --metacal deconvolves each stamp by the PSF it was drawn with: the
    same columns as measure --metacal --psf on the written stamps (same seed), bit for bit
    (the PSF features of the target aside: its sigma from a float32 vs float64 PSF image)."""
    args = ["--n-cases", "2", "--n-realizations", "8", "--seed", "3", *GALSIM, "-q"]
    _ok(
        "simulate", CONFIG, "-o", tmp_path / "cat.fits", "--stamps", tmp_path / "stamps.fits", *args
    )
    _ok("simulate", CONFIG, "-o", tmp_path / "sim.fits", "--measure", "--metacal", *args)
    galsim.Gaussian(sigma=2.0).drawImage(nx=SIZE, ny=SIZE, scale=1.0).write(
        str(tmp_path / "psf.fits")
    )
    _ok(
        "measure",
        tmp_path / "stamps.fits",
        tmp_path / "cat.fits",
        "--psf",
        tmp_path / "psf.fits",
        "--metacal",
        "--seed",
        "3",
        *GALSIM,
        "-o",
        tmp_path / "m.fits",
        "-q",
    )
    sim, meas = read_catalog(tmp_path / "sim.fits"), read_catalog(tmp_path / "m.fits")
    cols = [c for c in sim.colnames if c.endswith(TYPES) and not c.startswith("psf_")]
    assert len(cols) == 5 * 11
    for c in cols:
        assert _same(sim[c], meas[c]), c
    np.testing.assert_allclose(
        _column(sim, "psf_adamom_sigma_noshear"),
        _column(meas, "psf_adamom_sigma_noshear"),
        rtol=1e-6,
    )


def test_evaluate_response_at_zero_shear_needs_a_metacal_set_of_10_cases(measured, tmp_path):
    """--response zero-shear: one error line and exit 1 on 4 cases or a plain catalog; the
    default falls back to the mean response and says so in the table."""
    result = _runner().invoke(megalut, ["evaluate", str(measured / "s_mc5.fits")], env=ENV)
    assert result.exit_code == 0
    assert "calibrated by (<R> + R_sel)^-1" in result.stdout
    for name, message in (("s_mc5", "at least 10 cases"), ("s_plain", "metacal catalog")):
        result = _runner().invoke(
            megalut,
            ["evaluate", str(measured / f"{name}.fits"), "--response", "zero-shear", "-q"],
            env=ENV,
        )
        assert result.exit_code == 1, result.stderr
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and message in lines[0] and "--response" in lines[0], lines


def test_evaluate_failures_as_a_selection(measured, tmp_path):
    """--failures selection: the response of the versions' means (the table says so, the JSON
    records it); on a plain catalog, or with --great3-truth, one error line."""
    js = tmp_path / "sel.json"
    result = _runner().invoke(
        megalut,
        ["evaluate", str(measured / "s_mc5.fits"), "--failures", "selection", "--json", str(js)],
        env=ENV,
    )
    assert result.exit_code == 0, (result.output, result.stderr)
    assert "each version's failures a selection" in result.stdout
    mc = json.loads(js.read_text())["metacal"]
    assert mc["failures"] == "selection" and mc["selection_response"]["unweighted"] is None
    assert np.all(np.isfinite(np.array(mc["response"]["unweighted"], dtype=float)))
    result = _runner().invoke(
        megalut,
        ["evaluate", str(measured / "s_plain.fits"), "--failures", "selection", "-q"],
        env=ENV,
    )
    assert result.exit_code == 1, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "metacal catalog" in lines[0] and "--failures" in lines[0], lines
    bad = _runner().invoke(
        megalut, ["evaluate", str(measured / "s_mc5.fits"), "--failures", "drop"], env=ENV
    )
    assert bad.exit_code == 2
