"""Differences between the estimators on the same stamps, with one shared bootstrap.

    python examples/metacal/peers/compare.py WORKDIR [--bootstrap 500] [--seed 1]

Every estimator's m on a set moves with the set's own noise (its galaxies, their shapes and
pixel noise): on the same stamps most of that is common, and the difference of two
estimators' m is far better measured than either. This script recomputes m, c of each
estimator and scheme exactly as `megalut evaluate` does (per-case (weighted) means; for
metacal catalogs calibrated by the inverse of the mean 2x2 response of all rows used, plus
the selection response of the weights in the weighted scheme; ordinary least squares over
cases), resamples galaxy groups once for all (set A: the 90-degree pairs, rea // 2; set B:
the 30 galaxies, tru_real_index, with all their rows in both the real and twin sets), and
reports m of each estimator minus m of AnaCal (unweighted) with the standard deviation of
the resampled differences; for set B also m_real, m_twin, m_real - m_twin and their
differences from AnaCal's. The point values are those of the full catalogs; they equal
the single-set `megalut evaluate` (WORKDIR/A-*.json, B-{real,twin}-*.json), which the script
checks. (`megalut evaluate --twin` calibrates metacal sets by the diagonal mean response
only and, in the weighted scheme, without the selection response of the weights: its
weighted metacal m differ from these by about R_sel / R; README.md.)
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from megalut_cli.catalog import read_catalog
from megalut_cli.shear.bias import fit_bias

TYPES = ("1p", "1m", "2p", "2m")
EST = [
    ("sc", "unweighted", "(1) simulation-calibrated, unweighted"),
    ("sc", "weighted", "(1) simulation-calibrated, weighted"),
    ("mcal-nn", "unweighted", "(2) megalut + metacal, unweighted"),
    ("mcal-nn", "weighted", "(2) megalut + metacal, weighted"),
    ("mcal-am", "unweighted", "(3) metacal, adaptive moments"),
    ("anacal", "unweighted", "(4) AnaCal"),
]


class Sums:
    """Per (case, group) sums of one estimator and scheme, from which any resample's m, c follow."""

    def __init__(
        self, cat, est: str, scheme: str, groups: np.ndarray, n_groups: int, step: float = 0.01
    ):
        case = np.asarray(cat["case"])
        self.cases = np.unique(case)
        ci = np.searchsorted(self.cases, case)
        self.nc, self.ng = len(self.cases), n_groups
        key = ci * n_groups + groups
        size = self.nc * n_groups

        def s(v):
            return np.bincount(key, np.nan_to_num(v), size).reshape(self.nc, n_groups)

        mcal = est != "sc"
        sfx = "_noshear" if mcal else ""
        flags = np.asarray(cat["flags_noshear" if mcal else "flags"]) == 0
        self.w, self.wpre, self.wtru, self.wR, self.sw, self.swpre = {}, {}, {}, {}, {}, {}
        usable = flags.copy()
        for i in (1, 2):
            t = np.asarray(cat[f"tru_g{i}"], float)
            p = np.asarray(cat[f"pre_g{i}{sfx}"], float)
            ok = flags & np.isfinite(t) & np.isfinite(p)
            if mcal:
                for j in (1, 2):
                    ok &= np.isfinite(np.asarray(cat[f"mcal_r{i}{j}"], float))
                usable &= np.isfinite(p) & np.isfinite(t)
                for j in (1, 2):
                    usable &= np.isfinite(np.asarray(cat[f"mcal_r{i}{j}"], float))
            w = ok.astype(float)
            if scheme == "weighted":
                ww = np.asarray(cat[f"pre_g{i}_w{sfx}"], float)
                w = np.where(ok & np.isfinite(ww) & (ww > 0), ww, 0.0)
            self.w[i], self.wpre[i], self.wtru[i] = (
                s(w),
                s(w * np.where(ok, p, 0)),
                s(w * np.where(ok, t, 0)),
            )
            if mcal:
                for j in (1, 2):
                    self.wR[(i, j)] = s(
                        w * np.where(ok, np.asarray(cat[f"mcal_r{i}{j}"], float), 0)
                    )
        self.mcal = mcal
        self.selection = mcal and scheme == "weighted"
        if self.selection:
            for i in (1, 2):
                pre = np.nan_to_num(np.asarray(cat[f"pre_g{i}_noshear"], float))
                for kind in TYPES:
                    ww = np.asarray(cat[f"pre_g{i}_w_{kind}"], float)
                    w = np.where(usable & np.isfinite(ww) & (ww > 0), ww, 0.0)
                    self.sw[(i, kind)] = s(w)
                    self.swpre[(i, kind)] = s(w * pre / (2.0 * step))

    def fit(self, k: np.ndarray | None = None) -> dict[int, tuple[float, float]]:
        """m, c of g1 and g2 with galaxy-group multiplicities k (None: all once)."""
        k = np.ones(self.ng) if k is None else k
        tot = {i: (self.w[i] @ k) for i in (1, 2)}  # per case
        with np.errstate(invalid="ignore", divide="ignore"):
            tru = {i: (self.wtru[i] @ k) / tot[i] for i in (1, 2)}
            pre = {i: (self.wpre[i] @ k) / tot[i] for i in (1, 2)}
            if self.mcal:
                R = np.array(
                    [[(self.wR[(i, j)] @ k).sum() / tot[i].sum() for j in (1, 2)] for i in (1, 2)]
                )
                if self.selection:

                    def avg(i, kind):
                        return (self.swpre[(i, kind)] @ k).sum() / (self.sw[(i, kind)] @ k).sum()

                    R = R + np.array(
                        [[avg(i, f"{j}p") - avg(i, f"{j}m") for j in (1, 2)] for i in (1, 2)]
                    )
                det = R[0, 0] * R[1, 1] - R[0, 1] * R[1, 0]
                p1, p2 = pre[1], pre[2]
                pre = {
                    1: (R[1, 1] * p1 - R[0, 1] * p2) / det,
                    2: (R[0, 0] * p2 - R[1, 0] * p1) / det,
                }
        out = {}
        for i in (1, 2):
            use = np.isfinite(pre[i]) & np.isfinite(tru[i])
            f = fit_bias(tru[i][use], pre[i][use])
            out[i] = (f.m, f.c)
        return out


def groups_of(cat, kind: str) -> np.ndarray:
    if kind == "pairs":
        return np.asarray(cat["rea"]) // 2
    return np.asarray(cat["tru_real_index"]).astype(np.int64)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("workdir")
    ap.add_argument("--bootstrap", type=int, default=500)
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args(argv)
    W = a.workdir
    rng = np.random.default_rng(a.seed)

    # ------------------------------------------------------------ set A
    if all(os.path.exists(os.path.join(W, f"A-{e}.fits")) for e, _, _ in EST):
        sums = {}
        for est, scheme, _label in EST:
            cat = read_catalog(os.path.join(W, f"A-{est}.fits"))
            g = groups_of(cat, "pairs")
            sums[(est, scheme)] = Sums(cat, est, scheme, g, int(g.max()) + 1)
            d = json.load(open(os.path.join(W, f"A-{est}.json")))[scheme]
            p = sums[(est, scheme)].fit()
            assert abs(p[1][0] - d["g1"]["m"]) < 1e-9 and abs(p[2][0] - d["g2"]["m"]) < 1e-9, (
                est,
                scheme,
                p,
                d,
            )
        ng = next(iter(sums.values())).ng
        ref = ("anacal", "unweighted")
        point = {key: s.fit() for key, s in sums.items()}
        boot = {key: [] for key in sums}
        for _ in range(a.bootstrap):
            k = np.bincount(rng.integers(0, ng, ng), minlength=ng).astype(float)
            for key, s in sums.items():
                f = s.fit(k)
                boot[key].append([f[1][0], f[2][0]])
        boot = {key: np.array(v) for key, v in boot.items()}
        print(
            "## Set A: m of each estimator minus m of AnaCal, same stamps (per cent; "
            f"shared bootstrap over {ng} galaxy pairs, {a.bootstrap} resamples; "
            "point values equal megalut evaluate's)\n"
        )
        print("| estimator | m1 | m2 | m1 − m1(AnaCal) | m2 − m2(AnaCal) |")
        print("|---|---|---|---|---|")
        for est, scheme, label in EST:
            key = (est, scheme)
            b, r = boot[key], boot[ref]
            dm = [point[key][i][0] - point[ref][i][0] for i in (1, 2)]
            err = b.std(axis=0)
            derr = (b - r).std(axis=0)
            cell = "0" if key == ref else f"{100 * dm[0]:+.2f} ± {100 * derr[0]:.2f}"
            cell2 = "0" if key == ref else f"{100 * dm[1]:+.2f} ± {100 * derr[1]:.2f}"
            print(
                f"| {label} | {100 * point[key][1][0]:+.2f} ± {100 * err[0]:.2f} | "
                f"{100 * point[key][2][0]:+.2f} ± {100 * err[1]:.2f} | {cell} | {cell2} |"
            )
        print()

    # ------------------------------------------------------------ set B
    if all(
        os.path.exists(os.path.join(W, f"B-{s}-{e}.fits"))
        for e, _, _ in EST
        for s in ("real", "twin")
    ):
        sums = {}
        for est, scheme, _label in EST:
            for s in ("real", "twin"):
                cat = read_catalog(os.path.join(W, f"B-{s}-{est}.fits"))
                g = groups_of(cat, "galaxy")
                gal = np.unique(g)
                sums[(est, scheme, s)] = Sums(cat, est, scheme, np.searchsorted(gal, g), len(gal))
            for st in (
                "real",
                "twin",
            ):  # the single-set evaluation (2x2 response, selection response)
                path = os.path.join(W, f"B-{st}-{est}.json")
                if os.path.exists(path):
                    d = json.load(open(path))[scheme]
                    p = sums[(est, scheme, st)].fit()
                    assert (
                        abs(p[1][0] - d["g1"]["m"]) < 1e-9 and abs(p[2][0] - d["g2"]["m"]) < 1e-9
                    ), (est, scheme, st)
        ng = next(iter(sums.values())).ng
        point = {key: s.fit() for key, s in sums.items()}
        boot = {key: [] for key in sums}
        for _ in range(a.bootstrap):
            k = np.bincount(rng.integers(0, ng, ng), minlength=ng).astype(float)
            for key, s in sums.items():
                f = s.fit(k)
                boot[key].append([f[1][0], f[2][0]])
        boot = {key: np.array(v) for key, v in boot.items()}

        def val(key_real, key_twin=None):
            if key_twin is None:
                return np.array([point[key_real][i][0] for i in (1, 2)]), boot[key_real]
            p = np.array([point[key_real][i][0] - point[key_twin][i][0] for i in (1, 2)])
            return p, boot[key_real] - boot[key_twin]

        print(
            "## Set B: m_real, m_twin and m_real − m_twin (per cent; paired bootstrap over the "
            f"{ng} galaxies, {a.bootstrap} resamples, shared by all estimators; "
            "definitions of the single-set megalut evaluate)\n"
        )
        print("| estimator | m_real g1 / g2 | m_twin g1 / g2 | m_real − m_twin g1 / g2 |")
        print("|---|---|---|---|")
        for est, scheme, label in EST:
            cells = []
            for args in (
                ((est, scheme, "real"),),
                ((est, scheme, "twin"),),
                ((est, scheme, "real"), (est, scheme, "twin")),
            ):
                p, b = val(*args)
                e = b.std(axis=0)
                cells.append(
                    f"{100 * p[0]:+.1f} ± {100 * e[0]:.1f} / {100 * p[1]:+.1f} ± {100 * e[1]:.1f}"
                )
            print(f"| {label} | " + " | ".join(cells) + " |")
        print()
        print("## Set B: differences from AnaCal on the same stamps (per cent; same resamples)\n")
        print(
            "| estimator | m_real − m_real(AnaCal) g1 / g2 | m_twin − m_twin(AnaCal) g1 / g2 | "
            "(m_real − m_twin) − AnaCal's g1 / g2 |"
        )
        print("|---|---|---|---|")
        for est, scheme, label in EST:
            if (est, scheme) == ("anacal", "unweighted"):
                continue
            cells = []
            for which in ("real", "twin", "diff"):
                if which == "diff":
                    p, b = val((est, scheme, "real"), (est, scheme, "twin"))
                    pr, br = val(("anacal", "unweighted", "real"), ("anacal", "unweighted", "twin"))
                else:
                    p, b = val((est, scheme, which))
                    pr, br = val(("anacal", "unweighted", which))
                dp, de = p - pr, (b - br).std(axis=0)
                cells.append(
                    f"{100 * dp[0]:+.1f} ± {100 * de[0]:.1f} / {100 * dp[1]:+.1f} ± "
                    f"{100 * de[1]:.1f}"
                )
            print(f"| {label} | " + " | ".join(cells) + " |")
        print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
