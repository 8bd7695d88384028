"""Paired shear biases of two sets drawn with common random numbers (real galaxies and
their Sérsic twins): m and c of each, and their difference with errors from a paired
bootstrap over galaxies.

Both sets hold the same rows (same case = shear, galaxy, rotation, offset, noise seeds).
Each set is reduced to the named sums of the single-set evaluation
(:mod:`megalut_cli.shear.response`) per (case, galaxy): ``w``, ``w * g_est``, ``w * g_true``
(``w`` = 1, or the predicted weight; rows with a non-finite estimate or a non-zero flag
count with ``w = 0``) and, for metacal sets, the responses and the sheared versions' weights.
A resample draws galaxies with replacement (:func:`megalut_cli.shear.bootstrap.resample_counts`);
a galaxy drawn ``k`` times counts ``k`` times in every case, in both sets. Per resample and
set, the per-case means (metacal: calibrated by the resample's mean and selection response)
give m and c by the same ordinary least squares over cases as
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
from megalut_cli.measure.metacal_defaults import DEFAULT_STEP
from megalut_cli.shear.bootstrap import fit_columns, resample_counts
from megalut_cli.shear.evaluate import check_by
from megalut_cli.shear.options import N_BOOTSTRAP
from megalut_cli.shear.response import case_estimates, header_step, row_values

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
#: Scheme name of the sums of :func:`paired_bias` (one component, named ``g1``).
ONE_COMPONENT = "component"


@dataclass(frozen=True)
class Resampling:
    """The (case, galaxy) ``cell`` of each paired row and the galaxy multiplicities ``counts``
    ``(1 + n_boot, n_gal)``: the full sample, then the resamples."""

    cell: np.ndarray
    n_cases: int
    n_gal: int
    counts: np.ndarray

    @classmethod
    def draw(cls, galaxy: np.ndarray, case: np.ndarray, n_boot: int, seed: int) -> Resampling:
        """Cells of the rows' ``galaxy`` and ``case`` ids; ``n_boot`` resamples from ``seed``
        (the draw of the single-set bootstrap)."""
        gal_ids, gi = np.unique(np.asarray(galaxy), return_inverse=True)
        case_ids, ci = np.unique(np.asarray(case), return_inverse=True)
        n_gal = gal_ids.size
        counts = np.vstack([np.ones(n_gal), *(b.T for b in resample_counts(seed, n_gal, n_boot))])
        return cls(ci.ravel() * n_gal + gi.ravel(), case_ids.size, n_gal, counts)

    def fits(
        self, values: Mapping[str, np.ndarray], scheme: str
    ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """``(m, c)`` of each component of the per-row ``values`` of ``scheme``
        (:func:`set_values`), one per row of ``counts``; NaN with fewer than 3 cases."""
        n = self.n_cases * self.n_gal
        sums = {
            k: np.bincount(self.cell, weights=v, minlength=n).reshape(self.n_cases, self.n_gal)
            @ self.counts.T
            for k, v in values.items()
        }
        out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        with np.errstate(invalid="ignore", divide="ignore"):
            for comp, d in case_estimates(sums, scheme).items():
                m, c = fit_columns(d["tru"], d["pre"])
                few = (sums[f"{scheme}:w:{comp}"] > 0).sum(axis=0) < 3
                out[comp] = (np.where(few, np.nan, m), np.where(few, np.nan, c))
        return out


def set_values(
    scheme: str,
    g_true: Mapping[str, np.ndarray],
    est: Mapping[str, np.ndarray],
    weight: Mapping[str, np.ndarray],
    response: Mapping[tuple[int, int], np.ndarray] | None = None,
    sheared: Mapping[tuple[int, str], np.ndarray] | None = None,
    step: float = DEFAULT_STEP,
) -> dict[str, np.ndarray]:
    """:func:`megalut_cli.shear.response.row_values` of one set, per component (``g1``,
    ``g2``): a row is used where its estimate, weight (and metacal ``response[(i, j)]``) are
    finite and its weight positive; ``sheared[(i, kind)]``: the sheared versions' weights."""
    ok: dict[str, np.ndarray] = {}
    w: dict[str, np.ndarray] = {}
    t: dict[str, np.ndarray] = {}
    p: dict[str, np.ndarray] = {}
    for comp, e in est.items():
        ok[comp] = np.isfinite(e) & np.isfinite(weight[comp]) & (weight[comp] > 0)
        for j in (1, 2) if response is not None else ():
            ok[comp] &= np.isfinite(response[(int(comp[1]), j)])
        w[comp], t[comp], p[comp] = (
            np.where(ok[comp], x, 0.0) for x in (weight[comp], g_true[comp], e)
        )
    r = (
        None
        if response is None
        else {k: np.where(ok[f"g{k[0]}"], x, 0.0) for k, x in response.items()}
    )
    pre = {int(comp[1]): e for comp, e in est.items()}
    return row_values(scheme, w, t, p, r, sheared, pre, step)


def paired_fits(
    values_a: Mapping[str, np.ndarray],
    values_b: Mapping[str, np.ndarray],
    scheme: str,
    resampling: Resampling,
) -> dict[str, dict[str, Any]]:
    """The JSON-ready result of each component of the sets of :func:`set_values`: m, c of
    both and their differences, with 1-sigma errors from the spread over the resamples."""
    fa, fb = resampling.fits(values_a, scheme), resampling.fits(values_b, scheme)
    out: dict[str, dict[str, Any]] = {}
    for comp in fa:
        (m_a, c_a), (m_b, c_b) = fa[comp], fb[comp]
        res: dict[str, Any] = {}
        for name, v in (
            ("m_a", m_a),
            ("c_a", c_a),
            ("m_b", m_b),
            ("c_b", c_b),
            ("dm", m_a - m_b),
            ("dc", c_a - c_b),
        ):
            boot = v[1:][np.isfinite(v[1:])]
            res[name] = _num(v[0])
            res[f"{name}_err"] = _num(np.std(boot, ddof=1)) if boot.size > 1 else None
        res.update(
            n_galaxies=resampling.n_gal,
            n_cases=resampling.n_cases,
            n_boot=len(resampling.counts) - 1,
            n_rows_a=int(values_a[f"{scheme}:n:{comp}"].sum()),
            n_rows_b=int(values_b[f"{scheme}:n:{comp}"].sum()),
        )
        out[comp] = res
    return out


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
    ``c_a - c_b``, with 1-sigma errors from a paired bootstrap over galaxies.

    ``galaxy`` and ``case`` are the ids shared by the paired rows. Returns a JSON-ready dict:
    ``m_a, m_a_err, c_a, c_a_err, m_b, ..., dm, dm_err, dc, dc_err, n_galaxies, n_cases,
    n_rows_a, n_rows_b, n_boot``. Values that cannot be determined are None.
    """
    tru = {"g1": np.asarray(g_true, dtype=float)}
    values = [
        set_values(
            ONE_COMPONENT,
            tru,
            {"g1": np.asarray(est, dtype=float)},
            {"g1": np.ones(tru["g1"].size) if w is None else np.asarray(w, dtype=float)},
        )
        for est, w in ((est_a, weight_a), (est_b, weight_b))
    ]
    resampling = Resampling.draw(galaxy, case, n_boot, seed)
    return paired_fits(values[0], values[1], ONE_COMPONENT, resampling)["g1"]


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

    def values_of(t: Mapping[str, np.ndarray], scheme: str) -> dict[str, np.ndarray]:
        """The set's per-row values; metacal: its sheared versions' weights on the rows that the
        single-set evaluation finds usable (flags_noshear == 0 and every version measured)."""
        comps = ("g1", "g2")
        est = {c: np.asarray(t[f"pre_{c}{sfx}"], dtype=float) for c in comps}
        weight = {c: valid(t, c).astype(float) for c in comps}
        if scheme == "weighted":
            for c in comps:
                weight[c] = weight[c] * np.nan_to_num(np.asarray(t[f"pre_{c}_w{sfx}"], dtype=float))
        tru = {c: np.asarray(a[f"tru_{c}"], dtype=float) for c in comps}
        if not metacal:
            return set_values(scheme, tru, est, weight)
        resp = {(i, j): np.asarray(t[f"mcal_r{i}{j}"], dtype=float) for i in (1, 2) for j in (1, 2)}
        sheared = None
        if scheme == "weighted":
            usable = np.ones(len(est["g1"]), dtype=bool) if flag_col not in t else t[flag_col] == 0
            usable = usable & np.isfinite(est["g1"]) & np.isfinite(est["g2"])
            usable &= np.all(np.isfinite(np.asarray(list(resp.values()))), axis=0)
            sheared = {}
            for i in (1, 2):
                for kind in (f"{j}{sign}" for j in (1, 2) for sign in "pm"):
                    ws = np.asarray(t[f"pre_g{i}_w_{kind}"], dtype=float)
                    sheared[(i, kind)] = np.where(usable & np.isfinite(ws) & (ws > 0), ws, 0.0)
        return set_values(scheme, tru, est, weight, resp, sheared, metacal_step)

    per_set = {(t_name, s): values_of(t, s) for t_name, t in (("a", a), ("b", b)) for s in schemes}

    def evaluate(rows: np.ndarray) -> dict[str, Any]:
        if not rows.any():
            return {}
        resampling = Resampling.draw(gal[rows], case[rows], n_boot, seed)
        sub = {k: {name: v[rows] for name, v in vals.items()} for k, vals in per_set.items()}
        return {s: paired_fits(sub[("a", s)], sub[("b", s)], s, resampling) for s in schemes}

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
