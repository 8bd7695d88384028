"""Morphology features: exact on Gaussians, separating Sérsic n = 1 from n = 4."""

from __future__ import annotations

import galsim
import numpy as np
import pytest

from megalut_cli.measure.features import measure_stamps
from megalut_cli.measure.morphology import (
    MORPHOLOGY_COLUMNS,
    morphology_features,
    morphology_of_measured,
)


def _draw(
    profile: galsim.GSObject, size: int = 64, offset=(0.3, -0.2), method: str = "no_pixel"
) -> np.ndarray:
    return profile.drawImage(nx=size, ny=size, scale=1.0, offset=offset, method=method).array


@pytest.mark.parametrize("sigma,g1,g2", [(3.0, 0.0, 0.0), (4.0, 0.3, -0.2), (2.5, -0.1, 0.45)])
def test_gaussian_closed_form(sigma, g1, g2):
    """For an exact (unpixelated) Gaussian of any size and shape: F1/F2 = 5/8,
    F0.5/F1 = 2/5, size ratio sqrt(8/5), from the measured adaptive moments."""
    stamp = _draw(galsim.Gaussian(sigma=sigma, flux=100.0).shear(g1=g1, g2=g2))[None]
    feats = measure_stamps(stamp)
    out = morphology_of_measured(stamp, None, feats)
    # achieved <= 4.6e-9 (all three shapes and columns)
    assert out["morph_conc"][0] == pytest.approx(5 / 8, abs=2e-8)
    assert out["morph_conc_inner"][0] == pytest.approx(2 / 5, abs=2e-8)
    assert out["morph_size_ratio"][0] == pytest.approx(np.sqrt(8 / 5), abs=2e-8)


def test_true_ellipse_gives_exact_values():
    """With the true centroid and ellipse given, the Gaussian values hold to float32 rounding."""
    sig, g1, g2, off = 3.0, 0.2, 0.1, (0.25, -0.4)
    stamp = _draw(galsim.Gaussian(sigma=sig).shear(g1=g1, g2=g2), offset=off)[None]
    c = 32.5  # true centre of a 64-pixel stamp, 1-based
    # GalSim's sigma of a sheared Gaussian is preserved (area-conserving shear):
    # det(M)^(1/4) = sigma
    out = morphology_features(stamp, [c + off[0]], [c + off[1]], [sig], [g1], [g2])
    # achieved <= 1.6e-9
    assert out["morph_conc"][0] == pytest.approx(5 / 8, abs=5e-9)
    assert out["morph_conc_inner"][0] == pytest.approx(0.4, abs=5e-9)
    assert out["morph_size_ratio"][0] == pytest.approx(np.sqrt(1.6), abs=5e-9)


def test_sersic_index_separated_through_psf_and_noise():
    """At the fiducial resolution (PSF sigma 2 px, hlr 4 px) and S/N ~ 50, n = 4 puts more
    light in the wings than n = 1 (lower F1/F2, faster-growing extent), far beyond the
    scatter; n = 0.5 (a Gaussian) through the Gaussian PSF stays exactly Gaussian."""
    psf = galsim.Gaussian(sigma=2.0)
    rng = np.random.default_rng(5)
    res = {}
    for n in (0.5, 1.0, 4.0):
        gal = galsim.Sersic(n=n, half_light_radius=4.0, flux=800.0).shear(g1=0.15, g2=-0.1)
        clean = _draw(galsim.Convolve(gal, psf), method="no_pixel")
        stamps = np.concatenate([clean[None], clean[None] + rng.normal(0.0, 1.0, (40, 64, 64))])
        res[n] = morphology_of_measured(stamps, None, measure_stamps(stamps))
    assert res[0.5]["morph_conc"][0] == pytest.approx(5 / 8, abs=5e-7)  # achieved 1.4e-7
    for col, sign in (("morph_conc", -1), ("morph_size_ratio", +1)):
        a, b = res[1.0][col][1:], res[4.0][col][1:]
        assert np.all(np.isfinite(a)) and np.all(np.isfinite(b))
        gap = sign * (b.mean() - a.mean())
        assert gap > 0.01
        assert gap > 8 * np.hypot(a.std(), b.std()) / np.sqrt(40)


def test_failed_rows_are_nan():
    stamps = np.zeros((2, 16, 16))
    out = morphology_features(stamps, [8.0, np.nan], [8.0, 8.0], [2.0, 2.0], [0.0, 0.0], [0.0, 0.0])
    assert set(out) == set(MORPHOLOGY_COLUMNS)
    assert np.isnan(out["morph_conc"][1])
    assert np.isnan(out["morph_conc"][0])  # no light: 0/0


def test_simulate_measure_and_training_use_them(tmp_path, runner, cli):
    """simulate --measure --morphology equals measure --morphology on the stamps, and
    train-point takes the new columns as features."""
    from sim_configs import write

    from megalut_cli.catalog import read_catalog
    from megalut_cli.nn.model import ShearModel

    cfg = write(tmp_path, replace={"n_cases = 3": "n_cases = 6"})
    args = ["simulate", str(cfg), "--seed", "2"]
    res = runner.invoke(cli, [*args, "-o", str(tmp_path / "m.fits"), "--measure", "--morphology"])
    assert res.exit_code == 0, res.output
    res = runner.invoke(
        cli, [*args, "-o", str(tmp_path / "c.fits"), "--stamps", str(tmp_path / "s.fits")]
    )
    assert res.exit_code == 0, res.output
    res = runner.invoke(
        cli,
        [
            "measure",
            str(tmp_path / "s.fits"),
            str(tmp_path / "c.fits"),
            "-o",
            str(tmp_path / "f.fits"),
            "--morphology",
        ],
    )
    assert res.exit_code == 0, res.output
    a, b = read_catalog(tmp_path / "m.fits"), read_catalog(tmp_path / "f.fits")
    for c in MORPHOLOGY_COLUMNS:
        assert np.isfinite(a[c]).mean() > 0.9
        np.testing.assert_allclose(a[c], b[c], rtol=1e-10, equal_nan=True)
    res = runner.invoke(cli, ["simulate", str(cfg), "-o", str(tmp_path / "x.fits"), "--morphology"])
    assert res.exit_code == 2 and "--morphology needs --measure" in res.output
    feats = "adamom_g1,adamom_g2,adamom_sigma,adamom_flux,adamom_rho4,morph_conc,morph_size_ratio"
    res = runner.invoke(
        cli,
        [
            "train-point",
            str(tmp_path / "m.fits"),
            "-o",
            str(tmp_path / "model.h5"),
            "--features",
            feats,
            "--members",
            "1",
            "--iterations",
            "3",
            "--hidden",
            "3",
        ],
    )
    assert res.exit_code == 0, res.output
    assert ShearModel.load(tmp_path / "model.h5").point["tru_g1"].features == feats.split(",")
