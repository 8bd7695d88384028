"""The fast engine's per-stamp Gaussian noise (megalut_cli/sim/normals.py)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from megalut_cli.errors import MegalutError
from megalut_cli.sim.noise import StampNoise
from megalut_cli.sim.normals import add_gaussian_noise, standard_normals


@pytest.fixture(scope="module")
def draws() -> np.ndarray:
    return standard_normals(np.arange(1, 501), 4096)  # 2 048 000 normals


def test_normals_are_standard_normal(draws: np.ndarray) -> None:
    z = draws.ravel()
    n = len(z)
    assert abs(z.mean()) < 5 / np.sqrt(n)
    assert abs(z.var() - 1) < 5 * np.sqrt(2 / n)
    assert abs(stats.skew(z)) < 5 * np.sqrt(6 / n)
    assert abs(stats.kurtosis(z)) < 5 * np.sqrt(24 / n)
    # 400 equiprobable bins, and the fine structure of the ziggurat's layers on [-4, 4]
    edges = np.concatenate([[-np.inf], stats.norm.ppf(np.linspace(0, 1, 401)[1:-1]), [np.inf]])
    counts, _ = np.histogram(z, edges)
    chi2 = ((counts - n / 400) ** 2 / (n / 400)).sum()
    assert stats.chi2.sf(chi2, 399) > 1e-4
    fine = np.linspace(-4, 4, 1601)
    counts, _ = np.histogram(z, fine)
    expected = np.diff(stats.norm.cdf(fine)) * n
    chi2 = ((counts - expected) ** 2 / expected).sum()
    assert stats.chi2.sf(chi2, 1600) > 1e-4
    # the tail beyond the base strip's edge r = 3.654 (drawn by Marsaglia's tail method)
    tail = np.mean(np.abs(z) > 3.6541528853610088)
    p_tail = 2 * stats.norm.sf(3.6541528853610088)
    assert abs(tail - p_tail) < 5 * np.sqrt(p_tail / n)
    assert stats.kstest(z, "norm").pvalue > 1e-4


def test_normals_are_independent(draws: np.ndarray) -> None:
    n = draws[:, 1:].size
    assert abs(np.corrcoef(draws[:, :-1].ravel(), draws[:, 1:].ravel())[0, 1]) < 5 / np.sqrt(n)  # along a stamp
    assert abs(np.corrcoef(draws[:-1].ravel(), draws[1:].ravel())[0, 1]) < 5 / np.sqrt(n)  # neighbouring seeds


def test_each_row_depends_on_its_seed_only(draws: np.ndarray) -> None:
    seeds = np.array([7, 3, 2**31 - 2, 7])
    rows = standard_normals(seeds, 100)
    np.testing.assert_array_equal(rows[0], rows[3])
    np.testing.assert_array_equal(rows[1], standard_normals([3], 100)[0])
    np.testing.assert_array_equal(rows[1], draws[2, :100])  # same seed, another batch and length
    assert not np.array_equal(rows[0], rows[1])


def test_add_gaussian_noise_batches_and_scale() -> None:
    seeds = np.arange(10, 140)  # more than one chunk
    stamps = np.full((130, 8, 8), 3.0, dtype=np.float32)
    add_gaussian_noise(stamps, seeds, 2.5)
    expected = np.float32(3.0) + np.float32(2.5) * standard_normals(seeds, 64).astype(np.float32)
    np.testing.assert_array_equal(stamps.reshape(130, 64), expected)
    parts = np.full((130, 8, 8), 3.0, dtype=np.float32)
    add_gaussian_noise(parts[:50], seeds[:50], 2.5)
    add_gaussian_noise(parts[50:], seeds[50:], 2.5)
    np.testing.assert_array_equal(parts, stamps)
    with pytest.raises(MegalutError, match="seeds for"):
        add_gaussian_noise(stamps, seeds[:3], 1.0)


def test_stamp_noise_gaussian_uses_the_per_stamp_normals() -> None:
    stamps = np.zeros((4, 16, 16), dtype=np.float32)
    StampNoise("gaussian", sigma=1.5).add_batch(stamps, np.array([5, 6, 7, 8]))
    expected = np.float32(1.5) * standard_normals([5, 6, 7, 8], 256).astype(np.float32)
    np.testing.assert_array_equal(stamps.reshape(4, -1), expected)
