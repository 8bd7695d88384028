"""Training data structured in cases and realizations (paper Sect. 3.2).

A catalog has one row per realization and a ``case`` column. :func:`build_cases` groups it
by case, drops masked realizations (flags set, non-finite features, rows outside a
selection) and keeps, per case, one target value. The result, :class:`CaseData`, stores the
valid realizations compactly (rows grouped by case) so that memory follows the number of
valid rows and not ``n_cases x max_realizations``; :meth:`CaseData.padded` gives the
``(n_cases, n_rea_max, n_features)`` array + mask view of the same data, and
:meth:`CaseData.from_padded` builds one from such arrays.

Decision on cases without any valid realization: they are dropped when other cases remain
(a warning when all their rows are flagged or non-finite, an info line when a selection
removed them); an error is raised when none (or fewer than two) remain.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from megalut_cli.errors import InputError

log = logging.getLogger(__name__)


@dataclass
class CaseData:
    """Valid realizations grouped by case.

    ``x``: (n_rows, n_features) float64, rows of each case contiguous, cases in order;
    ``case``: (n_rows,) case index 0..n_cases-1 of each row;
    ``case_ids``: (n_cases,) the catalog's case ids;
    ``targets``: (n_cases, n_targets) one target per case (the mean over its valid rows);
    ``row_targets``: (n_rows, n_targets) the target of every row (used by MSE);
    ``point``: optional (n_rows, n_targets) point estimates (for MSWB training).
    """

    x: np.ndarray
    case: np.ndarray
    case_ids: np.ndarray
    targets: np.ndarray
    row_targets: np.ndarray
    features: list[str]
    target_names: list[str]
    point: np.ndarray | None = None

    @property
    def n_cases(self) -> int:
        return len(self.case_ids)

    @property
    def n_rows(self) -> int:
        return len(self.case)

    @property
    def counts(self) -> np.ndarray:
        """Number of valid realizations of each case."""
        return np.bincount(self.case, minlength=self.n_cases)

    def subset(self, cases: np.ndarray) -> CaseData:
        """The data of the cases with indices ``cases`` (renumbered 0..len-1, in that order)."""
        cases = np.asarray(cases, dtype=np.intp)
        counts = self.counts
        rows = case_rows(counts, cases)
        return CaseData(
            x=self.x[rows],
            case=np.repeat(np.arange(len(cases)), counts[cases]),
            case_ids=self.case_ids[cases],
            targets=self.targets[cases],
            row_targets=self.row_targets[rows],
            features=self.features,
            target_names=self.target_names,
            point=None if self.point is None else self.point[rows],
        )

    def padded(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(X, mask, targets)``: X (n_cases, n_rea_max, n_features) zero-padded,
        mask True = valid."""
        counts = self.counts
        r = int(counts.max()) if len(counts) else 0
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        pos = np.arange(self.n_rows) - starts[self.case]
        x = np.zeros((self.n_cases, r, self.x.shape[1]))
        mask = np.zeros((self.n_cases, r), bool)
        x[self.case, pos] = self.x
        mask[self.case, pos] = True
        return x, mask, self.targets

    @classmethod
    def from_padded(
        cls,
        x: np.ndarray,
        mask: np.ndarray,
        targets: np.ndarray,
        point: np.ndarray | None = None,
        features: Sequence[str] | None = None,
        target_names: Sequence[str] | None = None,
    ) -> CaseData:
        """Build from padded arrays: x (C, R, F), mask (C, R), targets (C,) or (C, T).

        ``point`` (C, R) or (C, R, T) holds point estimates for MSWB. Cases without any
        valid realization are not allowed here.
        """
        x = np.asarray(x, dtype=np.float64)
        mask = np.asarray(mask, bool)
        t = np.asarray(targets, dtype=np.float64)
        t = t[:, None] if t.ndim == 1 else t
        if np.any(mask.sum(axis=1) == 0):
            raise ValueError("every case needs at least one valid realization")
        ci, ri = np.nonzero(mask)
        pt = None
        if point is not None:
            p = np.asarray(point, dtype=np.float64)
            pt = p[ci, ri]
            pt = pt[:, None] if pt.ndim == 1 else pt
        nf = x.shape[2]
        return cls(
            x=x[ci, ri],
            case=ci.astype(np.intp),
            case_ids=np.arange(x.shape[0]),
            targets=t,
            row_targets=t[ci],
            features=list(features) if features else [f"x{i}" for i in range(nf)],
            target_names=list(target_names)
            if target_names
            else [f"t{i}" for i in range(t.shape[1])],
            point=pt,
        )


def case_rows(counts: np.ndarray, cases: np.ndarray) -> np.ndarray:
    """Row indices of the cases ``cases``, case after case, in data whose rows are grouped by
    case in order with ``counts`` rows per case (:class:`CaseData`)."""
    cases = np.asarray(cases, dtype=np.intp)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    sel_counts = counts[cases]
    offsets = np.repeat(
        starts[cases] - np.concatenate([[0], np.cumsum(sel_counts)[:-1]]), sel_counts
    )
    return np.arange(int(sel_counts.sum())) + offsets


def sorted_unique(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(values, return_inverse=True)`` of sorted integers ``values`` (the inverse
    as ``intp``), without sorting them again (nor importing ``numpy.ma``, as ``np.unique``
    does)."""
    inverse = np.zeros(len(values), dtype=np.intp)
    if not len(values):
        return values[:0].copy(), inverse
    starts = np.flatnonzero(values[1:] != values[:-1]) + 1
    inverse[starts] = 1
    np.cumsum(inverse, out=inverse)
    return values[np.concatenate([[0], starts])], inverse


def valid_rows(
    columns: Mapping[str, np.ndarray], features: Sequence[str], n_rows: int
) -> np.ndarray:
    """Rows usable for training: ``flags == 0`` (when the column exists) and finite features."""
    ok = np.ones(n_rows, bool)
    if "flags" in columns:
        ok &= np.asarray(columns["flags"]) == 0
    for f in features:
        ok &= np.isfinite(np.asarray(columns[f], dtype=np.float64))
    return ok


def _report_dropped(
    case: np.ndarray, empty: np.ndarray, measured: np.ndarray | None, where: str
) -> None:
    """Log the dropped cases by why: a selection removed them (info), or no row was valid
    (warning)."""
    if measured is not None:
        had_rows = np.isin(empty, case[np.asarray(measured, bool)])
        deselected, empty = empty[had_rows], empty[~had_rows]
        if len(deselected):
            log.info(
                "%s: %d case(s) left out by the selection (no selected realization; e.g. case %s)",
                where,
                len(deselected),
                ", ".join(str(v) for v in deselected[:5]),
            )
    if len(empty):
        log.warning(
            "%s: %d case(s) dropped: every realization is flagged or has a non-finite feature or "
            "estimate (e.g. case %s)",
            where,
            len(empty),
            ", ".join(str(v) for v in empty[:5]),
        )


def build_cases(
    columns: Mapping[str, np.ndarray],
    features: Sequence[str],
    targets: Sequence[str],
    valid: np.ndarray,
    where: str = "catalog",
    constant_targets: bool = True,
    point: Mapping[str, np.ndarray] | None = None,
    measured: np.ndarray | None = None,
) -> CaseData:
    """Group catalog rows by ``case`` into :class:`CaseData`.

    ``valid`` marks the usable rows. Targets must be finite on every row; with
    ``constant_targets`` (MSB, MSWB) they must also be constant within each case.
    ``point`` maps each target to the point estimates of every row (for MSWB).
    ``measured`` marks the rows valid before any selection (``valid`` then adds the
    selections): the log says which dropped cases a selection removed and which had no
    valid realization at all.
    """
    case = np.asarray(columns["case"])
    n = len(case)
    if n == 0:
        raise InputError(f"{where}: the catalog has no rows")
    valid = np.asarray(valid, bool)
    for name in targets:
        t = np.asarray(columns[name], dtype=np.float64)
        bad = ~np.isfinite(t)
        if np.any(bad):
            raise InputError(
                f"{where}: target {name} is not finite in {int(bad.sum())} row(s) (e.g. case "
                f"{case[bad][0]})"
            )
    if case.dtype.kind in "biu":  # sorted once (the same rows, ids and index)
        order = np.argsort(case, kind="stable")
        rows = order[valid[order]]
        ids, index = sorted_unique(case[rows])
        ids_all = ids if len(rows) == n else sorted_unique(case[order])[0]
    else:
        ids_all = np.unique(case)
        order = np.argsort(case[valid], kind="stable")
        rows = np.flatnonzero(valid)[order]
        ids, index = np.unique(case[rows], return_inverse=True)
    n_empty = len(ids_all) - len(ids)
    if len(ids) == 0:
        raise InputError(
            f"{where}: no valid realization in any case (all rows flagged, non-finite or "
            "deselected)"
        )
    if n_empty:
        _report_dropped(case, np.setdiff1d(ids_all, ids), measured, where)
    if len(ids) < 2:
        raise InputError(
            f"{where}: fewer than 2 cases with valid realizations ({len(ids)}); MSB training needs "
            "several cases"
        )
    index = index.ravel().astype(np.intp)
    counts = np.bincount(index, minlength=len(ids))
    in_order = len(rows) == n and bool(np.array_equal(rows, np.arange(n)))

    def gathered(values: np.ndarray) -> np.ndarray:
        """The rows ``rows`` of a column in float64 (no copy when they are all, in order)."""
        values = np.asarray(values, dtype=np.float64)
        return values if in_order else values[rows]

    row_t = np.column_stack([gathered(columns[t]) for t in targets])
    tsum = np.stack(
        [np.bincount(index, weights=row_t[:, j], minlength=len(ids)) for j in range(len(targets))],
        axis=1,
    )
    tcase = tsum / counts[:, None]
    if constant_targets:
        dev = np.abs(row_t - tcase[index])
        tol = 1e-9 * (1.0 + np.abs(tcase[index]))
        bad = dev > tol
        if np.any(bad):
            r, j = np.argwhere(bad)[0]
            raise InputError(
                f"{where}: target {targets[j]} varies within case {ids[index[r]]}; MSB needs one "
                "target value per case (use the MSE cost, or one case per target value)"
            )
    x = np.column_stack([gathered(columns[f]) for f in features])
    pt = None
    if point is not None:
        pt = np.column_stack([gathered(point[t]) for t in targets])
    return CaseData(
        x=x,
        case=index,
        case_ids=ids,
        targets=tcase,
        row_targets=row_t,
        features=list(features),
        target_names=list(targets),
        point=pt,
    )


def split_cases(
    n_cases: int, fraction: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Random ``(train, valid)`` case indices holding out ``fraction`` of the cases (both
    sorted)."""
    n_valid = max(1, int(round(fraction * n_cases)))
    perm = rng.permutation(n_cases)
    return np.sort(perm[n_valid:]), np.sort(perm[:n_valid])
