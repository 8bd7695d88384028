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
from typing import Any

import numpy as np

from megalut_cli.catalog import catalog_info, read_catalog
from megalut_cli.errors import ConfigError, InputError, Names, namer
from megalut_cli.expr import columns_used, evaluate_row_values
from megalut_cli.measure.metacal_defaults import DEFAULT_STEP, header_step
from megalut_cli.seeding import STREAM_BOOTSTRAP, rng_for
from megalut_cli.shear.bootstrap import fit_columns
from megalut_cli.shear.evaluate import check_by

#: Columns that must agree row by row between paired catalogs.
PAIRING_COLUMNS = ("case", "rea", "tru_g1", "tru_g2")
#: Columns of a metacal prediction catalog that the paired evaluation calibrates with
#: (the diagonal responses; the mean off-diagonal ones are zero for an isotropic set).
METACAL_COLUMNS = ("pre_g1_noshear", "pre_g2_noshear", "mcal_r11", "mcal_r22")
#: Default bootstrap resamples.
N_BOOTSTRAP = 1000


def group_sums(
    cell: np.ndarray,
    n_cells: int,
    g_true: np.ndarray,
    g_est: np.ndarray,
    weight: np.ndarray,
    response: np.ndarray | None = None,
    sheared_weights: tuple[np.ndarray, np.ndarray, float] | None = None,
) -> np.ndarray:
    """``(3, n_cells)`` sums of ``w``, ``w g_est``, ``w g_true`` per cell (invalid rows: w = 0);
    cell ``case * n_galaxies + galaxy`` for :func:`fit_resamples`. With a metacal
    ``response`` (per row, this component's), a fourth row ``w R`` (rows need a finite R);
    with ``sheared_weights`` ``(w_p, w_m, step)`` (the weights of the +step and -step
    versions along this component), four more: ``w_p``, ``w_p g / 2 step``, ``w_m``,
    ``w_m g / 2 step``, for the weights' selection response."""
    ok = np.isfinite(g_est) & np.isfinite(weight) & (weight > 0)
    if response is not None:
        ok &= np.isfinite(response)
    w = np.where(ok, weight, 0.0)
    rows = [w, np.where(ok, w * g_est, 0.0), np.where(ok, w * g_true, 0.0)]
    if response is not None:
        rows.append(np.where(ok, w * response, 0.0))
        if sheared_weights is not None:
            w_p, w_m, step = sheared_weights
            usable = np.isfinite(g_est) & np.isfinite(response)
            for ws in (w_p, w_m):
                ws = np.where(usable & np.isfinite(ws) & (ws > 0), ws, 0.0)
                rows += [ws, np.where(ws > 0, ws * g_est / (2.0 * step), 0.0)]
    return np.stack([np.bincount(cell, weights=r, minlength=n_cells) for r in rows])


def fit_resamples(
    sums: np.ndarray, counts: np.ndarray, n_cases: int, n_gal: int
) -> tuple[np.ndarray, np.ndarray]:
    """m and c of the per-case means of :func:`group_sums`, one per row of ``counts`` (galaxy
    multiplicities); NaN with fewer than 3 cases. With a response row, the means are divided
    by the mean response of the resample (metacal), plus the weights' selection response
    when the sums hold the sheared weights."""
    s = sums.reshape(len(sums), n_cases, n_gal) @ counts.T  # (rows, n_cases, B)
    with np.errstate(invalid="ignore", divide="ignore"):
        est = s[1] / s[0]
        if len(sums) >= 4:
            total = s.sum(axis=1)  # over the cases: (rows, B)
            response = total[3] / total[0]
            if len(sums) == 8:
                response = response + total[5] / total[4] - total[7] / total[6]
            est = est / response
        m, c = fit_columns(s[2] / s[0], est)
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
    response_a: np.ndarray | None = None,
    response_b: np.ndarray | None = None,
    sheared_weights_a: tuple[np.ndarray, np.ndarray, float] | None = None,
    sheared_weights_b: tuple[np.ndarray, np.ndarray, float] | None = None,
) -> dict[str, Any]:
    """m, c of sets ``a`` and ``b`` (one shear component, rows paired) and ``m_a - m_b``,
    ``c_a - c_b``, with 1-sigma errors from a paired bootstrap over galaxies. With per-row
    metacal responses (``response_a``, ``response_b``: ``mcal_r11`` or ``mcal_r22``), each
    set's estimates are calibrated by its mean response, recomputed in every resample, plus
    the selection response of its weights with ``sheared_weights_a`` and ``_b`` (see
    :func:`group_sums`).

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
    sums_a = group_sums(
        cell,
        n_cases * n_gal,
        g_true,
        np.asarray(est_a, dtype=float),
        wa,
        None if response_a is None else np.asarray(response_a, dtype=float),
        sheared_weights_a,
    )
    sums_b = group_sums(
        cell,
        n_cases * n_gal,
        g_true,
        np.asarray(est_b, dtype=float),
        wb,
        None if response_b is None else np.asarray(response_b, dtype=float),
        sheared_weights_b,
    )
    rng = rng_for(seed, STREAM_BOOTSTRAP)
    counts = np.vstack(
        [np.ones(n_gal), rng.multinomial(n_gal, np.full(n_gal, 1.0 / n_gal), size=n_boot)]
    )
    m_a, c_a = fit_resamples(sums_a, counts, n_cases, n_gal)
    m_b, c_b = fit_resamples(sums_b, counts, n_cases, n_gal)
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
        n_rows_a=int(np.count_nonzero(np.isfinite(est_a) & (wa > 0))),
        n_rows_b=int(np.count_nonzero(np.isfinite(est_b) & (wb > 0))),
    )
    return out


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
        [f"pre_g{i}_w_{i}{s}" for i in (1, 2) for s in "pm"] if metacal else []
    )
    schemes = ["unweighted"] + (
        ["weighted"] if all(c in t for t in (a, b) for c in weight_cols) else []
    )
    flag_col = "flags_noshear" if metacal else "flags"

    def valid(t: Mapping[str, np.ndarray], comp: str) -> np.ndarray:
        ok = np.isfinite(np.asarray(t[f"pre_{comp}{sfx}"], dtype=float))
        return ok & (np.asarray(t[flag_col]) == 0) if flag_col in t else ok

    def response(t: Mapping[str, np.ndarray], comp: str, rows: np.ndarray) -> np.ndarray | None:
        return np.asarray(t[f"mcal_r{comp[1]}{comp[1]}"], dtype=float)[rows] if metacal else None

    def sheared(
        t: Mapping[str, np.ndarray], comp: str, rows: np.ndarray, scheme: str
    ) -> tuple[np.ndarray, np.ndarray, float] | None:
        """The weights of the versions sheared along ``comp`` (the weights' selection response)."""
        if not metacal or scheme != "weighted":
            return None
        ok = valid(t, comp)
        w_p, w_m = (
            np.where(ok, np.asarray(t[f"pre_{comp}_w_{comp[1]}{sign}"], dtype=float), 0.0)[rows]
            for sign in "pm"
        )
        return w_p, w_m, metacal_step

    def evaluate(rows: np.ndarray) -> dict[str, Any]:
        res: dict[str, Any] = {}
        if not rows.any():
            return res
        for scheme in schemes:
            res[scheme] = {}
            for comp in ("g1", "g2"):
                wa = valid(a, comp).astype(float)
                wb = valid(b, comp).astype(float)
                if scheme == "weighted":
                    wa = wa * np.nan_to_num(np.asarray(a[f"pre_{comp}_w{sfx}"], dtype=float))
                    wb = wb * np.nan_to_num(np.asarray(b[f"pre_{comp}_w{sfx}"], dtype=float))
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
                    response_a=response(a, comp, rows),
                    response_b=response(b, comp, rows),
                    sheared_weights_a=sheared(a, comp, rows, scheme),
                    sheared_weights_b=sheared(b, comp, rows, scheme),
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
            "pre_g1_w_1p",
            "pre_g1_w_1m",
            "pre_g2_w_2p",
            "pre_g2_w_2m",
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
