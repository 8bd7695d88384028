"""Synthetic catalogs for tests, benchmarks and examples (no image simulation needed).

- :func:`appendix_columns`: the inverse regression of the paper's Appendix A,
  ``d = sqrt(1 + theta^2) + n`` with ``n ~ N(0, 0.1)``; feature ``d``, target ``tru_theta``.
- :func:`shear_like_columns`: a cheap stand-in for a shear training set with the paper's
  five feature names: a galaxy per case seen on a ring of orientations, diluted by a PSF,
  with noise growing for small faint galaxies (so that point estimates suffer noise bias).
"""

from __future__ import annotations

import numpy as np


def appendix_columns(
    theta: np.ndarray,
    n_rea: int,
    rng: np.random.Generator,
    sigma: float = 0.1,
    antithetic: bool = True,
) -> dict[str, np.ndarray]:
    """One case per value of ``theta``, ``n_rea`` noisy observations ``d`` each.

    With ``antithetic`` the noise comes in pairs (n, -n), the analogue of the paper's
    shape-noise cancellation: it does not change any estimator's bias, only the noise of
    its measurement.
    """
    theta = np.asarray(theta, dtype=np.float64)
    nc = len(theta)
    if antithetic:
        half = rng.normal(0.0, sigma, (nc, (n_rea + 1) // 2))
        noise = np.concatenate([half, -half], axis=1)[:, :n_rea]
    else:
        noise = rng.normal(0.0, sigma, (nc, n_rea))
    d = np.sqrt(1.0 + theta**2)[:, None] + noise
    return {
        "case": np.repeat(np.arange(nc, dtype=np.int64), n_rea),
        "rea": np.tile(np.arange(n_rea, dtype=np.int64), nc),
        "d": d.ravel(),
        "tru_theta": np.repeat(theta, n_rea),
        "flags": np.zeros(nc * n_rea, dtype=np.int32),
    }


def shear_like_columns(
    n_cases: int, n_rea: int, seed: int, psf_sigma: float = 2.0
) -> dict[str, np.ndarray]:
    """A shear-like training set: features ``adamom_g1, adamom_g2, adamom_sigma, adamom_flux,
    adamom_rho4`` and targets ``tru_g1, tru_g2`` (constant within each case)."""
    rng = np.random.default_rng(seed)
    g = rng.uniform(-0.1, 0.1, (n_cases, 2))
    rad = rng.uniform(1.0, 4.0, n_cases)
    flux = rng.uniform(200.0, 1500.0, n_cases)
    emod = rng.uniform(0.0, 0.5, n_cases)
    phi = (np.arange(n_rea) + 0.5) * np.pi / n_rea + rng.uniform(0, np.pi, (n_cases, 1))
    e1 = emod[:, None] * np.cos(2 * phi) + g[:, 0:1]
    e2 = emod[:, None] * np.sin(2 * phi) + g[:, 1:2]
    size2 = rad**2 + psf_sigma**2
    res = (rad**2 / size2)[:, None]
    snr_case = flux / (10.0 * np.sqrt(size2))
    noise = (0.5 / snr_case)[:, None] * np.ones((1, n_rea))
    n = rng.normal(size=(4, n_cases, n_rea)) * noise
    obs_e1 = e1 * res + n[0]
    obs_e2 = e2 * res + n[1]
    sigma = np.sqrt(size2)[:, None] * (1.0 + 0.3 * n[2]) * (1 + 0.1 * (obs_e1**2 + obs_e2**2))
    fl = flux[:, None] * (1.0 + n[3])
    rho4 = 2.0 + (rad / (rad + psf_sigma))[:, None] + 0.3 * n[2] ** 2
    snr = np.broadcast_to(snr_case[:, None], (n_cases, n_rea))
    return {
        "case": np.repeat(np.arange(n_cases, dtype=np.int64), n_rea),
        "rea": np.tile(np.arange(n_rea, dtype=np.int64), n_cases),
        "adamom_g1": obs_e1.ravel(),
        "adamom_g2": obs_e2.ravel(),
        "adamom_sigma": sigma.ravel(),
        "adamom_flux": fl.ravel(),
        "adamom_rho4": rho4.ravel(),
        "snr": snr.ravel().copy(),
        "tru_g1": np.repeat(g[:, 0], n_rea),
        "tru_g2": np.repeat(g[:, 1], n_rea),
        "flags": np.zeros(n_cases * n_rea, dtype=np.int32),
    }
