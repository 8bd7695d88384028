"""Model bias on real galaxies of several models, from the same real and twin stamps.

Usage: python compare_models.py REAL.fits TWIN.fits NAME=MODEL.h5 [NAME=MODEL.h5 ...]
       [--reference NAME] [--bootstrap 1000] [--seed 1] [--json OUT.json]

Every model predicts on the same real-galaxy set and its Sérsic-twin set (drawn with common
random numbers: docs/realgal.md). For each model it reports m_real, m_twin and m_real - m_twin
(weighted and unweighted), with errors from one bootstrap over galaxies shared by all models,
and for each model the change of m_real - m_twin against the reference model with the error
of that change (the same resamples, so what the galaxies have in common cancels).
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from megalut_cli.catalog import read_catalog
from megalut_cli.nn.model import ShearModel
from megalut_cli.shear.paired import Resampling, set_values
from megalut_cli.shear.predict import predict_columns


def slopes(table, pred, scheme: str, comp: int, resampling: Resampling) -> np.ndarray:
    """m of one set, the full sample then one per resample of ``resampling``, as ``megalut
    evaluate --twin`` fits it (:mod:`megalut_cli.shear.paired`); flagged rows have no weight."""
    est = np.asarray(pred[f"pre_g{comp}"], float)
    w = np.ones_like(est) if scheme == "unweighted" else np.asarray(pred[f"pre_g{comp}_w"], float)
    w = np.where(np.asarray(pred["flags"]) == 0, w, 0.0)
    c = f"g{comp}"
    values = set_values(scheme, {c: np.asarray(table[f"tru_{c}"], float)}, {c: est}, {c: w})
    return resampling.fits(values, scheme)[c][0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("real")
    ap.add_argument("twin")
    ap.add_argument("models", nargs="+", help="NAME=MODEL.h5")
    ap.add_argument(
        "--reference", default=None, help="NAME of the reference model (default: the first)"
    )
    ap.add_argument("--bootstrap", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    real, twin = read_catalog(args.real), read_catalog(args.twin)
    for c in ("case", "rea", "tru_g1", "tru_g2", "tru_real_index"):
        if not np.array_equal(np.asarray(real[c]), np.asarray(twin[c])):
            raise SystemExit(
                f"error: {args.real} and {args.twin} differ in column {c}: not a real/twin pair"
            )
    resampling = Resampling.draw(real["tru_real_index"], real["case"], args.bootstrap, args.seed)
    names = [m.split("=", 1)[0] for m in args.models]
    ref = args.reference or names[0]
    result: dict = {
        "real": args.real,
        "twin": args.twin,
        "n_galaxies": resampling.n_gal,
        "n_cases": resampling.n_cases,
        "n_boot": args.bootstrap,
        "seed": args.seed,
        "reference": ref,
        "models": {},
    }
    dms: dict = {}
    for spec in args.models:
        name, path = spec.split("=", 1)
        model = ShearModel.load(path)
        res = {"model": path, "features": list(model.features)}
        preds = {k: predict_columns(model, t) for k, t in (("real", real), ("twin", twin))}
        for scheme in ("unweighted", "weighted"):
            for comp in (1, 2):
                ms = {}
                for k, t in (("real", real), ("twin", twin)):
                    ms[k] = slopes(t, preds[k], scheme, comp, resampling)
                dm = ms["real"] - ms["twin"]
                dms[(name, scheme, comp)] = dm
                res[f"{scheme}_g{comp}"] = {
                    "m_real": ms["real"][0],
                    "m_real_err": ms["real"][1:].std(ddof=1),
                    "m_twin": ms["twin"][0],
                    "m_twin_err": ms["twin"][1:].std(ddof=1),
                    "dm": dm[0],
                    "dm_err": dm[1:].std(ddof=1),
                }
        result["models"][name] = res
    for name in names:
        for scheme in ("unweighted", "weighted"):
            for comp in (1, 2):
                d = dms[(name, scheme, comp)] - dms[(ref, scheme, comp)]
                result["models"][name][f"{scheme}_g{comp}"].update(
                    {"ddm_vs_ref": d[0], "ddm_vs_ref_err": d[1:].std(ddof=1)}
                )
    print(
        f"{resampling.n_gal} galaxies x {resampling.n_cases} shears; errors: {args.bootstrap} "
        "bootstrap resamples of the galaxies, shared by all models"
    )
    print(
        f"{'model':28s} {'scheme':10s} {'comp':4s} {'m_real':>18s} {'m_twin':>18s} "
        f"{'m_real - m_twin':>18s} {'change vs ' + ref:>22s}"
    )
    for name in names:
        for scheme in ("unweighted", "weighted"):
            for comp in (1, 2):
                r = result["models"][name][f"{scheme}_g{comp}"]
                print(
                    f"{name:28s} {scheme:10s} g{comp:<3d} {r['m_real']:+9.2e} ± "
                    f"{r['m_real_err']:.1e} {r['m_twin']:+9.2e} ± {r['m_twin_err']:.1e} "
                    f"{r['dm']:+9.2e} ± {r['dm_err']:.1e} {r['ddm_vs_ref']:+11.2e} ± "
                    f"{r['ddm_vs_ref_err']:.1e}"
                )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1, default=float)


if __name__ == "__main__":
    main()
