"""Simulation configuration: TOML loading, ``key=value`` overrides and validation.

The reference of every key is ``docs/config.md``. :func:`load_config` returns a
:class:`SimConfig` whose parts are plain, picklable data (distributions, numbers and the
input-catalog columns already read), so that work units can carry it to any worker.
Every problem is reported as one :class:`~megalut_cli.errors.ConfigError` naming the key.
"""

from __future__ import annotations

import copy
import hashlib
import json
import logging
import math
import os
import re
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from megalut_cli.errors import ConfigError, InputError
from megalut_cli.schema import (
    check_bool,
    check_choice,
    check_float,
    check_int,
    check_table,
    resolve_path,
)
from megalut_cli.sim.distributions import (
    DIST_TYPES,
    CatalogColumn,
    Distribution,
    Grid,
    is_distribution_table,
    parse_distribution,
)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

log = logging.getLogger("megalut")

#: Parameter groups that can be redrawn for every realization (else once per case).
VARY_GROUPS = ("shear", "galaxy", "angle", "psf")
SNC_MODES = ("ring", "pairs", "none")
PROFILES = ("sersic", "gaussian", "bulgedisk", "cosmos_fit", "real")
NOISE_TYPES = ("gaussian", "ccd", "correlated", "none")
FLUX_KEYS = ("flux", "sb", "mag")
#: GalSim's Sersic index range.
SERSIC_N_RANGE = (0.3, 6.2)

_TOP_KEYS = {
    "description",
    "structure",
    "shear",
    "galaxy",
    "psf",
    "noise",
    "instrument",
    "field",
    "catalog",
    "gsparams",
}
#: GalSim GSParams settable in [gsparams] (accuracy/speed of the rendering).
GSPARAMS_KEYS = {
    "folding_threshold": float,
    "maxk_threshold": float,
    "kvalue_accuracy": float,
    "xvalue_accuracy": float,
    "stepk_minimum_hlr": float,
    "minimum_fft_size": int,
    "maximum_fft_size": int,
}
_STRUCTURE_KEYS = {
    "n_cases",
    "n_realizations",
    "per_realization",
    "snc",
    "stamp_size",
    "offset",
    "n_x",
    "common",
}
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
_NOISE_KEYS = {"type", "sigma", "sky_mag", "read_noise", "override_sigma"}
#: Keys of correlated noise (noise.type = "correlated").
_CORRELATED_KEYS = {"sigma", "image", "correlation", "hdu", "pixel_scale"}
_NOISE_KEYS |= _CORRELATED_KEYS
_INSTRUMENT_KEYS = {"pixel_scale", "exptime", "gain", "zeropoint"}
_CATALOG_KEYS = {"path", "select", "hdu"}


@dataclass(frozen=True)
class StructureSpec:
    """Cases x realizations, what varies per realization, shape-noise cancellation."""

    n_cases: int
    n_realizations: int
    per_realization: frozenset[str]
    snc: str
    stamp_size: int
    offset: float
    n_x: int | None = None
    #: Common random numbers: every case draws the same galaxies, offsets and noise.
    common: bool = False

    @property
    def group_size(self) -> int:
        """Realizations sharing their per-realization parameters (an SNC group)."""
        return {"ring": self.n_realizations, "pairs": 2, "none": 1}[self.snc]

    @property
    def n_groups(self) -> int:
        return self.n_realizations // self.group_size

    @property
    def n_stamps(self) -> int:
        return self.n_cases * self.n_realizations

    @property
    def grid_nx(self) -> int:
        """Stamps per row of the grid image (``n_x``, default ceil(sqrt(N)))."""
        return self.n_x if self.n_x else max(1, math.ceil(math.sqrt(self.n_stamps)))

    def varies(self, group: str) -> bool:
        """Whether ``group`` is redrawn per realization (``galaxy`` implies ``angle``)."""
        return group in self.per_realization or (group == "angle" and "galaxy" in self.per_realization)


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


#: Sources of correlated noise: a noise image or a correlation-function image.
CORRELATED_SOURCES = ("image", "correlation")


@dataclass(frozen=True)
class CorrelationSource:
    """Where a correlated-noise model comes from (plain, picklable)."""

    kind: str  # "image" | "correlation"
    path: str
    hdu: int | None = None
    pixel_scale: float = 1.0  # size of the source's pixel in simulation pixels


@dataclass(frozen=True)
class NoiseSpec:
    type: str
    params: dict[str, Distribution]  # sigma | sky_mag, read_noise
    override_sigma: float | None = None
    #: type "correlated": where the correlation function comes from
    source: CorrelationSource | None = None


@dataclass(frozen=True)
class SimConfig:
    """A validated simulation configuration (picklable)."""

    path: str
    sha256: str
    raw: dict[str, Any]
    overrides: tuple[str, ...]
    structure: StructureSpec
    shear: dict[str, Distribution]
    field: dict[str, Distribution] | None
    psf: dict[str, Any]  # scalars and Distribution objects, resolved per case
    psf_varies: bool
    galaxy: GalaxySpec
    noise: NoiseSpec
    instrument: dict[str, float]
    catalog_rows: int = 0
    catalog_path: str | None = None
    gsparams: dict[str, float] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> str:
        """The effective configuration (overrides applied) as JSON text."""
        return json.dumps(self.raw, sort_keys=True, default=str)

    def with_structure(self, **changes: Any) -> SimConfig:
        return replace(self, structure=replace(self.structure, **changes))

    @property
    def gain(self) -> float | None:
        """The gain (e-/ADU) when the noise is CCD-like, else None (SNR by Eq. 10)."""
        if self.noise.type == "ccd" and self.noise.override_sigma is None:
            return self.instrument["gain"]
        return None


# --------------------------------------------------------------------------- loading


def parse_override(text: str) -> tuple[list[str], Any]:
    """``"galaxy.rad.max=6"`` -> (["galaxy", "rad", "max"], 6); values are TOML values
    (``psf.type=moffat`` gives the string ``"moffat"``)."""
    if "=" not in text:
        raise ConfigError(f"override {text!r}: expected KEY=VALUE (e.g. noise.sigma=0.5)")
    key, value = text.split("=", 1)
    key = key.strip()
    parts = key.split(".")
    if not key or any(not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_-]*", p) for p in parts):
        raise ConfigError(f"override {text!r}: bad key {key!r} (expected dotted names)")
    value = value.strip()
    try:
        parsed = tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        parsed = value  # bare words are strings
    return parts, parsed


def apply_overrides(raw: dict[str, Any], overrides: Sequence[str]) -> dict[str, Any]:
    """Return a copy of ``raw`` with dotted ``key=value`` overrides applied."""
    out = copy.deepcopy(raw)
    for text in overrides:
        parts, value = parse_override(text)
        node = out
        for i, p in enumerate(parts[:-1]):
            child = node.get(p)
            if child is None:
                child = node[p] = {}
            if not isinstance(child, dict):
                where = ".".join(parts[: i + 1])
                raise ConfigError(f"override {text!r}: {where} is not a table")
            node = child
        node[parts[-1]] = value
    return out


def read_toml(path: str | os.PathLike) -> tuple[dict[str, Any], str]:
    """Parse a TOML file; return ``(data, sha256 of its bytes)``."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    data = p.read_bytes()
    try:
        raw = tomllib.loads(data.decode("utf-8"))
    except UnicodeDecodeError:
        raise ConfigError(f"{p}: not a text (UTF-8) TOML file") from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{p}: invalid TOML ({err})") from None
    return raw, hashlib.sha256(data).hexdigest()


def load_config(
    path: str | os.PathLike,
    overrides: Sequence[str] = (),
    n_cases: int | None = None,
    n_realizations: int | None = None,
) -> SimConfig:
    """Read, override and validate a simulation config file."""
    raw, sha = read_toml(path)
    raw = apply_overrides(raw, overrides)
    structure = raw.setdefault("structure", {}) if isinstance(raw.get("structure", {}), dict) else None
    if structure is None:
        raise ConfigError("structure: expected a table")
    if n_cases is not None:
        structure["n_cases"] = int(n_cases)
    if n_realizations is not None:
        structure["n_realizations"] = int(n_realizations)
    return validate_config(raw, path=str(path), sha256=sha, overrides=tuple(overrides))


# --------------------------------------------------------------------------- validation










def _parse_structure(raw: Mapping[str, Any]) -> StructureSpec:
    t = check_table(raw.get("structure"), "structure", _STRUCTURE_KEYS, required=True)
    for k in ("n_cases", "n_realizations"):
        if k not in t:
            raise ConfigError(f"structure.{k}: missing")
    n_cases = check_int(t["n_cases"], "structure.n_cases", 1)
    n_rea = check_int(t["n_realizations"], "structure.n_realizations", 1)
    per = t.get("per_realization", ["angle"])
    if isinstance(per, str):
        per = [per]
    if not isinstance(per, list) or not all(isinstance(p, str) for p in per):
        raise ConfigError("structure.per_realization: expected a list of names")
    for p in per:
        check_choice(p, "structure.per_realization", VARY_GROUPS)
    snc = check_choice(t.get("snc", "none"), "structure.snc", SNC_MODES)
    if snc == "pairs" and n_rea % 2:
        raise ConfigError(
            f"structure.n_realizations: snc = 'pairs' needs an even number, got {n_rea}"
        )
    stamp = check_int(t.get("stamp_size", 64), "structure.stamp_size", 8)
    if stamp > 4096:
        raise ConfigError(f"structure.stamp_size: {stamp} is too large (max 4096)")
    offset = check_float(t.get("offset", 0.5), "structure.offset")
    if offset < 0 or offset > stamp / 4:
        raise ConfigError(f"structure.offset: must be in [0, stamp_size/4], got {offset}")
    n_x = t.get("n_x")
    if n_x is not None:
        n_x = check_int(n_x, "structure.n_x", 1)
    common = check_bool(t.get("common", False), "structure.common")
    if common:
        _check_common(frozenset(per), snc)
    return StructureSpec(n_cases, n_rea, frozenset(per), snc, stamp, offset, n_x, common)




def _check_common(per: frozenset[str], snc: str) -> None:
    """Refuse common-random-number sets that cannot mean anything."""
    if "galaxy" not in per:
        raise ConfigError(
            "structure.common: needs per_realization to include 'galaxy' (a new galaxy per realization "
            "group, the same one in every case)"
        )
    if "shear" in per:
        raise ConfigError("structure.common: the shear must be drawn per case; remove 'shear' from per_realization")
    if snc == "ring":
        raise ConfigError(
            "structure.common: snc = 'ring' makes one galaxy per case, nothing to share between cases; "
            "use snc = 'pairs' or 'none'"
        )


def _dists(table: Mapping[str, Any], prefix: str, keys: Sequence[str]) -> dict[str, Distribution]:
    return {k: parse_distribution(table[k], f"{prefix}.{k}") for k in keys if k in table}


def _parse_instrument(raw: Mapping[str, Any]) -> dict[str, float]:
    t = check_table(raw.get("instrument"), "instrument", _INSTRUMENT_KEYS)
    out = {}
    for k, v in t.items():
        out[k] = check_float(v, f"instrument.{k}")
        if k != "zeropoint" and out[k] <= 0:
            raise ConfigError(f"instrument.{k}: must be > 0, got {out[k]}")
    return out


def _need_instrument(instrument: Mapping[str, float], keys: Sequence[str], why: str) -> None:
    for k in keys:
        if k not in instrument:
            raise ConfigError(f"instrument.{k}: missing (needed by {why})")


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
    path = str(_resolve_path(t["twin_catalog"], "galaxy.twin_catalog", config_path))
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
    for k in ("rad", "sersicn", "sersicn_step", "ellipticity", "sb"):
        if k in t:
            raise ConfigError(
                f"galaxy.{k}: not a key of profile 'real' (size, shape and profile come from the HST images)"
            )
    for k in ("real_catalog", "pixel_scale"):
        if k not in t:
            what = "the RealGalaxyCatalog FITS file" if k == "real_catalog" else "arcsec per simulation pixel"
            raise ConfigError(f"galaxy.{k}: missing (required by profile 'real': {what})")
    cat = _resolve_path(t["real_catalog"], "galaxy.real_catalog", config_path)
    if "real_dir" in t:
        real_dir = str(_resolve_path(t["real_dir"], "galaxy.real_dir", config_path, folder=True))
    else:
        real_dir = str(cat.parent)
    scale = check_float(t["pixel_scale"], "galaxy.pixel_scale")
    if scale <= 0:
        raise ConfigError(f"galaxy.pixel_scale: must be > 0, got {scale}")
    from megalut_cli.sim.galaxies import real_galaxy_catalog

    n_obj = real_galaxy_catalog(str(cat), real_dir).nobjects
    given = [k for k in ("flux", "mag") if k in t]
    if len(given) != 1:
        raise ConfigError(f"galaxy.flux: profile 'real' needs exactly one of galaxy.flux or galaxy.mag (got {', '.join(given) or 'none'})")
    flux_mode = given[0]
    if flux_mode == "mag":
        _need_instrument(instrument, ("zeropoint", "exptime", "gain"), "galaxy.mag")
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


def _parse_galaxy(raw: Mapping[str, Any], instrument: Mapping[str, float], config_path: str = "<config>") -> GalaxySpec:
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
    params = _dists(t, "galaxy", keys)
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
        _need_instrument(instrument, ("zeropoint", "exptime", "gain"), "galaxy.mag")
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
    params = _dists(t, "galaxy", ["rad", flux_mode])
    params["fit_ident"] = CatalogColumn("galaxy.fit", "IDENT")
    for part in (["sersic", "bulgedisk"] if fit == "auto" else [fit]):
        for name, (column, element) in COSMOS_FIT_COLUMNS[part].items():
            params[name] = CatalogColumn("galaxy.fit", column, element)
    params.update(_knot_dists(t))
    return GalaxySpec("cosmos_fit", params, _angle(t), flux_mode, _sersicn_step(t),
                      model={"fit": fit, "pixel_scale": scale})


def _usable_fit_rows(galaxy: GalaxySpec, parts: dict[str, dict[str, Any]], n_rows: int) -> int:
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


_MEASURED_KEYS = {"type", "path", "column", "statistic", "select", "scale"}
MEASURED_STATISTICS = ("median", "mean")


def is_measured(value: Any) -> bool:
    """Whether a parameter value is a ``{type = "measured", ...}`` table."""
    return isinstance(value, Mapping) and value.get("type") == "measured"


def measured_value(value: Mapping[str, Any], key: str, config_path: str) -> float:
    """A value measured on data: ``statistic`` (median) of ``column`` (skymad) of the
    catalog ``path`` (FITS, or text with ``# name`` lines), over the rows passing
    ``select`` with a finite value, times ``scale`` (1)."""
    from megalut_cli.expr import check_expression, columns_used, evaluate_rows
    from megalut_cli.great3.layout import read_any_catalog

    unknown = sorted(set(value) - _MEASURED_KEYS)
    if unknown:
        raise ConfigError(f"{key}.{unknown[0]}: unknown key (allowed: {', '.join(sorted(_MEASURED_KEYS - {'type'}))})")
    path = _resolve_path(value.get("path"), f"{key}.path", config_path)
    column = value.get("column", "skymad")
    if not isinstance(column, str) or not column:
        raise ConfigError(f"{key}.column: expected a column name, got {column!r}")
    statistic = check_choice(value.get("statistic", "median"), f"{key}.statistic", MEASURED_STATISTICS)
    scale = check_float(value.get("scale", 1.0), f"{key}.scale")
    select = value.get("select")
    if select is not None and not isinstance(select, str):
        raise ConfigError(f"{key}.select: expected an expression string")
    table = read_any_catalog(path)
    if column not in table.colnames:
        raise ConfigError(f"{key}.column: no column {column!r} in {path}")
    v = np.asarray(table[column], dtype=float)
    if v.ndim != 1:
        raise ConfigError(f"{key}.column: {column!r} is not a scalar column")
    mask = np.isfinite(v)
    if select is not None:
        check_expression(select, list(table.colnames))
        cols = {c: np.asarray(table[c]) for c in columns_used(select)}
        mask &= np.asarray(evaluate_rows(select, cols, len(v)), dtype=bool)
    if not mask.any():
        raise ConfigError(f"{key}: no row of {path} with a finite {column}" + (f" passing {select!r}" if select else ""))
    out = float((np.median if statistic == "median" else np.mean)(v[mask])) * scale
    if not (math.isfinite(out) and out >= 0):
        raise ConfigError(f"{key}: the measured value {out!r} is not a valid noise level")
    log.info("%s = %g: %s of %s over %d row(s) of %s", key, out, statistic, column, int(mask.sum()), path)
    return out


def _parse_noise(raw: Mapping[str, Any], instrument: Mapping[str, float], config_path: str = "<config>") -> NoiseSpec:
    t = check_table(raw.get("noise"), "noise", _NOISE_KEYS, required=True)
    if is_measured(t.get("sigma")):
        t["sigma"] = measured_value(t["sigma"], "noise.sigma", config_path)
    kind = check_choice(t.get("type"), "noise.type", NOISE_TYPES)
    allowed = {"gaussian": {"sigma"}, "ccd": {"sky_mag", "read_noise"}, "correlated": _CORRELATED_KEYS,
               "none": set()}[kind]
    extra = sorted(set(t) - allowed - {"type", "override_sigma"})
    if extra:
        raise ConfigError(f"noise.{extra[0]}: not a key of noise type {kind!r}")
    source = None
    if kind == "correlated":
        source = _correlation_source(t, config_path)
        if "sigma" not in t:
            if source.kind == "correlation":
                raise ConfigError("noise.sigma: missing (pixel standard deviation in ADU of the correlated noise)")
            from megalut_cli.sim.noise import source_variance

            t["sigma"] = math.sqrt(source_variance(source))
            log.info("noise.sigma = %g: the pixel standard deviation of %s", t["sigma"], source.path)
        params = _dists(t, "noise", ["sigma"])
    elif kind == "gaussian":
        if "sigma" not in t:
            raise ConfigError("noise.sigma: missing (standard deviation in ADU)")
        params = _dists(t, "noise", ["sigma"])
    elif kind == "ccd":
        if "sky_mag" not in t:
            raise ConfigError("noise.sky_mag: missing (sky brightness in mag per arcsec^2)")
        _need_instrument(instrument, ("pixel_scale", "exptime", "gain", "zeropoint"), "noise type 'ccd'")
        params = {
            "sky_mag": parse_distribution(t["sky_mag"], "noise.sky_mag"),
            "read_noise": parse_distribution(t.get("read_noise", 0.0), "noise.read_noise"),
        }
    else:
        params = {}
    override = t.get("override_sigma")
    if override is not None:
        override = check_float(override, "noise.override_sigma")
        if override < 0:
            raise ConfigError(f"noise.override_sigma: must be >= 0, got {override}")
    return NoiseSpec(kind, params, override, source)


def _correlation_source(t: Mapping[str, Any], config_path: str) -> CorrelationSource:
    """The noise image or correlation-function image of ``noise.type = "correlated"``."""
    given = [k for k in CORRELATED_SOURCES if k in t]
    if len(given) != 1:
        raise ConfigError(
            "noise.image: correlated noise needs exactly one of noise.image (a FITS noise image, e.g. a "
            "blank-sky cutout) or noise.correlation (a FITS correlation-function image, e.g. GalSim's "
            f"acs_I_unrot_sci_20_cf.fits) (got {', '.join(given) or 'none'})"
        )
    kind = given[0]
    path = _resolve_path(t[kind], f"noise.{kind}", config_path)
    hdu = t.get("hdu")
    if hdu is not None:
        hdu = check_int(hdu, "noise.hdu", 0)
    scale = check_float(t.get("pixel_scale", 1.0), "noise.pixel_scale")
    if scale <= 0:
        raise ConfigError(f"noise.pixel_scale: must be > 0, got {scale}")
    if kind == "correlation" and hdu is not None:
        raise ConfigError("noise.hdu: only for noise.image (a correlation-function file is read from its first HDU)")
    source = CorrelationSource(kind, str(path), hdu, scale)
    from megalut_cli.sim.noise import unit_correlated_noise

    try:
        unit_correlated_noise(source)  # fail now, with one line, on an unusable file
    except InputError as err:
        raise ConfigError(str(err)) from None
    return source


def _parse_gsparams(raw: Mapping[str, Any]) -> dict[str, float]:
    t = check_table(raw.get("gsparams"), "gsparams", set(GSPARAMS_KEYS))
    out: dict[str, float] = {}
    for k, v in t.items():
        if GSPARAMS_KEYS[k] is int:
            out[k] = check_int(v, f"gsparams.{k}", 16)
        else:
            out[k] = check_float(v, f"gsparams.{k}")
            upper = math.inf if k == "stepk_minimum_hlr" else 1.0
            if not 0 < out[k] < upper:
                raise ConfigError(f"gsparams.{k}: must be in (0, {upper:g}), got {out[k]}")
    if out:
        import galsim

        try:
            galsim.GSParams(**out)
        except (ValueError, TypeError, galsim.GalSimError) as err:
            raise ConfigError(f"gsparams: {err}") from None
    return out


def _parse_psf(raw: Mapping[str, Any], config_path: str) -> dict[str, Any]:
    t = check_table(raw.get("psf"), "psf", None, required=True)
    if "type" not in t:
        raise ConfigError("psf.type: missing")
    if t["type"] == "stamp" and "path" in t:  # a star image: same lookup as catalog.path
        t["path"] = str(_resolve_path(t["path"], "psf.path", config_path))
    if t["type"] == "stamp" and t.get("index") == "random":  # one star of the grid per case
        if t.get("stamp_size") is None or "path" not in t:
            raise ConfigError("psf.index: 'random' needs psf.path and psf.stamp_size (a grid of stars)")
        from megalut_cli.sim.psf import star_grid_size

        t["stamp_size"] = check_int(t["stamp_size"], "psf.stamp_size", 3)
        n = star_grid_size(t["path"], t.get("hdu"), t["stamp_size"])
        t["index"] = {"type": "grid", "values": list(range(n))}
    elif isinstance(t.get("index"), str):
        raise ConfigError(f"psf.index: expected an integer, a distribution or 'random', got {t['index']!r}")
    spec: dict[str, Any] = {}
    for k, v in t.items():
        if k != "type" and is_distribution_table(v) and v.get("type") in DIST_TYPES:
            spec[k] = parse_distribution(v, f"psf.{k}")
        else:
            spec[k] = v
    return spec


def _resolve_path(text: Any, key: str, config_path: str, folder: bool = False) -> Path:
    """A path named by the config ``config_path`` (:func:`megalut_cli.schema.resolve_path`)."""
    return resolve_path(text, key, Path(config_path).resolve().parent, folder)


def _catalog_dists(parts: Mapping[str, Mapping[str, Any]]) -> list[tuple[str, str, CatalogColumn]]:
    found = []
    for part, dists in parts.items():
        for name, d in dists.items():
            if isinstance(d, CatalogColumn):
                found.append((part, name, d))
    return found


def _element_columns(expr_cols: Sequence[str], table: Any) -> dict[str, np.ndarray]:
    cols: dict[str, np.ndarray] = {}
    for name in expr_cols:
        if name in table.colnames:
            arr = np.asarray(table[name])
            if arr.ndim != 1:
                raise ConfigError(
                    f"catalog.select: {name!r} is an array column; use {name}_0, {name}_1, ..."
                )
            cols[name] = arr
            continue
        m = re.fullmatch(r"(.+)_(\d+)", name)
        if m and m.group(1) in table.colnames:
            arr = np.asarray(table[m.group(1)])
            i = int(m.group(2))
            if arr.ndim == 2 and i < arr.shape[1]:
                cols[name] = arr[:, i]
                continue
        raise ConfigError(f"catalog.select: unknown column {name!r}")
    return cols


def _load_catalog(
    raw: Mapping[str, Any], config_path: str, parts: dict[str, dict[str, Any]]
) -> tuple[int, str | None]:
    """Read the [catalog] columns used by ``catalog`` distributions; attach their data."""
    from megalut_cli.catalog import read_catalog
    from megalut_cli.expr import columns_used, evaluate_rows

    t = check_table(raw.get("catalog"), "catalog", _CATALOG_KEYS)
    found = _catalog_dists(parts)
    if not found:
        if t:
            log.warning("[catalog] given but no parameter has type = 'catalog'; ignored")
        return 0, None
    if not t:
        raise ConfigError(f"{found[0][2].key}: type 'catalog' needs a [catalog] table with a path")
    if "hdu" in t:
        log.warning("catalog.hdu is ignored: the first table extension is read")
    path = _resolve_path(t.get("path"), "catalog.path", config_path)
    select = t.get("select")
    expr_cols: list[str] = []
    if select is not None:
        if not isinstance(select, str):
            raise ConfigError("catalog.select: expected an expression string")
        expr_cols = columns_used(select)
    from megalut_cli.catalog import catalog_info

    _, names, _ = catalog_info(path)
    needed = {d.column for _, _, d in found}
    for name in expr_cols:
        m = re.fullmatch(r"(.+)_(\d+)", name)
        needed.add(m.group(1) if (m and name not in names and m.group(1) in names) else name)
    for _, _, d in found:
        if d.column not in names:
            raise ConfigError(f"{d.key}.column: no column {d.column!r} in {path}")
    unknown = sorted(n for n in needed if n not in names)
    if unknown:
        raise ConfigError(f"catalog.select: unknown column {unknown[0]!r}")
    table = read_catalog(path, columns=sorted(needed))
    n = len(table)
    mask = np.ones(n, dtype=bool)
    if select is not None:
        mask = np.asarray(evaluate_rows(select, _element_columns(expr_cols, table), n), dtype=bool)
    values: dict[tuple[str, str], np.ndarray] = {}
    for part, name, d in found:
        arr = np.asarray(table[d.column])
        if arr.dtype.kind not in "fiu":
            raise ConfigError(f"{d.key}.column: {d.column!r} is not numeric")
        if arr.ndim == 2:
            if d.element is None:
                raise ConfigError(
                    f"{d.key}.element: {d.column!r} is an array column of {arr.shape[1]} values; "
                    "give element = INDEX (0-based)"
                )
            if d.element >= arr.shape[1]:
                raise ConfigError(
                    f"{d.key}.element: {d.element} out of range for {d.column!r} "
                    f"({arr.shape[1]} values)"
                )
            arr = arr[:, d.element]
        elif arr.ndim != 1:
            raise ConfigError(f"{d.key}.column: {d.column!r} has an unsupported shape")
        elif d.element is not None:
            raise ConfigError(f"{d.key}.element: {d.column!r} is not an array column")
        values[(part, name)] = arr.astype(float) * d.scale + d.offset
    finite = np.all([np.isfinite(v) for v in values.values()], axis=0)
    bad = int(np.sum(mask & ~finite))
    if bad:
        log.warning("%s: %d selected row(s) with non-finite values skipped", path, bad)
    mask &= finite
    if not mask.any():
        raise ConfigError(f"catalog.select: no usable row left in {path}")
    for part, name, d in found:
        parts[part][name] = d.with_data(values[(part, name)][mask])
    log.info("catalog %s: sampling from %d of %d rows", path, int(mask.sum()), n)
    return int(mask.sum()), str(path)


def _check_range(d: Distribution, lo: float | None, hi: float | None, what: str, strict_lo: bool = False) -> None:
    a, b = d.bounds()
    if lo is not None and (a <= lo if strict_lo else a < lo):
        rel = ">" if strict_lo else ">="
        raise ConfigError(f"{d.key}: {what} must be {rel} {lo}, but values reach {a:g}")
    if hi is not None and b > hi:
        raise ConfigError(f"{d.key}: {what} must be <= {hi}, but values reach {b:g}")


def round_sersicn(n: np.ndarray, step: float) -> np.ndarray:
    """Round Sersic indices to multiples of ``step`` (GalSim caches profiles per index)."""
    if step <= 0:
        return np.asarray(n, dtype=float)
    return np.round(np.round(np.asarray(n) / step) * step, 10)


def validate_config(
    raw: Mapping[str, Any], path: str = "<config>", sha256: str = "", overrides: tuple[str, ...] = ()
) -> SimConfig:
    """Validate a parsed config mapping; return a :class:`SimConfig`."""
    if not isinstance(raw, Mapping):
        raise ConfigError("config: expected a table")
    unknown = sorted(set(raw) - _TOP_KEYS)
    if unknown:
        raise ConfigError(f"{unknown[0]}: unknown table or key (allowed: {', '.join(sorted(_TOP_KEYS))})")
    if "description" in raw and not isinstance(raw["description"], str):
        raise ConfigError("description: expected a string")
    structure = _parse_structure(raw)
    instrument = _parse_instrument(raw)
    shear_t = check_table(raw.get("shear"), "shear", {"g1", "g2"})
    shear = _dists(shear_t, "shear", ["g1", "g2"])
    galaxy = _parse_galaxy(raw, instrument, path)
    noise = _parse_noise(raw, instrument, path)
    if galaxy.real is not None and galaxy.real["hst_noise"] != "keep" and noise.type in ("ccd", "correlated") and noise.override_sigma is None:
        raise ConfigError(
            f"galaxy.hst_noise: {galaxy.real['hst_noise']!r} needs noise.type = 'gaussian' (the added noise "
            "makes up the rest of the variance); or set galaxy.hst_noise = 'keep'"
        )
    psf = _parse_psf(raw, path)
    gsparams = _parse_gsparams(raw)
    field_t = check_table(raw.get("field"), "field", {"x", "y"})
    field_d = _dists(field_t, "field", ["x", "y"]) if field_t else None
    if field_d is not None and len(field_d) != 2:
        raise ConfigError(f"field.{'y' if 'x' in field_d else 'x'}: missing")

    psf_dists = {k: v for k, v in psf.items() if isinstance(v, Distribution)}
    parts: dict[str, dict[str, Any]] = {
        "shear": shear,
        "field": field_d or {},
        "psf": psf_dists,
        "galaxy": galaxy.params,
        "angle": {"angle": galaxy.angle},
        "noise": noise.params,
    }
    if galaxy.profile == "cosmos_fit" and not isinstance(raw.get("catalog"), Mapping):
        raise ConfigError(
            "galaxy.profile: 'cosmos_fit' samples the rows of a [catalog] table (catalog.path = the COSMOS "
            "fits file, e.g. real_galaxy_catalog_23.5_example_fits.fits)"
        )
    n_rows, cat_path = _load_catalog(raw, path, parts)
    if galaxy.profile == "cosmos_fit":
        n_rows = _usable_fit_rows(galaxy, parts, n_rows)
    psf.update(parts["psf"])
    galaxy = replace(galaxy, angle=parts["angle"]["angle"])
    if field_d is not None:
        field_d = parts["field"]

    # Ranges
    g = galaxy.params
    if "rad" in g:
        _check_range(g["rad"], 0.0, None, "the half-light radius", strict_lo=True)
    if galaxy.flux_mode in ("flux", "sb"):
        _check_range(g[galaxy.flux_mode], 0.0, None, "the flux" if galaxy.flux_mode == "flux" else "the surface brightness")
    if "ellipticity" in g:
        _check_range(g["ellipticity"], 0.0, None, "the ellipticity modulus")
        a, b = g["ellipticity"].bounds()
        if b >= 1.0:
            raise ConfigError(f"galaxy.ellipticity: the modulus must be < 1, but values reach {b:g}")
    for name in ("sersicn", "bulge_sersicn"):
        if name in g:
            lo, hi = (float(round_sersicn(np.array(v), galaxy.sersicn_step)) for v in g[name].bounds())
            if lo < SERSIC_N_RANGE[0] or hi > SERSIC_N_RANGE[1]:
                raise ConfigError(
                    f"galaxy.{name}: GalSim supports {SERSIC_N_RANGE[0]} <= n <= {SERSIC_N_RANGE[1]}, "
                    f"but values reach [{lo:g}, {hi:g}]"
                )
    for name, lo, hi, what in (
        ("bulge_fraction", 0.0, 1.0, "the bulge's flux fraction"),
        ("knots_fraction", 0.0, 1.0, "the knots' fraction of the disk's flux"),
        ("knots", 0.0, 10000.0, "the number of knots"),
    ):
        if name in g:
            _check_range(g[name], lo, hi, what)
    if "bulge_rad_ratio" in g:
        _check_range(g["bulge_rad_ratio"], 0.0, None, "the bulge-to-disk half-light radius ratio", strict_lo=True)
    if "bulge_ellipticity" in g:
        _check_range(g["bulge_ellipticity"], 0.0, None, "the bulge's ellipticity modulus")
        if g["bulge_ellipticity"].bounds()[1] >= 1.0:
            raise ConfigError(f"galaxy.bulge_ellipticity: the modulus must be < 1, but values reach {g['bulge_ellipticity'].bounds()[1]:g}")
    for name in ("bulge_dx", "bulge_dy"):
        if name in g:
            a, b = g[name].bounds()
            if max(abs(a), abs(b)) > structure.stamp_size / 4:
                raise ConfigError(f"galaxy.{name}: the bulge offset must stay within stamp_size/4 pixels, but values reach {max(abs(a), abs(b)):g}")
    gmax = [max(abs(x) for x in d.bounds()) for d in shear.values()]
    if gmax and math.hypot(*gmax, 0.0) >= 1.0:
        raise ConfigError("shear: the reduced shear |g| must stay < 1")
    if "sigma" in noise.params:
        _check_range(noise.params["sigma"], 0.0, None, "the noise sigma")
    if "read_noise" in noise.params:
        _check_range(noise.params["read_noise"], 0.0, None, "the read noise")

    # PSF: validated by the PSF module on both ends of every distribution.
    from megalut_cli.sim import psf as psf_mod

    for end in (0, 1):
        spec = {k: (v.bounds()[end] if isinstance(v, Distribution) else v) for k, v in psf.items()}
        psf_mod.validate_psf_config(spec)
    varies = bool(psf_mod.psf_varies({k: (v.bounds()[0] if isinstance(v, Distribution) else v) for k, v in psf.items()}))
    if varies and field_d is None:
        field_d = {
            "x": parse_distribution({"type": "uniform", "min": 0.0, "max": 1.0}, "field.x"),
            "y": parse_distribution({"type": "uniform", "min": 0.0, "max": 1.0}, "field.y"),
        }

    return SimConfig(
        path=path,
        sha256=sha256,
        raw=json.loads(json.dumps(raw, default=str)),
        overrides=overrides,
        structure=structure,
        shear=shear,
        field=field_d,
        psf=psf,
        psf_varies=varies,
        galaxy=galaxy,
        noise=noise,
        instrument=instrument,
        catalog_rows=n_rows,
        catalog_path=cat_path,
        gsparams=gsparams,
    )
