"""Record a paired real-vs-twin result (``megalut evaluate --twin --json``) in a model file.

    python examples/realgal/record_bias.py models/fiducial.h5 paired.json \
        "fiducial resolution: Gaussian PSF sigma 2 px, 0.06\"/px, noise sigma 1 + symmetrized \
HST noise" \
        "megalut evaluate real-shears.fits --twin twin-shears.fits ..."

Stores the weighted m_real - m_twin (unweighted when the catalogs had no weights) as the
model's ``/validation`` ``real_galaxy_bias`` (docs/model-format.md); ``megalut predict`` logs it.

With ``--m-real``, RESULT.json is a single-set result (``examples/metacal/mcal_tools.py
single``: real galaxies alone, as for a metacal model, which needs no twins) and m_real itself
is recorded, with ``quantity = "m_real"``.
"""

from __future__ import annotations

import json
import sys

from megalut_cli.nn.population import record_real_bias


def main(model: str, result_json: str, setup: str, command: str, m_real: bool = False) -> None:
    """Record the overall paired result of ``result_json`` in ``model`` (``m_real``: the
    real set's own m of a single-set result)."""
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
    if m_real:
        record["quantity"] = "m_real"
    for comp in ("g1", "g2"):
        key = "m_a" if m_real else "dm"
        record[f"dm_{comp}"] = res[comp][key]
        record[f"dm_{comp}_err"] = res[comp][f"{key}_err"]
    record_real_bias(model, record)


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if a != "--m-real"]
    if len(args) != 4:
        sys.exit("usage: record_bias.py [--m-real] MODEL.h5 RESULT.json SETUP COMMAND")
    main(*args, m_real="--m-real" in sys.argv[1:])
