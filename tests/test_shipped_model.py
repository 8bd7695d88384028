"""The shipped models: pinned files, recorded predictions, and the Stage IV target (slow).

Default set: the sha256 of each shipped file is pinned, and its predictions on a committed
feature file (tests/data/shipped_model_features.fits, 256 fiducial VO stamps written by
tests/data/make_shipped_model_features.py) equal the recorded ones. A changed model file, or
a change of the network evaluation, fails here and must be stated.

Slow set: models/fiducial.h5 on a fresh common-random-number validation set
(examples/fiducial/vo-crn.toml: 4 shears x 200 000 galaxies in 90-degree pairs, 8 x 10^5
stamps, the same galaxies, offsets and noise under every shear), drawn with seed 1001, which
no set or training of the model used (models/fiducial-pipeline.toml: TP 41, TW 42, VO 43;
training 51, 52; nor the 3e6-stamp check of models/README.md, 44). With common random
numbers the error on m falls with the number of galaxies more than with the number of shears:
4 shears of 200 000 galaxies measure m to 4.4e-4 with the stamps that 20 shears of 40 000
measured to 9.2e-4. Errors from a bootstrap over the galaxy pairs, which holds the 4 shears
fixed: their draw adds a scatter it does not see (about 2e-3 at 10 000 pairs,
examples/fiducial/crn_shear_draws.py), so the gate below is stricter than the true error. It
asserts the Stage IV requirement, weighted |m| < 2e-3 and |c| < 2e-4 within 2 sigma, with
sigma_m <= 5e-4.
Issue 12's stricter target |m| < 1e-3 is not met on this set (m1 = -2.70e-3 +- 0.44e-3,
models/README.md). Run with ``python -m pytest -m slow -s tests/test_shipped_model.py``.
"""

from __future__ import annotations

from pathlib import Path

import fitsio
import numpy as np
import pytest

from megalut_cli.nn.model import ShearModel
from megalut_cli.provenance import sha256_file
from megalut_cli.shear.predict import predict_columns

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "models"
FEATURES = ROOT / "tests" / "data" / "shipped_model_features.fits"
VO_CRN = ROOT / "examples" / "fiducial" / "vo-crn.toml"

#: The shipped files (models/README.md). A new model is a new line here, stated in the note.
SHIPPED_SHA256 = {
    "fiducial": "3bdb52452b37b390d85694c915f23e4365118e726878f7ba728dab9d31aef7a2",
    "fiducial-1e6": "14ff239704736fb344097bad201995cad231d2afa2a67b3f2c428d6afa032e93",
}
REQUIREMENT_M, REQUIREMENT_C = 2e-3, 2e-4
#: The error of m on the test's 4-shear set includes the drawn shears' term since issue 39
#: (docs/evaluate.md): the galaxies' part alone was 4.1-4.4e-4, the whole 6.4e-4 in g1.
MAX_M_ERR = 8e-4


@pytest.mark.parametrize("name", sorted(SHIPPED_SHA256))
def test_shipped_model_files_are_pinned(name: str) -> None:
    path = MODELS / f"{name}.h5"
    assert path.resolve() == (ROOT / "megalut_cli" / "data" / f"{name}.h5").resolve()  # one file
    assert sha256_file(path) == SHIPPED_SHA256[name]


@pytest.mark.parametrize("name", sorted(SHIPPED_SHA256))
def test_shipped_model_predictions_equal_the_recorded_ones(name: str) -> None:
    table = fitsio.read(str(FEATURES))
    model = ShearModel.load(MODELS / f"{name}.h5")
    got = predict_columns(model, {k: table[k] for k in table.dtype.names})
    keys = [k for k in got if k.startswith("pre_")]
    assert sorted(keys) == ["pre_g1", "pre_g1_w", "pre_g2", "pre_g2_w"]
    for key in keys:
        recorded = table[f"{name.replace('-', '_')}_{key}"]
        # float64 network passes: equal up to the order of the BLAS sums
        np.testing.assert_allclose(got[key], recorded, rtol=1e-10, atol=1e-14, err_msg=key)
    flagged = table["flags"] != 0
    assert (
        flagged.any()
        and np.isnan(got["pre_g1"][flagged]).all()
        and (got["pre_g1_w"][flagged] == 0).all()
    )
    # the point estimates follow the shears: a sanity check that the file holds real stamps
    good = ~flagged
    assert np.corrcoef(got["pre_g1"][good], table["adamom_g1"][good])[0, 1] > 0.9


@pytest.mark.slow
def test_fiducial_model_meets_the_stage_iv_requirement_on_a_crn_set(tmp_path):
    from megalut_cli.shear.evaluate import evaluate_catalog
    from megalut_cli.shear.predict import predict_catalog
    from megalut_cli.sim.config import load_config
    from megalut_cli.sim.simulate import simulate

    config = load_config(VO_CRN, n_cases=4, n_realizations=200_000)
    vo = tmp_path / "vo.fits"
    simulate(config, vo, measure=True, seed=1001, nproc=2)
    shears = tmp_path / "shears.fits"
    predict_catalog(vo, MODELS / "fiducial.h5", shears, nproc=2)
    result = evaluate_catalog(shears, seed=1001)
    assert result["error"] == "bootstrap-galaxies"
    for scheme in ("unweighted", "weighted"):  # shown with pytest -s, recorded in models/README.md
        print(
            scheme,
            {
                c: {k: result[scheme][c][k] for k in ("m", "m_err", "c", "c_err", "n_rows")}
                for c in ("g1", "g2")
            },
        )
    for comp in ("g1", "g2"):
        fit = result["weighted"][comp]
        assert fit["m_err"] <= MAX_M_ERR, (comp, fit)
        assert abs(fit["m"]) < REQUIREMENT_M + 2 * fit["m_err"], (comp, fit)
        assert abs(fit["c"]) < REQUIREMENT_C + 2 * fit["c_err"], (comp, fit)
        # the weights are what brings the point estimates' noise bias (-2.7 %) within it
        assert result["unweighted"][comp]["m"] < -0.01, (comp, result["unweighted"][comp])
