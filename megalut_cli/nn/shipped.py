"""The models shipped with megalut (in ``megalut_cli/data/``), by name; see models/README.md."""

from __future__ import annotations

import importlib.resources
from pathlib import Path

from megalut_cli.errors import InputError

#: Name -> file in megalut_cli/data/ (models/ in the repository links to them).
SHIPPED_MODELS = {
    "fiducial": "fiducial.h5",
    "fiducial-1e6": "fiducial-1e6.h5",
    "fiducial-metacal": "fiducial-metacal.h5",
    "fiducial-metacal-d4": "fiducial-metacal-d4.h5",
    "fiducial-d4": "fiducial-d4.h5",
}


def shipped_model(name: str) -> Path:
    """The file of the shipped model ``name``."""
    if name not in SHIPPED_MODELS:
        raise InputError(f"no shipped model {name!r} (shipped: {', '.join(SHIPPED_MODELS)})")
    path = Path(
        str(importlib.resources.files("megalut_cli").joinpath("data", SHIPPED_MODELS[name]))
    )
    if not path.is_file():
        raise InputError(f"the shipped model {name!r} is missing from this installation ({path})")
    return path
