"""The registry of stamp sources: the input formats of ``megalut measure``.

A :class:`StampSourceType` says whether it recognises a file, checks the arguments that
apply to it, and measures a :class:`MeasureRequest` into a :class:`Measured` catalog (its
stamps cut into work units, :mod:`.units`, measured by :mod:`.measurer`). Modules that
define a source call :func:`register_stamp_source`; :mod:`.sources` imports them all.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from megalut_cli.errors import Names
from megalut_cli.measure.defaults import DUPLICATE_RADIUS, MASK_FILLS, MASK_MARGIN
from megalut_cli.measure.measurer import MeasureSettings
from megalut_cli.measure.options import MEASURE
from megalut_cli.progress import Progress


@dataclass(frozen=True)
class MeasureRequest:
    """What ``megalut measure`` is asked: the input files, what to measure
    (:class:`~.measurer.MeasureSettings`), the options of the input formats, and how to run."""

    stamps_path: str
    catalog_path: str | None
    output: str
    settings: MeasureSettings
    stamp_size: int | None = None
    origin: int = 1
    psf_path: str | None = None
    psf_model_path: str | None = None
    stars: bool | None = None
    cutout: int = 0
    nproc: int = 1
    scheduler: str | None = None
    progress: Progress | None = None
    names: Names | None = None
    epochs: bool = False
    metadetect: bool = False
    detect: DetectSettings | None = None
    cells: CellSettings | None = None
    detect_only: bool = False

    @property
    def detects(self) -> bool:
        """Whether the objects are found in the images (``--metadetect`` or ``--detect``)."""
        return self.metadetect or self.detect_only


@dataclass(frozen=True)
class CoaddImage:
    """An image given with a coadd measured in cells: the :class:`CellSettings` field (and
    argument of :func:`.measure.measure_file_columns`) holding its path, its name in
    messages (``the weight image``), what it is in header comments, and the prefix of its
    header cards (``<card>FILE``, ``<card>SHA``)."""

    field: str
    label: str
    what: str
    card: str


#: The images given with a coadd besides the coadd itself, in the order of their arguments,
#: messages and header cards: the weight map (required), the mask and a noise realization.
COADD_IMAGES: tuple[CoaddImage, ...] = (
    CoaddImage("weight_path", "weight", "weight map", "WGT"),
    CoaddImage("mask_path", "mask", "mask", "MSK"),
    CoaddImage("noise_path", "noise", "noise image", "NOI"),
)


@dataclass(frozen=True)
class CellSettings:
    """A coadd image measured with ``--metadetect``: its weight map (inverse variance), mask
    and noise image files (or None; :data:`COADD_IMAGES`), and how it is cut into cells: their
    side and the border outside each cell's inner region (the inner regions tile the image)."""

    weight_path: str | None
    mask_path: str | None
    noise_path: str | None
    size: int
    border: int

    def given(self) -> list[str]:
        """The arguments given for a coadd, in order: the images' paths that are not None,
        then ``cell_size`` and ``cell_border`` where not their defaults."""
        out = [image.field for image in COADD_IMAGES if getattr(self, image.field) is not None]
        for arg, value in (("cell_size", self.size), ("cell_border", self.border)):
            if value != MEASURE[arg].default:
                out.append(arg)
        return out


@dataclass(frozen=True)
class DetectSettings:
    """The detection of ``--metadetect`` (sep): threshold in noise sigmas, the fewest pixels
    of a detection, the deblending sub-thresholds and minimum contrast, and whether sep
    cleans the detections (its default); whether the other detections' segments are masked
    in each detection's stamp; how close to a masked pixel of the cell a detection's
    unsheared position may lie before it is flagged NEAR_MASK (pixels); what the masked
    pixels hold (``MASK_FILLS``); how close two detections' adaptive-moment centroids lie
    before one is flagged DUPLICATE (pixels)."""

    thresh: float
    minarea: int
    nthresh: int
    cont: float
    clean: bool = True
    mask_neighbours: bool = False
    mask_margin: float = MASK_MARGIN
    mask_fill: str = MASK_FILLS[0]
    duplicate_radius: float = DUPLICATE_RADIUS


@dataclass
class Measured:
    """A measured catalog to write: its columns (in order), header cards, HISTORY lines,
    HDUs carried from the input, format name, and the input catalog's header (``meta``)."""

    columns: dict[str, np.ndarray]
    cards: dict[str, Any]
    fmt: str
    history: list[str] | None = None
    extra_hdus: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class StampSourceType:
    """An input format: ``recognises(path)``, ``check(request)`` (its arguments, before any
    output is touched: a ConfigError names the one that does not apply) and
    ``measure(request)``. A ``fallback`` type takes what no other recognises or ``claims``."""

    name: str
    recognises: Callable[[str], bool]
    check: Callable[[MeasureRequest], None]
    measure: Callable[[MeasureRequest], Measured]
    fallback: bool = False
    #: Takes a request no source recognises by its file, by what it asks (e.g. a plain image
    #: with ``--metadetect``), before the fallback.
    claims: Callable[[MeasureRequest], bool] | None = None


_REGISTRY: dict[str, StampSourceType] = {}


def register_stamp_source(source: StampSourceType) -> StampSourceType:
    """Register ``source`` under its name (once) and return it."""
    if source.name in _REGISTRY:
        raise ValueError(f"stamp source {source.name!r} is registered already")
    if source.fallback and any(s.fallback for s in _REGISTRY.values()):
        raise ValueError("only one stamp source can be the fallback")
    _REGISTRY[source.name] = source
    return source


def registered_stamp_sources() -> tuple[StampSourceType, ...]:
    """Every registered source, in registration order."""
    return tuple(_REGISTRY.values())


def stamp_source_for(path: str, request: MeasureRequest | None = None) -> StampSourceType:
    """The source that recognises ``path``, else one that claims ``request``, else the
    fallback."""
    for source in _REGISTRY.values():
        if not source.fallback and source.recognises(path):
            return source
    if request is not None:
        for source in _REGISTRY.values():
            if source.claims is not None and source.claims(request):
                return source
    for source in _REGISTRY.values():
        if source.fallback:
            return source
    raise ValueError(f"{path}: no stamp source recognises it")


def unregister_stamp_source(name: str) -> None:
    """Remove the source registered as ``name`` (a plug-in's or a test's)."""
    if name not in _REGISTRY:
        raise ValueError(f"no stamp source {name!r} is registered")
    del _REGISTRY[name]
