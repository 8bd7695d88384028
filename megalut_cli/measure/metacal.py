"""Metacalibration image operation (issue 23): the GalSim reference and the engine dispatch.

Each stamp is deconvolved by its PSF image, sheared by ``±step`` along g1 and g2, and
reconvolved with a target PSF slightly wider than the PSF (chosen by name among
:mod:`.metacal_targets`; by default a round Gaussian), giving the five versions
:data:`TYPES`. With ``noise_sigma``, metacal's fixnoise is applied: a noise field of that
level, rotated by 90 degrees, goes through the same operation, is rotated back and added to
every version, so that the noise the operation shears and correlates no longer depends on
the applied shear (to first order), at the cost of twice the noise variance.
Arrays in and out; pixel units (scale 1).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import galsim
import numpy as np

from megalut_cli.measure import metacal_fft_multi
from megalut_cli.measure.feature_sets import compute_extra
from megalut_cli.measure.features import measure_stamps
from megalut_cli.measure.metacal_defaults import (
    DEFAULT_STEP,
    INTERPOLANT,
    MAX_STEP,
    SHEARS,
    TARGET_PSF_COLUMNS,
    TYPES,
)
from megalut_cli.measure.metacal_fft import fft_versions_fixnoise
from megalut_cli.measure.metacal_fft_nb import gather_fixnoise
from megalut_cli.measure.metacal_targets import DEFAULT_TARGET, MetacalTarget, gauss, metacal_target
from megalut_cli.measure.metacal_targets.gauss import GaussTarget
from megalut_cli.seeding import STREAM_METACAL, int_seed_for


@dataclass(frozen=True)
class MetacalImages:
    """The five versions of one stamp (``images[type]``, float64, the stamp's shape) and the
    sigma (pixels) of the target PSF they are convolved with."""

    images: dict[str, np.ndarray]
    target_sigma: float


@dataclass(frozen=True)
class _Operation:
    """What the operation needs of a PSF image: the PSF to deconvolve, the target to
    reconvolve with, and the step (built once per PSF)."""

    psf: galsim.GSObject
    target: MetacalTarget
    step: float


def target_psf_sigma(
    psf_image: np.ndarray, step: float = DEFAULT_STEP, target: str = DEFAULT_TARGET
) -> float:
    """Sigma of the target PSF of ``psf_image`` (which holds the pixel); for the round
    Gaussian: the PSF's adaptive-moment sigma dilated by ``1 + 2|step|`` so that the sheared,
    deconvolved galaxy's high frequencies stay under the target."""
    return float(metacal_target(target, np.asarray(psf_image), step).sigma)


def _finite_2d(image: np.ndarray, what: str) -> None:
    if image.ndim != 2:
        raise ValueError(f"the {what} must be a 2-d array")
    if not np.isfinite(image).all():
        raise ValueError(f"the {what} holds NaN or infinite pixels")


def _check_psf(psf_image: np.ndarray, step: float) -> None:
    """Raise ``ValueError`` unless ``psf_image`` and ``step`` suit the operation."""
    _finite_2d(psf_image, "PSF image")
    if psf_image.sum() <= 0:
        raise ValueError("the PSF image has no positive flux")
    if not 0.0 < step <= MAX_STEP:
        raise ValueError(f"metacal step {step}: expected 0 < step <= {MAX_STEP}")


def _operation(psf_image: np.ndarray, step: float, target: str) -> _Operation:
    """The operation for one PSF image (checked), step and target name."""
    _check_psf(psf_image, step)
    psf = galsim.InterpolatedImage(
        galsim.ImageD(psf_image / psf_image.sum(), scale=1.0), x_interpolant=INTERPOLANT
    )
    return _Operation(psf, metacal_target(target, psf_image, step), step)


def _versions(image: np.ndarray, op: _Operation) -> dict[str, np.ndarray]:
    """The five sheared and reconvolved versions of ``image`` (deconvolved by ``op.psf``)."""
    ny, nx = image.shape
    obj = galsim.InterpolatedImage(galsim.ImageD(image, scale=1.0), x_interpolant=INTERPOLANT)
    deconvolved = galsim.Convolve(obj, galsim.Deconvolve(op.psf))
    target = op.target.gsobject()
    out = {}
    for kind in TYPES:
        s1, s2 = SHEARS[kind]
        sheared = (
            deconvolved
            if kind == "noshear"
            else deconvolved.shear(g1=s1 * op.step, g2=s2 * op.step)
        )
        drawn = galsim.Convolve(sheared, target).drawImage(
            nx=nx, ny=ny, scale=1.0, method="no_pixel"
        )
        out[kind] = drawn.array.astype(np.float64)
    return out


def noise_field(sigma: float, seed: int, shape: tuple[int, int]) -> np.ndarray:
    """The fixnoise field of one stamp: Gaussian, of standard deviation ``abs(sigma)``, from
    ``seed``; a negative ``sigma`` gives the opposite field (antithetic twins)."""
    return sigma * np.random.default_rng(int(seed)).standard_normal(shape)


_SCRATCH = threading.local()
#: The largest work array (float64 elements, 512 MB) kept from call to call.
SCRATCH_MAX = 1 << 26


def _scratch(name: str, shape: tuple[int, ...]) -> np.ndarray:
    """A float64 work array of ``shape``, this thread's, reused from call to call (grown as
    needed, up to :data:`SCRATCH_MAX`): fresh pages cost about as much as the operation
    writing them (page faults)."""
    need = math.prod(shape)
    if need > SCRATCH_MAX:
        return np.empty(shape)
    buf = getattr(_SCRATCH, name, None)
    if buf is None or buf.size < need:
        buf = np.empty(need)
        setattr(_SCRATCH, name, buf)
    return buf[:need].reshape(shape)


def versions_buffer(n: int, size: int) -> np.ndarray:
    """A ``(5, n, size, size)`` float64 array for :func:`metacal_versions`'s ``out``, this
    thread's, reused from call to call: its contents last until the next call in this
    thread (for versions measured and dropped, as :func:`metacal_features` does)."""
    return _scratch("versions", (len(TYPES), n, size, size))


def _versions_array(out: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
    """The array ``(5, *shape)`` the versions of stamps of ``shape`` go into: a new one, or
    ``out`` (checked: C-contiguous float64 of that shape)."""
    if out is None:
        return np.empty((len(TYPES), *shape))
    if out.shape != (len(TYPES), *shape) or out.dtype != np.float64 or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous float64 array {(len(TYPES), *shape)}")
    return out


def _galsim_versions(images: np.ndarray, op: _Operation) -> dict[str, np.ndarray]:
    """The GalSim reference operation on a stack ``(n, S, S)`` that shares one PSF."""
    out = {kind: np.empty_like(images) for kind in TYPES}
    for i, image in enumerate(images):
        for kind, version in _versions(image, op).items():
            out[kind][i] = version
    return out


def _with_fixnoise(
    stamps: np.ndarray,
    psf_image: np.ndarray,
    op: _Operation,
    sigmas: np.ndarray,
    seeds: np.ndarray,
    engine: str,
    out: np.ndarray | None = None,
    fields: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """The five versions of stamps sharing one PSF; where ``sigmas != 0`` (or for every stamp
    with its given ``fields``), with fixnoise: the operation's image of a 90-degree rotated
    noise field, rotated back, added (its applied shear is the opposite of the stamp's).
    ``out``: as :func:`metacal_versions`'s."""
    n, shape = len(stamps), stamps.shape[1:]
    noisy = np.arange(n) if fields is not None else np.flatnonzero(sigmas != 0)
    stack = _scratch("stack", (n + len(noisy), *shape))  # the stamps, then their rotated fields
    stack[:n] = stamps
    for k, i in enumerate(noisy):
        field = fields[i] if fields is not None else noise_field(sigmas[i], seeds[i], shape)
        stack[n + k] = np.rot90(field, 1)
    if engine == "fast":  # the fields' versions added block by block
        return fft_versions_fixnoise(stack, n, noisy, psf_image, op.step, op.target, out=out)
    versions = _galsim_versions(stack, op)
    out = _versions_array(out, stamps.shape)
    for v, kind in enumerate(TYPES):
        out[v] = versions[kind][:n]
        if len(noisy):
            out[v, noisy] += np.rot90(versions[kind][n:], -1, axes=(1, 2))
    return {kind: out[v] for v, kind in enumerate(TYPES)}


def _fast_several_psfs(
    stamps: np.ndarray,
    psfs: np.ndarray,
    psf_index: np.ndarray,
    step: float,
    sigmas: np.ndarray,
    seeds: np.ndarray,
    target: str,
    out: np.ndarray,
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """:func:`metacal_versions` with the fast engine and several PSFs: every stamp and its
    fixnoise field through one :func:`~.metacal_fft_multi.fft_versions_multi` call (the
    stamps in PSF order, each followed by its rotated field: a PSF's rows are contiguous),
    into ``out`` ``(5, n, S, S)``."""
    n, shape = len(stamps), stamps.shape[1:]
    targets: list[MetacalTarget | None] = [None] * len(psfs)
    sigma = np.full(len(psfs), np.nan)
    for j in np.unique(psf_index):
        _check_psf(psfs[j], step)
        targets[j] = metacal_target(target, psfs[j], step)
        sigma[j] = targets[j].sigma
    order = np.argsort(psf_index, kind="stable")
    noisy = sigmas[order] != 0
    rows = np.cumsum(1 + noisy) - (1 + noisy)  # each stamp's row; its field's is the next
    stack = _scratch("stack", (n + int(noisy.sum()), *shape))
    stack[rows] = stamps[order]
    for r, i in zip(rows[noisy], order[noisy]):
        stack[r + 1] = np.rot90(noise_field(sigmas[i], seeds[i], shape), 1)
    index = np.empty(len(stack), np.int64)
    index[rows] = psf_index[order]
    index[rows[noisy] + 1] = psf_index[order][noisy]
    work = _scratch("multi", (len(TYPES), len(stack), *shape))
    metacal_fft_multi.fft_versions_multi(stack, psfs, index, step, targets, out=work)
    gather_fixnoise(work, rows, noisy, order, out)  # each stamp's versions plus its field's
    return {kind: out[k] for k, kind in enumerate(TYPES)}, sigma[psf_index]


def metacal_versions(
    stamps: np.ndarray,
    psf_images: np.ndarray,
    step: float = DEFAULT_STEP,
    noise_sigma: Sequence[float] | np.ndarray | None = None,
    seeds: Sequence[int] | np.ndarray | None = None,
    engine: str = "galsim",
    psf_index: Sequence[int] | np.ndarray | None = None,
    target: str = DEFAULT_TARGET,
    out: np.ndarray | None = None,
    noise_fields: np.ndarray | None = None,
    fixnoise_signs: np.ndarray | None = None,
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The five metacal versions of a stack of stamps ``(n, S, S)``, as ``({type: (n, S, S)},
    target_sigma (n,))``.

    ``psf_images``: one PSF image ``(P, P)`` for all stamps, or a stack ``(m, P, P)`` with
    ``psf_index`` (n,) naming each stamp's (default: one per stamp, ``m == n``); stamps
    sharing a PSF go through the operation together.
    ``noise_sigma`` (per stamp; e.g. the measured ``skymad``; 0 or NaN: none) turns fixnoise
    on, each stamp's field drawn from its ``seeds`` entry (default: the stamp index).
    ``engine``: ``"galsim"`` (the reference, stamp by stamp) or ``"fast"`` (FFTs over the
    stack, :mod:`.metacal_fft`; with several PSFs, in one pass: :mod:`.metacal_fft_multi`).
    ``target``: the target PSF's name (:mod:`.metacal_targets`); the second array holds its
    sigma for each stamp. ``out``: a C-contiguous float64 array ``(5, n, S, S)`` the
    versions are written into (in :data:`TYPES` order; the result holds its views), e.g. a
    buffer reused from call to call. ``noise_fields`` ``(n, S, S)``: the fixnoise fields
    themselves (e.g. a noise image with the data's correlations) instead of fields drawn
    from ``noise_sigma`` and ``seeds``; one PSF only. ``fixnoise_signs`` (per stamp, +1 or
    -1): -1 adds the opposite of the stamp's field (the second of antithetic twins).
    """
    stamps = np.asarray(stamps, dtype=np.float64)
    psfs = np.asarray(psf_images, dtype=np.float64)
    if stamps.ndim != 3:
        raise ValueError(f"stamps must be a stack (n, S, S), got shape {stamps.shape}")
    n = len(stamps)
    if psfs.ndim == 2:
        psfs, psf_index = psfs[None], np.zeros(n, dtype=np.int64)
    if psfs.ndim != 3:
        raise ValueError(f"PSF images must be (P, P) or (m, P, P), got shape {psfs.shape}")
    if psf_index is None:
        if len(psfs) != n:
            raise ValueError(f"{len(psfs)} PSF images for {n} stamps")
        psf_index = np.arange(n)
    psf_index = np.asarray(psf_index, dtype=np.int64)
    if psf_index.shape != (n,) or (n and (psf_index.min() < 0 or psf_index.max() >= len(psfs))):
        raise ValueError("psf_index must give each stamp one of the PSF images")
    bad = ~np.isfinite(stamps).all(axis=(1, 2)) if n else np.zeros(0, bool)
    if bad.any():
        raise ValueError(f"stamp {int(np.flatnonzero(bad)[0])} holds NaN or infinite pixels")
    sigmas = (
        np.zeros(n)
        if noise_sigma is None
        else np.nan_to_num(np.asarray(noise_sigma, dtype=np.float64), nan=0.0)
    )
    if fixnoise_signs is not None:  # the sign rides on the field's sigma (noise_field)
        sigmas = np.abs(sigmas) * np.asarray(fixnoise_signs, dtype=np.float64)
    seeds = np.arange(n, dtype=np.int64) if seeds is None else np.asarray(seeds, dtype=np.int64)
    groups = np.unique(psf_index)
    if noise_fields is not None:
        noise_fields = np.asarray(noise_fields, dtype=np.float64)
        if noise_fields.shape != stamps.shape or len(groups) > 1:
            raise ValueError("noise_fields must be one field per stamp, all under one PSF")
        if not np.isfinite(noise_fields).all():
            raise ValueError("noise_fields hold NaN or infinite pixels")
    if len(groups) == 1:  # one PSF (the usual case): no copy into a new stack
        op = _operation(psfs[groups[0]], step, target)
        versions = _with_fixnoise(
            stamps, psfs[groups[0]], op, sigmas, seeds, engine, out, noise_fields
        )
        return versions, np.full(n, op.target.sigma)
    out = _versions_array(out, stamps.shape)
    if engine == "fast":
        return _fast_several_psfs(stamps, psfs, psf_index, step, sigmas, seeds, target, out)
    versions = {kind: out[v] for v, kind in enumerate(TYPES)}
    sigma_t = np.empty(n)
    for j in groups:
        rows = np.flatnonzero(psf_index == j)
        op = _operation(psfs[j], step, target)
        group = _with_fixnoise(stamps[rows], psfs[j], op, sigmas[rows], seeds[rows], engine)
        for kind in TYPES:
            versions[kind][rows] = group[kind]
        sigma_t[rows] = op.target.sigma
    return versions, sigma_t


def fixnoise_seeds(seed: int, keys: Sequence[int] | np.ndarray) -> np.ndarray:
    """Per-stamp seeds of the fixnoise fields under the user's ``seed``: one per key (a row
    index, or the realization index of a common-random-number set, so that its cases share
    their fields)."""
    return np.array([int_seed_for(seed, STREAM_METACAL, int(k)) for k in keys], dtype=np.int64)


def target_psf_image(target_sigma: float, size: int) -> np.ndarray:
    """The round Gaussian target PSF of sigma ``target_sigma`` as the versions hold it (no
    pixel), ``size`` pixels (:meth:`.MetacalTarget.image` of any target)."""
    return GaussTarget(target_sigma).image(size)


def metacal_images(
    stamp: np.ndarray,
    psf_image: np.ndarray,
    step: float = DEFAULT_STEP,
    noise_sigma: float | None = None,
    seed: int = 0,
    engine: str = "galsim",
    target: str = DEFAULT_TARGET,
) -> MetacalImages:
    """The five metacal versions of ``stamp`` with the PSF image ``psf_image`` (both centred
    like GalSim's images: the true centre of an even-sized image is between pixels).

    ``noise_sigma``: the stamp's noise level; when given, fixnoise adds the operation's image
    of a rotated noise field of that level, drawn from ``seed``. ``target``: the target
    PSF's name.
    """
    stamp = np.asarray(stamp, dtype=np.float64)
    _finite_2d(stamp, "stamp")
    versions, target = metacal_versions(
        stamp[None],
        psf_image,
        step,
        None if noise_sigma is None else [noise_sigma],
        [seed],
        engine,
        target=target,
    )
    return MetacalImages({kind: v[0] for kind, v in versions.items()}, float(target[0]))


def metacal_features(
    stamps: np.ndarray,
    psf_images: np.ndarray,
    step: float = DEFAULT_STEP,
    noise_sigma: Sequence[float] | np.ndarray | None = None,
    seeds: Sequence[int] | np.ndarray | None = None,
    metacal_engine: str = "galsim",
    psf_index: Sequence[int] | np.ndarray | None = None,
    feature_sets: Sequence[str] = (),
    target: str = DEFAULT_TARGET,
    **measure_kw: Any,
) -> dict[str, np.ndarray]:
    """Features of the five metacal versions of a stack of stamps ``(n, S, S)``: every column
    ``X`` of :func:`~megalut_cli.measure.features.measure_stamps` (and of the optional
    ``feature_sets``, :mod:`.feature_sets`) as ``X_<type>``.

    Arguments as :func:`metacal_versions` (``metacal_engine`` is its ``engine``);
    ``measure_kw`` go to ``measure_stamps``.
    """
    stamps = np.asarray(stamps)
    square = stamps.ndim == 3 and stamps.shape[1] == stamps.shape[2]
    work = versions_buffer(len(stamps), stamps.shape[1]) if square else None
    versions, _ = metacal_versions(
        stamps, psf_images, step, noise_sigma, seeds, metacal_engine, psf_index, target, work
    )
    out: dict[str, np.ndarray] = {}
    for kind in TYPES:
        feats = measure_stamps(versions[kind], **measure_kw)
        if feature_sets:
            origins = measure_kw.get("origins")
            feats.update(compute_extra(feature_sets, versions[kind], origins, feats))
        for name, values in feats.items():
            out[f"{name}_{kind}"] = values
    return out


def target_columns(
    targets: Sequence[MetacalTarget], size: int, engine: str = "fast"
) -> dict[str, np.ndarray]:
    """``adamom_g1, adamom_g2, adamom_sigma, adamom_rho4`` of each target's image on a
    ``size``-pixel stamp (what the ``psf_adamom_*_<type>`` columns of a metacal catalog
    hold), the images measured in one call."""
    if not len(targets):
        return {c: np.zeros(0) for c in TARGET_PSF_COLUMNS}
    res = measure_stamps(np.array([t.image(size) for t in targets]), engine=engine)
    return {c: np.asarray(res[c], dtype=np.float64) for c in TARGET_PSF_COLUMNS}


def target_psf_columns(target_sigma: np.ndarray, size: int) -> dict[str, np.ndarray]:
    """``psf_<X>_<type>`` of each row from its round Gaussian target's sigma (NaN where not
    finite; the same for the five types), each distinct sigma (to 1e-6 px) measured once."""
    sigma = np.asarray(target_sigma, dtype=np.float64)
    out = {
        f"psf_{c}_{kind}": np.full(len(sigma), np.nan) for kind in TYPES for c in TARGET_PSF_COLUMNS
    }
    finite = np.isfinite(sigma)
    values, inverse = np.unique(np.round(sigma[finite], 6), return_inverse=True)
    feats = target_columns([GaussTarget(float(v)) for v in values], size)
    for kind in TYPES:
        for c in TARGET_PSF_COLUMNS:
            out[f"psf_{c}_{kind}"][finite] = feats[c][inverse.ravel()]
    return out


def stamp_target_columns(
    target: str,
    psf_images: np.ndarray,
    psf_index: np.ndarray,
    target_sigma: np.ndarray,
    step: float,
    size: int,
) -> dict[str, np.ndarray]:
    """``psf_<X>_<type>`` of each stamp's target ``target`` (NaN where ``psf_index < 0``:
    no versions): the round Gaussian by the sigma :func:`metacal_versions` gave
    (:func:`target_psf_columns`), another target built from the stamp's PSF image."""
    if target == gauss.NAME:
        return target_psf_columns(np.where(psf_index >= 0, target_sigma, np.nan), size)
    used = np.unique(psf_index[psf_index >= 0])
    feats = target_columns([metacal_target(target, psf_images[j], step) for j in used], size)
    rows = psf_index >= 0
    where = np.searchsorted(used, psf_index[rows])
    out = {}
    for kind in TYPES:
        for c in TARGET_PSF_COLUMNS:
            out[f"psf_{c}_{kind}"] = np.full(len(psf_index), np.nan)
            out[f"psf_{c}_{kind}"][rows] = feats[c][where]
    return out
