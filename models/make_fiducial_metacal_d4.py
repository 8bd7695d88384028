"""Write megalut_cli/data/fiducial-metacal-d4.h5: the networks of fiducial-metacal.h5 averaged
over the stamp's 90-degree rotations and reflections (``symmetry = "d4"``,
megalut_cli/nn/symmetry.py), so that they add no additive bias of their own (issue 39;
docs/metacal.md, "The networks' additive bias"). The networks, their domain and the rest of
the provenance are those of fiducial-metacal.h5. Run from the repository root:
``python models/make_fiducial_metacal_d4.py``.
"""

from __future__ import annotations

from pathlib import Path

from megalut_cli.nn.model import ShearModel

ROOT = Path(__file__).resolve().parents[1]

if __name__ == "__main__":
    source = ShearModel.load(ROOT / "megalut_cli/data/fiducial-metacal.h5")
    model = source.with_symmetry(
        "d4",
        "the networks of fiducial-metacal.h5 averaged over the four actions of the pixel "
        "grid's rotations and reflections on spin-2 features (docs/metacal.md)",
    )
    out = ROOT / "megalut_cli/data/fiducial-metacal-d4.h5"
    model.save(out, overwrite=True)
    print(f"wrote {out.relative_to(ROOT)} (sha256 {model.sha256})")
