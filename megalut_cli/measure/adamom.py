"""HSM adaptive moments of stacks of stamps, compiled with numba, with GalSim's numbers.

A port of ``galsim.hsm.FindAdaptiveMom`` (GalSim 2.8 ``src/hsm/PSFCorr.cpp``:
``FindAdaptiveMomView``, ``find_ellipmom_2``, ``find_ellipmom_1``) for elliptical weights
and an all-ones mask: same start, pixel window, step limits, convergence test, iteration
limit and failures (a status code per GalSim error message, :data:`STATUS_NAMES`), and
GalSim's float32 rounding of ``amp``, ``sigma`` and ``e1, e2``.

The weight ``exp(-rho^2 / 2)`` is factorised into row and column factors updated by
multiplication (``_ellipmom_1``) instead of an ``exp`` per pixel: sums agree with
GalSim's to ~1e-13 relative, which a long iteration amplifies. On runs of at most 64
iterations (~98 % of stamps) ``amp`` and ``sigma`` are GalSim's bit for bit, ``g1, g2``
within 1e-14, ``rho4`` and the centroid within ~1e-12; on longer runs the float64 outputs
are within a few 1e-9, except on rare stamps (3 of 9672 in 10^4 fiducial stamps) within
1e-6, so the float32 outputs are bit for bit on 99.98 % of stamps. Success or failure is
GalSim's except on rare stamps still unsettled after hundreds of iterations, where one
side may converge and the other give up. ``exact_exp=True`` evaluates the weight as
GalSim does and reproduces its statuses and numbers exactly (on x86-64).

This module is the Python API; the compiled kernels and their status codes are in
:mod:`.adamom_nb`.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from megalut_cli.measure.adamom_nb import (
    ALL_ZERO,
    BAD_BOUNDS,
    NAN,
    NO_ROW_SOLUTION,
    NOT_POSITIVE_DEFINITE,
    OUT_OF_RANGE,
    SINGULAR,
    SUCCESS,
    TOO_MANY_ITERATIONS,
    WEIGHT_NOT_POSITIVE_DEFINITE,
    adaptive_moments_stack,
)

#: Names of the status codes.
STATUS_NAMES: dict[int, str] = {
    SUCCESS: "SUCCESS",
    ALL_ZERO: "ALL_ZERO",
    NOT_POSITIVE_DEFINITE: "NOT_POSITIVE_DEFINITE",
    BAD_BOUNDS: "BAD_BOUNDS",
    NO_ROW_SOLUTION: "NO_ROW_SOLUTION",
    WEIGHT_NOT_POSITIVE_DEFINITE: "WEIGHT_NOT_POSITIVE_DEFINITE",
    OUT_OF_RANGE: "OUT_OF_RANGE",
    SINGULAR: "SINGULAR",
    TOO_MANY_ITERATIONS: "TOO_MANY_ITERATIONS",
    NAN: "NAN",
}

#: The start of GalSim's error message for each failure status (``ShapeData.error_message``).
GALSIM_MESSAGES: dict[int, str] = {
    ALL_ZERO: "Masked image is all 0's.",
    NOT_POSITIVE_DEFINITE: "Error: non positive definite adaptive moments!",
    BAD_BOUNDS: "Bounds don't make sense",
    NO_ROW_SOLUTION: "Failure in finding min/max x for some y!",
    WEIGHT_NOT_POSITIVE_DEFINITE: "Error: non positive-definite weight in find_ellipmom_2.",
    OUT_OF_RANGE: "Error: adaptive moment failed",
    SINGULAR: "Error: HSM collapsed to singular moment matrix. Object is too small.",
    TOO_MANY_ITERATIONS: "Error: too many iterations in adaptive moments",
    NAN: "Error: NaN in calculation of adaptive moments",
}


@dataclasses.dataclass(frozen=True)
class HSMParams:
    """The ``galsim.hsm.HSMParams`` used by adaptive moments, with GalSim's defaults."""

    convergence_threshold: float = 1.0e-6
    max_mom2_iter: int = 400
    bound_correct_wt: float = 0.25
    max_amoment: float = 8000.0
    max_ashift: float = 15.0


@dataclasses.dataclass(frozen=True)
class AdaptiveMoments:
    """Results of :func:`adaptive_moments`, one entry per stamp.

    ``status`` is 0 on success, otherwise a code of :data:`STATUS_NAMES`; the float fields of
    a failed stamp are NaN. ``amp, g1, g2, sigma, rho4`` are GalSim's ``moments_amp``,
    ``observed_shape.g1/g2``, ``moments_sigma`` and ``moments_rho4``; ``x, y`` its
    ``moments_centroid`` for a stamp whose lower-left pixel is (1, 1); ``n_iter`` is
    ``moments_n_iter`` (on failure: the iterations done).
    """

    status: np.ndarray
    amp: np.ndarray
    g1: np.ndarray
    g2: np.ndarray
    sigma: np.ndarray
    rho4: np.ndarray
    x: np.ndarray
    y: np.ndarray
    n_iter: np.ndarray


def guess_sigmas(guess_sigma: float | np.ndarray, n: int) -> np.ndarray:
    """HSM's initial sigma of each of ``n`` stamps (one value or one per stamp), checked."""
    guess = np.broadcast_to(np.asarray(guess_sigma, dtype=np.float64), (n,)).copy()
    if not (np.isfinite(guess).all() and (guess > 0).all()):
        raise ValueError("guess_sigma must be finite and positive")
    return guess


def kernel_settings(
    nx: int,
    ny: int,
    *,
    precision: float = 1.0e-6,
    params: HSMParams | None = None,
    exact_exp: bool = False,
    retry_step: float = 0.0,
) -> tuple[float, float, float, float, float, float, float, int, bool, float]:
    """The scalar arguments of the compiled kernels for ``ny x nx`` stamps (``settings`` of
    :func:`adaptive_moments_stack`: ``x_guess, y_guess, precision, nsig2, bound,
    max_amoment, max_ashift, max_iter, exact_exp, retry_step``), checked."""
    params = HSMParams() if params is None else params
    if not (math.isfinite(retry_step) and 0 <= retry_step < 1):
        raise ValueError(f"retry_step must be in [0, 1), got {retry_step}")
    if not (math.isfinite(precision) and 0 < precision < 1):
        raise ValueError(f"precision must be in (0, 1), got {precision}")
    if not (0 < params.convergence_threshold < 1):
        raise ValueError(
            f"convergence_threshold must be in (0, 1), got {params.convergence_threshold}"
        )
    return (
        (nx + 1) / 2.0,
        (ny + 1) / 2.0,
        float(precision),
        -2.0 * math.log(params.convergence_threshold / 10.0),
        float(params.bound_correct_wt),
        float(params.max_amoment),
        float(params.max_ashift),
        int(params.max_mom2_iter),
        bool(exact_exp),
        float(retry_step),
    )


def adaptive_moments(
    stamps: np.ndarray,
    guess_sigma: float | np.ndarray = 5.0,
    *,
    precision: float = 1.0e-6,
    params: HSMParams | None = None,
    exact_exp: bool = False,
    retry_step: float = 0.0,
) -> AdaptiveMoments:
    """HSM adaptive moments of every stamp of ``stamps``, as ``galsim.hsm.FindAdaptiveMom``.

    Equivalent to ``FindAdaptiveMom(galsim.ImageD(stamp), weight=ones, guess_sig=guess_sigma,
    precision=precision, hsmparams=params, strict=False)`` on each stamp (image bounds
    starting at 1, initial centroid at the stamp's true centre).

    Args:
        stamps: ``(n, S, S)`` pixel values (converted to float64); axis 1 is y, axis 2 is x.
        guess_sigma: initial Gaussian sigma (pixels), one value or one per stamp.
        precision: convergence threshold of the iteration (``FindAdaptiveMom``'s
            ``precision``).
        params: the HSM parameters (default GalSim's defaults).
        exact_exp: evaluate the weight with ``exp`` at every pixel, as GalSim does.
        retry_step: 0 (GalSim's behaviour), or the factor in (0, 1) that scales the updates
            of a second iteration from the same start on the stamps whose first one fails
            by itself (``adamom_nb.RETRIED``: too many iterations, moments out of range,
            NaN): a damped iteration with the same fixed points, which settles where
            GalSim's oscillates. GalSim has no such retry: those stamps' moments are
            megalut's own (its iteration's test of convergence, on the undamped update).

    Returns:
        An :class:`AdaptiveMoments` of arrays of length ``n``.
    """
    stamps = np.ascontiguousarray(stamps, dtype=np.float64)
    if stamps.ndim != 3:
        raise ValueError(f"stamps must have shape (n, ny, nx), got {stamps.shape}")
    n, ny, nx = stamps.shape
    guess = guess_sigmas(guess_sigma, n)
    settings = kernel_settings(
        nx, ny, precision=precision, params=params, exact_exp=exact_exp, retry_step=retry_step
    )
    status = np.zeros(n, dtype=np.int32)
    n_iter = np.zeros(n, dtype=np.int32)
    results = np.full((n, 7), np.nan)
    if n:
        adaptive_moments_stack(stamps, guess, settings, status, n_iter, results)
    results[status != SUCCESS] = np.nan
    return AdaptiveMoments(status, *results.T.copy(), n_iter)
