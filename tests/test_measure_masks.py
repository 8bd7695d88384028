"""Masked pixels of cells (``measure/masks.py``): the harmonic fill of ``--mask-fill
interpolate`` and the distance to the nearest masked pixel of ``--mask-margin``."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from megalut_cli.measure.masks import (
    MAX_INTERPOLATED_REGION,
    inpainted,
    mask_distance,
    nanmedian_rows,
)


def test_the_fill_is_harmonic():
    """A harmonic image (a plane, x² − y²) is filled exactly inside; every filled pixel is
    the mean of its four neighbours; a region touching no good pixel holds 0."""
    y, x = np.mgrid[0:40, 0:48].astype(float)
    bad = np.zeros(x.shape, bool)
    bad[15:21, 25:31] = True
    bad[5:30, 8] = True
    for image in (3.0 + 0.5 * x - 0.2 * y, (x - 20.0) ** 2 - (y - 17.0) ** 2):
        filled = inpainted(np.where(bad, np.nan, image), bad)
        np.testing.assert_allclose(filled, image, atol=1e-9)
    rng = np.random.default_rng(1)
    image = rng.normal(size=x.shape)
    bad[:, 0] = True  # a whole edge column: three neighbours at most
    filled = inpainted(image, bad)
    padded = np.pad(filled, 1)
    count = np.pad(np.ones(x.shape), 1)
    sums = padded[:-2, 1:-1] + padded[2:, 1:-1] + padded[1:-1, :-2] + padded[1:-1, 2:]
    n = count[:-2, 1:-1] + count[2:, 1:-1] + count[1:-1, :-2] + count[1:-1, 2:]
    np.testing.assert_allclose(filled[bad], (sums / n)[bad], atol=1e-9)
    np.testing.assert_array_equal(filled[~bad], image[~bad])
    assert np.all(inpainted(np.ones((5, 5)), np.ones((5, 5), bool)) == 0.0)
    # a region larger than MAX_INTERPOLATED_REGION (a coadd cell's part off the image): 0
    big = np.zeros((100, 100), bool)
    big[:, : MAX_INTERPOLATED_REGION // 100 + 1] = True
    big[50, 80] = True
    filled = inpainted(np.full(big.shape, 2.0), big)
    assert np.all(filled[:, : MAX_INTERPOLATED_REGION // 100 + 1] == 0.0)
    assert filled[50, 80] == 2.0


def test_the_distance_to_the_nearest_masked_pixel():
    rng = np.random.default_rng(2)
    bad = rng.random((30, 40)) < 0.01
    x, y = rng.uniform(-0.5, 39.49, 200), rng.uniform(-0.5, 29.49, 200)
    col, row = np.floor(x + 0.5), np.floor(y + 0.5)
    rr, cc = np.nonzero(bad)
    brute = np.min(np.hypot(col[:, None] - cc, row[:, None] - rr), axis=1)
    np.testing.assert_allclose(mask_distance(bad, x, y), brute)
    assert np.isinf(mask_distance(np.zeros((4, 4), bool), x[:3], y[:3])).all()


@pytest.mark.parametrize("seed", range(6))
def test_nanmedian_rows_is_numpys_bit_for_bit(seed):
    """Odd and even counts, ties, all-NaN rows, infinities, scales: np.nanmedian's values."""
    rng = np.random.default_rng(seed)
    for _ in range(40):
        m, k = int(rng.integers(1, 30)), int(rng.integers(1, 250))
        values = rng.normal(size=(m, k)) * rng.choice([1e-3, 1.0, 1e5])
        if rng.random() < 0.5:
            values = np.round(values, 1)
        values[rng.random((m, k)) < rng.random()] = np.nan
        values[0] = np.nan
        if k > 2 and m > 1:
            values[1, :2] = np.inf, -np.inf
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            expected = np.nanmedian(values, axis=1)
        np.testing.assert_array_equal(nanmedian_rows(values), expected)
