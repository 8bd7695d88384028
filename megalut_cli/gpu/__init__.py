"""The optional device backend of the fast engine and the trainings, in JAX (docs/gpu.md).

Importing this package does not import JAX; :func:`device_problem` says whether a device is
usable, :func:`jax_device` gives it. The submodules (``render``, ``noise``, ``adamom``,
``draw``, ``train``) import JAX and run in float64 where it matters (``jax_enable_x64``);
``backend`` holds the entry points the library calls, through
:func:`megalut_cli.engine.device_backend` only.

The environment variable ``MEGALUT_GPU_PLATFORM`` names the JAX platform that counts as the
device (default ``gpu``; ``cpu`` runs the device path on JAX's CPU mode, as the tests and the
CPU-mode benchmark do).
"""

from __future__ import annotations

import functools
import importlib.util
import os
from typing import Any

#: Environment variable naming the JAX platform used as the device.
PLATFORM_ENV = "MEGALUT_GPU_PLATFORM"


def platform() -> str:
    """The JAX platform that counts as the device (``gpu`` unless ``MEGALUT_GPU_PLATFORM``)."""
    return os.environ.get(PLATFORM_ENV, "gpu").strip().lower() or "gpu"


@functools.lru_cache(maxsize=4)
def _problem(name: str) -> str | None:
    try:
        import jax
    except ImportError:
        return "the GPU backend is not installed (pip install 'megalut-cli[gpu]')"
    try:
        devices = jax.devices(name)
    except RuntimeError:
        devices = []
    if not devices:
        return (
            f"JAX finds no {name} device (its devices: {', '.join(str(d) for d in jax.devices())})"
        )
    return None


def device_problem() -> str | None:
    """Why no device is usable (one line), or None when one is."""
    return _problem(platform())


#: Bytes of compiled device kernels kept in the cache folder's ``jax/`` (JAX drops the least
#: recently used beyond it).
COMPILED_CACHE_BYTES = 512 * 2**20


def jax_device() -> Any:
    """The JAX device that runs the backend (the first of :func:`platform`), float64 enabled,
    its compiled kernels kept in the cache folder (``megalut_cli.cache``) for later runs."""
    import jax

    jax.config.update("jax_enable_x64", True)
    _use_compilation_cache()
    return jax.devices(platform())[0]


@functools.lru_cache(maxsize=1)
def _use_compilation_cache() -> None:
    """Once per process: JAX's persistent cache in ``jax/`` of megalut's cache folder."""
    import jax

    from megalut_cli.cache import cache_dir

    folder = cache_dir()
    if folder is None or jax.config.values.get("jax_compilation_cache_dir"):
        return  # cache off, or the user's own JAX cache
    if (
        importlib.util.find_spec("filelock") is None
        or "jax_compilation_cache_max_size" not in jax.config.values
    ):
        return  # JAX bounds its cache's size only with filelock (the 'gpu' extra), if at all
    jax.config.update("jax_compilation_cache_dir", str(folder / "jax"))
    if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_compilation_cache_max_size", COMPILED_CACHE_BYTES)
