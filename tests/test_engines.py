"""The fast and galsim stamp engines of `simulate` and `measure`, end to end.

The renderer and the adaptive-moment kernel are tested against GalSim on their own in
test_sim_render.py and test_measure_adamom.py; here the whole `simulate` path (structure,
offsets, PSF truth, noise, ordering, work units) must give the same stamps and features
with either engine, and the fast engine's outputs must not depend on -j or batch size.
"""

from __future__ import annotations

import json
from pathlib import Path

import fitsio
import numpy as np
import pytest
from helpers import assert_ok, error_line
from sim_configs import TINY, write

from megalut_cli.catalog import read_catalog

FEATURES = (
    "adamom_flux",
    "adamom_g1",
    "adamom_g2",
    "adamom_sigma",
    "adamom_rho4",
    "adamom_x",
    "adamom_y",
)

#: Noiseless stamps, fast engine against galsim engine: largest pixel difference as a fraction
#: of the stamp's peak. Achieved: 1.8e-7 here (3.7e-7 over the render grid of test_sim_render.py).
RENDER_TOLERANCE = 1e-6
#: Features of those noiseless stamps (flags identical): relative for flux and sigma, absolute
#: for the others. Achieved: 1.1e-7 (flux, sigma), 1.9e-8 (g1, g2), 3.6e-8 (rho4), 5.3e-8 (x, y).
NOISELESS_FEATURE_TOLERANCE = {
    "adamom_flux": 5e-7,
    "adamom_sigma": 5e-7,
    "adamom_g1": 1e-7,
    "adamom_g2": 1e-7,
    "adamom_rho4": 1.5e-7,
    "adamom_x": 2.5e-7,
    "adamom_y": 2.5e-7,
}
RELATIVE = ("adamom_flux", "adamom_sigma")
#: `measure --engine fast|galsim` on the same stamps: every flag and every other column
#: identical, the outputs GalSim stores as float32 (flux, g1, g2, sigma) bit for bit, and rho4
#: and the centroid (float64) within this. Achieved: 2.8e-14 (x, y), 1.2e-14 (rho4).
HSM_FLOAT64_TOLERANCE = 1.5e-13
HSM_FLOAT64 = ("adamom_rho4", "adamom_x", "adamom_y")
#: Correlated noise (GalSim's in both engines): largest pixel difference as a fraction of the
#: largest noisy pixel. Achieved: 1.1e-7.
CORRELATED_TOLERANCE = 5e-7


def _simulate(runner, cli, cfg: Path, out: Path, engine: str, *extra: str) -> None:
    assert_ok(
        runner.invoke(
            cli, ["simulate", str(cfg), "-o", str(out), "--engine", engine, "--seed", "7", *extra]
        )
    )


def _stamps(path: Path, size: int, n: int) -> np.ndarray:
    image = fitsio.read(str(path))
    n_x = image.shape[1] // size
    return np.array(
        [
            image[
                (k // n_x) * size : (k // n_x + 1) * size, (k % n_x) * size : (k % n_x + 1) * size
            ]
            for k in range(n)
        ]
    )


def test_noiseless_stamps_equal_with_either_engine(runner, cli, tmp_path: Path) -> None:
    """Same config, same seed, no noise: the fast engine's stamps are GalSim's to 1e-6 of the
    peak."""
    text = TINY.replace('type = "gaussian"\nsigma = 1.0', 'type = "none"').replace(
        "n_cases = 3", "n_cases = 6"
    )
    cfg = write(tmp_path, text)
    for engine in ("fast", "galsim"):
        _simulate(
            runner,
            cli,
            cfg,
            tmp_path / f"{engine}.fits",
            engine,
            "--stamps",
            str(tmp_path / f"{engine}-st.fits"),
        )
    fast, ref = (_stamps(tmp_path / f"{e}-st.fits", 24, 24) for e in ("fast", "galsim"))
    peak = ref.max(axis=(1, 2))
    assert (peak > 0).all()
    err = np.abs(fast - ref).max(axis=(1, 2)) / peak
    assert err.max() <= RENDER_TOLERANCE, err.max()
    a, b = read_catalog(tmp_path / "fast.fits"), read_catalog(tmp_path / "galsim.fits")
    for name in a.colnames:  # the truth does not depend on the engine
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    assert fitsio.read_header(str(tmp_path / "fast.fits"), 1)["ENGINE"].strip() == "fast"


def test_noiseless_features_agree(runner, cli, tmp_path: Path) -> None:
    """simulate --measure without noise: every feature and flag the same with either engine."""
    text = TINY.replace('type = "gaussian"\nsigma = 1.0', 'type = "none"').replace(
        "n_cases = 3", "n_cases = 10"
    )
    cfg = write(tmp_path, text)
    for engine in ("fast", "galsim"):
        _simulate(runner, cli, cfg, tmp_path / f"{engine}.fits", engine, "--measure")
    a, b = read_catalog(tmp_path / "fast.fits"), read_catalog(tmp_path / "galsim.fits")
    np.testing.assert_array_equal(a["flags"], b["flags"])
    ok = a["flags"] == 0
    assert ok.mean() > 0.9
    for name in FEATURES:
        # the stamps differ by ~2e-7 of the peak, and so do the moments
        tol = NOISELESS_FEATURE_TOLERANCE[name]
        rtol, atol = (tol, 0) if name in RELATIVE else (0, tol)
        np.testing.assert_allclose(a[name][ok], b[name][ok], rtol=rtol, atol=atol, err_msg=name)


def test_fast_engine_noise_has_the_requested_level(runner, cli, tmp_path: Path) -> None:
    """The fast engine's Gaussian noise: sigma as asked (skymad of 40 stamps), per-stamp seeds."""
    cfg = write(
        tmp_path, TINY.replace("sigma = 1.0", "sigma = 2.5").replace("n_cases = 3", "n_cases = 10")
    )
    _simulate(runner, cli, cfg, tmp_path / "f.fits", "fast", "--measure")
    cat = read_catalog(tmp_path / "f.fits")
    skymad = np.asarray(cat["skymad"])
    # edge pixels are essentially pure noise on these stamps: 92 pixels each, 40 stamps
    assert abs(np.median(skymad) / 2.5 - 1) < 0.05
    assert len(np.unique(skymad)) == len(skymad)  # independent realizations


def test_ccd_noise_statistics_match_galsim() -> None:
    """add_batch's CCD noise has GalSim's CCDNoise mean and variance (Poisson of source + sky,
    read noise)."""
    import galsim

    from megalut_cli.sim.noise import StampNoise

    noise = StampNoise("ccd", sky=40.0, gain=2.0, read_noise=3.0)
    clean = np.full((64, 32, 32), 10.0, dtype=np.float32)
    fast = clean.copy()
    noise.add_batch(fast, np.arange(1, 65))
    ref = np.empty_like(clean)
    for i in range(len(clean)):
        image = galsim.ImageF(clean[i].copy())
        noise.add(image, i + 1)
        ref[i] = image.array
    expected_var = (10.0 + 40.0) / 2.0 + (3.0 / 2.0) ** 2
    for sample in (fast, ref):
        assert abs(sample.mean() - 10.0) < 0.05
        assert abs(sample.var() / expected_var - 1) < 0.03


def test_fast_engine_independent_of_workers_and_batches(
    runner, cli, tmp_path: Path, monkeypatch
) -> None:
    """-j 1, -j 2 and a measuring batch of 5 stamps: identical catalogs with the fast engine."""
    from megalut_cli.sim import draw

    cfg = write(
        tmp_path,
        TINY.replace("n_cases = 3", "n_cases = 7").replace(
            "n_realizations = 4", "n_realizations = 6"
        ),
    )
    _simulate(runner, cli, cfg, tmp_path / "j1.fits", "fast", "--measure")
    _simulate(runner, cli, cfg, tmp_path / "j2.fits", "fast", "--measure", "-j", "2")
    monkeypatch.setattr(draw, "MEASURE_BATCH", 5)
    _simulate(runner, cli, cfg, tmp_path / "b5.fits", "fast", "--measure")
    ref = read_catalog(tmp_path / "j1.fits")
    for other in ("j2.fits", "b5.fits"):
        cat = read_catalog(tmp_path / other)
        for name in ref.colnames:
            np.testing.assert_array_equal(
                np.asarray(cat[name]), np.asarray(ref[name]), err_msg=f"{other}: {name}"
            )


def test_measure_engines_agree_on_a_stamp_grid(runner, cli, tmp_path: Path) -> None:
    """`measure --engine fast|galsim` on the same noisy stamps: same flags, float32 features bit
    for bit, rho4 and centroid within 1.5e-13."""
    cfg = write(tmp_path, TINY.replace("n_cases = 3", "n_cases = 20"))
    _simulate(
        runner, cli, cfg, tmp_path / "cat.fits", "fast", "--stamps", str(tmp_path / "st.fits")
    )
    for engine in ("fast", "galsim"):
        assert_ok(
            runner.invoke(
                cli,
                [
                    "measure",
                    str(tmp_path / "st.fits"),
                    str(tmp_path / "cat.fits"),
                    "-o",
                    str(tmp_path / f"m-{engine}.fits"),
                    "--engine",
                    engine,
                ],
            )
        )
    a, b = read_catalog(tmp_path / "m-fast.fits"), read_catalog(tmp_path / "m-galsim.fits")
    # (a stamp still unsettled after hundreds of iterations may end either way,
    # test_measure_adamom.py; none of these 80 stamps does)
    np.testing.assert_array_equal(a["flags"], b["flags"])
    assert set(a.colnames) == set(b.colnames)
    for name in a.colnames:
        if name in HSM_FLOAT64:
            np.testing.assert_allclose(
                a[name], b[name], rtol=0, atol=HSM_FLOAT64_TOLERANCE, err_msg=name
            )
        else:
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    assert fitsio.read_header(str(tmp_path / "m-galsim.fits"), 1)["MENGINE"].strip() == "galsim"


def test_real_galaxies_fall_back_to_galsim_with_one_log_line(runner, cli, tmp_path: Path) -> None:
    """profile = "real": GalSim draws the stamps (one log line says so); features still come out."""
    from megalut_cli.sim import render

    assert render.can_render("sersic") and render.can_render("gaussian")
    assert not render.can_render("real")
    rgc = (
        Path(__file__).resolve().parents[1]
        / "examples/data/cosmos/real_galaxy_catalog_26_extension_example.fits"
    )
    text = TINY.replace(
        'profile = "sersic"\nsersicn = {type = "grid", min = 1.0, max = 2.0, step = 0.5}\n'
        'rad = {type = "uniform", min = 1.5, max = 3.0}\n'
        'sb = {type = "uniform", min = 5.0, max = 15.0}\n'
        'ellipticity = {type = "rayleigh", mode = 0.2, min = 0.0, max = 0.6}\n',
        f'profile = "real"\nreal_catalog = "{rgc}"\npixel_scale = 0.2\nreal_select = "MAG < 22"\n'
        "flux = 100.0\n",
    )
    text = text.replace("n_cases = 3", "n_cases = 1").replace(
        "n_realizations = 4", "n_realizations = 2"
    )
    cfg = write(tmp_path, text)
    r = runner.invoke(
        cli, ["simulate", str(cfg), "-o", str(tmp_path / "r.fits"), "--measure", "--seed", "7"]
    )
    assert_ok(r)
    lines = [line for line in r.stderr.splitlines() if "drawn by GalSim" in line]
    assert len(lines) == 1 and "'real'" in lines[0]
    assert (read_catalog(tmp_path / "r.fits")["flags"] == 0).all()


def test_bad_engine_is_a_usage_error(runner, cli, tmp_path: Path) -> None:
    r = runner.invoke(
        cli, ["simulate", str(write(tmp_path)), "-o", str(tmp_path / "x.fits"), "--engine", "gpu"]
    )
    assert r.exit_code == 2 and "'gpu' is not one of 'fast', 'galsim'" in (
        r.output + getattr(r, "stderr", "")
    )
    assert not (tmp_path / "x.fits").exists()


@pytest.mark.parametrize("engine", ["fast", "galsim"])
def test_an_fft_beyond_the_cap_stops_either_engine(runner, cli, tmp_path: Path, engine) -> None:
    """gsparams.maximum_fft_size is a cap in both engines (GalSim 2.7+ alone would warn and
    draw): one line naming the case, exit 1, nothing written."""
    cfg = write(tmp_path, replace={"[psf]": "[gsparams]\nmaximum_fft_size = 16\n\n[psf]"})
    out, stamps = tmp_path / "c.fits", tmp_path / "s.fits"
    r = runner.invoke(
        cli, ["simulate", str(cfg), "-o", str(out), "--stamps", str(stamps), "--engine", engine]
    )
    error_line(r, 1, "case 0", "maximum_fft_size")
    assert not out.exists() and not stamps.exists()


def test_pipeline_engine_key_is_validated() -> None:
    from megalut_cli.errors import ConfigError
    from megalut_cli.pipeline.file import load_pipeline

    assert load_pipeline(None, ["engine='galsim'"]).engine == "galsim"
    assert load_pipeline(None).engine == "fast"
    with pytest.raises(ConfigError, match="engine"):
        load_pipeline(None, ["engine='gpu'"])


@pytest.mark.slow
def test_training_on_either_engine_gives_the_same_biases(runner, cli, tmp_path: Path) -> None:
    """Science unchanged: the default pipeline at a quarter size, run with each engine (same
    config, same seeds: same galaxies, different noise realizations), then each model on
    both validation sets.

    * Same networks, either engine's validation set: the same m and c within 3 combined
      errors (what the engine changes in the data the estimates see).
    * Networks trained on either engine's sets, one validation set: the same m within 3
      combined errors. (c is only printed: the additive bias of the point estimates moves
      from one training to the next by more than the fit error, whatever the engine; three
      default runs with three noise streams gave unweighted c1 from -1.1e-3 to +1.1e-3,
      each quoted at 5e-4.)
    """
    for engine in ("fast", "galsim"):
        assert_ok(
            runner.invoke(
                cli,
                [
                    "run",
                    "scale=0.25",
                    f"engine='{engine}'",
                    "--workdir",
                    str(tmp_path / engine),
                    "-j",
                    "2",
                ],
            )
        )
    ev: dict[tuple[str, str], dict] = {}
    for model in ("fast", "galsim"):
        for data in ("fast", "galsim"):
            stem = tmp_path / f"{model}-on-{data}"
            assert_ok(
                runner.invoke(
                    cli,
                    [
                        "predict",
                        str(tmp_path / data / "vo.fits"),
                        "--model",
                        str(tmp_path / model / "model.h5"),
                        "-o",
                        f"{stem}.fits",
                    ],
                )
            )
            assert_ok(runner.invoke(cli, ["evaluate", f"{stem}.fits", "--json", f"{stem}.json"]))
            ev[model, data] = json.loads(Path(f"{stem}.json").read_text())

    def close(a: dict, b: dict, q: str) -> bool:
        return abs(a[q] - b[q]) < 3 * np.hypot(a[f"{q}_err"], b[f"{q}_err"])

    for kind in ("unweighted", "weighted"):
        for comp in ("g1", "g2"):
            fit = {k: v[kind][comp] for k, v in ev.items()}
            for k, f in fit.items():
                print(
                    f"{kind} {comp} model {k[0]} on {k[1]}: m = {f['m']:+.2e} ± {f['m_err']:.1e}, "
                    f"c = {f['c']:+.2e} ± {f['c_err']:.1e}"
                )
            for model in ("fast", "galsim"):
                for q in ("m", "c"):
                    assert close(fit[model, "fast"], fit[model, "galsim"], q), (
                        kind,
                        comp,
                        "model",
                        model,
                        q,
                    )
            for data in ("fast", "galsim"):
                assert close(fit["fast", data], fit["galsim", data], "m"), (
                    kind,
                    comp,
                    "data",
                    data,
                )


def test_correlated_noise_is_galsims_with_the_fast_engine(runner, cli, tmp_path: Path) -> None:
    """Correlated noise goes through GalSim in both engines, from the same per-stamp seeds:
    the fast engine's noisy stamps equal the galsim engine's up to the rendering tolerance."""
    from sim_configs import CF_FILE

    text = TINY.replace(
        'type = "gaussian"\nsigma = 1.0',
        f'type = "correlated"\nsigma = 1.0\ncorrelation = "{CF_FILE}"\npixel_scale = 1.0',
    )
    cfg = write(tmp_path, text)
    for engine in ("fast", "galsim"):
        _simulate(
            runner,
            cli,
            cfg,
            tmp_path / f"{engine}.fits",
            engine,
            "--stamps",
            str(tmp_path / f"{engine}-st.fits"),
        )
    fast, ref = (_stamps(tmp_path / f"{e}-st.fits", 24, 12) for e in ("fast", "galsim"))
    assert np.abs(fast - ref).max() <= CORRELATED_TOLERANCE * np.abs(ref).max()
    assert fast.std() > 0.5  # the noise is there


def test_knots_fall_back_to_galsim(runner, cli, tmp_path: Path) -> None:
    """A Sersic with knots is not a single Sersic: the fast engine hands it to GalSim."""
    cfg = write(tmp_path, TINY.replace("angle = {", "knots = 10\nknots_fraction = 0.3\nangle = {"))
    r = runner.invoke(
        cli,
        [
            "simulate",
            str(cfg),
            "-o",
            str(tmp_path / "k.fits"),
            "--stamps",
            str(tmp_path / "ks.fits"),
            "--seed",
            "3",
        ],
    )
    assert_ok(r)
    assert "with knots" in r.stderr
    assert_ok(
        runner.invoke(
            cli,
            [
                "simulate",
                str(cfg),
                "-o",
                str(tmp_path / "g.fits"),
                "--stamps",
                str(tmp_path / "gs.fits"),
                "--seed",
                "3",
                "--engine",
                "galsim",
            ],
        )
    )
    a, b = (_stamps(tmp_path / f, 24, 12) for f in ("ks.fits", "gs.fits"))
    # same GalSim drawing; only the noise generator differs: the noiseless parts agree in the mean
    assert abs(float(a.mean() - b.mean())) < 0.05
