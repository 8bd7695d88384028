"""Image simulations of the paper (Sects. 5-7): configuration, parameter distributions,
galaxies, PSFs, noise, the cases x realizations structure, drawing, and
:mod:`megalut_cli.sim.simulate` (:func:`~megalut_cli.sim.simulate.simulate` to files,
:func:`~megalut_cli.sim.simulate.simulate_table` in memory).

Typical use::

    from megalut_cli.sim import load_config
    from megalut_cli.sim.simulate import simulate, simulate_table
    cfg = load_config("examples/fiducial/tp.toml", n_cases=10, n_realizations=20)
    simulate(cfg, "tp.fits", measure=True, seed=1, nproc=2)                    # to files
    columns, stamps = simulate_table(cfg, 1, measure=True, keep_stamps=True)   # in memory

(The function ``simulate`` is not an attribute of this package: that name is its module.)
"""

from __future__ import annotations

from megalut_cli.sim.config import load_config  # no GalSim: sim.config loads it when it must

__all__ = ["load_config"]
