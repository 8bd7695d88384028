"""The ``[galaxy]`` table of a simulation config: Sersic, Gaussian, bulge + disk, COSMOS
parametric fits (``cosmos_fit``) and real galaxies (``real``), knots, Sérsic twins."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from megalut_cli.errors import ConfigError
from megalut_cli.schema import check_choice, check_float, check_table, resolve_beside
from megalut_cli.sim.distributions import (
    CatalogColumn,
    Distribution,
    Grid,
    parse_distribution,
    parse_distributions,
)
from megalut_cli.sim.noise_config import need_instrument

log = logging.getLogger(__name__)


PROFILES = ("sersic", "gaussian", "bulgedisk", "cosmos_fit", "real")
FLUX_KEYS = ("flux", "sb", "mag")
_GALAXY_KEYS = {"profile", "sersicn", "sersicn_step", "rad", "ellipticity", "angle", *FLUX_KEYS}
#: Star-forming knots (GalSim RandomKnots), for every profile but "real".
_KNOT_KEYS = {"knots", "knots_fraction"}
#: Bulge + disk keys (profile = "bulgedisk") and their defaults.
BULGE_DEFAULTS: dict[str, float] = {
    "bulge_rad_ratio": 0.5,
    "bulge_sersicn": 4.0,
    "bulge_ellipticity": 0.0,
    "bulge_angle": 0.0,
    "bulge_dx": 0.0,
    "bulge_dy": 0.0,
}
_BULGE_KEYS = {"bulge_fraction", *BULGE_DEFAULTS}
#: COSMOS parametric fits (profile = "cosmos_fit"): which fit, and the pixel scale.
_FIT_KEYS = {"fit"}
COSMOS_FITS = ("sersic", "bulgedisk", "auto")
_GALAXY_KEYS |= _KNOT_KEYS | _BULGE_KEYS | _FIT_KEYS
#: Keys of real galaxies (profile = "real") from a GalSim RealGalaxyCatalog.
_REAL_KEYS = {"real_catalog", "real_dir", "pixel_scale", "index", "real_select", "hst_noise", "twin", "twin_catalog",
              "real_order"}
#: What to do with the HST noise of real galaxies (see docs/config.md).
HST_NOISE_MODES = ("symmetrize", "whiten", "keep")
#: What to draw in place of each real galaxy: itself, or its Sérsic twin (docs/realgal.md).
TWIN_MODES = ("none", "sersic")
#: How real galaxies are assigned to SNC groups: drawn at random, or each in turn.
REAL_ORDERS = ("random", "each")
_GALAXY_KEYS |= _REAL_KEYS


@dataclass(frozen=True)
class GalaxySpec:
    profile: str
    params: dict[str, Distribution]  # rad, sersicn, flux|sb|mag, ellipticity (draw order)
    angle: Distribution  # position angle, degrees
    flux_mode: str
    sersicn_step: float
    #: profile "real": {"catalog": file, "dir": image folder, "pixel_scale": arcsec/pixel}
    real: dict[str, Any] | None = None
    #: profile "cosmos_fit": {"fit": "sersic" | "bulgedisk" | "auto", "pixel_scale": arcsec/pixel or None}
    model: dict[str, Any] | None = None

    @property
    def knots(self) -> bool:
        """Whether galaxies may get star-forming knots."""
        return "knots" in self.params


def _real_rows(select: Any, cat: Path) -> list[int]:
    """Rows of the RealGalaxyCatalog ``cat`` where the expression ``select`` holds."""
    from megalut_cli.catalog import catalog_info, read_catalog
    from megalut_cli.expr import check_expression, columns_used, evaluate_rows

    if not isinstance(select, str) or not select.strip():
        raise ConfigError("galaxy.real_select: expected an expression string, e.g. \"MAG < 24\"")
    _, names, _ = catalog_info(cat)
    try:
        check_expression(select, names)
    except ConfigError as err:
        raise ConfigError(f"galaxy.real_select: {err}") from None
    used = columns_used(select)
    table = read_catalog(cat, columns=used)
    mask = np.asarray(evaluate_rows(select, {c: np.asarray(table[c]) for c in used}, len(table)), dtype=bool)
    if not mask.any():
        raise ConfigError(f"galaxy.real_select: no galaxy of {cat.name} passes {select!r}")
    log.info("galaxy.real_select: %d of %d galaxies of %s", int(mask.sum()), len(mask), cat.name)
    return [int(i) for i in np.flatnonzero(mask)]


def _parse_twin(t: Mapping[str, Any], config_path: str, index: Distribution) -> dict[str, Any]:
    """``galaxy.twin`` and ``galaxy.twin_catalog``: draw each real galaxy's Sérsic twin."""
    twin = check_choice(t.get("twin", "none"), "galaxy.twin", TWIN_MODES)
    if "twin_catalog" not in t:
        if twin != "none":
            raise ConfigError("galaxy.twin_catalog: missing (required by galaxy.twin = 'sersic': the Sérsic-twin FITS table)")
        return {"twin": twin}
    path = str(resolve_beside(t["twin_catalog"], "galaxy.twin_catalog", config_path))
    if twin != "none":
        from megalut_cli.sim.twins import load_twins

        twins = load_twins(path)
        lo, hi = index.bounds()
        values = getattr(index, "values", None)
        rows = [int(v) for v in values] if values is not None else list(range(int(lo), int(hi) + 1))
        absent = [r for r in rows if r not in twins]
        if absent:
            raise ConfigError(f"galaxy.twin_catalog: {path}: no twin for real-catalog row(s) {absent[:5]}")
    return {"twin": twin, "twin_catalog": path}


def _parse_real_galaxy(t: dict[str, Any], instrument: Mapping[str, float], config_path: str) -> GalaxySpec:
    """``profile = "real"``: galaxies of a GalSim RealGalaxyCatalog (HST images)."""
    for k in ("rad", "sersicn", "sersicn_step", "ellipticity"):
        if k in t:
            raise ConfigError(
                f"galaxy.{k}: not a key of profile 'real' (size, shape and profile come from the HST images)"
            )
    for k in ("real_catalog", "pixel_scale"):
        if k not in t:
            what = "the RealGalaxyCatalog FITS file" if k == "real_catalog" else "arcsec per simulation pixel"
            raise ConfigError(f"galaxy.{k}: missing (required by profile 'real': {what})")
    cat = resolve_beside(t["real_catalog"], "galaxy.real_catalog", config_path)
    if "real_dir" in t:
        real_dir = str(resolve_beside(t["real_dir"], "galaxy.real_dir", config_path, folder=True))
    else:
        real_dir = str(cat.parent)
    scale = check_float(t["pixel_scale"], "galaxy.pixel_scale")
    if scale <= 0:
        raise ConfigError(f"galaxy.pixel_scale: must be > 0, got {scale}")
    from megalut_cli.sim.galaxies import real_galaxy_catalog

    n_obj = real_galaxy_catalog(str(cat), real_dir).nobjects
    given = [k for k in FLUX_KEYS if k in t]
    if len(given) != 1:
        raise ConfigError(
            "galaxy.flux: profile 'real' needs exactly one of galaxy.flux, galaxy.sb or galaxy.mag "
            f"(got {', '.join(given) or 'none'})"
        )
    flux_mode = given[0]
    if flux_mode == "sb" and "twin_catalog" not in t:
        raise ConfigError(
            "galaxy.sb: profile 'real' takes its size from galaxy.twin_catalog (the fitted half-light radius); "
            "give galaxy.twin_catalog, or galaxy.flux"
        )
    if flux_mode == "mag":
        need_instrument(instrument, ("zeropoint", "exptime", "gain"), "galaxy.mag")
    index = t.get("index", "random")
    if "real_select" in t:
        if "index" in t:
            raise ConfigError("galaxy.real_select: give either galaxy.index or galaxy.real_select")
        index = {"type": "grid", "values": _real_rows(t["real_select"], cat)}
    elif index == "random":
        index = {"type": "grid", "values": list(range(n_obj))}
    params = {"index": parse_distribution(index, "galaxy.index"), flux_mode: parse_distribution(t[flux_mode], f"galaxy.{flux_mode}")}
    lo, hi = params["index"].bounds()
    if lo < 0 or hi > n_obj - 1 or any(float(v) != int(v) for v in (lo, hi)):
        raise ConfigError(f"galaxy.index: must be integers in [0, {n_obj - 1}] (the rows of {cat.name}), got [{lo:g}, {hi:g}]")
    angle = parse_distribution(t.get("angle", {"type": "uniform", "min": 0.0, "max": 180.0}), "galaxy.angle")
    hst_noise = check_choice(t.get("hst_noise", "symmetrize"), "galaxy.hst_noise", HST_NOISE_MODES)
    real = {"catalog": str(cat), "dir": real_dir, "pixel_scale": scale, "n_objects": int(n_obj), "hst_noise": hst_noise}
    real.update(_parse_twin(t, config_path, params["index"]))
    real["order"] = check_choice(t.get("real_order", "random"), "galaxy.real_order", REAL_ORDERS)
    if real["order"] == "each":
        if not isinstance(params["index"], Grid):
            raise ConfigError("galaxy.real_order: 'each' needs galaxy.real_select or a grid of galaxy.index values")
        real["rows"] = tuple(int(v) for v in params["index"].values)
    return GalaxySpec("real", params, angle, flux_mode, 0.0, real)


def parse_galaxy(raw: Mapping[str, Any], instrument: Mapping[str, float], config_path: str = "<config>") -> GalaxySpec:
    t = check_table(raw.get("galaxy"), "galaxy", _GALAXY_KEYS, required=True)
    profile = check_choice(t.get("profile", "sersic"), "galaxy.profile", PROFILES)
    if profile == "real":
        extra = sorted(set(t) & (_KNOT_KEYS | _BULGE_KEYS | _FIT_KEYS))
        if extra:
            raise ConfigError(f"galaxy.{extra[0]}: not a key of profile 'real'")
        return _parse_real_galaxy(t, instrument, config_path)
    extra = sorted(set(t) & (_REAL_KEYS - ({"pixel_scale"} if profile == "cosmos_fit" else set())))
    if extra:
        where = "profile = 'real' or 'cosmos_fit'" if extra[0] == "pixel_scale" else "profile = 'real'"
        raise ConfigError(f"galaxy.{extra[0]}: only for {where}")
    extra = sorted(set(t) & (_BULGE_KEYS if profile != "bulgedisk" else set()))
    if extra:
        raise ConfigError(f"galaxy.{extra[0]}: only for profile = 'bulgedisk'")
    if "fit" in t and profile != "cosmos_fit":
        raise ConfigError("galaxy.fit: only for profile = 'cosmos_fit'")
    if profile == "cosmos_fit":
        return _parse_cosmos_fit(t, instrument)
    if "rad" not in t:
        raise ConfigError("galaxy.rad: missing (half-light radius in pixels)")
    flux_mode = _flux_mode(t, instrument)
    if profile == "sersic":
        if "sersicn" not in t:
            raise ConfigError("galaxy.sersicn: missing (Sersic index)")
    elif "sersicn" in t:
        raise ConfigError("galaxy.sersicn: only for profile = 'sersic'")
    step = _sersicn_step(t)
    keys = ["rad", "sersicn", flux_mode]
    params = parse_distributions(t, "galaxy", keys)
    params["ellipticity"] = parse_distribution(t.get("ellipticity", 0.0), "galaxy.ellipticity")
    if profile == "bulgedisk":
        if "bulge_fraction" not in t:
            raise ConfigError("galaxy.bulge_fraction: missing (fraction of the flux in the bulge, 0-1)")
        params["bulge_fraction"] = parse_distribution(t["bulge_fraction"], "galaxy.bulge_fraction")
        for k, default in BULGE_DEFAULTS.items():
            params[k] = parse_distribution(t.get(k, default), f"galaxy.{k}")
    params.update(_knot_dists(t))
    return GalaxySpec(profile, params, _angle(t), flux_mode, step)


def _flux_mode(t: Mapping[str, Any], instrument: Mapping[str, float]) -> str:
    given = [k for k in FLUX_KEYS if k in t]
    if len(given) != 1:
        raise ConfigError(
            "galaxy.flux: give exactly one of galaxy.flux, galaxy.sb (surface brightness) "
            f"or galaxy.mag (got {', '.join(given) or 'none'})"
        )
    if given[0] == "mag":
        need_instrument(instrument, ("zeropoint", "exptime", "gain"), "galaxy.mag")
    return given[0]


def _sersicn_step(t: Mapping[str, Any]) -> float:
    step = check_float(t.get("sersicn_step", 0.1), "galaxy.sersicn_step")
    if step < 0:
        raise ConfigError(f"galaxy.sersicn_step: must be >= 0, got {step}")
    return step


def _angle(t: Mapping[str, Any]) -> Distribution:
    return parse_distribution(t.get("angle", {"type": "uniform", "min": 0.0, "max": 180.0}), "galaxy.angle")


def _knot_dists(t: Mapping[str, Any]) -> dict[str, Distribution]:
    """``knots`` (number, 0 = none) and ``knots_fraction`` (of the disk's flux), if given."""
    if "knots" not in t:
        if "knots_fraction" in t:
            raise ConfigError("galaxy.knots_fraction: needs galaxy.knots (the number of knots)")
        return {}
    if "knots_fraction" not in t:
        raise ConfigError("galaxy.knots_fraction: missing (fraction of the disk's flux in the knots, 0-1)")
    return {k: parse_distribution(t[k], f"galaxy.{k}") for k in ("knots", "knots_fraction")}


#: Catalog columns of the COSMOS parametric fits (GalSim ``COSMOSCatalog._buildParametric``):
#: internal parameter -> (column, element).
COSMOS_FIT_COLUMNS: dict[str, dict[str, tuple[str, int | None]]] = {
    "sersic": {
        "fit_n": ("sersicfit", 2), "fit_q": ("sersicfit", 3), "fit_hlr": ("hlr", 0), "fit_viable": ("viable_sersic", None),
    },
    "bulgedisk": {
        "fit_disk_q": ("bulgefit", 3), "fit_disk_beta": ("bulgefit", 7), "fit_bulge_q": ("bulgefit", 11),
        "fit_bulge_beta": ("bulgefit", 15), "fit_bulge_hlr": ("hlr", 1), "fit_disk_hlr": ("hlr", 2),
        "fit_bulge_flux": ("flux", 1), "fit_disk_flux": ("flux", 2), "fit_use_bulge": ("use_bulgefit", None),
    },
}


def _parse_cosmos_fit(t: dict[str, Any], instrument: Mapping[str, float]) -> GalaxySpec:
    """``profile = "cosmos_fit"``: rows of the [catalog] (COSMOS parametric fits)."""
    for k in ("sersicn", "ellipticity", "real_select"):
        if k in t:
            raise ConfigError(f"galaxy.{k}: not a key of profile 'cosmos_fit' (profile and shape come from the fits)")
    fit = check_choice(t.get("fit", "auto"), "galaxy.fit", COSMOS_FITS)
    if ("rad" in t) == ("pixel_scale" in t):
        raise ConfigError(
            "galaxy.pixel_scale: profile 'cosmos_fit' needs exactly one of galaxy.pixel_scale (arcsec per "
            "simulation pixel) or galaxy.rad (half-light radius in pixels, the fits then set only the morphology)"
        )
    scale = None
    if "pixel_scale" in t:
        scale = check_float(t["pixel_scale"], "galaxy.pixel_scale")
        if scale <= 0:
            raise ConfigError(f"galaxy.pixel_scale: must be > 0, got {scale}")
    flux_mode = _flux_mode(t, instrument)
    params = parse_distributions(t, "galaxy", ["rad", flux_mode])
    params["fit_ident"] = CatalogColumn("galaxy.fit", "IDENT")
    for part in (["sersic", "bulgedisk"] if fit == "auto" else [fit]):
        for name, (column, element) in COSMOS_FIT_COLUMNS[part].items():
            params[name] = CatalogColumn("galaxy.fit", column, element)
    params.update(_knot_dists(t))
    return GalaxySpec("cosmos_fit", params, _angle(t), flux_mode, _sersicn_step(t),
                      model={"fit": fit, "pixel_scale": scale})


def usable_fit_rows(galaxy: GalaxySpec, parts: dict[str, dict[str, Any]], n_rows: int) -> int:
    """Keep the catalog rows whose chosen COSMOS fit is usable (positive sizes and axis
    ratios, a bulge fraction in [0, 1], GalSim's ``viable_sersic``/``use_bulgefit``)."""
    g = parts["galaxy"]
    cols = {k: v.data for k, v in g.items() if isinstance(v, CatalogColumn) and k.startswith("fit_")}
    fit = galaxy.model["fit"] if galaxy.model else "auto"
    ok_s = ok_b = np.zeros(n_rows, dtype=bool)
    if "fit_n" in cols:
        ok_s = (cols["fit_viable"] > 0.5) & (cols["fit_hlr"] > 0) & (cols["fit_q"] > 0) & (cols["fit_q"] <= 1)
    if "fit_disk_q" in cols:
        fb, fd = cols["fit_bulge_flux"], cols["fit_disk_flux"]
        ok_b = ((cols["fit_use_bulge"] > 0.5) & (cols["fit_bulge_hlr"] > 0) & (cols["fit_disk_hlr"] > 0)
                & (fb >= 0) & (fd >= 0) & (fb + fd > 0)
                & (cols["fit_disk_q"] > 0) & (cols["fit_disk_q"] <= 1)
                & (cols["fit_bulge_q"] > 0) & (cols["fit_bulge_q"] <= 1))
    if fit == "sersic":
        keep = ok_s
    elif fit == "bulgedisk":
        keep = ok_b
    else:
        keep = np.where(cols["fit_use_bulge"] > 0.5, ok_b, ok_s)
    if not keep.any():
        raise ConfigError(f"galaxy.fit: no catalog row has a usable {fit!r} fit")
    if not keep.all():
        log.info("galaxy.fit = %r: %d of %d catalog rows have a usable fit", fit, int(keep.sum()), n_rows)
    for part in parts.values():
        for name, d in part.items():
            if isinstance(d, CatalogColumn):
                part[name] = d.with_data(d.data[keep])
    return int(keep.sum())
