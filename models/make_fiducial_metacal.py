"""Write megalut_cli/data/fiducial-metacal.h5: the networks of fiducial.h5 for metacal catalogs.

The response is a finite difference of any estimator, so the simulation-calibrated networks
serve inside metacal (docs/metacal.md, "Which networks"); this file records that mode, so
that ``megalut predict`` accepts it on ``measure --metacal`` catalogs and refuses it on plain
ones. Run from the repository root: ``python models/make_fiducial_metacal.py``, then
``python models/record_domain.py fiducial-metacal`` (its domain: the noshear features).
"""

from __future__ import annotations

from pathlib import Path

from megalut_cli.nn.model import ShearModel

ROOT = Path(__file__).resolve().parents[1]

if __name__ == "__main__":
    source = ShearModel.load(ROOT / "megalut_cli/data/fiducial.h5")
    model = source.for_mode(
        "metacal",
        "the networks of fiducial.h5 applied to the metacal versions' features "
        "and calibrated by their response (docs/metacal.md)",
    )
    # fiducial.h5's domain is that of plain features: models/record_domain.py records the
    # noshear one
    model.provenance.pop("domain", None)
    model.save(ROOT / "megalut_cli/data/fiducial-metacal.h5", overwrite=True)
    print(f"wrote megalut_cli/data/fiducial-metacal.h5 (sha256 {model.sha256})")
