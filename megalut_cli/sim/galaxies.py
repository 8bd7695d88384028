"""Galaxy profiles and their true parameters (Sersic, Gaussian or real, in pixel units).

Fluxes (ADU) come directly, from a surface brightness ``F = S * pi * R^2`` (the paper's
fiducial coupling of size and flux), or from a magnitude with the instrument zero-point,
exposure time and gain, ``F = t / G * 10^(-0.4 (m - Zp))``. The intrinsic ellipticity is
a GalSim reduced-shear-type ellipticity of modulus ``|e| = (1 - q) / (1 + q)`` and position
angle ``theta``: ``e1 = |e| cos 2 theta``, ``e2 = |e| sin 2 theta``. The lensing shear is
applied after this intrinsic shape (and its rotation).

Real galaxies (``profile = "real"``) are HST images of a GalSim ``RealGalaxyCatalog``,
deconvolved from their HST PSF (``galsim.RealGalaxy``), scaled to the requested flux,
dilated from arcsec to simulation pixels, rotated by the position angle, then lensed.
Their own HST noise, correlated and sheared with them, is padded over the stamp and
symmetrized (or whitened) before the simulation's noise is added: see ``docs/config.md``.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Mapping
from typing import Any

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


@functools.lru_cache(maxsize=4)
def real_galaxy_catalog(path: str, image_dir: str) -> galsim.RealGalaxyCatalog:
    """A GalSim RealGalaxyCatalog, loaded once per process (images preloaded)."""
    from megalut_cli.catalog import catalog_info
    from megalut_cli.errors import InputError

    _, names, _ = catalog_info(path)
    missing = [c for c in ("GAL_FILENAME", "PSF_FILENAME", "GAL_HDU", "PSF_HDU", "PIXEL_SCALE")
               if c.lower() not in {n.lower() for n in names}]
    if missing:
        raise InputError(
            f"galaxy.real_catalog: {path}: not a readable GalSim RealGalaxyCatalog (no column {', '.join(missing)})"
        )
    try:
        # An absolute file name is kept as is; ``dir`` is where the images are.
        rgc = galsim.RealGalaxyCatalog(os.path.abspath(path), dir=image_dir, preload=False)
        files = set(map(str, rgc.gal_file_name)) | set(map(str, rgc.psf_file_name))
        absent = sorted(f for f in files if not os.path.isfile(f))
        if absent:
            raise InputError(f"galaxy.real_catalog: {path}: image file {absent[0]} not found (see galaxy.real_dir)")
        rgc.preload()
        return rgc
    except (OSError, ValueError, KeyError, galsim.GalSimError) as err:
        raise InputError(f"galaxy.real_catalog: {path}: not a readable GalSim RealGalaxyCatalog ({err})") from None


#: Fixed seed base of the noise padding of real galaxies (per catalog row: the padding,
#: like the HST noise inside the postage stamp, belongs to the galaxy image).
_PAD_SEED = 271828


@functools.lru_cache(maxsize=16)  # noise-padded profiles are big (tens of MB): few of them
def _real_unit(
    path: str, image_dir: str, index: int, pixel_scale: float, gsparams: galsim.GSParams, pad_pixels: float = 0.0
) -> tuple[galsim.GSObject, float]:
    """Real galaxy ``index`` (deconvolved from its HST PSF), flux 1, in simulation pixels,
    padded with HST-like correlated noise over ``pad_pixels`` (0: none); and its HST flux."""
    rgc = real_galaxy_catalog(path, image_dir)
    pad = pad_pixels * pixel_scale  # arcsec
    gal = galsim.RealGalaxy(rgc, index=int(index), noise_pad_size=pad,
                            rng=galsim.BaseDeviate(_PAD_SEED + int(index)) if pad else None, gsparams=gsparams)
    flux0 = float(gal.flux)
    return gal.withFlux(1.0).dilate(1.0 / pixel_scale), flux0  # arcsec -> pixels (dilate keeps the flux)


def real_footprint(real: Mapping[str, Any], index: int) -> float:
    """Half-diagonal (simulation pixels) of the HST postage stamp of catalog row ``index``:
    beyond it (plus the PSF), a drawn real galaxy holds only its noise padding."""
    rgc = real_galaxy_catalog(real["catalog"], real["dir"])
    img = rgc.getGalImage(int(index))
    ny, nx = img.array.shape
    return 0.5 * float(np.hypot(nx, ny)) * float(rgc.pixel_scale[int(index)]) / float(real["pixel_scale"])


def real_profile(
    real: Mapping[str, Any], index: int, flux: float, gsparams: galsim.GSParams = GSPARAMS, pad_pixels: float = 0.0
) -> galsim.GSObject:
    """Real galaxy ``index`` of the catalog described by ``real`` (see ``GalaxySpec.real``),
    with ``flux`` (ADU), in simulation pixels of ``real['pixel_scale']`` arcsec; with
    ``pad_pixels``, its HST noise extends over a square of that size (for symmetrizing)."""
    unit, _ = _real_unit(real["catalog"], real["dir"], int(index), float(real["pixel_scale"]), gsparams, float(pad_pixels))
    return unit.withFlux(float(flux))


@functools.lru_cache(maxsize=512)
def _hst_noise(path: str, image_dir: str, index: int) -> galsim.BaseCorrelatedNoise:
    """The HST correlated noise of catalog row ``index`` (pixel variance 1 in HST units),
    deconvolved from the HST PSF like the galaxy."""
    rgc = real_galaxy_catalog(path, image_dir)
    cn = galsim.getCOSMOSNoise(file_name=str(rgc.noise_file_name[index]), cosmos_scale=float(rgc.pixel_scale[index]),
                               variance=1.0)
    return cn.convolvedWith(galsim.Deconvolve(rgc.getPSF(index)))


def real_noise(
    real: Mapping[str, Any],
    index: int,
    flux: float,
    theta_deg: float,
    g1: float,
    g2: float,
    kernel: galsim.GSObject,
    seed: int,
    gsparams: galsim.GSParams = GSPARAMS,
) -> galsim.BaseCorrelatedNoise:
    """The correlated HST noise carried by a drawn real galaxy (pixel units), to symmetrize
    or whiten it.

    Built from the catalog's noise correlation function and variance, scaled by the flux
    ratio, and transformed like the galaxy (dilated to simulation pixels, rotated, lensed,
    convolved with ``kernel``: the PSF, times the pixel when drawing adds it). GalSim's own
    tracking (``RealGalaxy.noise``) gets the variance wrong when the pixel scale changes
    (GalSim issue 1071): the variance of an HST pixel value ``v`` is ``v / s**4`` in
    surface-brightness units of an ``s``-arcsec pixel, which is what is used here. The
    correlation *shape* of this model matches the noise-padded stamps; its variance is
    within ~20% at 0.2"/pixel but ~40% low at 0.05"/pixel (high-frequency noise boosted by
    the HST-PSF deconvolution), so the simulator rescales it to the variance measured on
    the stamp's own padding (``draw._process_hst_noise``; ``tests/test_great3_sim.py``).
    """
    rgc = real_galaxy_catalog(real["catalog"], real["dir"])
    i = int(index)
    _, flux0 = _real_unit(real["catalog"], real["dir"], i, float(real["pixel_scale"]), gsparams, 0.0)
    scale = float(rgc.pixel_scale[i])
    var = float(rgc.variance[i]) * (float(flux) / flux0) ** 2 / scale**4
    cn = _hst_noise(real["catalog"], real["dir"], i).withScaledVariance(var)  # built with variance 1
    cn = cn.dilate(1.0 / float(real["pixel_scale"])).rotate(float(theta_deg) * galsim.degrees)
    if g1 != 0.0 or g2 != 0.0:
        cn = cn.shear(g1=float(g1), g2=float(g2))
    cn = cn.convolvedWith(kernel)
    cn.rng.reset(int(seed))
    return cn


def rotated(base: galsim.GSObject, theta_deg: float, g1: float, g2: float) -> galsim.GSObject:
    """``base`` rotated by ``theta_deg`` (its intrinsic orientation), then lensed by (g1, g2)."""
    gal = base.rotate(float(theta_deg) * galsim.degrees) if theta_deg else base
    if g1 != 0.0 or g2 != 0.0:
        gal = gal.shear(g1=float(g1), g2=float(g2))
    return gal


def shaped(base: galsim.GSObject, e1: float, e2: float, g1: float, g2: float) -> galsim.GSObject:
    """``base`` with intrinsic ellipticity (e1, e2), then lensed by reduced shear (g1, g2)."""
    gal = base
    if e1 != 0.0 or e2 != 0.0:
        gal = gal.shear(g1=float(e1), g2=float(e2))
    if g1 != 0.0 or g2 != 0.0:
        gal = gal.shear(g1=float(g1), g2=float(g2))
    return gal
