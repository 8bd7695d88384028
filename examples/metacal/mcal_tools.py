"""Helpers of the metacal real-vs-twin experiments (issue 23; see README.md).

    python mcal_tools.py merge OUT.fits S0.fits S1.fits ...   # shear runs -> one catalog, \
case = run
    python mcal_tools.py adamom OUT.fits SIM.fits              # (b): metacal on adaptive moments
    python mcal_tools.py plain OUT.fits SIM.fits               # (c): the plain features of the \
same stamps
    python mcal_tools.py concat OUT.fits A.fits B.fits ...     # merged runs of other seeds: \
more rings
    python mcal_tools.py subset OUT.fits IN.fits CONFIG.toml   # the rows of the galaxies of \
CONFIG's index
    python mcal_tools.py paired OUT.json REAL.fits TWIN.fits [N_BOOT] [SEED]  # --twin, \
weights with R_sel
    python mcal_tools.py single OUT.json SHEARS.fits [N_BOOT] [SEED]  # one set, bootstrap \
over galaxies
    python mcal_tools.py pergalaxy SHEARS.fits [OTHER.fits]    # m of each galaxy, their scatter
    python mcal_tools.py chi2 SHEARS.fits [N_BOOT] [SEED]      # per-galaxy m with errors, chi^2
    python mcal_tools.py table RESULTS.json ...                # the README tables from --json files
    python mcal_tools.py responses SHEARS.fits ...             # mean and scatter of the responses
    python mcal_tools.py failures SHEARS.fits ... [--groups 2]  # failures as a selection \
(bootstrap)
    python mcal_tools.py snrweight SHEARS.fits ... [--snr 8 15] [--adamom]  # a smooth S/N \
weight against none

``merge``: the shear runs of one config and seed (each a constant shear, every other draw
identical: common random numbers) become the cases of one catalog: ``case`` = the run's
position, ``rea`` = its case x NREA + its rea, so that a realization group (a ring, SNC
"ring", group size NREA) is one galaxy of one run and the same galaxy in every case.
Checks that the runs hold the same galaxies, rotations, offsets and fluxes.

``adamom`` (on a ``--metacal`` simulation catalog): ``pre_g<i>_<type> :=
adamom_g<i>_<type>`` (NaN where ``flags_<type> != 0``), ``pre_g<i> := pre_g<i>_noshear`` and
the responses ``mcal_r<i><j> = (pre_g<i>_<j>p - pre_g<i>_<j>m) / (2 step)``, as ``megalut
predict`` writes them with a metacal model; no weights.

``paired``: an independent implementation of ``megalut evaluate REAL --twin TWIN --json OUT``
on metacal catalogs (same resamples for the same seed), the weighted scheme calibrated by
``<R> + R_sel`` with the selection response of the weights, ``R_sel,ii = (<g_i>_{w_ip} -
<g_i>_{w_im}) / (2 step)`` (``<g_i>_{w}``: the mean of ``pre_g<i>_noshear`` weighted by
``pre_g<i>_w_<type>``), as the single-set ``megalut evaluate`` does. ``evaluate --twin`` left
R_sel out before commit c4e8e7c (README.md, "Bug"); from then on both agreed to all digits,
until ``evaluate --twin`` took the full 2x2 responses (2026-11-28): ``paired`` keeps the
diagonal ones, so the two now differ by the off-diagonal terms (zero in expectation).

``single``: m and c of one metacal set (no twins) with errors from a bootstrap over
galaxies (``tru_real_index``), as ``megalut evaluate --twin`` computes them for each set
(the set paired with itself: ``m_a``; ``m_a - m_b`` is then zero).

``pergalaxy`` (on a merged metacal catalog with ``tru_real_index``): for each galaxy, m1, m2
of its rows alone (its per-case means calibrated by its own mean 2x2 response, then the
least-squares line over the cases), its mean R11, median ``snr`` and the relative change of
its mean ``skymad`` between the cases of positive and negative g1; then the scatter of m over
the galaxies, their mean and the correlation of m1 and m2. With ``OTHER.fits`` (an
independent run of the same galaxies, e.g. another seed): the correlation of each galaxy's m
between the two runs, the noise per galaxy (half the scatter of their differences) and the
scatter of their means.

``failures`` (on a ``megalut predict`` metacal catalog of a common-random-number set):
m of two estimators with a paired bootstrap over galaxy groups (``rea // groups``; 200
resamples, seed 1). *evaluate*: what ``megalut evaluate`` reports (rows with every version
measured, ``<R>`` per row, ``R_sel`` of the weights); it reproduces evaluate's m to all
digits. *version-selected*: failures treated as a selection, as metadetection does: each
version averaged over its own measured rows with its own weights, ``<g>`` from noshear, the
response ``(<g_i>_{jp} - <g_i>_{jm}) / (2 step)`` of the sheared versions' own estimates.

``snrweight`` (on ``megalut predict`` metacal catalogs of common-random-number sets; with
``--adamom`` on the adaptive moments ``adamom_g<i>_<type>`` instead of ``pre_g<i>_<type>``):
m and c of the unweighted estimator (what ``megalut evaluate`` reports) against the same
rows weighted by a smooth function of each version's own S/N, ``w = s((snr - LO) / (HI -
LO))`` with ``s`` the smoothstep clipped to [0, 1] (0 below LO, 1 above HI), calibrated by
the weighted mean response plus the selection response of the weights (``<g>`` of noshear
under each sheared version's weights): a selection without the sharp edge where the
adaptive moments start to fail (S/N about 6). Paired bootstrap over galaxy groups
(``rea // 2``, 100 resamples, seed 1); m in 1e-3, c in 1e-4; the last lines combine the
catalogs (inverse-variance means and their chi^2).

``plain``: the catalog without its metacal columns (``X_<type>``) and cards (``MCALSTEP``,
``MCALSEED``), for ``megalut predict`` with a simulation-calibrated model: the plain features
of the very same stamps.
"""

from __future__ import annotations

import json
import sys

import numpy as np

from megalut_cli.catalog import read_cards, read_carried_hdus, read_catalog, write_catalog
from megalut_cli.measure.metacal_defaults import DEFAULT_STEP, SEED_CARD, STEP_CARD, TYPES

SAME = ("tru_real_index", "tru_theta", "tru_dx", "tru_dy", "tru_flux", "rea")


def merge(out: str, paths: list[str]) -> None:
    tables = [read_catalog(p) for p in paths]
    cards = read_cards(paths[0])
    nrea = int(cards["NREA"][0])
    first = tables[0]
    for p, t in zip(paths[1:], tables[1:]):
        if t.colnames != first.colnames or len(t) != len(first):
            raise SystemExit(f"{p}: not the same columns or rows as {paths[0]}")
        for c in SAME:
            if not np.array_equal(np.asarray(t[c]), np.asarray(first[c])):
                raise SystemExit(
                    f"{p}: column {c} differs from {paths[0]}: not common random numbers"
                )
    cols = {}
    for c in first.colnames:
        parts = [np.asarray(t[c]) for t in tables]
        if c == "case":
            parts = [
                np.full(len(t), k, dtype=np.asarray(t["case"]).dtype) for k, t in enumerate(tables)
            ]
        elif c == "rea":
            parts = [
                np.asarray(t["case"]).astype(np.int64) * nrea + np.asarray(t["rea"]) for t in tables
            ]
        cols[c] = np.concatenate(parts)
    cards["NCASES"] = (len(tables), "shear runs merged (mcal_tools.py merge)")
    cards["NSHEARS"] = (len(tables), "cases = shear runs of common random numbers")
    write_catalog(
        out,
        cols,
        fmt="megalut.simulation",
        overwrite=True,
        cards=cards,
        history=[f"mcal_tools.py merge {' '.join(paths)}"],
        extra_hdus=read_carried_hdus(paths[0]),
    )
    print(f"{out}: {len(tables)} cases x {len(first)} rows")


def adamom(out: str, path: str) -> None:
    t = read_catalog(path)
    cards = read_cards(path)
    step = float(cards[STEP_CARD][0])
    cols = {c: np.asarray(t[c]) for c in t.colnames}
    for i in (1, 2):
        for kind in TYPES:
            g = np.asarray(t[f"adamom_g{i}_{kind}"], dtype=float)
            cols[f"pre_g{i}_{kind}"] = np.where(
                (np.asarray(t[f"flags_{kind}"]) == 0) & np.isfinite(g), g, np.nan
            )
        cols[f"pre_g{i}"] = cols[f"pre_g{i}_noshear"]
    for i in (1, 2):
        for j in (1, 2):
            cols[f"mcal_r{i}{j}"] = (cols[f"pre_g{i}_{j}p"] - cols[f"pre_g{i}_{j}m"]) / (2.0 * step)
    cards["MODEL"] = ("adamom", "pre_g* := adamom_g* (mcal_tools.py adamom)")
    write_catalog(
        out,
        cols,
        fmt="megalut.predictions",
        overwrite=True,
        cards=cards,
        history=[f"mcal_tools.py adamom {path}"],
        extra_hdus=read_carried_hdus(path),
    )
    print(f"{out}: {len(t)} rows, adaptive-moment estimates, step {step}")


def plain(out: str, path: str) -> None:
    t = read_catalog(path)
    cols = {
        c: np.asarray(t[c]) for c in t.colnames if not c.endswith(tuple(f"_{k}" for k in TYPES))
    }
    cards = {k: v for k, v in read_cards(path).items() if k not in (STEP_CARD, SEED_CARD)}
    write_catalog(
        out,
        cols,
        fmt="megalut.simulation",
        overwrite=True,
        cards=cards,
        history=[f"mcal_tools.py plain {path}"],
        extra_hdus=read_carried_hdus(path),
    )
    print(
        f"{out}: {len(t)} rows, {len(cols)} of {len(t.colnames)} columns (metacal columns and "
        "cards dropped)"
    )


def concat(out: str, paths: list[str]) -> None:
    """Merged catalogs (``merge``) of the same config and shears but other seeds, one after
    the other: the same 4 cases, ``rea`` offset so that every ring keeps its own group."""
    tables = [read_catalog(p) for p in paths]
    offset, parts = 0, []
    for t in tables:
        cols = {c: np.asarray(t[c]) for c in t.colnames}
        cols["rea"] = cols["rea"] + offset
        offset = int(cols["rea"].max()) + 1
        parts.append(cols)
    names = [c for c in tables[0].colnames if all(c in t.colnames for t in tables)]
    cols = {c: np.concatenate([p[c] for p in parts]) for c in names}
    cards = read_cards(paths[0])
    write_catalog(
        out,
        cols,
        fmt="megalut.predictions",
        overwrite=True,
        cards=cards,
        history=[f"mcal_tools.py concat {' '.join(paths)}"],
        extra_hdus=read_carried_hdus(paths[0]),
    )
    print(f"{out}: {len(cols['case'])} rows from {len(paths)} catalogs")


def subset(out: str, path: str, config: str) -> None:
    import tomllib

    rows = tomllib.load(open(config, "rb"))["galaxy"]["index"]["values"]
    t = read_catalog(path)
    keep = np.isin(np.asarray(t["tru_real_index"]), rows)
    cols = {c: np.asarray(t[c])[keep] for c in t.colnames}
    write_catalog(
        out,
        cols,
        fmt="megalut.predictions",
        overwrite=True,
        cards=read_cards(path),
        history=[f"mcal_tools.py subset {path} {config}"],
        extra_hdus=read_carried_hdus(path),
    )
    print(
        f"{out}: {int(keep.sum())} of {len(t)} rows "
        f"({len(set(np.asarray(t['tru_real_index'])[keep]))} galaxies of {config})"
    )


def _paired_sums(t, comp: int, cell: np.ndarray, n_cells: int, weighted: bool) -> np.ndarray:
    """Per-cell sums: w, w g_est, w g_true, w R and, weighted, the sheared weights' w_p,
    w_p g_est, w_m, w_m g_est."""
    i = comp
    pre = np.asarray(t[f"pre_g{i}_noshear"], dtype=float)
    tru = np.asarray(t[f"tru_g{i}"], dtype=float)
    resp = np.asarray(t[f"mcal_r{i}{i}"], dtype=float)
    usable = (
        (np.asarray(t["flags_noshear"]) == 0)
        & np.isfinite(pre)
        & np.isfinite(tru)
        & np.isfinite(resp)
    )
    w = np.where(usable, 1.0, 0.0)
    if weighted:
        wn = np.asarray(t[f"pre_g{i}_w_noshear"], dtype=float)
        w = np.where(usable & np.isfinite(wn) & (wn > 0), wn, 0.0)
    g = np.where(usable, pre, 0.0)
    rows = [w, w * g, w * np.where(usable, tru, 0.0), w * np.where(usable, resp, 0.0)]
    if weighted:
        for kind in (f"{i}p", f"{i}m"):
            ws = np.asarray(t[f"pre_g{i}_w_{kind}"], dtype=float)
            ws = np.where(usable & np.isfinite(ws) & (ws > 0), ws, 0.0)
            rows += [ws, ws * g]
    return np.stack([np.bincount(cell, weights=r, minlength=n_cells) for r in rows])


def _paired_fit(sums: np.ndarray, counts: np.ndarray, n_cases: int, n_gal: int, step: float):
    from megalut_cli.shear.bootstrap import fit_columns

    s = sums.reshape(len(sums), n_cases, n_gal) @ counts.T  # (rows, cases, B)
    tot = s.sum(axis=1)  # (rows, B): every case together
    with np.errstate(invalid="ignore", divide="ignore"):
        resp = tot[3] / tot[0]
        if len(sums) > 4:
            resp = resp + (tot[5] / tot[4] - tot[7] / tot[6]) / (2.0 * step)
        est = s[1] / s[0] / resp
        return fit_columns(s[2] / s[0], est)


def paired(out: str, path_a: str, path_b: str, n_boot: int = 1000, seed: int = 1) -> None:
    from megalut_cli.seeding import STREAM_BOOTSTRAP, rng_for

    a, b = read_catalog(path_a), read_catalog(path_b)
    for c in ("case", "rea", "tru_g1", "tru_g2", "tru_real_index"):
        if not np.array_equal(np.asarray(a[c]), np.asarray(b[c])):
            raise SystemExit(f"{path_a} and {path_b} are not paired (column {c})")
    step = float(read_cards(path_a)[STEP_CARD][0])
    gal_ids, gi = np.unique(np.asarray(a["tru_real_index"]), return_inverse=True)
    case_ids, ci = np.unique(np.asarray(a["case"]), return_inverse=True)
    n_gal, n_cases = gal_ids.size, case_ids.size
    cell = ci.ravel() * n_gal + gi.ravel()
    weighted = all(f"pre_g{i}_w_{k}" in t.colnames for t in (a, b) for i in (1, 2) for k in TYPES)
    result: dict = {
        "names": ["real", "twin"],
        "galaxy_column": "tru_real_index",
        "n_boot": n_boot,
        "seed": seed,
        "metacal": True,
        "selection_response": "weights (mcal_tools.py paired)",
        "overall": {},
    }
    for scheme in ["unweighted"] + (["weighted"] if weighted else []):
        result["overall"][scheme] = {}
        for i in (1, 2):
            rng = rng_for(seed, STREAM_BOOTSTRAP)
            counts = np.vstack(
                [np.ones(n_gal), rng.multinomial(n_gal, np.full(n_gal, 1.0 / n_gal), size=n_boot)]
            )
            w = scheme == "weighted"
            m_a, c_a = _paired_fit(
                _paired_sums(a, i, cell, n_cases * n_gal, w), counts, n_cases, n_gal, step
            )
            m_b, c_b = _paired_fit(
                _paired_sums(b, i, cell, n_cases * n_gal, w), counts, n_cases, n_gal, step
            )
            r: dict = {}
            for name, v in (
                ("m_a", m_a),
                ("c_a", c_a),
                ("m_b", m_b),
                ("c_b", c_b),
                ("dm", m_a - m_b),
                ("dc", c_a - c_b),
            ):
                boot = v[1:][np.isfinite(v[1:])]
                r[name] = float(v[0]) if np.isfinite(v[0]) else None
                r[f"{name}_err"] = float(np.std(boot, ddof=1)) if boot.size > 1 else None
            r.update(n_galaxies=int(n_gal), n_cases=int(n_cases), n_boot=int(n_boot))
            result["overall"][scheme][f"g{i}"] = r
    with open(out, "w") as f:
        json.dump(result, f, indent=1)
    print(f"{out}: paired metacal biases, weighted scheme with the selection response")


def _f(v: float | None, e: float | None, scale: float = 1e3) -> str:
    if v is None:
        return "n/a"
    return f"{v * scale:+.2f} ± {e * scale:.2f}" if e is not None else f"{v * scale:+.2f}"


def responses(paths: list[str]) -> None:
    """Per estimator (a ``megalut predict`` or ``adamom`` catalog): mean and scatter of the
    per-row diagonal responses and of the noshear estimates, on the rows ``evaluate`` uses
    (noshear features measured, every response finite); with weights, the weighted mean
    response and the effective scatter sqrt(N sum w^2 (R - <R>)^2) / sum w that sets the
    error of <R> (the error on m of a common-random-number set, whose shears share it)."""
    print(
        "| catalog | rows | <R11> | sd R11 | <R22> | sd R22 | sd g1 | weighted <R11> | "
        "eff. sd R11 | weighted <R22> | eff. sd R22 |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for p in paths:
        t = read_catalog(p)
        r11, r22 = (np.asarray(t[c], dtype=float) for c in ("mcal_r11", "mcal_r22"))
        g1 = np.asarray(t["pre_g1"], dtype=float)
        ok = np.isfinite(r11) & np.isfinite(r22) & np.isfinite(g1)
        if "flags_noshear" in t.colnames:
            ok &= np.asarray(t["flags_noshear"]) == 0
        row = [p.rsplit("/", 1)[-1], f"{ok.sum()}"]
        for r in (r11, r22):
            row += [f"{r[ok].mean():.4f}", f"{r[ok].std():.3f}"]
        row.append(f"{g1[ok].std():.3f}")
        for i, r in ((1, r11), (2, r22)):
            if f"pre_g{i}_w" in t.colnames:
                w = np.asarray(t[f"pre_g{i}_w"], dtype=float)
                good = ok & np.isfinite(w)
                mean = np.average(r[good], weights=w[good])
                eff = (
                    np.sqrt(good.sum() * np.sum(w[good] ** 2 * (r[good] - mean) ** 2))
                    / w[good].sum()
                )
                row += [f"{mean:.4f}", f"{eff:.3f}"]
            else:
                row += ["", ""]
        print("| " + " | ".join(row) + " |")


VERSIONS = ("noshear", "1p", "1m", "2p", "2m")


def _failure_sums(t, weighted: bool, groups: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per (galaxy group, case) sums of weights and weighted estimates: for each component
    and version, first on the rows evaluate uses (noshear weights, per-row responses), then
    on each version's own measured rows; the cases' true shears."""
    cases, ci = np.unique(np.asarray(t["case"]), return_inverse=True)
    grp = np.asarray(t["rea"]) // groups
    idx = grp * cases.size + ci
    n_cells = (grp.max() + 1) * cases.size

    def col(name: str) -> np.ndarray:
        return np.asarray(t[name], dtype=float)

    measured = {
        k: (np.asarray(t[f"flags_{k}"]) == 0)
        & np.isfinite(col(f"pre_g1_{k}"))
        & np.isfinite(col(f"pre_g2_{k}"))
        for k in VERSIONS
    }
    every = measured["noshear"] & np.all(
        [np.isfinite(col(f"mcal_r{i}{j}")) for i in (1, 2) for j in (1, 2)], axis=0
    )

    def weight(kind: str, comp: int, rows: np.ndarray) -> np.ndarray:
        if not weighted:
            return rows.astype(float)
        w = col(f"pre_g{comp}_w_{kind}")
        return np.where(rows & np.isfinite(w) & (w > 0), w, 0.0)

    q = []
    for i in (1, 2):
        g_ns = np.nan_to_num(col(f"pre_g{i}_noshear"))
        w0 = weight("noshear", i, every)
        q += [w0, w0 * g_ns, *(w0 * np.nan_to_num(col(f"mcal_r{i}{j}")) for j in (1, 2))]
        for kind in VERSIONS[1:]:  # the selection response of the weights (evaluate's R_sel)
            wk = weight(kind, i, every) if weighted else w0
            q += [wk, wk * g_ns]
        for kind in VERSIONS:
            wk = weight(kind, i, measured[kind])
            q += [wk, wk * np.nan_to_num(col(f"pre_g{i}_{kind}"))]
    sums = np.stack([np.bincount(idx, weights=x, minlength=n_cells) for x in q]).reshape(
        len(q), -1, cases.size
    )
    tru = np.array([[col(f"tru_g{i}")[ci == c][0] for i in (1, 2)] for c in range(cases.size)])
    return sums, tru, np.array([measured["noshear"].mean(), every.mean()])


def _failure_m(s: np.ndarray, tru: np.ndarray, step: float, weighted: bool) -> np.ndarray:
    """m (2 estimators x 2 components) from the per-case sums ``s`` of :func:`_failure_sums`."""
    per = s.shape[0] // 2
    out = np.zeros((2, 2))
    for e, name in enumerate(("evaluate", "version")):
        g, resp = np.zeros((tru.shape[0], 2)), np.zeros((2, 2))
        for i in range(2):
            q = s[i * per : (i + 1) * per]
            if name == "evaluate":
                g[:, i] = q[1] / q[0]
                resp[i] = q[2].sum() / q[0].sum(), q[3].sum() / q[0].sum()
                if weighted:
                    avg = {
                        k: q[4 + 2 * n + 1].sum() / q[4 + 2 * n].sum()
                        for n, k in enumerate(VERSIONS[1:])
                    }
                    resp[i] += [(avg[f"{j}p"] - avg[f"{j}m"]) / (2 * step) for j in (1, 2)]
            else:
                avg = {
                    k: q[12 + 2 * n + 1].sum() / q[12 + 2 * n].sum() for n, k in enumerate(VERSIONS)
                }
                g[:, i] = q[13] / q[12]
                resp[i] = [(avg[f"{j}p"] - avg[f"{j}m"]) / (2 * step) for j in (1, 2)]
        cal = np.linalg.solve(resp, g.T).T
        for i in range(2):
            slope = np.polyfit(tru[:, i], cal[:, i], 1)[0]
            out[e, i] = slope - 1.0
    return out


def failures(paths: list[str], groups: int = 2, n_boot: int = 200, seed: int = 1) -> None:
    """m of evaluate's estimator and of the version-selected one, and their difference, with
    a paired bootstrap over galaxy groups (units of 1e-3)."""
    print(
        "| catalog | scheme | measured (noshear / every version) | m evaluate | "
        "m version-selected | difference |"
    )
    print("|---|---|---|---|---|---|")
    for p in paths:
        t = read_catalog(p)
        step = float(read_cards(p).get(STEP_CARD, (0.01, ""))[0])
        for weighted in (False, True) if "pre_g1_w_noshear" in t.colnames else (False,):
            sums, tru, frac = _failure_sums(t, weighted, groups)
            n_groups = sums.shape[1]
            rng = np.random.default_rng(seed)
            counts = np.vstack(
                [np.ones(n_groups)]
                + [
                    rng.multinomial(n_groups, np.full(n_groups, 1 / n_groups))
                    for _ in range(n_boot)
                ]
            )
            resampled = np.einsum("bg,qgc->bqc", counts, sums)
            m = np.array([_failure_m(r, tru, step, weighted) for r in resampled])

            def cell(a: np.ndarray) -> str:
                return " / ".join(_f(a[0, i], a[1:, i].std()) for i in (0, 1))

            print(
                f"| {p.rsplit('/', 1)[-1]} | {'weighted' if weighted else 'unweighted'} | "
                f"{frac[0]:.4f} / {frac[1]:.4f} | {cell(m[:, 0])} | {cell(m[:, 1])} | "
                f"{cell(m[:, 1] - m[:, 0])} |"
            )


def _snr_sums(t, lo: float, hi: float, adamom: bool) -> tuple[dict, np.ndarray, np.ndarray]:
    """Per (case, galaxy pair) sums of the unweighted and S/N-weighted estimates, responses
    and the weights' selection terms, on the rows with every version measured."""
    cases, ci = np.unique(np.asarray(t["case"]), return_inverse=True)
    groups, gi = np.unique(np.asarray(t["rea"]) // 2, return_inverse=True)
    key = ci * groups.size + gi
    name = "adamom_g{i}_{k}" if adamom else "pre_g{i}_{k}"
    g = {
        (i, k): np.asarray(t[name.format(i=i, k=k)], dtype=float) for i in (1, 2) for k in VERSIONS
    }
    every = np.logical_and.reduce(
        [
            (np.asarray(t[f"flags_{k}"]) == 0) & np.isfinite(g[(1, k)]) & np.isfinite(g[(2, k)])
            for k in VERSIONS
        ]
    )
    g = {k: np.where(every, v, 0.0) for k, v in g.items()}

    def smooth(k: str) -> np.ndarray:
        x = np.clip((np.nan_to_num(np.asarray(t[f"snr_{k}"], dtype=float)) - lo) / (hi - lo), 0, 1)
        return np.where(every, x * x * (3 - 2 * x), 0.0)

    weights = {"none": every.astype(float), "snr": smooth("noshear")}
    weights.update({k: smooth(k) for k in VERSIONS[1:]})
    q: dict[str, np.ndarray] = {}
    for label in ("none", "snr"):
        w = weights[label]
        q[f"w:{label}"] = w
        for i in (1, 2):
            q[f"g{i}:{label}"] = w * g[(i, "noshear")]
            for j in (1, 2):
                q[f"R{i}{j}:{label}"] = w * (g[(i, f"{j}p")] - g[(i, f"{j}m")])
    for k in VERSIONS[1:]:
        q[f"w:{k}"] = weights[k]
        for i in (1, 2):
            q[f"g{i}:{k}"] = weights[k] * g[(i, "noshear")]
    n = cases.size * groups.size
    sums = {
        k: np.bincount(key, weights=v, minlength=n).reshape(cases.size, -1) for k, v in q.items()
    }
    tru = np.array(
        [[np.asarray(t[f"tru_g{i}"])[ci == c][0] for i in (1, 2)] for c in range(cases.size)]
    )
    return sums, tru, every


def _snr_mc(sums: dict, counts: np.ndarray, tru: np.ndarray, step: float) -> np.ndarray:
    """(m1, c1, m2, c2) of the unweighted and the S/N-weighted estimator, galaxy pairs
    counted ``counts`` times."""
    per_case = {k: v @ counts for k, v in sums.items()}
    total = {k: v.sum() for k, v in per_case.items()}
    out = []
    for label in ("none", "snr"):
        resp = np.array(
            [
                [total[f"R{i}{j}:{label}"] / total[f"w:{label}"] / (2 * step) for j in (1, 2)]
                for i in (1, 2)
            ]
        )
        if label == "snr":
            avg = {k: [total[f"g{i}:{k}"] / total[f"w:{k}"] for i in (1, 2)] for k in VERSIONS[1:]}
            resp += np.array(
                [[(avg[f"{j}p"][i] - avg[f"{j}m"][i]) / (2 * step) for j in (1, 2)] for i in (0, 1)]
            )
        g = np.stack([per_case[f"g{i}:{label}"] / per_case[f"w:{label}"] for i in (1, 2)], axis=1)
        cal = np.linalg.solve(resp, g.T).T
        row = []
        for i in range(2):
            slope, intercept = np.polyfit(tru[:, i], cal[:, i], 1)
            row += [slope - 1.0, intercept]
        out.append(row)
    return np.array(out)


def snrweight(
    paths: list[str], lo: float = 8.0, hi: float = 15.0, adamom: bool = False, n_boot: int = 100
) -> None:
    """The unweighted metacal estimator against a smooth S/N weight (see the docstring)."""
    print(
        f"S/N weight: smoothstep from {lo:g} to {hi:g}; {'adaptive moments' if adamom else 'pre_g'}"
    )
    print("| catalog | estimator | rows | m1 | m2 | c1 | c2 |")
    print("|---|---|---|---|---|---|---|")
    results = []
    for p in paths:
        t = read_catalog(p)
        step = float(read_cards(p).get(STEP_CARD, (DEFAULT_STEP, ""))[0])
        sums, tru, every = _snr_sums(t, lo, hi, adamom)
        n_groups = next(iter(sums.values())).shape[1]
        rng = np.random.default_rng(1)
        full = _snr_mc(sums, np.ones(n_groups), tru, step)
        boot = np.array(
            [
                _snr_mc(
                    sums,
                    np.bincount(rng.integers(0, n_groups, n_groups), minlength=n_groups),
                    tru,
                    step,
                )
                for _ in range(n_boot)
            ]
        )
        err = boot.std(axis=0)
        diff, diff_err = full[1] - full[0], (boot[:, 1] - boot[:, 0]).std(axis=0)
        results.append((full, err, diff, diff_err))
        name = p.rsplit("/", 1)[-1]
        for e, label in enumerate(("unweighted", "S/N-weighted")):
            cells = [_f(full[e, k], err[e, k], 1e3 if k in (0, 2) else 1e4) for k in (0, 2, 1, 3)]
            print(f"| {name} | {label} | {every.mean():.4f} | " + " | ".join(cells) + " |")
        print(
            f"| {name} | difference | | {_f(diff[0], diff_err[0])} | "
            f"{_f(diff[2], diff_err[2])} | | |"
        )
    if len(results) > 1:
        for e, label in enumerate(("unweighted", "S/N-weighted", "difference")):
            vals = np.array([r[2] if e == 2 else r[0][e] for r in results])
            errs = np.array([r[3] if e == 2 else r[1][e] for r in results])
            w = 1.0 / errs**2
            mean = (w * vals).sum(axis=0) / w.sum(axis=0)
            chi2 = (w * (vals - mean) ** 2).sum(axis=0)
            mean_err = 1.0 / np.sqrt(w.sum(axis=0))
            print(
                f"| all ({len(results)}) | {label} | | "
                f"{_f(mean[0], mean_err[0])} (chi2 {chi2[0]:.1f}) | "
                f"{_f(mean[2], mean_err[2])} (chi2 {chi2[2]:.1f}) | | |"
            )


def single(out: str, path: str, n_boot: int = 1000, seed: int = 1) -> None:
    from megalut_cli.shear.paired import paired_evaluation

    t = read_catalog(path)
    columns = {c: np.asarray(t[c]) for c in t.colnames}
    step = float(read_cards(path).get(STEP_CARD, [DEFAULT_STEP])[0])
    res = paired_evaluation(
        columns, columns, n_boot=n_boot, seed=seed, names=("real", "real"), metacal_step=step
    )
    with open(out, "w") as f:
        json.dump(res, f, indent=1)
    for scheme, comps in res["overall"].items():
        cells = [
            f"m_{comp} {_f(r['m_a'], r['m_a_err'])} e-3, c_{comp} "
            f"{_f(r['c_a'], r['c_a_err'], 1e4)} e-4"
            for comp, r in comps.items()
        ]
        print(f"{path} {scheme}: {'; '.join(cells)} ({comps['g1']['n_galaxies']} galaxies)")


def _pergalaxy_m(path: str) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Galaxy ids, per-galaxy ``(m1, m2)`` and the table lines of :func:`pergalaxy`."""
    from megalut_cli.shear.bias import calibrate_by_response

    t = read_catalog(path)
    col = {c: np.asarray(t[c], dtype=float) for c in t.colnames if c != "flags_noshear"}
    gal, case = np.asarray(t["tru_real_index"]), np.asarray(t["case"])
    ok = np.asarray(t["flags_noshear"]) == 0
    for c in ("pre_g1_noshear", "pre_g2_noshear", "mcal_r11", "mcal_r12", "mcal_r21", "mcal_r22"):
        ok &= np.isfinite(col[c])
    cases = np.unique(case)
    ids, rows = np.unique(gal), []
    lines = [
        "| galaxy | m1 (%) | m2 (%) | R11 | median snr | skymad, g1 > 0 against < 0 (%) |",
        "|---|---|---|---|---|---|",
    ]
    for g in ids:
        sel = ok & (gal == g)
        r = [[col[f"mcal_r{i}{j}"][sel].mean() for j in (1, 2)] for i in (1, 2)]
        per = [sel & (case == k) for k in cases]
        tru = [np.array([col[f"tru_g{i}"][p].mean() for p in per]) for i in (1, 2)]
        est = [np.array([col[f"pre_g{i}_noshear"][p].mean() for p in per]) for i in (1, 2)]
        cal = calibrate_by_response(r[0][0], r[0][1], r[1][0], r[1][1], est[0], est[1])
        m = [np.polyfit(tru[i], cal[i], 1)[0] - 1.0 for i in (0, 1)]
        rows.append(m)
        snr = np.nanmedian(col["snr"][sel]) if "snr" in col else np.nan
        sky = col.get("skymad", np.full(gal.size, np.nan))
        g1 = col["tru_g1"]
        dsky = (sky[sel & (g1 > 0)].mean() / sky[sel & (g1 < 0)].mean() - 1.0) * 100
        lines.append(
            f"| {int(g)} | {100 * m[0]:+.2f} | {100 * m[1]:+.2f} | {r[0][0]:.3f} | {snr:.1f} | "
            f"{dsky:+.2f} |"
        )
    return ids, np.array(rows), lines


def pergalaxy(paths: list[str]) -> None:
    ids, a, lines = _pergalaxy_m(paths[0])
    print("\n".join(lines))
    print(
        f"\n{len(a)} galaxies: sd of m1, m2 {100 * a[:, 0].std(ddof=1):.2f} %, "
        f"{100 * a[:, 1].std(ddof=1):.2f} %; mean {100 * a[:, 0].mean():+.3f} %, "
        f"{100 * a[:, 1].mean():+.3f} %; corr(m1, m2) {np.corrcoef(a[:, 0], a[:, 1])[0, 1]:+.2f}"
    )
    if len(paths) > 1:  # an independent run of the same galaxies: intrinsic or noise?
        ids_b, b, _ = _pergalaxy_m(paths[1])
        if not np.array_equal(ids, ids_b):
            raise SystemExit(f"{paths[0]} and {paths[1]} hold other galaxies")
        for k in (0, 1):
            corr = np.corrcoef(a[:, k], b[:, k])[0, 1]
            noise = (a[:, k] - b[:, k]).std(ddof=1) / 2  # per galaxy, of the mean of the two
            print(
                f"m{k + 1} against {paths[1]}: corr {corr:+.2f}; noise per galaxy of the mean "
                f"of both {100 * noise:.2f} %, scatter of that mean "
                f"{100 * ((a[:, k] + b[:, k]) / 2).std(ddof=1):.2f} %"
            )


def _ring_m(weights: np.ndarray, sums: dict, n: np.ndarray) -> np.ndarray:
    """(m1, m2) of one galaxy from its per-(ring, case) ``sums`` and counts ``n``, each ring
    counted ``weights`` times, calibrated by its mean response."""
    from megalut_cli.shear.bias import calibrate_by_response

    cnt = weights @ n
    mean = {c: (weights @ v) / cnt for c, v in sums.items()}
    r = [[(weights @ sums[f"mcal_r{i}{j}"]).sum() / cnt.sum() for j in (1, 2)] for i in (1, 2)]
    cal = calibrate_by_response(
        r[0][0], r[0][1], r[1][0], r[1][1], mean["pre_g1_noshear"], mean["pre_g2_noshear"]
    )
    return np.array([np.polyfit(mean[f"tru_g{i + 1}"], cal[i], 1)[0] - 1.0 for i in (0, 1)])


def chi2(path: str, n_boot: int = 200, seed: int = 1) -> None:
    """Per-galaxy m (calibrated by the galaxy's own mean response) with its error from a
    bootstrap over the galaxy's rings, and the chi^2 of the galaxies about their mean: is the
    scatter between galaxies what their noise explains? (issue 39)"""
    t = read_catalog(path)
    nrea = int(read_cards(path)["NREA"][0])
    gal, case = np.asarray(t["tru_real_index"]), np.asarray(t["case"])
    ring = np.asarray(t["rea"]) // nrea
    cols = ("pre_g1_noshear", "pre_g2_noshear", "mcal_r11", "mcal_r12", "mcal_r21", "mcal_r22")
    val = {c: np.asarray(t[c], dtype=float) for c in (*cols, "tru_g1", "tru_g2")}
    ok = np.asarray(t["flags_noshear"]) == 0
    for c in cols:
        ok &= np.isfinite(val[c])
    cases = np.unique(case)
    rng = np.random.default_rng(seed)
    out = []
    for g in np.unique(gal):
        sel = ok & (gal == g)
        rings, r_idx = np.unique(ring[sel], return_inverse=True)
        c_idx = np.searchsorted(cases, case[sel])
        # per (ring, case) sums of every column and the counts
        shape = (rings.size, cases.size)
        flat = r_idx * cases.size + c_idx
        sums = {
            c: np.bincount(flat, weights=val[c][sel], minlength=rings.size * cases.size).reshape(
                shape
            )
            for c in val
        }
        n = np.bincount(flat, minlength=rings.size * cases.size).reshape(shape).astype(float)

        m = _ring_m(np.ones(rings.size), sums, n)
        boot = np.array(
            [
                _ring_m(
                    np.bincount(rng.integers(0, rings.size, rings.size), minlength=rings.size),
                    sums,
                    n,
                )
                for _ in range(n_boot)
            ]
        )
        out.append((int(g), rings.size, *m, *boot.std(axis=0, ddof=1)))
    a = np.array(out)
    print("| galaxy | rings | m1 (%) | m2 (%) |")
    print("|---|---|---|---|")
    for row in a:
        print(
            f"| {int(row[0])} | {int(row[1])} | {100 * row[2]:+.2f} ± {100 * row[4]:.2f} | "
            f"{100 * row[3]:+.2f} ± {100 * row[5]:.2f} |"
        )
    for k, comp in ((0, "m1"), (1, "m2")):
        m, e = a[:, 2 + k], a[:, 4 + k]
        w = 1.0 / e**2
        mean = (w * m).sum() / w.sum()
        pull = (m - mean) / e
        chi = (pull**2).sum()
        worst = int(a[np.argmax(np.abs(pull)), 0])
        print(
            f"{comp}: {len(m)} galaxies, scatter {100 * m.std(ddof=1):.2f} %, median noise "
            f"{100 * np.median(e):.2f} %, chi2 {chi:.1f} for {len(m) - 1} dof "
            f"(chi2/dof {chi / (len(m) - 1):.2f}); largest |pull| "
            f"{np.abs(pull).max():.1f} (galaxy {worst})"
        )


def table(paths: list[str]) -> None:
    """One row per JSON file (megalut evaluate --twin --json) and scheme: m in units of
    1e-3, c in units of 1e-4."""
    print(
        "| run | scheme | comp | m_real (1e-3) | m_twin (1e-3) | m_real − m_twin (1e-3) | "
        "c_real (1e-4) | c_twin (1e-4) | c_real − c_twin (1e-4) | galaxies |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for p in paths:
        res = json.load(open(p))
        for scheme, comps in res["overall"].items():
            for comp, r in comps.items():
                print(
                    f"| {p.rsplit('/', 1)[-1].removesuffix('.json')} | {scheme} | {comp} | "
                    f"{_f(r['m_a'], r['m_a_err'])} | {_f(r['m_b'], r['m_b_err'])} | "
                    f"{_f(r['dm'], r['dm_err'])} | {_f(r['c_a'], r['c_a_err'], 1e4)} | "
                    f"{_f(r['c_b'], r['c_b_err'], 1e4)} | {_f(r['dc'], r['dc_err'], 1e4)} | "
                    f"{r['n_galaxies']} |"
                )


if __name__ == "__main__":
    cmd, args = sys.argv[1], sys.argv[2:]
    if cmd == "merge":
        merge(args[0], args[1:])
    elif cmd == "adamom":
        adamom(args[0], args[1])
    elif cmd == "plain":
        plain(args[0], args[1])
    elif cmd == "concat":
        concat(args[0], args[1:])
    elif cmd == "subset":
        subset(args[0], args[1], args[2])
    elif cmd == "paired":
        paired(args[0], args[1], args[2], *(int(x) for x in args[3:5]))
    elif cmd == "pergalaxy":
        pergalaxy(args)
    elif cmd == "chi2":
        chi2(args[0], *(int(x) for x in args[1:3]))
    elif cmd == "single":
        single(args[0], args[1], *(int(x) for x in args[2:4]))
    elif cmd == "table":
        table(args)
    elif cmd == "responses":
        responses(args)
    elif cmd == "failures":
        if "--groups" in args:
            k = args.index("--groups")
            failures(args[:k] + args[k + 2 :], groups=int(args[k + 1]))
        else:
            failures(args)
    elif cmd == "snrweight":
        lo, hi = 8.0, 15.0
        if "--snr" in args:
            k = args.index("--snr")
            lo, hi = float(args[k + 1]), float(args[k + 2])
            args = args[:k] + args[k + 3 :]
        adamom = "--adamom" in args
        snrweight([a for a in args if a != "--adamom"], lo, hi, adamom)
    else:
        raise SystemExit(__doc__)
