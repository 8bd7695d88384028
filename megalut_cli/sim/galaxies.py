"""GalSim galaxies from their true parameters (Sersic, Gaussian, bulge + disk, knots,
COSMOS fits or real, in pixel units); which a config draws is its profile's choice
(:mod:`megalut_cli.sim.profiles`).

Fluxes and intrinsic ellipticities come from the drawn parameters
(:mod:`megalut_cli.sim.intrinsic`). The lensing shear is applied after the intrinsic shape
(and its rotation).

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
from collections import OrderedDict
from collections.abc import Callable, Mapping
from typing import Any

import galsim
import numpy as np

from megalut_cli.catalog import catalog_info
from megalut_cli.errors import InputError

#: One GSParams object for every profile, so that GalSim's Sersic cache is shared.
GSPARAMS = galsim.GSParams()


def make_gsparams(settings: Mapping[str, float] | None) -> galsim.GSParams:
    """The GSParams of the ``[gsparams]`` config table (GalSim's defaults when empty)."""
    return galsim.GSParams(**settings) if settings else GSPARAMS


def round_sersic(
    rad: float, flux: float, sersicn: float | None, gsparams: galsim.GSParams = GSPARAMS
) -> galsim.GSObject:
    """A round Sérsic of index ``sersicn``, half-light radius ``rad`` (pixels), ``flux`` (ADU)."""
    return galsim.Sersic(
        n=float(sersicn), half_light_radius=float(rad), flux=float(flux), gsparams=gsparams
    )


def round_gaussian(
    rad: float, flux: float, sersicn: float | None = None, gsparams: galsim.GSParams = GSPARAMS
) -> galsim.GSObject:
    """A round Gaussian of half-light radius ``rad`` (pixels) and ``flux`` (ADU)."""
    return galsim.Gaussian(half_light_radius=float(rad), flux=float(flux), gsparams=gsparams)


#: ``(rad, flux, sersicn, gsparams) -> profile``: a round single profile.
RoundProfile = Callable[[float, float, "float | None", galsim.GSParams], galsim.GSObject]
#: The round single profiles by the name of the fast renderer's family that reproduces them
#: (``GalaxyProfile.fast``, :mod:`megalut_cli.sim.render`).
ROUND_PROFILES: dict[str, RoundProfile] = {"sersic": round_sersic, "gaussian": round_gaussian}


def base_profile(
    profile: str,
    rad: float,
    flux: float,
    sersicn: float | None = None,
    gsparams: galsim.GSParams = GSPARAMS,
) -> galsim.GSObject:
    """The round profile of family ``profile`` (:data:`ROUND_PROFILES`): half-light radius
    ``rad`` (pixels), ``flux`` (ADU)."""
    if profile not in ROUND_PROFILES:
        raise ValueError(f"unknown galaxy profile {profile!r}")
    return ROUND_PROFILES[profile](rad, flux, sersicn, gsparams)


@functools.lru_cache(maxsize=4)
def real_galaxy_catalog(path: str, image_dir: str) -> galsim.RealGalaxyCatalog:
    """A GalSim RealGalaxyCatalog, loaded once per process (images preloaded)."""
    _, names, _ = catalog_info(path)
    missing = [
        c
        for c in ("GAL_FILENAME", "PSF_FILENAME", "GAL_HDU", "PSF_HDU", "PIXEL_SCALE")
        if c.lower() not in {n.lower() for n in names}
    ]
    if missing:
        raise InputError(
            f"galaxy.real_catalog: {path}: not a readable GalSim RealGalaxyCatalog "
            f"(no column {', '.join(missing)})"
        )
    try:
        # An absolute file name is kept as is; ``dir`` is where the images are.
        rgc = galsim.RealGalaxyCatalog(os.path.abspath(path), dir=image_dir, preload=False)
        files = set(map(str, rgc.gal_file_name)) | set(map(str, rgc.psf_file_name))
        absent = sorted(f for f in files if not os.path.isfile(f))
        if absent:
            raise InputError(
                f"galaxy.real_catalog: {path}: image file {absent[0]} not found "
                "(see galaxy.real_dir)"
            )
        rgc.preload()
        return rgc
    except (OSError, ValueError, KeyError, galsim.GalSimError) as err:
        raise InputError(
            f"galaxy.real_catalog: {path}: not a readable GalSim RealGalaxyCatalog ({err})"
        ) from None


#: Fixed seed base of the noise padding of real galaxies (per catalog row: the padding,
#: like the HST noise inside the postage stamp, belongs to the galaxy image).
_PAD_SEED = 271828
#: The zero-padded image that GalSim interpolates (in Fourier space) is made at least this
#: many times the side of the noise padding. GalSim pads only to the larger of the two, so a
#: small cutout's padding filled the whole interpolated image, whose periodic copies leaked
#: into the stamp (issue 39; ``examples/realgal/probe_padding.py``).
PAD_ZEROS = 4.0


def real_padded_side(real: Mapping[str, Any], index: int, pad_pixels: float) -> float:
    """Side (simulation pixels) of the square of HST noise around real galaxy ``index`` padded
    over ``pad_pixels``: GalSim rounds the padding up to an FFT size in HST pixels."""
    if not pad_pixels:
        return 0.0
    rgc = real_galaxy_catalog(real["catalog"], real["dir"])
    hst_scale = float(rgc.pixel_scale[int(index)])
    side = galsim.Image.good_fft_size(
        int(np.ceil(float(pad_pixels) * float(real["pixel_scale"]) / hst_scale))
    )
    return side * hst_scale / float(real["pixel_scale"])


#: Memory for the real galaxies kept built in one process (bytes). A padded galaxy holds
#: its zero-padded HST image and that image's transform: 24 MB for a 64-px stamp at
#: 0.06"/pixel, ten times more at 0.2"; building one costs 25-130 ms, drawing it 2-6 ms.
REAL_CACHE_BYTES = 768 << 20
_REAL_CACHE: OrderedDict[tuple[Any, ...], tuple[galsim.GSObject, float, int]] = OrderedDict()


def _real_unit(
    path: str,
    image_dir: str,
    index: int,
    pixel_scale: float,
    gsparams: galsim.GSParams,
    pad_pixels: float = 0.0,
) -> tuple[galsim.GSObject, float]:
    """Real galaxy ``index`` (deconvolved from its HST PSF), flux 1, in simulation pixels,
    padded with HST-like correlated noise over ``pad_pixels`` (0: none); and its HST flux.
    The most recently used ones are kept, up to :data:`REAL_CACHE_BYTES`."""
    key = (path, image_dir, int(index), float(pixel_scale), gsparams, float(pad_pixels))
    if key in _REAL_CACHE:
        _REAL_CACHE.move_to_end(key)
        unit, flux0, _ = _REAL_CACHE[key]
        return unit, flux0
    rgc = real_galaxy_catalog(path, image_dir)
    pad = pad_pixels * pixel_scale  # arcsec
    cutout = max(rgc.getGalImage(int(index)).array.shape)
    pad_factor = 4.0  # GalSim's default
    if pad:
        real = {"catalog": path, "dir": image_dir, "pixel_scale": pixel_scale}
        padded = real_padded_side(real, index, pad_pixels) * pixel_scale / rgc.pixel_scale[index]
        pad_factor = max(pad_factor, PAD_ZEROS * padded / cutout)
    gal = galsim.RealGalaxy(
        rgc,
        index=int(index),
        noise_pad_size=pad,
        pad_factor=pad_factor,
        rng=galsim.BaseDeviate(_PAD_SEED + int(index)) if pad else None,
        gsparams=gsparams,
    )
    flux0 = float(gal.flux)
    unit = gal.withFlux(1.0).dilate(1.0 / pixel_scale)  # arcsec -> pixels (keeps the flux)
    side = galsim.Image.good_fft_size(int(np.ceil(pad_factor * cutout)))
    _REAL_CACHE[key] = (unit, flux0, 24 * side * side)  # the image and its transform
    while sum(v[2] for v in _REAL_CACHE.values()) > REAL_CACHE_BYTES and len(_REAL_CACHE) > 1:
        _REAL_CACHE.popitem(last=False)
    return unit, flux0


def real_footprint(real: Mapping[str, Any], index: int) -> float:
    """Half-diagonal (simulation pixels) of the HST postage stamp of catalog row ``index``:
    beyond it (plus the PSF), a drawn real galaxy holds only its noise padding."""
    rgc = real_galaxy_catalog(real["catalog"], real["dir"])
    img = rgc.getGalImage(int(index))
    ny, nx = img.array.shape
    return (
        0.5
        * float(np.hypot(nx, ny))
        * float(rgc.pixel_scale[int(index)])
        / float(real["pixel_scale"])
    )


def real_profile(
    real: Mapping[str, Any],
    index: int,
    flux: float,
    gsparams: galsim.GSParams = GSPARAMS,
    pad_pixels: float = 0.0,
) -> galsim.GSObject:
    """Real galaxy ``index`` of the catalog described by ``real`` (see ``GalaxySpec.real``),
    with ``flux`` (ADU), in simulation pixels of ``real['pixel_scale']`` arcsec; with
    ``pad_pixels``, its HST noise extends over a square of that size (for symmetrizing)."""
    unit, _ = _real_unit(
        real["catalog"],
        real["dir"],
        int(index),
        float(real["pixel_scale"]),
        gsparams,
        float(pad_pixels),
    )
    return unit.withFlux(float(flux))


@functools.lru_cache(maxsize=512)
def _hst_noise(path: str, image_dir: str, index: int) -> galsim.BaseCorrelatedNoise:
    """The HST correlated noise of catalog row ``index`` (pixel variance 1 in HST units),
    deconvolved from the HST PSF like the galaxy."""
    rgc = real_galaxy_catalog(path, image_dir)
    cn = galsim.getCOSMOSNoise(
        file_name=str(rgc.noise_file_name[index]),
        cosmos_scale=float(rgc.pixel_scale[index]),
        variance=1.0,
    )
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
    within ~15% of the padding's (12% high at 0.2"/pixel, 8% low at 0.05"/pixel), so the
    simulator rescales it to the variance measured on the stamp's own padding
    (``draw._process_hst_noise``; ``tests/test_great3_sim.py``).
    """
    rgc = real_galaxy_catalog(real["catalog"], real["dir"])
    i = int(index)
    _, flux0 = _real_unit(
        real["catalog"], real["dir"], i, float(real["pixel_scale"]), gsparams, 0.0
    )
    scale = float(rgc.pixel_scale[i])
    var = float(rgc.variance[i]) * (float(flux) / flux0) ** 2 / scale**4
    cn = _hst_noise(real["catalog"], real["dir"], i).withScaledVariance(
        var
    )  # built with variance 1
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


def is_framed(truth: Mapping[str, np.ndarray]) -> bool:
    """Whether galaxies of these truth columns are built in their own frame and rotated
    (composites, knots, real images), rather than round and sheared by their ellipticity."""
    return "tru_disk_rad" in truth or "tru_knots" in truth or "tru_real_index" in truth


def _component(n: float, rad: float, flux: float, gsparams: galsim.GSParams) -> galsim.GSObject:
    if n == 1.0:
        return galsim.Exponential(half_light_radius=rad, flux=flux, gsparams=gsparams)
    return galsim.Sersic(n=n, half_light_radius=rad, flux=flux, gsparams=gsparams)


def galaxy_profile(
    truth: Mapping[str, np.ndarray],
    k: int,
    gsparams: galsim.GSParams = GSPARAMS,
    single: RoundProfile = round_sersic,
) -> galsim.GSObject:
    """The parametric galaxy of row ``k`` of the truth columns (pixel units, flux
    ``tru_flux``), before its orientation and the lensing shear (:func:`oriented`).

    A single profile (``single``: a Sérsic of index ``tru_sersicn``, or a Gaussian) is
    round. Framed galaxies (:func:`is_framed`) have the disk's (or single profile's) major
    axis along x: a disk of ellipticity ``tru_ell`` whose flux fraction
    ``tru_knots_fraction`` sits in ``tru_knots`` GalSim ``RandomKnots`` sampled from the
    disk's own profile (seed ``tru_knot_seed``), plus a bulge of flux fraction
    ``tru_bulge_fraction``, ellipticity ``tru_bulge_ell`` at ``tru_bulge_dtheta``
    degrees from the disk's axis, centred at (``tru_bulge_dx``, ``tru_bulge_dy``).
    """

    def val(name: str) -> float:
        return float(truth[name][k])

    flux = val("tru_flux")
    sersicn = val("tru_sersicn") if "tru_sersicn" in truth else None
    if not is_framed(truth):
        return single(val("tru_rad"), flux, sersicn, gsparams)
    frac = val("tru_bulge_fraction") if "tru_bulge_fraction" in truth else 0.0
    disk_flux = (1.0 - frac) * flux
    if "tru_disk_rad" in truth:
        disk_unit = _component(val("tru_disk_sersicn"), val("tru_disk_rad"), 1.0, gsparams)
    else:  # a single profile with knots
        disk_unit = single(val("tru_rad"), 1.0, sersicn, gsparams)
    n_knots = int(truth["tru_knots"][k]) if "tru_knots" in truth else 0
    knot_frac = val("tru_knots_fraction") if n_knots > 0 else 0.0
    parts = []
    if knot_frac < 1.0:
        parts.append(disk_unit.withFlux(disk_flux * (1.0 - knot_frac)))
    if knot_frac > 0.0 and disk_flux > 0.0:
        parts.append(
            galsim.RandomKnots(
                n_knots,
                profile=disk_unit.withFlux(disk_flux * knot_frac),
                rng=galsim.BaseDeviate(int(truth["tru_knot_seed"][k])),
                gsparams=gsparams,
            )
        )
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


def oriented(
    base: galsim.GSObject, truth: Mapping[str, np.ndarray], k: int, theta_deg: float
) -> galsim.GSObject:
    """Galaxy ``base`` of row ``k`` (from :func:`galaxy_profile`) at position angle
    ``theta_deg`` (with its intrinsic shape), then lensed by (``tru_g1``, ``tru_g2``)."""
    g1, g2 = float(truth["tru_g1"][k]), float(truth["tru_g2"][k])
    if is_framed(truth):
        return rotated(base, theta_deg, g1, g2)
    return shaped(base, float(truth["tru_e1"][k]), float(truth["tru_e2"][k]), g1, g2)
