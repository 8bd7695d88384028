"""The round Gaussian target (the default; ngmix's ``psf="gauss"``): sigma the PSF image's
adaptive-moment sigma dilated by ``1 + 2|step|``, so that the sheared, deconvolved galaxy's
high frequencies stay under it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import galsim
import numpy as np

from megalut_cli.measure.metacal_defaults import DEFAULT_TARGET
from megalut_cli.measure.metacal_targets.base import MetacalTarget

NAME = DEFAULT_TARGET


def dilated_sigma(psf_sigma: float | np.ndarray, step: float) -> float | np.ndarray:
    """The target's sigma from the PSF's adaptive-moment sigma: dilated by ``1 + 2|step|``."""
    return psf_sigma * (1.0 + 2.0 * abs(step))


def psf_sigma(psf_image: np.ndarray) -> float:
    """The adaptive-moment sigma of ``psf_image`` (the round-equivalent size of an elliptical
    PSF: ``det(M)^(1/4)``)."""
    res = galsim.hsm.FindAdaptiveMom(
        galsim.ImageD(np.asarray(psf_image, dtype=np.float64), scale=1.0)
    )
    return res.moments_sigma


@dataclass(frozen=True)
class GaussTarget(MetacalTarget):
    """A round Gaussian of standard deviation ``sigma_px`` pixels."""

    sigma_px: float
    name = NAME

    @property
    def sigma(self) -> float:
        return self.sigma_px

    def gsobject(self) -> galsim.Gaussian:
        return galsim.Gaussian(sigma=self.sigma_px)

    def kvalue(self, kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
        return np.exp(-0.5 * self.sigma_px**2 * (kx * kx + ky * ky))

    def kvalue_shifted(self, kx: np.ndarray, ky: np.ndarray, shift: float) -> np.ndarray:
        # one exponential (the arithmetic the fast engine has always used)
        return np.exp(-0.5 * self.sigma_px**2 * (kx * kx + ky * ky) + 1j * shift * (kx + ky))

    def grid_kvalue(self, k1: np.ndarray) -> np.ndarray:
        # separable: the product of the axes' factors
        g = np.exp(-0.5 * np.array([self.sigma_px])[:, None] ** 2 * (k1 * k1)[None, :])[0]
        return np.multiply.outer(g, g)

    def cards(self) -> dict[str, tuple[Any, str]]:
        """None: a catalog without the target card was measured with the round Gaussian."""
        return {}


def from_psf_sigma(sigma: float, step: float) -> GaussTarget:
    """The target of a PSF of adaptive-moment sigma ``sigma`` (e.g. ``psf_adamom_sigma``)."""
    return GaussTarget(float(dilated_sigma(sigma, step)))


def from_psf(psf_image: np.ndarray, step: float) -> GaussTarget:
    """The target of the PSF image ``psf_image`` (pixel included) and the shear ``step``."""
    return from_psf_sigma(psf_sigma(psf_image), step)
