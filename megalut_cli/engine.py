"""The stamp engines: how ``simulate`` draws and ``measure`` measures stamps.

``fast`` (the default) renders parametric galaxies in batches in Fourier space
(:mod:`megalut_cli.sim.render`), adds the noise with numpy and measures adaptive moments with
a compiled kernel (:mod:`megalut_cli.measure.adamom`); ``galsim`` draws, adds noise and
measures one stamp at a time through GalSim, the reference. Both give the same noiseless
pixels and the same features to within tests' tolerances (docs/engines.md); their noise
realizations differ (different generators from the same per-stamp seeds).
"""

from __future__ import annotations

#: Engine name -> one-line description (the CLI's choices and help come from here).
ENGINES: dict[str, str] = {
    "fast": "batched Fourier-space rendering, numpy noise, compiled adaptive moments",
    "galsim": "GalSim drawImage, GalSim noise and galsim.hsm.FindAdaptiveMom, stamp by stamp (the reference)",
}

DEFAULT_ENGINE = "fast"


def check_engine(name: str, key: str = "engine") -> str:
    """``name`` if it is an engine, else a ``ConfigError`` naming ``key``."""
    from megalut_cli.errors import ConfigError

    if name not in ENGINES:
        raise ConfigError(f"{key}: unknown engine {name!r} (choose from {', '.join(ENGINES)})")
    return name
