"""The device backend's entry points, which the library reaches through
:func:`megalut_cli.engine.device_backend` (never by importing this package's modules): importing
this module imports JAX.

* :func:`draw_unit`: a fast-engine work unit of ``simulate`` drawn, given its noise and
  measured on the device (:func:`megalut_cli.gpu.draw.draw_unit_device`);
* :func:`pixel_measurements`: the moments, sky MAD and finiteness of host stamps measured on
  the device (:mod:`megalut_cli.gpu.measure`).
"""

from __future__ import annotations

from megalut_cli.gpu.draw import draw_unit_device as draw_unit
from megalut_cli.gpu.measure import pixel_measurements

__all__ = ["draw_unit", "pixel_measurements"]
