"""Cases x realizations: grouping catalog rows, masks, dropping empty cases, padded views."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from megalut_cli.errors import InputError
from megalut_cli.nn.data import CaseData, build_cases, sorted_unique, split_cases, valid_rows
from megalut_cli.nn.normalization import apply, column_extremes, fit


def _columns() -> dict[str, np.ndarray]:
    # three cases of unequal sizes, rows shuffled
    case = np.array([2, 0, 1, 0, 2, 1, 0, 2, 2])
    return {
        "case": case,
        "f": np.arange(9, dtype=float),
        "tru_x": case * 0.1,
        "flags": np.array([0, 0, 1, 0, 0, 0, 0, 4, 0]),
    }


def test_build_cases_groups_and_masks() -> None:
    cols = _columns()
    ok = valid_rows(cols, ["f"], 9)
    assert ok.tolist() == [True, True, False, True, True, True, True, False, True]
    d = build_cases(cols, ["f"], ["tru_x"], ok)
    assert d.case_ids.tolist() == [0, 1, 2]
    assert d.counts.tolist() == [3, 1, 3]
    assert d.x[:, 0].tolist() == [1, 3, 6, 5, 0, 4, 8]  # grouped by case, catalog order kept
    assert np.allclose(d.targets[:, 0], [0.0, 0.1, 0.2])
    x, mask, t = d.padded()
    assert x.shape == (3, 3, 1) and mask.sum(axis=1).tolist() == [3, 1, 3]
    back = CaseData.from_padded(x, mask, t)
    assert np.array_equal(back.x, d.x) and np.array_equal(back.case, d.case)
    sub = d.subset(np.array([2, 0]))
    assert sub.case_ids.tolist() == [2, 0] and sub.x[:, 0].tolist() == [0, 4, 8, 1, 3, 6]
    assert sub.counts.tolist() == [3, 3]


def test_non_finite_features_are_masked() -> None:
    cols = _columns()
    cols["f"][0] = np.nan
    ok = valid_rows(cols, ["f"], 9)
    assert not ok[0]


def test_empty_case_dropped_with_warning(caplog: pytest.LogCaptureFixture) -> None:
    cols = _columns()
    ok = valid_rows(cols, ["f"], 9)
    ok[cols["case"] == 1] = False
    with caplog.at_level(logging.WARNING):
        d = build_cases(cols, ["f"], ["tru_x"], ok, where="cat.fits")
    assert d.case_ids.tolist() == [0, 2]
    assert "1 case(s) dropped: every realization is flagged" in caplog.text


def test_errors() -> None:
    cols = _columns()
    ok = np.ones(9, bool)
    with pytest.raises(InputError, match="fewer than 2 cases"):
        build_cases(cols, ["f"], ["tru_x"], cols["case"] == 0)
    with pytest.raises(InputError, match="no valid realization"):
        build_cases(cols, ["f"], ["tru_x"], np.zeros(9, bool))
    bad = dict(cols, tru_x=np.where(np.arange(9) == 4, np.nan, cols["tru_x"]))
    with pytest.raises(InputError, match="tru_x is not finite in 1 row"):
        build_cases(bad, ["f"], ["tru_x"], ok)
    varying = dict(cols, tru_x=cols["f"])
    with pytest.raises(InputError, match="varies within case"):
        build_cases(varying, ["f"], ["tru_x"], ok)
    d = build_cases(varying, ["f"], ["tru_x"], ok, constant_targets=False)  # fine for MSE
    assert np.array_equal(d.row_targets[:, 0], d.x[:, 0])


def test_split_and_normalization() -> None:
    tr, va = split_cases(10, 0.2, np.random.default_rng(1))
    assert len(va) == 2 and len(tr) == 8 and not set(tr) & set(va)
    x = np.random.default_rng(0).normal(size=(1000, 3)) * [1, 10, 100] + [0, 5, -3]
    loc, scale = fit(x, "minmax")
    xn = apply(x, loc, scale)
    assert np.allclose(xn.min(axis=0), -1) and np.allclose(xn.max(axis=0), 1)
    x[0, 2] = 1e9  # one wild outlier
    loc, scale = fit(x, "robust")
    xn = apply(x, loc, scale)
    assert np.all(np.abs(np.percentile(xn[1:], [1, 99], axis=0)) < 1.05)
    loc, scale = fit(np.ones((5, 1)))
    assert scale[0] == 1.0


@pytest.mark.parametrize("dtype", [np.int64, np.int16, np.uint8, bool])
def test_sorted_unique_is_numpy_unique(dtype) -> None:
    rng = np.random.default_rng(3)
    for n in (0, 1, 2, 50):
        values = np.sort(rng.integers(0, 2 if dtype is bool else 9, n).astype(dtype))
        ids, inverse = sorted_unique(values)
        want_ids, want_inverse = np.unique(values, return_inverse=True)
        assert ids.dtype == want_ids.dtype and ids.tobytes() == want_ids.tobytes()
        assert inverse.dtype == np.intp
        np.testing.assert_array_equal(inverse, want_inverse)


def test_build_cases_rows_in_order_or_not() -> None:
    """Rows already grouped by case are taken as they are; shuffled rows are grouped by case
    in their catalog order."""
    rng = np.random.default_rng(4)
    case = np.repeat(np.arange(6), 5)
    cols = {"case": case, "a": rng.normal(size=30), "t": np.repeat(rng.normal(size=6), 5)}
    ordered = build_cases(cols, ["a"], ["t"], np.ones(30, bool))
    np.testing.assert_array_equal(ordered.x[:, 0], cols["a"])
    np.testing.assert_array_equal(ordered.case, case)
    perm = rng.permutation(30)
    shuffled = build_cases({k: v[perm] for k, v in cols.items()}, ["a"], ["t"], np.ones(30, bool))
    rows = np.argsort(case[perm], kind="stable")
    np.testing.assert_array_equal(shuffled.x[:, 0], cols["a"][perm][rows])
    np.testing.assert_array_equal(shuffled.case, case)
    np.testing.assert_array_equal(shuffled.targets, ordered.targets)


def test_column_extremes_are_numpys_axis_reduction() -> None:
    rng = np.random.default_rng(6)
    x = rng.normal(size=(1000, 4))
    x[::7, 1] = 0.0
    x[::5, 1] = -0.0  # a zero minimum of either sign: numpy's own reduction decides
    for arr in (x, np.asfortranarray(x), x[:, 2:3]):
        lo, hi = column_extremes(arr)
        assert lo.tobytes() == arr.min(axis=0).tobytes()
        assert hi.tobytes() == arr.max(axis=0).tobytes()
