"""The training library in memory (``fit_point``, ``fit_weight``) against its file functions."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from megalut_cli.catalog import CatalogColumns, write_catalog
from megalut_cli.errors import ConfigError
from megalut_cli.nn.fit import fit_point, fit_weight, train_point, train_weight
from megalut_cli.nn.model import ShearModel
from megalut_cli.nn.options import PointSpec, WeightSpec
from megalut_cli.nn.toy import shear_like_columns
from megalut_cli.pipeline.config import key_names

FEATURES = ["adamom_g1", "adamom_g2", "adamom_sigma"]
POINT = PointSpec(features=FEATURES, members=2, iterations=15, seed=3)
WEIGHT = WeightSpec(members=2, iterations=8, seed=4)


def _same_members(a: ShearModel, b: ShearModel) -> None:
    """Every member's parameters equal, bit for bit, in both kinds of committees."""
    for kind in ("point", "weight"):
        ca, cb = getattr(a, kind), getattr(b, kind)
        assert list(ca) == list(cb)
        for t in ca:
            assert ca[t].training == cb[t].training or kind == "weight"
            for i in range(len(ca[t].members)):
                assert np.array_equal(ca[t].member_params(i), cb[t].member_params(i)), (kind, t, i)


def test_fit_in_memory_equals_the_file_functions(tmp_path: Path) -> None:
    tp, tw = shear_like_columns(24, 30, seed=1), shear_like_columns(12, 40, seed=2)
    write_catalog(tmp_path / "tp.fits", tp, fmt="megalut.toy")
    write_catalog(tmp_path / "tw.fits", tw, fmt="megalut.toy")
    point_file = train_point(tmp_path / "tp.fits", tmp_path / "p.h5", POINT)
    both_file = train_weight(tmp_path / "tw.fits", tmp_path / "p.h5", tmp_path / "w.h5", WEIGHT)
    point = fit_point(tp, POINT, sources={"train": str(tmp_path / "tp.fits")})
    both = fit_weight(tw, point, WEIGHT)
    _same_members(point, point_file)
    _same_members(both, both_file)
    # the point estimates of the in-memory model are those of the file's (the same networks)
    x = np.column_stack([tw[f] for f in FEATURES])
    for t, comm in both.point.items():
        assert np.array_equal(comm.predict(x), both_file.point[t].predict(x))
    assert both.weight["tru_g1"].training["point_model_sha256"] is None  # never written to a file
    assert "inputs" in both_file.provenance and both_file.provenance["inputs"]["train"][
        "path"
    ].endswith("tw.fits")


def test_catalog_columns_read_on_demand(tmp_path: Path) -> None:
    cols = shear_like_columns(4, 5, seed=1)
    write_catalog(tmp_path / "c.fits", cols, fmt="megalut.toy")
    table = CatalogColumns(tmp_path / "c.fits")
    assert list(table) == list(cols) and len(table) == len(cols)
    assert np.array_equal(table["adamom_g1"], cols["adamom_g1"])
    with pytest.raises(KeyError):
        table["nope"]


def test_messages_name_the_callers_words() -> None:
    tp = shear_like_columns(10, 10, seed=1)
    spec = PointSpec(
        features=FEATURES, select_cases="mean(adamom_sigma) > 1e9", members=1, iterations=2
    )
    for names, word in (
        (None, "select_cases"),
        (key_names("train_point"), "train_point.select_cases"),
        ({"select_cases": "--select-cases"}, "--select-cases"),
    ):
        with pytest.raises(
            ConfigError, match=f"^{word} 'mean\\(adamom_sigma\\) > 1e9' selects no case"
        ):
            fit_point(tp, spec, names=names)


def test_an_astropy_table_is_a_table_too() -> None:
    from astropy.table import Table

    tp = shear_like_columns(12, 20, seed=5)
    spec = PointSpec(features=FEATURES, members=1, iterations=4, seed=2)
    a = fit_point(tp, spec)
    b = fit_point(Table(tp), spec)
    for t in a.point:
        assert np.array_equal(a.point[t].member_params(0), b.point[t].member_params(0))


@pytest.mark.slow
def test_float32_training_changes_m_less_than_the_training_seed() -> None:
    """Float32 passes (the default of `megalut run` and of the shipped model) against float64 on
    the same data: fiducial TP (400 cases x 100 on rings), point committees of 4 members, 800
    iterations, two training seeds; unweighted m on one CRN validation set (4 shears x 10 000
    galaxies), the same rows for every model, so the differences are paired.

    * The precision moves m less than a new training seed does, in quadratic mean over the
      two seeds (precision) and the two precisions (seed), both components (benchmarks/
      training.md at the paper's size: 1e-3 against 3.8e-3 and 1.9e-3). Achieved: 9.1e-3
      against 2.0e-2 on an AVX-512 CPU (where the largest precision change, 1.46e-2, passed
      the smallest seed change, 1.32e-2); at most 9.1e-3 against at least 1.9e-2 with AVX2
      (these committees are small and not converged).
    * The committees' summed validation costs agree within 15 % (achieved 0.6-8.8 %, float32
      lower in all four).
    """
    from megalut_cli.shear.evaluate import evaluate_columns
    from megalut_cli.shear.predict import predict_columns
    from megalut_cli.sim import load_config
    from megalut_cli.sim.simulate import simulate_table

    fiducial = Path(__file__).resolve().parents[1] / "examples" / "fiducial"
    tp, _ = simulate_table(
        load_config(fiducial / "tp.toml", n_cases=400, n_realizations=100), 1, measure=True, nproc=2
    )
    vo, _ = simulate_table(
        load_config(fiducial / "vo-crn.toml", n_cases=4, n_realizations=10_000),
        3,
        measure=True,
        nproc=2,
    )
    m: dict[tuple[str, int], np.ndarray] = {}
    cost: dict[tuple[str, int], dict[str, float]] = {}
    for precision in ("float64", "float32"):
        for seed in (5, 7):
            spec = PointSpec(
                select_cases="mean(snr) > 10",
                members=4,
                iterations=800,
                precision=precision,
                seed=seed,
            )
            model = fit_point(tp, spec, nproc=2)
            result = evaluate_columns({**vo, **predict_columns(model, vo)})
            m[precision, seed] = np.array([result["unweighted"][c]["m"] for c in ("g1", "g2")])
            cost[precision, seed] = {
                t: sum(mem.valid_cost for mem in c.members) for t, c in model.point.items()
            }
            print(precision, seed, "m", m[precision, seed], "valid cost", cost[precision, seed])
    by_precision = [np.abs(m["float32", s] - m["float64", s]) for s in (5, 7)]
    by_seed = [np.abs(m[p, 7] - m[p, 5]) for p in ("float64", "float32")]
    rms = {
        k: float(np.sqrt(np.mean(np.square(v))))
        for k, v in (("precision", by_precision), ("seed", by_seed))
    }
    assert rms["precision"] < rms["seed"], (rms, by_precision, by_seed)
    for seed in (5, 7):
        for target, c64 in cost["float64", seed].items():
            assert abs(cost["float32", seed][target] / c64 - 1) < 0.15, (seed, target, cost)
