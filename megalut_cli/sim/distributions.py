"""Distributions of simulation parameters, parsed from TOML values.

A parameter is a plain number (a constant) or an inline table with a ``type``::

    rad = 3.0                                                    # constant
    rad = {type = "uniform", min = 2.0, max = 8.0}
    g1 = {type = "normal", mean = 0.0, sigma = 0.05, min = -0.1, max = 0.1}
    ellipticity = {type = "rayleigh", mode = 0.2, min = 0.0, max = 0.6}
    sersicn = {type = "grid", min = 1.0, max = 4.0, step = 0.1}   # or values = [...]
    g1 = {type = "sequence", values = [0.03, -0.03, 0.0, 0.0]}  # draw k takes values[k % 4]
    rad = {type = "catalog", column = "hlr", element = 0, scale = 10.0}

``min``/``max`` of ``normal`` and ``rayleigh`` truncate the distribution (no sample falls
outside, the shape inside is unchanged; sampled exactly by inverse CDF, as the paper's
"clipped" distributions). ``sequence`` takes its values in order, not at random: draw k
(case k at the case level, galaxy group k at the realization level) gets ``values[k % len]``,
for designed shears. ``catalog`` parameters sample rows of the ``[catalog]`` table;
all ``catalog`` parameters drawn at the same level share one row (joint sampling, as the
paper does with GEMS) unless ``joint = false``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from megalut_cli.errors import ConfigError
from megalut_cli.schema import check_bool, check_float, check_int

DIST_TYPES = ("constant", "uniform", "normal", "rayleigh", "grid", "sequence", "catalog")


@dataclass(frozen=True)
class Distribution:
    """Base class: ``sample(rng, n)`` returns ``n`` float64 values."""

    key: str

    def sample(
        self, rng: np.random.Generator, n: int, rows: np.ndarray | None = None
    ) -> np.ndarray:
        raise NotImplementedError

    def bounds(self) -> tuple[float, float]:
        """Smallest and largest value a sample can take."""
        raise NotImplementedError

    @property
    def is_constant(self) -> bool:
        lo, hi = self.bounds()
        return lo == hi


@dataclass(frozen=True)
class Constant(Distribution):
    value: float = 0.0

    def sample(
        self, rng: np.random.Generator, n: int, rows: np.ndarray | None = None
    ) -> np.ndarray:
        return np.full(n, self.value)

    def bounds(self) -> tuple[float, float]:
        return self.value, self.value


@dataclass(frozen=True)
class Uniform(Distribution):
    min: float = 0.0
    max: float = 1.0

    def sample(
        self, rng: np.random.Generator, n: int, rows: np.ndarray | None = None
    ) -> np.ndarray:
        return rng.uniform(self.min, self.max, n)

    def bounds(self) -> tuple[float, float]:
        return self.min, self.max


@dataclass(frozen=True)
class Normal(Distribution):
    """Normal distribution, truncated to [min, max] (infinite bounds when not given)."""

    mean: float = 0.0
    sigma: float = 1.0
    min: float = -math.inf
    max: float = math.inf

    def sample(
        self, rng: np.random.Generator, n: int, rows: np.ndarray | None = None
    ) -> np.ndarray:
        if self.sigma == 0.0:
            return np.full(n, self.mean)
        if math.isinf(self.min) and math.isinf(self.max):
            return rng.normal(self.mean, self.sigma, n)
        a = (self.min - self.mean) / self.sigma
        b = (self.max - self.mean) / self.sigma
        u = rng.random(n)
        from scipy import stats  # only here: importing scipy.stats costs every worker ~0.5 s

        out = stats.truncnorm.ppf(u, a, b, loc=self.mean, scale=self.sigma)
        return np.clip(out, self.min, self.max)

    def bounds(self) -> tuple[float, float]:
        if self.sigma == 0.0:
            return self.mean, self.mean
        return self.min, self.max


@dataclass(frozen=True)
class Rayleigh(Distribution):
    """Rayleigh distribution of mode ``mode``, truncated to [min, max]."""

    mode: float = 1.0
    min: float = 0.0
    max: float = math.inf

    def sample(
        self, rng: np.random.Generator, n: int, rows: np.ndarray | None = None
    ) -> np.ndarray:
        s2 = 2.0 * self.mode**2
        q_lo = math.exp(-(self.min**2) / s2)  # survival function at min
        q_hi = math.exp(-(self.max**2) / s2) if math.isfinite(self.max) else 0.0
        q = q_lo - rng.random(n) * (q_lo - q_hi)
        q = np.maximum(q, np.finfo(float).tiny)
        return np.clip(np.sqrt(-s2 * np.log(q)), self.min, self.max)

    def bounds(self) -> tuple[float, float]:
        return self.min, self.max


@dataclass(frozen=True)
class Grid(Distribution):
    """Uniform choice among a finite set of values."""

    values: tuple[float, ...] = (0.0,)

    def sample(
        self, rng: np.random.Generator, n: int, rows: np.ndarray | None = None
    ) -> np.ndarray:
        vals = np.asarray(self.values, dtype=float)
        return vals[rng.integers(0, len(vals), n)]

    def bounds(self) -> tuple[float, float]:
        return min(self.values), max(self.values)


@dataclass(frozen=True)
class InOrder(Distribution):
    """The values in order, draw ``k`` taking ``values[k % len(values)]`` (no random number)."""

    values: tuple[float, ...] = (0.0,)

    def sample(
        self, rng: np.random.Generator, n: int, rows: np.ndarray | None = None
    ) -> np.ndarray:
        return self.at(np.arange(n))

    def at(self, positions: np.ndarray) -> np.ndarray:
        """The values of the draws at ``positions`` (their places in the run)."""
        vals = np.asarray(self.values, dtype=float)
        return vals[np.asarray(positions, dtype=np.int64) % len(vals)]

    def bounds(self) -> tuple[float, float]:
        return min(self.values), max(self.values)


@dataclass(frozen=True)
class CatalogColumn(Distribution):
    """Values of a column of the input catalog (after selection and unit scaling).

    With ``joint`` the caller passes the shared ``rows``; otherwise rows are drawn here.
    """

    column: str = ""
    element: int | None = None
    scale: float = 1.0
    offset: float = 0.0
    joint: bool = True
    data: np.ndarray = field(default_factory=lambda: np.zeros(0), compare=False, repr=False)

    def sample(
        self, rng: np.random.Generator, n: int, rows: np.ndarray | None = None
    ) -> np.ndarray:
        if rows is None or not self.joint:
            rows = rng.integers(0, len(self.data), n)
        return self.data[rows]

    def bounds(self) -> tuple[float, float]:
        if len(self.data) == 0:
            return 0.0, 0.0
        return float(np.min(self.data)), float(np.max(self.data))

    @property
    def is_constant(self) -> bool:
        return False

    def with_data(self, data: np.ndarray) -> CatalogColumn:
        return CatalogColumn(
            key=self.key,
            column=self.column,
            element=self.element,
            scale=self.scale,
            offset=self.offset,
            joint=self.joint,
            data=np.ascontiguousarray(data, dtype=float),
        )


_ALLOWED = {
    "constant": {"value"},
    "uniform": {"min", "max"},
    "normal": {"mean", "sigma", "min", "max"},
    "rayleigh": {"mode", "min", "max"},
    "grid": {"values", "min", "max", "step", "n"},
    "sequence": {"values"},
    "catalog": {"column", "element", "scale", "offset", "joint"},
}


def is_distribution_table(value: Any) -> bool:
    """True for an inline table that describes a distribution (has a ``type`` key)."""
    return isinstance(value, Mapping) and "type" in value


def parse_distribution(value: Any, key: str) -> Distribution:
    """Parse a TOML value (number or inline table) into a :class:`Distribution`.

    Errors are :class:`ConfigError` naming ``key`` (e.g. ``galaxy.rad.max``).
    """
    if not isinstance(value, Mapping):
        return Constant(key, check_float(value, key))
    kind = value.get("type")
    if kind is None:
        raise ConfigError(f"{key}: a distribution table needs a 'type' ({', '.join(DIST_TYPES)})")
    if kind not in _ALLOWED:
        raise ConfigError(
            f"{key}.type: unknown distribution {kind!r} (expected one of {', '.join(DIST_TYPES)})"
        )
    unknown = sorted(set(value) - _ALLOWED[kind] - {"type"})
    if unknown:
        raise ConfigError(
            f"{key}.{unknown[0]}: unknown key for a {kind} distribution "
            f"(allowed: {', '.join(sorted(_ALLOWED[kind]))})"
        )

    def num(name: str, default: float | None = None) -> float:
        if name not in value:
            if default is None:
                raise ConfigError(f"{key}.{name}: missing (needed by a {kind} distribution)")
            return default
        return check_float(value[name], f"{key}.{name}")

    if kind == "constant":
        return Constant(key, num("value"))
    if kind == "uniform":
        lo, hi = num("min"), num("max")
        if not lo <= hi:
            raise ConfigError(f"{key}: uniform needs min <= max, got min={lo}, max={hi}")
        return Uniform(key, lo, hi)
    if kind == "normal":
        mean, sigma = num("mean"), num("sigma")
        lo, hi = num("min", -math.inf), num("max", math.inf)
        if sigma < 0:
            raise ConfigError(f"{key}.sigma: must be >= 0, got {sigma}")
        if not lo < hi:
            raise ConfigError(f"{key}: normal needs min < max, got min={lo}, max={hi}")
        if sigma > 0 and (lo - mean) / sigma > 30 or sigma > 0 and (mean - hi) / sigma > 30:
            raise ConfigError(f"{key}: the range [{lo}, {hi}] is more than 30 sigma from the mean")
        if sigma == 0 and not lo <= mean <= hi:
            raise ConfigError(f"{key}: mean {mean} outside [min, max] with sigma = 0")
        return Normal(key, mean, sigma, lo, hi)
    if kind == "rayleigh":
        mode = num("mode")
        lo, hi = num("min", 0.0), num("max", math.inf)
        if mode <= 0:
            raise ConfigError(f"{key}.mode: must be > 0, got {mode}")
        if lo < 0 or not lo < hi:
            raise ConfigError(f"{key}: rayleigh needs 0 <= min < max, got min={lo}, max={hi}")
        if lo**2 / (2 * mode**2) > 700:
            raise ConfigError(
                f"{key}.min: {lo} is too far in the tail of a Rayleigh of mode {mode}"
            )
        return Rayleigh(key, mode, lo, hi)
    if kind == "grid":
        return _parse_grid(value, key, num)
    if kind == "sequence":
        vals = value.get("values")
        if not isinstance(vals, list) or not vals:
            raise ConfigError(f"{key}.values: expected a non-empty list of numbers")
        return InOrder(key, tuple(check_float(v, f"{key}.values") for v in vals))
    return _parse_catalog(value, key)


def _parse_grid(value: Mapping[str, Any], key: str, num: Any) -> Grid:
    if "values" in value:
        if set(value) & {"min", "max", "step", "n"}:
            raise ConfigError(f"{key}: give either 'values' or 'min', 'max' and 'step' (or 'n')")
        vals = value["values"]
        if not isinstance(vals, list) or not vals:
            raise ConfigError(f"{key}.values: expected a non-empty list of numbers")
        return Grid(key, tuple(check_float(v, f"{key}.values") for v in vals))
    lo, hi = num("min"), num("max")
    if not lo <= hi:
        raise ConfigError(f"{key}: grid needs min <= max, got min={lo}, max={hi}")
    if ("step" in value) == ("n" in value):
        raise ConfigError(f"{key}: a grid needs 'values', or 'min', 'max' and one of 'step' or 'n'")
    if "step" in value:
        step = num("step")
        if step <= 0:
            raise ConfigError(f"{key}.step: must be > 0, got {step}")
        count = int(math.floor((hi - lo) / step + 1e-9)) + 1
        if count > 1_000_000:
            raise ConfigError(f"{key}.step: too many grid values ({count})")
        vals = np.round(lo + step * np.arange(count), 12)
    else:
        n = check_int(value["n"], f"{key}.n", 1)
        vals = np.linspace(lo, hi, n)
    return Grid(key, tuple(float(v) for v in vals))


def _parse_catalog(value: Mapping[str, Any], key: str) -> CatalogColumn:
    column = value.get("column")
    if not isinstance(column, str) or not column:
        raise ConfigError(f"{key}.column: missing (the [catalog] column to sample)")
    element = value.get("element")
    if element is not None:
        element = check_int(element, f"{key}.element", 0)
    scale = check_float(value.get("scale", 1.0), f"{key}.scale")
    offset = check_float(value.get("offset", 0.0), f"{key}.offset")
    joint = check_bool(value.get("joint", True), f"{key}.joint")
    return CatalogColumn(key, column, element, scale, offset, joint)


def parse_distributions(
    table: Mapping[str, Any], prefix: str, keys: Sequence[str]
) -> dict[str, Distribution]:
    """The distributions of those ``keys`` that ``table`` has (keys named ``prefix.key``)."""
    return {k: parse_distribution(table[k], f"{prefix}.{k}") for k in keys if k in table}


def check_bounds(
    d: Distribution, lo: float | None, hi: float | None, what: str, strict_lo: bool = False
) -> None:
    """Every value of ``d`` lies in ``[lo, hi]`` (``(lo, hi]`` with ``strict_lo``); errors say
    ``what`` the values are."""
    a, b = d.bounds()
    if lo is not None and (a <= lo if strict_lo else a < lo):
        rel = ">" if strict_lo else ">="
        raise ConfigError(f"{d.key}: {what} must be {rel} {lo}, but values reach {a:g}")
    if hi is not None and b > hi:
        raise ConfigError(f"{d.key}: {what} must be <= {hi}, but values reach {b:g}")


def sample_level(
    dists: Mapping[str, Distribution],
    rng: np.random.Generator,
    n: int,
    n_catalog_rows: int,
    positions: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Draw ``n`` values of each distribution (in the mapping's order).

    Joint catalog parameters share one row index per draw (drawn first, only if any).
    ``positions``: the draws' places in the run (e.g. ``[case]``), which a ``sequence``
    follows (default ``0 .. n-1``); the other distributions draw from ``rng``.
    """
    rows = None
    if any(isinstance(d, CatalogColumn) and d.joint for d in dists.values()):
        rows = rng.integers(0, n_catalog_rows, n)
    return {name: draw(d, rng, n, rows, positions) for name, d in dists.items()}


def draw(
    d: Distribution,
    rng: np.random.Generator,
    n: int,
    rows: np.ndarray | None = None,
    positions: np.ndarray | None = None,
) -> np.ndarray:
    """``n`` values of ``d``: a ``sequence`` follows ``positions`` (the draws' places in the
    run, default ``0 .. n-1``), the others draw from ``rng`` (``rows``: joint catalog rows)."""
    if isinstance(d, InOrder):
        return d.at(np.arange(n) if positions is None else np.asarray(positions))
    return d.sample(rng, n, rows)


def short_text(value: Any) -> str:
    """A config value in a few characters, as one-line summaries write it: ``U(min, max)``
    for a uniform distribution, the value of a constant, the type of another distribution
    (``?`` without one), a plain value as it is."""
    if isinstance(value, Mapping):
        t = value.get("type", "")
        if t == "uniform":
            return f"U({value.get('min')}, {value.get('max')})"
        if t == "constant":
            return str(value.get("value"))
        return t or "?"
    return str(value)
