"""Costs and analytic gradients of the network engine (paper Eqs. 3-5) against references."""

from __future__ import annotations

import numpy as np
import pytest

from megalut_cli.nn import costs
from megalut_cli.nn.data import CaseData
from megalut_cli.nn.network import CHUNK, Network
from megalut_cli.nn.train import Objective


def _data(
    n_cases: int = 7, n_rea: int = 9, n_feat: int = 3, seed: int = 1, frac_masked: float = 0.35
) -> tuple:
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n_cases, n_rea, n_feat))
    mask = rng.random((n_cases, n_rea)) > frac_masked
    mask[:, 0] = True  # unequal case sizes, but no empty case
    mask[0, 1:] = False  # one case with a single realization
    t = rng.normal(size=n_cases) * 0.3
    point = rng.normal(size=(n_cases, n_rea)) * 0.3
    return x, mask, t, point


def _fd_grad(f, p: np.ndarray, h: float = 1e-6) -> np.ndarray:
    g = np.empty_like(p)
    for i in range(len(p)):
        e = np.zeros_like(p)
        e[i] = h
        g[i] = (f(p + e) - f(p - e)) / (2 * h)
    return g


CASES = [
    ("msb", "identity", (4, 3)),
    ("msb", "identity", (5,)),
    ("mse", "identity", (4, 3)),
    ("mse", "identity", (2, 3, 2)),
    ("mswb", "sigmoid4", (5,)),
    ("mswb", "sigmoid4", (3, 4)),
    ("msb", "identity", ()),
]


@pytest.mark.parametrize("cost,output,hidden", CASES)
def test_analytic_gradient_matches_finite_differences(
    cost: str, output: str, hidden: tuple
) -> None:
    x, mask, t, point = _data()
    data = CaseData.from_padded(x, mask, t, point=point)
    kw = {"out_loc": 0.1, "out_scale": 0.7} if output == "identity" else {}
    net = Network(x.shape[2], hidden, output, **kw)
    obj = Objective(net, cost, data, 0, np.full(3, 0.2), np.full(3, 1.5))
    p = net.init_normal(np.random.default_rng(3), 0.5)
    f, g = obj.value_and_grad(p)
    fd = _fd_grad(obj.value, p)
    assert np.isfinite(f) and f > 0
    # relative to the gradient's scale, element by element
    assert np.max(np.abs(g - fd)) <= 1e-6 * np.max(np.abs(fd))
    assert f == pytest.approx(obj.value(p), rel=1e-14)


def test_gradient_across_several_chunks(monkeypatch: pytest.MonkeyPatch) -> None:
    """Rows spanning several processing chunks (and a ragged last one) give the same gradient."""
    rng = np.random.default_rng(5)
    n_cases, n_rea = 5, (CHUNK * 2 + 123) // 5 + 1
    x = rng.normal(size=(n_cases, n_rea, 2))
    mask = rng.random((n_cases, n_rea)) > 0.1
    t = rng.normal(size=n_cases)
    data = CaseData.from_padded(x, mask, t)
    net = Network(2, (3,))
    obj = Objective(net, "msb", data, 0, np.zeros(2), np.ones(2))
    p = net.init_normal(rng, 0.5)
    _, g = obj.value_and_grad(p)
    fd = _fd_grad(obj.value, p)
    assert np.max(np.abs(g - fd)) <= 1e-6 * np.max(np.abs(fd))
    # and the same as processing all rows as one block
    import megalut_cli.nn.network as network

    monkeypatch.setattr(network, "CHUNK", 10**9)
    single = Objective(net, "msb", data, 0, np.zeros(2), np.ones(2))
    assert np.allclose(single.value_and_grad(p)[1], g, rtol=1e-10, atol=0)


@pytest.mark.parametrize("cost", ["mse", "msb", "mswb"])
def test_compact_costs_equal_the_literal_equations(cost: str) -> None:
    """Masked realizations are excluded: compact rows and padded arrays + mask agree (Eqs. 3-5)."""
    x, mask, t, point = _data(seed=2)
    rng = np.random.default_rng(0)
    out = rng.uniform(0.1, 0.9, mask.shape)
    data = CaseData.from_padded(x, mask, t, point=point)
    o = out[mask]  # row order of from_padded: case by case
    n = data.counts.astype(float)
    if cost == "mse":
        compact = costs.mse(o, data.case, n, data.row_targets[:, 0])[0]
    elif cost == "msb":
        compact = costs.msb(o, data.case, n, data.targets[:, 0])[0]
    else:
        compact = costs.mswb(o, data.point[:, 0], data.case, n, data.targets[:, 0])[0]
    ref = costs.padded_cost(cost, out, mask, t, point=point)
    # achieved <= 1.2e-16 rel (float64 rounding): the gate is a few tens of ulp, not a tolerance
    # on the equations, leaving room for another BLAS's summation order
    assert compact == pytest.approx(ref, rel=1e-14)
    # garbage in masked slots does not matter
    garbage = np.where(mask, out, 1e6)
    assert costs.padded_cost(
        cost, garbage, mask, t, point=np.where(mask, point, -1e6)
    ) == pytest.approx(ref, rel=1e-14)


def test_msb_is_mean_before_square_and_mse_after() -> None:
    # one case, outputs symmetric around the target: MSB 0, MSE the variance
    o = np.array([1.0, 3.0])
    case = np.array([0, 0])
    n = np.array([2.0])
    assert costs.msb(o, case, n, np.array([2.0]))[0] == 0.0
    assert costs.mse(o, case, n, np.array([2.0, 2.0]))[0] == pytest.approx(
        1.0, rel=1e-14
    )  # achieved: exact


def test_mswb_with_equal_weights_is_msb() -> None:
    x, mask, t, point = _data(seed=4)
    data = CaseData.from_padded(x, mask, t, point=point)
    n = data.counts.astype(float)
    w = np.full(data.n_rows, 0.37)
    # achieved <= 1.2e-16 rel (float64 rounding); the gate allows a few tens of ulp
    assert costs.mswb(w, data.point[:, 0], data.case, n, data.targets[:, 0])[0] == pytest.approx(
        costs.msb(data.point[:, 0], data.case, n, data.targets[:, 0])[0], rel=1e-14
    )


def test_float32_passes_agree_with_float64() -> None:
    x, mask, t, _ = _data(n_cases=20, n_rea=50, n_feat=5, seed=6)
    data = CaseData.from_padded(x, mask, t)
    net = Network(5, (5, 5))
    p = net.init_normal(np.random.default_rng(1), 0.3)
    f64, g64 = Objective(net, "msb", data, 0, np.zeros(5), np.ones(5)).value_and_grad(p)
    f32, g32 = Objective(
        net, "msb", data, 0, np.zeros(5), np.ones(5), dtype="float32"
    ).value_and_grad(p)
    assert f32 == pytest.approx(f64, rel=1e-4)
    assert np.max(np.abs(g32 - g64)) <= 1e-3 * np.max(np.abs(g64))


@pytest.mark.parametrize("cost", ["msb", "mse", "mswb"])
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_batch_objective_is_the_objective_of_the_subset(cost: str, dtype: str) -> None:
    """A mini-batch taken from the normalised data (Objective.batch) holds the same numbers,
    bit for bit, as an objective built from CaseData.subset, and gives the same cost and
    gradient; the value-only MSB (validation passes) is the MSB."""
    x, mask, t, point = _data(n_cases=30, n_rea=40, n_feat=3, seed=7)
    data = CaseData.from_padded(x, mask, t, point=point)
    net = Network(3, (4,), "sigmoid4" if cost == "mswb" else "identity", 0.1, 0.7)
    p = net.init_normal(np.random.default_rng(2), 0.5)
    loc, scale = np.array([0.1, -0.2, 0.3]), np.array([1.7, 2.1, 0.9])
    full = Objective(net, cost, data, 0, loc, scale, 0.3, dtype)
    cases = np.sort(np.random.default_rng(3).choice(data.n_cases, size=11, replace=False))
    batch = full.batch(cases)
    ref = Objective(net, cost, data.subset(cases), 0, loc, scale, 0.3, dtype)
    assert batch.xt.flags.c_contiguous and batch.xt.dtype == ref.xt.dtype
    for name in ("xt", "t", "t_row", "n"):
        assert np.array_equal(getattr(batch, name), getattr(ref, name))
    assert np.array_equal(batch.groups.case, ref.groups.case)
    if cost == "mswb":
        assert np.array_equal(batch.point, ref.point)
    fb, gb = batch.value_and_grad(p)
    fr, gr = ref.value_and_grad(p)
    assert fb == fr and np.array_equal(gb, gr)
    assert batch.value(p) == ref.value(p) == fr
    assert full.n_evals == 0 and batch.n_evals == 2


def test_msb_value_is_the_msb() -> None:
    x, mask, t, _ = _data(seed=8)
    data = CaseData.from_padded(x, mask, t)
    o = np.random.default_rng(0).normal(size=data.n_rows)
    n = data.counts.astype(float)
    assert (
        costs.msb_value(o, data.case, n, data.targets[:, 0])
        == costs.msb(o, data.case, n, data.targets[:, 0])[0]
    )


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_normalised_columns_by_blocks(dtype: str) -> None:
    """The blockwise normalisation gives the numbers of the whole-array expression."""
    from megalut_cli.nn.train import normalised_columns

    x = np.random.default_rng(4).normal(size=(1000, 3)) * 5
    loc, scale = np.array([0.3, -1.0, 2.0]), np.array([3.1, 0.7, 1.3])
    xt = normalised_columns(x, loc, scale, dtype, block=64)
    assert xt.flags.c_contiguous and xt.dtype == np.dtype(dtype)
    assert np.array_equal(xt, np.ascontiguousarray(((x - loc) / scale).T, dtype=dtype))
