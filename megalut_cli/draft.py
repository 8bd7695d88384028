"""Draft a pipeline file for training networks on one's own setup (``megalut draft``).

From the features measured on a survey's own stamps (``megalut measure`` output, optionally
with a star catalog) :func:`draft_setup` derives what the data determine — the stamp size,
the PSF, the pixel noise — each with the numbers it comes from (:class:`Drafted`), and
comments on what it could not decide (:class:`Note`); :func:`render_pipeline` writes them
into the default pipeline of ``megalut run`` (its comments, sets and training kept).

How the values are drafted (all sizes in pixels):

* ``stamp_size``: the ``STAMPSZ`` card of the catalog, else the median ``box_size`` (MEDS).
* The PSF, from ``psf_adamom_*`` (of the stars, or of the catalog's rows): the HSM sigma of
  a Gaussian is its sigma, and star images sampled like the galaxies contain the pixel (a
  box of variance 1/12), so ``sigma = sqrt(s^2 - 1/12)`` for the median measured ``s``
  (0.2 % from the exact inversion at s = 1, 0.003 % at s = 3). HSM's ``rho4`` of a Gaussian
  is 2 (1.99 when drawn with a 1-px pixel at sigma 1): a median ``rho4`` more than
  :data:`RHO4_TOLERANCE` above that of the Gaussian of the same size means wings, and a
  Moffat whose pixelated image has the measured sigma and rho4 (``beta`` within
  :data:`MOFFAT_BETA`, found with GalSim) is drafted instead; otherwise a Gaussian, with a
  warning when rho4 is off. A median PSF ellipticity ``|g|`` above :data:`PSF_G_SMALL`
  shears it (``g1, g2``, corrected for the pixel's dilution). A 5–95 % spread of
  ``psf_adamom_sigma`` above :data:`PSF_SPREAD_VARIES` of its median is a PSF varying across
  the field: a warning points to ``examples/varpsf``.
* The noise: the median ``noise_weight`` (from weight maps) when the catalog has it, else
  the median ``skymad``.
* The galaxies: the fiducial ranges stay; the half-light radius range is only widened, never
  narrowed: when the data's adaptive-moment sizes (rows with ``snr >``
  :data:`SIZE_SNR_MIN`, 5–95 %) reach beyond those of the simulated galaxies drawn with the
  drafted PSF (the largest: Sérsic index at its minimum and ``rad`` at its maximum; the
  smallest: the opposite corner), the ``rad`` range is widened until they are covered.
  ``snr``, ``adamom_flux`` and ``adamom_sigma`` quantiles are reported in comments.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from megalut_cli import flags as fl
from megalut_cli.configfile import tomllib
from megalut_cli.errors import InputError
from megalut_cli.measure.features import signal_to_noise
from megalut_cli.measure.metacal_defaults import STEP_CARD
from megalut_cli.schema import Option

#: The options of ``megalut draft`` beyond its input, output and ``--overwrite``.
STARS_OPTION = Option(
    "stars",
    "path",
    None,
    "A star catalog (`megalut measure STARFIELD -o STARS --stars`): the PSF is drafted from its "
    "stars' psf_adamom_* instead of the catalog's own psf_adamom_* columns.",
    metavar="STARS.fits",
)

#: Variance of the 1-pixel box that a star image sampled like the galaxies contains.
PIXEL_VARIANCE = 1.0 / 12.0
#: ``|rho4 - rho4 of the Gaussian of the same size|`` under which the PSF is taken as Gaussian
#: (a Moffat of beta 20 is 0.025 above it, beta 8: 0.063).
RHO4_TOLERANCE = 0.03
#: The Moffat ``beta`` range searched for a PSF with wings.
MOFFAT_BETA = (1.5, 30.0)
#: Median PSF ``|g|`` above which the drafted PSF is sheared by the measured ellipticity.
PSF_G_SMALL = 0.01
#: 5–95 % spread of ``psf_adamom_sigma`` (relative to its median) above which the PSF varies.
PSF_SPREAD_VARIES = 0.05
#: Rows whose sizes enter the comparison of galaxy sizes: ``snr`` above this.
SIZE_SNR_MIN = 10.0
#: Smallest half-light radius (pixels) a widened ``rad`` range starts at.
RAD_FLOOR = 0.5
#: Quantiles (percent) reported for the data's distributions.
QUANTILES = (5.0, 50.0, 95.0)

#: The tables the draft writes, as the pipeline file names them.
STRUCTURE, PSF, NOISE, GALAXY = (
    "simulation.structure",
    "simulation.psf",
    "simulation.noise",
    "simulation.galaxy",
)


@dataclass(frozen=True)
class Drafted:
    """A value of the pipeline file set from the data: its table and key, and where it comes
    from."""

    table: str
    key: str
    value: Any
    source: str


@dataclass(frozen=True)
class Note:
    """A comment above a table of the drafted file (and a log line): what the data say that
    the draft did not decide; ``warning`` when the setup may need more than the draft."""

    table: str
    text: str
    warning: bool = False


@dataclass(frozen=True)
class Draft:
    """What :func:`draft_setup` found: the values to set, the keys of the base to remove (a
    Gaussian's ``sigma`` under a Moffat), the notes, and a one-line description."""

    values: tuple[Drafted, ...]
    notes: tuple[Note, ...]
    removed: tuple[tuple[str, str], ...] = ()
    description: str = ""
    inputs: tuple[str, ...] = field(default_factory=tuple)

    def value(self, table: str, key: str) -> Any:
        """The drafted value of ``key`` in ``table`` (KeyError if none)."""
        for v in self.values:
            if (v.table, v.key) == (table, key):
                return v.value
        raise KeyError(f"{table}.{key}")


# --------------------------------------------------------------------------- numbers


def _quantiles(x: np.ndarray) -> tuple[float, float, float]:
    q = np.percentile(x, QUANTILES)
    return float(q[0]), float(q[1]), float(q[2])


def _fmt(x: float) -> str:
    """A number as comments and TOML values write it: 4 significant digits, always a float."""
    return repr(float(f"{x:.4g}"))


def _fmt_g(x: float) -> str:
    """An ellipticity as comments write it: 4 decimals."""
    return f"{x:.4f}"


def _spread(x: np.ndarray, unit: str = "") -> str:
    lo, med, hi = _quantiles(x)
    return f"{_fmt(med)}{unit} (5-95 %: {_fmt(lo)}-{_fmt(hi)})"


def _finite(
    columns: Mapping[str, np.ndarray],
    name: str,
    keep: np.ndarray | None = None,
    positive: bool = True,
) -> np.ndarray:
    x = np.asarray(columns[name], dtype=float)
    ok = np.isfinite(x) & ((x > 0) if positive else True)
    if keep is not None:
        ok &= keep
    return x[ok]


def _flags(columns: Mapping[str, np.ndarray], n: int) -> np.ndarray:
    return (
        np.asarray(columns["flags"], dtype=np.int64)
        if "flags" in columns
        else np.zeros(n, dtype=np.int64)
    )


def _n_rows(columns: Mapping[str, np.ndarray]) -> int:
    return len(next(iter(columns.values()))) if columns else 0


# --------------------------------------------------------------------------- GalSim forward models


def _hsm(profile: Any, size: int) -> Any:
    """HSM adaptive moments of ``profile`` drawn with the pixel on a ``size`` x ``size`` stamp."""
    import galsim

    image = profile.drawImage(nx=size, ny=size, scale=1.0)
    return galsim.hsm.FindAdaptiveMom(image, strict=False)


def _image_size(sigma: float) -> int:
    return int(min(1024, max(64, 2 * math.ceil(8 * sigma))))


def gaussian_rho4(sigma: float) -> float:
    """HSM ``rho4`` of a Gaussian PSF of ``sigma`` drawn with the pixel (2 for a large one)."""
    import galsim

    return float(_hsm(galsim.Gaussian(sigma=sigma), _image_size(sigma)).moments_rho4)


def moffat_like(measured_sigma: float, rho4: float) -> tuple[float, float, float] | None:
    """``(beta, fwhm, rho4_fit)`` of the round Moffat whose image, drawn with the pixel, has
    the HSM sigma ``measured_sigma`` and the ``rho4`` measured; None when rho4 lies outside
    what a Moffat of :data:`MOFFAT_BETA` gives at that size."""
    import galsim
    from scipy.optimize import brentq

    size = _image_size(measured_sigma)

    def fitted(beta: float) -> tuple[float, float]:
        """``(fwhm, rho4)`` of the Moffat of ``beta`` whose pixelated image has the measured sigma
        (HSM sigma is close to proportional to the FWHM: a fixed point, 1e-5 in 2-4 draws)."""
        fwhm = 2.3548 * math.sqrt(max(measured_sigma**2 - PIXEL_VARIANCE, 1e-4))
        for _ in range(8):
            res = _hsm(galsim.Moffat(beta=beta, fwhm=fwhm), size)
            if abs(res.moments_sigma / measured_sigma - 1) < 1e-5:
                break
            fwhm *= measured_sigma / res.moments_sigma
        return fwhm, float(res.moments_rho4)

    def rho4_of(beta: float) -> float:
        return fitted(beta)[1]

    lo, hi = MOFFAT_BETA
    r_lo, r_hi = rho4_of(lo), rho4_of(hi)  # rho4 falls as beta grows
    if not (r_hi <= rho4 <= r_lo):
        return None
    beta = float(brentq(lambda b: rho4_of(b) - rho4, lo, hi, xtol=0.01))
    fwhm, fit_rho4 = fitted(beta)
    return beta, fwhm, fit_rho4


def _psf_profile(psf: Mapping[str, Any]) -> Any:
    import galsim

    if psf["type"] == "moffat":
        prof = galsim.Moffat(beta=psf["beta"], fwhm=psf["fwhm"])
    else:
        prof = galsim.Gaussian(sigma=psf["sigma"])
    if psf.get("g1") or psf.get("g2"):
        prof = prof.shear(g1=psf.get("g1", 0.0), g2=psf.get("g2", 0.0))
    return prof


def galaxy_moments(
    rad: float, sersicn: float, psf: Mapping[str, Any], stamp_size: int
) -> tuple[float, float]:
    """``(adamom_flux per unit flux, adamom_sigma)``: HSM of a round Sérsic galaxy (half-light
    radius ``rad``, index ``sersicn``, flux 1) convolved with ``psf`` (a ``[psf]`` table) and
    drawn with the pixel on a stamp of ``stamp_size``, as the simulation draws it; NaN if HSM
    fails."""
    import galsim

    gal = galsim.Sersic(n=sersicn, half_light_radius=rad)
    res = _hsm(galsim.Convolve(gal, _psf_profile(psf)), stamp_size)
    if res.moments_status != 0:
        return math.nan, math.nan
    return float(res.moments_amp), float(res.moments_sigma)


def _radius_for(
    size: float, sersicn: float, psf: Mapping[str, Any], stamp_size: int, lo: float, hi: float
) -> float | None:
    """The half-light radius in [lo, hi] whose galaxy has the adaptive-moment ``size``, or None."""
    from scipy.optimize import brentq

    def f(r: float) -> float:
        return galaxy_moments(r, sersicn, psf, stamp_size)[1] - size

    try:
        f_lo, f_hi = f(lo), f(hi)
    except (RuntimeError, ValueError):  # GalSim could not draw an end
        return None
    if not (math.isfinite(f_lo) and math.isfinite(f_hi)) or f_lo * f_hi > 0:
        return None
    return float(brentq(f, lo, hi, xtol=0.01))


# --------------------------------------------------------------------------- the draft


def _stamp_size(
    columns: Mapping[str, np.ndarray], header: Mapping[str, Any], where: str, notes: list[Note]
) -> Drafted | None:
    card = header.get("STAMPSZ")
    if card is not None:
        return Drafted(STRUCTURE, "stamp_size", int(card), f"the STAMPSZ card of {where}")
    if "box_size" in columns:
        box = _finite(columns, "box_size")
        if box.size:
            size = int(np.median(box))
            values = np.unique(box)
            if values.size > 1:
                notes.append(
                    Note(
                        STRUCTURE,
                        f"the MEDS box sizes vary ({', '.join(str(int(v)) for v in values[:8])}"
                        f"{', ...' if values.size > 8 else ''}): the simulation draws every stamp "
                        f"at the median, {size} px",
                        warning=True,
                    )
                )
            return Drafted(
                STRUCTURE, "stamp_size", size, f"median box_size of {box.size} rows of {where}"
            )
    return None


def _noise(columns: Mapping[str, np.ndarray], where: str, notes: list[Note]) -> Drafted | None:
    n = _n_rows(columns)
    if "noise_weight" in columns:
        w = _finite(columns, "noise_weight")
        if w.size:
            if "skymad" in columns and _finite(columns, "skymad").size:
                notes.append(
                    Note(
                        NOISE,
                        f"for comparison, skymad of {where}: {_spread(_finite(columns, 'skymad'))}",
                    )
                )
            return Drafted(
                NOISE,
                "sigma",
                float(_fmt(float(np.median(w)))),
                f"median noise_weight (from the weight maps) of {w.size} rows: {_spread(w)}",
            )
    if "skymad" in columns:
        s = _finite(columns, "skymad", positive=False)
        s = s[s >= 0]
        if s.size:
            if n and s.size < n:
                notes.append(
                    Note(NOISE, f"{n - s.size} of {n} rows have no finite skymad (BAD_SKY)")
                )
            return Drafted(
                NOISE,
                "sigma",
                float(_fmt(float(np.median(s)))),
                f"median skymad of {s.size} rows: {_spread(s)}",
            )
    return None


def _psf_rows(
    features: Mapping[str, np.ndarray],
    stars: Mapping[str, np.ndarray] | None,
    where: str,
    stars_where: str,
) -> tuple[Mapping[str, np.ndarray], np.ndarray, str] | None:
    """The catalog the PSF is drafted from, its usable rows, and how to name them."""
    if stars is not None:
        if "psf_adamom_sigma" not in stars:
            return None
        n = _n_rows(stars)
        usable = _flags(stars, n) == 0
        return stars, usable, f"stars of {stars_where}"
    if "psf_adamom_sigma" not in features:
        return None
    n = _n_rows(features)
    usable = (_flags(features, n) & fl.PSF_FAILED) == 0
    return features, usable, f"rows of {where}"


def _draft_psf(
    cat: Mapping[str, np.ndarray], usable: np.ndarray, what: str, where: str, notes: list[Note]
) -> tuple[list[Drafted], list[tuple[str, str]], dict[str, Any]]:
    """The ``[simulation.psf]`` values, the keys of the base to remove, and the PSF as a table."""
    s_all = np.asarray(cat["psf_adamom_sigma"], dtype=float)
    ok = usable & np.isfinite(s_all) & (s_all > 0)
    for name in ("psf_adamom_rho4", "psf_adamom_g1", "psf_adamom_g2"):
        if name in cat:
            ok &= np.isfinite(np.asarray(cat[name], dtype=float))
    if not ok.any():
        raise InputError(
            f"{where}: no usable PSF measurement: every one of the {len(s_all)} {what} is flagged "
            "or has no finite psf_adamom_sigma"
        )
    s = s_all[ok]
    n = int(ok.sum())
    s_med = float(np.median(s))
    one = bool(np.all(s == s[0]))
    counted = f"the one PSF of all {n} {what}" if one else f"{n} {what}"
    if s_med**2 <= PIXEL_VARIANCE * 1.5:
        raise InputError(
            f"{where}: the PSF's median psf_adamom_sigma is {_fmt(s_med)} px: smaller than the "
            "pixel allows a drafted PSF (undersampled stars); write [simulation.psf] by hand"
        )
    sigma = math.sqrt(s_med**2 - PIXEL_VARIANCE)
    measured = (
        f"psf_adamom_sigma of {counted}: {_fmt(s_med)} px"
        if one
        else f"median psf_adamom_sigma of {counted}: {_spread(s, ' px')}"
    )
    pixel = f"without the pixel, sqrt(s^2 - 1/12) of {_fmt(s_med)} px"
    lo, _, hi = _quantiles(s)
    if not one and (hi - lo) / s_med > PSF_SPREAD_VARIES:
        notes.append(
            Note(
                PSF,
                "the PSF varies across the field: psf_adamom_sigma 5-95 % spans "
                f"{_fmt(lo)}-{_fmt(hi)} px, {100 * (hi - lo) / s_med:.0f} % of its median (more "
                f"than {100 * PSF_SPREAD_VARIES:.0f} %); one PSF cannot train networks for all of "
                "it: see examples/varpsf (a PSF varying with the field position, PSF features "
                "given to the networks)",
                warning=True,
            )
        )
    values: list[Drafted] = []
    removed: list[tuple[str, str]] = []
    psf: dict[str, Any] = {"type": "gaussian", "sigma": sigma}
    rho4 = (
        float(np.median(np.asarray(cat["psf_adamom_rho4"], dtype=float)[ok]))
        if "psf_adamom_rho4" in cat
        else None
    )
    gauss_rho4 = gaussian_rho4(sigma)
    if rho4 is None:
        notes.append(
            Note(
                PSF,
                f"no psf_adamom_rho4 in {where}: the PSF's profile is not known; a Gaussian is "
                "drafted",
            )
        )
    elif abs(rho4 - gauss_rho4) <= RHO4_TOLERANCE:
        notes.append(
            Note(
                PSF,
                f"median psf_adamom_rho4 {_fmt(rho4)}, a Gaussian's of this size "
                f"{_fmt(gauss_rho4)} (within {RHO4_TOLERANCE}): Gaussian",
            )
        )
    else:
        fit = moffat_like(s_med, rho4) if rho4 > gauss_rho4 else None
        if fit is not None:
            beta, fwhm, fit_rho4 = fit
            psf = {"type": "moffat", "beta": beta, "fwhm": fwhm}
            notes.append(
                Note(
                    PSF,
                    f"median psf_adamom_rho4 {_fmt(rho4)}, a Gaussian's of this size "
                    f"{_fmt(gauss_rho4)}: the PSF has wings; a Moffat of beta {_fmt(beta)} has the "
                    f"measured sigma and rho4 ({_fmt(fit_rho4)}) when drawn with the pixel",
                    warning=True,
                )
            )
            removed.append((PSF, "sigma"))
            values += [
                Drafted(
                    PSF,
                    "type",
                    "moffat",
                    f"psf_adamom_rho4 {_fmt(rho4)} (a Gaussian: {_fmt(gauss_rho4)})",
                ),
                Drafted(
                    PSF,
                    "beta",
                    float(_fmt(beta)),
                    f"the Moffat with the median psf_adamom_rho4 {_fmt(rho4)}",
                ),
                Drafted(
                    PSF,
                    "fwhm",
                    float(_fmt(fwhm)),
                    f"the Moffat of beta {_fmt(beta)} with {measured}",
                ),
            ]
        else:
            shape = (
                "more peaked"
                if rho4 < gauss_rho4
                else "with heavier wings than a Moffat of beta >= 1.5"
            )
            notes.append(
                Note(
                    PSF,
                    f"median psf_adamom_rho4 {_fmt(rho4)}, a Gaussian's of this size "
                    f"{_fmt(gauss_rho4)}: the PSF is {shape}, which no supported profile matches; "
                    'a Gaussian of the same size is drafted (a star image, type = "stamp", '
                    "docs/config.md, would fit better)",
                    warning=True,
                )
            )
    if psf["type"] == "gaussian":
        values += [
            Drafted(PSF, "type", "gaussian", "Gaussian (see the note above)"),
            Drafted(PSF, "sigma", float(_fmt(sigma)), f"{measured}; {pixel}"),
        ]
    if "psf_adamom_g1" in cat and "psf_adamom_g2" in cat:
        g1s = np.asarray(cat["psf_adamom_g1"], dtype=float)[ok]
        g2s = np.asarray(cat["psf_adamom_g2"], dtype=float)[ok]
        g1m, g2m = float(np.median(g1s)), float(np.median(g2s))
        g = math.hypot(g1m, g2m)
        if g > PSF_G_SMALL:
            dilution = s_med**2 / (
                s_med**2 - PIXEL_VARIANCE
            )  # the round pixel dilutes the measured ellipticity
            g1, g2 = g1m * dilution, g2m * dilution
            notes.append(
                Note(
                    PSF,
                    "the PSF is elliptical: median psf_adamom_g1, g2 = "
                    f"{_fmt_g(g1m)}, {_fmt_g(g2m)} (|g| = {_fmt_g(g)} > {PSF_G_SMALL}); the "
                    "drafted PSF is sheared by them (divided by the pixel's dilution "
                    f"{_fmt(1 / dilution)})",
                    warning=not one,
                )
            )
            values += [
                Drafted(PSF, "g1", float(_fmt(g1)), f"median psf_adamom_g1 {_spread(g1s)}"),
                Drafted(PSF, "g2", float(_fmt(g2)), f"median psf_adamom_g2 {_spread(g2s)}"),
            ]
            psf.update(g1=g1, g2=g2)
        else:
            notes.append(
                Note(
                    PSF,
                    f"the PSF is round: median psf_adamom_g1, g2 = {_fmt_g(g1m)}, {_fmt_g(g2m)} "
                    f"(|g| = {_fmt_g(g)} <= {PSF_G_SMALL})",
                )
            )
    return values, removed, psf


def _uniform(base: Mapping[str, Any], key: str) -> tuple[float, float] | None:
    d = base.get(key)
    if isinstance(d, Mapping) and d.get("type") == "uniform" and "min" in d and "max" in d:
        return float(d["min"]), float(d["max"])
    if isinstance(d, Mapping) and d.get("type") == "grid" and "min" in d and "max" in d:
        return float(d["min"]), float(d["max"])
    return None


def _draft_galaxies(
    features: Mapping[str, np.ndarray],
    where: str,
    base_galaxy: Mapping[str, Any],
    psf: Mapping[str, Any],
    stamp_size: int,
    noise_sigma: float,
    gain: Any,
    notes: list[Note],
) -> list[Drafted]:
    """Report the data's galaxy distributions; widen the ``rad`` and ``sb`` ranges where the
    data's sizes and S/N reach beyond those of the simulated galaxies (never narrow them)."""
    n = _n_rows(features)
    good = _flags(features, n) == 0
    reported = []
    for name, unit in (("adamom_sigma", " px"), ("snr", ""), ("adamom_flux", " ADU")):
        if name in features:
            x = _finite(features, name, good)
            if x.size:
                reported.append(f"{name} {_spread(x, unit)}")
    if reported:
        notes.append(
            Note(
                GALAXY,
                f"the data ({int(good.sum())} unflagged rows of {where}): " + "; ".join(reported),
            )
        )
    rad, sersicn, sb = (
        _uniform(base_galaxy, "rad"),
        _uniform(base_galaxy, "sersicn"),
        _uniform(base_galaxy, "sb"),
    )
    if (
        rad is None
        or sersicn is None
        or sb is None
        or "adamom_sigma" not in features
        or "snr" not in features
    ):
        notes.append(
            Note(GALAXY, "the galaxy ranges are the fiducial ones (not compared with the data)")
        )
        return []
    snr = np.asarray(features["snr"], dtype=float)
    keep = good & np.isfinite(snr) & (snr > SIZE_SNR_MIN)
    sizes = _finite(features, "adamom_sigma", keep)
    snrs = _finite(features, "snr", good)
    if sizes.size < 20:
        notes.append(
            Note(
                GALAXY,
                f"the galaxy ranges are the fiducial ones: only {sizes.size} rows with snr > "
                f"{SIZE_SNR_MIN:g} to compare sizes with",
            )
        )
        return []
    (r_min, r_max), (n_min, n_max), (sb_min, sb_max) = rad, sersicn, sb
    ends = (n_min, n_max)
    drafted: list[Drafted] = []
    said: list[str] = []

    # Sizes: the largest simulated galaxies have the largest rad and the smallest Sersic index, the
    # smallest ones the opposite (a concentrated profile has the smaller adaptive-moment size).
    q_lo, _, q_hi = _quantiles(sizes)
    sim_lo = galaxy_moments(r_min, n_max, psf, stamp_size)[1]
    sim_hi = galaxy_moments(r_max, n_min, psf, stamp_size)[1]
    said.append(
        f"adamom_sigma of the {sizes.size} rows with snr > {SIZE_SNR_MIN:g}: 5-95 % "
        f"{_fmt(q_lo)}-{_fmt(q_hi)} px; the simulated galaxies, drawn with the drafted PSF on "
        f"{stamp_size}-px stamps, span {_fmt(sim_lo)} px (rad {_fmt(r_min)}, sersicn "
        f"{_fmt(n_max)}) to {_fmt(sim_hi)} px (rad {_fmt(r_max)}, sersicn {_fmt(n_min)})"
    )
    new_min, new_max = r_min, r_max
    if math.isfinite(sim_hi) and q_hi > sim_hi:
        hi = max(4 * r_max, stamp_size / 2)
        found = _radius_for(q_hi, n_min, psf, stamp_size, r_max, hi)
        new_max = math.ceil(10 * found) / 10 if found is not None else hi
        said.append(
            f"rad max raised to {_fmt(new_max)}: a sersicn {_fmt(n_min)} galaxy of that rad has "
            "the data's 95 % size"
            + ("" if found is not None else " (not reached: the largest tried)")
        )
    if math.isfinite(sim_lo) and q_lo < sim_lo:
        found = _radius_for(q_lo, n_max, psf, stamp_size, RAD_FLOOR, r_min)
        new_min = max(RAD_FLOOR, math.floor(10 * found) / 10) if found is not None else RAD_FLOOR
        said.append(
            f"rad min lowered to {_fmt(new_min)}: a sersicn {_fmt(n_max)} galaxy of that rad has "
            "the data's 5 % size"
            + ("" if found is not None else f" (not reached: the smallest allowed, {RAD_FLOOR} px)")
        )
    if (new_min, new_max) != (r_min, r_max):
        drafted.append(
            Drafted(
                GALAXY,
                "rad",
                {"type": "uniform", "min": float(_fmt(new_min)), "max": float(_fmt(new_max))},
                f"the fiducial {_fmt(r_min)}-{_fmt(r_max)} px widened to the data's sizes "
                "(see above)",
            )
        )

    # S/N (Eq. 10, the drafted noise): linear in sb, so the ends scale exactly.
    def snr_of(sb_value: float, r: float, sersic: float) -> float:
        amp, sigma = galaxy_moments(r, sersic, psf, stamp_size)
        return float(signal_to_noise(sb_value * math.pi * r**2 * amp, sigma, noise_sigma))

    if gain is not None:
        said.append(
            "the sb range is not compared with the data's snr, measured with a gain (Eq. 8)"
        )
    elif snrs.size >= 20 and noise_sigma > 0:
        s_lo, _, s_hi = _quantiles(snrs)
        snr_lo = min(snr_of(sb_min, new_min, x) for x in ends)
        snr_hi = max(snr_of(sb_max, new_max, x) for x in ends)
        said.append(
            f"snr of the {snrs.size} unflagged rows: 5-95 % {_fmt(s_lo)}-{_fmt(s_hi)}; the "
            f"simulated galaxies (Eq. 10, noise sigma {_fmt(noise_sigma)}) span {_fmt(snr_lo)} "
            f"(sb {_fmt(sb_min)}, rad {_fmt(new_min)}) to {_fmt(snr_hi)} (sb {_fmt(sb_max)}, rad "
            f"{_fmt(new_max)})"
        )
        new_sb = [sb_min, sb_max]
        if math.isfinite(snr_hi) and s_hi > snr_hi:
            new_sb[1] = math.ceil(10 * sb_max * s_hi / snr_hi) / 10
            said.append(
                f"sb max raised to {_fmt(new_sb[1])}: the brightest simulated galaxy then has the "
                "data's 95 % snr (snr is proportional to sb)"
            )
        if math.isfinite(snr_lo) and 0 < s_lo < snr_lo:
            new_sb[0] = max(0.1, math.floor(10 * sb_min * s_lo / snr_lo) / 10)
            said.append(
                f"sb min lowered to {_fmt(new_sb[0])}: the faintest simulated galaxy then has the "
                "data's 5 % snr"
            )
        if new_sb != [sb_min, sb_max]:
            drafted.append(
                Drafted(
                    GALAXY,
                    "sb",
                    {
                        "type": "uniform",
                        "min": float(_fmt(new_sb[0])),
                        "max": float(_fmt(new_sb[1])),
                    },
                    f"the fiducial {_fmt(sb_min)}-{_fmt(sb_max)} widened to the data's snr "
                    "(see above)",
                )
            )
    if drafted:
        text = (
            "the fiducial galaxy ranges stay (not fitted to the data), except "
            + " and ".join(d.key for d in drafted)
            + ", widened to cover the data: "
            + "; ".join(said)
        )
    else:
        text = (
            "the fiducial galaxy ranges stay (not fitted to the data); they cover it: "
            + "; ".join(said)
        )
    notes.append(Note(GALAXY, text, warning=bool(drafted)))
    return drafted


def draft_setup(
    features: Mapping[str, np.ndarray],
    header: Mapping[str, Any] | None = None,
    stars: Mapping[str, np.ndarray] | None = None,
    *,
    base: Mapping[str, Any] | None = None,
    features_name: str = "features",
    stars_name: str = "stars",
) -> Draft:
    """The simulation setup of a pipeline file, drafted from the columns of a features catalog
    (``megalut measure`` output) and its ``header`` cards, with the PSF from ``stars`` (columns
    of ``megalut measure --stars``) when given. ``base``: the pipeline the ranges are taken
    from (default: the embedded default). ``features_name``, ``stars_name``: how messages and
    comments name the two catalogs. Every missing column is reported at once (InputError)."""
    header = header or {}
    if base is None:
        # the pipeline and simulation config modules, ~50 ms: not for `megalut draft --help`
        from megalut_cli.pipeline.config import default_pipeline_text

        base = tomllib.loads(default_pipeline_text())
    notes: list[Note] = []
    missing: list[
        tuple[str, str, str]
    ] = []  # (file, what, how to get it): every one reported at once
    stamp = _stamp_size(features, header, features_name, notes)
    if stamp is None:
        missing.append(
            (
                features_name,
                "STAMPSZ card or box_size column",
                "measure the stamps with `megalut measure`, which records the stamp size",
            )
        )
    noise = _noise(features, features_name, notes)
    if noise is None:
        missing.append(
            (features_name, "skymad or noise_weight", "measure the stamps with `megalut measure`")
        )
    rows = _psf_rows(features, stars, features_name, stars_name)
    if rows is None and stars is not None:
        missing.append(
            (
                stars_name,
                "psf_adamom_sigma",
                "not a star catalog: measure the star field with `megalut "
                "measure STARFIELD -o STARS --stars`",
            )
        )
    elif rows is None:
        missing.append(
            (
                features_name,
                "psf_adamom_sigma",
                "measure with --psf or --psf-model, or give --stars",
            )
        )
    if missing:
        files = dict.fromkeys(where for where, _, _ in missing)
        raise InputError(
            "; ".join(
                f"{f}: "
                + "; ".join(f"no {what}: {how}" for where, what, how in missing if where == f)
                for f in files
            )
        )
    assert stamp is not None and noise is not None and rows is not None
    cat, usable, what = rows
    psf_values, removed, psf = _draft_psf(
        cat, usable, what, stars_name if stars is not None else features_name, notes
    )
    if stars is not None and "psf_adamom_sigma" in features:
        own = _finite(features, "psf_adamom_sigma")
        if own.size:
            notes.append(
                Note(
                    PSF,
                    f"from the stars of {stars_name}; the psf_adamom_sigma of {features_name}'s "
                    f"own rows: {_spread(own, ' px')}",
                )
            )
    gain = header.get("GAIN")
    if gain is not None:
        notes.append(
            Note(
                NOISE,
                f"{features_name} was measured with a gain of {gain} e-/ADU (its snr: Eq. 8, with "
                "the galaxies' own Poisson noise); the simulated sets' snr, with this Gaussian "
                "noise, is Eq. 10: compare snr cuts with that in mind (CCD noise with a gain: "
                'docs/config.md, noise type "ccd")',
            )
        )
    base_galaxy = base.get("simulation", {}).get("galaxy", {})
    galaxy = _draft_galaxies(
        features, features_name, base_galaxy, psf, int(stamp.value), float(noise.value), gain, notes
    )
    metacal_values: list[Drafted] = []
    if header.get(STEP_CARD) is not None or "adamom_g1_noshear" in features:
        source = (
            f"{features_name} was measured in metacal mode ({STEP_CARD} card or X_noshear columns)"
        )
        metacal_values = [Drafted(TOP, "metacal", True, source)]
        if base.get("reference", {}).get("model"):
            metacal_values.append(Drafted("reference", "model", METACAL_REFERENCE, source))
        notes.append(
            Note(
                "reference",
                f"{source}: the sets are measured, the networks trained and the predictions "
                "made as metacal ones (`metacal = true`), so that the model fits the catalog; "
                "drafted networks in metacal mode are calibrated by the response, and their "
                "simulations matter for the response's precision, not for its bias",
            )
        )
    reference = METACAL_REFERENCE if metacal_values else base.get("reference", {}).get("model")
    if reference:
        notes.append(
            Note(
                "reference",
                f"the shipped model {reference!r} was trained on the fiducial setup (PSF sigma "
                "2 px, noise sigma 1, 64-px stamps): on this setup its table shows how far off it "
                "is; remove [reference] to skip it",
            )
        )
    inputs = (features_name,) if stars is None else (features_name, stars_name)
    description = f"drafted by megalut draft from {' and '.join(inputs)}"
    return Draft(
        tuple([*metacal_values, stamp, *psf_values, noise, *galaxy]),
        tuple(notes),
        tuple(removed),
        description,
        inputs,
    )


# --------------------------------------------------------------------------- rendering

#: The table of a pipeline file's top-level keys (``description``, ``metacal``).
TOP = ""
#: The reference model of a drafted metacal pipeline.
METACAL_REFERENCE = "fiducial-metacal"
_HEADER_LINE = re.compile(r"^\s*\[\s*([^\[\]]+?)\s*\]\s*(?:#.*)?$")
_KEY_LINE = re.compile(r"^\s*([A-Za-z0-9_-]+)\s*=")
#: Width of the drafted comments.
WIDTH = 100


def toml_value(value: Any) -> str:
    """``value`` as TOML writes it (numbers, strings, booleans, inline tables of those)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return _fmt(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, Mapping):
        return "{" + ", ".join(f"{k} = {toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(f"no TOML form for {value!r}")


def _comment(text: str, indent: str = "# ") -> list[str]:
    import textwrap

    return textwrap.wrap(
        text,
        WIDTH,
        initial_indent=indent,
        subsequent_indent=indent + "  ",
        break_long_words=False,
        break_on_hyphens=False,
    )


def _section(lines: list[str], table: str) -> tuple[int, int]:
    """``(header index, end index)`` of ``[table]`` in ``lines``: its key lines are between;
    for :data:`TOP`, the lines before the first table (header index -1)."""
    if table == TOP:
        first = next((i for i, ln in enumerate(lines) if _HEADER_LINE.match(ln)), len(lines))
        end = first
        while end > 0 and not _KEY_LINE.match(lines[end - 1]):
            end -= 1
        return -1, end
    start = next(
        (i for i, ln in enumerate(lines) if (m := _HEADER_LINE.match(ln)) and m.group(1) == table),
        None,
    )
    if start is None:
        raise KeyError(table)
    end = next(
        (i for i in range(start + 1, len(lines)) if _HEADER_LINE.match(lines[i])), len(lines)
    )
    while end > start + 1 and not _KEY_LINE.match(
        lines[end - 1]
    ):  # the blank and comment lines of the next table
        end -= 1
    return start, end


def render_pipeline(draft: Draft, base_text: str | None = None) -> str:
    """The pipeline file of ``draft``: ``base_text`` (default: the embedded default pipeline)
    with the drafted values set (each with its source as a comment), the keys of
    ``draft.removed`` removed, the notes as comments above their tables, and a header saying
    what was drafted from what."""
    if base_text is None:
        # the pipeline and simulation config modules, ~50 ms: not for `megalut draft --help`
        from megalut_cli.pipeline.config import default_pipeline_text

        base_text = default_pipeline_text()
    lines = base_text.splitlines()
    for table, key in draft.removed:
        start, end = _section(lines, table)
        lines = [
            ln
            for i, ln in enumerate(lines)
            if not (start < i < end and (m := _KEY_LINE.match(ln)) and m.group(1) == key)
        ]
    for v in draft.values:
        start, end = _section(lines, v.table)
        text = f"{v.key} = {toml_value(v.value)}"
        comment = f"  # drafted: {v.source}"
        found = next(
            (
                i
                for i in range(start + 1, end)
                if (m := _KEY_LINE.match(lines[i])) and m.group(1) == v.key
            ),
            None,
        )
        if found is None:
            lines.insert(end, text + comment)
        else:
            lines[found] = text + comment
    for table in dict.fromkeys(n.table for n in draft.notes):
        start, _ = _section(lines, table)
        block = [
            ln
            for n in draft.notes
            if n.table == table
            for ln in _comment(("WARNING: " if n.warning else "") + n.text)
        ]
        lines[start:start] = block
    for i, ln in enumerate(lines):
        if _KEY_LINE.match(ln) and ln.split("=")[0].strip() == "description":
            lines[i] = f"description = {toml_value(draft.description)}"
            break
    head = [
        *_comment(
            f"Drafted by `megalut draft` from {' and '.join(draft.inputs)}: the default pipeline "
            "of `megalut run` (below) with the stamp size, PSF and noise measured on your data; "
            "each drafted value says where it comes from, and the comments above its table what "
            "the draft did not decide (WARNING: where the setup may need more). Check them, then "
            "`megalut run THIS_FILE --dry-run`."
        ),
        "#",
    ]
    return "\n".join(head + lines) + "\n"
