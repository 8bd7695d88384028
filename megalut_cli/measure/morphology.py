"""Morphology features: light profiles seen through Gaussian windows of several sizes.

Each stamp is weighted by elliptical Gaussian windows ``W_k = exp(-rho^2 / (2 k^2))``
centred on the adaptive-moment centroid, where ``rho^2 = x^T M^-1 x`` uses the adaptive
moments' own ellipse ``M = sigma^2 S S^T`` (``sigma = adamom_sigma``, ``S`` the shear
matrix of ``adamom_g1, adamom_g2``). With ``F_k = sum I W_k`` and ``R_k = sum I W_k rho^2 / F_k``:

* ``morph_conc = F_1 / F_2``: the light inside the adaptive window over that inside a
  window twice as large, a concentration (a Gaussian gives 5/8 for any size and shape;
  profiles with more light in their wings give less: at the fiducial resolution, PSF sigma
  2 px and half-light radius 4 px, 0.606 for n = 1 and 0.589 for n = 4);
* ``morph_conc_inner = F_0.5 / F_1`` (Gaussian: 2/5);
* ``morph_size_ratio = sqrt(R_2 / R_1)``, how fast the light's extent grows with the window
  (Gaussian: sqrt(8/5)).

Because the windows follow the adaptive ellipse, these are ratios that do not depend on the
galaxy's size, flux or orientation, only on its radial profile (and the PSF and noise). For
an exact Gaussian ``I`` of covariance ``M``, ``F_k = F k^2 / (1 + k^2)`` and
``R_k = 2 k^2 / (1 + k^2)``.
"""

from __future__ import annotations

import numpy as np

from megalut_cli.measure.feature_registry import Column, FeatureSet, register_feature_set
from megalut_cli.schema import Option

#: The columns of :func:`morphology_features`, in this order.
COLUMNS = (
    Column("morph_conc", "", "light in the adaptive Gaussian window over that in 2x it"),
    Column("morph_conc_inner", "", "light in 0.5x the adaptive Gaussian window over 1x"),
    Column("morph_size_ratio", "", "sqrt of mean rho^2 in a 2x adaptive window over 1x"),
)
#: Columns added by :func:`morphology_features`, in this order.
MORPHOLOGY_COLUMNS: tuple[str, ...] = tuple(c.name for c in COLUMNS)
#: Window sizes in units of the adaptive ellipse.
WINDOW_SCALES = (0.5, 1.0, 2.0)
#: Stamps processed at once (bounds the temporaries: CHUNK x S x S floats).
CHUNK = 256


def morphology_features(
    stamps: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    sigma: np.ndarray,
    g1: np.ndarray,
    g2: np.ndarray,
) -> dict[str, np.ndarray]:
    """Features :data:`MORPHOLOGY_COLUMNS` of ``stamps`` (n, S, S; axis 1 is y).

    ``x, y`` are the adaptive-moment centroids in 1-based pixel coordinates of each stamp
    (the first pixel's centre is 1), ``sigma, g1, g2`` the adaptive size and shape. Rows with
    a non-finite input get NaN.
    """
    stamps = np.asarray(stamps, dtype=np.float64)
    n, size = stamps.shape[0], stamps.shape[-1]
    x, y, sigma, g1, g2 = (
        np.asarray(v, dtype=np.float64).reshape(n) for v in (x, y, sigma, g1, g2)
    )
    out = {c: np.full(n, np.nan) for c in MORPHOLOGY_COLUMNS}
    ok = (
        np.isfinite(x)
        & np.isfinite(y)
        & np.isfinite(sigma)
        & (sigma > 0)
        & np.isfinite(g1)
        & np.isfinite(g2)
    )
    ok &= g1**2 + g2**2 < 1.0
    pix = np.arange(1, size + 1, dtype=np.float64)
    for start in range(0, n, CHUNK):
        rows = np.flatnonzero(ok[start : start + CHUNK]) + start
        if rows.size == 0:
            continue
        dx = pix[None, None, :] - x[rows, None, None]
        dy = pix[None, :, None] - y[rows, None, None]
        a, b = g1[rows], g2[rows]
        norm = (1.0 - a**2 - b**2) * sigma[
            rows
        ] ** 2  # M^-1 = [[(1-g1)^2+g2^2, -2 g2], [.., (1+g1)^2+g2^2]] / norm
        rho2 = (
            ((1 - a) ** 2 + b**2)[:, None, None] * dx**2
            - 4 * b[:, None, None] * dx * dy
            + ((1 + a) ** 2 + b**2)[:, None, None] * dy**2
        ) / norm[:, None, None]
        img = stamps[rows]
        flux, spread = {}, {}
        for k in WINDOW_SCALES:
            w = img * np.exp(-rho2 / (2.0 * k * k))
            flux[k] = w.sum(axis=(1, 2))
            spread[k] = (w * rho2).sum(axis=(1, 2))
        with np.errstate(divide="ignore", invalid="ignore"):
            out["morph_conc"][rows] = flux[1.0] / flux[2.0]
            out["morph_conc_inner"][rows] = flux[0.5] / flux[1.0]
            ratio = (spread[2.0] / flux[2.0]) / (spread[1.0] / flux[1.0])
            out["morph_size_ratio"][rows] = np.sqrt(np.where(ratio > 0, ratio, np.nan))
    return out


def morphology_of_measured(
    stamps: np.ndarray, origins: np.ndarray | None, features: dict[str, np.ndarray]
) -> dict[str, np.ndarray]:
    """:func:`morphology_features` from the output of ``measure_stamps`` (its ``adamom_x,
    adamom_y`` are in the big image whose pixel ``origins`` is each stamp's lower-left one)."""
    n = len(features["adamom_sigma"])
    origins = (
        np.ones((n, 2)) if origins is None else np.asarray(origins, dtype=np.float64).reshape(n, 2)
    )
    return morphology_features(
        stamps,
        features["adamom_x"] - origins[:, 0] + 1.0,
        features["adamom_y"] - origins[:, 1] + 1.0,
        features["adamom_sigma"],
        features["adamom_g1"],
        features["adamom_g2"],
    )


#: The morphology feature set, asked for by ``--morphology``.
MORPHOLOGY_SET = register_feature_set(
    FeatureSet(
        "morphology",
        COLUMNS,
        compute=morphology_of_measured,
        option=Option(
            "morphology",
            "bool",
            False,
            "Also the morphology features morph_conc, morph_conc_inner, "
            "morph_size_ratio (light inside Gaussian windows of 0.5, 1, 2 times the adaptive "
            "ellipse; docs/realgal.md).",
        ),
        nan_when_flagged=MORPHOLOGY_COLUMNS,
    )
)
