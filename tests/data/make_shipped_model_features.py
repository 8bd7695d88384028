"""Write tests/data/shipped_model_features.fits: features of 256 fiducial VO stamps and the
shipped models' predictions on them, recorded for tests/test_shipped_model.py.

    python tests/data/make_shipped_model_features.py

Rerun only when a shipped model changes on purpose (and say so): the test compares every
prediction of models/*.h5 with the values recorded here.
"""

from __future__ import annotations

from pathlib import Path

import fitsio
import numpy as np

from megalut_cli.nn.model import ShearModel
from megalut_cli.shear.predict import predict_columns
from megalut_cli.sim import load_config
from megalut_cli.sim.simulate import simulate_table

ROOT = Path(__file__).resolve().parents[2]
OUT = Path(__file__).with_name("shipped_model_features.fits")
MODELS = ("fiducial", "fiducial-1e6")
KEEP = (
    "case",
    "rea",
    "tru_g1",
    "tru_g2",
    "snr",
    "flags",
    "adamom_g1",
    "adamom_g2",
    "adamom_sigma",
    "adamom_flux",
    "adamom_rho4",
)


def main() -> None:
    config = load_config(ROOT / "examples" / "fiducial" / "vo.toml", n_cases=8, n_realizations=32)
    table, _ = simulate_table(config, 77, measure=True)
    cols = {k: np.asarray(table[k]) for k in KEEP}
    header = []
    for name in MODELS:
        model = ShearModel.load(ROOT / "models" / f"{name}.h5")
        pred = predict_columns(model, cols)
        for key, values in pred.items():
            if key.startswith("pre_"):
                cols[f"{name.replace('-', '_')}_{key}"] = values
        header.append(
            {"name": f"SHA{len(header)}", "value": model.sha256[:64], "comment": f"{name}.h5"}
        )
    arr = np.zeros(len(cols["case"]), dtype=[(k, v.dtype, v.shape[1:]) for k, v in cols.items()])
    for k, v in cols.items():
        arr[k] = v
    tmp = OUT.with_suffix(".tmp")
    with fitsio.FITS(str(tmp), "rw", clobber=True) as f:
        f.write(arr, header=header, extname="CATALOG")
    tmp.replace(OUT)
    print(f"wrote {OUT} ({len(arr)} rows, {int((cols['flags'] != 0).sum())} flagged)")


if __name__ == "__main__":
    main()
