"""Antithetic noise, ``structure.antithetic = true``: realizations ``2k, 2k+1`` are twins alike
in everything but the sign of their noise and of metacal's fixnoise field."""

from __future__ import annotations

import fitsio
import numpy as np
import pytest
from sim_configs import write

from megalut_cli.errors import ConfigError
from megalut_cli.measure.metacal import metacal_versions
from megalut_cli.shear.bootstrap import group_size_for
from megalut_cli.sim.config import load_config
from megalut_cli.sim.simulate import simulate
from megalut_cli.sim.structure import draw_case

CRN = ['structure.per_realization=["galaxy"]', "structure.snc=pairs", "structure.common=true"]
TWINS = [*CRN, "structure.antithetic=true"]


def _cfg(tmp_path, overrides, n_rea=8, n_cases=2):
    return load_config(write(tmp_path), list(overrides), n_cases=n_cases, n_realizations=n_rea)


def test_twins_are_the_half_size_set_doubled_with_opposite_noise(tmp_path):
    """Twin 2k is realization k of the set of half the size; 2k+1 its copy, noise negated."""
    twins = draw_case(_cfg(tmp_path, TWINS, 8), 7, 1)
    half = draw_case(_cfg(tmp_path, CRN, 4), 7, 1)
    for k, v in half.truth.items():
        assert np.array_equal(twins.truth[k][0::2], v) and np.array_equal(twins.truth[k][1::2], v)
    assert np.array_equal(twins.noise_seeds[1::2], half.noise_seeds)
    assert np.array_equal(twins.offsets[0::2], half.offsets)
    assert twins.noise_signs is not None and half.noise_signs is None
    assert twins.noise_signs.tolist() == [1.0, -1.0] * 4
    # 90-degree pairs of galaxies, each seen twice
    e = twins.truth["tru_e1"] + 1j * twins.truth["tru_e2"]
    np.testing.assert_allclose(e[2::4], -e[0::4], atol=1e-15)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ([*TWINS], "multiple of 4"),  # pairs of twins: 4 realizations per galaxy pair
        (["structure.antithetic=true"], "an even number"),
        (
            [
                *TWINS,
                'noise={type="ccd", sky_mag=22.0, read_noise=5.0}',
                "instrument.zeropoint=25.0",
                "instrument.exptime=100.0",
                "instrument.gain=2.0",
                "instrument.pixel_scale=0.2",
            ],
            "has no opposite",
        ),
    ],
)
def test_refusals(tmp_path, overrides, message):
    n_rea = 6 if "multiple of 4" in message else 7 if "even" in message else 8
    with pytest.raises(ConfigError, match=message):
        _cfg(tmp_path, overrides, n_rea)


@pytest.mark.parametrize("engine", ["fast", "galsim"])
def test_twin_stamps_sum_to_twice_the_noiseless_stamps(tmp_path, engine):
    """Stamp 2k + stamp 2k+1 = 2 x the same stamp without noise (float32 pixels); the first
    twins are the half-size set's stamps bit for bit."""
    paths = {}
    for name, overrides, n_rea in (
        ("twins", TWINS, 8),
        ("clean", [*TWINS, "noise.override_sigma=0"], 8),
        ("half", CRN, 4),
    ):
        cfg = _cfg(tmp_path, overrides, n_rea)
        paths[name] = tmp_path / f"{name}-st.fits"
        simulate(cfg, tmp_path / f"{name}.fits", paths[name], seed=3, engine=engine)
    size = 24

    def stamps(name: str) -> np.ndarray:
        grid = fitsio.read(str(paths[name]))
        nx = grid.shape[1] // size
        tiles = grid.reshape(grid.shape[0] // size, size, nx, size).swapaxes(1, 2)
        return tiles.reshape(-1, size, size)

    twins, clean, half = stamps("twins"), stamps("clean"), stamps("half")
    n = 2 * 8  # 2 cases x 8 realizations
    assert np.ptp(twins[:n:2] - clean[:n:2]) > 1.0  # noisy
    np.testing.assert_allclose(twins[:n:2] + twins[1:n:2], 2 * clean[:n:2], atol=2e-5)
    assert np.array_equal(twins[:n:2], half[: n // 2])
    assert fitsio.read_header(str(tmp_path / "twins.fits"), 1)["ANTITHET"] is True


@pytest.mark.parametrize("engine", ["fast", "galsim"])
def test_metacal_versions_of_twins_sum_to_twice_the_noiseless_versions(engine):
    """The operation is linear in the image: with opposite fixnoise fields, the versions of the
    twins G + n and G - n sum to twice those of G without fixnoise, every term odd in the
    noise gone (to the fast engine's single-precision FFT level)."""
    import galsim

    size = 32
    psf = galsim.Gaussian(sigma=1.5)
    gal = galsim.Exponential(half_light_radius=2.0).shear(g1=0.2, g2=-0.1)
    clean = galsim.Convolve(gal, psf).drawImage(nx=size, ny=size, scale=1.0).array
    psf_image = psf.drawImage(nx=size, ny=size, scale=1.0).array
    noise = np.random.default_rng(1).normal(0.0, 0.5, (size, size))
    stack = np.stack([clean + noise, clean - noise])
    twins, _ = metacal_versions(
        stack, psf_image, 0.01, [0.5, 0.5], [11, 11], engine, fixnoise_signs=np.array([1.0, -1.0])
    )
    alone, _ = metacal_versions(clean[None], psf_image, 0.01, None, None, engine)
    for kind, versions in twins.items():
        assert np.ptp(versions[0] - alone[kind][0]) > 0.5  # noise and fixnoise are there
        np.testing.assert_allclose(versions[0] + versions[1], 2 * alone[kind][0], atol=1e-5)


def test_bootstrap_keeps_twins_together():
    assert group_size_for("pairs", 100, antithetic=True) == 4
    assert group_size_for("none", 100, antithetic=True) == 2
    assert group_size_for("ring", 100, antithetic=True) == 100
    assert group_size_for("pairs", 100) == 2
