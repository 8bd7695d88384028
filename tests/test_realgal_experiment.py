"""The real-vs-twin experiment end to end (slow): examples/realgal at a small size.

Real COSMOS galaxies and their Sérsic twins are simulated from one config and seed,
predicted with both shipped models (fiducial-1e6.h5 is the model of the recorded results) and
compared with the paired bootstrap. Run with
``python -m pytest -m slow -s tests/test_realgal_experiment.py`` (about 1 minute on 2 cores).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
MODELS = {
    "fiducial-1e6": ROOT / "models" / "fiducial-1e6.h5",
    "fiducial": ROOT / "models" / "fiducial.h5",
}
CONFIG = ROOT / "examples" / "realgal" / "fiducial.toml"
#: m_real - m_twin of the independent measurement of issue 14 (docs/realgal.md).
INDEPENDENT_DM = {"g1": -0.022, "g2": -0.023}


@pytest.mark.slow
def test_real_vs_twin_paired_bias(tmp_path):
    from megalut_cli.shear.paired import evaluate_paired_catalogs, format_paired
    from megalut_cli.shear.predict import predict_catalog
    from megalut_cli.sim.config import load_config
    from megalut_cli.sim.simulate import simulate

    for name, overrides in (("real", []), ("twin", ["galaxy.twin='sersic'"])):
        cfg = load_config(CONFIG, overrides, n_cases=8)
        simulate(cfg, tmp_path / f"{name}.fits", measure=True, seed=2024, nproc=2)
    for model, path in MODELS.items():  # both shipped models on the same stamps
        shears = {}
        for name in ("real", "twin"):
            shears[name] = tmp_path / f"{name}-{model}.fits"
            predict_catalog(tmp_path / f"{name}.fits", path, shears[name])
        res = evaluate_paired_catalogs(
            str(shears["real"]),
            str(shears["twin"]),
            by=["tru_twin_rad/tru_psf_sigma"],
            n_bins=2,
            n_boot=500,
            seed=1,
        )
        print(model, format_paired(res), sep="\n")
        for scheme in ("unweighted", "weighted"):
            for comp in ("g1", "g2"):
                r = res["overall"][scheme][comp]
                assert r["n_galaxies"] == 30 and r["n_cases"] == 8
                assert all(np.isfinite(r[k]) for k in ("m_a", "m_b", "dm", "dm_err", "m_b_err"))
                # Common random numbers: the shared shears, rotations and most of the noise
                # cancel in the difference, whose error is below that of the twins' own bias
                # (0.6-0.7 times it in the recorded 40-shear run).
                assert r["dm_err"] < 0.9 * r["m_b_err"]
                # Each model's bias on real galaxies is the percent-level one measured
                # independently (docs/realgal.md: -2.2 % and -2.3 % weighted, 41 galaxies),
                # within 2 sigma of this run, whose errors are 2.4-3.5 % (fiducial-1e6,
                # 2026-11-29, after the padding fix of issue 39: unweighted -3.7 %, -0.5 %,
                # weighted -5.7 %, -0.1 %; before it -3.8 %, -0.5 %, -5.5 %, -0.2 %).
                assert r["dm_err"] < 0.04
                assert abs(r["dm"] - INDEPENDENT_DM[comp]) < 2 * r["dm_err"], (
                    model,
                    scheme,
                    comp,
                    r,
                )
        bins = res["by"]["tru_twin_rad/tru_psf_sigma"]["bins"]
        assert sum(b["unweighted"]["g1"]["n_galaxies"] for b in bins) >= 30
