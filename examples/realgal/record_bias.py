"""Record a paired real-vs-twin result (``megalut evaluate --twin --json``) in a model file.

    python examples/realgal/record_bias.py models/fiducial.h5 paired.json \
        "fiducial resolution: Gaussian PSF sigma 2 px, 0.06\"/px, noise sigma 1 + symmetrized \
HST noise" \
        "megalut evaluate real-shears.fits --twin twin-shears.fits ..."

Stores the weighted m_real - m_twin (unweighted when the catalogs had no weights) as the
model's ``/validation`` ``real_galaxy_bias`` (docs/model-format.md); ``megalut predict`` logs it.
"""

from __future__ import annotations

import json
import sys

from megalut_cli.nn.population import record_real_bias


def main(model: str, result_json: str, setup: str, command: str) -> None:
    """Record the overall paired result of ``result_json`` in ``model``."""
    with open(result_json) as f:
        result = json.load(f)
    scheme = "weighted" if "weighted" in result["overall"] else "unweighted"
    res = result["overall"][scheme]
    record = {
        "scheme": scheme,
        "setup": setup,
        "command": command,
        "n_galaxies": res["g1"]["n_galaxies"],
        "n_cases": res["g1"]["n_cases"],
    }
    for comp in ("g1", "g2"):
        record[f"dm_{comp}"] = res[comp]["dm"]
        record[f"dm_{comp}_err"] = res[comp]["dm_err"]
    record_real_bias(model, record)


if __name__ == "__main__":
    if len(sys.argv) != 5:
        sys.exit("usage: record_bias.py MODEL.h5 PAIRED.json SETUP COMMAND")
    main(*sys.argv[1:])
