"""Paired shear biases of two sets drawn with common random numbers (real galaxies and
their Sérsic twins): m and c of each, and their difference with errors from a paired
bootstrap over galaxies.

Both sets hold the same rows (same case = shear, galaxy, rotation, offset, noise seeds).
Each set is reduced to sums per (case, galaxy) of ``w``, ``w * g_est`` and ``w * g_true``
(``w`` = 1, or the predicted weight; rows with a non-finite estimate or a non-zero flag
count with ``w = 0``). A resample draws galaxies with replacement; a galaxy drawn ``k``
times counts ``k`` times in every case, in both sets. Per resample and set, the per-case
means give m and c by the same ordinary least squares over cases as
:func:`megalut_cli.shear.bias.fit_bias`; the spread of ``m_a - m_b`` over resamples is the
error of the difference, which therefore keeps the correlation that the common galaxies,
shears and noise give the two sets.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from megalut_cli.catalog import catalog_info, read_catalog
from megalut_cli.errors import ConfigError, InputError, Names, namer
from megalut_cli.expr import columns_used, evaluate_row_values
from megalut_cli.measure.metacal_defaults import DEFAULT_STEP, header_step
from megalut_cli.seeding import STREAM_BOOTSTRAP, rng_for
from megalut_cli.shear.bias import calibrate_by_response
from megalut_cli.shear.bootstrap import fit_columns
from megalut_cli.shear.evaluate import check_by

#: Columns that must agree row by row between paired catalogs.
PAIRING_COLUMNS = ("case", "rea", "tru_g1", "tru_g2")
#: Columns of a metacal prediction catalog that the paired evaluation calibrates with.
METACAL_COLUMNS = (
    "pre_g1_noshear",
    "pre_g2_noshear",
    "mcal_r11",
    "mcal_r12",
    "mcal_r21",
    "mcal_r22",
)
#: The weights of the sheared versions (the weights' selection response).
SHEARED_WEIGHT_COLUMNS = tuple(f"pre_g{i}_w_{j}{sign}" for i in "12" for j in "12" for sign in "pm")
#: Default bootstrap resamples.
N_BOOTSTRAP = 1000


def group_sums(
    cell: np.ndarray,
    n_cells: int,
    g_true: np.ndarray,
    g_est: np.ndarray,
    weight: np.ndarray,
) -> np.ndarray:
    """``(3, n_cells)`` sums of ``w``, ``w g_est``, ``w g_true`` per cell (invalid rows: w = 0);
    cell ``case * n_galaxies + galaxy`` for :func:`fit_resamples`."""
    ok = np.isfinite(g_est) & np.isfinite(weight) & (weight > 0)
    w = np.where(ok, weight, 0.0)
    rows = [w, np.where(ok, w * g_est, 0.0), np.where(ok, w * g_true, 0.0)]
    return np.stack([np.bincount(cell, weights=r, minlength=n_cells) for r in rows])


def fit_resamples(
    sums: np.ndarray, counts: np.ndarray, n_cases: int, n_gal: int
) -> tuple[np.ndarray, np.ndarray]:
    """m and c of the per-case means of :func:`group_sums`, one per row of ``counts`` (galaxy
    multiplicities); NaN with fewer than 3 cases."""
    s = sums.reshape(len(sums), n_cases, n_gal) @ counts.T  # (rows, n_cases, B)
    with np.errstate(invalid="ignore", divide="ignore"):
        m, c = fit_columns(s[2] / s[0], s[1] / s[0])
    few = (s[0] > 0).sum(axis=0) < 3
    return np.where(few, np.nan, m), np.where(few, np.nan, c)


def paired_bias(
    galaxy: np.ndarray,
    case: np.ndarray,
    g_true: np.ndarray,
    est_a: np.ndarray,
    est_b: np.ndarray,
    weight_a: np.ndarray | None = None,
    weight_b: np.ndarray | None = None,
    n_boot: int = N_BOOTSTRAP,
    seed: int = 0,
) -> dict[str, Any]:
    """m, c of sets ``a`` and ``b`` (one shear component, rows paired) and ``m_a - m_b``,
    ``c_a - c_b``, with 1-sigma errors from a paired bootstrap over galaxies (metacal sets:
    :func:`paired_metacal_bias`).

    ``galaxy`` and ``case`` are the ids shared by the paired rows. Returns a JSON-ready dict:
    ``m_a, m_a_err, c_a, c_a_err, m_b, ..., dm, dm_err, dc, dc_err, n_galaxies, n_cases,
    n_rows_a, n_rows_b, n_boot``. Values that cannot be determined are None.
    """
    gal_ids, gi = np.unique(np.asarray(galaxy), return_inverse=True)
    case_ids, ci = np.unique(np.asarray(case), return_inverse=True)
    n_gal, n_cases = gal_ids.size, case_ids.size
    cell = ci.ravel() * n_gal + gi.ravel()
    g_true = np.asarray(g_true, dtype=float)
    ones = np.ones(g_true.size)
    wa = ones if weight_a is None else np.asarray(weight_a, dtype=float)
    wb = ones if weight_b is None else np.asarray(weight_b, dtype=float)
    sums_a = group_sums(cell, n_cases * n_gal, g_true, np.asarray(est_a, dtype=float), wa)
    sums_b = group_sums(cell, n_cases * n_gal, g_true, np.asarray(est_b, dtype=float), wb)
    rng = rng_for(seed, STREAM_BOOTSTRAP)
    counts = np.vstack(
        [np.ones(n_gal), rng.multinomial(n_gal, np.full(n_gal, 1.0 / n_gal), size=n_boot)]
    )
    m_a, c_a = fit_resamples(sums_a, counts, n_cases, n_gal)
    m_b, c_b = fit_resamples(sums_b, counts, n_cases, n_gal)
    return _paired_result(
        (m_a, c_a, m_b, c_b),
        n_gal,
        n_cases,
        n_boot,
        int(np.count_nonzero(np.isfinite(est_a) & (wa > 0))),
        int(np.count_nonzero(np.isfinite(est_b) & (wb > 0))),
    )


def _paired_result(
    fits: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    n_gal: int,
    n_cases: int,
    n_boot: int,
    n_rows_a: int,
    n_rows_b: int,
) -> dict[str, Any]:
    """The JSON-ready result of :func:`paired_bias` from ``(m_a, c_a, m_b, c_b)`` (the full
    sample first, then one per resample)."""
    m_a, c_a, m_b, c_b = fits
    out: dict[str, Any] = {}
    for name, v in (
        ("m_a", m_a),
        ("c_a", c_a),
        ("m_b", m_b),
        ("c_b", c_b),
        ("dm", m_a - m_b),
        ("dc", c_a - c_b),
    ):
        boot = v[1:][np.isfinite(v[1:])]
        out[name] = _num(v[0])
        out[f"{name}_err"] = _num(np.std(boot, ddof=1)) if boot.size > 1 else None
    out.update(
        n_galaxies=int(n_gal),
        n_cases=int(n_cases),
        n_boot=int(n_boot),
        n_rows_a=n_rows_a,
        n_rows_b=n_rows_b,
    )
    return out


@dataclass(frozen=True)
class MetacalSet:
    """One set of a paired metacal evaluation, per row: the noshear estimates ``est`` and
    weights ``weight`` (``(g1, g2)``; 0 where not used), the responses ``response[i][j]``
    (``mcal_r<i+1><j+1>``), ``usable`` (the rows whose every version was measured) and, for
    the weights' selection response, ``sheared[(i, j, sign)]``: the weight of component
    ``i`` on the version sheared by ``sign`` (``"p"``, ``"m"``) along ``j`` (None: no
    weights)."""

    est: tuple[np.ndarray, np.ndarray]
    weight: tuple[np.ndarray, np.ndarray]
    response: tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
    usable: np.ndarray
    sheared: Mapping[tuple[int, int, str], np.ndarray] | None = None

    def used(self, i: int) -> np.ndarray:
        """The rows that component ``i`` (0 or 1) uses: a finite estimate and responses and a
        positive weight."""
        g_est, w, r = self.est[i], self.weight[i], self.response[i]
        return np.isfinite(g_est) & np.isfinite(w) & (w > 0) & np.isfinite(r[0]) & np.isfinite(r[1])

    def rows(self, keep: np.ndarray) -> MetacalSet:
        """The set restricted to the rows ``keep``."""
        return MetacalSet(
            (self.est[0][keep], self.est[1][keep]),
            (self.weight[0][keep], self.weight[1][keep]),
            tuple(tuple(r[keep] for r in row) for row in self.response),  # type: ignore[arg-type]
            self.usable[keep],
            None if self.sheared is None else {k: v[keep] for k, v in self.sheared.items()},
        )


def metacal_group_sums(
    cell: np.ndarray, n_cells: int, g_true: np.ndarray, data: MetacalSet, i: int, step: float
) -> np.ndarray:
    """Sums per cell for component ``i`` (0 or 1) of a metacal set: ``w``, ``w g_est``,
    ``w g_true``, ``w R_i1``, ``w R_i2`` and, with sheared weights, ``w_s`` and
    ``w_s g_est / 2 step`` for the versions 1p, 1m, 2p, 2m (the single-set evaluation's
    sums, per cell)."""
    g_est, r = data.est[i], data.response[i]
    ok = data.used(i)
    w = np.where(ok, data.weight[i], 0.0)
    rows = [w, np.where(ok, w * g_est, 0.0), np.where(ok, w * g_true, 0.0)]
    rows += [np.where(ok, w * rj, 0.0) for rj in r]
    if data.sheared is not None:
        pre = np.nan_to_num(g_est)
        for j in (1, 2):
            for sign in "pm":
                ws = data.sheared[(i + 1, j, sign)]
                ws = np.where(data.usable & np.isfinite(ws) & (ws > 0), ws, 0.0)
                rows += [ws, ws * pre / (2.0 * step)]
    return np.stack([np.bincount(cell, weights=x, minlength=n_cells) for x in rows])


def fit_metacal_resamples(
    sums: tuple[np.ndarray, np.ndarray], counts: np.ndarray, n_cases: int, n_gal: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``m1, c1, m2, c2`` of the per-case means of :func:`metacal_group_sums` (``sums``: one
    per component), one per row of ``counts``, calibrated by the resample's 2x2 mean response
    plus the weights' selection response, as the single-set evaluation does."""
    s = [x.reshape(len(x), n_cases, n_gal) @ counts.T for x in sums]  # (rows, n_cases, B)
    total = [x.sum(axis=1) for x in s]  # (rows, B)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = [[total[i][3 + j] / total[i][0] for j in (0, 1)] for i in (0, 1)]
        if len(sums[0]) > 5:
            for i in (0, 1):
                for j in (0, 1):
                    t = total[i][5 + 4 * j : 9 + 4 * j]  # w_p, w_p g, w_m, w_m g
                    r[i][j] = r[i][j] + t[1] / t[0] - t[3] / t[2]
        est = [x[1] / x[0] for x in s]
        g1, g2 = calibrate_by_response(r[0][0], r[0][1], r[1][0], r[1][1], est[0], est[1])
        out = []
        for x, g in zip(s, (g1, g2)):
            m, c = fit_columns(x[2] / x[0], g)
            few = (x[0] > 0).sum(axis=0) < 3
            out += [np.where(few, np.nan, m), np.where(few, np.nan, c)]
    return out[0], out[1], out[2], out[3]


def paired_metacal_bias(
    galaxy: np.ndarray,
    case: np.ndarray,
    g_true: tuple[np.ndarray, np.ndarray],
    set_a: MetacalSet,
    set_b: MetacalSet,
    step: float = DEFAULT_STEP,
    n_boot: int = N_BOOTSTRAP,
    seed: int = 0,
) -> dict[str, dict[str, Any]]:
    """:func:`paired_bias` of both components of two metacal sets, each calibrated by its
    full 2x2 mean response (plus its weights' selection response), recomputed in every
    resample: ``{"g1": {...}, "g2": {...}}``."""
    gal_ids, gi = np.unique(np.asarray(galaxy), return_inverse=True)
    case_ids, ci = np.unique(np.asarray(case), return_inverse=True)
    n_gal, n_cases = gal_ids.size, case_ids.size
    cell = ci.ravel() * n_gal + gi.ravel()
    sums_a = tuple(
        metacal_group_sums(cell, n_cases * n_gal, g_true[i], set_a, i, step) for i in (0, 1)
    )
    sums_b = tuple(
        metacal_group_sums(cell, n_cases * n_gal, g_true[i], set_b, i, step) for i in (0, 1)
    )
    rng = rng_for(seed, STREAM_BOOTSTRAP)
    counts = np.vstack(
        [np.ones(n_gal), rng.multinomial(n_gal, np.full(n_gal, 1.0 / n_gal), size=n_boot)]
    )
    fa = fit_metacal_resamples(sums_a, counts, n_cases, n_gal)  # type: ignore[arg-type]
    fb = fit_metacal_resamples(sums_b, counts, n_cases, n_gal)  # type: ignore[arg-type]
    return {
        comp: _paired_result(
            (fa[2 * i], fa[2 * i + 1], fb[2 * i], fb[2 * i + 1]),
            n_gal,
            n_cases,
            n_boot,
            int(set_a.used(i).sum()),
            int(set_b.used(i).sum()),
        )
        for i, comp in enumerate(("g1", "g2"))
    }


def _num(x: float) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


def check_pairing(
    a: Mapping[str, np.ndarray],
    b: Mapping[str, np.ndarray],
    names: tuple[str, str],
    galaxy_column: str,
) -> None:
    """Raise one :class:`InputError` line unless ``a`` and ``b`` are row-by-row paired."""
    na, nb = len(a["case"]), len(b["case"])
    if na != nb:
        raise InputError(f"{names[0]} and {names[1]} are not paired: {na} rows against {nb}")
    for col in (*PAIRING_COLUMNS, galaxy_column):
        x, y = np.asarray(a[col]), np.asarray(b[col])
        same = (x == y) | (np.isnan(x) & np.isnan(y)) if x.dtype.kind == "f" else x == y
        diff = np.flatnonzero(~same)
        if diff.size:
            r = int(diff[0])
            raise InputError(
                f"{names[0]} and {names[1]} are not paired: column {col} differs at row {r} "
                f"({x[r]!r} against {y[r]!r}; simulate both from one config and seed)"
            )


def group_bins(
    values: np.ndarray, galaxy: np.ndarray, case: np.ndarray, n_bins: int
) -> tuple[np.ndarray, np.ndarray]:
    """Equal-population bins of (case, galaxy) groups by the group mean of ``values``
    (pairs and rotations stay together). Returns ``(bin index per row, bin edges)``;
    rows of groups with no finite value get -1."""
    _, gi = np.unique(np.asarray(galaxy), return_inverse=True)
    _, ci = np.unique(np.asarray(case), return_inverse=True)
    key = ci.ravel() * (gi.max() + 1) + gi.ravel()
    keys, inv = np.unique(key, return_inverse=True)
    v = np.asarray(values, dtype=float)
    ok = np.isfinite(v)
    num = np.bincount(inv.ravel(), weights=np.where(ok, v, 0.0), minlength=keys.size)
    den = np.bincount(inv.ravel(), weights=ok.astype(float), minlength=keys.size)
    with np.errstate(invalid="ignore", divide="ignore"):
        gm = num / den
    finite = np.isfinite(gm)
    if not finite.any():
        return np.full(v.size, -1, dtype=np.int64), np.zeros(0)
    edges = np.quantile(gm[finite], np.linspace(0.0, 1.0, n_bins + 1))
    idx = np.clip(np.searchsorted(edges, gm, side="right") - 1, 0, n_bins - 1)
    idx = np.where(finite, idx, -1)
    return idx[inv.ravel()], edges


def paired_evaluation(
    a: Mapping[str, np.ndarray],
    b: Mapping[str, np.ndarray],
    galaxy_column: str = "tru_real_index",
    by: Mapping[str, np.ndarray] | None = None,
    n_bins: int = 3,
    n_boot: int = N_BOOTSTRAP,
    seed: int = 0,
    names: Sequence[str] = ("real", "twin"),
    metacal_step: float = DEFAULT_STEP,
) -> dict[str, Any]:
    """Paired biases of catalogs ``a`` and ``b`` (columns as arrays; checked to be paired),
    unweighted and, when both have ``pre_g1_w, pre_g2_w``, weighted; overall and in
    ``n_bins`` equal-population bins of each quantity of ``by`` (values per row, averaged
    over both sets and per (case, galaxy)). JSON-ready; layout in ``docs/realgal.md``."""
    check_pairing(a, b, (names[0], names[1]), galaxy_column)
    gal, case = np.asarray(a[galaxy_column]), np.asarray(a["case"])
    metacal = all(c in t for c in METACAL_COLUMNS for t in (a, b))
    sfx = "_noshear" if metacal else ""
    weight_cols = [f"pre_g{i}_w{sfx}" for i in (1, 2)] + (
        list(SHEARED_WEIGHT_COLUMNS) if metacal else []
    )
    schemes = ["unweighted"] + (
        ["weighted"] if all(c in t for t in (a, b) for c in weight_cols) else []
    )
    flag_col = "flags_noshear" if metacal else "flags"

    def valid(t: Mapping[str, np.ndarray], comp: str) -> np.ndarray:
        ok = np.isfinite(np.asarray(t[f"pre_{comp}{sfx}"], dtype=float))
        return ok & (np.asarray(t[flag_col]) == 0) if flag_col in t else ok

    def weight(t: Mapping[str, np.ndarray], comp: str, scheme: str) -> np.ndarray:
        w = valid(t, comp).astype(float)
        if scheme == "weighted":
            w = w * np.nan_to_num(np.asarray(t[f"pre_{comp}_w{sfx}"], dtype=float))
        return w

    def metacal_set(t: Mapping[str, np.ndarray], scheme: str) -> MetacalSet:
        """The set as the single-set evaluation sees it (its ``usable`` rows: flags_noshear
        == 0 and every version measured)."""
        est = tuple(np.asarray(t[f"pre_g{i}_noshear"], dtype=float) for i in (1, 2))
        resp = tuple(
            tuple(np.asarray(t[f"mcal_r{i}{j}"], dtype=float) for j in (1, 2)) for i in (1, 2)
        )
        usable = np.ones(len(est[0]), dtype=bool) if flag_col not in t else t[flag_col] == 0
        usable = usable & np.isfinite(est[0]) & np.isfinite(est[1])
        usable &= np.all(np.isfinite(np.asarray(resp)), axis=(0, 1))
        sheared = (
            {
                (i, j, sign): np.asarray(t[f"pre_g{i}_w_{j}{sign}"], dtype=float)
                for i in (1, 2)
                for j in (1, 2)
                for sign in "pm"
            }
            if scheme == "weighted"
            else None
        )
        return MetacalSet(
            est,  # type: ignore[arg-type]
            (weight(t, "g1", scheme), weight(t, "g2", scheme)),
            resp,  # type: ignore[arg-type]
            usable,
            sheared,
        )

    def evaluate(rows: np.ndarray) -> dict[str, Any]:
        res: dict[str, Any] = {}
        if not rows.any():
            return res
        for scheme in schemes:
            if metacal:
                res[scheme] = paired_metacal_bias(
                    gal[rows],
                    case[rows],
                    (
                        np.asarray(a["tru_g1"], dtype=float)[rows],
                        np.asarray(a["tru_g2"], dtype=float)[rows],
                    ),
                    metacal_set(a, scheme).rows(rows),
                    metacal_set(b, scheme).rows(rows),
                    metacal_step,
                    n_boot,
                    seed,
                )
                continue
            res[scheme] = {}
            for comp in ("g1", "g2"):
                wa, wb = weight(a, comp, scheme), weight(b, comp, scheme)
                res[scheme][comp] = paired_bias(
                    gal[rows],
                    case[rows],
                    np.asarray(a[f"tru_{comp}"], dtype=float)[rows],
                    np.asarray(a[f"pre_{comp}{sfx}"], dtype=float)[rows],
                    np.asarray(b[f"pre_{comp}{sfx}"], dtype=float)[rows],
                    wa[rows],
                    wb[rows],
                    n_boot=n_boot,
                    seed=seed,
                )
        return res

    result: dict[str, Any] = {
        "names": list(names),
        "galaxy_column": galaxy_column,
        "n_boot": int(n_boot),
        "metacal": metacal,
        "seed": int(seed),
        "overall": evaluate(np.ones(case.size, dtype=bool)),
        "by": {},
    }
    for label, values in (by or {}).items():
        idx, edges = group_bins(values, gal, case, n_bins)
        result["by"][label] = {
            "edges": [float(e) for e in edges],
            "bins": [evaluate(idx == k) for k in range(len(edges) - 1)],
        }
    return result


def _pm(v: float | None, e: float | None) -> str:
    if v is None:
        return f"{'n/a':>21}"
    return f"{v:+.2e} ± {e:.1e}" if e is not None else f"{v:+.2e}         "


def format_paired(result: Mapping[str, Any]) -> str:
    """Plain-text table of :func:`paired_evaluation`'s result."""
    a, b = result["names"]
    lines = (
        [
            "metacal: pre_g*_noshear of each set calibrated by its mean response "
            "(mcal_r11, mcal_r22)",
            "",
        ]
        if result.get("metacal")
        else []
    )

    def block(res: Mapping[str, Any], title: str) -> None:
        for scheme, comps in res.items():
            first = next(iter(comps.values()))
            lines.append(
                f"{title}{scheme} ({first['n_galaxies']} galaxies, {first['n_cases']} cases, "
                f"paired bootstrap of {first['n_boot']})"
            )
            lines.append(
                f"{'':6}{'m_' + a:>22}{'m_' + b:>24}"
                f"{'m_' + a + ' - m_' + b:>24}{'c_' + a + ' - c_' + b:>24}"
            )
            for comp, r in comps.items():
                lines.append(
                    f"  {comp:4}{_pm(r['m_a'], r['m_a_err']):>22}{_pm(r['m_b'], r['m_b_err']):>24}"
                    f"{_pm(r['dm'], r['dm_err']):>24}{_pm(r['dc'], r['dc_err']):>24}"
                )
            lines.append("")

    block(result["overall"], "")
    if not result["overall"]:
        lines.append("no rows")
    for label, info in result["by"].items():
        for k, res in enumerate(info["bins"]):
            lo, hi = info["edges"][k], info["edges"][k + 1]
            block(res, f"{label} in [{lo:.3g}, {hi:.3g}]: ")
    return "\n".join(lines).rstrip() + "\n"


def evaluate_paired_catalogs(
    path_a: str,
    path_b: str,
    by: Sequence[str] | None = None,
    n_bins: int = 3,
    n_boot: int = N_BOOTSTRAP,
    seed: int = 0,
    galaxy_column: str = "tru_real_index",
    names: Names | None = None,
) -> dict[str, Any]:
    """:func:`paired_evaluation` of two prediction catalogs (e.g. ``real_shears.fits`` and
    ``twin_shears.fits``). ``by`` holds columns or numeric row expressions (e.g.
    ``tru_twin_rad/tru_psf_sigma``); their values are averaged over both catalogs. Messages
    name the arguments by ``names`` (``by``, ``twin``)."""
    _, names_a, header_a = catalog_info(path_a)
    names_b = catalog_info(path_b)[1]
    common = [c for c in names_a if c in set(names_b)]
    need = [*PAIRING_COLUMNS, galaxy_column, "pre_g1", "pre_g2"]
    for path, colnames in ((path_a, names_a), (path_b, names_b)):
        missing = [c for c in need if c not in colnames]
        if missing:
            raise InputError(
                f"{path}: missing column(s) {', '.join(missing)} (a prediction catalog of a "
                "real-galaxy or twin set)"
            )
    name = namer(names)  # the caller's names of the arguments
    kinds = check_by(list(by or []), common, name("by"), where=f"both {path_a} and {path_b}")
    if "case" in kinds.values():
        bad = next(c for c, k in kinds.items() if k == "case")
        raise ConfigError(
            f"{name('by')}: {bad!r}: per-case aggregates do not apply with {name('twin')} (groups "
            "are binned by their mean already)"
        )
    used = {c for c in kinds if kinds[c] == "column"} | {
        u for c in kinds if kinds[c] == "row" for u in columns_used(c)
    }
    extra = [
        c
        for c in (
            "flags",
            "pre_g1_w",
            "pre_g2_w",
            *METACAL_COLUMNS,
            "flags_noshear",
            "pre_g1_w_noshear",
            "pre_g2_w_noshear",
            *SHEARED_WEIGHT_COLUMNS,
        )
        if c in common
    ]
    cols = list(dict.fromkeys(need + extra + sorted(used)))
    ta, tb = read_catalog(path_a, columns=cols), read_catalog(path_b, columns=cols)
    a = {c: np.asarray(ta[c]) for c in cols}
    b = {c: np.asarray(tb[c]) for c in cols}
    check_pairing(a, b, (str(path_a), str(path_b)), galaxy_column)
    values = {}
    for c in by or []:
        row_expression = kinds[c] == "row"
        va = evaluate_row_values(c, a, len(ta)) if row_expression else np.asarray(a[c], dtype=float)
        vb = evaluate_row_values(c, b, len(tb)) if row_expression else np.asarray(b[c], dtype=float)
        values[c] = 0.5 * (va + vb)
    step = header_step(header_a)
    return paired_evaluation(
        a,
        b,
        galaxy_column,
        values,
        n_bins,
        n_boot,
        seed,
        names=("real", "twin"),
        metacal_step=DEFAULT_STEP if step is None else step,
    )
