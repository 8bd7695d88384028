"""Parameter distributions: ranges, moments, parsing errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate, stats

from megalut_cli.errors import ConfigError
from megalut_cli.sim.distributions import (
    CatalogColumn,
    Constant,
    Grid,
    InOrder,
    parse_distribution,
    sample_level,
)

N = 200_000


def _rng(seed: int = 1) -> np.random.Generator:
    return np.random.default_rng(seed)


def test_constant_number_and_table():
    for value in (3.5, {"type": "constant", "value": 3.5}):
        d = parse_distribution(value, "galaxy.rad")
        assert isinstance(d, Constant)
        assert np.all(d.sample(_rng(), 10) == 3.5)
        assert d.bounds() == (3.5, 3.5)


def test_uniform_range_and_moments():
    d = parse_distribution({"type": "uniform", "min": 2.0, "max": 8.0}, "k")
    x = d.sample(_rng(), N)
    assert x.min() >= 2.0 and x.max() <= 8.0
    assert abs(x.mean() - 5.0) < 4 * math.sqrt(3.0 / N)
    assert abs(x.var() - 36 / 12) < 0.02 * 3


def test_truncated_normal_range_and_moments():
    spec = {"type": "normal", "mean": 0.1, "sigma": 0.3, "min": -0.2, "max": 0.6}
    x = parse_distribution(spec, "k").sample(_rng(2), N)
    assert x.min() >= -0.2 and x.max() <= 0.6
    ref = stats.truncnorm((-0.2 - 0.1) / 0.3, (0.6 - 0.1) / 0.3, loc=0.1, scale=0.3)
    assert abs(x.mean() - ref.mean()) < 4 * ref.std() / math.sqrt(N)
    assert abs(x.std() / ref.std() - 1) < 0.01


def test_untruncated_normal_moments():
    x = parse_distribution({"type": "normal", "mean": -1.0, "sigma": 2.0}, "k").sample(_rng(3), N)
    assert abs(x.mean() + 1.0) < 4 * 2.0 / math.sqrt(N)
    assert abs(x.std() / 2.0 - 1) < 0.01


def test_truncated_rayleigh_range_and_moments():
    """The paper's R(0.2)_[0, 0.6]: mode 0.2, no sample beyond 0.6."""
    mode, hi = 0.2, 0.6
    x = parse_distribution({"type": "rayleigh", "mode": mode, "min": 0.0, "max": hi}, "k").sample(
        _rng(4), N
    )
    assert x.min() >= 0.0 and x.max() <= hi
    pdf = stats.rayleigh(scale=mode).pdf
    norm = integrate.quad(pdf, 0, hi)[0]
    mean = integrate.quad(lambda t: t * pdf(t), 0, hi)[0] / norm
    var = integrate.quad(lambda t: t * t * pdf(t), 0, hi)[0] / norm - mean**2
    assert abs(x.mean() - mean) < 4 * math.sqrt(var / N)
    assert abs(x.var() / var - 1) < 0.02
    # the mode of the histogram is near 0.2
    hist, edges = np.histogram(x, bins=30, range=(0, hi))
    assert abs(edges[np.argmax(hist)] - mode) < 0.05


def test_rayleigh_with_lower_bound():
    x = parse_distribution({"type": "rayleigh", "mode": 1.0, "min": 0.5, "max": 2.0}, "k").sample(
        _rng(5), 10_000
    )
    assert x.min() >= 0.5 and x.max() <= 2.0


def test_grid_values_and_step():
    d = parse_distribution({"type": "grid", "min": 1.0, "max": 4.0, "step": 0.1}, "k")
    assert isinstance(d, Grid) and len(d.values) == 31
    assert d.values[0] == 1.0 and d.values[-1] == 4.0
    x = d.sample(_rng(6), N)
    vals, counts = np.unique(x, return_counts=True)
    assert np.allclose(vals, np.round(np.arange(1.0, 4.01, 0.1), 10))
    expected = N / 31
    assert np.all(np.abs(counts - expected) < 5 * math.sqrt(expected))
    d2 = parse_distribution({"type": "grid", "values": [1, 2.5, 4]}, "k")
    assert set(np.unique(d2.sample(_rng(), 1000))) == {1.0, 2.5, 4.0}
    d3 = parse_distribution({"type": "grid", "min": 0.0, "max": 1.0, "n": 5}, "k")
    assert d3.values == (0.0, 0.25, 0.5, 0.75, 1.0)


def test_sequence_takes_its_values_in_turn():
    d = parse_distribution({"type": "sequence", "values": [0.05, -0.05, 0.0]}, "shear.g1")
    assert isinstance(d, InOrder) and d.bounds() == (-0.05, 0.05) and not d.is_constant
    assert np.array_equal(d.sample(_rng(), 7), [0.05, -0.05, 0.0, 0.05, -0.05, 0.0, 0.05])
    assert np.array_equal(d.at(np.array([4, 2])), [-0.05, 0.0])
    # a level of draws follows its positions; the other distributions still draw from rng
    u = parse_distribution({"type": "uniform", "min": 0, "max": 1}, "u")
    out = sample_level({"g": d, "u": u}, _rng(3), 1, 0, positions=np.array([5]))
    assert out["g"][0] == 0.0 and out["u"][0] == _rng(3).uniform(0, 1, 1)[0]


def test_catalog_joint_rows_share_the_row():
    base = CatalogColumn("a", column="a")
    a = base.with_data(np.arange(100.0))
    b = CatalogColumn("b", column="b").with_data(np.arange(100.0) * 10 + 5)
    c = CatalogColumn("c", column="c", joint=False).with_data(np.arange(100.0) * 10 + 5)
    out = sample_level({"a": a, "b": b, "c": c}, _rng(7), 5000, 100)
    assert np.array_equal(out["b"], out["a"] * 10 + 5)  # same row
    assert not np.array_equal(out["c"], out["a"] * 10 + 5)  # independent row
    assert set(np.unique(out["a"])) <= set(range(100))
    assert len(np.unique(out["a"])) == 100  # every row reachable


@pytest.mark.parametrize(
    "value, key_in_message",
    [
        ({"type": "unifrom", "min": 0, "max": 1}, "k.type: unknown distribution 'unifrom'"),
        ({"min": 0, "max": 1}, "k: a distribution table needs a 'type'"),
        ({"type": "uniform", "min": 0}, "k.max: missing"),
        ({"type": "uniform", "min": 2, "max": 1}, "k: uniform needs min <= max"),
        ({"type": "uniform", "min": 0, "max": float("nan")}, "k.max: must be a finite number"),
        ({"type": "uniform", "min": 0, "max": "big"}, "k.max: expected a number"),
        ({"type": "uniform", "min": 0, "max": 1, "mean": 3}, "k.mean: unknown key"),
        ({"type": "normal", "mean": 0, "sigma": -1}, "k.sigma: must be >= 0"),
        ({"type": "rayleigh", "mode": 0}, "k.mode: must be > 0"),
        ({"type": "grid", "values": []}, "k.values: expected a non-empty list"),
        ({"type": "grid", "min": 0, "max": 1}, "k: a grid needs"),
        ({"type": "sequence", "values": []}, "k.values: expected a non-empty list"),
        ({"type": "sequence", "values": [0.1, "x"]}, "k.values: expected a number"),
        ({"type": "sequence", "values": [0.1], "n": 2}, "k.n: unknown key"),
        ({"type": "catalog"}, "k.column: missing"),
        ({"type": "catalog", "column": "x", "element": -1}, "k.element"),
        (float("inf"), "k: must be a finite number"),
        ("3", "k: expected a number"),
    ],
)
def test_parse_errors_name_the_key(value, key_in_message):
    with pytest.raises(ConfigError) as err:
        parse_distribution(value, "k")
    assert key_in_message in str(err.value)
