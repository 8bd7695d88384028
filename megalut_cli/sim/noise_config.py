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
from megalut_cli.expr import check_expression, columns_used, evaluate_rows
from megalut_cli.schema import (
    OneOf,
    Option,
    Required,
    check_choice,
    check_float,
    check_params,
    check_table,
    resolve_beside,
)
from megalut_cli.sim.distributions import Distribution, parse_distribution, parse_distributions
from megalut_cli.sim.noise_source import CORRELATED_SOURCES, CorrelationSource

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class NoiseType:
    """One ``noise.type``: what it is (docs), its keys besides ``type`` and
    ``override_sigma`` and their rules (checked by :func:`~megalut_cli.schema.check_params`)."""

    name: str
    help: str
    options: tuple[Option, ...] = ()
    rules: tuple[Required | OneOf, ...] = ()


NOISE_TYPES = ("gaussian", "ccd", "correlated", "none")
#: The keys of ``[noise]`` every type takes.
NOISE_OPTIONS = (
    Option("type", "choice", None, "the noise model", choices=NOISE_TYPES, default_text="required"),
    Option(
        "override_sigma",
        "float",
        None,
        "replaces the noise above by Gaussian noise of this sigma (low-noise pretraining sets: "
        "`megalut simulate tp.toml ... noise.override_sigma=0.1`)",
        default_text="—",
        allowed_text=">= 0",
    ),
)
OVERRIDE_SIGMA = NOISE_OPTIONS[1]
#: ``noise.sigma`` of Gaussian noise, as docs write a level measured on data.
_MEASURED_SIGMA = (
    '`{type = "measured", path = "features.fits", column = "skymad", statistic = "median", '
    'select = "...", scale = 1.0}`'
)
#: The noise types by name, with their keys.
NOISE_KINDS: dict[str, NoiseType] = {
    t.name: t
    for t in (
        NoiseType(
            "gaussian",
            "stationary Gaussian noise, the paper's background-limited toy model",
            (
                Option(
                    "sigma",
                    "dist",
                    None,
                    "standard deviation in ADU, drawn per case; or measured on data: "
                    f"{_MEASURED_SIGMA} (only `path` required; FITS or `# name` text catalogs; see "
                    "`docs/great3.md`)",
                    default_text="required",
                    allowed_text="*dist*, >= 0",
                ),
            ),
            (Required("sigma", "standard deviation in ADU"),),
        ),
        NoiseType(
            "ccd",
            "GalSim `CCDNoise`: Poisson noise of the source and the (subtracted) sky, read noise "
            "(below)",
            (
                Option(
                    "sky_mag",
                    "dist",
                    None,
                    "sky brightness in mag/arcsec², drawn per case",
                    default_text="required",
                ),
                Option(
                    "read_noise",
                    "dist",
                    0.0,
                    "read noise in electrons, drawn per case",
                    default_text="0",
                    allowed_text="*dist*, >= 0",
                ),
            ),
            (Required("sky_mag", "sky brightness in mag per arcsec^2"),),
        ),
        NoiseType(
            "correlated",
            "stationary Gaussian noise correlated as in the data, GalSim `CorrelatedNoise` (below)",
            (
                Option(
                    "image",
                    "path",
                    None,
                    "a FITS noise image (e.g. a blank-sky cutout of the data; its mean is "
                    "subtracted), read with GalSim's `CorrelatedNoise(image)`",
                    default_text="—",
                ),
                Option(
                    "correlation",
                    "path",
                    None,
                    "a FITS image of a correlation function centred on its central pixel, read "
                    "with GalSim's `getCOSMOSNoise` (e.g. "
                    "`examples/data/cosmos/acs_I_unrot_sci_20_cf.fits`, the HST/ACS COSMOS F814W "
                    "coadds)",
                    default_text="—",
                ),
                Option(
                    "hdu", "int", None, "HDU of `image`", minimum=0, default_text="the primary HDU"
                ),
                Option(
                    "pixel_scale",
                    "float",
                    1.0,
                    "the source's pixel size in simulation pixels (0.3 for COSMOS's 0.03″ in 0.1″ "
                    "pixels)",
                    allowed_text="> 0",
                ),
                Option(
                    "sigma",
                    "dist",
                    None,
                    "the **pixel standard deviation** in ADU, drawn per case",
                    default_text="the image's own (for `image`); required for `correlation`",
                    allowed_text="*dist*, >= 0",
                ),
            ),
            (
                OneOf(
                    CORRELATED_SOURCES,
                    "correlated noise needs exactly one of noise.image (a FITS noise image, e.g. a "
                    "blank-sky cutout) or noise.correlation (a FITS correlation-function image, "
                    "e.g. GalSim's acs_I_unrot_sci_20_cf.fits) (got {got})",
                ),
            ),
        ),
        NoiseType("none", "noiseless stamps"),
    )
}


@dataclass(frozen=True)
class NoiseSpec:
    type: str
    params: dict[str, Distribution]  # sigma | sky_mag, read_noise
    override_sigma: float | None = None
    #: type "correlated": where the correlation function comes from
    source: CorrelationSource | None = None


def noise_keys() -> set[str]:
    """Every key of ``[noise]``."""
    names = ({o.name for o in t.options} for t in NOISE_KINDS.values())
    return {o.name for o in NOISE_OPTIONS}.union(*names)


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
    from megalut_cli.catalog import read_any_catalog  # fitsio: not needed for --help

    unknown = sorted(set(value) - _MEASURED_KEYS)
    if unknown:
        raise ConfigError(
            f"{key}.{unknown[0]}: unknown key (allowed: "
            f"{', '.join(sorted(_MEASURED_KEYS - {'type'}))})"
        )
    path = resolve_beside(value.get("path"), f"{key}.path", config_path)
    column = value.get("column", "skymad")
    if not isinstance(column, str) or not column:
        raise ConfigError(f"{key}.column: expected a column name, got {column!r}")
    statistic = check_choice(
        value.get("statistic", "median"), f"{key}.statistic", MEASURED_STATISTICS
    )
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
        raise ConfigError(
            f"{key}: no row of {path} with a finite {column}"
            + (f" passing {select!r}" if select else "")
        )
    out = float((np.median if statistic == "median" else np.mean)(v[mask])) * scale
    if not (math.isfinite(out) and out >= 0):
        raise ConfigError(f"{key}: the measured value {out!r} is not a valid noise level")
    log.info(
        "%s = %g: %s of %s over %d row(s) of %s", key, out, statistic, column, int(mask.sum()), path
    )
    return out


def parse_noise(
    raw: Mapping[str, Any], instrument: Mapping[str, float], config_path: str = "<config>"
) -> NoiseSpec:
    """The ``[noise]`` table of the config ``raw``: its type's keys checked, then read."""
    t = check_table(raw.get("noise"), "noise", noise_keys(), required=True)
    if is_measured(t.get("sigma")):
        t["sigma"] = measured_value(t["sigma"], "noise.sigma", config_path)
    kind = check_choice(t.get("type"), "noise.type", NOISE_TYPES)
    given = {k: v for k, v in t.items() if k != "type"}
    spec = NOISE_KINDS[kind]
    values = check_params(
        given,
        "noise",
        (*spec.options, OVERRIDE_SIGMA),
        spec.rules,
        lambda key: f"not a key of noise type {kind!r}",
    )
    source = None
    if kind == "correlated":
        source = _correlation_source(given, values, config_path)
        if "sigma" not in given:
            if source.kind == "correlation":
                raise ConfigError(
                    "noise.sigma: missing (pixel standard deviation in ADU of the correlated noise)"
                )
            from megalut_cli.sim.noise import source_variance  # numba, GalSim: not for --help

            given["sigma"] = math.sqrt(source_variance(source))
            log.info(
                "noise.sigma = %g: the pixel standard deviation of %s", given["sigma"], source.path
            )
        params = parse_distributions(given, "noise", ["sigma"])
    elif kind == "gaussian":
        params = parse_distributions(given, "noise", ["sigma"])
    elif kind == "ccd":
        need_instrument(
            instrument, ("pixel_scale", "exptime", "gain", "zeropoint"), "noise type 'ccd'"
        )
        params = {
            "sky_mag": parse_distribution(given["sky_mag"], "noise.sky_mag"),
            "read_noise": parse_distribution(values["read_noise"], "noise.read_noise"),
        }
    else:
        params = {}
    override = values["override_sigma"]
    if override is not None:
        override = float(override)
        if override < 0:
            raise ConfigError(f"noise.override_sigma: must be >= 0, got {override}")
    return NoiseSpec(kind, params, override, source)


def _correlation_source(
    given: Mapping[str, Any], values: Mapping[str, Any], config_path: str
) -> CorrelationSource:
    """The noise image or correlation-function image of ``noise.type = "correlated"``."""
    kind = next(k for k in CORRELATED_SOURCES if k in given)
    path = resolve_beside(given[kind], f"noise.{kind}", config_path)
    hdu = values["hdu"]
    scale = float(values["pixel_scale"])
    if scale <= 0:
        raise ConfigError(f"noise.pixel_scale: must be > 0, got {scale}")
    if kind == "correlation" and hdu is not None:
        raise ConfigError(
            "noise.hdu: only for noise.image (a correlation-function file is read "
            "from its first HDU)"
        )
    source = CorrelationSource(kind, str(path), hdu, scale)
    from megalut_cli.sim.noise import unit_correlated_noise  # numba, GalSim: not for --help

    try:
        unit_correlated_noise(source)  # fail now, with one line, on an unusable file
    except InputError as err:
        raise ConfigError(str(err)) from None
    return source
