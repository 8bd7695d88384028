"""The metacal target PSF as an object, and the registry of targets by name.

A target is the PSF the deconvolved, sheared stamp is reconvolved with. What the metacal
engines need of it: its profile for GalSim (the reference engine), its Fourier transform on
the fast engines' k grids, its ``stepk`` (GalSim's FFT period), its image on a stamp (the
``psf_<X>_<type>`` columns) and its header cards. A target module defines a
:class:`MetacalTarget` and a factory ``(psf_image, step) -> MetacalTarget`` (how it is built
from the PSF image and the shear step), registered by name in :mod:`.` (``__init__``).
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import Any

import numpy as np

from megalut_cli.measure.metacal_defaults import TARGET_CARD

#: A target's factory: the target for one PSF image (pixel included, scale 1) and step.
TargetFactory = Callable[[np.ndarray, float], "MetacalTarget"]

#: Every metacal target's factory by name, in the order of registration.
METACAL_TARGETS: dict[str, TargetFactory] = {}


class MetacalTarget(abc.ABC):
    """One target PSF (unit flux, pixel units, centred). Subclasses are hashable value
    objects (e.g. frozen dataclasses): the fast engines cache their plans on them."""

    #: The name it is registered under.
    name: str = ""

    @property
    @abc.abstractmethod
    def sigma(self) -> float:
        """Its round-equivalent size (pixels): what the catalogs record as the target's
        sigma."""

    @abc.abstractmethod
    def gsobject(self) -> Any:
        """Its GalSim profile (``galsim.GSObject``), for the reference engine."""

    @abc.abstractmethod
    def kvalue(self, kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
        """Its Fourier transform (real: the target is symmetric) at ``(kx, ky)``
        (radians per pixel)."""

    @property
    def stepk(self) -> float:
        """GalSim's ``stepk`` of its profile (sets the fast engines' FFT period)."""
        return float(self.gsobject().stepk)

    def kvalue_shifted(self, kx: np.ndarray, ky: np.ndarray, shift: float) -> np.ndarray:
        """:meth:`kvalue` times ``exp(i shift (kx + ky))``: the target drawn ``shift`` pixels
        off along both axes (the half-pixel centre of even-sized stamps); the Fourier kernel
        of :mod:`..metacal_fft`."""
        return self.kvalue(kx, ky) * np.exp(1j * shift * (kx + ky))

    def grid_kvalue(self, k1: np.ndarray) -> np.ndarray:
        """:meth:`kvalue` on the grid ``k1 x k1``, as ``[j, i]`` at ``(k1[i], k1[j])``: the
        Fourier kernel of :mod:`..metacal_fft_multi`."""
        return self.kvalue(k1[None, :], k1[:, None])

    def image(self, size: int) -> np.ndarray:
        """Its image on a ``size``-pixel stamp as the versions hold it (no pixel)."""
        return np.asarray(
            self.gsobject().drawImage(nx=size, ny=size, scale=1.0, method="no_pixel").array
        )

    def cards(self) -> dict[str, tuple[Any, str]]:
        """The header cards of a catalog measured with it: its name."""
        return {TARGET_CARD: (self.name, "metacal target PSF")}


def register_metacal_target(name: str, factory: TargetFactory) -> None:
    """Make ``factory`` (``(psf_image, step) -> MetacalTarget``) the metacal target ``name``
    (the one place a target is added)."""
    if name in METACAL_TARGETS:
        raise ValueError(f"metacal target {name!r} is already registered")
    METACAL_TARGETS[name] = factory


def metacal_target(name: str, psf_image: np.ndarray, step: float) -> MetacalTarget:
    """The target ``name`` for the PSF image ``psf_image`` and the shear ``step``."""
    try:
        factory = METACAL_TARGETS[name]
    except KeyError:
        known = ", ".join(METACAL_TARGETS)
        raise ValueError(f"unknown metacal target {name!r}; expected one of {known}") from None
    return factory(psf_image, step)
