"""Where an additive bias c of a CRN validation set comes from (issue 12; models/README.md).

    python examples/fiducial/additive_check.py vo3m.fits models/fiducial.h5 mirror-shears.fits
    megalut evaluate mirror-shears.fits

``vo3m.fits`` is a measured common-random-number set (``examples/fiducial/vo-crn.toml``).
For the model's own predictions the script prints, per component and weighted, (1) c and m
of the straight-line fit of the per-case means against the true shear and of a fit with
the non-linear terms g**3 and g * g_other**2 that the pixel grid's symmetries allow, and
(2) the spread of c over 10 disjoint groups of galaxy pairs, to compare with the bootstrap
error of ``megalut evaluate``. It then writes the predictions of the model made exactly
mirror-symmetric: for a round PSF on square pixels, the mirror x -> -x maps adamom_g2 to
-adamom_g2 and the transpose maps adamom_g1 to -adamom_g1, the other features unchanged, so
``(f(x) - f(Mx)) / 2`` is an estimate odd under the mirror and ``(w(x) + w(Mx)) / 2`` an
even weight. Such an estimator has c = 0 on any mirror-symmetric population: on a finite
set its c is the set's own fluctuation.
"""

from __future__ import annotations

import sys

import numpy as np

from megalut_cli.catalog import read_cards, read_catalog, write_catalog
from megalut_cli.nn.model import ShearModel
from megalut_cli.shear.predict import predict_arrays

GROUPS = 10


def case_means(case: np.ndarray, est: np.ndarray, weight: np.ndarray, n_cases: int) -> np.ndarray:
    """Weighted mean estimate of every case."""
    return np.bincount(case, weight * est, n_cases) / np.bincount(case, weight, n_cases)


def report(columns: dict[str, np.ndarray], preds: dict[str, np.ndarray]) -> None:
    """The fits and the split-set spread of c for the weighted estimates."""
    case, rea = columns["case"], columns["rea"]
    n_cases = int(case.max()) + 1
    first = np.unique(case, return_index=True)[1]
    for comp, other in (("g1", "g2"), ("g2", "g1")):
        est, w = preds[f"pre_{comp}"], preds[f"pre_{comp}_w"]
        good = (preds["flags"] == 0) & np.isfinite(est) & np.isfinite(w)
        g, go = columns[f"tru_{comp}"][first], columns[f"tru_{other}"][first]
        y = case_means(case[good], est[good], w[good], n_cases)
        c_lin, m_lin = np.polyfit(g, y, 1)[::-1]
        coef = np.linalg.lstsq(np.c_[np.ones_like(g), g, g**3, g * go**2], y, rcond=None)[0]
        print(
            f"{comp}: straight line c = {c_lin:+.2e}, m = {m_lin - 1:+.2e}; "
            f"with g^3, g*g_other^2: c = {coef[0]:+.2e}, m = {coef[1] - 1:+.2e}"
        )
        group = (rea // 2) % GROUPS  # galaxy pairs, the unit of the bootstrap
        cs = []
        for k in range(GROUPS):
            sel = good & (group == k)
            cs.append(np.polyfit(g, case_means(case[sel], est[sel], w[sel], n_cases), 1)[1])
        print(
            f"    c over {GROUPS} disjoint groups of pairs: mean {np.mean(cs):+.2e}, "
            f"error from their spread {np.std(cs, ddof=1) / np.sqrt(GROUPS):.1e}"
        )


def main(catalog: str, model_path: str, output: str) -> None:
    table = read_catalog(catalog)
    model = ShearModel.load(model_path)
    x = np.column_stack([np.asarray(table[f], float) for f in model.features])
    flags = np.asarray(table["flags"])
    keep = ("case", "rea", "tru_g1", "tru_g2", "tru_psf_g1", "tru_psf_g2")
    columns = {c: np.asarray(table[c]) for c in keep}
    preds = predict_arrays(model, x, flags)
    report(columns, preds)
    mirrored = dict(columns, flags=preds["flags"])
    for comp in ("g1", "g2"):
        xm = x.copy()
        xm[:, model.features.index(f"adamom_{comp}")] *= -1
        mirror = predict_arrays(model, xm, flags)
        mirrored[f"pre_{comp}"] = 0.5 * (preds[f"pre_{comp}"] - mirror[f"pre_{comp}"])
        mirrored[f"pre_{comp}_w"] = 0.5 * (preds[f"pre_{comp}_w"] + mirror[f"pre_{comp}_w"])
    cards = {
        k: v
        for k, v in read_cards(catalog).items()
        if k in ("CRN", "SNC", "NCASES", "NREA", "SEED")
    }
    write_catalog(output, mirrored, fmt="megalut.predictions", cards=cards, overwrite=True)
    print(f"wrote {output}: the mirror-symmetric predictions (megalut evaluate {output})")


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit("usage: additive_check.py CRN_CATALOG.fits MODEL.h5 OUTPUT.fits")
    main(*sys.argv[1:])
