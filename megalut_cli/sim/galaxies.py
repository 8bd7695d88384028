"""Galaxy profiles and their true parameters (Sersic or Gaussian, in pixel units).

Fluxes (ADU) come directly, from a surface brightness ``F = S * pi * R^2`` (the paper's
fiducial coupling of size and flux), or from a magnitude with the instrument zero-point,
exposure time and gain, ``F = t / G * 10^(-0.4 (m - Zp))``. The intrinsic ellipticity is
a GalSim reduced-shear-type ellipticity of modulus ``|e| = (1 - q) / (1 + q)`` and position
angle ``theta``: ``e1 = |e| cos 2 theta``, ``e2 = |e| sin 2 theta``. The lensing shear is
applied after this intrinsic shape (and its rotation).
"""

from __future__ import annotations

from collections.abc import Mapping

import galsim
import numpy as np

#: One GSParams object for every profile, so that GalSim's Sersic cache is shared.
GSPARAMS = galsim.GSParams()


def flux_from_mag(mag: np.ndarray, zeropoint: float, exptime: float, gain: float) -> np.ndarray:
    """Flux in ADU of magnitude ``mag``: ``t / G * 10^(-0.4 (m - Zp))``."""
    return exptime / gain * 10.0 ** (-0.4 * (np.asarray(mag, dtype=float) - zeropoint))


def mag_from_flux(flux: np.ndarray, zeropoint: float, exptime: float, gain: float) -> np.ndarray:
    """Inverse of :func:`flux_from_mag` (NaN for non-positive fluxes)."""
    f = np.asarray(flux, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        m = zeropoint - 2.5 * np.log10(f * gain / exptime)
    return np.where(f > 0, m, np.nan)


def galaxy_fluxes(
    flux_mode: str, values: np.ndarray, rad: np.ndarray, instrument: Mapping[str, float]
) -> np.ndarray:
    """True fluxes (ADU) from the configured flux parameter (``flux``, ``sb`` or ``mag``)."""
    values = np.asarray(values, dtype=float)
    if flux_mode == "flux":
        return values
    if flux_mode == "sb":
        return values * np.pi * np.asarray(rad, dtype=float) ** 2
    if flux_mode == "mag":
        return flux_from_mag(values, instrument["zeropoint"], instrument["exptime"], instrument["gain"])
    raise ValueError(f"unknown flux mode {flux_mode!r}")


def ellipticity_components(modulus: np.ndarray, angle_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(e1, e2)`` of ellipticity ``modulus`` at position angle ``angle_deg`` (degrees)."""
    two_theta = np.deg2rad(2.0 * np.asarray(angle_deg, dtype=float))
    m = np.asarray(modulus, dtype=float)
    return m * np.cos(two_theta), m * np.sin(two_theta)


def make_gsparams(settings: Mapping[str, float] | None) -> galsim.GSParams:
    """The GSParams of the ``[gsparams]`` config table (GalSim's defaults when empty)."""
    return galsim.GSParams(**settings) if settings else GSPARAMS


def base_profile(
    profile: str, rad: float, flux: float, sersicn: float | None = None, gsparams: galsim.GSParams = GSPARAMS
) -> galsim.GSObject:
    """A round profile of half-light radius ``rad`` (pixels) and ``flux`` (ADU)."""
    if profile == "sersic":
        return galsim.Sersic(n=float(sersicn), half_light_radius=float(rad), flux=float(flux), gsparams=gsparams)
    if profile == "gaussian":
        return galsim.Gaussian(half_light_radius=float(rad), flux=float(flux), gsparams=gsparams)
    raise ValueError(f"unknown galaxy profile {profile!r}")


def shaped(base: galsim.GSObject, e1: float, e2: float, g1: float, g2: float) -> galsim.GSObject:
    """``base`` with intrinsic ellipticity (e1, e2), then lensed by reduced shear (g1, g2)."""
    gal = base
    if e1 != 0.0 or e2 != 0.0:
        gal = gal.shear(g1=float(e1), g2=float(e2))
    if g1 != 0.0 or g2 != 0.0:
        gal = gal.shear(g1=float(g1), g2=float(g2))
    return gal
