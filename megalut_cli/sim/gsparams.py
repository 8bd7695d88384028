"""GalSim's ``GSParams`` as plain numbers, and GalSim's version, without importing GalSim.

The fast engine reads its drawing parameters (FFT sizes, accuracies) and names its disk-cache
entries by them; with its Sersic tables and PSF k-images in the disk cache it then draws
without loading GalSim (0.4-0.5 s with astropy). :class:`GsParams` holds the values that
define a ``galsim.GSParams`` (its constructor's arguments, converted as GalSim converts them;
GalSim's defaults), compares and prints like it, and makes the GalSim object when GalSim must
draw (``tests/test_sim_gsparams.py`` checks the defaults and the text against GalSim).
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.metadata
import math
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class GsParams:
    """The values of a ``galsim.GSParams`` (GalSim's defaults); ``repr`` is GalSim's."""

    minimum_fft_size: int = 128
    maximum_fft_size: int = 8192
    folding_threshold: float = 5.0e-3
    stepk_minimum_hlr: float = 5.0
    maxk_threshold: float = 1.0e-3
    kvalue_accuracy: float = 1.0e-5
    xvalue_accuracy: float = 1.0e-5
    table_spacing: int = 1
    realspace_relerr: float = 1.0e-4
    realspace_abserr: float = 1.0e-6
    integration_relerr: float = 1.0e-6
    integration_abserr: float = 1.0e-8
    shoot_accuracy: float = 1.0e-5

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):  # as galsim.GSParams converts its arguments
            kind = int if f.type == "int" else float
            object.__setattr__(self, f.name, kind(getattr(self, f.name)))

    def __repr__(self) -> str:
        texts = [repr(v) for v in self.values()]  # ints print as GalSim's %d, floats as its %r
        return f"galsim.GSParams({','.join(texts)})"

    def values(self) -> tuple[int | float, ...]:
        """The values in GalSim's order (``GSParams._getinitargs``)."""
        return dataclasses.astuple(self)

    @classmethod
    def of(cls, gsparams: Any) -> GsParams:
        """The values of ``gsparams``: a :class:`GsParams`, or a ``galsim.GSParams`` (read
        through its attributes)."""
        if isinstance(gsparams, GsParams):
            return gsparams
        return cls(**{f.name: getattr(gsparams, f.name) for f in dataclasses.fields(cls)})

    @classmethod
    def from_values(cls, values: Any) -> GsParams:
        """Inverse of :meth:`values` (e.g. from a float array of the disk cache)."""
        return cls(*(v.item() if hasattr(v, "item") else v for v in values))

    def galsim(self) -> Any:
        """The ``galsim.GSParams`` of these values (imports GalSim)."""
        import galsim

        return galsim.GSParams(**dataclasses.asdict(self))


@functools.lru_cache(maxsize=1)
def galsim_version() -> str:
    """The installed GalSim's version, from its package metadata (no import of GalSim)."""
    try:
        return importlib.metadata.version("galsim")
    except importlib.metadata.PackageNotFoundError:  # not installed as a package: ask it
        import galsim

        return str(galsim.__version__)


def good_fft_size(input_size: int) -> int:
    """``galsim.Image.good_fft_size``: the next 2^k or 3 x 2^k at or above ``input_size``
    (GalSim's C++ ``goodFFTSize``, operation for operation)."""
    n = int(input_size)
    if n <= 2:
        return 2
    insize = (1.0 - 1.0e-5) * n  # GalSim reduces it slightly against rounding errors
    log2n = math.log(2.0) * math.ceil(math.log(insize) / math.log(2.0))
    log2n3 = math.log(3.0) + math.log(2.0) * math.ceil(
        (math.log(insize) - math.log(3.0)) / math.log(2.0)
    )
    log2n3 = max(log2n3, math.log(6.0))  # must be even
    return int(math.ceil(math.exp(min(log2n, log2n3)) - 1.0e-5))
