"""Features of the paper's Sect. 4 on stamps: HSM moments, skymad, S/N, flags."""

from __future__ import annotations

import math

import galsim
import numpy as np
import pytest

from megalut_cli import flags as fl
from megalut_cli.measure.features import (
    FEATURE_COLUMNS,
    effective_area,
    measure_stamps,
    sky_mad,
)

S = 64


def gaussian_stamp(sigma=3.0, g1=0.2, g2=-0.1, flux=500.0, offset=(0.0, 0.0), size=S):
    prof = galsim.Gaussian(sigma=sigma, flux=flux).shear(g1=g1, g2=g2)
    return prof.drawImage(nx=size, ny=size, scale=1.0, method="no_pixel", offset=offset).array


def test_columns_and_types():
    res = measure_stamps(np.stack([gaussian_stamp(), gaussian_stamp(sigma=2.0)]))
    assert tuple(res) == FEATURE_COLUMNS
    assert res["flags"].dtype == np.int32
    assert all(
        res[c].dtype == np.float64 and res[c].shape == (2,) for c in FEATURE_COLUMNS if c != "flags"
    )


def test_noiseless_elliptical_gaussian_matches_analytic_values():
    offset = (0.3, -0.2)
    stamp = gaussian_stamp(sigma=3.0, g1=0.2, g2=-0.1, flux=500.0, offset=offset)
    origin = np.array([[65, 129]])
    res = measure_stamps(stamp[None], origin)
    assert res["flags"][0] == 0
    assert res["adamom_sigma"][0] == pytest.approx(3.0, rel=1e-5)
    assert res["adamom_g1"][0] == pytest.approx(0.2, abs=1e-5)
    assert res["adamom_g2"][0] == pytest.approx(-0.1, abs=1e-5)
    assert res["adamom_flux"][0] == pytest.approx(500.0, rel=1e-4)
    assert res["adamom_logflux"][0] == pytest.approx(math.log10(500.0), rel=1e-6)
    assert res["adamom_rho4"][0] == pytest.approx(2.0, rel=1e-4)  # a Gaussian's rho4
    # GalSim centres the profile on the stamp's true centre (S+1)/2 = 32.5, plus offset;
    # the stamp's first pixel is pixel (65, 129) of the big image.
    assert res["adamom_x"][0] == pytest.approx(65 - 1 + 32.5 + offset[0], abs=1e-4)
    assert res["adamom_y"][0] == pytest.approx(129 - 1 + 32.5 + offset[1], abs=1e-4)


def test_default_origin_gives_stamp_coordinates():
    res = measure_stamps(gaussian_stamp(g1=0.0, g2=0.0)[None])
    assert res["adamom_x"][0] == pytest.approx(32.5, abs=1e-5)
    assert res["adamom_y"][0] == pytest.approx(32.5, abs=1e-5)


def test_float32_and_float64_stamps_agree():
    stamp = gaussian_stamp().astype(np.float32)
    a = measure_stamps(stamp[None])
    b = measure_stamps(stamp.astype(np.float64)[None])
    for c in FEATURE_COLUMNS:
        np.testing.assert_array_equal(a[c], b[c])


def test_skymad_of_pure_gaussian_noise_within_2_percent():
    rng = np.random.default_rng(42)
    sigma = 1.7
    noise = rng.normal(0.0, sigma, size=(200, S, S))
    mad = sky_mad(noise)
    assert np.mean(mad) == pytest.approx(sigma, rel=0.02)
    assert np.median(mad) == pytest.approx(sigma, rel=0.02)
    # ... and with a galaxy in the middle: only the edges count.
    with_gal = noise + gaussian_stamp(sigma=3.0, flux=5000.0)
    res = measure_stamps(with_gal)
    assert np.mean(res["skymad"]) == pytest.approx(sigma, rel=0.02)
    np.testing.assert_allclose(res["skymad"], mad, rtol=1e-6)


def test_skymad_uses_exactly_the_edge_pixels():
    stamp = np.zeros((1, 8, 8))
    stamp[0, 1:-1, 1:-1] = 1000.0  # interior ignored
    edge = np.arange(28, dtype=float)
    stamp[0, 0, :] = edge[:8]
    stamp[0, -1, :] = edge[8:16]
    stamp[0, 1:-1, 0] = edge[16:22]
    stamp[0, 1:-1, -1] = edge[22:]
    expected = 1.4826 * np.median(np.abs(edge - np.median(edge)))
    assert sky_mad(stamp)[0] == pytest.approx(expected)


def _noisy_galaxies(n=20, sigma_noise=1.0, seed=3):
    rng = np.random.default_rng(seed)
    gal = gaussian_stamp(sigma=2.5, g1=0.1, g2=0.05, flux=800.0)
    return gal + rng.normal(0.0, sigma_noise, size=(n, S, S))


def test_snr_follows_eq10_without_gain():
    res = measure_stamps(_noisy_galaxies())
    ok = res["flags"] == 0
    assert ok.all()
    area = np.pi * (3.0 * res["adamom_sigma"] * 1.1774100225154747) ** 2
    np.testing.assert_allclose(effective_area(res["adamom_sigma"]), area, rtol=1e-12)
    expected = res["adamom_flux"] / np.sqrt(area * res["skymad"] ** 2)
    np.testing.assert_allclose(res["snr"], expected, rtol=1e-12)
    # flux 800, sigma ~2.5 px, unit noise: S/N ~ 800 / (1 * sqrt(pi) * 3 * 2.5 * 1.1774) ~ 51
    assert 40 < np.median(res["snr"]) < 65


def test_snr_follows_eq8_with_gain():
    gain = 3.1
    res = measure_stamps(_noisy_galaxies(), gain=gain)
    area = effective_area(res["adamom_sigma"])
    f, s = res["adamom_flux"], res["skymad"]
    expected = gain * f / np.sqrt(gain * f + area * (gain * s) ** 2)
    np.testing.assert_allclose(res["snr"], expected, rtol=1e-12)
    # Eq. 8 adds the source's Poisson noise: always below the sky-limited S/N.
    assert (res["snr"] < measure_stamps(_noisy_galaxies())["snr"]).all()


def test_bad_gain_rejected():
    with pytest.raises(ValueError):
        measure_stamps(gaussian_stamp()[None], gain=0.0)


def test_flags_on_empty_and_nan_stamps():
    stamps = np.stack([np.zeros((S, S)), np.full((S, S), np.nan), gaussian_stamp()])
    stamps[2, 10, 10] = np.inf
    res = measure_stamps(stamps)
    assert res["flags"][0] & fl.HSM_FAILED
    assert res["flags"][1] & fl.BAD_PIXELS and res["flags"][1] & fl.BAD_SKY
    assert res["flags"][2] & fl.BAD_PIXELS
    for c in FEATURE_COLUMNS:
        if c not in ("flags", "skymad"):
            assert np.isnan(res[c]).all(), c
    assert res["skymad"][0] == 0.0  # the sky of an empty stamp is measurable


def test_pure_noise_is_flagged():
    rng = np.random.default_rng(7)
    res = measure_stamps(rng.normal(size=(60, S, S)))
    flagged = res["flags"] != 0
    assert flagged.mean() > 0.85
    assert np.isnan(res["adamom_g1"][flagged]).all()
    assert np.isfinite(res["skymad"]).all()


def test_negative_source_and_centroid_shift_flags():
    negative = -gaussian_stamp(g1=0.0, g2=0.0)
    shifted = gaussian_stamp(sigma=2.0, g1=0.0, g2=0.0, offset=(14.0, 0.0))
    res = measure_stamps(np.stack([negative, shifted]))
    assert res["flags"][0] & (fl.NEGATIVE_FLUX | fl.HSM_FAILED)
    assert res["flags"][1] == fl.CENTROID_SHIFT
    assert np.isnan(res["adamom_sigma"]).all()
    # With a wider limit the shifted galaxy is fine.
    res = measure_stamps(shifted[None], max_shift=20.0)
    assert res["flags"][0] == 0
    assert res["adamom_x"][0] == pytest.approx(46.5, abs=1e-4)


def test_empty_stack():
    res = measure_stamps(np.zeros((0, S, S)))
    assert all(len(v) == 0 for v in res.values())


def test_bad_shapes_rejected():
    with pytest.raises(ValueError):
        measure_stamps(np.zeros((2, 8, 9)))
    with pytest.raises(ValueError):
        measure_stamps(np.zeros((8, 8)))
