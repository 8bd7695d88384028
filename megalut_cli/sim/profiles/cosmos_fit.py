"""``profile = "cosmos_fit"``: galaxies of the COSMOS parametric fits, sampled from the rows
of the ``[catalog]`` table and built as GalSim's ``COSMOSCatalog`` builds them (a single
Sérsic, or a de Vaucouleurs bulge + exponential disk), at the simulation's position angle
and flux (``docs/config.md``)."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

import numpy as np

from megalut_cli.errors import ConfigError
from megalut_cli.schema import OneOf, Option
from megalut_cli.sim.distributions import CatalogColumn, parse_distributions
from megalut_cli.sim.profiles import bulgedisk
from megalut_cli.sim.profiles.base import GalaxyProfile, GalaxySpec, ProfileTruth
from megalut_cli.sim.profiles.common import (
    ANGLE,
    FLUX,
    KNOTS,
    KNOTS_FRACTION,
    MAG,
    ONE_FLUX,
    RAD,
    SB,
    SERSICN_STEP,
    composite_hlr,
    flux_mode,
    knot_dists,
    position_angle,
    q_to_ellipticity,
    round_sersicn,
    sersicn_step,
    with_help,
)

log = logging.getLogger(__name__)

#: Which fit of each row: the single Sérsic, the bulge + disk, or GalSim's choice.
COSMOS_FITS = ("sersic", "bulgedisk", "auto")
#: GalSim's Sersic range used for the COSMOS fits (as ``galsim.COSMOSCatalog`` clamps them).
COSMOS_SERSIC_RANGE = (0.3, 6.0)
#: Catalog columns of the COSMOS parametric fits (GalSim ``COSMOSCatalog._buildParametric``):
#: internal parameter -> (column, element).
COSMOS_FIT_COLUMNS: dict[str, dict[str, tuple[str, int | None]]] = {
    "sersic": {
        "fit_n": ("sersicfit", 2),
        "fit_q": ("sersicfit", 3),
        "fit_hlr": ("hlr", 0),
        "fit_viable": ("viable_sersic", None),
    },
    "bulgedisk": {
        "fit_disk_q": ("bulgefit", 3),
        "fit_disk_beta": ("bulgefit", 7),
        "fit_bulge_q": ("bulgefit", 11),
        "fit_bulge_beta": ("bulgefit", 15),
        "fit_bulge_hlr": ("hlr", 1),
        "fit_disk_hlr": ("hlr", 2),
        "fit_bulge_flux": ("flux", 1),
        "fit_disk_flux": ("flux", 2),
        "fit_use_bulge": ("use_bulgefit", None),
    },
}

OPTIONS = (
    Option(
        "fit",
        "choice",
        "auto",
        '`"sersic"` (every row with `viable_sersic`), `"bulgedisk"` (rows with '
        "`use_bulgefit`, 36 of the example's 100) or `\"auto\"` (GalSim's choice per row)",
        choices=COSMOS_FITS,
    ),
    Option(
        "pixel_scale",
        "float",
        None,
        "arcsec per simulation pixel: the fitted sizes (arcsec) are divided by it",
        default_text="—",
        allowed_text="> 0",
    ),
    with_help(
        RAD,
        "the composite half-light radius in pixels: the galaxy is dilated to it (the fits then "
        "set only the morphology)",
        default_text="—",
    ),
    FLUX,
    SB,
    with_help(
        MAG,
        'magnitude, as above; `mag = {type = "catalog", column = "mag_auto"}` takes the row\'s own '
        "magnitude",
    ),
    with_help(ANGLE, "position angle of the disk (or single Sérsic), degrees"),
    with_help(
        SERSICN_STEP, "rounding of the fitted Sérsic index (GalSim's `COSMOSCatalog` uses 0.05)"
    ),
    KNOTS,
    KNOTS_FRACTION,
)
#: Why it refuses these keys of other profiles.
FROM_THE_FITS = "profile and shape come from the fits"


def parse(
    given: Mapping[str, Any],
    values: Mapping[str, Any],
    instrument: Mapping[str, float],
    config_path: str,
) -> GalaxySpec:
    """Rows of the [catalog] (COSMOS parametric fits)."""
    fit = values["fit"]
    scale = None
    if "pixel_scale" in given:
        scale = float(values["pixel_scale"])
        if scale <= 0:
            raise ConfigError(f"galaxy.pixel_scale: must be > 0, got {scale}")
    mode = flux_mode(given, instrument)
    params = parse_distributions(given, "galaxy", ["rad", mode])
    params["fit_ident"] = CatalogColumn("galaxy.fit", "IDENT")
    for part in ["sersic", "bulgedisk"] if fit == "auto" else [fit]:
        for name, (column, element) in COSMOS_FIT_COLUMNS[part].items():
            params[name] = CatalogColumn("galaxy.fit", column, element)
    params.update(knot_dists(given))
    return GalaxySpec(
        "cosmos_fit",
        params,
        position_angle(values),
        mode,
        sersicn_step(values),
        model={"fit": fit, "pixel_scale": scale},
    )


def usable_fit_rows(galaxy: GalaxySpec, parts: dict[str, dict[str, Any]], n_rows: int) -> int:
    """Keep the catalog rows whose chosen COSMOS fit is usable (positive sizes and axis
    ratios, a bulge fraction in [0, 1], GalSim's ``viable_sersic``/``use_bulgefit``)."""
    g = parts["galaxy"]
    cols = {
        k: v.data for k, v in g.items() if isinstance(v, CatalogColumn) and k.startswith("fit_")
    }
    fit = galaxy.model["fit"] if galaxy.model else "auto"
    ok_s = ok_b = np.zeros(n_rows, dtype=bool)
    if "fit_n" in cols:
        ok_s = (
            (cols["fit_viable"] > 0.5)
            & (cols["fit_hlr"] > 0)
            & (cols["fit_q"] > 0)
            & (cols["fit_q"] <= 1)
        )
    if "fit_disk_q" in cols:
        fb, fd = cols["fit_bulge_flux"], cols["fit_disk_flux"]
        ok_b = (
            (cols["fit_use_bulge"] > 0.5)
            & (cols["fit_bulge_hlr"] > 0)
            & (cols["fit_disk_hlr"] > 0)
            & (fb >= 0)
            & (fd >= 0)
            & (fb + fd > 0)
            & (cols["fit_disk_q"] > 0)
            & (cols["fit_disk_q"] <= 1)
            & (cols["fit_bulge_q"] > 0)
            & (cols["fit_bulge_q"] <= 1)
        )
    if fit == "sersic":
        keep = ok_s
    elif fit == "bulgedisk":
        keep = ok_b
    else:
        keep = np.where(cols["fit_use_bulge"] > 0.5, ok_b, ok_s)
    if not keep.any():
        raise ConfigError(f"galaxy.fit: no catalog row has a usable {fit!r} fit")
    if not keep.all():
        log.info(
            "galaxy.fit = %r: %d of %d catalog rows have a usable fit", fit, int(keep.sum()), n_rows
        )
    for part in parts.values():
        for name, d in part.items():
            if isinstance(d, CatalogColumn):
                part[name] = d.with_data(d.data[keep])
    return int(keep.sum())


def fit_truth(
    drawn: Mapping[str, np.ndarray], fit: str, pixel_scale: float | None, step: float
) -> ProfileTruth:
    """The parametric fit of the sampled catalog rows, as ``galsim.COSMOSCatalog`` builds it
    (``_buildParametric``), in simulation pixels of ``pixel_scale`` arcsec, or dilated to the
    composite half-light radius ``drawn["rad"]``; the ellipticity modulus is the disk's (or
    single Sersic's). The fit's own position angle is replaced by the simulation's
    (``angle``); the bulge keeps its angle relative to the disk."""
    n_rows = len(drawn["fit_ident"])
    use_bulge = {
        "sersic": np.zeros(n_rows, dtype=bool),
        "bulgedisk": np.ones(n_rows, dtype=bool),
        "auto": np.asarray(drawn.get("fit_use_bulge", np.zeros(n_rows)), dtype=float) > 0.5,
    }[fit]
    nan = np.full(n_rows, np.nan)

    def get(name: str) -> np.ndarray:  # fit columns absent for this fit: NaN
        return np.asarray(drawn.get(name, nan), dtype=float)

    n_single = round_sersicn(np.clip(get("fit_n"), *COSMOS_SERSIC_RANGE), step)
    fb, fd = get("fit_bulge_flux"), get("fit_disk_flux")
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(use_bulge, fb / (fb + fd), 0.0)
        ratio = np.where(use_bulge, get("fit_bulge_hlr") / get("fit_disk_hlr"), np.nan)
    disk_hlr = np.where(use_bulge, get("fit_disk_hlr"), get("fit_hlr"))  # arcsec
    disk_n = np.where(use_bulge, 1.0, n_single)
    hlr = disk_hlr * composite_hlr(frac, np.where(use_bulge, ratio, 1.0), 4.0, disk_n)
    if "rad" in drawn:
        rad = np.asarray(drawn["rad"], dtype=float)
        to_pixels = rad / hlr
    else:
        to_pixels = np.full(n_rows, 1.0 / float(pixel_scale))
        rad = hlr * to_pixels
    disk_rad = disk_hlr * to_pixels
    ellipticity = q_to_ellipticity(np.where(use_bulge, get("fit_disk_q"), get("fit_q")))
    cols: dict[str, np.ndarray] = {
        "tru_rad": rad,
        "tru_cosmos_ident": np.round(get("fit_ident")).astype(np.int64),
    }
    if fit == "sersic":
        cols["tru_sersicn"] = n_single
        return ProfileTruth(cols, ellipticity, rad)
    dtheta = np.rad2deg(get("fit_bulge_beta") - get("fit_disk_beta"))
    cols.update(
        {
            "tru_disk_rad": disk_rad,
            "tru_disk_sersicn": disk_n,
            "tru_bulge_fraction": frac,
            "tru_bulge_rad": np.where(use_bulge, ratio * disk_rad, np.nan),
            "tru_bulge_sersicn": np.where(use_bulge, 4.0, np.nan),
            "tru_bulge_ell": np.where(use_bulge, q_to_ellipticity(get("fit_bulge_q")), np.nan),
            "tru_bulge_dtheta": np.where(use_bulge, np.mod(dtheta + 90.0, 180.0) - 90.0, np.nan),
            "tru_bulge_dx": np.zeros(n_rows),
            "tru_bulge_dy": np.zeros(n_rows),
        }
    )
    return ProfileTruth(cols, ellipticity, rad)


def truth(spec: GalaxySpec, drawn: dict[str, np.ndarray], sequence: np.ndarray) -> ProfileTruth:
    model = spec.model or {}
    return fit_truth(drawn, model.get("fit", "auto"), model.get("pixel_scale"), spec.sersicn_step)


def build(
    spec: GalaxySpec, truth: Mapping[str, np.ndarray], k: int, gsparams: Any, pad_pixels: float
) -> Any:
    from megalut_cli.sim import galaxies  # GalSim: not needed to read a config

    return galaxies.galaxy_profile(truth, k, gsparams)  # a "sersic" fit is a Sérsic


PROFILE = GalaxyProfile(
    "cosmos_fit",
    "a COSMOS parametric fit (a Sérsic, or a bulge + disk) of a `[catalog]` row (below)",
    OPTIONS,
    (
        OneOf(
            ("pixel_scale", "rad"),
            "profile 'cosmos_fit' needs exactly one of galaxy.pixel_scale (arcsec per simulation "
            "pixel) or galaxy.rad (half-light radius in pixels, the fits then set only the "
            "morphology)",
        ),
        ONE_FLUX,
    ),
    parse,
    truth,
    build,
    truth_columns=("tru_cosmos_ident", "tru_sersicn", *bulgedisk.TRUTH_COLUMNS),
    refuses={"sersicn": FROM_THE_FITS, "ellipticity": FROM_THE_FITS},
    catalog="samples the rows of a [catalog] table (catalog.path = the COSMOS fits file, e.g. "
    "real_galaxy_catalog_23.5_example_fits.fits)",
    select_rows=usable_fit_rows,
)
