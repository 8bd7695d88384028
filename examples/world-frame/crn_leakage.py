"""The PSF leakage of a route from two twin catalogs: the same objects, noise and Jacobians
drawn with opposite PSF ellipticities (``make_meds.py --psf-e E`` and ``--psf-e -E`` with one
``--seed``), each measured and predicted alike.

A leakage ``g = alpha e_psf + c`` is then half the difference of the twins' calibrated
world-frame estimates against half the difference of their PSF ellipticities, object by
object: the galaxies' shapes and the noise, common to the twins, drop out of the difference,
where a single catalog's regression (``megalut calibrate``'s alpha) carries their chance
correlation with the PSF pattern. Each twin is calibrated by ``megalut calibrate``'s
library function (its total response, weights and world frame); the error is a delete-one
jackknife over the same sky patches.

    python crn_leakage.py shears-plus.fits shears-minus.fits [--unweighted] [--json OUT]
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from astropy.io import fits

from megalut_cli.shear.calibrate import calibrate_columns, sky_patches

PATCHES = 100


def calibrated(path: str, unweighted: bool) -> dict[str, np.ndarray]:
    """Per-object calibrated world-frame estimates, weights and PSF ellipticities of one
    twin (NaN where the object is not usable)."""
    with fits.open(path, memmap=False) as hdul:
        table, header = hdul[1].data, hdul[1].header
        columns = {name: np.asarray(table[name]) for name in table.columns.names}
    # the objects with every version measured, as when the recorded runs were made
    # (``megalut calibrate``'s default until 2026-12-01; the difference is object by object)
    cal = calibrate_columns(
        columns, header=header, unweighted=unweighted, source=path, failures="exclude"
    )
    if cal.psf is None:
        raise SystemExit(f"{path}: no PSF ellipticity columns (psf_adamom_g1, psf_adamom_g2)")
    inverse = np.linalg.inv(cal.responses[0])
    est = np.stack([cal.estimates[1], cal.estimates[2]])
    g = inverse @ est
    use = cal.rows
    return {
        "g": np.where(use, g, np.nan),
        "w": np.where(use, 0.5 * (cal.weights[1] + cal.weights[2]), 0.0),
        "e": np.stack(cal.psf),
        "ra": columns["ra"],
        "dec": columns["dec"],
        "alpha": np.array(cal.result["all"]["alpha"], dtype=float),
        "alpha_err": np.array(cal.result["all"]["alpha_err"], dtype=float),
    }


def slope(dg: np.ndarray, de: np.ndarray, w: np.ndarray) -> float:
    """Weighted least-squares slope through the origin of ``dg`` on ``de``."""
    return float(np.sum(w * dg * de) / np.sum(w * de * de))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("plus", help="predictions of the twin drawn with --psf-e E")
    ap.add_argument("minus", help="predictions of the twin drawn with --psf-e -E")
    ap.add_argument("--unweighted", action="store_true", help="ignore the weights")
    ap.add_argument("--json", help="write the result here")
    args = ap.parse_args()
    p, m = calibrated(args.plus, args.unweighted), calibrated(args.minus, args.unweighted)
    if len(p["ra"]) != len(m["ra"]) or not np.allclose(p["ra"], m["ra"]):
        raise SystemExit("the two catalogs do not hold the same objects in the same order")
    both = np.isfinite(p["g"]).all(axis=0) & np.isfinite(m["g"]).all(axis=0)
    w = np.where(both, 0.5 * (p["w"] + m["w"]), 0.0)
    dg = 0.5 * np.nan_to_num(p["g"] - m["g"])
    de = 0.5 * (p["e"] - m["e"])
    patches = sky_patches(p["ra"], p["dec"], PATCHES)
    alpha, err = [], []
    for i in (0, 1):
        a = slope(dg[i], de[i], w)
        samples = np.array(
            [slope(dg[i], de[i], np.where(patches == k, 0.0, w)) for k in np.unique(patches)]
        )
        n = len(samples)
        alpha.append(a)
        err.append(float(np.sqrt((n - 1) / n * np.sum((samples - samples.mean()) ** 2))))
    result = {
        "objects": int(both.sum()),
        "scheme": "unweighted" if args.unweighted else "weighted",
        "alpha": alpha,
        "alpha_err": err,
        "rms_psf_difference": float(np.sqrt(np.mean(de[:, both] ** 2))),
        "single_catalog_alpha": {"plus": p["alpha"].tolist(), "minus": m["alpha"].tolist()},
        "single_catalog_alpha_err": {
            "plus": p["alpha_err"].tolist(),
            "minus": m["alpha_err"].tolist(),
        },
    }
    print(
        f"{result['objects']} objects in both twins ({result['scheme']}): "
        f"alpha1 = {alpha[0]:+.4f} ± {err[0]:.4f}, alpha2 = {alpha[1]:+.4f} ± {err[1]:.4f}"
    )
    for twin in ("plus", "minus"):
        a, e = result["single_catalog_alpha"][twin], result["single_catalog_alpha_err"][twin]
        print(
            f"  {twin} alone (megalut calibrate): "
            f"{a[0]:+.4f} ± {e[0]:.4f}, {a[1]:+.4f} ± {e[1]:.4f}"
        )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=1)


if __name__ == "__main__":
    main()
