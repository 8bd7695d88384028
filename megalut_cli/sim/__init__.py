"""Image simulations of the paper (Sects. 5-7): configuration, parameter distributions,
galaxies, PSFs, noise, the cases x realizations structure, drawing and the top-level
:func:`~megalut_cli.sim.simulate.simulate`.

Typical use::

    from megalut_cli.sim import load_config, simulate
    cfg = load_config("examples/fiducial/tp.toml", n_cases=10, n_realizations=20)
    simulate(cfg, "tp.fits", measure=True, seed=1, nproc=2)
"""

from __future__ import annotations

from typing import Any

__all__ = ["load_config", "simulate"]


def __getattr__(name: str) -> Any:  # lazy: importing the package does not import GalSim
    if name == "load_config":
        from megalut_cli.sim.config import load_config

        return load_config
    if name == "simulate":
        from megalut_cli.sim.simulate import simulate

        return simulate
    raise AttributeError(name)
