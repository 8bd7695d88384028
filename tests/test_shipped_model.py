"""The shipped model models/fiducial.h5 on an independent fiducial validation set (slow).

The validation set is drawn with seed 1001, which no training set of the model used
(models/fiducial-pipeline.toml: TP 21, TW 22, VO 23; training 31, 32). Its recorded result
is in models/README.md. Run with ``python -m pytest -m slow tests/test_shipped_model.py``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "fiducial.h5"
VO = ROOT / "examples" / "fiducial" / "vo.toml"


@pytest.mark.slow
def test_fiducial_model_meets_its_recorded_accuracy(tmp_path):
    from megalut_cli.shear.evaluate import evaluate_catalog
    from megalut_cli.shear.predict import predict_catalog
    from megalut_cli.sim.config import load_config
    from megalut_cli.sim.simulate import simulate

    if not MODEL.exists():
        pytest.skip("models/fiducial.h5 is not shipped in this checkout")
    # One shear per case, a new galaxy per realization in 90-degree pairs, as the model's VO.
    config = load_config(
        VO,
        overrides=['structure.snc="pairs"'],
        n_cases=200,
        n_realizations=1500,
    )
    vo = tmp_path / "vo.fits"
    simulate(config, vo, measure=True, seed=1001, nproc=2)
    shears = tmp_path / "shears.fits"
    predict_catalog(vo, MODEL, shears)
    result = evaluate_catalog(shears)
    for scheme in ("unweighted", "weighted"):  # shown with pytest -s, recorded in models/README.md
        print(scheme, {c: {k: result[scheme][c][k] for k in ("m", "m_err", "c", "c_err", "n_rows")} for c in ("g1", "g2")})
    for comp in ("g1", "g2"):
        fit = result["weighted"][comp]
        assert abs(fit["m"]) < 5e-3, (comp, fit)
        assert abs(fit["c"]) < 5e-4, (comp, fit)
