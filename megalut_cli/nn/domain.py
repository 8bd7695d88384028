"""The domain of a model: how the measured quantities of its training rows were distributed,
and what a catalog shows that lies outside it.

A trained model records, in its ``/provenance`` ``domain`` attribute (JSON,
``docs/model-format.md``), quantiles (:data:`QUANTILES`) of the columns of
:data:`DOMAIN_COLUMNS` present in its training catalog, over its usable rows (``flags ==
0``, finite features, inside the training selection), and the stamp size.
:func:`domain_findings` compares a catalog's columns with such a record (arrays in,
:class:`Finding` out); ``megalut predict`` warns with them, or refuses with ``--strict``.

The rule, once (:func:`domain_findings`): a column is outside the model's domain when the
catalog's median (usable rows) lies outside the model's 1-99 % range, or when more than
:data:`OUTSIDE_FRACTION` of the catalog's usable rows lie outside the model's 0.5-99.5 %
range (judged only with at least :data:`MIN_TAIL_ROWS` usable rows here and
:data:`MIN_MODEL_TAIL_ROWS` in training, where those quantiles mean something); the joint
(size, flux) coverage (:data:`JOINT_KEY`: more than :data:`OUTSIDE_FRACTION` of the usable
rows in cells where the training set has (almost) no row); a stamp size (the ``STAMPSZ``
card, else every row's ``box_size``) that differs from the model's; a catalog with no
usable row.

Which items apply depends on the model's shear mode (:func:`mode_domain`): a
simulation-calibrated model is calibrated for its training PSF, noise and stamp size, and
every item applies. A metacal model's response is measured on each galaxy's own image, so
it absorbs the PSF (size and ellipticity) and the noise level to first order: what stays
meaningful is what the networks' response cannot absorb, the S/N (``snr``) and the galaxy's
size relative to the PSF (``resolution``, ``adamom_sigma / psf_adamom_sigma`` of the
noshear version); the noise level (``skymad``), the absolute size and flux, the PSF's size
and ellipticity, the stamp size and the recorded setup do not apply (:data:`METACAL_ITEMS`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from megalut_cli.provenance import own_or_parent

#: Provenance key of the record.
DOMAIN_KEY = "domain"
#: The measured quantities whose training distribution a model records (those present).
DOMAIN_COLUMNS: tuple[str, ...] = (
    "skymad",
    "snr",
    "adamom_sigma",
    "adamom_flux",
    "psf_adamom_sigma",
    "psf_adamom_g1",
    "psf_adamom_g2",
)
#: The PSF measurements a model records in its domain (``measure`` with a PSF).
DOMAIN_PSF_COLUMNS: tuple[str, ...] = ("psf_adamom_sigma", "psf_adamom_g1", "psf_adamom_g2")
#: The galaxy's size relative to the PSF's: ``adamom_sigma / psf_adamom_sigma`` (derived).
RESOLUTION = "resolution"
#: Quantiles recorded (fractions).
QUANTILES: tuple[float, ...] = (0.005, 0.01, 0.05, 0.5, 0.95, 0.99, 0.995)
#: The model's range a catalog's median must lie in (quantiles).
MEDIAN_RANGE = (0.01, 0.99)
#: The model's range most of a catalog must lie in (quantiles) ...
TAIL_RANGE = (0.005, 0.995)
#: ... that is, no more than this fraction of its usable rows outside.
OUTSIDE_FRACTION = 0.10
#: Fewest usable rows of a catalog, and of the training set, to judge the tails.
MIN_TAIL_ROWS = 100
MIN_MODEL_TAIL_ROWS = 1000
#: Relative margin of the ranges (float rounding of values recorded in float32).
TOLERANCE = 1e-6
#: Relative margin of a PSF size the training config fixed (a constant PSF): about the
#: precision to which a survey knows its PSF size; to first order a relative size error d
#: biases a PSF-corrected shear by about 2 d (R_psf / R_gal)^2 (Paulin-Henriksson et al. 2008).
PSF_SIZE_TOLERANCE = 0.01
#: Absolute margin of a PSF ellipticity (each component) the training config fixed: a
#: simulation-calibrated model trained on one PSF does not correct another PSF's anisotropy
#: (the shipped ``fiducial``, trained on a round PSF, passes a PSF g2 of 0.02 into its
#: estimates whole: leakage about 1), so the margin is the Stage IV additive requirement
#: (|c| < 2e-4, :data:`megalut_cli.shear.bias.STAGE_IV_C`) at a leakage of 1.
PSF_G_TOLERANCE = 2e-4
#: Units shown after the values of a column.
UNITS = {"adamom_sigma": " px", "psf_adamom_sigma": " px"}
#: Provenance key (inside the domain) of the joint (size, flux) occupancy.
JOINT_KEY = "joint"
#: Its columns, and the cells per axis (edges at the training set's quantiles).
JOINT_COLUMNS: tuple[str, str] = ("adamom_sigma", "adamom_flux")
JOINT_BINS = 8
#: A cell is empty when it holds fewer than this fraction of the training rows (an average
#: cell holds 1 / JOINT_BINS**2, 1.6 %).
EMPTY_CELL_FRACTION = 1e-3
#: The items that stay meaningful for a metacal model (module doc); the others are dropped.
METACAL_ITEMS: tuple[str, ...] = ("snr", RESOLUTION)


@dataclass(frozen=True)
class Finding:
    """One way a catalog lies outside a model's domain: ``item`` (a column, ``stamp_size``
    or a setup key) and a message with the numbers."""

    item: str
    message: str

    def __str__(self) -> str:
        return self.message


def usable_rows(columns: Mapping[str, np.ndarray], n_rows: int) -> np.ndarray:
    """The rows with ``flags == 0`` (all rows of a table without ``flags``)."""
    if "flags" in columns:
        return np.asarray(columns["flags"]) == 0
    return np.ones(n_rows, dtype=bool)


def _finite(values: Any, rows: np.ndarray | None) -> np.ndarray:
    v = np.asarray(values, dtype=np.float64)
    if rows is not None:
        v = v[rows]
    return v[np.isfinite(v)]


def domain_record(
    columns: Mapping[str, Any],
    usable: np.ndarray | None = None,
    stamp_size: int | None = None,
    **about: Any,
) -> dict[str, Any]:
    """The domain record of a training table: the :data:`QUANTILES` (and count) of every
    column of :data:`DOMAIN_COLUMNS` in ``columns`` over the rows ``usable`` (default:
    ``flags == 0``), finite values only; ``stamp_size`` and ``about`` (e.g. ``source``,
    ``version``) as given."""
    present = [c for c in DOMAIN_COLUMNS if c in columns]
    record: dict[str, Any] = {
        "quantiles": list(QUANTILES),
        "columns": {},
        "stamp_size": stamp_size,
        "n_rows": 0,
    }
    rows = usable
    for c in present:
        v = np.asarray(columns[c])
        if rows is None:
            rows = usable_rows(columns, len(v))
        v = _finite(v, rows)
        if v.size:
            record["columns"][c] = {
                "n": int(v.size),
                "q": [float(x) for x in np.quantile(v, QUANTILES)],
            }
    if rows is not None:
        record["n_rows"] = int(np.count_nonzero(rows))
        ratio = resolution(columns)
        if ratio is not None:
            v = _finite(ratio, rows)
            if v.size:
                record["columns"][RESOLUTION] = {
                    "n": int(v.size),
                    "q": [float(x) for x in np.quantile(v, QUANTILES)],
                }
        joint = joint_record(columns, rows)
        if joint is not None:
            record[JOINT_KEY] = joint
    record.update(about)
    return record


def resolution(columns: Mapping[str, Any]) -> np.ndarray | None:
    """``adamom_sigma / psf_adamom_sigma`` of every row (None without both columns)."""
    if "adamom_sigma" not in columns or "psf_adamom_sigma" not in columns:
        return None
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(columns["adamom_sigma"], dtype=np.float64) / np.asarray(
            columns["psf_adamom_sigma"], dtype=np.float64
        )


def joint_record(columns: Mapping[str, Any], rows: np.ndarray) -> dict[str, Any] | None:
    """The joint occupancy of the rows ``rows`` in (:data:`JOINT_COLUMNS`): cell edges at the
    quantiles ``0.005, 1/JOINT_BINS, ..., 0.995`` of each column and the training rows per
    cell (rows outside the outer edges are in no cell); None without both columns or rows."""
    if not all(c in columns for c in JOINT_COLUMNS):
        return None
    x, y = (np.asarray(columns[c], dtype=np.float64)[rows] for c in JOINT_COLUMNS)
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if not x.size:
        return None
    qs = np.linspace(0.0, 1.0, JOINT_BINS + 1)
    qs[0], qs[-1] = TAIL_RANGE
    edges = [np.quantile(v, qs) for v in (x, y)]
    counts, _, _ = np.histogram2d(x, y, bins=edges)
    return {
        "columns": list(JOINT_COLUMNS),
        "edges": [[float(e) for e in edge] for edge in edges],
        "counts": [[int(c) for c in row] for row in counts],
        "n": int(x.size),
    }


def with_constant_column(
    domain: Mapping[str, Any],
    column: str,
    value: float,
    tolerance: float,
    source: str,
    absolute: bool = False,
) -> dict[str, Any]:
    """``domain`` with ``column`` recorded as the constant ``value`` (every quantile), when it
    does not record that column yet: a quantity fixed by the training config (the PSF size or
    ellipticity of a constant PSF) rather than measured on its rows. A catalog's median within
    ``tolerance`` of it (relative; ``absolute``: in the column's units, key ``atol``) is
    inside; ``source`` says where the value comes from."""
    out = dict(domain)
    columns = dict(out.get("columns", {}))
    if column not in columns and np.isfinite(value):
        n = int(out.get("n_rows", 0))
        columns[column] = {
            "n": n,
            "q": [float(value)] * len(out.get("quantiles", QUANTILES)),
            "atol" if absolute else "tolerance": float(tolerance),
            "from": source,
        }
        out["columns"] = columns
    return out


def with_resolution(domain: Mapping[str, Any]) -> dict[str, Any]:
    """``domain`` with the :data:`RESOLUTION` column derived from ``adamom_sigma`` and a
    constant ``psf_adamom_sigma`` (a fixed training PSF: the ratio's quantiles are the sizes'
    over it), when it does not record it."""
    out = dict(domain)
    columns = dict(out.get("columns", {}))
    size, psf = columns.get("adamom_sigma"), columns.get("psf_adamom_sigma")
    if RESOLUTION in columns or size is None or psf is None:
        return out
    if len(set(psf["q"])) != 1 or not psf["q"][0] > 0:
        return out  # a PSF that varied: the ratio's quantiles are not those of the sizes
    columns[RESOLUTION] = {
        "n": int(size.get("n", 0)),
        "q": [float(q) / float(psf["q"][0]) for q in size["q"]],
        "from": "adamom_sigma over the constant psf_adamom_sigma",
    }
    out["columns"] = columns
    return out


def mode_domain(domain: Mapping[str, Any], shear_mode: str) -> tuple[dict[str, Any], list[str]]:
    """The items of ``domain`` that apply to a model of ``shear_mode`` (module doc), and the
    names of those dropped: all of them for a simulation-calibrated model; for a metacal one
    only :data:`METACAL_ITEMS` (the resolution derived when needed), no stamp size and no
    joint occupancy."""
    if shear_mode != "metacal":
        return dict(domain), []
    full = with_resolution(domain)
    columns = full.get("columns", {})
    out = {k: v for k, v in full.items() if k not in ("columns", "stamp_size", JOINT_KEY)}
    out["columns"] = {c: columns[c] for c in METACAL_ITEMS if c in columns}
    dropped = [c for c in columns if c not in out["columns"]]
    dropped += ["stamp_size"] * (full.get("stamp_size") is not None)
    dropped += [JOINT_KEY] * (JOINT_KEY in full)
    return out, dropped


def model_domain(provenance: Mapping[str, Any]) -> dict[str, Any] | None:
    """The domain a model records: its own training set's, else (an older weight-trained
    model) its point training set's; None when it records none."""
    domain = own_or_parent(provenance, DOMAIN_KEY)
    return None if domain is None else dict(domain)


def recorded_columns(domain: Mapping[str, Any]) -> list[str]:
    """The columns a domain records, in the order of :data:`DOMAIN_COLUMNS` (then any other)."""
    have = list(domain.get("columns", {}))
    return [c for c in DOMAIN_COLUMNS if c in have] + [c for c in have if c not in DOMAIN_COLUMNS]


def _quantile(entry: Mapping[str, Any], quantiles: Sequence[float], p: float) -> float:
    """The recorded quantile ``p`` (interpolated between recorded ones if absent)."""
    return float(np.interp(p, list(quantiles), entry["q"]))


def fmt(x: float) -> str:
    """A value as findings and summaries show it (3 significant digits, no exponent below 10^5)."""
    if not np.isfinite(x):
        return str(x)
    if abs(x) >= 1000 and abs(x) < 1e5:
        return f"{x:.0f}"
    return f"{x:.3g}"


def shown(entry: Mapping[str, Any], x: float) -> str:
    """A recorded value as findings show it: :func:`fmt`, and 0 for a value of an entry with an
    absolute margin (``atol``) that is 0 to within its rounding (a round PSF's ellipticity)."""
    if "atol" in entry and abs(x) < float(entry["atol"]) / 100:
        return "0"
    return fmt(x)


def _pct(p: float) -> str:
    return f"{100 * p:g}"


def column_range(
    domain: Mapping[str, Any], column: str, lo: float = MEDIAN_RANGE[0], hi: float = MEDIAN_RANGE[1]
) -> tuple[float, float, float]:
    """``(low, high, median)`` of a recorded column: its ``lo`` and ``hi`` quantiles."""
    entry, qs = domain["columns"][column], domain.get("quantiles", QUANTILES)
    return _quantile(entry, qs, lo), _quantile(entry, qs, hi), _quantile(entry, qs, 0.5)


def domain_summary(domain: Mapping[str, Any]) -> str:
    """One line: the 1-99 % range of every recorded column and the stamp size, e.g.
    ``skymad 0.83-1.17, snr 6-310, adamom_sigma 2.1-9.8 px, stamp 64 px``."""
    parts = []
    for c in recorded_columns(domain):
        lo, hi, _ = column_range(domain, c)
        span = fmt(lo) if fmt(lo) == fmt(hi) else f"{fmt(lo)}–{fmt(hi)}"
        parts.append(f"{c} {span}{UNITS.get(c, '')}")
    if domain.get("stamp_size"):
        parts.append(f"stamp {domain['stamp_size']} px")
    return ", ".join(parts)


def _margin(entry: Mapping[str, Any], lo: float, hi: float) -> float:
    """How far outside ``lo``-``hi`` a value may lie and still be inside: the entry's ``atol``,
    else its relative ``tolerance`` (at least :data:`TOLERANCE`) of the range's scale."""
    if "atol" in entry:
        return float(entry["atol"])
    return max(TOLERANCE, float(entry.get("tolerance", 0.0))) * max(abs(lo), abs(hi))


def _trained_text(entry: Mapping[str, Any], lo: float, hi: float, med: float, unit: str) -> str:
    if lo == hi:  # a constant of the training config (a fixed PSF)
        if "atol" in entry:
            return f"model trained at {shown(entry, lo)}{unit} (±{fmt(float(entry['atol']))})"
        rel = max(TOLERANCE, float(entry.get("tolerance", 0.0)))
        return f"model trained at {fmt(lo)}{unit} (±{100 * rel:g} %)"
    return (
        f"model trained on {fmt(lo)}–{fmt(hi)}{unit} ({_pct(MEDIAN_RANGE[0])}–"
        f"{_pct(MEDIAN_RANGE[1])} %, median {fmt(med)})"
    )


def column_findings(
    domain: Mapping[str, Any], columns: Mapping[str, Any], rows: np.ndarray
) -> list[Finding]:
    """The findings of the 1-D rule (module doc) for every column of ``domain`` that
    ``columns`` holds (the :data:`RESOLUTION` derived from its sizes), over the rows ``rows``."""
    out: list[Finding] = []
    qs = domain.get("quantiles", QUANTILES)
    for c in recorded_columns(domain):
        entry = domain["columns"][c]
        values = resolution(columns) if c == RESOLUTION and c not in columns else columns.get(c)
        if values is None:
            continue
        v = _finite(values, rows)
        if not v.size:
            continue
        unit = UNITS.get(c, "")
        med, q5, q95 = (float(x) for x in np.quantile(v, (0.5, 0.05, 0.95)))
        lo, hi = _quantile(entry, qs, MEDIAN_RANGE[0]), _quantile(entry, qs, MEDIAN_RANGE[1])
        model_med = _quantile(entry, qs, 0.5)
        here = f"median {fmt(med)}{unit} (5–95 %: {fmt(q5)}–{fmt(q95)})"
        tol = _margin(entry, lo, hi)  # a constant column (a fixed PSF) stays inside itself
        if not lo - tol <= med <= hi + tol:
            out.append(Finding(c, f"{c} {here}, {_trained_text(entry, lo, hi, model_med, unit)}"))
            continue
        constant = lo == hi
        if v.size < MIN_TAIL_ROWS or (
            int(entry.get("n", 0)) < MIN_MODEL_TAIL_ROWS and not constant
        ):
            continue
        tlo, thi = _quantile(entry, qs, TAIL_RANGE[0]), _quantile(entry, qs, TAIL_RANGE[1])
        tol = _margin(entry, tlo, thi)
        outside = float(np.mean((v < tlo - tol) | (v > thi + tol)))
        if outside > OUTSIDE_FRACTION:
            if constant:  # a fixed training PSF: the catalog's varies over the rows
                where = f"model trained at {shown(entry, tlo)}{unit} (±{fmt(tol)}{unit})"
            else:
                where = (
                    f"model's {_pct(TAIL_RANGE[0])}–{_pct(TAIL_RANGE[1])} % range "
                    f"{fmt(tlo)}–{fmt(thi)}{unit} (median {fmt(model_med)})"
                )
            out.append(
                Finding(c, f"{c} {here}: {100 * outside:.0f} % of the rows outside the {where}")
            )
    return out


def joint_findings(
    domain: Mapping[str, Any], columns: Mapping[str, Any], rows: np.ndarray
) -> list[Finding]:
    """One finding when more than :data:`OUTSIDE_FRACTION` of the rows ``rows`` (at least
    :data:`MIN_TAIL_ROWS`, the model's :data:`JOINT_KEY` record from at least
    :data:`MIN_MODEL_TAIL_ROWS`) fall outside the recorded cells or into cells holding fewer
    than :data:`EMPTY_CELL_FRACTION` of the training rows; none when the model records no
    joint occupancy (models from before it was recorded)."""
    joint = domain.get(JOINT_KEY)
    if not isinstance(joint, Mapping) or int(joint.get("n", 0)) < MIN_MODEL_TAIL_ROWS:
        return []
    names = list(joint["columns"])
    if not all(c in columns for c in names):
        return []
    x, y = (np.asarray(columns[c], dtype=np.float64)[rows] for c in names)
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size < MIN_TAIL_ROWS:
        return []
    ex, ey = (np.asarray(e, dtype=np.float64) for e in joint["edges"])
    counts = np.asarray(joint["counts"], dtype=np.float64)
    ix = np.searchsorted(ex, x, side="right") - 1
    iy = np.searchsorted(ey, y, side="right") - 1
    ix[x == ex[-1]] = len(ex) - 2  # the last edge closes the last cell
    iy[y == ey[-1]] = len(ey) - 2
    inside = (ix >= 0) & (ix < len(ex) - 1) & (iy >= 0) & (iy < len(ey) - 1)
    empty = counts < EMPTY_CELL_FRACTION * float(joint["n"])
    bad = ~inside
    bad[inside] = empty[ix[inside], iy[inside]]
    frac = float(np.mean(bad))
    if frac <= OUTSIDE_FRACTION:
        return []
    n_empty = int(np.count_nonzero(empty))
    return [
        Finding(
            JOINT_KEY,
            f"{names[0]} × {names[1]}: {100 * frac:.0f} % of the rows where the model has "
            f"(almost) no training row (outside its {_pct(TAIL_RANGE[0])}–{_pct(TAIL_RANGE[1])} "
            f"% box or in one of its {n_empty} of {counts.size} (size, flux) quantile cells "
            f"holding < {100 * EMPTY_CELL_FRACTION:g} % of its {int(joint['n'])} rows), "
            "although each column alone may lie inside",
        )
    ]


def stamp_findings(
    trained: int | None, stamp_size: int | None, box_size: Any | None = None
) -> list[Finding]:
    """A finding for a ``stamp_size`` (the catalog's ``STAMPSZ``) other than the model's
    ``trained`` one; without a ``stamp_size``, for the per-row ``box_size`` (MEDS, usable
    rows) when any differs (with the sizes found and their shares)."""
    if trained is None:
        return []
    if stamp_size is not None:
        if int(stamp_size) == int(trained):
            return []
        return [
            Finding(
                "stamp_size", f"stamp size {int(stamp_size)} px, model trained at {int(trained)} px"
            )
        ]
    if box_size is None:
        return []
    box = np.asarray(box_size)
    box = box[np.isfinite(box.astype(np.float64))]
    if not box.size or np.all(box == int(trained)):
        return []
    sizes, counts = np.unique(box.astype(np.int64), return_counts=True)
    shares = ", ".join(
        f"{int(s)} px ({100 * c / box.size:.0f} %)"
        for s, c in sorted(zip(sizes, counts), key=lambda t: -t[1])
    )
    return [
        Finding(
            "stamp_size",
            f"stamp sizes (box_size) {shares}, model trained at {int(trained)} px",
        )
    ]


def domain_findings(
    domain: Mapping[str, Any],
    columns: Mapping[str, Any],
    stamp_size: int | None = None,
    usable: np.ndarray | None = None,
) -> list[Finding]:
    """How a catalog lies outside a model's ``domain`` (a :func:`domain_record`): no usable
    row (``usable``, default ``flags == 0`` when ``columns`` has ``flags``) is one finding
    (item ``rows``) and the only one; else one :class:`Finding` per column of the record
    that ``columns`` holds and fails the rule of the module doc, one for the joint (size, flux)
    coverage (:func:`joint_findings`), and one for a stamp size (``stamp_size``, else the
    ``box_size`` column) that differs from the record's. Empty: nothing found."""
    n = len(next(iter(columns.values()))) if columns else 0
    rows = usable_rows(columns, n) if usable is None else np.asarray(usable, dtype=bool)
    if n and not rows.any():
        return [Finding("rows", f"no usable row: all {n} rows are flagged (flags != 0)")]
    out = column_findings(domain, columns, rows)
    out += joint_findings(domain, columns, rows)
    box = np.asarray(columns["box_size"])[rows] if "box_size" in columns else None
    out += stamp_findings(domain.get("stamp_size"), stamp_size, box)
    return out
