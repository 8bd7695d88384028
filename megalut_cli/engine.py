"""The stamp engines: how ``simulate`` draws and ``measure`` measures stamps; and the devices.

``fast`` (the default) renders parametric galaxies in batches in Fourier space
(:mod:`megalut_cli.sim.render`), adds the noise with numpy and measures adaptive moments with
a compiled kernel (:mod:`megalut_cli.measure.adamom`); ``galsim`` draws, adds noise and
measures one stamp at a time through GalSim, the reference. Both give the same noiseless
pixels and the same features to within tests' tolerances (docs/engines.md); their noise
realizations differ (different generators from the same per-stamp seeds).

The ``device`` runs the fast engine and the trainings: ``cpu`` (the default) or ``gpu``, the
optional JAX backend (:mod:`megalut_cli.gpu`, docs/gpu.md); ``auto`` picks ``gpu`` when the
backend finds one.

The library reaches the device backend through one seam, :func:`device_backend`: the backend's
modules import JAX and the library (the renderer, the features), so the library imports them
by name, when a unit runs on the device, and never the other way round.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol, cast

from megalut_cli.errors import ArgumentError
from megalut_cli.gpu import device_problem
from megalut_cli.schema import Option, check_choice

if TYPE_CHECKING:
    import numpy as np

#: Engine name -> one-line description (the CLI's choices and help come from here).
ENGINES: dict[str, str] = {
    "fast": "batched Fourier-space rendering, numpy noise, compiled adaptive moments",
    "galsim": (
        "GalSim drawImage, GalSim noise and galsim.hsm.FindAdaptiveMom, stamp by stamp "
        "(the reference)"
    ),
}

DEFAULT_ENGINE = "fast"

#: Device name -> one-line description (the CLI's choices and help, the ``device`` key).
DEVICES: dict[str, str] = {
    "cpu": "numba and numpy on the CPU cores",
    "gpu": "the JAX backend on a GPU (the 'gpu' extra; one clear error if none is usable)",
    "auto": "gpu when the backend finds one, else cpu",
}

DEFAULT_DEVICE = "cpu"


def described(choices: dict[str, str]) -> str:
    """``name: text; name: text``: choices with their descriptions, as help texts list them."""
    return "; ".join(f"{name}: {text}" for name, text in choices.items())


#: The ``engine`` option of ``simulate``, ``measure`` and pipeline files (the command line
#: says per command what the engine does).
ENGINE_OPTION = Option(
    "engine",
    "choice",
    DEFAULT_ENGINE,
    f"Stamp engine ({described(ENGINES)}).",
    choices=tuple(ENGINES),
)
#: The ``device`` option of ``simulate``, ``measure``, the trainings and pipeline files.
DEVICE_OPTION = Option(
    "device",
    "choice",
    DEFAULT_DEVICE,
    f"Where the fast engine and the trainings run "
    f"({described(DEVICES)}; env MEGALUT_DEVICE; docs/gpu.md).",
    choices=tuple(DEVICES),
    envvar="MEGALUT_DEVICE",
)


def check_engine(name: str, key: str = "engine") -> str:
    """``name`` if it is an engine, else a ``ConfigError`` naming ``key``."""
    return check_choice(name, key, ENGINE_OPTION.choices)


def check_device(name: str, key: str = "device") -> str:
    """``name`` if it is a device choice, else a ``ConfigError`` naming ``key``."""
    return check_choice(name, key, DEVICE_OPTION.choices)


def resolve_device(name: str) -> str:
    """``cpu`` or ``gpu`` for a device choice: ``auto`` becomes ``gpu`` when the backend finds
    one (silently ``cpu`` otherwise); ``gpu`` with none usable raises a one-line
    ``MegalutError``."""
    check_device(name)
    if name == "cpu":
        return "cpu"
    problem = device_problem()
    if problem is None:
        return "gpu"
    if name == "auto":
        return "cpu"
    raise ArgumentError("device", f" gpu: {problem}")


#: The module of the device backend's entry points (it imports JAX).
DEVICE_BACKEND = "megalut_cli.gpu.backend"


class DeviceBackend(Protocol):
    """What the library runs on the device: the entry points of :mod:`megalut_cli.gpu.backend`."""

    #: ``megalut_cli.gpu.train.DeviceObjective``: the interface of
    #: ``megalut_cli.nn.train.Objective`` (costs and gradients of a training), on the device.
    DeviceObjective: Callable[..., Any]

    def draw_unit(self, unit: Any) -> dict[str, Any]:
        """``megalut_cli.sim.draw.draw_unit`` of a fast-engine ``WorkUnit`` on the device."""
        ...

    def pixel_measurements(
        self, stamps: np.ndarray, guess_sigma: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(moments, skymad, finite)`` of host stamps ``(n, S, S)``, measured on the device."""
        ...


def device_backend() -> DeviceBackend:
    """The device backend (:data:`DEVICE_BACKEND`), imported on the first call: the one place
    where the library reaches it."""
    return cast(DeviceBackend, importlib.import_module(DEVICE_BACKEND))
