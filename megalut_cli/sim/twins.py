"""Sérsic twins of real galaxies: a PSF-convolved Sérsic fit of each HST image.

A twin has the fitted Sérsic index, half-light radius, intrinsic shape (reduced shear
``g1, g2``) and centroid of its real galaxy. Drawn with ``galaxy.twin = "sersic"`` it
takes the real galaxy's place under the same rotation, shear, offset and noise
(``docs/realgal.md``). Fluxes are fitted too: ``flux_ratio`` is the fitted total flux over
the HST stamp's sum, so that a twin scaled like its real galaxy has the same core flux.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence
from typing import Any

import galsim
import numpy as np

from megalut_cli.catalog import read_catalog
from megalut_cli.errors import InputError

log = logging.getLogger(__name__)

#: Format name of twin catalogs (``MLFORMAT``).
TWIN_FORMAT = "megalut.sersic-twins"
#: Columns of a twin catalog (angles in arcsec of the HST frame).
TWIN_COLUMNS = (
    "index",
    "sersicn",
    "hlr",
    "g1",
    "g2",
    "dx",
    "dy",
    "flux_ratio",
    "chi2_dof",
    "success",
)
#: Sérsic indices GalSim draws well, the fit's bounds.
SERSICN_RANGE = (0.3, 6.0)
_GSPARAMS = galsim.GSParams(folding_threshold=1e-2, maxk_threshold=1e-2)


def sersic_model(
    params: np.ndarray, flux: float = 1.0, gsparams: galsim.GSParams = _GSPARAMS
) -> galsim.GSObject:
    """Sérsic of ``params = (log hlr, n, eta1, eta2, dx, dy)`` (arcsec) and ``flux``."""
    log_hlr, n, eta1, eta2, dx, dy = (float(p) for p in params)
    prof = galsim.Sersic(
        n=n, half_light_radius=float(np.exp(log_hlr)), flux=flux, gsparams=gsparams
    )
    return prof.shear(galsim.Shear(eta1=eta1, eta2=eta2)).shift(dx, dy)


def fit_sersic(image: galsim.Image, psf: galsim.GSObject, variance: float) -> dict[str, float]:
    """Least-squares fit of a PSF-convolved Sérsic to ``image`` (pixel response in ``psf``).

    The flux is solved linearly at every step; the index is bounded to
    :data:`SERSICN_RANGE`. Returns ``sersicn, hlr, g1, g2, dx, dy, flux, chi2_dof, success``
    (lengths in the image's units, the centroid relative to its true centre).
    """
    data = image.array.astype(np.float64)
    scale = float(image.scale)
    work = image.copy()
    try:
        mom = galsim.hsm.FindAdaptiveMom(image, strict=True)
        sigma = mom.moments_sigma * scale
        shape = mom.observed_shape
        cx = (mom.moments_centroid.x - image.true_center.x) * scale
        cy = (mom.moments_centroid.y - image.true_center.y) * scale
        eta0 = (shape.eta1 * 0.5, shape.eta2 * 0.5)
    except galsim.GalSimError:
        sigma, eta0, cx, cy = 3.0 * scale, (0.0, 0.0), 0.0, 0.0
    psf_sigma = psf.calculateMomentRadius(rtype="det")
    hlr0 = 1.1774 * float(np.sqrt(max(sigma**2 - psf_sigma**2, (0.5 * sigma) ** 2)))
    p0 = np.array([np.log(hlr0), 1.5, eta0[0], eta0[1], cx, cy])
    lo = np.array([np.log(0.2 * scale), SERSICN_RANGE[0], -3.0, -3.0, -10 * scale, -10 * scale])
    hi = np.array(
        [np.log(0.5 * scale * max(data.shape)), SERSICN_RANGE[1], 3.0, 3.0, 10 * scale, 10 * scale]
    )
    p0 = np.clip(p0, lo + 1e-6, hi - 1e-6)
    sqrt_var = float(np.sqrt(variance))
    last: dict[str, float] = {}

    def residuals(p: np.ndarray) -> np.ndarray:
        model = galsim.Convolve(sersic_model(p), psf).drawImage(image=work, method="no_pixel").array
        mm = float(np.sum(model * model))
        flux = float(np.sum(model * data)) / mm if mm > 0 else 0.0
        last["flux"] = flux
        return ((data - flux * model) / sqrt_var).ravel()

    from scipy.optimize import least_squares  # a second to import: only fits need it

    res = least_squares(
        residuals,
        p0,
        bounds=(lo, hi),
        x_scale=np.array([0.1, 0.3, 0.1, 0.1, scale, scale]),
        diff_step=1e-3,
        max_nfev=200,
    )
    chi2 = float(np.sum(residuals(res.x) ** 2))
    g = galsim.Shear(eta1=float(res.x[2]), eta2=float(res.x[3]))
    return {
        "sersicn": float(res.x[1]),
        "hlr": float(np.exp(res.x[0])),
        "g1": float(g.g1),
        "g2": float(g.g2),
        "dx": float(res.x[4]),
        "dy": float(res.x[5]),
        "flux": last["flux"],
        "chi2_dof": chi2 / max(data.size - 7, 1),
        "success": bool(res.success),
    }


def fit_real_catalog(
    rgc: galsim.RealGalaxyCatalog, rows: Sequence[int] | None = None
) -> dict[str, np.ndarray]:
    """Sérsic twins of the rows of a loaded ``RealGalaxyCatalog`` (all by default), as columns
    :data:`TWIN_COLUMNS` in arcsec of the HST frame."""
    rows = list(range(rgc.nobjects)) if rows is None else [int(r) for r in rows]
    out: dict[str, list[Any]] = {k: [] for k in TWIN_COLUMNS}
    for i in rows:
        image = rgc.getGalImage(i)
        fit = fit_sersic(image, rgc.getPSF(i), float(rgc.variance[i]))
        stamp_sum = float(image.array.sum())
        fit["flux_ratio"] = fit["flux"] / stamp_sum if stamp_sum > 0 else np.nan
        fit["index"] = i
        log.info(
            'twin %d: n=%.2f hlr=%.3f" g=(%.3f, %.3f) chi2/dof=%.2f',
            i,
            fit["sersicn"],
            fit["hlr"],
            fit["g1"],
            fit["g2"],
            fit["chi2_dof"],
        )
        for k in TWIN_COLUMNS:
            out[k].append(fit[k])
    cols = {k: np.asarray(v, dtype=float) for k, v in out.items()}
    cols["index"] = cols["index"].astype(np.int64)
    cols["success"] = cols["success"].astype(np.int16)
    return cols


@functools.lru_cache(maxsize=4)
def load_twins(path: str) -> dict[int, tuple[float, ...]]:
    """Twin parameters of a twin catalog, by real-catalog row:
    ``(sersicn, hlr, g1, g2, dx, dy, flux_ratio)``."""
    table = read_catalog(path)
    if table.meta.get("MLFORMAT") != TWIN_FORMAT:
        raise InputError(
            f"galaxy.twin_catalog: {path}: not a Sérsic-twin catalog (MLFORMAT {TWIN_FORMAT!r})"
        )
    keys = ("sersicn", "hlr", "g1", "g2", "dx", "dy", "flux_ratio")
    return {int(r["index"]): tuple(float(r[k]) for k in keys) for r in table}


def twin_profile(
    twin: Sequence[float], flux: float, pixel_scale: float, gsparams: galsim.GSParams
) -> galsim.GSObject:
    """The Sérsic twin in simulation pixels of ``pixel_scale`` arcsec, scaled like its real
    galaxy of ``flux`` (ADU): built in arcsec, then dilated like ``galsim.RealGalaxy``."""
    n, hlr, g1, g2, dx, dy, ratio = twin
    prof = galsim.Sersic(
        n=float(n), half_light_radius=float(hlr), flux=float(flux) * float(ratio), gsparams=gsparams
    )
    return (
        prof.shear(g1=float(g1), g2=float(g2))
        .shift(float(dx), float(dy))
        .dilate(1.0 / float(pixel_scale))
    )


def real_twin(
    real: dict[str, Any], index: int, flux: float, gsparams: galsim.GSParams
) -> galsim.GSObject:
    """The Sérsic twin of real-catalog row ``index`` for the galaxy spec ``real`` (its
    ``twin_catalog`` and ``pixel_scale``), scaled like the real galaxy of ``flux``."""
    twins = load_twins(str(real["twin_catalog"]))
    if int(index) not in twins:
        raise InputError(f"galaxy.twin_catalog: no twin for real-catalog row {int(index)}")
    return twin_profile(twins[int(index)], flux, float(real["pixel_scale"]), gsparams)


def twin_truth(real: dict[str, Any], index: np.ndarray) -> dict[str, np.ndarray]:
    """Truth columns of the twins of real-catalog rows ``index``, written for real and twin
    sets alike: ``tru_twin_rad`` (fitted half-light radius, simulation pixels),
    ``tru_twin_sersicn``, ``tru_twin_g1, tru_twin_g2`` (fitted shape, HST frame) and
    ``tru_twin`` (1 where the twin was drawn, 0 where the real galaxy was)."""
    twins = load_twins(str(real["twin_catalog"]))
    rows = np.array(
        [twins.get(int(i), (np.nan,) * 7) for i in np.asarray(index)], dtype=float
    ).reshape(-1, 7)
    return {
        "tru_twin_rad": rows[:, 1] / float(real["pixel_scale"]),
        "tru_twin_sersicn": rows[:, 0],
        "tru_twin_g1": rows[:, 2],
        "tru_twin_g2": rows[:, 3],
        "tru_twin": np.full(len(rows), int(real.get("twin", "none") != "none"), dtype=np.int16),
    }
