"""The intrinsic values of simulated galaxies from their drawn parameters (plain numpy).

Fluxes (ADU) come directly, from a surface brightness ``F = S * pi * R^2`` (the paper's
fiducial coupling of size and flux), or from a magnitude with the instrument zero-point,
exposure time and gain, ``F = t / G * 10^(-0.4 (m - Zp))``. The intrinsic ellipticity is
a GalSim reduced-shear-type ellipticity of modulus ``|e| = (1 - q) / (1 + q)`` and position
angle ``theta``: ``e1 = |e| cos 2 theta``, ``e2 = |e| sin 2 theta``
(:mod:`megalut_cli.sim.galaxies` builds the galaxies).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np


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
        return flux_from_mag(
            values, instrument["zeropoint"], instrument["exptime"], instrument["gain"]
        )
    raise ValueError(f"unknown flux mode {flux_mode!r}")


def ellipticity_components(
    modulus: np.ndarray, angle_deg: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(e1, e2)`` of ellipticity ``modulus`` at position angle ``angle_deg`` (degrees)."""
    two_theta = np.deg2rad(2.0 * np.asarray(angle_deg, dtype=float))
    m = np.asarray(modulus, dtype=float)
    return m * np.cos(two_theta), m * np.sin(two_theta)
