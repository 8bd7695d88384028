"""The device backend (megalut_cli.gpu) against the CPU fast engine, on JAX's CPU mode.

Tolerances (issue 13): noiseless stamps within 1e-5 of the peak pixel over the render test
grid; on noisy stamps the same adaptive-moment failures and features within 1e-6; the same
noise (bit for bit); training reaches the same validation cost (relative 1e-6).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

jax = pytest.importorskip("jax")

from helpers import toy_cases, toy_task  # noqa: E402
from render_cases import RENDER_CASES, random_galaxies, render_setup, write_starfield  # noqa: E402

from megalut_cli.engine import resolve_device  # noqa: E402
from megalut_cli.errors import MegalutError  # noqa: E402
from megalut_cli.gpu import PLATFORM_ENV  # noqa: E402

PEAK_TOLERANCE = 1e-5
FEATURE_TOLERANCE = 1e-6


@pytest.fixture(autouse=True)
def _jax_cpu_is_the_device(monkeypatch):
    monkeypatch.setenv(PLATFORM_ENV, "cpu")


def test_device_resolution(monkeypatch) -> None:
    assert resolve_device("cpu") == "cpu"
    assert resolve_device("gpu") == "gpu"  # JAX's CPU mode counts as the device here
    monkeypatch.setenv(PLATFORM_ENV, "no-such-platform")
    assert resolve_device("auto") == "cpu"
    with pytest.raises(MegalutError, match="^device gpu: JAX finds no no-such-platform device"):
        resolve_device("gpu")


def test_noise_is_the_cpu_stream_bit_for_bit() -> None:
    from megalut_cli.gpu.noise import add_gaussian_noise as device_noise
    from megalut_cli.gpu.noise import standard_normals as device_normals
    from megalut_cli.sim.normals import add_gaussian_noise, standard_normals

    seeds = np.array([0, 1, 2, 12345, 2**40 + 17, 2**62 + 3] + list(range(1000, 1026)), dtype=np.int64)
    ref = standard_normals(seeds, 1024)
    got = np.asarray(device_normals(jax.numpy.asarray(seeds), 1024))
    np.testing.assert_array_equal(got, ref)
    assert (np.abs(ref) > 3.6541528853610088).any()  # the tail and
    stamps = np.random.default_rng(0).normal(size=(len(seeds), 32, 32)).astype(np.float32)
    sigma = np.full(len(seeds), 1.7)
    expect = stamps.copy()
    add_gaussian_noise(expect, seeds, 1.7)
    np.testing.assert_array_equal(np.asarray(device_noise(stamps, seeds, sigma)), expect)


@pytest.fixture(scope="module")
def starfield(tmp_path_factory):

    return str(write_starfield(tmp_path_factory.mktemp("gpu") / "stars.fits"))


def _device_draw(renderer, psf, key, method, gals):
    from megalut_cli.gpu import render as grender

    plan = renderer.plan(psf, key, method, **gals)
    eparams, eint, coef = grender.profile_arrays(plan.profiles)
    out = np.empty((len(plan.n_fft), renderer.stamp_size, renderer.stamp_size), np.float32)
    for nf, nk in set(zip(plan.n_fft.tolist(), plan.n_k.tolist())):
        sel = np.flatnonzero((plan.n_fft == nf) & (plan.n_k == nk))
        pad = np.concatenate([sel, np.full(16 - len(sel), sel[0])])  # one batch shape per grid
        kpsf = renderer.psf_kimage(psf, key, method, nf, nk)
        out[sel] = np.asarray(grender.render_batch(
            kpsf, plan.amat[pad], plan.flux[pad], plan.shift_x[pad], plan.shift_y[pad], plan.table[pad],
            eparams, eint, coef, *grender.fold_indices(nf, nk), n_fft=nf, n_k=nk, size=renderer.stamp_size))[:len(sel)]
    return out


#: Cases of tests/test_sim_render.py in the default run: the fiducial PSF, a small Moffat
#: (Nk > N: GalSim's wrapping), a star image (no_pixel). The
#: whole grid (each new FFT grid costs a compilation on JAX's CPU mode) runs with -m slow.
QUICK_CASES = (0, 3, 8)


def _check_render_cases(profile: str, cases, starfield: str) -> None:

    from megalut_cli.sim.render import StampRenderer

    for case in cases:

        psf, method, gsparams, size, m = render_setup(RENDER_CASES[case], starfield)
        gals = random_galaxies(100 + case, m if profile == "sersic" else max(3, m // 3), profile)
        renderer = StampRenderer(size, gsparams)
        ref = renderer.draw(psf, ("psf", case), method, **gals)
        got = _device_draw(renderer, psf, ("psf", case), method, gals)
        err = np.abs(got - ref).max(axis=(1, 2)) / np.abs(ref).max(axis=(1, 2))
        assert err.max() <= PEAK_TOLERANCE, (case, err.max())


@pytest.mark.parametrize("profile", ["sersic", "gaussian"])
def test_noiseless_stamps_equal_cpu(profile, starfield) -> None:
    _check_render_cases(profile, QUICK_CASES, starfield)


@pytest.mark.slow
@pytest.mark.parametrize("profile", ["sersic", "gaussian"])
def test_noiseless_stamps_equal_cpu_over_the_render_grid(profile, starfield) -> None:
    """Every PSF, grid and galaxy of tests/test_sim_render.py."""

    _check_render_cases(profile, range(len(RENDER_CASES)), starfield)


def _noisy_stamps(m: int = 96, size: int = 32) -> np.ndarray:
    """Sérsic stamps with noise (some faint: failures), a blank one and one with a NaN."""
    from megalut_cli.sim.normals import add_gaussian_noise
    from megalut_cli.sim.render import StampRenderer

    rng = np.random.default_rng(4)
    gals = dict(profile="sersic", rad=rng.uniform(1.0, 4.0, m), flux=rng.uniform(5.0, 800.0, m),
                sersicn=rng.choice([1.0, 2.5, 4.0], m), e1=rng.uniform(-0.4, 0.4, m), e2=rng.uniform(-0.4, 0.4, m),
                g1=np.zeros(m), g2=np.zeros(m), dx=rng.uniform(-0.5, 0.5, m), dy=rng.uniform(-0.5, 0.5, m))
    import galsim

    stamps = StampRenderer(size).draw(galsim.Gaussian(sigma=1.5), "g", "auto", **gals)
    add_gaussian_noise(stamps, np.arange(m) + 7, 1.0)
    stamps[0] = 0.0
    stamps[1, 3, 4] = np.nan
    return stamps


def test_adaptive_moments_same_failures_and_features() -> None:
    from megalut_cli.gpu.measure import pixel_measurements
    from megalut_cli.measure.adamom import adaptive_moments
    from megalut_cli.measure.features import measure_stamps

    stamps = _noisy_stamps()
    ok = np.isfinite(stamps).all(axis=(1, 2))
    ref = adaptive_moments(stamps[ok], 4.0)
    moments, skymad, finite = pixel_measurements(stamps, 4.0)
    np.testing.assert_array_equal(finite, ok)
    assert (ref.status != 0).sum() >= 2  # the blank stamp and faint ones fail
    np.testing.assert_array_equal(np.isnan(moments[ok]).any(axis=1), ref.status != 0)
    expect = np.stack([ref.amp, ref.g1, ref.g2, ref.sigma, ref.rho4, ref.x, ref.y], axis=1)
    np.testing.assert_allclose(moments[ok], expect, rtol=0, atol=FEATURE_TOLERANCE)
    # the feature catalog: same flags, same features
    cpu = measure_stamps(stamps, engine="fast", device="cpu")
    dev = measure_stamps(stamps, engine="fast", device="gpu")
    np.testing.assert_array_equal(dev["flags"], cpu["flags"])
    for name, values in cpu.items():
        np.testing.assert_allclose(dev[name], values, rtol=0, atol=FEATURE_TOLERANCE, err_msg=name)


def test_work_unit_on_the_device_equals_the_fast_engine() -> None:
    """simulate's work unit: same truth, same noisy stamps (noise stream ported), same features."""
    import tempfile
    from pathlib import Path

    from sim_configs import TINY, write

    from megalut_cli.sim.config import load_config
    from megalut_cli.sim.draw import WorkUnit, draw_unit

    with tempfile.TemporaryDirectory() as tmp:
        cfg = load_config(write(Path(tmp), TINY))  # 3 cases x 4 realizations, as the CLI test below
    unit = WorkUnit(cfg, 5, 0, 3, cfg.structure.grid_nx, keep_stamps=True, measure=True)
    cpu = draw_unit(unit)
    dev = draw_unit(dataclasses.replace(unit, device="gpu"))
    peak = np.abs(cpu["stamps"]).max(axis=(1, 2))
    assert (np.abs(dev["stamps"] - cpu["stamps"]).max(axis=(1, 2)) <= PEAK_TOLERANCE * peak).all()
    assert set(dev["columns"]) == set(cpu["columns"])
    np.testing.assert_array_equal(dev["columns"]["flags"], cpu["columns"]["flags"])
    for name, values in cpu["columns"].items():
        np.testing.assert_allclose(dev["columns"][name], values, rtol=0, atol=FEATURE_TOLERANCE, err_msg=name)


@pytest.mark.parametrize("cost", ["msb", "mse"])
def test_training_reaches_the_same_validation_cost(cost) -> None:

    from megalut_cli.nn.train import train_member

    tr, va = toy_cases(1), toy_cases(2, 30)
    cpu = train_member(toy_task(tr, va, cost=cost, iterations=60))
    dev = train_member(toy_task(tr, va, cost=cost, iterations=60, device="gpu"))
    assert dev.best_iter > 0
    np.testing.assert_allclose(dev.valid_cost, cpu.valid_cost, rtol=1e-6)
    np.testing.assert_allclose(dev.history[:, 1], cpu.history[:, 1], rtol=1e-6)


def test_mswb_cost_and_gradient_equal_the_analytic_ones() -> None:
    from megalut_cli.gpu.train import DeviceObjective
    from megalut_cli.nn.data import CaseData
    from megalut_cli.nn.network import Network
    from megalut_cli.nn.train import Objective

    rng = np.random.default_rng(7)
    nc, nr = 20, 50
    t = rng.uniform(-1, 1, nc)
    q = rng.uniform(0, 1, (nc, nr))
    point = t[:, None] * np.where(q > 0.7, 0.4, 1.0) + rng.normal(0, 0.05, (nc, nr))
    data = CaseData.from_padded(q[:, :, None], rng.uniform(size=(nc, nr)) > 0.1, t, point=point)
    net = Network(1, (4, 3), "sigmoid4")
    params = net.init_normal(rng, 0.5)
    args = (net, "mswb", data, 0, np.full(1, 0.5), np.full(1, 0.5), 0.7)
    c_cpu, g_cpu = Objective(*args).scaled_with_grad(params)
    c_dev, g_dev = DeviceObjective(*args).scaled_with_grad(params)
    np.testing.assert_allclose(c_dev, c_cpu, rtol=1e-12)
    np.testing.assert_allclose(g_dev, g_cpu, rtol=1e-9, atol=1e-14)


def test_cli_device_gpu_without_a_device_is_one_line(tmp_path, runner, cli, monkeypatch) -> None:
    from sim_configs import write

    monkeypatch.setenv(PLATFORM_ENV, "no-such-platform")
    res = runner.invoke(cli, ["simulate", str(write(tmp_path)), "-o", str(tmp_path / "o.fits"), "--measure",
                              "--device", "gpu"])
    assert res.exit_code == 1
    assert "--device gpu: JAX finds no no-such-platform device" in res.stderr
    assert "Traceback" not in res.stderr and not (tmp_path / "o.fits").exists()
    res = runner.invoke(cli, ["simulate", str(write(tmp_path)), "-o", str(tmp_path / "o.fits"), "--measure",
                              "--device", "auto"])
    assert res.exit_code == 0, res.stderr


def test_cli_simulate_on_the_device_equals_cpu(tmp_path, runner, cli) -> None:
    from sim_configs import write

    from megalut_cli.catalog import read_catalog

    cfg = str(write(tmp_path))
    for device in ("cpu", "gpu"):
        res = runner.invoke(cli, ["simulate", cfg, "-o", str(tmp_path / f"{device}.fits"), "--measure",
                                  "--device", device, "--seed", "3"])
        assert res.exit_code == 0, res.stderr
    cpu, dev = (read_catalog(str(tmp_path / f"{d}.fits")) for d in ("cpu", "gpu"))
    for name in ("adamom_g1", "adamom_g2", "adamom_sigma", "adamom_flux", "snr", "flags"):
        np.testing.assert_allclose(np.asarray(dev[name], float), np.asarray(cpu[name], float), rtol=0,
                                   atol=FEATURE_TOLERANCE, err_msg=name)
