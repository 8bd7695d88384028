"""The paper's features (Tewes et al. 2019, Sect. 4) measured on stacks of stamps.

For every stamp:

* ``adamom_flux, adamom_g1, adamom_g2, adamom_sigma, adamom_rho4`` are the GalSim HSM
  ``FindAdaptiveMom`` results ``moments_amp``, ``observed_shape.g1``/``g2``,
  ``moments_sigma`` (pixels) and ``moments_rho4``;
* ``adamom_x, adamom_y`` its ``moments_centroid``, as FITS 1-based pixel coordinates of
  the big image the stamp was cut from (the stamp's lower-left pixel sits at ``origins``);
* ``adamom_logflux`` is ``log10(adamom_flux)``;
* ``skymad`` is 1.4826 times the median absolute deviation of the pixels along the four
  edges of the stamp (Eq. 7);
* ``snr`` follows Eq. 8 when a ``gain`` G (electrons/ADU) is given, and Eq. 10 otherwise,
  with the effective area of Eq. 9, ``A_eff = pi (3 adamom_sigma sqrt(2 ln 2))^2``;
* ``flags`` is a bitmask of :mod:`megalut_cli.flags`.

Two engines measure the moments, with the same results (:data:`MEASURE_ENGINES`):
``"fast"`` runs the compiled batch port of HSM of :mod:`.adamom`, ``"galsim"`` calls
``galsim.hsm.FindAdaptiveMom`` stamp by stamp (the reference).

A stamp with ``flags != 0`` has every ``adamom_*`` feature and ``snr`` set to NaN.
``skymad`` is kept wherever the edge pixels are finite (it describes the sky, not the
source, and remains useful e.g. to measure the noise level of failed stamps). A zero
``skymad`` (noiseless simulations) is legitimate and not flagged; its ``snr`` is ``inf``
with Eq. 10.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from megalut_cli import flags as fl
from megalut_cli.engine import ENGINES, device_backend
from megalut_cli.errors import Names, namer
from megalut_cli.measure.defaults import MAD_TO_SIGMA
from megalut_cli.measure.feature_registry import Column, FeatureSet, register_feature_set

log = logging.getLogger(__name__)

#: Engines of :func:`measure_stamps` for the adaptive moments: the compiled batch port of
#: HSM (:mod:`.adamom`), and GalSim's ``FindAdaptiveMom`` stamp by stamp (the reference).
MEASURE_ENGINES: tuple[str, ...] = tuple(ENGINES)

#: Columns set to NaN when a stamp is flagged: all of the base set but the sky and the flags.
SOURCE_COLUMNS: tuple[str, ...] = (
    *(f"adamom_{q}" for q in ("flux", "g1", "g2", "sigma", "rho4", "x", "y", "logflux")),
    "snr",
)
#: The base feature set (:func:`measure_stamps`): the adaptive moments, the sky and the flags.
ADAMOM_SET = register_feature_set(
    FeatureSet(
        "adamom",
        (
            Column("adamom_flux", "adu", "HSM adaptive-moment amplitude (moments_amp)"),
            Column("adamom_g1", "", "HSM adaptive-moment shape g1"),
            Column("adamom_g2", "", "HSM adaptive-moment shape g2"),
            Column("adamom_sigma", "pixel", "HSM adaptive-moment size (moments_sigma)"),
            Column("adamom_rho4", "", "HSM adaptive-moment radial kurtosis (moments_rho4)"),
            Column("adamom_x", "pixel", "HSM adaptive-moment centroid x (FITS 1-based)"),
            Column("adamom_y", "pixel", "HSM adaptive-moment centroid y (FITS 1-based)"),
            Column("adamom_logflux", "", "log10 of adamom_flux in ADU"),
            Column("skymad", "adu", "sky noise: 1.4826 MAD of the stamp-edge pixels"),
            Column("snr", "", "signal-to-noise ratio (paper Eq. 8 or 10)"),
            Column("flags", "", "bitmask of failures, see FLAGBITn cards (0: good)"),
        ),
        # skymad describes the sky, not the source: kept on flagged rows, as the flags
        nan_when_flagged=SOURCE_COLUMNS,
    )
)
#: Feature columns added by :func:`measure_stamps`, in this order.
FEATURE_COLUMNS: tuple[str, ...] = ADAMOM_SET.names

#: Initial sigma guess of HSM (pixels): GalSim's default, also used by the original
#: MegaLUT; capped to ``S/8`` on small stamps.
DEFAULT_GUESS_SIGMA = 5.0

#: A centroid farther than this (pixels) from the stamp centre gets CENTROID_SHIFT
#: (the original MegaLUT's 10 pixels); capped to ``S/4`` on small stamps.
DEFAULT_MAX_SHIFT = 10.0


def default_guess_sigma(stamp_size: int) -> float:
    """HSM's initial sigma guess for stamps of ``stamp_size`` pixels."""
    return min(DEFAULT_GUESS_SIGMA, stamp_size / 8.0)


def default_max_shift(stamp_size: int) -> float:
    """Largest allowed centroid distance (pixels) from the centre of a stamp."""
    return min(DEFAULT_MAX_SHIFT, stamp_size / 4.0)


def edge_pixels(stamps: np.ndarray) -> np.ndarray:
    """The ``4 (S - 1)`` pixels along the edges of each stamp, shape ``(n, 4 S - 4)``."""
    return np.concatenate(
        [stamps[:, 0, :], stamps[:, -1, :], stamps[:, 1:-1, 0], stamps[:, 1:-1, -1]], axis=1
    )


def sky_mad(stamps: np.ndarray) -> np.ndarray:
    """Eq. 7: ``1.4826 * median(|xi - median(xi)|)`` over the edge pixels of each stamp."""
    edges = edge_pixels(np.asarray(stamps, dtype=np.float64))
    # What scipy.stats.median_abs_deviation(edges, axis=1) computes (NaN propagates),
    # without importing scipy.stats (~0.5 s in every worker process).
    mad = np.median(np.abs(edges - np.median(edges, axis=1, keepdims=True)), axis=1)
    return MAD_TO_SIGMA * mad


def effective_area(sigma: np.ndarray) -> np.ndarray:
    """Eq. 9: circular aperture of three half-light radii of a Gaussian of ``sigma``."""
    return np.pi * (3.0 * np.asarray(sigma) * math.sqrt(2.0 * math.log(2.0))) ** 2


def signal_to_noise(
    flux: np.ndarray, sigma: np.ndarray, skymad: np.ndarray, gain: float | None = None
) -> np.ndarray:
    """Eq. 8 (CCD equation with ``gain`` in e-/ADU) or Eq. 10 (``gain`` None: sky-limited)."""
    flux = np.asarray(flux, dtype=np.float64)
    area = effective_area(sigma)
    skymad = np.asarray(skymad, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        if gain is None:
            return flux / np.sqrt(area * skymad**2)
        signal = gain * flux
        return signal / np.sqrt(signal + area * (gain * skymad) ** 2)


def galsim_moments(stamps: np.ndarray, guess_sigma: float) -> np.ndarray:
    """``(amp, g1, g2, sigma, rho4, x, y)`` of each stamp by ``galsim.hsm.FindAdaptiveMom``.

    Returns an ``(n, 7)`` array, NaN rows where HSM fails; ``x, y`` are 1-based stamp
    coordinates.
    """
    import galsim  # only this engine needs it (~1 s to import)

    n, ny, nx = stamps.shape
    moments = np.full((n, 7), np.nan)
    image = galsim.ImageD(nx, ny)
    weight = galsim.ImageI(nx, ny, init_value=1)
    for i in range(n):
        image.array[:, :] = stamps[i]
        res = galsim.hsm.FindAdaptiveMom(
            image, weight=weight, guess_sig=guess_sigma, strict=False, check=False
        )
        if res.moments_status == 0:
            shape = res.observed_shape
            cen = res.moments_centroid
            moments[i] = (
                res.moments_amp,
                shape.g1,
                shape.g2,
                res.moments_sigma,
                res.moments_rho4,
                cen.x,
                cen.y,
            )
    return moments


def fast_moments(stamps: np.ndarray, guess_sigma: float, retry_step: float = 0.0) -> np.ndarray:
    """The same as :func:`galsim_moments`, by the compiled batch port of :mod:`.adamom`
    (``retry_step``: its damped retry of the failed iterations,
    :func:`~megalut_cli.measure.adamom.adaptive_moments`)."""
    from megalut_cli.measure.adamom import adaptive_moments  # imports numba

    res = adaptive_moments(stamps, guess_sigma, retry_step=retry_step)
    return np.stack([res.amp, res.g1, res.g2, res.sigma, res.rho4, res.x, res.y], axis=1)


def measure_stamps(
    stamps: np.ndarray,
    origins: np.ndarray | None = None,
    gain: float | None = None,
    *,
    guess_sigma: float | None = None,
    max_shift: float | None = None,
    engine: str = "fast",
    device: str = "cpu",
    finite: np.ndarray | None = None,
    skymad: np.ndarray | None = None,
    moments_retry: float = 0.0,
) -> dict[str, np.ndarray]:
    """Measure the features of a stack of stamps.

    Args:
        stamps: ``(n, S, S)`` pixel values (ADU); axis 1 is y, axis 2 is x, as in FITS.
        origins: ``(n, 2)`` FITS 1-based ``(x, y)`` of each stamp's lower-left pixel in the
            big image (default ``(1, 1)``: centroids relative to the stamp itself).
        gain: electrons per ADU for the S/N of Eq. 8; None uses Eq. 10.
        guess_sigma: HSM's initial sigma (pixels); default :func:`default_guess_sigma`.
        max_shift: centroid distance (pixels) from the stamp centre beyond which a stamp is
            flagged CENTROID_SHIFT; default :func:`default_max_shift`.
        engine: one of :data:`MEASURE_ENGINES`; both give the same features and flags.
        device: ``cpu``, or ``gpu`` to measure the fast engine's moments with the device
            backend (:mod:`megalut_cli.gpu`; a resolved device, not ``auto``).
        finite, skymad: whether all pixels of each stamp are finite and its :func:`sky_mad`,
            when the caller has them already (e.g. from
            :func:`megalut_cli.measure.stamps.cut_stamps_checked`); both or neither.
        moments_retry: 0, or the step factor of the damped second iteration on stamps whose
            HSM iteration fails (:func:`megalut_cli.measure.adamom.adaptive_moments`'s
            ``retry_step``; with the ``galsim`` engine or the device, the failed stamps are
            measured again by the compiled port).

    Returns:
        A dict of :data:`FEATURE_COLUMNS` arrays of length ``n`` (float64; ``flags`` int32).
    """
    stamps = np.asarray(stamps)
    if stamps.ndim != 3 or stamps.shape[1] != stamps.shape[2]:
        raise ValueError(f"stamps must have shape (n, S, S), got {stamps.shape}")
    n, size = stamps.shape[0], stamps.shape[1]
    if size < 3:
        raise ValueError(f"stamps must be at least 3x3 pixels, got {size}x{size}")
    if gain is not None and not (math.isfinite(gain) and gain > 0):
        raise ValueError(f"gain must be a positive number, got {gain}")
    if engine not in MEASURE_ENGINES:
        raise ValueError(f"engine must be one of {', '.join(MEASURE_ENGINES)}, got {engine!r}")
    if origins is None:
        origins = np.ones((n, 2))
    origins = np.asarray(origins, dtype=np.float64).reshape(n, 2)
    guess = default_guess_sigma(size) if guess_sigma is None else float(guess_sigma)
    limit = default_max_shift(size) if max_shift is None else float(max_shift)

    if (finite is None) != (skymad is None):
        raise ValueError("give both finite and skymad, or neither")
    if engine == "fast" and device == "gpu" and n:
        moments, skymad, finite = device_backend().pixel_measurements(stamps, guess)
        retry_failed(stamps, moments, finite, guess, moments_retry)
        return features_from_moments(moments, skymad, finite, origins, size, gain, limit)
    if finite is None and engine == "fast" and n:  # checks and moments in one compiled pass
        from megalut_cli.measure.stamps import cut_and_measure, grid_origins

        column = np.ascontiguousarray(stamps).reshape(n * size, size)  # a grid of one column
        tops = grid_origins(n, 1, size)
        found = cut_and_measure(column, 0, tops, size, guess, moments_retry)
        return features_from_moments(
            found.moments, found.skymad, found.finite, origins, size, gain, limit
        )
    if finite is None or skymad is None:
        finite = np.isfinite(stamps).all(axis=(1, 2)) if n else np.zeros(0, bool)
        skymad = sky_mad(stamps) if n else np.zeros(0)
    elif np.shape(finite) != (n,) or np.shape(skymad) != (n,):
        raise ValueError(f"finite and skymad must have one value per stamp ({n})")
    moments = np.full((n, 7), np.nan)
    if finite.any() and engine == "fast":
        if finite.all():  # no copy of the stack
            moments[:] = fast_moments(stamps, guess, moments_retry)
        else:
            moments[finite] = fast_moments(stamps[finite], guess, moments_retry)
    elif finite.any():
        moments[finite] = galsim_moments(stamps[finite], guess)
        retry_failed(stamps, moments, finite, guess, moments_retry)
    return features_from_moments(moments, skymad, finite, origins, size, gain, limit)


def retry_failed(
    stamps: np.ndarray,
    moments: np.ndarray,
    finite: np.ndarray,
    guess_sigma: float,
    retry_step: float,
) -> None:
    """With ``retry_step`` > 0, the moments (in place) of the finite stamps another engine
    failed on, by the compiled port with its damped retry (which repeats GalSim's iteration
    first, so a stamp keeps GalSim's failure unless the damped iteration converges)."""
    failed = np.asarray(finite, dtype=bool) & ~np.isfinite(moments).all(axis=1)
    if retry_step > 0 and failed.any():
        moments[failed] = fast_moments(stamps[failed], guess_sigma, retry_step)


def features_from_moments(
    moments: np.ndarray,
    skymad: np.ndarray,
    finite: np.ndarray,
    origins: np.ndarray,
    size: int,
    gain: float | None,
    max_shift: float,
) -> dict[str, np.ndarray]:
    """The features and flags of :func:`measure_stamps` from what it measures on the pixels:
    ``moments`` (n, 7: ``amp, g1, g2, sigma, rho4, x, y``, NaN rows where HSM failed),
    the sky MAD and whether all pixels of each stamp are finite."""
    n = len(moments)
    limit = max_shift
    out = {c: np.full(n, np.nan) for c in FEATURE_COLUMNS if c != "flags"}
    flags = np.zeros(n, dtype=np.int32)
    finite = np.asarray(finite, dtype=bool)
    flags[~finite] |= fl.BAD_PIXELS
    out["skymad"][:] = skymad
    flags[~np.isfinite(out["skymad"])] |= fl.BAD_SKY
    measured = np.isfinite(moments).all(axis=1)
    flags[finite & ~measured] |= fl.HSM_FAILED  # status != 0, or NaN results

    amp, g1, g2, sigma, rho4, cx, cy = moments.T
    centre = (size + 1) / 2.0  # true centre of a stamp whose first pixel is 1
    with np.errstate(invalid="ignore"):
        flags[measured & ~(amp > 0)] |= fl.NEGATIVE_FLUX
        flags[measured & (np.hypot(cx - centre, cy - centre) > limit)] |= fl.CENTROID_SHIFT

    good = measured & (flags == 0)
    out["adamom_flux"][good] = amp[good]
    out["adamom_g1"][good] = g1[good]
    out["adamom_g2"][good] = g2[good]
    out["adamom_sigma"][good] = sigma[good]
    out["adamom_rho4"][good] = rho4[good]
    out["adamom_x"][good] = cx[good] - 1.0 + origins[good, 0]
    out["adamom_y"][good] = cy[good] - 1.0 + origins[good, 1]
    out["adamom_logflux"][good] = np.log10(amp[good])
    out["snr"][good] = signal_to_noise(amp[good], sigma[good], out["skymad"][good], gain)
    out["flags"] = flags
    return out


#: Fraction of flagged stamps above which ``measure`` warns that something is off.
MOSTLY_FLAGGED = 0.5


def warn_if_mostly_flagged(
    flags: np.ndarray, where: str, names: Names | None = None, suspects: str | None = None
) -> None:
    """Warn when more than :data:`MOSTLY_FLAGGED` of the stamps are flagged, saying why and
    what may be wrong: ``suspects``, else the stamp size, origin or catalog (of a grid image;
    the arguments named by ``names``)."""
    name = namer(names)
    bad = flags != 0
    if len(flags) == 0 or bad.mean() <= MOSTLY_FLAGGED:
        return
    reasons = {name: int(np.sum((flags & value) != 0)) for value, name in fl.FLAG_NAMES.items()}
    ranked = sorted(reasons.items(), key=lambda kv: -kv[1])
    why = ", ".join(f"{name} {n}" for name, n in ranked if n)
    if suspects is None:
        suspects = f"wrong {name('stamp_size')}, {name('origin')} or catalog"
    log.warning(
        "%s: %d of %d stamps flagged (%s): %s?", where, int(bad.sum()), len(flags), why, suspects
    )
