"""The ``[noise]`` table of a simulation config: noise types, correlated-noise sources and
noise levels measured on data (``{type = "measured"}``)."""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from megalut_cli.errors import ConfigError, InputError
from megalut_cli.schema import check_choice, check_float, check_int, check_table, resolve_beside
from megalut_cli.sim.distributions import Distribution, parse_distribution, parse_distributions

log = logging.getLogger(__name__)


NOISE_TYPES = ("gaussian", "ccd", "correlated", "none")
_NOISE_KEYS = {"type", "sigma", "sky_mag", "read_noise", "override_sigma"}
#: Keys of correlated noise (noise.type = "correlated").
_CORRELATED_KEYS = {"sigma", "image", "correlation", "hdu", "pixel_scale"}
_NOISE_KEYS |= _CORRELATED_KEYS
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


def need_instrument(instrument: Mapping[str, float], keys: Sequence[str], why: str) -> None:
    for k in keys:
        if k not in instrument:
            raise ConfigError(f"instrument.{k}: missing (needed by {why})")


_MEASURED_KEYS = {"type", "path", "column", "statistic", "select", "scale"}
MEASURED_STATISTICS = ("median", "mean")


def is_measured(value: Any) -> bool:
    """Whether a parameter value is a ``{type = "measured", ...}`` table."""
    return isinstance(value, Mapping) and value.get("type") == "measured"


def measured_value(value: Mapping[str, Any], key: str, config_path: str) -> float:
    """A value measured on data: ``statistic`` (median) of ``column`` (skymad) of the
    catalog ``path`` (FITS, or text with ``# name`` lines), over the rows passing
    ``select`` with a finite value, times ``scale`` (1)."""
    from megalut_cli.catalog import read_any_catalog
    from megalut_cli.expr import check_expression, columns_used, evaluate_rows

    unknown = sorted(set(value) - _MEASURED_KEYS)
    if unknown:
        raise ConfigError(f"{key}.{unknown[0]}: unknown key (allowed: {', '.join(sorted(_MEASURED_KEYS - {'type'}))})")
    path = resolve_beside(value.get("path"), f"{key}.path", config_path)
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


def parse_noise(raw: Mapping[str, Any], instrument: Mapping[str, float], config_path: str = "<config>") -> NoiseSpec:
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
        params = parse_distributions(t, "noise", ["sigma"])
    elif kind == "gaussian":
        if "sigma" not in t:
            raise ConfigError("noise.sigma: missing (standard deviation in ADU)")
        params = parse_distributions(t, "noise", ["sigma"])
    elif kind == "ccd":
        if "sky_mag" not in t:
            raise ConfigError("noise.sky_mag: missing (sky brightness in mag per arcsec^2)")
        need_instrument(instrument, ("pixel_scale", "exptime", "gain", "zeropoint"), "noise type 'ccd'")
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
    path = resolve_beside(t[kind], f"noise.{kind}", config_path)
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
