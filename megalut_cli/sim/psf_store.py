"""Fixed PSFs of the fast engine kept in the disk cache, so that it draws without GalSim.

A run whose PSF is one spec of numbers (:func:`stores_psf`: a type of :data:`STORED_TYPES`,
no field dependence, no drawn parameters) names it in the disk cache
(:mod:`megalut_cli.cache`) by that spec, the GSParams, GalSim's and numpy's versions and the
source of the code that builds and draws it (:func:`stored_psf_key`). Its truth, what the
renderer needs of it (:class:`megalut_cli.sim.render.StampRenderer`: GSParams, stepk, maxk)
and its k-image per FFT grid are stored there as GalSim computed them, so a later process
loads them (byte for byte what GalSim gives) and GalSim builds the PSF only on a miss: the
first run, or another GalSim. Star-image PSFs (a file) and varying PSFs (an entry per field
position or draw) are built with GalSim as before.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from megalut_cli.cache import load_arrays, source_digest, store_arrays
from megalut_cli.sim.distributions import Distribution
from megalut_cli.sim.gsparams import galsim_version

#: PSF types whose profile and truth depend on the numbers of their spec only.
STORED_TYPES = ("gaussian", "moffat", "euclid")
#: Entries of this kind in the disk cache.
CACHE_KIND = "psf"
_STORED_MAX = 64  # StoredPsf objects kept per process


def stores_psf(psf_config: Mapping[str, Any], varies: bool) -> bool:
    """Whether a run's PSF (the config's ``[psf]`` table) is kept in the disk cache: one spec
    of numbers, of a type of :data:`STORED_TYPES`, not varying over the field."""
    return (
        not varies
        and psf_config.get("type") in STORED_TYPES
        and not any(isinstance(v, (Distribution, Mapping)) for v in psf_config.values())
    )


#: The code that builds, summarises and draws a stored PSF: this module, the PSF builders,
#: GSParams and the renderer.
_CODE = tuple(
    Path(__file__).parent / name for name in ("psf_store.py", "psf.py", "gsparams.py", "render.py")
)


def stored_psf_key(psf_key: str) -> str:
    """Everything a stored PSF depends on: its spec and GSParams (``psf_key``, as
    :func:`megalut_cli.sim.draw.psf_cache_key` writes them), GalSim's and numpy's versions
    and the source of the code that builds and draws it."""
    code = source_digest(*_CODE)
    return f"psf {psf_key} galsim={galsim_version()} numpy={np.__version__} code={code}"


class StoredPsf:
    """A fixed PSF whose truth, renderer summary and k-images are kept in the disk cache;
    ``build()`` (GalSim) makes its profile and truth, called only when one is missing.

    :class:`megalut_cli.sim.render.StampRenderer` takes it in place of a GalSim profile.
    """

    def __init__(self, psf_key: str, build: Callable[[], tuple[Any, dict[str, float]]]):
        self.key = stored_psf_key(psf_key)
        self._build = build
        self._built: tuple[Any, dict[str, float]] | None = None
        self._truth: dict[str, float] | None = None

    def profile(self) -> Any:
        """The GalSim profile (built at the first call)."""
        if self._built is None:
            self._built = self._build()
        return self._built[0]

    def truth(self) -> dict[str, float]:
        """The truth columns of the PSF (:data:`megalut_cli.sim.psf.TRUTH_COLUMNS`)."""
        if self._truth is None:
            stored = self.load("truth")
            if stored is not None:
                names = [str(n) for n in stored["names"]]
                self._truth = {n: float(v) for n, v in zip(names, stored["values"])}
            else:
                self.profile()
                assert self._built is not None
                self._truth = dict(self._built[1])
                values = np.array(list(self._truth.values()), dtype=np.float64)
                self.store("truth", {"names": np.array(list(self._truth)), "values": values})
        return self._truth

    def load(self, what: str) -> dict[str, np.ndarray] | None:
        """The arrays stored as ``what`` of this PSF (None: absent, cache off)."""
        return load_arrays(CACHE_KIND, f"{self.key} | {what}")

    def store(self, what: str, arrays: Mapping[str, np.ndarray]) -> None:
        """Store ``arrays`` as ``what`` of this PSF."""
        store_arrays(CACHE_KIND, f"{self.key} | {what}", arrays)


_STORED: OrderedDict[str, StoredPsf] = OrderedDict()


def stored_psf(psf_key: str, build: Callable[[], tuple[Any, dict[str, float]]]) -> StoredPsf:
    """The :class:`StoredPsf` named ``psf_key`` in this process (``build`` makes it on a miss)."""
    hit = _STORED.get(psf_key)
    if hit is None:
        hit = _STORED[psf_key] = StoredPsf(psf_key, build)
        while len(_STORED) > _STORED_MAX:
            _STORED.popitem(last=False)
    _STORED.move_to_end(psf_key)
    return hit
