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
:data:`MIN_MODEL_TAIL_ROWS` in training, where those quantiles mean something); a stamp
size that differs from the model's is a finding too.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

#: Provenance key of the record.
DOMAIN_KEY = "domain"
#: The measured quantities whose training distribution a model records (those present).
DOMAIN_COLUMNS: tuple[str, ...] = (
    "skymad",
    "snr",
    "adamom_sigma",
    "adamom_flux",
    "psf_adamom_sigma",
)
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
#: Units shown after the values of a column.
UNITS = {"adamom_sigma": " px", "psf_adamom_sigma": " px"}


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
    record.update(about)
    return record


def with_constant_column(
    domain: Mapping[str, Any], column: str, value: float, tolerance: float, source: str
) -> dict[str, Any]:
    """``domain`` with ``column`` recorded as the constant ``value`` (every quantile), when it
    does not record that column yet: a quantity fixed by the training config (the PSF size of a
    constant PSF) rather than measured on its rows. A catalog's median within ``tolerance``
    (relative) of it is inside; ``source`` says where the value comes from."""
    out = dict(domain)
    columns = dict(out.get("columns", {}))
    if column not in columns and np.isfinite(value):
        n = int(out.get("n_rows", 0))
        columns[column] = {
            "n": n,
            "q": [float(value)] * len(out.get("quantiles", QUANTILES)),
            "tolerance": float(tolerance),
            "from": source,
        }
        out["columns"] = columns
    return out


def model_domain(provenance: Mapping[str, Any]) -> dict[str, Any] | None:
    """The domain a model records: its own training set's, else (an older weight-trained
    model) its point training set's; None when it records none."""
    for prov in (provenance, provenance.get("parent")):
        if isinstance(prov, Mapping) and isinstance(prov.get(DOMAIN_KEY), Mapping):
            return dict(prov[DOMAIN_KEY])
    return None


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


def domain_findings(
    domain: Mapping[str, Any], columns: Mapping[str, Any], stamp_size: int | None = None
) -> list[Finding]:
    """How a catalog lies outside a model's ``domain`` (a :func:`domain_record`): one
    :class:`Finding` per column of the record that ``columns`` holds (usable rows: ``flags
    == 0`` when ``columns`` has ``flags``) and fails the rule of the module doc, and one for a
    ``stamp_size`` that differs from the record's. Empty: nothing found."""
    out: list[Finding] = []
    n = len(next(iter(columns.values()))) if columns else 0
    rows = usable_rows(columns, n)
    qs = domain.get("quantiles", QUANTILES)
    for c in recorded_columns(domain):
        entry = domain["columns"][c]
        if c not in columns:
            continue
        v = _finite(columns[c], rows)
        if not v.size:
            continue
        unit = UNITS.get(c, "")
        med, q5, q95 = (float(x) for x in np.quantile(v, (0.5, 0.05, 0.95)))
        lo, hi = _quantile(entry, qs, MEDIAN_RANGE[0]), _quantile(entry, qs, MEDIAN_RANGE[1])
        model_med = _quantile(entry, qs, 0.5)
        here = f"median {fmt(med)}{unit} (5–95 %: {fmt(q5)}–{fmt(q95)})"
        rel = max(TOLERANCE, float(entry.get("tolerance", 0.0)))
        tol = rel * max(abs(lo), abs(hi))  # a constant column (a fixed PSF) stays inside itself
        if not lo - tol <= med <= hi + tol:
            if lo == hi:  # a constant of the training config (a fixed PSF)
                trained = f"model trained at {fmt(lo)}{unit} (±{100 * rel:g} %)"
            else:
                trained = (
                    f"model trained on {fmt(lo)}–{fmt(hi)}{unit} ({_pct(MEDIAN_RANGE[0])}–"
                    f"{_pct(MEDIAN_RANGE[1])} %, median {fmt(model_med)})"
                )
            out.append(Finding(c, f"{c} {here}, {trained}"))
            continue
        if v.size < MIN_TAIL_ROWS or int(entry.get("n", 0)) < MIN_MODEL_TAIL_ROWS:
            continue
        tlo, thi = _quantile(entry, qs, TAIL_RANGE[0]), _quantile(entry, qs, TAIL_RANGE[1])
        tol = rel * max(abs(tlo), abs(thi))
        outside = float(np.mean((v < tlo - tol) | (v > thi + tol)))
        if outside > OUTSIDE_FRACTION:
            out.append(
                Finding(
                    c,
                    f"{c} {here}: {100 * outside:.0f} % of the rows outside the model's "
                    f"{_pct(TAIL_RANGE[0])}–{_pct(TAIL_RANGE[1])} % range "
                    f"{fmt(tlo)}–{fmt(thi)}{unit} "
                    f"(median {fmt(model_med)})",
                )
            )
    trained = domain.get("stamp_size")
    if stamp_size is not None and trained is not None and int(stamp_size) != int(trained):
        out.append(
            Finding(
                "stamp_size", f"stamp size {int(stamp_size)} px, model trained at {int(trained)} px"
            )
        )
    return out
