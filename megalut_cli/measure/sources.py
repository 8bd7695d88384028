"""The stamp sources of ``megalut measure`` (:mod:`.source_registry`): importing this module
registers them all. A new input format is a module that calls ``register_stamp_source`` and
one import line here."""

from __future__ import annotations

from megalut_cli.measure import cells, coadd, grid, meds
from megalut_cli.measure.source_registry import (
    CellSettings,
    DetectSettings,
    Measured,
    MeasureRequest,
    StampSourceType,
    registered_stamp_sources,
    stamp_source_for,
)

#: The sources registered by the modules imported above.
BUILTIN_SOURCES: tuple[StampSourceType, ...] = (
    meds.MEDS_SOURCE,
    cells.CELLS_SOURCE,
    coadd.COADD_SOURCE,
    grid.GRID_SOURCE,
)

__all__ = [
    "BUILTIN_SOURCES",
    "CellSettings",
    "DetectSettings",
    "MeasureRequest",
    "Measured",
    "StampSourceType",
    "registered_stamp_sources",
    "stamp_source_for",
]
