"""The HDF5 model file: exact round trip, layout readable with h5py alone, refusal of bad files."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import h5py
import numpy as np
import pytest

from megalut_cli.errors import InputError
from megalut_cli.nn.model import Committee, Member, ShearModel, component_name, prediction_column
from megalut_cli.nn.network import Network

FEATURES = ["adamom_g1", "adamom_g2", "adamom_sigma", "adamom_flux", "adamom_rho4"]


def _committee(
    kind: str, target: str, features: list[str], hidden: tuple, seed: int, n: int = 8
) -> Committee:
    rng = np.random.default_rng(seed)
    out = "identity" if kind == "point" else "sigmoid4"
    net = Network(len(features), hidden, out, 0.01, 0.05)
    members = []
    for i in range(n):
        p = net.init_normal(rng, 0.5)
        members.append(
            Member(
                layers=[(w.copy(), b.copy()) for w, b in net.unpack(p)],
                seed=7,
                keys=(2, 99, i),
                train_cost=1e-4 + i,
                valid_cost=2e-4 + i,
                n_iter=30,
                best_iter=20,
                selected=i % 2 == 0,
                history=rng.random((30, 2)),
            )
        )
    return Committee(
        kind,
        target,
        features,
        hidden,
        rng.normal(size=len(features)),
        rng.uniform(0.5, 2, len(features)),
        members,
        out_loc=0.01 if kind == "point" else 0.0,
        out_scale=0.05 if kind == "point" else 1.0,
        cost="msb" if kind == "point" else "mswb",
        training={"iterations": 30},
    )


def _model() -> ShearModel:
    point = {
        t: _committee("point", t, FEATURES, (5, 5), s) for s, t in enumerate(["tru_g1", "tru_g2"])
    }
    weight = {
        t: _committee("weight", t, FEATURES + ["snr"], (5,), 10 + s)
        for s, t in enumerate(["tru_g1", "tru_g2"])
    }
    return ShearModel(
        point, weight, provenance={"argv": "megalut test", "versions": {"numpy": np.__version__}}
    )


def _rows(n: int = 5000, nf: int = 6, seed: int = 3) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, nf))


def test_names() -> None:
    assert component_name("tru_g1") == "g1"
    assert component_name("theta") == "theta"
    assert prediction_column("tru_theta") == "pre_theta"
    assert prediction_column("tru_g2", "weight") == "pre_g2_w"


def test_predict_is_mean_of_selected_members_and_nan_for_bad_rows() -> None:
    model = _model()
    x = _rows(nf=5)
    x[3, 2] = np.nan
    x[7, 0] = np.inf
    for comm in [model.point["tru_g1"], model.weight["tru_g2"]]:
        xx = x if comm.kind == "point" else np.column_stack([x, np.ones(len(x))])
        pred = comm.predict(xx)
        net = comm.network
        good = np.isfinite(xx).all(axis=1)
        xt = np.ascontiguousarray(((xx[good] - comm.in_loc) / comm.in_scale).T)
        ref = np.mean([net.forward(net.pack(m.layers), xt) for m in comm.selected], axis=0)
        assert comm.n_selected == 4
        assert np.allclose(pred[good], ref, rtol=1e-12, atol=1e-15)
        assert np.isnan(pred[[3, 7]]).all() and np.isfinite(pred[good]).all()
        if comm.kind == "weight":
            assert np.all((pred[good] > 0) & (pred[good] < 1))


def test_round_trip_is_exact(tmp_path: Path) -> None:
    model = _model()
    path = tmp_path / "m.h5"
    model.save(path)
    assert len(model.sha256) == 64
    back = ShearModel.load(path)
    assert back.sha256 == model.sha256
    assert back.features == FEATURES + ["snr"]
    assert list(back.point) == ["tru_g1", "tru_g2"] and list(back.weight) == ["tru_g1", "tru_g2"]
    x = _rows()
    for kind in ("point", "weight"):
        for t, comm in getattr(model, kind).items():
            other = getattr(back, kind)[t]
            xx = x[:, : len(comm.features)]
            assert np.array_equal(comm.predict(xx), other.predict(xx))  # bit-identical
            assert other.features == comm.features and other.target == t and other.kind == kind
            assert [m.selected for m in other.members] == [m.selected for m in comm.members]
            assert np.array_equal(other.members[1].history, comm.members[1].history)
            assert other.members[0].keys == (2, 99, 0)
            assert other.training == {"iterations": 30}
    assert back.provenance["argv"] == "megalut test"


def test_file_readable_with_h5py_alone(tmp_path: Path) -> None:
    """The documented layout (docs/model-format.md) is enough to recompute predictions."""
    model = _model()
    path = tmp_path / "m.h5"
    model.save(path)
    x = _rows(200, 5)
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == "megalut.model"
        assert f.attrs["format_version"] == "1.0"
        assert f.attrs["creator"].startswith("megalut ")
        assert f.attrs["created"] and f.attrs["uuid"]
        assert set(f["point"]) == {"g1", "g2"} and set(f["weight"]) == {"g1", "g2"}
        g = f["point/g1"]
        assert g.attrs["target"] == "tru_g1" and g.attrs["combine"] == "mean"
        assert json.loads(g.attrs["features"]) == FEATURES
        assert g.attrs["n_selected"] == 4
        loc = g["normalization/in_loc"][()]
        scale = g["normalization/in_scale"][()]
        out_loc = g["normalization/out_loc"][()]
        out_scale = g["normalization/out_scale"][()]
        preds = []
        for name, mem in g["members"].items():
            assert {"seed", "train_cost", "valid_cost", "n_iter", "selected"} <= set(mem.attrs)
            assert g["history/" + name].shape == (30, 2)
            if not mem.attrs["selected"]:
                continue
            a = (x - loc) / scale
            layers = mem["layers"]
            for i in range(len(layers)):
                layer = layers[str(i)]
                z = a @ layer["W"][()] + layer["b"][()]
                act = layer.attrs["activation"]
                a = np.tanh(z) if act == "tanh" else z
            assert act == "identity"
            preds.append(out_loc + out_scale * a[:, 0])
        assert "versions" in f["provenance"].attrs and "argv" in f["provenance"].attrs
    # achieved <= 1.0e-17 abs (predictions of order 0.1-1: float64 rounding only); the gate
    # allows a few tens of ulp for another BLAS's summation order
    assert np.allclose(
        np.mean(preds, axis=0), model.point["tru_g1"].predict(x), rtol=1e-14, atol=1e-16
    )


def test_save_is_atomic_and_refuses_overwrite(tmp_path: Path) -> None:
    path = tmp_path / "m.h5"
    path.write_text("keep me")
    with pytest.raises(Exception, match="exists"):
        _model().save(path)
    assert path.read_text() == "keep me"
    _model().save(path, overwrite=True)
    assert ShearModel.load(path).point
    assert [p.name for p in tmp_path.iterdir()] == ["m.h5"]  # no temporary left behind


def test_load_refuses_foreign_truncated_and_unknown_versions(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    good = tmp_path / "good.h5"
    _model().save(good)
    data = good.read_bytes()

    trunc = tmp_path / "trunc.h5"
    trunc.write_bytes(data[: len(data) // 2])
    text = tmp_path / "text.h5"
    text.write_text("not a model\n")
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f.create_dataset("x", data=[1, 2, 3])
    for path, message in [
        (trunc, "truncated"),
        (text, "not a readable HDF5"),
        (foreign, "not a megalut model"),
        (tmp_path / "missing.h5", "no such"),
    ]:
        with pytest.raises(InputError, match=message):
            ShearModel.load(path)

    major = tmp_path / "v2.h5"
    major.write_bytes(data)
    with h5py.File(major, "r+") as f:
        f.attrs["format_version"] = "2.0"
    with pytest.raises(InputError, match="version 2.0 is not supported"):
        ShearModel.load(major)

    minor = tmp_path / "v1_5.h5"
    minor.write_bytes(data)
    with h5py.File(minor, "r+") as f:
        f.attrs["format_version"] = "1.5"
    with caplog.at_level(logging.WARNING):
        assert ShearModel.load(minor).point
    assert "newer" in caplog.text

    broken = tmp_path / "broken.h5"
    broken.write_bytes(data)
    with h5py.File(broken, "r+") as f:
        del f["point/g1/members/000/layers/1/W"]
    with pytest.raises(InputError, match="corrupt"):
        ShearModel.load(broken)
