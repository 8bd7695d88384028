"""The device backend's entry points, which the library reaches through
:func:`megalut_cli.engine.device_backend` (never by importing this package's modules): importing
this module imports JAX.

* :func:`draw_unit`: a fast-engine work unit of ``simulate`` drawn, given its noise and
  measured on the device (:func:`megalut_cli.gpu.draw.draw_unit_device`);
* :func:`pixel_measurements`: the moments, sky MAD and finiteness of host stamps measured on
  the device (:mod:`megalut_cli.gpu.measure`);
* :class:`DeviceObjective`: the costs and gradients of a network's training on the device
  (:mod:`megalut_cli.gpu.train`), for :func:`megalut_cli.nn.train.train_member`.

The first two import their modules when called: a training loads neither GalSim (the drawing's)
nor numba (the measurement's).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from megalut_cli.gpu.train import DeviceObjective

if TYPE_CHECKING:
    import numpy as np

__all__ = ["DeviceObjective", "draw_unit", "pixel_measurements"]


def draw_unit(unit: Any) -> dict[str, Any]:
    """``megalut_cli.sim.draw.draw_unit`` of a fast-engine ``WorkUnit`` on the device."""
    from megalut_cli.gpu.draw import draw_unit_device  # GalSim, numba: not for a training

    return draw_unit_device(unit)


def pixel_measurements(
    stamps: np.ndarray, guess_sigma: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(moments, skymad, finite)`` of host stamps ``(n, S, S)``, measured on the device."""
    from megalut_cli.gpu.measure import pixel_measurements as measured  # numba: not for a training

    return measured(stamps, guess_sigma)
