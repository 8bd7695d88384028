"""Training on metacal catalogs (nn/fit.py: training_columns) and the model's shear mode."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.table import Table

from megalut_cli.errors import InputError
from megalut_cli.measure.metacal_defaults import STEP_CARD, TYPES
from megalut_cli.nn.fit import train_point, train_weight
from megalut_cli.nn.model import ShearModel
from megalut_cli.nn.options import PointSpec, WeightSpec
from megalut_cli.shear.predict import predict_catalog

FEATURES = ["adamom_g1", "adamom_g2", "adamom_sigma"]
POINT = PointSpec(features=FEATURES, members=2, iterations=10, seed=3)


def _catalog(path, metacal: bool, rng_seed: int = 1):
    """A small training set; in metacal mode each feature also as X_<type>, the noshear one
    holding other values than the plain one (so that reading the wrong one shows)."""
    rng = np.random.default_rng(rng_seed)
    n_cases, n_rea = 12, 40
    case = np.repeat(np.arange(n_cases), n_rea)
    g = rng.uniform(-0.05, 0.05, (n_cases, 2))[case]
    e = rng.normal(0, 0.2, (len(case), 2))
    t = Table(
        {
            "case": case,
            "rea": np.tile(np.arange(n_rea), n_cases),
            "tru_g1": g[:, 0],
            "tru_g2": g[:, 1],
            "adamom_g1": e[:, 0] + g[:, 0],
            "adamom_g2": e[:, 1] + g[:, 1],
            "adamom_sigma": rng.uniform(2, 4, len(case)),
            "flags": np.zeros(len(case), np.int32),
        }
    )
    if metacal:
        for kind in TYPES:
            for c in FEATURES:
                t[f"{c}_{kind}"] = 0.5 * np.asarray(t[c]) + (0.01 if kind != "noshear" else 0.0)
            t[f"flags_{kind}"] = np.zeros(len(case), np.int32)
        t.meta[STEP_CARD] = 0.01
    t.write(path)
    return t


def test_a_metacal_catalog_trains_on_its_noshear_features(tmp_path):
    """train-point on a metacal catalog gives a metacal model whose networks are those trained
    on a plain catalog holding the noshear values (bit-identical)."""
    t = _catalog(tmp_path / "mc.fits", metacal=True)
    plain = Table({c: t[c] for c in ("case", "rea", "tru_g1", "tru_g2", "flags")})
    for c in FEATURES:
        plain[c] = t[f"{c}_noshear"]
    plain.write(tmp_path / "noshear.fits")
    train_point(tmp_path / "mc.fits", tmp_path / "m.h5", POINT)
    train_point(tmp_path / "noshear.fits", tmp_path / "p.h5", POINT)
    m, p = ShearModel.load(tmp_path / "m.h5"), ShearModel.load(tmp_path / "p.h5")
    assert m.shear_mode == "metacal" and p.shear_mode == "simulation"
    x = np.column_stack([np.asarray(plain[c]) for c in FEATURES])
    for target in m.point:
        assert np.array_equal(m.point[target].predict(x), p.point[target].predict(x))


def test_predict_and_train_weight_refuse_the_other_mode(tmp_path):
    """A metacal model on a plain catalog, a plain one on a metacal catalog, and weights of a
    plain point model on a metacal catalog: one clear error each."""
    _catalog(tmp_path / "mc.fits", metacal=True)
    _catalog(tmp_path / "plain.fits", metacal=False)
    train_point(tmp_path / "mc.fits", tmp_path / "m.h5", POINT)
    train_point(tmp_path / "plain.fits", tmp_path / "p.h5", POINT)
    with pytest.raises(InputError, match="metacal model"):
        predict_catalog(tmp_path / "plain.fits", tmp_path / "m.h5", tmp_path / "s1.fits")
    with pytest.raises(InputError, match="simulation-calibrated model"):
        predict_catalog(tmp_path / "mc.fits", tmp_path / "p.h5", tmp_path / "s2.fits")
    with pytest.raises(InputError, match="simulation model"):
        train_weight(
            tmp_path / "mc.fits",
            tmp_path / "p.h5",
            tmp_path / "w.h5",
            WeightSpec(members=2, iterations=10, seed=3),
        )
    assert not any((tmp_path / f).exists() for f in ("s1.fits", "s2.fits", "w.h5"))
    report = predict_catalog(tmp_path / "mc.fits", tmp_path / "m.h5", tmp_path / "s.fits")
    assert "mcal_r11" in report.columns
