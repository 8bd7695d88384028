"""Shear-bias analysis of a catalog of predictions with truth (``megalut evaluate``).

The catalog needs ``case, tru_g1, tru_g2`` and ``pre_g1, pre_g2``; with ``pre_g1_w,
pre_g2_w`` a weighted analysis is added. Rows with ``flags != 0`` or a non-finite estimate
(or true shear) count with weight 0, i.e. not at all. For every component the estimates
of each case are averaged (unweighted, and weighted) and ``m, c`` are fitted over cases
(:func:`megalut_cli.shear.bias.fit_bias`: OLS, errors from the residual scatter).

PSF frame: with PSF ellipticity columns (``tru_psf_g1, tru_psf_g2``, else
``psf_adamom_g1, psf_adamom_g2``) the per-case averages of estimates and true shears are
also rotated by ``-2 theta``, ``theta = 0.5 atan2(psf_g2, psf_g1)`` of the case's PSF (the
mean PSF ellipticity over its rows), giving the ``plus`` and ``cross`` components (GREAT3
convention, paper Sect. 2.2). Rotating case averages is what GREAT3 does; it equals
rotating every row when the PSF is the same for all rows of a case, as it is in megalut
simulations.

Conditional biases (``by``): equal-population bins of any column, over the rows used;
in each bin the rows of each case are averaged and the line fitted over cases.

Errors: from the fit (OLS over cases), or, for common-random-number sets whose cases share
their galaxies (header ``CRN = T``), from a bootstrap over galaxies
(:mod:`megalut_cli.shear.bootstrap`): realization groups (``rea // group_size``) are
resampled with replacement across all cases together and every fit is redone.

Catalogs are read in row chunks: memory grows with the number of cases (and with the
``by`` columns, whose values are needed to place the bin edges), not with the rows.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from megalut_cli import expr as _expr
from megalut_cli.catalog import (
    VersionColumns,
    catalog_info,
    history_steps,
    is_fits_file,
    iter_catalog,
    read_catalog,
)
from megalut_cli.errors import ConfigError, InputError, MegalutError
from megalut_cli.measure.metacal_defaults import DEFAULT_STEP, TYPES
from megalut_cli.provenance import CREATOR, command_line, sha256_file, software_versions, utc_now
from megalut_cli.shear.bias import (
    GREAT3_SIGMA2_MIN_GROUND,
    BiasFit,
    fit_bias,
    psf_angle,
    q_c,
    stage_iv_requirement,
)
from megalut_cli.shear.bootstrap import (
    ERROR_BOOTSTRAP,
    ERROR_FIT,
    SHEAR_TERM,
    GroupResampler,
    ResidualMoments,
    fit_columns,
    group_size_for,
    resample_counts,
    residuals,
    shear_draw_variance,
    spread,
)
from megalut_cli.shear.conditional import assign_bins, equal_population_edges
from megalut_cli.shear.options import (
    ERROR_CHOICES,
    FAILURES_CHOICES,
    JSON_FORMAT,
    JSON_FORMAT_VERSION,
    N_BOOTSTRAP,
    RESPONSE_CHOICES,
)
from megalut_cli.shear.response import (
    MIN_ZERO_SHEAR_CASES,
    RESPONSE_MEAN,
    RESPONSE_ZERO_SHEAR,
    calibration_response,
    case_estimates,
    case_shears,
    header_step,
    metacal_response,
    row_values,
    zero_shear_weights,
)

log = logging.getLogger(__name__)

TRUTH_COLUMNS = ("case", "tru_g1", "tru_g2")
ESTIMATE_COLUMNS = ("pre_g1", "pre_g2")
WEIGHT_COLUMNS = ("pre_g1_w", "pre_g2_w")
#: PSF ellipticity columns, in order of preference.
PSF_SHAPE_COLUMNS = (("tru_psf_g1", "tru_psf_g2"), ("psf_adamom_g1", "psf_adamom_g2"))
COMPONENTS = ("g1", "g2", "plus", "cross")
SCHEMES = ("unweighted", "weighted")
#: Rows read at a time.
CHUNK_ROWS = 500_000
#: |m| above which a fit is flagged as the sign of an untrained or mismatched model
#: (when it exceeds it by more than its 1-sigma error: noise alone does not warn).
WARN_M = 0.1
#: Galaxy groups below which bootstrap errors are flagged as rough.
FEW_GROUPS = 30
#: Per-row metacal responses written by ``megalut predict`` on a metacal catalog.
RESPONSE_COLUMNS = ("mcal_r11", "mcal_r12", "mcal_r21", "mcal_r22")
#: The sheared metacal versions whose selection gives the selection response.
SHEARED_TYPES = TYPES[1:]
#: Bits of a (case, group) key that hold the group (case ids must fit in the rest).
_GROUP_BITS = 32


# --------------------------------------------------------------------------- planning


@dataclass(frozen=True)
class BootstrapSpec:
    """A bootstrap over galaxy groups: ``group_size`` consecutive realizations (``rea``)
    form a group, resampled ``n_resamples`` times from ``seed``; ``crn`` records whether
    the input is a common-random-number set (reported, not used)."""

    group_size: int = 1
    n_resamples: int = N_BOOTSTRAP
    seed: int = 1
    crn: bool = False


@dataclass
class _Plan:
    source: str
    weighted: bool
    psf: tuple[str, str] | None
    by: list[str]
    select: str | None
    select_cases: str | None
    columns: list[str] = field(default_factory=list)
    has_flags: bool = False
    selected_cases: np.ndarray | None = None
    by_kind: dict[str, str] = field(
        default_factory=dict
    )  # "column", "row" or "case" (see check_by)
    case_by: dict[str, tuple[np.ndarray, np.ndarray]] = field(
        default_factory=dict
    )  # expr -> (case ids, values)
    bootstrap: BootstrapSpec | None = None
    names: dict[str, str] = field(default_factory=dict)  # how messages name the arguments
    metacal: float | None = None  # the metacal step: calibrate pre_*_noshear by the response
    response: str = "auto"  # --response: "auto", "mean" or "zero-shear"
    failures: str = "exclude"  # --failures: "exclude" or "selection"
    crn: bool = False  # a common-random-number set (header CRN = T)
    zero_shear: bool = False  # decided from the cases: calibrate by the response at zero shear

    @property
    def schemes(self) -> tuple[str, ...]:
        return SCHEMES if self.weighted else SCHEMES[:1]

    @property
    def failures_select(self) -> bool:
        """Whether a metacal evaluation counts each version's failures as a selection."""
        return self.metacal is not None and self.failures == "selection"

    @property
    def binned_selection(self) -> bool:
        """Whether ``--by`` bins are a selection whose response is taken on the sheared
        versions: metacal catalogs with a per-row ``by`` entry (per-case ones bin whole cases)."""
        return self.metacal is not None and any(k != "case" for k in self.by_kind.values())

    def name(self, arg: str) -> str:
        """How messages name the argument ``arg`` (``by``, ``select``, ``select_cases``,
        ``errors``)."""
        return self.names.get(arg, arg)


def check_by(
    by: Sequence[str], available: Sequence[str], key: str = "by", where: str = "the catalog"
) -> dict[str, str]:
    """Kind of each ``by`` entry: ``"column"``, ``"row"`` (numeric row expression such as
    ``sqrt(tru_e1**2 + tru_e2**2)``) or ``"case"`` (per-case aggregate such as ``mean(snr)``,
    the paper's binning by average S/N per case). Raises :class:`ConfigError` naming ``key``."""
    have = set(available)
    kinds: dict[str, str] = {}
    unknown = [c for c in by if c not in have and c.isidentifier()]
    if unknown:
        raise ConfigError(f"{key}: no column {', '.join(unknown)} in {where}")
    for c in by:
        if c in have:
            kinds[c] = "column"
            continue
        try:
            case_mode = _expr.check_quantity(c, list(available))
        except MegalutError as err:
            raise ConfigError(f"{key}: {err}") from None
        kinds[c] = "case" if case_mode else "row"
    return kinds


def _make_plan(
    colnames: Sequence[str],
    source: str,
    by: Sequence[str] | None,
    select: str | None,
    select_cases: str | None,
    bootstrap: BootstrapSpec | None = None,
    names: Mapping[str, str] | None = None,
    metacal_step: float | None = None,
    response: str = "auto",
    crn: bool = False,
    failures: str = "exclude",
) -> _Plan:
    given = dict(names or {})
    have = set(colnames)
    metacal = _metacal_mode(have, source, metacal_step)
    if response not in RESPONSE_CHOICES:
        raise ConfigError(
            f"{given.get('response', 'response')}: unknown value {response!r} "
            f"(expected one of {', '.join(RESPONSE_CHOICES)})"
        )
    if failures not in FAILURES_CHOICES:
        raise ConfigError(
            f"{given.get('failures', 'failures')}: unknown value {failures!r} "
            f"(expected one of {', '.join(FAILURES_CHOICES)})"
        )
    if failures == "selection" and metacal is None:
        raise InputError(
            f"{source}: {given.get('failures', 'failures')} selection applies to a metacal "
            "catalog (columns mcal_r11 .. mcal_r22 from 'megalut predict' on metacal features)"
        )
    if response == RESPONSE_ZERO_SHEAR and metacal is None:
        raise InputError(
            f"{source}: {given.get('response', 'response')} {response} calibrates a metacal "
            "catalog (columns mcal_r11 .. mcal_r22 from 'megalut predict' on metacal features)"
        )
    estimates = (
        [f"{c}_noshear" for c in ESTIMATE_COLUMNS]
        if metacal is not None
        else list(ESTIMATE_COLUMNS)
    )
    missing = [c for c in (*TRUTH_COLUMNS, *estimates) if c not in have]
    if missing:
        raise InputError(
            f"{source}: evaluate needs the true shear of each case (columns case, tru_g1, tru_g2) "
            f"and the estimates from 'megalut predict' (pre_g1, pre_g2); "
            f"missing: {', '.join(missing)}"
        )
    weighted = all(c in have for c in WEIGHT_COLUMNS)
    if metacal is not None:
        weighted = all(
            f"{c}_{kind}" in have for c in WEIGHT_COLUMNS for kind in ("noshear", *SHEARED_TYPES)
        )
    if not weighted and any(c in have for c in WEIGHT_COLUMNS):
        log.warning(
            "%s: only one of %s present; weighted analysis skipped",
            source,
            ", ".join(WEIGHT_COLUMNS),
        )
    psf = next((pair for pair in PSF_SHAPE_COLUMNS if all(c in have for c in pair)), None)
    by = list(dict.fromkeys(by or []))
    by_kind = check_by(by, list(colnames), given.get("by", "by"), source)
    if select is not None:
        _expr.check_expression(select, list(colnames))
    if select_cases is not None:
        _expr.check_expression(select_cases, list(colnames), case_mode=True)
    if bootstrap is not None:
        if "rea" not in have:
            raise InputError(
                f"{source}: bootstrap errors need the realization column 'rea' to resample "
                f"galaxies (or use fit errors: {given.get('errors', 'errors')} fit)"
            )
        if bootstrap.n_resamples < 2 or bootstrap.group_size < 1:
            raise ConfigError("bootstrap: needs at least 2 resamples and a group size >= 1")
    plan = _Plan(
        source,
        weighted,
        psf,
        by,
        select,
        select_cases,
        has_flags="flags" in have,
        by_kind=by_kind,
        bootstrap=bootstrap,
        names=given,
        metacal=metacal,
        response=response,
        failures=failures,
        crn=crn,
    )
    cols = [*TRUTH_COLUMNS, *(ESTIMATE_COLUMNS if metacal is None else ())]
    if metacal is not None:
        cols += [*RESPONSE_COLUMNS, *(f"{c}_noshear" for c in ESTIMATE_COLUMNS), "flags_noshear"]
        if failures == "selection":
            per_version = [f"{c}_{k}" for k in SHEARED_TYPES for c in ("flags", *ESTIMATE_COLUMNS)]
            missing = [c for c in per_version if c not in have]
            if missing:
                raise InputError(
                    f"{source}: {given.get('failures', 'failures')} selection needs each "
                    f"version's flags and estimates; missing: {', '.join(missing)}"
                )
            cols += per_version
        if weighted:
            cols += [f"{c}_{kind}" for c in WEIGHT_COLUMNS for kind in ("noshear", *SHEARED_TYPES)]
        used = list(_expr.columns_used(select)) if select is not None else []
        for c in by:  # the bins too are taken on the noshear versions
            used += (
                [c]
                if by_kind[c] == "column"
                else _expr.columns_used(c)
                if by_kind[c] == "row"
                else []
            )
        cols += [f"{c}_{kind}" for kind in TYPES for c in used if f"{c}_{kind}" in have]
    if bootstrap is not None:
        cols.append("rea")
    if weighted:
        cols += WEIGHT_COLUMNS
    if plan.has_flags:
        cols.append("flags")
    if psf:
        cols += psf
    for c in by:
        cols += (
            [c] if by_kind[c] == "column" else _expr.columns_used(c) if by_kind[c] == "row" else []
        )
    if select is not None:
        cols += _expr.columns_used(select)
    plan.columns = list(dict.fromkeys(c for c in cols if c in have))
    return plan


def _metacal_mode(have: set[str], source: str, step: float | None) -> float | None:
    """The metacal step when the catalog holds ``megalut predict``'s metacal columns, else None."""
    present = [c for c in RESPONSE_COLUMNS if c in have]
    if not present:
        return None
    needed = [*RESPONSE_COLUMNS, *(f"{c}_noshear" for c in ESTIMATE_COLUMNS), "flags_noshear"]
    missing = [c for c in needed if c not in have]
    if missing:
        raise InputError(
            f"{source}: a metacal catalog (with {', '.join(present)}) lacks {', '.join(missing)}"
        )
    return float(step) if step is not None else DEFAULT_STEP


# --------------------------------------------------------------------------- per-chunk rows


@dataclass
class _Rows:
    case: np.ndarray
    selected: np.ndarray
    valid: dict[str, np.ndarray]  # "g1", "g2": usable estimate on this row
    tru: dict[str, np.ndarray]  # NaN-free (0 where not valid)
    pre: dict[str, np.ndarray]
    weight: dict[tuple[str, str], np.ndarray]  # (scheme, comp) -> weight (0 = row not used)
    psf: tuple[np.ndarray, np.ndarray] | None
    key: (
        np.ndarray
    )  # what sums are grouped by: the case, or (case, galaxy group) when bootstrapping
    # metacal: per-row responses (0 where not valid) and, per scheme, component i and sheared
    # type, the weight of the row under that type's selection and weights
    response: dict[tuple[int, int], np.ndarray] | None = None
    sheared_weight: dict[str, dict[tuple[int, str], np.ndarray]] | None = None
    pre_noshear: dict[int, np.ndarray] | None = None
    step: float | None = None
    # failures as a selection: the sheared versions' own estimates (component i, type)
    version_pre: dict[tuple[int, str], np.ndarray] | None = None


def _rows(chunk: Mapping[str, np.ndarray], plan: _Plan) -> _Rows:
    case = np.asarray(chunk["case"])
    if case.dtype.kind not in "iu":
        if case.dtype.kind == "f" and np.all(np.isfinite(case)) and np.all(case == np.round(case)):
            case = case.astype(np.int64)
        else:
            raise InputError(f"{plan.source}: column 'case' must hold integer case ids")
    n = case.size
    selected = np.ones(n, dtype=bool)
    if plan.select is not None:  # in metacal mode on the noshear versions' columns
        selected &= _expr.evaluate_rows(plan.select, _version_view(chunk, plan, "noshear"), n)
    if plan.selected_cases is not None:
        selected &= np.isin(case, plan.selected_cases)
    base = selected.copy()
    suffix = "_noshear" if plan.metacal is not None else ""
    if plan.metacal is not None:
        base &= np.asarray(chunk["flags_noshear"]) == 0
    elif plan.has_flags:
        base &= np.asarray(chunk["flags"]) == 0
    valid, tru, pre, weight = {}, {}, {}, {}
    for comp in ("g1", "g2"):
        t = np.asarray(chunk[f"tru_{comp}"], dtype=float)
        p = np.asarray(chunk[f"pre_{comp}{suffix}"], dtype=float)
        ok = base & np.isfinite(t) & np.isfinite(p)
        if plan.metacal is not None and not plan.failures_select:  # its response too
            ok &= np.isfinite(np.asarray(chunk[f"mcal_r{comp[1]}1"], dtype=float))
            ok &= np.isfinite(np.asarray(chunk[f"mcal_r{comp[1]}2"], dtype=float))
        valid[comp] = ok
        tru[comp] = np.where(ok, t, 0.0)
        pre[comp] = np.where(ok, p, 0.0)
        weight[("unweighted", comp)] = ok.astype(float)
        if plan.weighted:
            wcol = f"pre_{comp}_w{suffix}"
            w = np.asarray(chunk[wcol], dtype=float)
            bad = ok & (w < 0)
            if np.any(bad):
                raise InputError(
                    f"{plan.source}: column {wcol} has {int(bad.sum())} negative weight(s)"
                )
            weight[("weighted", comp)] = np.where(ok & np.isfinite(w) & (w > 0), w, 0.0)
    psf = None
    if plan.psf is not None:
        psf = (
            np.asarray(chunk[plan.psf[0]], dtype=float),
            np.asarray(chunk[plan.psf[1]], dtype=float),
        )
    key = (
        case
        if plan.bootstrap is None
        else _case_group_key(case, chunk["rea"], plan.bootstrap.group_size, plan.source)
    )
    rows = _Rows(case, selected, valid, tru, pre, weight, psf, key)
    if plan.metacal is not None:
        _metacal_rows(rows, chunk, plan)
    return rows


def _version_view(
    chunk: Mapping[str, np.ndarray], plan: _Plan, kind: str
) -> Mapping[str, np.ndarray]:
    """The chunk as the metacal version ``kind`` sees it: ``X`` is ``X_<kind>`` where the
    chunk has it (the chunk itself in plain mode); the plan reads the ``X_<kind>`` of the
    columns that ``select`` and ``by`` use."""
    return chunk if plan.metacal is None else VersionColumns(chunk, kind)


def _metacal_rows(rows: _Rows, chunk: Mapping[str, np.ndarray], plan: _Plan) -> None:
    """The responses of the valid rows and, with a selection or weights, each row's weight
    under the selection (and weights) of each sheared version (Sheldon & Huff 2017, Sect. 5)."""
    n = rows.case.size
    rows.step = plan.metacal
    rows.pre_noshear = {i: np.asarray(chunk[f"pre_g{i}_noshear"], dtype=float) for i in (1, 2)}
    rows.response = {}
    for i in (1, 2):
        for j in (1, 2):
            if plan.failures_select:  # the response of the versions' means instead (below)
                rows.response[(i, j)] = np.zeros(n)
                continue
            rows.response[(i, j)] = np.where(
                rows.valid[f"g{i}"], np.asarray(chunk[f"mcal_r{i}{j}"], dtype=float), 0.0
            )
    if (
        plan.select is None
        and not plan.weighted
        and not plan.binned_selection
        and not plan.failures_select
    ):
        return
    # The rows usable whatever the selection: flags_noshear == 0 and finite estimates and
    # responses (which needs every sheared version measured). With failures as a selection,
    # each version's mean is over its own measured rows, whatever the noshear version did.
    usable = (
        np.ones(n, dtype=bool) if plan.failures_select else np.asarray(chunk["flags_noshear"]) == 0
    )
    if plan.selected_cases is not None:
        usable &= np.isin(rows.case, plan.selected_cases)
    for i in (1, 2):
        usable &= np.isfinite(np.asarray(chunk[f"tru_g{i}"], dtype=float))
        if not plan.failures_select:
            usable &= np.isfinite(rows.pre_noshear[i])
            for j in (1, 2):
                usable &= np.isfinite(np.asarray(chunk[f"mcal_r{i}{j}"], dtype=float))
    if plan.failures_select:
        rows.version_pre = {
            (i, kind): np.asarray(chunk[f"pre_g{i}_{kind}"], dtype=float)
            for i in (1, 2)
            for kind in SHEARED_TYPES
        }
    rows.sheared_weight = {}
    for kind in SHEARED_TYPES:
        sel = usable.copy()
        if plan.failures_select:
            sel &= np.asarray(chunk[f"flags_{kind}"]) == 0
        if plan.select is not None:
            sel &= _expr.evaluate_rows(plan.select, _version_view(chunk, plan, kind), n)
        for s in plan.schemes:
            if s == "unweighted" and not _unweighted_selection(plan):
                continue
            for i in (1, 2):
                w = np.asarray(chunk[f"pre_g{i}_w_{kind}"], dtype=float) if s == "weighted" else 1.0
                ok = sel & np.isfinite(w) & (w > 0)
                if plan.failures_select:  # the version's own estimate is averaged
                    ok &= np.isfinite(rows.version_pre[(i, kind)])
                rows.sheared_weight.setdefault(s, {})[(i, kind)] = np.where(ok, w, 0.0)


def _unweighted_selection(plan: _Plan, binned: bool = True) -> bool:
    """Whether the unweighted scheme has a selection whose response the sheared versions give:
    ``select``, the failures (``failures_select``) or, for ``binned`` sums, ``--by`` bins."""
    return plan.select is not None or plan.failures_select or (binned and plan.binned_selection)


def _case_group_key(case: np.ndarray, rea: np.ndarray, group_size: int, source: str) -> np.ndarray:
    """One integer per (case, galaxy group): ``case << 32 | rea // group_size``."""
    rea = np.asarray(rea)
    if rea.dtype.kind not in "iu":
        if rea.dtype.kind == "f" and np.all(np.isfinite(rea)) and np.all(rea == np.round(rea)):
            rea = rea.astype(np.int64)
        else:
            raise InputError(f"{source}: column 'rea' must hold integer realization indices")
    if rea.size and (rea.min() < 0 or rea.max() >= 2**_GROUP_BITS):
        raise InputError(f"{source}: column 'rea' must hold realization indices in [0, 2^32)")
    if case.size and np.max(np.abs(case)) >= 2**30:
        raise InputError(f"{source}: case ids beyond 2^30 cannot be bootstrapped")
    group = rea.astype(np.int64) // group_size
    return (case.astype(np.int64) << _GROUP_BITS) | group


def _split_key(key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(case, group)`` of the keys of :func:`_case_group_key`."""
    key = np.asarray(key, dtype=np.int64)
    return key >> _GROUP_BITS, key & (2**_GROUP_BITS - 1)


# --------------------------------------------------------------------------- group sums


class _GroupSums:
    """Sums of row quantities per (bin, case), accumulated over chunks."""

    def __init__(self, names: Sequence[str]):
        self.names = list(names)
        self._bins: list[np.ndarray] = []
        self._cases: list[np.ndarray] = []
        self._sums: list[np.ndarray] = []

    def add(
        self,
        case: np.ndarray,
        values: Mapping[str, np.ndarray],
        bin_idx: np.ndarray | None = None,
        name_bins: Mapping[str, np.ndarray] | None = None,
    ) -> None:
        """Add the rows' ``values`` to the sums of their (bin, case); ``name_bins`` gives some
        names their own bin of each row (a metacal version's bin, for the selection response)."""
        if name_bins:
            by_bins: dict[int, tuple[np.ndarray, list[str]]] = {}
            for name in self.names:
                b = name_bins.get(name, bin_idx)
                by_bins.setdefault(id(b), (b, []))[1].append(name)
            for b, names in by_bins.values():
                zeros = np.zeros(case.size)
                self.add(case, {k: values[k] if k in names else zeros for k in self.names}, b)
            return
        if bin_idx is not None:
            keep = bin_idx >= 0
            case, bin_idx = case[keep], bin_idx[keep]
            values = {k: v[keep] for k, v in values.items()}
        else:
            bin_idx = np.zeros(case.size, dtype=np.int64)
        if case.size == 0:
            return
        ids, inv = np.unique(case, return_inverse=True)
        key = bin_idx * ids.size + inv.ravel()
        size = int(bin_idx.max() + 1) * ids.size
        present = np.flatnonzero(np.bincount(key, minlength=size))
        self._bins.append(present // ids.size)
        self._cases.append(ids[present % ids.size])
        self._sums.append(
            np.stack(
                [np.bincount(key, weights=values[k], minlength=size)[present] for k in self.names]
            )
        )

    def result(self) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """``(bins, cases, {name: sums})`` with one entry per (bin, case) present."""
        if not self._cases:
            empty = np.zeros(0)
            return (
                np.zeros(0, dtype=np.int64),
                np.zeros(0, dtype=np.int64),
                {k: empty for k in self.names},
            )
        bins = np.concatenate(self._bins)
        cases = np.concatenate(self._cases)
        sums = np.concatenate(self._sums, axis=1)
        ids, cinv = np.unique(cases, return_inverse=True)
        keys, inv = np.unique(bins * ids.size + cinv.ravel(), return_inverse=True)
        inv = inv.ravel()
        out = {
            k: np.bincount(inv, weights=sums[i], minlength=keys.size)
            for i, k in enumerate(self.names)
        }
        return keys // ids.size, ids[keys % ids.size], out


def _sum_names(
    schemes: Sequence[str], plan: _Plan | None = None, binned: bool = False
) -> list[str]:
    """Names of the per-(bin, case) sums; ``binned``: of ``--by`` bins (their selection)."""
    names = []
    for s in schemes:
        for comp in ("g1", "g2"):
            names += [f"{s}:w:{comp}", f"{s}:wpre:{comp}", f"{s}:wtru:{comp}", f"{s}:n:{comp}"]
        names.append(f"{s}:n:both")
        if plan is not None and plan.metacal is not None:
            names += [f"{s}:wR:{i}{j}" for i in (1, 2) for j in (1, 2)]
            if s == "weighted" or _unweighted_selection(plan, binned):
                names += [
                    f"{s}:{q}:{i}:{kind}"
                    for q in (("vw", "vwpre") if plan.failures_select else ("sw", "swpre"))
                    for i in (1, 2)
                    for kind in SHEARED_TYPES
                ]
    return names


def _row_values(rows: _Rows, schemes: Sequence[str]) -> dict[str, np.ndarray]:
    vals: dict[str, np.ndarray] = {}
    for s in schemes:
        weight = {comp: rows.weight[(s, comp)] for comp in ("g1", "g2")}
        sheared = (rows.sheared_weight or {}).get(s)
        vals.update(
            row_values(
                s,
                weight,
                rows.tru,
                rows.pre,
                rows.response,
                sheared,
                rows.pre_noshear,
                rows.step,
                rows.version_pre,
            )
        )
    return vals


# --------------------------------------------------------------------------- fits


def _fit_components(per_case: Mapping[str, Mapping[str, np.ndarray]]) -> dict[str, BiasFit]:
    fits = {}
    for comp, d in per_case.items():
        use = np.isfinite(d["pre"]) & np.isfinite(d["tru"])
        fits[comp] = fit_bias(d["tru"][use], d["pre"][use], n_rows=int(d["n_rows"][use].sum()))
    return fits


def _spread(x: np.ndarray) -> bool:
    x = x[np.isfinite(x)]
    return x.size > 1 and np.ptp(x) > 1e-12 + 1e-9 * float(np.max(np.abs(x)))


def _json_list(a: np.ndarray) -> list[Any]:
    return [
        None
        if not math.isfinite(v)
        else (int(v) if float(v).is_integer() and abs(v) < 2**53 else float(v))
        for v in np.asarray(a, dtype=float)
    ]


# --------------------------------------------------------------------------- main entry


def _iter_path(
    path: str | os.PathLike, plan: _Plan, chunk_rows: int
) -> Iterator[Mapping[str, np.ndarray]]:
    for table in iter_catalog(path, chunk_rows, plan.columns):
        yield {c: np.asarray(table[c]) for c in plan.columns}


def evaluate_catalog(
    path: str | os.PathLike,
    *,
    by: Sequence[str] | None = None,
    bins: int = 5,
    select: str | None = None,
    select_cases: str | None = None,
    chunk_rows: int = CHUNK_ROWS,
    sigma2_min: float = GREAT3_SIGMA2_MIN_GROUND,
    errors: str = "auto",
    n_bootstrap: int = N_BOOTSTRAP,
    seed: int = 1,
    names: Mapping[str, str] | None = None,
    response: str = "auto",
    failures: str = "exclude",
) -> dict[str, Any]:
    """Evaluate the shear biases of the catalog at ``path``; returns a JSON-ready dict.

    ``by``: columns for conditional biases in ``bins`` equal-population bins; ``select``:
    row selection expression (:func:`megalut_cli.expr.evaluate_rows`); ``select_cases``:
    case selection on per-case aggregates (:func:`megalut_cli.expr.evaluate_cases`),
    e.g. ``"mean(snr) > 10"`` as in paper Fig. 12; ``sigma2_min``: the ``Q_c`` damping
    term (4 ground, 1 space). ``errors``: ``"auto"`` (a bootstrap over galaxies when the
    header says ``CRN = T``, else from the fit), ``"fit"`` or ``"bootstrap"``; the galaxy
    groups follow the header's ``SNC`` (pairs: 2 realizations). ``response`` (metacal
    catalogs): ``"auto"`` (at zero shear when the header says ``CRN = T``), ``"mean"`` or
    ``"zero-shear"``, and ``failures``, see :func:`evaluate_columns`. ``names``: how
    messages name the arguments (``by``, ``select``, ``select_cases``, ``errors``,
    ``response``, ``failures``), e.g. as command-line flags or pipeline keys.
    """
    _, colnames, header = catalog_info(path)
    plan = _make_plan(
        colnames,
        str(path),
        by,
        select,
        select_cases,
        bootstrap_from_header(header, errors, n_bootstrap, seed),
        names,
        header_step(header),
        response,
        header.get("CRN") is True,
        failures,
    )
    _prepare_cases(plan, lambda cols: _read_columns(path, cols))
    result = _evaluate(lambda: _iter_path(path, plan, chunk_rows), plan, bins, sigma2_min)
    result["input"] = str(path)
    result["provenance"] = evaluation_provenance(path)
    return result


def m_too_large(m: float | None, m_err: float | None) -> bool:
    """Whether ``|m| > WARN_M`` by more than its 1-sigma error ``m_err`` (or, without an
    error, at all): the multiplicative bias of an untrained or mismatched model."""
    if m is None or not math.isfinite(m):
        return False
    margin = m_err if m_err is not None and math.isfinite(m_err) else 0.0
    return abs(m) - margin > WARN_M


def large_m(result: Mapping[str, Any]) -> list[str]:
    """The fits of ``result`` where :func:`m_too_large`, as
    ``"unweighted g1: m = -0.53 ± 0.01"``."""
    out = []
    for scheme in ("unweighted", "weighted"):
        for comp, fit in (result.get(scheme) or {}).items():
            if m_too_large(fit.get("m"), fit.get("m_err")):
                err = f" ± {fit['m_err']:.2f}" if fit.get("m_err") is not None else ""
                out.append(f"{scheme} {comp}: m = {fit['m']:+.2f}{err}")
    return out


#: Cases below which the fit gives no errors (its residual scatter has N - 2 degrees of freedom).
MIN_CASES_FOR_ERRORS = 3


def _no_errors(fit: Mapping[str, Any]) -> bool:
    return fit.get("m") is not None and (fit.get("m_err") is None or fit.get("c_err") is None)


def errors_na_note(result: Mapping[str, Any]) -> str | None:
    """One line saying why some errors of ``result`` are ``n/a`` (None when none is): too
    few cases for the fit's residual scatter, or a bootstrap whose resamples too often
    leave a fit undefined."""
    schemes = [s for s in ("unweighted", "weighted") if s in result]
    overall = [f for s in schemes for f in (result.get(s) or {}).values() if _no_errors(f)]
    binned = [
        b[s][comp]
        for cond in (result.get("conditional") or {}).values()
        for b in cond.get("bins", [])
        for s in schemes
        if s in b
        for comp in b[s]
        if _no_errors(b[s][comp])
    ]
    fits = overall or binned
    if not fits:
        return None
    where = "" if overall else " (conditional bins)"
    n = min(int(f.get("n_cases") or 0) for f in fits)
    have = "the catalog has" if overall else "a bin has"
    boot = result.get("bootstrap")
    if result.get("error") == ERROR_BOOTSTRAP and boot:
        return (
            f"errors n/a{where}: the bootstrap over {boot['groups']} galaxy groups leaves the fit "
            "undefined in more than half of its resamples (a fit needs at least 2 cases with "
            f"different true shears; {have} {n})"
        )
    return (
        f"errors n/a{where}: errors from the fit need at least {MIN_CASES_FOR_ERRORS} cases "
        "(the residual scatter about the line has N - 2 degrees of freedom); "
        f"{have} {n} usable case{'s' * (n != 1)}"
    )


def evaluation_provenance(path: str | os.PathLike) -> dict[str, Any]:
    """Provenance of an evaluation of ``path``: this run (creator, date, command, versions)
    and its input (sha256; for a megalut catalog its format, date, model and config hashes
    and the HISTORY of the steps that made it)."""
    source: dict[str, Any] = {"path": str(path), "sha256": sha256_file(path)}
    if is_fits_file(path):
        header = catalog_info(path)[2]
        for key, card in (
            ("format", "MLFORMAT"),
            ("created", "DATE"),
            ("creator", "CREATOR"),
            ("model", "MODEL"),
            ("model_sha256", "MODELSHA"),
            ("config_sha256", "CFGSHA"),
        ):
            source[key] = header.get(card)
        source["history"] = history_steps(header.get("HISTORY", []))
    return {
        "creator": CREATOR,
        "created": utc_now(),
        "command": command_line(),
        "versions": software_versions(),
        "input": source,
    }


def evaluate_columns(
    columns: Mapping[str, np.ndarray],
    *,
    by: Sequence[str] | None = None,
    bins: int = 5,
    select: str | None = None,
    select_cases: str | None = None,
    source: str = "catalog",
    sigma2_min: float = GREAT3_SIGMA2_MIN_GROUND,
    bootstrap: BootstrapSpec | None = None,
    names: Mapping[str, str] | None = None,
    metacal_step: float | None = None,
    response: str = "auto",
    crn: bool = False,
    failures: str = "exclude",
) -> dict[str, Any]:
    """Evaluate in-memory columns (a dict of arrays or an astropy Table), as
    :func:`evaluate_catalog`.

    The result holds, for ``"unweighted"`` and (with weight columns) ``"weighted"``, a
    dict per component (``g1, g2`` and ``plus, cross`` with PSF columns) with ``m, m_err,
    c, c_err, n_cases, n_rows``; ``"conditional"`` when ``by`` is given; ``"requirement"``
    (Stage IV check), ``"q_c"`` (GREAT3 metric), ``"per_case"`` averages and row counts;
    ``"error"`` says where the errors come from: ``"fit"``, or ``"bootstrap-galaxies"`` with
    ``bootstrap`` given (then ``"bootstrap"`` holds its settings; needs the ``rea`` column).

    A metacal catalog (``megalut predict`` on ``measure --metacal`` features: columns
    ``mcal_r11 .. mcal_r22``) is evaluated on ``pre_g*_noshear`` calibrated by the
    response of the rows used plus the selection response of ``select`` and the weights
    (each computed on the sheared versions; ``metacal_step``, default 0.01, is the catalog's
    ``MCALSTEP``): with ``response="mean"`` their mean over all the cases, with
    ``"zero-shear"`` the response at zero shear, the intercept of a fit of each case's own
    response against its true shear (:func:`megalut_cli.shear.response.calibration_response`;
    at least 10 cases), ``"auto"``: zero-shear for a common-random-number set (``crn``) with
    enough cases, else the mean. ``failures``: ``"exclude"`` uses the rows with every
    version measured; ``"selection"`` every row whose noshear version is measured, and the
    response of the versions' means instead, each sheared version's own estimates over its
    own measured rows (selection and failures included, as metadetection takes it).
    ``"metacal"`` then holds the responses, which one calibrated and ``"failures"``.
    """
    colnames = list(columns.colnames) if hasattr(columns, "colnames") else list(columns)
    plan = _make_plan(
        colnames,
        source,
        by,
        select,
        select_cases,
        bootstrap,
        names,
        metacal_step,
        response,
        crn,
        failures,
    )
    data = {c: np.asarray(columns[c]) for c in plan.columns}
    _prepare_cases(plan, lambda cols: {c: np.asarray(columns[c]) for c in cols})
    result = _evaluate(lambda: iter([data]), plan, bins, sigma2_min)
    result["input"] = source
    return result


def bootstrap_from_header(
    header: Mapping[str, Any], errors: str = "auto", n_bootstrap: int = N_BOOTSTRAP, seed: int = 1
) -> BootstrapSpec | None:
    """The bootstrap of a catalog with this header under ``errors`` (``auto``: only for
    common-random-number sets, ``CRN = T``), or None for errors from the fit."""
    if errors not in ERROR_CHOICES:
        raise ConfigError(
            f"errors: unknown value {errors!r} (expected one of {', '.join(ERROR_CHOICES)})"
        )
    crn = header.get("CRN") is True
    if errors == "fit" or (errors == "auto" and not crn):
        if crn:
            log.warning(
                "the input is a common-random-number set (CRN = T): errors from the fit ignore "
                "that its cases share their galaxies and are too small"
            )
        return None
    nrea = header.get("NREA")
    gsize = group_size_for(
        header.get("SNC"), nrea if isinstance(nrea, int) else None, header.get("ANTITHET") is True
    )
    return BootstrapSpec(gsize, int(n_bootstrap), int(seed), crn)


def _read_columns(path: str | os.PathLike, columns: list[str]) -> dict[str, np.ndarray]:
    t = read_catalog(path, columns=columns)
    return {c: np.asarray(t[c]) for c in t.colnames}


def _prepare_cases(plan: _Plan, read: Callable[[list[str]], Mapping[str, np.ndarray]]) -> None:
    """Per-case aggregates, over all rows of each case: the cases kept by ``select_cases``
    and the values of the per-case ``by`` expressions. ``read(columns)`` returns whole columns."""
    case_by = [c for c in plan.by if plan.by_kind.get(c) == "case"]
    exprs = ([plan.select_cases] if plan.select_cases is not None else []) + case_by
    if not exprs:
        return
    cols = read(list(dict.fromkeys(["case", *(c for e in exprs for c in _expr.columns_used(e))])))
    case = np.asarray(cols["case"])
    if plan.select_cases is not None:
        ids, mask = _expr.evaluate_cases(plan.select_cases, cols, case)
        plan.selected_cases = ids[mask]
    for c in case_by:
        plan.case_by[c] = _expr.evaluate_case_values(c, cols, case)


def _by_values(
    chunk: Mapping[str, np.ndarray], plan: _Plan, c: str, n: int, version: str = "noshear"
) -> np.ndarray:
    """Values of the ``by`` entry ``c`` on the rows of ``chunk`` (a case's value for per-case
    entries), as the metacal ``version`` sees them."""
    kind = plan.by_kind.get(c, "column")
    chunk = _version_view(chunk, plan, version)
    if kind == "column":
        return np.asarray(chunk[c], dtype=float)
    if kind == "row":
        return _expr.evaluate_row_values(c, chunk, n)
    ids, values = plan.case_by[c]
    if ids.size == 0:
        return np.full(n, np.nan)
    case = np.asarray(chunk["case"])
    pos = np.clip(np.searchsorted(ids, case), 0, ids.size - 1)
    return np.where(ids[pos] == case, values[pos], np.nan)


def _sheared_bins(
    chunk: Mapping[str, np.ndarray],
    plan: _Plan,
    c: str,
    n: int,
    edges: np.ndarray,
    names: Sequence[str],
) -> dict[str, np.ndarray] | None:
    """The bins of the rows under each sheared version's values of the ``by`` entry ``c``,
    for the sums of that version's selection (metacal, per-row entries only)."""
    if not plan.binned_selection or plan.by_kind.get(c) == "case":
        return None
    bins = {kind: assign_bins(_by_values(chunk, plan, c, n, kind), edges) for kind in SHEARED_TYPES}
    per_version = {"sw", "swpre", "vw", "vwpre"}  # each version's selection or mean
    return {
        name: bins[name.rsplit(":", 1)[1]] for name in names if name.split(":")[1] in per_version
    }


def _evaluate(
    chunks: Any, plan: _Plan, n_bins: int, sigma2_min: float = GREAT3_SIGMA2_MIN_GROUND
) -> dict[str, Any]:
    """Two passes over ``chunks()`` when ``plan.by`` (bin edges first), else one."""
    schemes = plan.schemes
    # Pass 1 (conditional biases only): values of the 'by' columns on the rows used.
    edges: dict[str, np.ndarray] = {}
    by_values: dict[str, list[np.ndarray]] = {c: [] for c in plan.by}
    if plan.by:
        for chunk in chunks():
            rows = _rows(chunk, plan)
            used = rows.valid["g1"] | rows.valid["g2"]
            for c in plan.by:
                by_values[c].append(_by_values(chunk, plan, c, rows.case.size)[used])
        for c in plan.by:
            vals = np.concatenate(by_values[c]) if by_values[c] else np.zeros(0)
            if vals.size:
                edges[c] = equal_population_edges(vals, n_bins, c, plan.name("by"))
                by_values[c] = [vals]

    # Pass 2: per-(bin, case) sums.
    names = _sum_names(schemes, plan)
    overall = _GroupSums(names)
    conditional = {c: _GroupSums(_sum_names(schemes, plan, binned=True)) for c in edges}
    psf_sums = _GroupSums(["psf1", "psf2", "npsf"]) if plan.psf else None
    n_total = n_selected = n_valid = 0
    for chunk in chunks():
        rows = _rows(chunk, plan)
        n_total += rows.case.size
        n_selected += int(rows.selected.sum())
        n_valid += int((rows.valid["g1"] | rows.valid["g2"]).sum())
        vals = _row_values(rows, schemes)
        overall.add(rows.key, vals)
        for c, g in conditional.items():
            n = rows.case.size
            g.add(
                rows.key,
                vals,
                assign_bins(_by_values(chunk, plan, c, n), edges[c]),
                _sheared_bins(chunk, plan, c, n, edges[c], g.names),
            )
        if psf_sums is not None and rows.psf is not None:
            ok = np.isfinite(rows.psf[0]) & np.isfinite(rows.psf[1])
            psf_sums.add(
                rows.case,
                {
                    "psf1": np.where(ok, rows.psf[0], 0.0),
                    "psf2": np.where(ok, rows.psf[1], 0.0),
                    "npsf": ok.astype(float),
                },
            )

    _check_usable(plan, n_total, n_selected, n_valid)
    bins0, keys, key_sums = overall.result()
    groups: _Groups | None = None
    if plan.bootstrap is not None:
        _, case_ids, sums, groups = _collapse(bins0, keys, key_sums)
    else:
        case_ids, sums = keys, key_sums

    theta_of: dict[int, float] = {}
    theta = None
    psf_round = False
    if psf_sums is not None:
        _, pcases, psums = psf_sums.result()
        with np.errstate(invalid="ignore", divide="ignore"):
            th = psf_angle(psums["psf1"] / psums["npsf"], psums["psf2"] / psums["npsf"])
        theta_of = dict(zip(pcases.tolist(), th.tolist()))
        theta = np.array([theta_of.get(int(k), np.nan) for k in case_ids])
        psf_round = bool(np.all((psums["psf1"] == 0) & (psums["psf2"] == 0)))
        if psf_round:
            log.info("the PSF is round in every case: the PSF frame is the pixel frame")

    shears = None  # the cases' true shears, where they set the metacal response
    if plan.metacal is not None:
        shears = case_shears(case_estimates(sums, schemes[0]))
        plan.zero_shear = _zero_shear_decision(plan, shears)
    per_case = {s: case_estimates(sums, s, theta, plan.zero_shear) for s in schemes}
    _check_cases(plan, per_case["unweighted"], case_ids)
    if (
        plan.weighted
        and not np.any(sums["weighted:w:g1"] > 0)
        and not np.any(sums["weighted:w:g2"] > 0)
    ):
        raise InputError(
            f"{plan.source}: the weights {', '.join(WEIGHT_COLUMNS)} are zero on every usable row"
        )

    result: dict[str, Any] = {
        "format": JSON_FORMAT,
        "format_version": JSON_FORMAT_VERSION,
        "input": plan.source,
        "n_rows": n_total,
        "n_selected": n_selected,
        "n_valid": n_valid,
        "select": plan.select,
        "select_cases": plan.select_cases,
        "psf_frame": {"columns": list(plan.psf), "round": psf_round} if plan.psf else None,
        "weights": list(WEIGHT_COLUMNS) if plan.weighted else None,
    }
    if plan.metacal is not None:
        result["metacal"] = {
            "step": plan.metacal,
            "failures": plan.failures,
            "estimate": [f"{c}_noshear" for c in ESTIMATE_COLUMNS],
            **_metacal_summary(sums, schemes, shears if plan.zero_shear else None),
        }
    fits = {s: _fit_components(per_case[s]) for s in schemes}
    families: list[_Family] = []
    if groups is not None:
        families.append(
            _Family(
                fits,
                groups.resampler(
                    np.ones(groups.key_index.size, dtype=bool), case_ids.size, key_sums
                ),
                theta,
            )
        )
    cond_out: dict[str, Any] = {}
    for c in plan.by:
        if c not in edges:
            log.warning("%s %s: no usable row has a value", plan.name("by"), c)
            cond_out[c] = {"edges": [], "bins": []}
            continue
        cond_out[c] = _conditional(
            conditional[c],
            edges[c],
            by_values[c][0],
            schemes,
            theta_of,
            families if groups is not None else None,
            groups,
            plan.zero_shear,
        )
    result.update(_bootstrap_errors(families, plan, groups, schemes))
    for s in schemes:
        result[s] = {comp: fits[s][comp].as_dict() for comp in COMPONENTS if comp in fits[s]}
        for comp, f in fits[s].items():
            if not math.isfinite(f.m):
                log.warning(
                    "%s %s: m and c undetermined (%d case(s) with usable rows, or no spread in the "
                    "true shear)",
                    s,
                    comp,
                    f.n_cases,
                )
    result["requirement"] = _requirement(fits, schemes)
    frame = ("plus", "cross") if plan.psf else ("g1", "g2")
    result["q_c"] = {
        "frame": "psf" if plan.psf else "pixel",
        "sigma2_min": float(sigma2_min),
        **{
            s: _json_q(
                q_c(
                    fits[s][frame[0]].m,
                    fits[s][frame[0]].c,
                    fits[s][frame[1]].m,
                    fits[s][frame[1]].c,
                    sigma2_min=sigma2_min,
                )
            )
            for s in schemes
        },
    }
    for cond in cond_out.values():
        for entry in cond["bins"]:
            for scheme in schemes:
                entry[scheme] = {
                    comp: f.as_dict() for comp, f in entry[scheme].items() if comp in COMPONENTS
                }
    if plan.by:
        result["conditional"] = cond_out
    result["per_case"] = {
        "case": [int(k) for k in case_ids],
        **({"psf_theta": _json_list(theta)} if theta is not None else {}),
        **{
            s: {comp: {k: _json_list(v) for k, v in d.items()} for comp, d in per_case[s].items()}
            for s in schemes
        },
    }
    return result


def _metacal_summary(
    sums: Mapping[str, np.ndarray], schemes: Sequence[str], shears: np.ndarray | None = None
) -> dict[str, Any]:
    """The responses of the cases behind ``sums`` per scheme: the mean and selection
    responses over all the cases, the response that calibrates them (at zero shear with the
    cases' true ``shears`` where they determine it) and how it was taken (``response_at``:
    ``"mean"`` or ``"zero-shear"``, :func:`calibration_response`)."""
    out: dict[str, Any] = {
        "response": {},
        "selection_response": {},
        "calibration_response": {},
        "response_at": RESPONSE_MEAN,
    }
    for s in schemes:
        mean, selection = metacal_response(sums, s)
        out["response"][s] = [_json_list(row) for row in mean]
        out["selection_response"][s] = (
            None if selection is None else [_json_list(row) for row in selection]
        )
        r, how = calibration_response(sums, s, shears)
        out["calibration_response"][s] = [_json_list(row) for row in r]
        out["response_at"] = how
    return out


def _zero_shear_decision(plan: _Plan, shears: np.ndarray) -> bool:
    """Whether a metacal set is calibrated at zero shear (``plan.response``; ``auto``: a
    common-random-number set whose cases' true ``shears`` determine the fit); says which in
    the log."""
    wanted = plan.response == RESPONSE_ZERO_SHEAR or (plan.response == "auto" and plan.crn)
    if not wanted:
        log.info("metacal: the cases are calibrated by their mean response")
        return False
    if zero_shear_weights(shears) is None:
        why = (
            f"the response at zero shear needs at least {MIN_ZERO_SHEAR_CASES} cases with "
            f"usable rows and shears that spread in g1 and g2 (found "
            f"{int(np.all(np.isfinite(shears), axis=1).sum())} cases)"
        )
        if plan.response == RESPONSE_ZERO_SHEAR:
            raise InputError(f"{plan.source}: {plan.name('response')} {plan.response}: {why}")
        log.info("metacal: %s; the cases are calibrated by their mean response", why)
        return False
    log.info(
        "metacal: the cases are calibrated by the response at zero shear (a fit of each "
        "case's response against its true shear)"
    )
    return True


@dataclass
class _Groups:
    """(key, galaxy group) entries behind per-key sums: entry ``e`` belongs to key
    ``key_index[e]`` and group ``group[e]``."""

    key_index: np.ndarray
    group: np.ndarray
    n_groups: int

    def resampler(
        self, entries: np.ndarray, n_keys: int, sums: Mapping[str, np.ndarray]
    ) -> GroupResampler:
        """A resampler of the selected ``entries`` (bool mask), keys renumbered in order."""
        keys = np.unique(self.key_index[entries])
        index = np.searchsorted(keys, self.key_index[entries])
        values = {k: v[entries] for k, v in sums.items() if ":n:" not in k}
        return GroupResampler(index, self.group[entries], values, n_keys, self.n_groups)


@dataclass
class _Family:
    """Fits sharing one set of per-key sums (the overall fit, or one bin of a ``--by``)."""

    fits: dict[
        str, dict[str, BiasFit]
    ]  # scheme -> component -> fit; errors replaced by the bootstrap
    resampler: GroupResampler
    theta: np.ndarray | None


def _collapse(
    bins: np.ndarray, keys: np.ndarray, sums: Mapping[str, np.ndarray], n_groups: int | None = None
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray], _Groups]:
    """Per-(bin, case) sums from per-(bin, case, group) sums; returns the bins and cases
    of the collapsed keys, their sums and the entries behind them."""
    case, group = _split_key(keys)
    pairs, inv = np.unique(np.stack([bins, case], axis=1), axis=0, return_inverse=True)
    inv = inv.ravel()
    collapsed = {k: np.bincount(inv, weights=v, minlength=len(pairs)) for k, v in sums.items()}
    n = int(group.max()) + 1 if n_groups is None and group.size else int(n_groups or 0)
    return pairs[:, 0], pairs[:, 1], collapsed, _Groups(inv, group, n)


def _bootstrap_errors(
    families: list[_Family], plan: _Plan, groups: _Groups | None, schemes: Sequence[str]
) -> dict[str, Any]:
    """Replace the errors of every family's fits by the bootstrap spread; return the
    ``error`` and ``bootstrap`` entries of the result."""
    spec = plan.bootstrap
    if spec is None or groups is None:
        return {"error": ERROR_FIT, "bootstrap": None}
    n_groups = groups.n_groups
    if n_groups < 2:
        raise InputError(
            f"{plan.source}: the bootstrap over galaxies needs at least 2 galaxy groups, "
            f"found {n_groups} (group size {spec.group_size}); use {plan.name('errors')} fit"
        )
    if n_groups < FEW_GROUPS:
        log.warning("only %d galaxy groups: the bootstrap errors are rough", n_groups)
    acc: list[dict[tuple[str, str], tuple[list[np.ndarray], list[np.ndarray], ResidualMoments]]]
    acc = [
        {(s, comp): ([], [], ResidualMoments()) for s in schemes for comp in f.fits[s]}
        for f in families
    ]

    def estimates(fam: _Family, counts: np.ndarray, s: str) -> dict[str, dict[str, np.ndarray]]:
        zeros = np.zeros((fam.resampler.n_keys, counts.shape[1]))
        sums = {**{k: zeros for k in _sum_names(schemes)}, **fam.resampler.sums(counts)}
        theta = fam.theta[:, None] if fam.theta is not None else None
        return case_estimates(sums, s, theta, plan.zero_shear)

    for counts in resample_counts(spec.seed, n_groups, spec.n_resamples):
        for fam, values in zip(families, acc):
            for s in schemes:
                for comp, d in estimates(fam, counts, s).items():
                    m, c = fit_columns(d["tru"], d["pre"])
                    values[(s, comp)][0].append(m)
                    values[(s, comp)][1].append(c)
                    values[(s, comp)][2].add(residuals(d["tru"], d["pre"], m, c))
    everything = np.ones((n_groups, 1))  # the catalog itself: every group once
    for fam, values in zip(families, acc):
        full = {s: estimates(fam, everything, s) for s in schemes}
        for (s, comp), (m, c, moments) in values.items():
            f = fam.fits[s][comp]
            m_gal = spread(np.concatenate(m)) if math.isfinite(f.m) else f.m_err
            c_gal = spread(np.concatenate(c)) if math.isfinite(f.c) else f.c_err
            d = full[s][comp]
            var_m, var_c = (
                shear_draw_variance(d["tru"][:, 0], d["pre"][:, 0], f.m, f.c, moments.variance())
                if spec.crn  # independent cases: each case's residual is its own galaxies'
                else (math.nan, math.nan)
            )
            m_shear, c_shear = math.sqrt(var_m), math.sqrt(var_c)  # NaN: not estimable
            fam.fits[s][comp] = replace(
                f,
                m_err=math.hypot(m_gal, m_shear) if math.isfinite(m_shear) else m_gal,
                c_err=math.hypot(c_gal, c_shear) if math.isfinite(c_shear) else c_gal,
                error_parts=(m_gal, m_shear, c_gal, c_shear),
            )
    return {
        "error": ERROR_BOOTSTRAP,
        "bootstrap": {
            "resamples": spec.n_resamples,
            "seed": spec.seed,
            "group_size": spec.group_size,
            "groups": n_groups,
            "crn": spec.crn,
            "shear_term": SHEAR_TERM if spec.crn else None,
        },
    }


def _json_q(q: float) -> float | None:
    return q if math.isfinite(q) else None


def _check_usable(plan: _Plan, n_total: int, n_selected: int, n_valid: int) -> None:
    if n_total == 0:
        raise InputError(f"{plan.source}: the catalog has no rows")
    if n_selected == 0:
        what = " and ".join(
            f"{plan.name(o)} {e!r}"
            for o, e in (("select", plan.select), ("select_cases", plan.select_cases))
            if e is not None
        )
        raise InputError(f"{plan.source}: no row passes {what}")
    if n_valid == 0:
        raise InputError(
            f"{plan.source}: all {n_selected} rows failed (flags != 0 or NaN estimates); "
            "nothing to evaluate"
        )


def _check_cases(
    plan: _Plan, per_case: Mapping[str, Mapping[str, np.ndarray]], case_ids: np.ndarray
) -> None:
    usable = np.isfinite(per_case["g1"]["pre"]) | np.isfinite(per_case["g2"]["pre"])
    if usable.sum() < 2:
        which = f" (case {int(case_ids[usable][0])})" if usable.any() else ""
        raise InputError(
            f"{plan.source}: only one case{which} has usable rows; m and c need several cases "
            "with different true shears"
        )
    if not (_spread(per_case["g1"]["tru"]) or _spread(per_case["g2"]["tru"])):
        g1 = np.nanmean(per_case["g1"]["tru"])
        g2 = np.nanmean(per_case["g2"]["tru"])
        raise InputError(
            f"{plan.source}: the true shear is the same in every case "
            f"(tru_g1={g1:g}, tru_g2={g2:g}); no lever arm to fit m"
        )


def _requirement(
    fits: Mapping[str, Mapping[str, BiasFit]], schemes: Sequence[str]
) -> dict[str, Any]:
    scheme = schemes[-1]  # weighted when present
    return stage_iv_requirement({comp: (f.m, f.c) for comp, f in fits[scheme].items()}, scheme)


def _conditional(
    sums: _GroupSums,
    edges: np.ndarray,
    values: np.ndarray,
    schemes: Sequence[str],
    theta_of: Mapping[int, float],
    families: list[_Family] | None = None,
    overall: _Groups | None = None,
    zero_shear: bool = False,
) -> dict[str, Any]:
    """Fits per bin (``BiasFit`` objects, turned into dicts by the caller once the bootstrap,
    when ``families`` is given, has set their errors); metacal bins calibrated at zero shear
    with ``zero_shear`` where the bin's cases determine it, else by the bin's mean."""
    bins, keys, key_sums = sums.result()
    groups = None
    if overall is not None:
        bins, cases, s, groups = _collapse(bins, keys, key_sums, overall.n_groups)
    else:
        cases, s = keys, key_sums
    value_bin = assign_bins(values, edges)
    out_bins = []
    for k in range(edges.size - 1):
        sel = bins == k
        sub = {name: v[sel] for name, v in s.items()}
        theta = np.array([theta_of.get(int(c), np.nan) for c in cases[sel]]) if theta_of else None
        in_bin = values[value_bin == k]
        entry: dict[str, Any] = {
            "lo": float(edges[k]),
            "hi": float(edges[k + 1]),
            "center": float(np.median(in_bin)) if in_bin.size else None,
            "n_rows": int(in_bin.size),
        }
        per_case = {scheme: case_estimates(sub, scheme, theta, zero_shear) for scheme in schemes}
        fits = {scheme: _fit_components(per_case[scheme]) for scheme in schemes}
        for scheme in schemes:
            entry[scheme] = fits[scheme]
        if f"{schemes[0]}:wR:11" in sub:  # metacal: this bin's responses
            shears = case_shears(per_case[schemes[0]]) if zero_shear else None
            entry["metacal"] = _metacal_summary(sub, schemes, shears)
        if families is not None and groups is not None:
            families.append(
                _Family(
                    fits, groups.resampler(sel[groups.key_index], int(sel.sum()), key_sums), theta
                )
            )
        out_bins.append(entry)
    return {"edges": [float(e) for e in edges], "bins": out_bins}


# --------------------------------------------------------------------------- reporting


def requirement_met(result: Mapping[str, Any]) -> bool:
    """Whether the Stage IV requirement holds (weighted results when present, else unweighted)."""
    return bool(result["requirement"]["met"])
