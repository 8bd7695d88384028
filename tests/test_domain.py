"""A model that knows its domain (issue 24): predict compares a catalog's measured
distributions with the model's training rows, shipped models by name, info tells both.

The trap of issue 24: 48-px stamps with noise sigma 3 and a Gaussian PSF of sigma 3 px,
given to the shipped fiducial model (64 px, noise sigma 1, PSF sigma 2), exited 0 with one
warning about the stamp size; now the skymad finding carries the numbers and --strict
refuses, with or without the catalog's setup cards.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import fitsio
import h5py
import numpy as np
import pytest

from megalut_cli.catalog import write_catalog
from megalut_cli.nn.domain import (
    QUANTILES,
    domain_findings,
    domain_record,
    fmt,
    model_domain,
)
from megalut_cli.nn.model import ShearModel
from megalut_cli.nn.shipped import SHIPPED_MODELS, shipped_model

ROOT = Path(__file__).resolve().parents[1]
VO = ROOT / "examples" / "fiducial" / "vo.toml"
#: The trap of issue 24, on the fiducial VO config.
TRAP = ("structure.stamp_size=48", "noise.sigma=3.0", "psf.sigma=3.0")


def _simulate(path: Path, overrides=(), n_cases=2, n_rea=150, seed=7, metacal=False) -> Path:
    from megalut_cli.sim.config import load_config
    from megalut_cli.sim.simulate import simulate

    simulate(
        load_config(VO, overrides, n_cases=n_cases, n_realizations=n_rea),
        path,
        measure=True,
        seed=seed,
        metacal=metacal,
    )
    return path


@pytest.fixture(scope="module")
def cats(tmp_path_factory):
    d = tmp_path_factory.mktemp("domain")
    trap = _simulate(d / "trap.fits", TRAP)
    # the same rows as a survey would deliver them: no setup cards, no CONFIG HDU
    t = fitsio.read(str(trap))
    write_catalog(
        d / "bare.fits", {k: t[k] for k in t.dtype.names if not k.startswith("tru_")}, fmt="survey"
    )
    own = _simulate(d / "own.fits", n_rea=200, seed=8)  # the fiducial population itself (VO)
    return {"dir": d, "trap": trap, "bare": d / "bare.fits", "own": own}


def _usable(path: Path, column: str) -> np.ndarray:
    t = fitsio.read(str(path), columns=[column, "flags"])
    v = t[column][t["flags"] == 0].astype(np.float64)
    return v[np.isfinite(v)]


def _skymad_message(path: Path) -> str:
    """The finding the trap must give, computed here from the catalog and the model file."""
    v = _usable(path, "skymad")
    rec = model_domain(ShearModel.load(shipped_model("fiducial")).provenance)["columns"]["skymad"][
        "q"
    ]
    q = dict(zip(QUANTILES, rec))
    med, q5, q95 = np.quantile(v, (0.5, 0.05, 0.95))
    return (
        f"skymad median {fmt(med)} (5–95 %: {fmt(q5)}–{fmt(q95)}), model trained on {fmt(q[0.01])}–"
        f"{fmt(q[0.99])} (1–99 %, median {fmt(q[0.5])})"
    )


def test_the_trap_warns_with_the_numbers_and_strict_refuses(runner, cli, cats):
    # the catalog's own noise is what was simulated: sigma 3, three times the model's
    assert 2.8 < np.median(_usable(cats["trap"], "skymad")) < 3.2
    out = cats["dir"] / "trap-shears.fits"
    r = runner.invoke(cli, ["predict", str(cats["trap"]), "--model", "fiducial", "-o", str(out)])
    assert r.exit_code == 0, r.stderr
    assert _skymad_message(cats["trap"]) in r.stderr
    assert "stamp size 48 px, model trained at 64 px" in r.stderr
    assert (
        "noise {'sigma': 1.0, 'type': 'gaussian'} vs {'sigma': 3.0, 'type': 'gaussian'}" in r.stderr
    )
    assert "snr median" not in r.stderr  # inside the model's range: no finding
    strict = cats["dir"] / "strict.fits"
    r = runner.invoke(
        cli, ["predict", str(cats["trap"]), "--model", "fiducial", "-o", str(strict), "--strict"]
    )
    assert r.exit_code == 1 and not strict.exists()
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "--strict" in lines[0] and _skymad_message(cats["trap"]) in lines[0]
    assert "stamp size 48 px" in lines[0] and "Traceback" not in r.stderr


def test_a_catalog_without_setup_cards_still_gets_the_column_findings(runner, cli, cats):
    header = fitsio.read_header(str(cats["bare"]), 1)
    assert "STAMPSZ" not in header and "CONFIG" not in fitsio.FITS(str(cats["bare"]))
    out = cats["dir"] / "bare-shears.fits"
    r = runner.invoke(cli, ["predict", str(cats["bare"]), "--model", "fiducial", "-o", str(out)])
    assert r.exit_code == 0, r.stderr
    assert _skymad_message(cats["bare"]) in r.stderr
    assert (
        "recorded setup differs" not in r.stderr and "stamp size" not in r.stderr
    )  # nothing recorded to compare
    r = runner.invoke(
        cli,
        [
            "predict",
            str(cats["bare"]),
            "--model",
            "fiducial",
            "-o",
            str(out),
            "--overwrite",
            "--strict",
        ],
    )
    assert r.exit_code == 1 and "skymad median" in r.stderr


def test_a_catalog_of_the_models_own_population_gives_no_finding(runner, cli, cats):
    from megalut_cli.catalog import catalog_info
    from megalut_cli.shear.predict import domain_report

    model = ShearModel.load(shipped_model("fiducial"))
    n, names, header = catalog_info(cats["own"])
    assert n == 400
    assert domain_report(model, cats["own"], colnames=names, header=header) == []
    out = cats["dir"] / "own-shears.fits"
    r = runner.invoke(
        cli, ["predict", str(cats["own"]), "--model", "fiducial", "-o", str(out), "--strict"]
    )
    assert r.exit_code == 0, r.stderr
    assert "finding" not in r.stderr and out.exists()


def test_domain_findings_rule():
    """The rule, arrays in: median outside 1-99 %, or more than 10 % outside 0.5-99.5 %."""
    rng = np.random.default_rng(3)
    domain = domain_record(
        {"skymad": rng.normal(1.0, 0.05, 20000), "snr": rng.lognormal(3, 0.5, 20000)}, stamp_size=64
    )
    assert domain["columns"]["skymad"]["n"] == 20000 and domain["stamp_size"] == 64
    same = {"skymad": rng.normal(1.0, 0.05, 1000), "snr": rng.lognormal(3, 0.5, 1000)}
    assert domain_findings(domain, same, 64) == []
    noisy = {**same, "skymad": rng.normal(3.0, 0.15, 1000)}
    (f,) = domain_findings(domain, noisy)
    assert f.item == "skymad" and f.message.startswith("skymad median 3")
    tail = dict(same)
    tail["snr"] = np.where(
        np.arange(1000) < 200, 500.0, same["snr"]
    )  # 20 % far above, median unchanged
    (f,) = domain_findings(domain, tail)
    assert f.item == "snr" and "20 % of the rows outside the model's 0.5–99.5 % range" in f.message
    few = dict(same)
    few["snr"] = np.where(np.arange(1000) < 50, 500.0, same["snr"])  # 5 %: within the rule
    assert domain_findings(domain, few) == []
    flagged = {**noisy, "flags": np.where(np.arange(1000) < 900, 1, 0)}  # usable rows only
    flagged["skymad"] = np.where(np.arange(1000) < 900, 3.0, 1.0)
    assert domain_findings(domain, flagged) == []
    (f,) = domain_findings(domain, same, 48)
    assert f.message == "stamp size 48 px, model trained at 64 px"


def test_training_records_the_domain_of_its_usable_rows(tmp_path, runner, cli):
    from sim_configs import write

    from megalut_cli.nn.fit import train_point
    from megalut_cli.nn.options import PointSpec
    from megalut_cli.sim.config import load_config
    from megalut_cli.sim.simulate import simulate

    cfg = write(tmp_path, replace={"n_cases = 3": "n_cases = 8"})
    tp = tmp_path / "tp.fits"
    simulate(load_config(cfg), tp, measure=True, seed=3)
    model = train_point(tp, tmp_path / "m.h5", PointSpec(hidden=[3], members=1, iterations=3))
    dom = model.provenance["domain"]
    assert dom["stamp_size"] == 24 and dom["source"] == "tp.fits"
    for col in ("skymad", "snr", "adamom_sigma", "adamom_flux"):
        np.testing.assert_allclose(
            dom["columns"][col]["q"], np.quantile(_usable(tp, col), QUANTILES), rtol=1e-12
        )
    # the recorded inputs name files; the path is never absolute (tmp_path is outside the current
    # folder)
    train = model.provenance["inputs"]["train"]
    assert train["name"] == "tp.fits" and not Path(train["path"]).is_absolute()
    # its own catalog is inside its domain; three times the noise is not
    r = runner.invoke(
        cli,
        [
            "predict",
            str(tp),
            "--model",
            str(tmp_path / "m.h5"),
            "-o",
            str(tmp_path / "s.fits"),
            "--strict",
        ],
    )
    assert r.exit_code == 0, r.stderr
    noisy = tmp_path / "noisy.fits"
    simulate(load_config(cfg, ("noise.sigma=3.0",)), noisy, measure=True, seed=4)
    r = runner.invoke(
        cli,
        ["predict", str(noisy), "--model", str(tmp_path / "m.h5"), "-o", str(tmp_path / "n.fits")],
    )
    assert r.exit_code == 0 and "skymad median" in r.stderr
    info = runner.invoke(cli, ["info", str(tmp_path / "m.h5")]).stdout
    assert (
        "domain: 1–99 % of" in info
        and "stamp 24 px" in info
        and "PSF: gaussian; sigma 1.5 px" in info
    )


def test_a_constant_training_psf_is_in_the_domain_and_a_wider_psf_is_a_finding(
    tmp_path, cats, runner, cli
):
    """Simulated training rows carry no PSF measurement: a constant PSF's size enters the domain
    from the config, drawn with the pixel as `measure --psf` measures it (also in the shipped
    models), so a survey catalog measured with a wider PSF is a finding even without setup cards."""
    import galsim

    from megalut_cli.sim.psf import measured_psf_sigma

    expected = galsim.hsm.FindAdaptiveMom(
        galsim.Gaussian(sigma=2.0).drawImage(nx=64, ny=64, scale=1.0)
    ).moments_sigma
    assert measured_psf_sigma({"type": "gaussian", "sigma": 2.0}, 64) == pytest.approx(
        expected, rel=1e-12
    )
    assert measured_psf_sigma({"type": "field"}, 64) is None  # varies: nothing recorded
    dom = model_domain(ShearModel.load(shipped_model("fiducial")).provenance)
    entry = dom["columns"]["psf_adamom_sigma"]
    assert (
        entry["q"] == [pytest.approx(expected, rel=1e-12)] * len(QUANTILES)
        and entry["tolerance"] == 0.01
    )
    t = fitsio.read(str(cats["bare"]))
    base = {k: t[k] for k in t.dtype.names}
    for sigma, found in (
        (expected, False),
        (1.008 * expected, False),
        (1.02 * expected, True),
        (3.03, True),
    ):
        cols = {**base, "psf_adamom_sigma": np.full(len(t), sigma)}
        names = [f.item for f in domain_findings(dom, cols)]
        assert ("psf_adamom_sigma" in names) is found, (sigma, names)
    survey = tmp_path / "survey.fits"  # the trap as a survey delivers it: measured PSF, no cards
    psf3 = measured_psf_sigma({"type": "gaussian", "sigma": 3.0}, 48)
    write_catalog(survey, {**base, "psf_adamom_sigma": np.full(len(t), psf3)}, fmt="survey")
    r = runner.invoke(
        cli, ["predict", str(survey), "--model", "fiducial", "-o", str(tmp_path / "s.fits")]
    )
    assert r.exit_code == 0, r.stderr
    assert (
        f"psf_adamom_sigma median {fmt(psf3)} px" in r.stderr
        and f"model trained at {fmt(expected)} px (±1 %)" in r.stderr
    )
    # a model trained today records its own constant PSF the same way
    from sim_configs import write

    from megalut_cli.nn.fit import train_point
    from megalut_cli.nn.options import PointSpec
    from megalut_cli.sim.config import load_config
    from megalut_cli.sim.simulate import simulate

    tp = tmp_path / "tp.fits"
    simulate(
        load_config(write(tmp_path, replace={"n_cases = 3": "n_cases = 8"})),
        tp,
        measure=True,
        seed=3,
    )
    model = train_point(tp, tmp_path / "m.h5", PointSpec(hidden=[3], members=1, iterations=3))
    got = model.provenance["domain"]["columns"]["psf_adamom_sigma"]["q"][0]
    assert got == pytest.approx(
        measured_psf_sigma({"type": "gaussian", "sigma": 1.5}, 24), rel=1e-12
    )


def test_metacal_catalogs_are_compared_on_their_noshear_columns(runner, cli, tmp_path):
    cat = _simulate(tmp_path / "mc.fits", n_cases=1, n_rea=40, metacal=True)
    # the noshear noise is lower than the plain one: comparing the wrong columns would be a finding
    assert np.median(_usable(cat, "skymad")) > 1.5 * np.median(_usable(cat, "skymad_noshear"))
    r = runner.invoke(
        cli,
        [
            "predict",
            str(cat),
            "--model",
            "fiducial-metacal",
            "-o",
            str(tmp_path / "s.fits"),
            "--strict",
        ],
    )
    assert r.exit_code == 0, r.stderr
    dom = model_domain(ShearModel.load(shipped_model("fiducial-metacal")).provenance)
    assert dom["version"] == "noshear" and "psf_adamom_sigma" in dom["columns"]


def test_models_by_name(runner, cli, cats):
    out = cats["dir"] / "named.fits"
    r = runner.invoke(cli, ["predict", str(cats["own"]), "--model", "fiducial-1e6", "-o", str(out)])
    assert r.exit_code == 0, r.stderr
    assert fitsio.read_header(str(out), 1)["MODEL"] == "fiducial-1e6.h5"
    r = runner.invoke(
        cli, ["predict", str(cats["own"]), "--model", "fidutial", "-o", str(out), "--overwrite"]
    )
    assert (
        r.exit_code == 2
        and "nor a shipped model (shipped: fiducial, fiducial-1e6, fiducial-metacal, "
        "fiducial-metacal-d4, fiducial-d4)"
        in r.stderr
    )
    r = runner.invoke(cli, ["info", "fidutial"])
    assert r.exit_code == 2 and "fiducial-metacal" in r.stderr
    r = runner.invoke(cli, ["info", "--models"])
    assert r.exit_code == 0, r.stderr
    lines = r.stdout.splitlines()
    assert [line.split()[:2] for line in lines] == [
        ["fiducial", "simulation"],
        ["fiducial-1e6", "simulation"],
        ["fiducial-metacal", "metacal"],
        ["fiducial-metacal-d4", "metacal+d4"],
        ["fiducial-d4", "simulation+d4"],
    ]
    assert all(
        "gaussian PSF sigma 2.0; gaussian noise sigma 1.0, stamp 64 px" in line for line in lines
    )
    js = json.loads(runner.invoke(cli, ["info", "--models", "--json"]).stdout)
    assert [m["name"] for m in js] == list(SHIPPED_MODELS) and js[2]["shear_mode"] == "metacal"
    assert runner.invoke(cli, ["info", "--models", "fiducial"]).exit_code == 2
    assert runner.invoke(cli, ["info"]).exit_code == 2


def test_info_shows_the_population_and_the_domain(runner, cli):
    r = runner.invoke(cli, ["info", "fiducial"])
    assert r.exit_code == 0, r.stderr
    text = r.stdout
    for words in (
        "weights (tw.fits): Sersic galaxies (n grid, rad U(2.0, 8.0) px)",
        "galaxies: sersic; sersicn grid 1 to 4 step 0.1; rad uniform 2 to 8 px; sb uniform 1 to 15",
        "ellipticity Rayleigh of mode 0.2 in 0 to 0.6",
        "PSF: gaussian; sigma 2 px",
        "noise: gaussian; sigma 1 adu",
        "stamp size: 64 px",
        "point estimates (tp.fits): the same population",
    ):
        assert words in text, words
    (domain,) = [line for line in text.splitlines() if line.startswith("domain: ")]
    assert (
        "skymad 0.835–1.17" in domain
        and "stamp 64 px" in domain
        and "models/record_domain.py" in domain
    )
    assert "/work/exp12" not in text  # where it was made (its path here heads the first line)
    js = json.loads(runner.invoke(cli, ["info", "fiducial", "--json"]).stdout)
    assert (
        js["domain"]["stamp_size"] == 64 and js["training_sets"][0]["setup"]["psf"]["sigma"] == 2.0
    )


#: Digest of everything in the shipped files but /provenance, recorded from the files before
#: their domains were added (commit 6a47fb0): the networks did not change.
NETWORK_DIGESTS = {
    "fiducial": "e2b709eb3525818f379ac613722afce73854b12f14d051289d791ebff7d01165",
    "fiducial-1e6": "a56e2ec5c490e4f4b8f4b200d38118eb0ebd4c10b956e3bd78bd7a5792d4364c",
    "fiducial-metacal": "6f4acc532a3cf8709d9bebfcad87cd0494869bbe6250fc5825598142a331310a",
    # the networks of fiducial-metacal (the same datasets), averaged over the pixel grid's
    # symmetries (root attribute symmetry = "d4")
    "fiducial-metacal-d4": "6322d9ea6a9cf11e18c8c24196194d2e54d20d520bf871a99074c8cae8523f46",
    "fiducial-d4": "f4b85fafc7d88fcd1cff7cf3886d650b8431f52d6948fcec2c32d2cfcc1e9c6b",
}


def _network_digest(path: Path) -> str:
    h = hashlib.sha256()
    with h5py.File(path, "r") as f:

        def visit(name: str, obj) -> None:
            if name == "provenance" or name.startswith("provenance/"):
                return
            h.update(name.encode())
            for k in sorted(obj.attrs):
                h.update(k.encode())
                h.update(repr(obj.attrs[k]).encode())
            if isinstance(obj, h5py.Dataset):
                a = obj[()]
                h.update(str(a.dtype).encode())
                h.update(np.ascontiguousarray(a).tobytes())

        for k in sorted(f.attrs):
            h.update(k.encode())
            h.update(repr(f.attrs[k]).encode())
        f.visititems(visit)
    return h.hexdigest()


@pytest.mark.parametrize("name", sorted(SHIPPED_MODELS))
def test_shipped_networks_are_unchanged_and_carry_no_absolute_path(name):
    path = shipped_model(name)
    assert _network_digest(path) == NETWORK_DIGESTS[name]
    prov = ShearModel.load(path).provenance
    assert model_domain(prov)["derived"]["script"] == "models/record_domain.py"
    text = json.dumps(prov)
    assert '"/' not in text and " /" not in text  # no absolute path, in inputs or command lines


def test_megalut_run_logs_the_findings_of_its_predict_steps(tmp_path, caplog):
    """Each predict step goes through predict_catalog: the reference model (fiducial, 64 px)
    on the tiny pipeline's 24-px VO set is reported; the pipeline's own model on it is not."""
    import logging

    from pipeline_configs import write_pipeline

    from megalut_cli.pipeline.file import load_pipeline
    from megalut_cli.pipeline.run import run_pipeline

    pipe = load_pipeline(write_pipeline(tmp_path), ['reference.model="fiducial"'])
    with caplog.at_level(logging.WARNING, logger="megalut_cli.shear.predict"):
        run_pipeline(pipe, tmp_path / "work")
    found = [r.getMessage() for r in caplog.records if r.name == "megalut_cli.shear.predict"]
    assert any("vo.fits: stamp size 24 px, model trained at 64 px" in m for m in found), found
    assert any("against the training domain of fiducial.h5" in m for m in found)
    assert not any("of model.h5" in m for m in found), found


def test_a_large_catalog_is_sampled_chunk_by_chunk(cats, monkeypatch):
    """Above MAX_DOMAIN_ROWS rows the check keeps every k-th row, read chunk by chunk, and
    counts every row in the same pass."""
    from megalut_cli.catalog import catalog_info
    from megalut_cli.shear import predict

    monkeypatch.setattr(predict, "MAX_DOMAIN_ROWS", 7)
    monkeypatch.setattr(predict, "DOMAIN_CHUNK_ROWS", 13)
    domain = model_domain(ShearModel.load(shipped_model("fiducial")).provenance)
    n, names, _ = catalog_info(cats["trap"])
    features = ["adamom_g1", "adamom_sigma"]
    read = predict.domain_rows(cats["trap"], features, names, domain=domain, n_rows=n)
    table = fitsio.read(str(cats["trap"]))
    step = -(-n // 7)
    got = read.columns
    assert sorted(got) == ["adamom_flux", "adamom_sigma", "flags", "skymad", "snr"]
    for c, values in got.items():
        assert np.array_equal(values, table[c][::step], equal_nan=True), c
    flagged = table["flags"] != 0
    usable = ~flagged & np.isfinite(table["adamom_g1"]) & np.isfinite(table["adamom_sigma"])
    assert (read.counts.n_rows, read.counts.n_flagged) == (n, flagged.sum()) and n > 13
    assert read.counts.n_usable == usable.sum()
    whole = predict.domain_rows(cats["trap"], features, names, domain=domain, n_rows=n - 1)
    assert whole.counts == read.counts  # counts never sampled
    without = predict.domain_rows(cats["trap"], features, names)
    assert without.counts == read.counts and without.columns == {}


def test_predict_reads_the_catalogs_rows_once_before_predicting(cats, monkeypatch, tmp_path):
    """The domain check counts the rows and takes the domain's columns in one pass; the
    prediction is the second and last pass over the rows."""
    from megalut_cli import catalog
    from megalut_cli.shear import predict

    passes = []

    def chunks(path, *args, **kwargs):
        passes.append(kwargs.get("columns"))
        return catalog.iter_catalog(path, *args, **kwargs)

    def whole(path, columns=None, *args, **kwargs):
        passes.append(columns)
        return catalog.read_catalog_columns(path, columns, *args, **kwargs)

    monkeypatch.setattr(predict, "iter_catalog", chunks)
    monkeypatch.setattr(predict, "read_catalog_columns", whole, raising=False)
    out = tmp_path / "shears.fits"
    predict.predict_catalog(cats["own"], shipped_model("fiducial"), out)
    assert len(passes) == 2 and passes[1] is None, passes
    assert {"adamom_g1", "flags", "skymad", "snr"} <= set(passes[0])
