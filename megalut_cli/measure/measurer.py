"""One measurer for every stamp source: a :class:`StampBatch` in, its catalog columns out.

It owns the base features, the optional feature sets (:mod:`.feature_sets`), masked
pixels, the PSF features, the metacal versions and every flag; sources (a grid image, a
MEDS file, simulated stamps) only cut or draw the stamps and say where they lie.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from megalut_cli import flags as fl
from megalut_cli.engine import DEFAULT_DEVICE, DEFAULT_ENGINE
from megalut_cli.errors import InputError
from megalut_cli.measure.defaults import PSF_COLUMNS
from megalut_cli.measure.feature_sets import compute_extra, nan_when_flagged, optional_columns
from megalut_cli.measure.features import (
    FEATURE_COLUMNS,
    default_max_shift,
    measure_stamps,
    signal_to_noise,
)
from megalut_cli.measure.masks import (
    MASK_DISTANCE_COLUMN,
    MASKED_COLUMN,
    NOISE_COLUMN,
    filled_stamps,
    masked_sky_mad,
    nan_flagged,
    stamp_mask_distance,
    too_masked,
    weight_noise,
)
from megalut_cli.measure.metacal_defaults import (
    DEFAULT_TARGET,
    INTERPOLANT,
    SEED_CARD,
    STEP_CARD,
    TARGET_CARD,
    TYPES,
)

#: Header card of the step factor of the moments' damped retry (``--moments-retry``).
RETRY_CARD = "HSMRETRY"

#: Flags of a stamp that metacal leaves out (its versions get the same flags).
METACAL_SKIPPED = fl.MASKED_PIXELS | fl.NEAR_MASK | fl.PSF_FAILED | fl.BAD_PIXELS


@dataclass(frozen=True)
class MetacalSettings:
    """The metacal operation: its shear step, the seed of the fixnoise fields and the target
    PSF's name (:mod:`.metacal_targets`)."""

    step: float
    seed: int
    target: str = DEFAULT_TARGET


@dataclass(frozen=True)
class MeasureSettings:
    """What is measured of every stamp: the gain of the S/N, the moments' engine and device,
    the optional feature sets (names), the metacal operation (None: none), the step
    factor of the moments' damped retry (0: none, GalSim's failures), and how close to the
    object a masked pixel of its stamp may lie before it is flagged NEAR_MASK (pixels; 0:
    never)."""

    gain: float | None = None
    engine: str = DEFAULT_ENGINE
    device: str = DEFAULT_DEVICE
    feature_sets: tuple[str, ...] = ()
    metacal: MetacalSettings | None = None
    moments_retry: float = 0.0
    mask_margin: float = 0.0

    @property
    def feature_columns(self) -> tuple[str, ...]:
        """The feature columns of a stamp: the base set's, then the optional sets'."""
        return FEATURE_COLUMNS + optional_columns(self.feature_sets)

    @property
    def needs_pixels(self) -> bool:
        """Whether more than the base features are measured on the pixels (else a source may
        cut and measure in one compiled pass)."""
        return bool(self.feature_sets) or self.metacal is not None


@dataclass(frozen=True)
class PsfImages:
    """The PSFs of a batch: distinct images ``(m, P, P)`` and each stamp's ``index`` into
    them; ``columns``: whether the PSF features ``psf_adamom_*`` are measured (a simulation
    knows its PSFs and keeps them for metacal only)."""

    images: np.ndarray
    index: np.ndarray
    columns: bool = True


@dataclass(frozen=True)
class StampBatch:
    """Stamps to measure, ``(n, S, S)``, with what their source knows of them.

    ``origins``: FITS 1-based ``(x, y)`` of each stamp's lower-left pixel in its image;
    ``finite``, ``skymad``: when the source computed them while cutting; ``masked``: bad
    pixels (left out of the moments, counted, flagged when too many or central, see
    :mod:`.masks`) with ``centres`` (0-based ``(col, row)`` of the object in its stamp) and
    ``weights`` (the noise of the S/N); ``noise``: the known pixel noise of each stamp (a
    metadetection version's), on which ``snr`` is computed instead of ``skymad``; ``psfs``;
    ``fixnoise_keys``: the key of each stamp's metacal fixnoise field, ``fixnoise_signs``: its
    sign (+1, or -1 for the second of antithetic twins; None: all +1); ``base``: the base
    features, when the source measured them itself (while cutting, or on the device;
    ``stamps`` may then be None when nothing else is measured on the pixels).
    """

    stamps: np.ndarray | None
    origins: np.ndarray
    finite: np.ndarray | None = None
    skymad: np.ndarray | None = None
    masked: np.ndarray | None = None
    centres: np.ndarray | None = None
    weights: np.ndarray | None = None
    noise: np.ndarray | None = None
    psfs: PsfImages | None = None
    fixnoise_keys: np.ndarray | None = None
    fixnoise_signs: np.ndarray | None = None
    base: dict[str, np.ndarray] | None = None


def twin_fixnoise(keys: np.ndarray, realizations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The fixnoise keys and signs of antithetic twins (realizations ``2k, 2k+1``): both share
    the key of the half-size set (``keys // 2``), the second has the opposite field."""
    keys, realizations = np.asarray(keys, dtype=np.int64), np.asarray(realizations, np.int64)
    return keys // 2, 1.0 - 2.0 * (realizations % 2)


def metacal_columns(names: tuple[str, ...] | list[str]) -> list[str]:
    """The metacal column names ``X_<type>`` of the columns ``names``, type by type."""
    return [f"{name}_{kind}" for kind in TYPES for name in names]


def metacal_cards(step: float, seed: int, command: str) -> dict[str, tuple[float | int, str]]:
    """The header cards of a catalog measured in metacal mode by ``command`` (``simulate``,
    ``measure``): the shear step and the seed of the fixnoise fields."""
    return {
        STEP_CARD: (float(step), f"metacal shear step ({command} --metacal-step)"),
        SEED_CARD: (int(seed), f"seed of the metacal fixnoise fields ({command} --seed)"),
    }


def retry_cards(retry_step: float) -> dict[str, tuple[float, str]]:
    """The header card of the moments' damped retry (none without one)."""
    if retry_step <= 0:
        return {}
    return {RETRY_CARD: (float(retry_step), "step factor of the damped moments retry")}


def measure_cards(settings: MeasureSettings, size: int | None) -> dict[str, Any]:
    """Header cards of what was measured: the gain, the centroid limit (one stamp ``size``),
    the moments' engine and the metacal step and seed."""
    cards: dict[str, Any] = {
        "GAIN": (settings.gain, "gain [e-/ADU] of the S/N (Eq. 8)")
        if settings.gain is not None
        else None,
        "MAXSHIFT": (default_max_shift(size), "centroid shift limit [pixels]")
        if size is not None
        else None,
        "MENGINE": (settings.engine, "engine of the adaptive moments (megalut --engine)"),
        **retry_cards(settings.moments_retry),
    }
    if settings.metacal is not None:
        cards.update(metacal_cards(settings.metacal.step, settings.metacal.seed, "measure"))
        if settings.metacal.target != DEFAULT_TARGET:
            cards[TARGET_CARD] = (settings.metacal.target, "metacal target PSF")
    return cards


def distinct_psfs(psfs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct images of a PSF stack ``(n, P, P)`` and each stamp's index into them:
    objects sharing a PSF (a constant PSF, or one cutout per CCD) go through metacal's
    operation together."""
    flat = np.ascontiguousarray(psfs).reshape(len(psfs), -1)
    _, first, index = np.unique(
        flat.view(np.dtype((np.void, flat.shape[1] * flat.itemsize))).ravel(),
        return_index=True,
        return_inverse=True,
    )
    return psfs[first], index.ravel()


def same_parity_psfs(psfs: np.ndarray, size: int) -> np.ndarray:
    """PSF images ``(n, P, P)`` for stamps of ``size`` pixels: as they are when ``P`` has the
    parity of ``size``, else each redrawn (``lanczos15`` interpolation, no further pixel) on
    ``P + 1`` pixels with its profile's centre kept at the image's true centre, where metacal
    expects it (MEDS PSF cutouts are often odd-sized, boxes even)."""
    psfs = np.asarray(psfs, dtype=np.float64)
    if psfs.shape[1] % 2 == size % 2:
        return psfs
    import galsim

    p = psfs.shape[1] + 1
    out = np.empty((len(psfs), p, p))
    for i, img in enumerate(psfs):
        prof = galsim.InterpolatedImage(galsim.ImageD(img, scale=1.0), x_interpolant=INTERPOLANT)
        out[i] = prof.drawImage(nx=p, ny=p, scale=1.0, method="no_pixel").array
    return out


def psf_features(psfs: np.ndarray, engine: str = DEFAULT_ENGINE) -> dict[str, np.ndarray]:
    """``psf_adamom_g1, psf_adamom_g2, psf_adamom_sigma, psf_adamom_rho4`` of each PSF image
    ``(n, P, P)`` and ``flags`` (PSF_FAILED where it cannot be measured)."""
    psfs = np.asarray(psfs, dtype=np.float64)
    n = len(psfs)
    if psfs.ndim != 3 or psfs.shape[1] != psfs.shape[2]:
        raise InputError(f"PSF cutouts must be square, got {psfs.shape[1]}x{psfs.shape[2]}")
    res = measure_stamps(psfs, engine=engine) if n else {c: np.zeros(0) for c in FEATURE_COLUMNS}
    out = {p: np.asarray(res[p[len("psf_") :]], dtype=np.float64) for p in PSF_COLUMNS}
    out["flags"] = np.where(np.asarray(res["flags"]) != 0, fl.PSF_FAILED, 0).astype(np.int32)
    return out


class Measurer:
    """Measures batches of stamps as :class:`MeasureSettings` say."""

    def __init__(self, settings: MeasureSettings):
        self.settings = settings

    def features(
        self, stamps: np.ndarray, origins: np.ndarray | None, **pixels: np.ndarray | None
    ) -> dict[str, np.ndarray]:
        """The base and optional features of ``stamps`` (``pixels``: ``finite``, ``skymad``
        when known)."""
        s = self.settings
        feats = measure_stamps(
            stamps,
            origins,
            s.gain,
            max_shift=default_max_shift(stamps.shape[-1]),
            engine=s.engine,
            device=s.device,
            moments_retry=s.moments_retry,
            **pixels,
        )
        if s.feature_sets:
            feats.update(compute_extra(s.feature_sets, stamps, origins, feats))
        return feats

    def masked_features(
        self, stamps: np.ndarray, masked: np.ndarray, origins: np.ndarray | None
    ) -> dict[str, np.ndarray]:
        """:meth:`features` of ``stamps`` whose ``masked`` pixels are left out (GalSim's
        badpix: 0 for the moments, out of the edge pixels of ``skymad``)."""
        n = len(stamps)
        zeroed = np.where(masked, 0.0, stamps) if masked.any() else stamps
        finite = np.isfinite(zeroed).all(axis=(1, 2)) if n else np.zeros(0, bool)
        skymad = masked_sky_mad(stamps, masked) if n else np.zeros(0)
        return self.features(zeroed, origins, finite=finite, skymad=skymad)

    def measure(self, batch: StampBatch) -> dict[str, np.ndarray]:
        """The columns of a batch: features, then ``n_masked`` and ``noise_weight`` (with a
        mask), ``psf_adamom_*`` (with PSFs), the metacal columns (with metacal and PSFs)."""
        s = self.settings
        stamps = batch.stamps
        if batch.base is not None:  # measured by the source; the optional sets on its stamps
            feats = dict(batch.base)
            if stamps is not None and s.feature_sets:
                feats.update(compute_extra(s.feature_sets, stamps, batch.origins, feats))
        else:
            assert stamps is not None
            if batch.masked is not None:  # GalSim's badpix: masked pixels are 0 for the moments
                feats = self.masked_features(stamps, batch.masked, batch.origins)
                self._masks(batch, feats)
            else:
                feats = self.features(
                    stamps, batch.origins, finite=batch.finite, skymad=batch.skymad
                )
            if batch.noise is not None:
                self._snr_on(feats, np.asarray(batch.noise, dtype=np.float64))
        self._psfs(batch, feats)
        if stamps is None:
            return feats
        if s.metacal is not None and batch.psfs is not None:
            feats.update(self._metacal(batch, feats))
        return feats

    def _psfs(self, batch: StampBatch, feats: dict[str, np.ndarray]) -> None:
        """``psf_adamom_*`` of each stamp's PSF; PSF_FAILED (and NaN features) where it fails."""
        if batch.psfs is None or not batch.psfs.columns:
            return
        psf = psf_features(batch.psfs.images, self.settings.engine)
        feats["flags"] |= psf.pop("flags")[batch.psfs.index]
        nan_flagged(feats, feats["flags"], nan_when_flagged(self.settings.feature_sets))
        feats.update({c: v[batch.psfs.index] for c, v in psf.items()})

    def _masks(self, batch: StampBatch, feats: dict[str, np.ndarray]) -> None:
        """``n_masked``, MASKED_PIXELS, and with weights ``noise_weight`` and its ``snr``."""
        assert batch.masked is not None
        masked, n = batch.masked, len(batch.masked)
        feats[MASKED_COLUMN] = masked.reshape(n, -1).sum(axis=1).astype(np.int32)
        distance = None
        if self.settings.mask_margin > 0:
            distance = stamp_mask_distance(masked, batch.centres)
            feats[MASK_DISTANCE_COLUMN] = distance.astype(np.float32)
            feats["flags"][distance <= self.settings.mask_margin] |= fl.NEAR_MASK
        feats["flags"][too_masked(masked, batch.centres, distance)] |= fl.MASKED_PIXELS
        nan_flagged(feats, feats["flags"], nan_when_flagged(self.settings.feature_sets))
        if batch.weights is not None:
            noise = weight_noise(np.asarray(batch.weights), masked)
            feats[NOISE_COLUMN] = noise
            self._snr_on(feats, noise)

    def _snr_on(self, feats: dict[str, np.ndarray], noise: np.ndarray) -> None:
        """``snr`` (in place) of the measured rows on the per-stamp ``noise`` where it is finite."""
        use = (feats["flags"] == 0) & np.isfinite(noise)
        feats["snr"][use] = signal_to_noise(
            feats["adamom_flux"][use], feats["adamom_sigma"][use], noise[use], self.settings.gain
        )

    def _common_sky(self, measured: dict[str, np.ndarray], sky: np.ndarray) -> None:
        """A sheared version's ``skymad`` and ``snr`` (in place) on the noshear version's sky
        noise ``sky``: the operation resamples the noise along a stamp's edges differently in
        each version (their edge MADs 1p and 1m differ by ~7 %, the shear moves the S/N by
        ~0.3 %), which would make an S/N cut's selection response noise (docs/metacal.md)."""
        measured["skymad"] = np.where(np.isfinite(sky), sky, measured["skymad"])
        self._snr_on(measured, sky)

    def _metacal(self, batch: StampBatch, feats: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``X_<type>`` of the five metacal versions and ``psf_adamom_*_<type>`` of the target
        PSF; stamps flagged :data:`METACAL_SKIPPED` are left out, with those flags. Masked
        pixels are filled (:func:`~.masks.filled_stamps`) before the operation and left out
        of each version's moments, as of the stamp's: the mask stays where it is while the
        versions shear the object, as a real shear would."""
        from megalut_cli.measure.metacal import (  # GalSim: metacal only
            fixnoise_seeds,
            metacal_versions,
            stamp_target_columns,
            versions_buffer,
        )

        s, psfs, stamps = self.settings, batch.psfs, batch.stamps
        assert s.metacal is not None and psfs is not None and stamps is not None
        n, size = len(stamps), stamps.shape[-1]
        names = s.feature_columns
        out = {
            c: np.zeros(n, dtype=np.int32) if c.startswith("flags_") else np.full(n, np.nan)
            for c in metacal_columns(names)
        }
        skipped = feats["flags"] & METACAL_SKIPPED
        ok = skipped == 0
        target = np.full(n, np.nan)
        index = np.full(n, -1)
        images = psfs.images[:0]
        masked = None if batch.masked is None or not batch.masked[ok].any() else batch.masked[ok]
        if ok.any():
            used, index[ok] = np.unique(psfs.index[ok], return_inverse=True)
            images = same_parity_psfs(psfs.images[used], size)
            noise = feats.get(NOISE_COLUMN, np.full(n, np.nan))
            noise = np.where(np.isfinite(noise), noise, feats["skymad"])
            keys = np.arange(n) if batch.fixnoise_keys is None else batch.fixnoise_keys
            origins = batch.origins[ok]
            versions, target[ok] = metacal_versions(
                stamps[ok] if masked is None else filled_stamps(stamps[ok], masked),
                images,
                s.metacal.step,
                noise[ok],
                fixnoise_seeds(s.metacal.seed, keys[ok]),
                s.engine,
                index[ok],
                s.metacal.target,
                versions_buffer(int(ok.sum()), size) if stamps.shape[1] == size else None,
                fixnoise_signs=None if batch.fixnoise_signs is None else batch.fixnoise_signs[ok],
            )
            sky: np.ndarray | None = None
            for kind in TYPES:  # noshear first: its sky noise is every version's
                measured = (
                    self.features(versions[kind], origins)
                    if masked is None
                    else self.masked_features(versions[kind], masked, origins)
                )
                if sky is None:
                    sky = measured["skymad"]
                else:
                    self._common_sky(measured, sky)
                for c, v in measured.items():
                    out[f"{c}_{kind}"][ok] = v
        nan_names = nan_when_flagged(s.feature_sets)
        for kind in TYPES:
            out[f"flags_{kind}"] |= skipped
            nan_flagged(out, out[f"flags_{kind}"], tuple(f"{c}_{kind}" for c in nan_names))
        step = s.metacal.step
        out.update(stamp_target_columns(s.metacal.target, images, index, target, step, size))
        return out
