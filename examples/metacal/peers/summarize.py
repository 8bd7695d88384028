"""Tables of the peer comparison from the outputs of run.sh (markdown on stdout).

    python examples/metacal/peers/summarize.py WORKDIR [--bootstrap 500]

Reads WORKDIR/{A,B}-<estimator>.json (megalut evaluate), the catalogs, and times.txt. Adds:
* sigma_g, the shear error per galaxy: sqrt(N) x the standard error of the calibrated mean
  shear over the rows used, SE = sqrt(sum w^2 (e - R g)^2) / (sum w R), with N all the stamps
  (failures count as galaxies lost), R = 1 for the simulation-calibrated estimate, else the
  (weighted) mean response; per component, then averaged over g1 and g2. n_eff is relative to
  (1) unweighted: (sigma_ref / sigma_g)^2. Rows are treated as independent galaxies (what a
  survey would see), although set A shows each galaxy under 4 shears.
* for AnaCal, its own estimator as a cross-check of the metacal-layout evaluation: per case
  <e>/<R> (the case's own mean response), m and c by megalut_cli.shear.bias.fit_bias over
  cases, errors from a bootstrap over galaxy pairs (rea // 2; both sets together for B).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from megalut_cli.catalog import read_catalog
from megalut_cli.shear.bias import fit_bias

EST = [
    ("sc", "(1) megalut, simulation-calibrated"),
    ("mcal-nn", "(2) megalut + metacal"),
    ("mcal-nn4", "(2') megalut + metacal, networks averaged (d4)"),
    ("mcal-am", "(3) metacal, adaptive moments"),
    ("anacal", "(4) AnaCal"),
]


def load_times(path: str) -> dict[str, tuple[float, float]]:
    out: dict[str, tuple[float, float]] = {}
    if os.path.exists(path):
        for line in open(path):
            p = line.split()
            if len(p) == 4:
                try:
                    out[p[0]] = (float(p[1]) + float(p[2]), float(p[3]))
                except ValueError:
                    pass
    return out


def columns(cat, est: str, scheme: str, i: int):
    """(estimate, weight, true shear, is metacal) of component i for the rows used."""
    n = len(cat)
    tru = np.asarray(cat[f"tru_g{i}"], float)
    if est == "sc":
        e = np.asarray(cat[f"pre_g{i}"], float)
        ok = (np.asarray(cat["flags"]) == 0) & np.isfinite(e) & np.isfinite(tru)
        w = np.asarray(cat[f"pre_g{i}_w"], float) if scheme == "weighted" else np.ones(n)
        return e, np.where(ok & np.isfinite(w), w, 0.0), tru, None
    e = np.asarray(cat[f"pre_g{i}_noshear"], float)
    r = np.asarray(cat[f"mcal_r{i}{i}"], float)
    ok = (np.asarray(cat["flags_noshear"]) == 0) & np.isfinite(e) & np.isfinite(tru)
    for j in (1, 2):
        ok &= np.isfinite(np.asarray(cat[f"mcal_r{i}{j}"], float))
    w = np.asarray(cat[f"pre_g{i}_w_noshear"], float) if scheme == "weighted" else np.ones(n)
    return e, np.where(ok & np.isfinite(w), w, 0.0), tru, r


def sigma_g(cat, est: str, scheme: str, r_mean: list[float] | None) -> float:
    out = []
    for i in (1, 2):
        e, w, g, r = columns(cat, est, scheme, i)
        R = (
            1.0
            if r is None
            else (r_mean[i - 1] if r_mean is not None else np.sum(w * np.nan_to_num(r)) / np.sum(w))
        )
        res = np.where(w > 0, e - R * g, 0.0)
        se = np.sqrt(np.sum(w**2 * res**2)) / (np.sum(w) * R)
        out.append(se * np.sqrt(len(cat)))
    return float(np.mean(out))


def anacal_own(
    cats: list, n_boot: int, seed: int = 1
) -> dict[str, tuple[float, float, float, float]]:
    """AnaCal's <e>/<R> per case, m and c over cases, bootstrap over galaxy pairs (rea // 2)."""
    rng = np.random.default_rng(seed)
    res = {}
    for i in (1, 2):

        def fit(weights_per_group=None, i=i):
            ms, cs = [], []
            for cat in cats:
                case = np.asarray(cat["case"])
                grp = np.asarray(cat["rea"]) // 2
                e = np.asarray(cat[f"anacal_e{i}"], float)
                r = np.asarray(cat[f"anacal_de{i}_dg{i}"], float)
                ok = (np.asarray(cat["flags_noshear"]) == 0) & np.isfinite(e) & np.isfinite(r)
                w = ok.astype(float) if weights_per_group is None else ok * weights_per_group[grp]
                cases = np.unique(case)
                idx = np.searchsorted(cases, case)
                se = np.bincount(idx, w * np.nan_to_num(e), len(cases))
                sr = np.bincount(idx, w * np.nan_to_num(r), len(cases))
                tru = np.bincount(
                    idx, np.asarray(cat[f"tru_g{i}"], float), len(cases)
                ) / np.bincount(idx, None, len(cases))
                f = fit_bias(tru, se / sr)
                ms.append(f.m)
                cs.append(f.c)
            return ms, cs

        m0, c0 = fit()
        ngrp = int(max(np.asarray(cat["rea"]).max() for cat in cats)) // 2 + 1
        boot_m, boot_c = [], []
        for _ in range(n_boot):
            draw = np.bincount(rng.integers(0, ngrp, ngrp), minlength=ngrp).astype(float)
            mb, cb = fit(draw)
            boot_m.append(mb)
            boot_c.append(cb)
        boot_m, boot_c = np.array(boot_m), np.array(boot_c)
        res[f"g{i}"] = (
            m0,
            boot_m.std(axis=0),
            c0,
            boot_c.std(axis=0),
            (m0[0] - m0[-1], float(np.std(boot_m[:, 0] - boot_m[:, -1])))
            if len(cats) == 2
            else None,
        )
    return res


def pct(v, e=None, nd=1):
    if v is None:
        return "–"
    s = f"{100 * v:+.{nd}f}"
    return s if e is None else f"{s} ± {100 * e:.{nd}f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("workdir")
    ap.add_argument("--bootstrap", type=int, default=500)
    a = ap.parse_args(argv)
    W = a.workdir
    times = load_times(os.path.join(W, "times.txt"))
    engine = (
        open(os.path.join(W, "engine.txt")).read().split(":")[-1].strip()
        if os.path.exists(os.path.join(W, "engine.txt"))
        else "?"
    )
    print(f"metacal image engine: {engine}\n")

    # ---------------------------------------------------------------- set A
    if os.path.exists(os.path.join(W, "A-sc.json")):
        print(
            "## Set A: Sérsic, common random numbers (4 shears x 5000 galaxy pairs = "
            "40 000 stamps)\n"
        )
        print(
            "m, c in per cent (c in 1e-4 below); errors: bootstrap over galaxy pairs (megalut "
            "evaluate, 500 resamples)\n"
        )
        print(
            "| estimator | scheme | m1 | m2 | c1 (1e-4) | c2 (1e-4) | <R11>, <R22> | rows used | "
            "sigma_g per galaxy | n_eff / n_eff(1) |"
        )
        print("|---|---|---|---|---|---|---|---|---|---|")
        ref = None
        for est, label in EST:
            path = os.path.join(W, f"A-{est}.json")
            if not os.path.exists(path):
                continue
            d = json.load(open(path))
            cat = read_catalog(os.path.join(W, f"A-{est}.fits"))
            for scheme in ("unweighted", "weighted"):
                if scheme not in d:
                    continue
                f1, f2 = d[scheme]["g1"], d[scheme]["g2"]
                resp = (d.get("metacal") or {}).get("response", {}).get(scheme)
                sel = (d.get("metacal") or {}).get("selection_response", {}).get(scheme)
                rtxt = "–" if resp is None else f"{resp[0][0]:.4f}, {resp[1][1]:.4f}"
                if sel is not None:
                    rtxt += f" (+ R_sel {sel[0][0]:+.4f}, {sel[1][1]:+.4f})"
                rm = (
                    None
                    if resp is None
                    else [
                        resp[0][0] + (sel[0][0] if sel else 0),
                        resp[1][1] + (sel[1][1] if sel else 0),
                    ]
                )
                sg = sigma_g(cat, est, scheme, rm)
                if ref is None:
                    ref = sg
                print(
                    f"| {label} | {scheme} | {pct(f1['m'], f1['m_err'], 2)} | "
                    f"{pct(f2['m'], f2['m_err'], 2)} | "
                    f"{1e4 * f1['c']:+.1f} ± {1e4 * f1['c_err']:.1f} | "
                    f"{1e4 * f2['c']:+.1f} ± {1e4 * f2['c_err']:.1f} | {rtxt} | "
                    f"{min(f1['n_rows'], f2['n_rows'])} | {sg:.3f} | {(ref / sg) ** 2:.2f} |"
                )
        if os.path.exists(os.path.join(W, "A-anacal.fits")):
            own = anacal_own([read_catalog(os.path.join(W, "A-anacal.fits"))], a.bootstrap)
            print(
                "\nAnaCal's own estimator (<e>/<R> per case, bootstrap over pairs, "
                f"{a.bootstrap} resamples): "
                + ", ".join(
                    f"m{i} = {pct(own[f'g{i}'][0][0], own[f'g{i}'][1][0], 2)} %, "
                    f"c{i} = {1e4 * own[f'g{i}'][2][0]:+.1f} ± {1e4 * own[f'g{i}'][3][0]:.1f} e-4"
                    for i in (1, 2)
                )
            )
        print()

    diag = [
        ("A0-anacal", "AnaCal, the same stamps without noise (no noise image)"),
        ("A-anacal", "AnaCal as in the table (adaptive-moment centroid, noise image)"),
        ("A-anacal-truecentre", "AnaCal at the true centre (diagnostic: uses the truth)"),
        ("A-anacal-stampcentre", "AnaCal at the stamp centre"),
        ("A-anacal-nonoiseimage", "AnaCal without its noise image (no noise-bias correction)"),
    ]
    if os.path.exists(os.path.join(W, "A0-anacal.json")):
        print(
            "### AnaCal diagnostics on set A (m, c in per cent / 1e-4, "
            "bootstrap over galaxy pairs)\n"
        )
        print("| variant | m1 | m2 | c1 (1e-4) | c2 (1e-4) | <R11>, <R22> | sigma_g per galaxy |")
        print("|---|---|---|---|---|---|---|")
        for name, label in diag:
            path = os.path.join(W, f"{name}.json")
            if not os.path.exists(path):
                continue
            d = json.load(open(path))
            f1, f2 = d["unweighted"]["g1"], d["unweighted"]["g2"]
            resp = d["metacal"]["response"]["unweighted"]
            sg = sigma_g(
                read_catalog(os.path.join(W, f"{name}.fits")), "anacal", "unweighted", None
            )
            print(
                f"| {label} | {pct(f1['m'], f1['m_err'], 2)} | {pct(f2['m'], f2['m_err'], 2)} | "
                f"{1e4 * f1['c']:+.1f} ± {1e4 * f1['c_err']:.1f} | "
                f"{1e4 * f2['c']:+.1f} ± {1e4 * f2['c_err']:.1f} | {resp[0][0]:.4f}, "
                f"{resp[1][1]:.4f} | {sg:.3f} |"
            )
        print()

    # ---------------------------------------------------------------- set B
    if os.path.exists(os.path.join(W, "B-sc.json")):
        print(
            "## Set B: 30 real COSMOS galaxies vs their Sérsic twins (10 shears x 30 galaxies x "
            "90° pairs = 600 stamps per set)\n"
        )
        print(
            "m in per cent; errors: paired bootstrap over the 30 galaxies (megalut evaluate "
            "--twin, 1000 resamples)\n"
        )
        print(
            "| estimator | scheme | m_real g1 / g2 | m_twin g1 / g2 | m_real − m_twin g1 / g2 | "
            "rows real / twin | sigma_g real / twin |"
        )
        print("|---|---|---|---|---|---|---|")
        for est, label in EST:
            path = os.path.join(W, f"B-{est}.json")
            if not os.path.exists(path):
                continue
            d = json.load(open(path))
            creal = read_catalog(os.path.join(W, f"B-real-{est}.fits"))
            ctwin = read_catalog(os.path.join(W, f"B-twin-{est}.fits"))
            for scheme, v in d["overall"].items():
                f1, f2 = v["g1"], v["g2"]
                try:
                    sg = (
                        f"{sigma_g(creal, est, scheme, None):.3f} / "
                        f"{sigma_g(ctwin, est, scheme, None):.3f}"
                    )
                except KeyError:
                    sg = "–"
                print(
                    f"| {label} | {scheme} | {pct(f1['m_a'], f1['m_a_err'])} / "
                    f"{pct(f2['m_a'], f2['m_a_err'])} | {pct(f1['m_b'], f1['m_b_err'])} / "
                    f"{pct(f2['m_b'], f2['m_b_err'])} | **{pct(f1['dm'], f1['dm_err'])} / "
                    f"{pct(f2['dm'], f2['dm_err'])}** | "
                    f"{f1['n_rows_a']} / {f1['n_rows_b']} | {sg} |"
                )
        if os.path.exists(os.path.join(W, "B-real-anacal.fits")):
            cats = [read_catalog(os.path.join(W, f"B-{s}-anacal.fits")) for s in ("real", "twin")]
            own = anacal_own(cats, a.bootstrap)
            print(
                "\nAnaCal's own estimator (<e>/<R> per case; bootstrap over the 30 galaxies, "
                f"pairs of both sets together, {a.bootstrap} resamples): "
                + "; ".join(
                    f"g{i}: m_real {pct(own[f'g{i}'][0][0], own[f'g{i}'][1][0])}, "
                    f"m_twin {pct(own[f'g{i}'][0][1], own[f'g{i}'][1][1])}, "
                    f"difference {pct(*own[f'g{i}'][4])} %"
                    for i in (1, 2)
                )
            )
        print()

    # ---------------------------------------------------------------- CPU
    print("## CPU time per galaxy (user + sys of each command and its workers, / stamps)\n")
    print("| step | A (40 000 Sérsic) ms | B real (600) ms | B twin (600) ms |")
    print("|---|---|---|---|")
    sizes = {"A": None, "B-real": None, "B-twin": None}
    for s in sizes:
        p = os.path.join(W, f"{s}.fits")
        if os.path.exists(p):
            sizes[s] = len(read_catalog(p, columns=["case"]))
    steps = [
        "simulate",
        "measure",
        "predict",
        "measure-metacal",
        "predict-metacal",
        "adamom-metacal",
        "anacal",
    ]
    for st in steps:
        row = []
        for s in sizes:
            t = times.get(f"{st}:{s}")
            row.append("–" if t is None or not sizes[s] else f"{1e3 * t[0] / sizes[s]:.2f}")
        print(f"| {st} | " + " | ".join(row) + " |")
    row = []
    for s in sizes:
        p = os.path.join(W, f"{s}-anacal.fits")
        row.append(
            f"{1e3 * float(read_catalog(p, columns=['case']).meta['ANCPUGAL']):.2f}"
            if os.path.exists(p)
            else "–"
        )
    print("| AnaCal calls only (time.process_time) | " + " | ".join(row) + " |")
    print(
        "\nPer estimator (simulation excluded): (1) measure + predict; "
        "(2) measure-metacal + predict-metacal; (3) measure-metacal + adamom-metacal; "
        "(4) measure (the centroid) + anacal.\n"
    )
    print("| estimator | A ms | B real ms |")
    print("|---|---|---|")
    combos = {
        "(1)": ("measure", "predict"),
        "(2)": ("measure-metacal", "predict-metacal"),
        "(3)": ("measure-metacal", "adamom-metacal"),
        "(4)": ("measure", "anacal"),
    }
    for k, parts in combos.items():
        row = []
        for s in ("A", "B-real"):
            ts = [times.get(f"{p}:{s}") for p in parts]
            row.append(
                "–"
                if None in ts or not sizes[s]
                else f"{1e3 * sum(t[0] for t in ts) / sizes[s]:.2f}"
            )
        print(f"| {k} | " + " | ".join(row) + " |")
    print("\nWall times (s): " + ", ".join(f"{k} {v[1]:.0f}" for k, v in times.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
