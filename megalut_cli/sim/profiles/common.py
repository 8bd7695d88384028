"""What galaxy profiles share: the common keys of ``[galaxy]``, their parsing, the Sérsic
index rounding and range, and the size of bulge + disk composites.

Plain numbers and numpy (scipy when a composite is sized): nothing here draws.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from typing import Any

import numpy as np

from megalut_cli.errors import ConfigError
from megalut_cli.schema import OneOf, Option, Required
from megalut_cli.sim.distributions import (
    Distribution,
    check_bounds,
    parse_distribution,
    parse_distributions,
)
from megalut_cli.sim.noise_config import need_instrument

#: GalSim's Sersic index range.
SERSIC_N_RANGE = (0.3, 6.2)
#: The keys that set a galaxy's flux: exactly one is given.
FLUX_KEYS = ("flux", "sb", "mag")
#: The default position angle: uniform in [0, 180) degrees.
ANGLE_DEFAULT = {"type": "uniform", "min": 0.0, "max": 180.0}

SERSICN = Option(
    "sersicn",
    "dist",
    None,
    "Sérsic index (rounded to `sersicn_step`)",
    default_text="required",
    allowed_text="*dist*, GalSim range 0.3–6.2",
)
SERSICN_STEP = Option(
    "sersicn_step",
    "float",
    0.1,
    "drawn indices are rounded to multiples of this step (0: "
    "continuous), so GalSim reuses its cached Sérsic profiles (the paper grids n, Table 1 note a)",
    allowed_text=">= 0",
)
RAD = Option(
    "rad",
    "dist",
    None,
    "half-light radius in pixels",
    default_text="required",
    allowed_text="*dist*, > 0",
)
FLUX = Option("flux", "dist", None, "flux in ADU", default_text="—", allowed_text="*dist*, >= 0")
SB = Option(
    "sb",
    "dist",
    None,
    "surface brightness S (ADU/pixel²): flux F = S·π·R² (Sect. 5.1)",
    default_text="—",
    allowed_text="*dist*, >= 0",
)
MAG = Option(
    "mag",
    "dist",
    None,
    "magnitude: F = t_exp / G · 10^(−0.4 (m − Z_p)) with `[instrument]` `exptime`, "
    "`gain`, `zeropoint` (Sect. 7.1.2)",
    default_text="—",
)
ELLIPTICITY = Option(
    "ellipticity",
    "dist",
    0.0,
    "intrinsic ellipticity modulus |e| = (1 − q)/(1 + q) (GalSim reduced-shear convention)",
    default_text="0",
    allowed_text="*dist*, [0, 1)",
)
ANGLE = Option(
    "angle", "dist", ANGLE_DEFAULT, "position angle θ in degrees", default_text="uniform 0–180"
)
KNOTS = Option(
    "knots",
    "dist",
    None,
    "star-forming knots: the number of GalSim `RandomKnots` (rounded to an integer; "
    "0 = none; below)",
    default_text="none",
    allowed_text="*dist*, [0, 10000]",
)
KNOTS_FRACTION = Option(
    "knots_fraction",
    "dist",
    None,
    "the knots' fraction of the **disk's** flux (of the whole "
    "galaxy for `sersic`, `gaussian`); goes with `knots`",
    default_text="none",
    allowed_text="*dist*, [0, 1]",
)
#: The keys of a parametric galaxy (Sérsic, Gaussian), in the order of the docs.
PARAMETRIC_OPTIONS = (RAD, FLUX, SB, MAG, ELLIPTICITY, ANGLE, KNOTS, KNOTS_FRACTION)

RAD_REQUIRED = Required("rad", "half-light radius in pixels")
ONE_FLUX = OneOf(
    FLUX_KEYS,
    "give exactly one of galaxy.flux, galaxy.sb (surface brightness) or galaxy.mag (got {got})",
)


def with_help(option: Option, help: str, **changes: Any) -> Option:
    """``option`` as a profile means it (another help text, default or range)."""
    return replace(option, help=help, **changes)


def flux_mode(given: Mapping[str, Any], instrument: Mapping[str, float]) -> str:
    """Which of ``flux``, ``sb``, ``mag`` sets the flux (exactly one is given); a magnitude
    needs the instrument's zero-point, exposure time and gain."""
    mode = next(k for k in FLUX_KEYS if k in given)
    if mode == "mag":
        need_instrument(instrument, ("zeropoint", "exptime", "gain"), "galaxy.mag")
    return mode


def sersicn_step(values: Mapping[str, Any]) -> float:
    """``galaxy.sersicn_step`` (a number, checked), >= 0."""
    step = float(values["sersicn_step"])
    if step < 0:
        raise ConfigError(f"galaxy.sersicn_step: must be >= 0, got {step}")
    return step


def position_angle(values: Mapping[str, Any]) -> Distribution:
    return parse_distribution(values["angle"], "galaxy.angle")


def knot_dists(given: Mapping[str, Any]) -> dict[str, Distribution]:
    """``knots`` (number, 0 = none) and ``knots_fraction`` (of the disk's flux), if given."""
    if "knots" not in given:
        if "knots_fraction" in given:
            raise ConfigError("galaxy.knots_fraction: needs galaxy.knots (the number of knots)")
        return {}
    if "knots_fraction" not in given:
        raise ConfigError(
            "galaxy.knots_fraction: missing (fraction of the disk's flux in the knots, 0-1)"
        )
    return {k: parse_distribution(given[k], f"galaxy.{k}") for k in ("knots", "knots_fraction")}


def parametric_params(
    given: Mapping[str, Any], values: Mapping[str, Any], instrument: Mapping[str, float]
) -> tuple[str, float, dict[str, Distribution]]:
    """The flux mode, Sérsic step and first distributions (``rad``, ``sersicn`` when given,
    the flux's, ``ellipticity``: their draw order) of a parametric galaxy."""
    mode = flux_mode(given, instrument)
    step = sersicn_step(values)
    params = parse_distributions(given, "galaxy", ["rad", "sersicn", mode])
    params["ellipticity"] = parse_distribution(values["ellipticity"], "galaxy.ellipticity")
    return mode, step, params


def round_sersicn(n: np.ndarray, step: float) -> np.ndarray:
    """Round Sersic indices to multiples of ``step`` (GalSim caches profiles per index)."""
    if step <= 0:
        return np.asarray(n, dtype=float)
    return np.round(np.round(np.asarray(n) / step) * step, 10)


def check_sersic_index(params: Mapping[str, Distribution], name: str, step: float) -> None:
    """The Sérsic indices of ``params[name]``, once rounded, stay within GalSim's range."""
    lo, hi = (float(round_sersicn(np.array(v), step)) for v in params[name].bounds())
    if lo < SERSIC_N_RANGE[0] or hi > SERSIC_N_RANGE[1]:
        raise ConfigError(
            f"galaxy.{name}: GalSim supports {SERSIC_N_RANGE[0]} <= n <= {SERSIC_N_RANGE[1]}, "
            f"but values reach [{lo:g}, {hi:g}]"
        )


def check_modulus(d: Distribution, what: str) -> None:
    """An ellipticity modulus: in [0, 1)."""
    check_bounds(d, 0.0, None, what)
    b = d.bounds()[1]
    if b >= 1.0:
        raise ConfigError(f"{d.key}: the modulus must be < 1, but values reach {b:g}")


# --------------------------------------------------------------------------- composites


def sersic_b(n: np.ndarray) -> np.ndarray:
    """``b_n`` of a Sersic profile ``I ~ exp(-b_n (r/R)^(1/n))`` of half-light radius R."""
    from scipy.special import gammaincinv  # scipy: only composites need it

    return gammaincinv(2.0 * np.asarray(n, dtype=float), 0.5)


def sersic_enclosed(radius_over_hlr: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Fraction of the flux of an untruncated round Sersic profile inside ``r / R``."""
    from scipy.special import gammainc

    n = np.asarray(n, dtype=float)
    x = np.asarray(radius_over_hlr, dtype=float)
    return gammainc(2.0 * n, sersic_b(n) * np.maximum(x, 0.0) ** (1.0 / n))


def composite_hlr(
    bulge_fraction: np.ndarray,
    rad_ratio: np.ndarray,
    bulge_n: np.ndarray,
    disk_n: np.ndarray | float = 1.0,
) -> np.ndarray:
    """Half-light radius of a round disk (index ``disk_n``, half-light radius 1) plus a round
    concentric bulge (index ``bulge_n``, half-light radius ``rad_ratio``) holding the flux
    fraction ``bulge_fraction``; found by bisection (it lies between the two radii)."""
    b, r, nb, nd = np.broadcast_arrays(
        *(np.asarray(v, dtype=float) for v in (bulge_fraction, rad_ratio, bulge_n, disk_n))
    )
    lo = np.log(np.minimum(1.0, r))
    hi = np.log(np.maximum(1.0, r))
    safe_r = np.where(r > 0, r, 1.0)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        x = np.exp(mid)
        inside = b * sersic_enclosed(x / safe_r, nb) + (1.0 - b) * sersic_enclosed(x, nd)
        below = inside < 0.5
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    out = np.exp(0.5 * (lo + hi))
    return np.where(b <= 0.0, 1.0, np.where(b >= 1.0, r, out))


def q_to_ellipticity(q: np.ndarray) -> np.ndarray:
    """Ellipticity modulus ``(1 - q) / (1 + q)`` of an axis ratio ``q`` (GalSim's g)."""
    q = np.asarray(q, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):  # unused fits hold q = -1
        return (1.0 - q) / (1.0 + q)
