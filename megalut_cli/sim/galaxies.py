"""Galaxy profiles and their true parameters (Sersic, Gaussian, bulge + disk, knots,
COSMOS fits or real, in pixel units).

Fluxes (ADU) come directly, from a surface brightness ``F = S * pi * R^2`` (the paper's
fiducial coupling of size and flux), or from a magnitude with the instrument zero-point,
exposure time and gain, ``F = t / G * 10^(-0.4 (m - Zp))``. The intrinsic ellipticity is
a GalSim reduced-shear-type ellipticity of modulus ``|e| = (1 - q) / (1 + q)`` and position
angle ``theta``: ``e1 = |e| cos 2 theta``, ``e2 = |e| sin 2 theta``. The lensing shear is
applied after this intrinsic shape (and its rotation).

Bulge + disk (``profile = "bulgedisk"``), COSMOS-fit (``"cosmos_fit"``) galaxies and
galaxies with star-forming knots are built from their truth row in their own frame (the
disk's major axis along x; :func:`galaxy_profile`), then rotated and lensed
(:func:`oriented`); ``tru_rad`` is then the half-light radius of the round composite.

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


# --------------------------------------------------------------------------- composite models
#
# Bulge + disk, knots and COSMOS-fit galaxies are built in their own frame (the disk's major
# axis along x) from their truth row, then rotated by the position angle and lensed
# (:func:`oriented`), so that every realization of a ring is an exact rotated copy.

#: Profiles built by :func:`galaxy_profile` from the composite truth columns.
COMPOSITE_PROFILES = ("bulgedisk", "cosmos_fit")
#: GalSim's Sersic range used for the COSMOS fits (as ``galsim.COSMOSCatalog`` clamps them).
COSMOS_SERSIC_RANGE = (0.3, 6.0)


def sersic_b(n: np.ndarray) -> np.ndarray:
    """``b_n`` of a Sersic profile ``I ~ exp(-b_n (r/R)^(1/n))`` of half-light radius R."""
    from scipy.special import gammaincinv

    return gammaincinv(2.0 * np.asarray(n, dtype=float), 0.5)


def sersic_enclosed(radius_over_hlr: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Fraction of the flux of an untruncated round Sersic profile inside ``r / R``."""
    from scipy.special import gammainc

    n = np.asarray(n, dtype=float)
    x = np.asarray(radius_over_hlr, dtype=float)
    return gammainc(2.0 * n, sersic_b(n) * np.maximum(x, 0.0) ** (1.0 / n))


def composite_hlr(
    bulge_fraction: np.ndarray, rad_ratio: np.ndarray, bulge_n: np.ndarray, disk_n: np.ndarray | float = 1.0
) -> np.ndarray:
    """Half-light radius of a round disk (index ``disk_n``, half-light radius 1) plus a round
    concentric bulge (index ``bulge_n``, half-light radius ``rad_ratio``) holding the flux
    fraction ``bulge_fraction``; found by bisection (it lies between the two radii)."""
    b, r, nb, nd = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (bulge_fraction, rad_ratio, bulge_n, disk_n)))
    lo = np.log(np.minimum(1.0, r))
    hi = np.log(np.maximum(1.0, r))
    safe_r = np.where(r > 0, r, 1.0)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        x = np.exp(mid)
        inside = b * sersic_enclosed(x / safe_r, nb) + (1.0 - b) * sersic_enclosed(x, nd)
        below = inside < 0.5
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    out = np.exp(0.5 * (lo + hi))
    return np.where(b <= 0.0, 1.0, np.where(b >= 1.0, r, out))


def q_to_ellipticity(q: np.ndarray) -> np.ndarray:
    """Ellipticity modulus ``(1 - q) / (1 + q)`` of an axis ratio ``q`` (GalSim's g)."""
    q = np.asarray(q, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):  # unused fits hold q = -1
        return (1.0 - q) / (1.0 + q)


def bulgedisk_truth(
    gvals: dict[str, np.ndarray], sersicn_step: float
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """``profile = "bulgedisk"``: the composite half-light radius (``rad``) sets the disk's
    and the bulge's; returns ``(rad, truth columns)``."""
    from megalut_cli.sim.config import round_sersicn

    rad = np.asarray(gvals["rad"], dtype=float)
    frac = np.asarray(gvals["bulge_fraction"], dtype=float)
    ratio = np.asarray(gvals["bulge_rad_ratio"], dtype=float)
    nb = round_sersicn(gvals["bulge_sersicn"], sersicn_step)
    disk_rad = rad / composite_hlr(frac, ratio, nb)
    cols = {
        "tru_disk_rad": disk_rad,
        "tru_disk_sersicn": np.ones_like(rad),
        "tru_bulge_fraction": frac,
        "tru_bulge_rad": ratio * disk_rad,
        "tru_bulge_sersicn": nb,
        "tru_bulge_ell": np.asarray(gvals["bulge_ellipticity"], dtype=float),
        "tru_bulge_dtheta": np.asarray(gvals["bulge_angle"], dtype=float),
        "tru_bulge_dx": np.asarray(gvals["bulge_dx"], dtype=float),
        "tru_bulge_dy": np.asarray(gvals["bulge_dy"], dtype=float),
    }
    return rad, cols


def cosmos_fit_truth(
    gvals: dict[str, np.ndarray], fit: str, pixel_scale: float | None, sersicn_step: float
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """``profile = "cosmos_fit"``: the parametric fit of the sampled catalog row, as
    ``galsim.COSMOSCatalog`` builds it (``_buildParametric``), in simulation pixels of
    ``pixel_scale`` arcsec, or dilated to the composite half-light radius ``gvals["rad"]``.

    Returns ``(rad, truth columns)``; ``gvals["ellipticity"]`` is set to the (disk's or
    single Sersic's) ellipticity modulus. The fit's own position angle is replaced by the
    simulation's (``angle``); the bulge keeps its angle relative to the disk.
    """
    from megalut_cli.sim.config import round_sersicn

    n_rows = len(gvals["fit_ident"])
    use_bulge = {
        "sersic": np.zeros(n_rows, dtype=bool),
        "bulgedisk": np.ones(n_rows, dtype=bool),
        "auto": np.asarray(gvals.get("fit_use_bulge", np.zeros(n_rows)), dtype=float) > 0.5,
    }[fit]
    nan = np.full(n_rows, np.nan)

    def get(name: str) -> np.ndarray:  # fit columns absent for this fit: NaN
        return np.asarray(gvals.get(name, nan), dtype=float)

    n_single = round_sersicn(np.clip(get("fit_n"), *COSMOS_SERSIC_RANGE), sersicn_step)
    fb, fd = get("fit_bulge_flux"), get("fit_disk_flux")
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(use_bulge, fb / (fb + fd), 0.0)
        ratio = np.where(use_bulge, get("fit_bulge_hlr") / get("fit_disk_hlr"), np.nan)
    disk_hlr = np.where(use_bulge, get("fit_disk_hlr"), get("fit_hlr"))  # arcsec
    disk_n = np.where(use_bulge, 1.0, n_single)
    hlr = disk_hlr * composite_hlr(frac, np.where(use_bulge, ratio, 1.0), 4.0, disk_n)
    if "rad" in gvals:
        rad = np.asarray(gvals["rad"], dtype=float)
        to_pixels = rad / hlr
    else:
        to_pixels = np.full(n_rows, 1.0 / float(pixel_scale))
        rad = hlr * to_pixels
    disk_rad = disk_hlr * to_pixels
    gvals["ellipticity"] = q_to_ellipticity(np.where(use_bulge, get("fit_disk_q"), get("fit_q")))
    cols: dict[str, np.ndarray] = {"tru_cosmos_ident": np.round(get("fit_ident")).astype(np.int64)}
    if fit == "sersic":
        cols["tru_sersicn"] = n_single
        return rad, cols
    dtheta = np.rad2deg(get("fit_bulge_beta") - get("fit_disk_beta"))
    cols.update({
        "tru_disk_rad": disk_rad,
        "tru_disk_sersicn": disk_n,
        "tru_bulge_fraction": frac,
        "tru_bulge_rad": np.where(use_bulge, ratio * disk_rad, np.nan),
        "tru_bulge_sersicn": np.where(use_bulge, 4.0, np.nan),
        "tru_bulge_ell": np.where(use_bulge, q_to_ellipticity(get("fit_bulge_q")), np.nan),
        "tru_bulge_dtheta": np.where(use_bulge, np.mod(dtheta + 90.0, 180.0) - 90.0, np.nan),
        "tru_bulge_dx": np.zeros(n_rows),
        "tru_bulge_dy": np.zeros(n_rows),
    })
    return rad, cols


def is_framed(truth: Mapping[str, np.ndarray]) -> bool:
    """Whether galaxies of these truth columns are built in their own frame and rotated
    (composites, knots), rather than round and sheared by their ellipticity."""
    return "tru_disk_rad" in truth or "tru_knots" in truth


def _component(n: float, rad: float, flux: float, gsparams: galsim.GSParams) -> galsim.GSObject:
    if n == 1.0:
        return galsim.Exponential(half_light_radius=rad, flux=flux, gsparams=gsparams)
    return galsim.Sersic(n=n, half_light_radius=rad, flux=flux, gsparams=gsparams)


def galaxy_profile(
    profile: str, truth: Mapping[str, np.ndarray], k: int, gsparams: galsim.GSParams = GSPARAMS
) -> galsim.GSObject:
    """The galaxy of row ``k`` of the truth columns (pixel units, flux ``tru_flux``), before
    its orientation and the lensing shear (:func:`oriented`).

    Plain Sersic and Gaussian galaxies are round. Framed galaxies (:func:`is_framed`) have
    the disk's (or single profile's) major axis along x: a disk of ellipticity ``tru_ell``
    whose flux fraction ``tru_knots_fraction`` sits in ``tru_knots`` GalSim ``RandomKnots``
    sampled from the disk's own profile (seed ``tru_knot_seed``), plus a bulge of flux
    fraction ``tru_bulge_fraction``, ellipticity ``tru_bulge_ell`` at ``tru_bulge_dtheta``
    degrees from the disk's axis, centred at (``tru_bulge_dx``, ``tru_bulge_dy``).
    """
    def val(name: str) -> float:
        return float(truth[name][k])

    flux = val("tru_flux")
    single = "gaussian" if profile == "gaussian" else "sersic"  # a cosmos_fit "sersic" fit is a Sersic
    if not is_framed(truth):
        return base_profile(single, val("tru_rad"), flux, val("tru_sersicn") if "tru_sersicn" in truth else None,
                            gsparams)
    frac = val("tru_bulge_fraction") if "tru_bulge_fraction" in truth else 0.0
    disk_flux = (1.0 - frac) * flux
    if "tru_disk_rad" in truth:
        disk_unit = _component(val("tru_disk_sersicn"), val("tru_disk_rad"), 1.0, gsparams)
    else:  # a Sersic or Gaussian galaxy with knots
        disk_unit = base_profile(single, val("tru_rad"), 1.0,
                                 val("tru_sersicn") if "tru_sersicn" in truth else None, gsparams)
    n_knots = int(truth["tru_knots"][k]) if "tru_knots" in truth else 0
    knot_frac = val("tru_knots_fraction") if n_knots > 0 else 0.0
    parts = []
    if knot_frac < 1.0:
        parts.append(disk_unit.withFlux(disk_flux * (1.0 - knot_frac)))
    if knot_frac > 0.0 and disk_flux > 0.0:
        parts.append(galsim.RandomKnots(n_knots, profile=disk_unit.withFlux(disk_flux * knot_frac),
                                        rng=galsim.BaseDeviate(int(truth["tru_knot_seed"][k])), gsparams=gsparams))
    disk = parts[0] if len(parts) == 1 else galsim.Add(parts, gsparams=gsparams)
    ell = val("tru_ell")
    if ell > 0.0:
        disk = disk.shear(g=ell, beta=0.0 * galsim.degrees)
    if frac <= 0.0:
        return disk
    bulge = _component(val("tru_bulge_sersicn"), val("tru_bulge_rad"), frac * flux, gsparams)
    if val("tru_bulge_ell") > 0.0:
        bulge = bulge.shear(g=val("tru_bulge_ell"), beta=val("tru_bulge_dtheta") * galsim.degrees)
    if val("tru_bulge_dx") != 0.0 or val("tru_bulge_dy") != 0.0:
        bulge = bulge.shift(val("tru_bulge_dx"), val("tru_bulge_dy"))
    if frac >= 1.0:
        return bulge
    return galsim.Add([disk, bulge], gsparams=gsparams)


def oriented(base: galsim.GSObject, truth: Mapping[str, np.ndarray], k: int, theta_deg: float) -> galsim.GSObject:
    """Galaxy ``base`` of row ``k`` (from :func:`galaxy_profile`) at position angle
    ``theta_deg`` (with its intrinsic shape), then lensed by (``tru_g1``, ``tru_g2``)."""
    g1, g2 = float(truth["tru_g1"][k]), float(truth["tru_g2"][k])
    if is_framed(truth):
        return rotated(base, theta_deg, g1, g2)
    return shaped(base, float(truth["tru_e1"][k]), float(truth["tru_e2"][k]), g1, g2)
