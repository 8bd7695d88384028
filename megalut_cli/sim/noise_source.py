"""Where a correlated-noise model comes from (``noise.type = "correlated"``): read by the
``[noise]`` table (:mod:`megalut_cli.sim.noise_config`), drawn by :mod:`megalut_cli.sim.noise`."""

from __future__ import annotations

from dataclasses import dataclass

#: Sources of correlated noise: a noise image or a correlation-function image.
CORRELATED_SOURCES = ("image", "correlation")


@dataclass(frozen=True)
class CorrelationSource:
    """Where a correlated-noise model comes from (plain, picklable)."""

    kind: str  # "image" | "correlation"
    path: str
    hdu: int | None = None
    pixel_scale: float = 1.0  # size of the source's pixel in simulation pixels
