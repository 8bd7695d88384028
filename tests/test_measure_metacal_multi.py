"""The fast metacal engine on stacks whose stamps have different PSF images
(measure/metacal_fft_multi.py): against the one-PSF path and the GalSim reference."""

from __future__ import annotations

import galsim
import numpy as np
import pytest

from megalut_cli.measure import metacal_fft_multi
from megalut_cli.measure.metacal import TYPES, metacal_versions, target_psf_sigma
from megalut_cli.measure.metacal_fft import fft_versions
from megalut_cli.measure.metacal_fft_multi import fft_versions_multi

STEP = 0.01


def _stack(
    n: int, size: int, psf_sizes: list[int], seed: int
) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """``n`` sheared exponential galaxies (noise 1e-3), stamp ``k`` seen through a Moffat PSF
    ``k`` (FWHM 2.5..4 px, |g| < 0.05, with the pixel) drawn on ``psf_sizes[k % len]`` pixels:
    ``(stamps, psf images, noise sigmas)``."""
    rng = np.random.default_rng(seed)
    stamps, psfs = np.empty((n, size, size)), []
    for k in range(n):
        psf = galsim.Moffat(beta=3.0, fwhm=rng.uniform(2.5, 4.0)).shear(
            g1=rng.uniform(-0.05, 0.05), g2=rng.uniform(-0.05, 0.05)
        )
        psf = galsim.Convolve(psf, galsim.Pixel(1.0))
        p = psf_sizes[k % len(psf_sizes)]
        psfs.append(psf.drawImage(nx=p, ny=p, scale=1.0, method="no_pixel").array)
        gal = galsim.Exponential(half_light_radius=rng.uniform(1.0, 3.0)).shear(
            g1=rng.uniform(-0.3, 0.3), g2=rng.uniform(-0.3, 0.3)
        )
        img = (
            galsim.Convolve(gal, psf)
            .drawImage(nx=size, ny=size, scale=1.0, method="no_pixel")
            .array
        )
        stamps[k] = img + rng.normal(0.0, 1e-3, img.shape)
    return stamps, psfs, np.full(n, 1e-3)


#: Two float32 computations of the same versions whose sums run in another order (longer
#: tables, other blocks): a few units of float32's 1.2e-7 of the noshear peak. The order
#: numba's reassociated (fastmath) loops take depends on the CPU's vector width: achieved
#: ~1e-8 with AVX2, 1.7e-7 to 5.3e-7 with AVX-512 (AMD family 26). 20x below the 1e-5 to GalSim.
FLOAT32_ORDER = 2e-6


def _errors(a: dict, b: dict, peak: np.ndarray) -> np.ndarray:
    """Max |a - b| over the five versions of each stamp, relative to ``peak`` (per stamp)."""
    return (
        np.array([max(np.abs(a[k][i] - b[k][i]).max() for k in TYPES) for i in range(len(peak))])
        / peak
    )


@pytest.mark.parametrize("size, psf_size", [(48, 48), (64, 64), (48, 33), (49, 32)])
def test_several_psfs_agree_with_the_one_psf_path_and_galsim(size, psf_size):
    """Fixnoise on, two stamps sharing a PSF: the batched pass agrees with the one-PSF path
    run PSF by PSF to ``FLOAT32_ORDER`` of the noshear peak (float32 sums over the union's
    longer tables) and with GalSim as the fast engine's tests require (1e-5; achieved ~6e-7),
    with the same target sigmas."""
    stamps, psfs, sigma = _stack(5, size, [psf_size], seed=size + psf_size)
    psfs = np.array(psfs[:4])
    index = np.array([0, 1, 2, 3, 3])
    seeds = np.arange(5) + 100
    multi, target = metacal_versions(
        stamps, psfs, STEP, sigma, seeds, engine="fast", psf_index=index
    )
    for j in range(4):
        rows = np.flatnonzero(index == j)
        one, t_one = metacal_versions(
            stamps[rows], psfs[j], STEP, sigma[rows], seeds[rows], engine="fast"
        )
        peak = one["noshear"].max(axis=(1, 2))
        errors = _errors({k: multi[k][rows] for k in TYPES}, one, peak)
        assert np.all(errors <= FLOAT32_ORDER), errors
        np.testing.assert_array_equal(target[rows], t_one)
    ref, t_ref = metacal_versions(
        stamps, psfs, STEP, sigma, seeds, engine="galsim", psf_index=index
    )
    np.testing.assert_array_equal(target, t_ref)
    errors = _errors(multi, ref, ref["noshear"].max(axis=(1, 2)))
    assert np.all(errors < 1e-5), errors


def test_one_psf_takes_the_one_psf_path(monkeypatch):
    """A stack whose stamps all name one PSF goes through the one-PSF function unchanged:
    bit for bit its result."""

    def refuse(*args, **kwargs):
        raise AssertionError("the batched path was taken")

    monkeypatch.setattr(metacal_fft_multi, "fft_versions_multi", refuse)
    stamps, psfs, _ = _stack(3, 48, [48], seed=3)
    psfs = np.array(psfs)
    direct = fft_versions(stamps, psfs[1], STEP, target_psf_sigma(psfs[1], STEP))
    for versions, _ in (
        metacal_versions(stamps, psfs, STEP, engine="fast", psf_index=[1, 1, 1]),
        metacal_versions(stamps, psfs[1], STEP, engine="fast"),
    ):
        assert all(np.array_equal(versions[k], direct[k]) for k in TYPES)


def test_mixed_psf_sizes_are_planned_by_size(monkeypatch):
    """PSF images of two sizes (33 and 48 px) in one call: one plan per size, each stamp as
    the one-PSF function gives it (to ``FLOAT32_ORDER`` of its noshear peak)."""
    stamps, psfs, _ = _stack(4, 48, [33, 48], seed=5)
    target = np.array([target_psf_sigma(p, STEP) for p in psfs])
    shapes = []
    plan = metacal_fft_multi.multi_plan

    def spy(psf_stack, *args):
        shapes.append(psf_stack.shape)
        return plan(psf_stack, *args)

    monkeypatch.setattr(metacal_fft_multi, "multi_plan", spy)
    multi = fft_versions_multi(stamps, psfs, np.arange(4), STEP, target)
    assert sorted(shapes) == [(2, 33, 33), (2, 48, 48)]
    for i in range(4):
        one = fft_versions(stamps[i : i + 1], psfs[i], STEP, target[i])
        errors = _errors(
            {k: multi[k][i : i + 1] for k in TYPES}, one, one["noshear"].max(axis=(1, 2))
        )
        assert np.all(errors <= FLOAT32_ORDER), (i, errors)


def test_independent_of_stamp_order_and_chunk():
    """Shuffling the stamps or changing the PSFs per plan (1, 3, 64) changes the versions only
    by float32 rounding (the block's matrix products, the union's tables): within
    ``FLOAT32_ORDER`` of the noshear peak (not bit for bit)."""
    stamps, psfs, _ = _stack(7, 48, [48], seed=11)
    index = np.array([0, 1, 2, 3, 4, 5, 5])
    target = np.array([target_psf_sigma(p, STEP) for p in psfs])
    base = fft_versions_multi(stamps, psfs, index, STEP, target)
    peak = base["noshear"].max(axis=(1, 2))
    perm = np.random.default_rng(0).permutation(7)
    shuffled = fft_versions_multi(stamps[perm], psfs, index[perm], STEP, target)
    back = {k: np.empty_like(v) for k, v in shuffled.items()}
    for k in TYPES:
        back[k][perm] = shuffled[k]
    assert np.all(_errors(back, base, peak) <= FLOAT32_ORDER)
    for chunk in (1, 3, 64):
        other = fft_versions_multi(stamps, psfs, index, STEP, target, chunk=chunk)
        assert np.all(_errors(other, base, peak) <= FLOAT32_ORDER), chunk
