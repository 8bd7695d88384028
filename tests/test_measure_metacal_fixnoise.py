"""The fast engine's fixnoise (measure/metacal_fft.py ``fft_versions_fixnoise``, the multi-PSF
gather of measure/metacal.py): bit for bit the stack's versions with the rotated fields'
added, whatever the blocks, grids and the order in which the two parts arrive."""

from __future__ import annotations

import galsim
import numpy as np
import pytest

from megalut_cli.measure.metacal import TYPES, metacal_features, metacal_versions
from megalut_cli.measure.metacal_fft import fft_versions, fft_versions_fixnoise
from megalut_cli.measure.metacal_fft_nb import gather_fixnoise, take_columns

STEP = 0.01


def _stamps(n: int, size: int, seed: int) -> np.ndarray:
    """Compact and extended Sersic galaxies (different k grids on a 128-px stamp), noise 1."""
    rng = np.random.default_rng(seed)
    psf = galsim.Gaussian(sigma=2.0)
    out = np.empty((n, size, size))
    for i in range(n):
        gal = galsim.Sersic(n=[1.0, 4.0, 2.0][i % 3], half_light_radius=[0.8, 2.0, 9.0][i % 3])
        img = galsim.Convolve(gal.withFlux(3000.0), psf).drawImage(nx=size, ny=size, scale=1.0)
        out[i] = img.array + rng.normal(0.0, 1.0, (size, size))
    return out


@pytest.mark.parametrize("size, n", [(64, 37), (128, 21)])
def test_fixnoise_blocks_are_the_stack_versions_plus_the_rotated_fields(size, n):
    stamps = _stamps(n, size, 1)
    psf = galsim.Gaussian(sigma=2.0).drawImage(nx=size, ny=size, scale=1.0).array
    rng = np.random.default_rng(2)
    field_rows = rng.permutation(n)[: n - 5]  # some stamps without a field, shuffled
    stack = np.concatenate(
        [stamps, np.rot90(rng.normal(size=(len(field_rows), size, size)), 1, (1, 2))]
    )
    whole = fft_versions(stack, psf, STEP, 4.1)
    got = fft_versions_fixnoise(stack, n, field_rows, psf, STEP, 4.1)
    for kind in TYPES:
        want = whole[kind][:n].copy()
        want[field_rows] += np.rot90(whole[kind][n:], -1, axes=(1, 2))
        assert got[kind].tobytes() == want.tobytes(), kind


def test_fixnoise_rejects_bad_field_rows():
    stack = np.zeros((3, 16, 16))
    psf = galsim.Gaussian(sigma=2.0).drawImage(nx=16, ny=16, scale=1.0).array
    with pytest.raises(ValueError, match="field_rows"):
        fft_versions_fixnoise(stack, 2, np.array([2]), psf, STEP, 3.0)


def test_gather_and_take_kernels():
    rng = np.random.default_rng(0)
    versions = rng.normal(size=(5, 7, 6, 6))
    rows = np.array([0, 2, 3, 5], dtype=np.int64)
    field = np.array([False, False, True, True])
    order = np.array([2, 0, 3, 1], dtype=np.int64)
    out = np.empty((5, 4, 6, 6))
    gather_fixnoise(versions, rows, field, order, out)
    for r, f, o in zip(rows, field, order):
        want = versions[:, r] + (np.rot90(versions[:, r + 1], -1, axes=(1, 2)) if f else 0.0)
        np.testing.assert_array_equal(out[:, o], want)
    w = rng.normal(size=(2, 3, 4, 9)).astype(np.float32)
    col = np.array([4, 4, 0, 8], dtype=np.int64)
    got = np.empty((2, 3, 4, 4), np.float32)
    take_columns(w, col, got)
    np.testing.assert_array_equal(got, w[..., col])


def test_features_reuse_their_work_arrays_without_leaking_between_calls():
    """metacal_features keeps its versions in a reused buffer: calls of other sizes in
    between leave the results of a call unchanged; metacal_versions' own arrays are not
    that buffer."""
    stamps = _stamps(9, 48, 3)
    psf = galsim.Gaussian(sigma=2.0).drawImage(nx=48, ny=48, scale=1.0).array
    kw = dict(noise_sigma=np.ones(9), metacal_engine="fast", engine="fast")
    first = metacal_features(stamps, psf, STEP, **kw)
    versions, _ = metacal_versions(stamps[:4], psf, STEP, noise_sigma=np.ones(4), engine="fast")
    kept = {k: v.copy() for k, v in versions.items()}
    metacal_features(stamps[2:], psf, STEP, **{**kw, "noise_sigma": np.ones(7)})
    again = metacal_features(stamps, psf, STEP, **kw)
    for name, values in first.items():
        assert values.tobytes() == again[name].tobytes(), name
    for kind in TYPES:
        np.testing.assert_array_equal(versions[kind], kept[kind])
