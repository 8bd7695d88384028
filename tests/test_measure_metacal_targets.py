"""The metacal target registry (measure/metacal_targets/): the round Gaussian default, a toy
second target registered by name through both fast engines against the GalSim reference."""

from __future__ import annotations

from dataclasses import dataclass

import galsim
import numpy as np
import pytest

from megalut_cli.measure.metacal import (
    TYPES,
    metacal_images,
    metacal_versions,
    target_psf_image,
    target_psf_sigma,
)
from megalut_cli.measure.metacal_targets import (
    DEFAULT_TARGET,
    METACAL_TARGETS,
    TARGET_CARD,
    MetacalTarget,
    metacal_target,
    register_metacal_target,
)
from megalut_cli.measure.metacal_targets.gauss import GaussTarget, psf_sigma

STEP = 0.01


def _psf(fwhm: float = 3.0, size: int = 48) -> np.ndarray:
    psf = galsim.Convolve(galsim.Moffat(beta=3.0, fwhm=fwhm), galsim.Pixel(1.0))
    return psf.drawImage(nx=size, ny=size, scale=1.0, method="no_pixel").array


@dataclass(frozen=True)
class WideGauss(MetacalTarget):
    """A toy target: a round Gaussian 1.5 times wider than the PSF, written with the base
    class's generic Fourier kernels (not the Gaussian's fused ones)."""

    width: float
    name = "wide"

    @property
    def sigma(self) -> float:
        return self.width

    def gsobject(self) -> galsim.GSObject:
        return galsim.Gaussian(sigma=self.width)

    def kvalue(self, kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
        return np.exp(-0.5 * self.width**2 * (kx**2 + ky**2))


def _wide(psf_image: np.ndarray, step: float) -> WideGauss:
    return WideGauss(1.5 * psf_sigma(psf_image))


def test_the_default_is_the_round_gaussian_dilated_by_the_step():
    psf = _psf()
    target = metacal_target(DEFAULT_TARGET, psf, STEP)
    assert isinstance(target, GaussTarget)
    assert target.sigma == target_psf_sigma(psf, STEP)
    assert target.sigma == pytest.approx(psf_sigma(psf) * (1 + 2 * STEP), rel=1e-15)
    assert target.cards() == {}  # the default leaves the catalogs' cards as they were
    np.testing.assert_array_equal(target.image(33), target_psf_image(target.sigma, 33))


def test_gauss_kernels_agree_with_galsim_and_each_other():
    target = GaussTarget(2.3)
    k = np.linspace(0.0, 2.0, 9)
    gs = target.gsobject()
    want = np.array([[gs.kValue(kx, ky).real for kx in k] for ky in k])
    np.testing.assert_allclose(target.grid_kvalue(k), want, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(target.kvalue(k[None, :], k[:, None]), want, rtol=1e-12)
    phased = target.kvalue_shifted(k, k, 0.5)
    np.testing.assert_allclose(phased, want.diagonal() * np.exp(1j * k), rtol=1e-12)
    assert target.stepk == gs.stepk


def test_unknown_and_duplicate_names_are_refused():
    with pytest.raises(ValueError, match="unknown metacal target 'nope'.*gauss"):
        metacal_target("nope", _psf(), STEP)
    with pytest.raises(ValueError, match="already registered"):
        register_metacal_target(DEFAULT_TARGET, METACAL_TARGETS[DEFAULT_TARGET])


def test_a_second_target_is_a_registration(monkeypatch):
    """A registered target goes through the GalSim reference and both fast engines (one PSF,
    several PSFs) by name; the fast ones agree with the reference as for the default."""
    monkeypatch.setitem(METACAL_TARGETS, "wide", _wide)
    rng = np.random.default_rng(3)
    psfs = np.array([_psf(2.8), _psf(3.4)])
    gal = galsim.Exponential(half_light_radius=2.0).shear(g1=0.2, g2=-0.1)
    stamps = np.array(
        [
            galsim.Convolve(gal, galsim.Moffat(beta=3.0, fwhm=f))
            .drawImage(nx=48, ny=48, scale=1.0)
            .array
            for f in (2.8, 3.4, 2.8)
        ]
    ) + rng.normal(0.0, 1e-3, (3, 48, 48))
    index = np.array([0, 1, 0])
    ref, sigma = metacal_versions(
        stamps, psfs, STEP, engine="galsim", psf_index=index, target="wide"
    )
    fast, sigma_fast = metacal_versions(
        stamps, psfs, STEP, engine="fast", psf_index=index, target="wide"
    )
    one = metacal_images(stamps[0], psfs[0], STEP, engine="fast", target="wide")
    np.testing.assert_array_equal(sigma, sigma_fast)
    assert sigma[0] == pytest.approx(1.5 * psf_sigma(psfs[0]))
    assert one.target_sigma == sigma[0]
    peak = ref["noshear"].max(axis=(1, 2))
    for kind in TYPES:
        err = np.abs(fast[kind] - ref[kind]).max(axis=(1, 2)) / peak
        assert err.max() < 1e-5, kind
        assert np.abs(one.images[kind] - ref[kind][0]).max() / peak[0] < 1e-5, kind
    wider = metacal_versions(stamps[:1], psfs[0], STEP, engine="fast")[0]["noshear"][0]
    assert ref["noshear"][0].max() < 0.9 * wider.max()  # the wide target, not the default
    assert WideGauss(1.0).cards()[TARGET_CARD][0] == "wide"  # a non-default target
