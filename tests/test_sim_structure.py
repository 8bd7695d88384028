"""Cases x realizations structure: what varies where, shape-noise cancellation, seeds."""

from __future__ import annotations

import numpy as np
import pytest
from sim_configs import write

from megalut_cli.sim.config import load_config
from megalut_cli.sim.structure import draw_case, ring_angles

GAL_KEYS = ("tru_rad", "tru_flux", "tru_sersicn", "tru_ell")


def _cfg(tmp_path, per, snc, n_rea=8, shear=True, extra=()):
    replace = {
        'per_realization = ["angle"]': f"per_realization = {per}",
        'snc = "ring"': f'snc = "{snc}"',
        "n_realizations = 4": f"n_realizations = {n_rea}",
    }
    if not shear:
        replace[
            "[shear]\n"
            'g1 = {type = "uniform", min = -0.1, max = 0.1}\n'
            'g2 = {type = "uniform", min = -0.1, max = 0.1}\n'
        ] = ""
    return load_config(write(tmp_path, replace=replace), list(extra))


def _constant(a):
    return np.all(a == a[0])


@pytest.mark.parametrize("n_rea", [2, 3, 7, 100])
def test_ring_cancels_mean_ellipticity_exactly(tmp_path, n_rea):
    cfg = _cfg(tmp_path, '["angle"]', "ring", n_rea)
    for case in range(5):
        t = draw_case(cfg, 11, case).truth
        # exact up to float64 rounding: achieved |mean e| <= 8.0e-17 (n_rea 2-100, |e| < 1);
        # 4e-16 is a few ulp of 1, room for another libm's cos/sin and summation order
        assert abs(t["tru_e1"].mean()) < 4e-16
        assert abs(t["tru_e2"].mean()) < 4e-16
        # one galaxy and one shear per case, rotated on the ring
        for k in (*GAL_KEYS, "tru_g1", "tru_g2"):
            assert _constant(t[k]), k
        e = t["tru_e1"] + 1j * t["tru_e2"]
        np.testing.assert_allclose(np.abs(e), t["tru_ell"][0], rtol=1e-12)
        steps = np.angle(e[1:] / e[:-1])
        np.testing.assert_allclose(np.mod(steps, 2 * np.pi), 2 * np.pi / n_rea, atol=1e-9)


def test_ring_angles_formula():
    theta = ring_angles(np.array([10.0]), 4, 4)
    np.testing.assert_allclose(theta, [10.0, 55.0, 100.0, 145.0])
    np.testing.assert_allclose(
        ring_angles(np.array([10.0, 30.0]), 4, 2), [10.0, 100.0, 30.0, 120.0]
    )


def test_pairs_are_rotated_by_90_degrees(tmp_path):
    """Sect. 6 TW: a new galaxy per pair, the two realizations 90 degrees apart."""
    cfg = _cfg(tmp_path, '["galaxy"]', "pairs", 10)
    t = draw_case(cfg, 5, 0).truth
    e = t["tru_e1"] + 1j * t["tru_e2"]
    # 90 degrees in position angle = 180 degrees in ellipticity: e_{2j+1} = -e_{2j}
    np.testing.assert_allclose(e[1::2], -e[0::2], atol=1e-15)
    np.testing.assert_allclose(
        np.mod(t["tru_theta"][1::2] - t["tru_theta"][0::2], 180), 90, atol=1e-9
    )
    for k in GAL_KEYS:
        assert np.array_equal(t[k][0::2], t[k][1::2])  # same galaxy within a pair
        assert len(np.unique(t[k][0::2])) == 5 or k == "tru_sersicn"  # new galaxy per pair
    assert _constant(t["tru_g1"]) and _constant(t["tru_g2"])  # one shear per case


def test_weight_training_structure(tmp_path):
    """Fig. 5: one shear per case, a different galaxy for every realization."""
    cfg = _cfg(tmp_path, '["galaxy"]', "none", 50)
    t = draw_case(cfg, 5, 1).truth
    assert _constant(t["tru_g1"]) and _constant(t["tru_g2"])
    assert len(np.unique(t["tru_rad"])) == 50 and len(np.unique(t["tru_theta"])) == 50


def test_pretraining_structure(tmp_path):
    """Fig. 6: no shear; realizations differ only by offsets and noise."""
    cfg = _cfg(tmp_path, "[]", "none", 20, shear=False)
    d = draw_case(cfg, 5, 2)
    t = d.truth
    assert np.all(t["tru_g1"] == 0) and np.all(t["tru_g2"] == 0)
    for k in (*GAL_KEYS, "tru_e1", "tru_e2"):
        assert _constant(t[k]), k
    assert len(np.unique(t["tru_dx"])) == 20
    assert len(np.unique(d.noise_seeds)) == 20


def test_shear_per_realization(tmp_path):
    cfg = _cfg(tmp_path, '["shear"]', "none", 30)
    t = draw_case(cfg, 5, 2).truth
    assert len(np.unique(t["tru_g1"])) == 30
    assert _constant(t["tru_rad"])


def test_designed_shears_in_turn_over_common_galaxies(tmp_path):
    """A ``sequence`` of shears gives case k the k-th pair (cycling), and a common-random-
    number set keeps its galaxies, angles and noise seeds whatever the shear."""
    seq = {
        'g1 = {type = "uniform", min = -0.1, max = 0.1}': (
            'g1 = {type = "sequence", values = [0.05, -0.05, 0.0]}'
        ),
        'g2 = {type = "uniform", min = -0.1, max = 0.1}': (
            'g2 = {type = "sequence", values = [0.0, 0.0, 0.05]}'
        ),
        'per_realization = ["angle"]': 'per_realization = ["galaxy"]',
        'snc = "ring"': 'snc = "pairs"\ncommon = true',
    }
    cfg = load_config(write(tmp_path, replace=seq), [])
    cases = [draw_case(cfg, 11, k).truth for k in range(5)]
    shears = [(t["tru_g1"][0], t["tru_g2"][0]) for t in cases]
    assert shears == [(0.05, 0.0), (-0.05, 0.0), (0.0, 0.05), (0.05, 0.0), (-0.05, 0.0)]
    for t in cases:
        assert _constant(t["tru_g1"]) and _constant(t["tru_g2"])
        for k in (*GAL_KEYS, "tru_theta", "tru_dx"):
            assert np.array_equal(t[k], cases[0][k])


def test_offsets_within_half_pixel(tmp_path):
    cfg = _cfg(tmp_path, '["angle"]', "ring", 2000)
    t = draw_case(cfg, 1, 0).truth
    for k in ("tru_dx", "tru_dy"):
        assert t[k].min() >= -0.5 and t[k].max() <= 0.5
        assert abs(t[k].mean()) < 4 * np.sqrt(1 / 12 / 2000)
        assert t[k].std() == pytest.approx(np.sqrt(1 / 12), rel=0.06)


def test_seeds_per_case(tmp_path):
    """A case's draws depend only on (seed, case); case params survive n_realizations changes."""
    cfg = _cfg(tmp_path, '["angle"]', "ring", 8)
    a = draw_case(cfg, 7, 3).truth
    b = draw_case(cfg, 7, 3).truth
    for k in a:
        assert np.array_equal(a[k], b[k])
    c = draw_case(cfg, 8, 3).truth
    assert a["tru_rad"][0] != c["tru_rad"][0]
    d = draw_case(cfg, 7, 4).truth
    assert a["tru_rad"][0] != d["tru_rad"][0]
    more = draw_case(cfg.with_structure(n_realizations=16), 7, 3).truth
    for k in ("tru_rad", "tru_flux", "tru_g1", "tru_g2", "tru_ell"):
        assert more[k][0] == a[k][0]


def test_field_psf_truth(tmp_path):
    p = write(
        tmp_path,
        replace={
            'type = "gaussian"\nsigma = 1.5': 'type = "field"',
            "[noise]": '[field]\nx = {type = "uniform", min = 0.0, max = 1.0}\ny = 0.25\n\n[noise]',
        },
    )
    cfg = load_config(p)
    assert cfg.psf_varies
    d = draw_case(cfg, 2, 0)
    assert _constant(d.truth["tru_field_x"]) and np.all(d.truth["tru_field_y"] == 0.25)
    assert len(d.psf_specs) == 1
    spec, fx, fy = d.psf_specs[0]
    assert fx == d.truth["tru_field_x"][0] and fy == 0.25
    # with "psf" per realization (no SNC), every realization has its own position and PSF
    cfg2 = load_config(p, ['structure.per_realization=["angle", "psf"]', "structure.snc=none"])
    d2 = draw_case(cfg2, 2, 0)
    assert len(np.unique(d2.truth["tru_field_x"])) == 4 and len(d2.psf_specs) == 4
    assert np.array_equal(d2.psf_index, np.arange(4))
    # within a ring, per-realization parameters are drawn once per group (the whole case)
    cfg3 = load_config(p, ['structure.per_realization=["angle", "psf"]'])
    assert len(np.unique(draw_case(cfg3, 2, 0).truth["tru_field_x"])) == 1
