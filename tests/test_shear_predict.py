"""The predict library: predictions match an independent forward pass, failed rows, streaming."""

from __future__ import annotations

import tracemalloc

import fitsio
import numpy as np
import pytest
from helpers import FEATURES, features_catalog, make_model, manual_predict

from megalut_cli import flags
from megalut_cli.catalog import read_catalog, write_catalog
from megalut_cli.cli.predict import parse_column_map
from megalut_cli.errors import ConfigError, InputError, MegalutError
from megalut_cli.nn.model import ShearModel
from megalut_cli.provenance import sha256_file
from megalut_cli.shear import predict as P


@pytest.fixture
def model_path(tmp_path):
    path = tmp_path / "model.h5"
    make_model(path)
    return path


def test_predictions_match_independent_forward_pass(tmp_path, model_path):
    d = features_catalog()
    src = tmp_path / "f.fits"
    write_catalog(src, d, fmt="megalut.features", cards={"SEED": (42, "simulation seed")})
    out = tmp_path / "p.fits"
    report = P.predict_catalog(src, model_path, out, chunk_rows=137)
    assert report.columns == ["pre_g1", "pre_g2", "pre_g1_w", "pre_g2_w"] and report.n_failed == 0
    t = read_catalog(out)
    model = ShearModel.load(model_path)
    x = np.column_stack([d[f] for f in FEATURES])
    for target, comm in model.point.items():
        np.testing.assert_allclose(
            t[P.prediction_column(target)], manual_predict(comm, x), rtol=1e-12, atol=1e-14
        )
    xw = np.column_stack([d[f] for f in [*FEATURES[2:], "snr"]])
    for target, comm in model.weight.items():
        w = np.asarray(t[P.prediction_column(target, "weight")])
        np.testing.assert_allclose(w, manual_predict(comm, xw), rtol=1e-12)
        assert np.all((w > 0) & (w < 1))
    # Every input column passes through unchanged; provenance in the header.
    for c in d:
        assert np.array_equal(np.asarray(t[c]), d[c]), c
    assert t.meta["MODELSHA"] == sha256_file(model_path) == report.model_sha256
    assert t.meta["MLFORMAT"] == "megalut.predictions" and t.meta["SEED"] == 42


def test_failed_rows_get_nan_zero_weight_and_flag(tmp_path, model_path):
    d = features_catalog(200)
    d["adamom_rho4"][3] = np.nan
    d["snr"][4] = np.inf  # a weight-only feature also fails the row
    d["flags"][5] = flags.HSM_FAILED  # flagged upstream, features still finite
    src, out = tmp_path / "f.fits", tmp_path / "p.fits"
    write_catalog(src, d, fmt="megalut.features")
    report = P.predict_catalog(src, model_path, out)
    t = read_catalog(out)
    bad = [3, 4, 5]
    assert report.n_failed == 3
    for c in ("pre_g1", "pre_g2"):
        assert np.all(np.isnan(t[c][bad])) and np.all(np.isfinite(np.delete(np.asarray(t[c]), bad)))
    for c in ("pre_g1_w", "pre_g2_w"):
        assert np.all(t[c][bad] == 0.0) and np.all(np.delete(np.asarray(t[c]), bad) > 0)
    assert t["flags"][3] == flags.BAD_FEATURES and t["flags"][4] == flags.BAD_FEATURES
    assert t["flags"][5] == flags.HSM_FAILED | flags.BAD_FEATURES
    assert np.count_nonzero(t["flags"]) == 3


def test_flags_column_created_and_column_map(tmp_path, model_path):
    d = features_catalog(300)
    del d["flags"]
    d["E1"] = d.pop("adamom_g1")
    d["adamom_g1"] = np.full(300, 99.0)  # a decoy with the feature's name: --col wins
    src, out = tmp_path / "f.fits", tmp_path / "p.fits"
    write_catalog(src, d, fmt="megalut.features")
    P.predict_catalog(src, model_path, out, column_map={"adamom_g1": "E1"})
    t = read_catalog(out)
    assert t["flags"].dtype == np.int32 and not np.any(t["flags"])
    model = ShearModel.load(model_path)
    x = np.column_stack([d["E1"], *(d[f] for f in FEATURES[1:])])
    np.testing.assert_allclose(t["pre_g1"], manual_predict(model.point["tru_g1"], x), rtol=1e-12)


def test_missing_features_listed_at_once(tmp_path, model_path):
    d = features_catalog(50)
    for c in ("adamom_g1", "adamom_rho4", "snr"):
        del d[c]
    src = tmp_path / "f.fits"
    write_catalog(src, d, fmt="megalut.features")
    with pytest.raises(InputError) as err:
        P.predict_catalog(src, model_path, tmp_path / "p.fits", names={"column_map": "--col"})
    msg = str(err.value)
    assert all(c in msg for c in ("adamom_g1", "adamom_rho4", "snr", "--col")) and "\n" not in msg
    with pytest.raises(InputError, match=r"adamom_g1 \(column_map adamom_g1=E1\)"):
        P.predict_catalog(src, model_path, tmp_path / "p.fits", column_map={"adamom_g1": "E1"})
    with pytest.raises(ConfigError, match="not a feature of the model"):
        P.predict_catalog(src, model_path, tmp_path / "p.fits", column_map={"size": "adamom_sigma"})
    with pytest.raises(ConfigError, match="FEATURE=COLUMN"):
        parse_column_map(["adamom_g1"])
    assert not (tmp_path / "p.fits").exists()


def test_parallel_equals_serial(tmp_path, model_path):
    """Same chunks: bit-identical whatever the engine; other chunk sizes: equal to rounding."""
    d = features_catalog(3000)
    d["adamom_g2"][::97] = np.nan
    src = tmp_path / "f.fits"
    write_catalog(src, d, fmt="megalut.features")
    P.predict_catalog(src, model_path, tmp_path / "serial.fits", chunk_rows=250)
    P.predict_catalog(src, model_path, tmp_path / "pool.fits", chunk_rows=250, nproc=2)
    P.predict_catalog(src, model_path, tmp_path / "big.fits", chunk_rows=5000)
    a, b = fitsio.read(tmp_path / "serial.fits"), fitsio.read(tmp_path / "pool.fits")
    c = fitsio.read(tmp_path / "big.fits")
    assert a.dtype == b.dtype == c.dtype
    for name in a.dtype.names:
        np.testing.assert_array_equal(a[name], b[name])
        if a[name].dtype.kind == "f":
            np.testing.assert_allclose(a[name], c[name], rtol=1e-13, atol=1e-16)
        else:
            np.testing.assert_array_equal(a[name], c[name])


def test_memory_is_bounded_by_chunks(tmp_path, model_path):
    """Predicting a catalog 8x longer takes no more memory (chunks of 5000 rows, a bounded
    number of them in flight, some run in this process): traced after a first, warm-up call
    (the model's first load, one-time buffers)."""
    peaks = {}
    for n in (60_000, 60_000, 480_000):
        rng = np.random.default_rng(0)
        d = {f: rng.uniform(1, 2, n) for f in [*FEATURES, "snr"]}
        src = tmp_path / "big.fits"
        write_catalog(src, d, fmt="megalut.features", overwrite=True)
        del d
        tracemalloc.start()
        try:
            P.predict_catalog(src, model_path, tmp_path / "p.fits", chunk_rows=5000, overwrite=True)
            _, peaks[n] = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        assert fitsio.FITS(str(tmp_path / "p.fits"))[1].get_nrows() == n
    full = 480_000 * (len(FEATURES) + 1 + 5) * 8  # the long catalog with its predictions
    assert peaks[480_000] < 1.2 * peaks[60_000] + 1e6, peaks  # not growing with the rows
    assert peaks[480_000] < full / 2, (peaks, full)


def test_empty_catalog_and_overwrite(tmp_path, model_path):
    d = {k: v[:0] for k, v in features_catalog(10).items()}
    src, out = tmp_path / "f.fits", tmp_path / "p.fits"
    write_catalog(src, d, fmt="megalut.features")
    P.predict_catalog(src, model_path, out)
    t = read_catalog(out)
    assert len(t) == 0 and "pre_g2_w" in t.colnames
    with pytest.raises(MegalutError, match="exists; pass overwrite=True"):
        P.predict_catalog(src, model_path, out)
    P.predict_catalog(src, model_path, out, overwrite=True)


def test_predict_columns_in_memory(model_path):
    model = ShearModel.load(model_path)
    d = features_catalog(20)
    new = P.predict_columns(model, d)
    assert set(new) == {"pre_g1", "pre_g2", "pre_g1_w", "pre_g2_w", "flags"}
    x = np.column_stack([d[f] for f in FEATURES])
    np.testing.assert_allclose(new["pre_g2"], manual_predict(model.point["tru_g2"], x), rtol=1e-12)


def test_not_a_model(tmp_path):
    d = features_catalog(10)
    src = tmp_path / "f.fits"
    write_catalog(src, d, fmt="megalut.features")
    junk = tmp_path / "model.h5"
    junk.write_bytes(b"nope" * 100)
    with pytest.raises(InputError, match="model"):
        P.predict_catalog(src, junk, tmp_path / "p.fits")


def test_narrow_flags_column_is_widened(tmp_path, model_path):
    d = features_catalog(30)
    d["flags"] = np.zeros(30, dtype=np.uint8)
    d["flags"][2] = flags.CENTROID_SHIFT
    d["adamom_g1"][3] = np.nan
    src, out = tmp_path / "f.fits", tmp_path / "p.fits"
    write_catalog(src, d, fmt="megalut.features")
    P.predict_catalog(src, model_path, out)
    f = np.asarray(read_catalog(out)["flags"])
    assert f.dtype.itemsize >= 2
    assert f[2] == flags.CENTROID_SHIFT | flags.BAD_FEATURES and f[3] == flags.BAD_FEATURES


def test_a_metadetection_catalog_is_predicted_row_by_row(runner, cli, tmp_path):
    """A metadetection catalog (``mdet_step``, ``MDETSTEP``): a metacal model predicts each
    detection's row from its plain features (the same numbers as a plain catalog of those
    rows), the card rides along; a simulation-calibrated model is refused (exit 1)."""
    from helpers import features_catalog, invoke_fails

    from megalut_cli.catalog import read_catalog_columns, write_catalog
    from megalut_cli.nn.model import ShearModel
    from megalut_cli.nn.shipped import shipped_model
    from megalut_cli.shear.predict import predict_arrays

    cols = features_catalog(n=50, seed=3)
    cols.pop("vec"), cols.pop("name")
    cols["psf_adamom_g1"] = np.zeros(50)
    cols["psf_adamom_g2"] = np.zeros(50)
    cols["psf_adamom_sigma"] = np.full(50, 2.5)
    cols["psf_adamom_rho4"] = np.full(50, 2.0)
    cols["skymad"] = np.full(50, 0.6)
    cols["mdet_step"] = np.array(["noshear", "1p", "1m", "2p", "2m"] * 10)
    path = tmp_path / "det.fits"
    write_catalog(path, cols, fmt="megalut.metadetect", cards={"MDETSTEP": (0.01, "step")})
    out = tmp_path / "p.fits"
    result = runner.invoke(
        cli, ["predict", str(path), "--model", "fiducial-metacal", "-o", str(out)]
    )
    assert result.exit_code == 0, result.output
    pred, header = read_catalog_columns(out)
    assert header["MDETSTEP"] == 0.01 and list(pred["mdet_step"][:2]) == ["noshear", "1p"]
    model = ShearModel.load(shipped_model("fiducial-metacal"))
    x = np.column_stack([cols[f] for f in model.features])
    direct = predict_arrays(model, x, cols["flags"])
    np.testing.assert_allclose(pred["pre_g1"], direct["pre_g1"], rtol=1e-12)
    invoke_fails(
        runner,
        cli,
        ["predict", str(path), "--model", "fiducial", "-o", str(tmp_path / "x.fits")],
        1,
        "metadetection",
    )
