"""Metacalibration image operation, GalSim reference (issue 23; no command uses it yet).

Each stamp is deconvolved by its PSF image, sheared by ``±step`` along g1 and g2, and
reconvolved with a round Gaussian target PSF slightly wider than the PSF, giving the five
versions :data:`TYPES`. With ``noise_sigma``, metacal's fixnoise is applied: a noise field of
that level, rotated by 90 degrees, goes through the same operation, is rotated back and added
to every version, so that the noise the operation shears and correlates no longer depends on
the applied shear (to first order), at the cost of twice the noise variance.
Arrays in and out; pixel units (scale 1).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import galsim
import numpy as np

from megalut_cli.measure.features import measure_stamps

#: The five versions of a stamp, in output order.
TYPES = ("noshear", "1p", "1m", "2p", "2m")
#: The applied shear of each version, for a step of 1.
SHEARS = {"noshear": (0.0, 0.0), "1p": (1.0, 0.0), "1m": (-1.0, 0.0), "2p": (0.0, 1.0), "2m": (0.0, -1.0)}
DEFAULT_STEP = 0.01
#: The interpolant of the stamp and PSF images (ngmix's choice; lanczos15 keeps the
#: interpolation error of a sheared, deconvolved image at the 1e-4 level).
INTERPOLANT = "lanczos15"


@dataclass(frozen=True)
class MetacalImages:
    """The five versions of one stamp (``images[type]``, float64, the stamp's shape) and the
    sigma (pixels) of the round Gaussian target PSF they are convolved with."""

    images: dict[str, np.ndarray]
    target_sigma: float


@dataclass(frozen=True)
class _Operation:
    """What the operation needs of a PSF image: the PSF to deconvolve, the target to
    reconvolve with, and the step (built once per PSF)."""

    psf: galsim.GSObject
    target: galsim.Gaussian
    step: float


def target_psf_sigma(psf_image: np.ndarray, step: float = DEFAULT_STEP) -> float:
    """Sigma of the round Gaussian target PSF: the adaptive-moment sigma of ``psf_image``
    (which holds the pixel), dilated by ``1 + 2|step|`` so that the sheared, deconvolved
    galaxy's high frequencies stay under the target."""
    res = galsim.hsm.FindAdaptiveMom(galsim.ImageD(np.asarray(psf_image, dtype=np.float64), scale=1.0))
    # the round-equivalent size of an elliptical PSF: sigma = det(M)^(1/4)
    return float(res.moments_sigma) * (1.0 + 2.0 * abs(step))


def _finite_2d(image: np.ndarray, what: str) -> None:
    if image.ndim != 2:
        raise ValueError(f"the {what} must be a 2-d array")
    if not np.isfinite(image).all():
        raise ValueError(f"the {what} holds NaN or infinite pixels")


def _operation(psf_image: np.ndarray, step: float) -> _Operation:
    """The operation for one PSF image (checked) and step."""
    _finite_2d(psf_image, "PSF image")
    if psf_image.sum() <= 0:
        raise ValueError("the PSF image has no positive flux")
    if not 0.0 < step < 0.1:
        raise ValueError(f"metacal step {step}: expected 0 < step < 0.1")
    psf = galsim.InterpolatedImage(galsim.ImageD(psf_image / psf_image.sum(), scale=1.0), x_interpolant=INTERPOLANT)
    return _Operation(psf, galsim.Gaussian(sigma=target_psf_sigma(psf_image, step)), step)


def _versions(image: np.ndarray, op: _Operation) -> dict[str, np.ndarray]:
    """The five sheared and reconvolved versions of ``image`` (deconvolved by ``op.psf``)."""
    ny, nx = image.shape
    obj = galsim.InterpolatedImage(galsim.ImageD(image, scale=1.0), x_interpolant=INTERPOLANT)
    deconvolved = galsim.Convolve(obj, galsim.Deconvolve(op.psf))
    out = {}
    for kind in TYPES:
        s1, s2 = SHEARS[kind]
        sheared = deconvolved if kind == "noshear" else deconvolved.shear(g1=s1 * op.step, g2=s2 * op.step)
        drawn = galsim.Convolve(sheared, op.target).drawImage(nx=nx, ny=ny, scale=1.0, method="no_pixel")
        out[kind] = drawn.array.astype(np.float64)
    return out


def _apply(stamp: np.ndarray, op: _Operation, noise_sigma: float | None, seed: int) -> MetacalImages:
    stamp = np.asarray(stamp, dtype=np.float64)
    _finite_2d(stamp, "stamp")
    images = _versions(stamp, op)
    if noise_sigma is not None and noise_sigma > 0:
        noise = np.random.default_rng(seed).normal(0.0, noise_sigma, stamp.shape)
        rotated = _versions(np.rot90(noise, 1), op)
        for kind in TYPES:  # rotated back: its applied shear is the opposite of the stamp's
            images[kind] = images[kind] + np.rot90(rotated[kind], -1)
    return MetacalImages(images, op.target.sigma)


def metacal_images(
    stamp: np.ndarray,
    psf_image: np.ndarray,
    step: float = DEFAULT_STEP,
    noise_sigma: float | None = None,
    seed: int = 0,
) -> MetacalImages:
    """The five metacal versions of ``stamp`` with the PSF image ``psf_image`` (both centred
    like GalSim's images: the true centre of an even-sized image is between pixels).

    ``noise_sigma``: the stamp's noise level; when given, fixnoise adds the operation's image
    of a rotated noise field of that level, drawn from ``seed``.
    """
    return _apply(stamp, _operation(np.asarray(psf_image, dtype=np.float64), step), noise_sigma, seed)


def metacal_features(
    stamps: np.ndarray,
    psf_images: np.ndarray,
    step: float = DEFAULT_STEP,
    noise_sigma: Sequence[float] | np.ndarray | None = None,
    seeds: Sequence[int] | np.ndarray | None = None,
    **measure_kw: Any,
) -> dict[str, np.ndarray]:
    """Features of the five metacal versions of a stack of stamps ``(n, S, S)``: every column
    ``X`` of :func:`~megalut_cli.measure.features.measure_stamps` as ``X_<type>``.

    ``psf_images``: one PSF image ``(P, P)`` for all stamps, or one per stamp ``(n, P, P)``.
    ``noise_sigma`` (per stamp; e.g. the measured ``skymad``) turns fixnoise on, with the
    per-stamp ``seeds`` (default: the stamp index). ``measure_kw`` go to ``measure_stamps``.
    """
    stamps = np.asarray(stamps, dtype=np.float64)
    psfs = np.asarray(psf_images, dtype=np.float64)
    n = len(stamps)
    if psfs.ndim == 3 and psfs.shape[0] != n:
        raise ValueError(f"{psfs.shape[0]} PSF images for {n} stamps")
    shared = _operation(psfs, step) if psfs.ndim == 2 else None  # one PSF: built once
    sigmas = [None] * n if noise_sigma is None else [float(v) for v in noise_sigma]
    seeds = np.arange(n) if seeds is None else np.asarray(seeds, dtype=np.int64)
    versions = {kind: np.empty_like(stamps) for kind in TYPES}
    for i in range(n):
        op = shared if shared is not None else _operation(psfs[i], step)
        mc = _apply(stamps[i], op, sigmas[i], int(seeds[i]))
        for kind in TYPES:
            versions[kind][i] = mc.images[kind]
    out: dict[str, np.ndarray] = {}
    for kind in TYPES:
        for name, values in measure_stamps(versions[kind], **measure_kw).items():
            out[f"{name}_{kind}"] = values
    return out
