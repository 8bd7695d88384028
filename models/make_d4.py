"""Write megalut_cli/data/NAME-d4.h5: the networks of the shipped model NAME averaged over the
stamp's 90-degree rotations and reflections (``symmetry = "d4"``, megalut_cli/nn/symmetry.py),
so that they add no additive bias of their own (issue 39; docs/metacal.md, "Issue 39"). The
networks, their domain and the rest of the provenance are NAME's. From the repository root::

    python models/make_d4.py fiducial fiducial-metacal
"""

from __future__ import annotations

import sys
from pathlib import Path

from megalut_cli.nn.model import ShearModel

ROOT = Path(__file__).resolve().parents[1]

if __name__ == "__main__":
    for name in sys.argv[1:] or ["fiducial", "fiducial-metacal"]:
        source = ShearModel.load(ROOT / f"megalut_cli/data/{name}.h5")
        model = source.with_symmetry(
            "d4",
            f"the networks of {name}.h5 averaged over the four actions of the pixel grid's "
            "rotations and reflections on spin-2 features (docs/metacal.md)",
        )
        out = ROOT / f"megalut_cli/data/{name}-d4.h5"
        model.save(out, overwrite=True)
        print(f"wrote {out.relative_to(ROOT)} (sha256 {model.sha256})")
