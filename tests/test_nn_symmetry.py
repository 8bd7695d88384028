"""Models averaged over the pixel grid's symmetries (``symmetry = "d4"``, issue 39): exactly
equivariant, so that a ring of orientations has no mean of their own making."""

from __future__ import annotations

import numpy as np
import pytest

from megalut_cli.errors import InputError
from megalut_cli.nn.model import ShearModel
from megalut_cli.nn.shipped import shipped_model
from megalut_cli.nn.symmetry import feature_signs
from megalut_cli.shear.predict import predict_arrays

#: adamom_g1, adamom_g2 (spin 2), sigma, flux, rho4 (invariant)
NEGATE = np.array([-1.0, -1.0, 1.0, 1.0, 1.0])
REFLECT = np.array([1.0, -1.0, 1.0, 1.0, 1.0])


def features(n: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack(
        [
            rng.normal(0, 0.3, n),
            rng.normal(0, 0.3, n),
            rng.uniform(2.0, 5.0, n),
            rng.uniform(100.0, 1500.0, n),
            rng.uniform(1.9, 2.3, n),
        ]
    )


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    plain = ShearModel.load(shipped_model("fiducial-metacal"))
    path = tmp_path_factory.mktemp("d4") / "d4.h5"
    plain.with_symmetry("d4", "test").save(path)
    return plain, ShearModel.load(path)


def test_d4_model_is_equivariant(models):
    plain, d4 = models
    assert d4.symmetry == "d4" and d4.format_version == "1.1" and plain.symmetry == "none"
    assert d4.shear_mode == plain.shear_mode == "metacal"
    x = features(500)
    p, n, r = (predict_arrays(d4, x * s) for s in (1.0, NEGATE, REFLECT))
    # a 90-degree rotation negates the shear, a reflection its second component; weights stay
    np.testing.assert_allclose(n["pre_g1"], -p["pre_g1"], rtol=0, atol=1e-14)
    np.testing.assert_allclose(n["pre_g2"], -p["pre_g2"], rtol=0, atol=1e-14)
    np.testing.assert_allclose(r["pre_g1"], p["pre_g1"], rtol=0, atol=1e-14)
    np.testing.assert_allclose(r["pre_g2"], -p["pre_g2"], rtol=0, atol=1e-14)
    np.testing.assert_allclose(n["pre_g1_w"], p["pre_g1_w"], rtol=1e-14)
    # the trained networks are not: f(x) + f(-x) is 1e-3 to 1e-2 (the additive bias)
    q, qn = predict_arrays(plain, x), predict_arrays(plain, x * NEGATE)
    assert np.median(np.abs(q["pre_g1"] + qn["pre_g1"])) > 1e-4


def test_a_ring_has_no_mean_of_the_networks_making(models):
    # Four orientations 45 degrees apart turn a shape by 90 degrees each (spin 2): at zero
    # shear their mean estimate is the networks' own additive bias.
    plain, d4 = models
    x = features(2000, seed=2)
    ring = [x]
    for _ in range(3):
        y = ring[-1].copy()
        y[:, 0], y[:, 1] = -ring[-1][:, 1], ring[-1][:, 0]
        ring.append(y)
    for model, bound in ((d4, 1e-15), (plain, None)):
        mean = np.mean([predict_arrays(model, y)["pre_g1"] for y in ring], axis=0)
        if bound is None:
            assert np.abs(mean).mean() > 1e-4
        else:
            assert np.abs(mean).max() < bound


def test_unknown_features_are_refused(models):
    plain, _ = models
    with pytest.raises(InputError, match="adamom_x"):
        feature_signs(["adamom_g1", "adamom_g2", "adamom_x"])
    with pytest.raises(ValueError, match="unknown symmetry"):
        plain.with_symmetry("c4", "test")


def test_info_says_which(models, runner, cli, tmp_path):
    _, d4 = models
    path = tmp_path / "m.h5"
    d4.save(path)
    r = runner.invoke(cli, ["info", str(path)])
    assert r.exit_code == 0 and "symmetry: d4" in r.stdout
    r = runner.invoke(cli, ["info", "fiducial"])
    assert r.exit_code == 0 and "symmetry: none" in r.stdout
