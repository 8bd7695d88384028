"""Pixel noise of the simulated stamps (sky-subtracted images).

- ``gaussian``: stationary Gaussian noise of standard deviation ``sigma`` (ADU), the
  paper's background-limited toy model;
- ``ccd``: GalSim ``CCDNoise``: Poisson noise of the source plus a sky level that has
  been subtracted, and Gaussian read noise, with the sky level from a magnitude per
  arcsec^2: ``F_sky = pix^2 * t / G * 10^(-0.4 (m_sky - Zp))`` (ADU per pixel);
- ``correlated``: stationary Gaussian noise of pixel standard deviation ``sigma`` (ADU)
  whose correlation function is that of a noise image (e.g. a blank-sky cutout of the
  data, GalSim ``CorrelatedNoise``) or a correlation-function image (GalSim
  ``getCOSMOSNoise``), dilated by the source's pixel size in simulation pixels
  (``pixel_scale``), sampled at the simulation's pixel separations and rescaled to the
  pixel variance ``sigma**2``;
- ``none``: noiseless stamps.

``override_sigma`` replaces any of these by Gaussian noise of that sigma (low-noise
pretraining sets, Sect. 6 of the paper).

GalSim is imported by the functions that use it (correlated noise, the GalSim engine's
:meth:`StampNoise.add`), not with this module: the fast engine's Gaussian and CCD noise do
not load it.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from megalut_cli.errors import InputError
from megalut_cli.sim.noise_source import CorrelationSource
from megalut_cli.sim.normals import add_gaussian_noise

if TYPE_CHECKING:
    import galsim


@functools.lru_cache(maxsize=8)
def unit_correlated_noise(source: CorrelationSource) -> galsim.BaseCorrelatedNoise:
    """The correlated-noise model of ``source`` in simulation pixels, pixel variance 1
    (built once per process; its random generator is reset for every stamp)."""
    import galsim

    try:
        if source.kind == "correlation":
            cn = galsim.getCOSMOSNoise(
                file_name=source.path, cosmos_scale=source.pixel_scale, variance=1.0
            )
        else:
            image = galsim.fits.read(source.path, hdu=source.hdu)
            cn = galsim.CorrelatedNoise(image, scale=source.pixel_scale, subtract_mean=True)
    except (OSError, ValueError, KeyError, galsim.GalSimError) as err:
        raise InputError(
            f"noise.{source.kind}: {source.path}: not a usable {source.kind} image ({err})"
        ) from None
    if not cn.getVariance() > 0:
        raise InputError(f"noise.{source.kind}: {source.path}: the noise has no variance")
    return cn.withVariance(1.0)


def source_variance(source: CorrelationSource) -> float:
    """Pixel variance of the noise of a noise image."""
    import galsim

    image = galsim.fits.read(source.path, hdu=source.hdu)
    cn = galsim.CorrelatedNoise(image, scale=source.pixel_scale, subtract_mean=True)
    return float(cn.getVariance())


def sky_level(sky_mag: float, instrument: Mapping[str, float]) -> float:
    """Sky level in ADU per pixel for a sky brightness of ``sky_mag`` mag per arcsec^2."""
    return (
        instrument["pixel_scale"] ** 2
        * instrument["exptime"]
        / instrument["gain"]
        * 10.0 ** (-0.4 * (sky_mag - instrument["zeropoint"]))
    )


class StampNoise:
    """The noise of one case: ``add(image, seed)`` adds a realization seeded by ``seed``."""

    def __init__(
        self,
        kind: str,
        *,
        sigma: float = 0.0,
        sky: float = 0.0,
        gain: float = 1.0,
        read_noise: float = 0.0,
        source: CorrelationSource | None = None,
    ):
        self.kind = kind
        self.sigma = float(sigma)
        self.sky = float(sky)
        self.gain = float(gain)
        self.read_noise = float(read_noise)
        self.source = source

    @property
    def sky_sigma(self) -> float:
        """Standard deviation (ADU) of the background noise of a pixel without source."""
        if self.kind in ("gaussian", "correlated"):
            return self.sigma
        if self.kind == "ccd":
            return math.sqrt(self.sky / self.gain + (self.read_noise / self.gain) ** 2)
        return 0.0

    def add(self, image: galsim.Image, seed: int, sign: float = 1.0) -> None:
        """Add a realization seeded by ``seed`` to the GalSim ``image`` (``sign`` -1: its
        opposite, Gaussian and correlated noise only)."""
        import galsim

        if sign != 1.0:
            if self.kind not in ("gaussian", "correlated"):
                raise ValueError(f"{self.kind} noise has no opposite")
            field = galsim.ImageF(image.bounds, scale=image.scale)
            self.add(field, seed)
            image.array[...] -= field.array.astype(image.array.dtype, copy=False)
            return
        if self.kind == "gaussian":
            if self.sigma > 0:
                image.addNoise(
                    galsim.GaussianNoise(galsim.BaseDeviate(int(seed)), sigma=self.sigma)
                )
        elif self.kind == "correlated":
            if self.sigma > 0 and self.source is not None:
                unit = unit_correlated_noise(self.source)
                unit.rng.reset(int(seed))
                field = galsim.ImageD(image.bounds, scale=image.scale)
                field.addNoise(unit)
                image.array[...] += (self.sigma * field.array).astype(image.array.dtype, copy=False)
        elif self.kind == "ccd":
            image.addNoise(
                galsim.CCDNoise(
                    galsim.BaseDeviate(int(seed)),
                    sky_level=self.sky,
                    gain=self.gain,
                    read_noise=self.read_noise,
                )
            )

    def add_batch(
        self, stamps: np.ndarray, seeds: np.ndarray, signs: np.ndarray | None = None
    ) -> None:
        """Add the noise to float32 ``stamps`` ``(n, S, S)`` in place (the fast engine).

        Stamp ``i`` gets its own realization from ``seeds[i]`` (the same per-stamp seed that
        the GalSim engine gives GalSim), so the noise never depends on how stamps are batched
        or which worker draws them: Gaussian noise from :mod:`megalut_cli.sim.normals`
        (compiled, one xoshiro256** stream per seed), CCD noise from numpy's PCG64 seeded
        with it. Correlated noise is generated by GalSim, stamp by stamp, exactly as
        :meth:`add` does. ``signs`` (per stamp, +1 or -1): -1 adds the opposite realization
        (antithetic twins; Gaussian and correlated noise only).
        """
        if self.kind == "none":
            return
        if signs is not None and self.kind not in ("gaussian", "correlated"):
            raise ValueError(f"{self.kind} noise has no opposite")
        if self.kind == "gaussian":
            if self.sigma > 0:
                add_gaussian_noise(stamps, np.asarray(seeds, dtype=np.int64), self.sigma, signs)
            return
        if self.kind == "correlated":
            import galsim

            each = np.ones(len(stamps)) if signs is None else np.asarray(signs, dtype=float)
            for stamp, seed, sign in zip(
                stamps, np.asarray(seeds, dtype=np.int64).tolist(), each.tolist()
            ):
                image = galsim.ImageF(stamp.copy(), scale=1.0)
                self.add(image, seed, sign)
                stamp[...] = image.array
            return
        for stamp, seed in zip(stamps, np.asarray(seeds, dtype=np.int64).tolist()):
            rng = np.random.Generator(np.random.PCG64(seed))
            if (
                self.kind == "ccd"
            ):  # as GalSim's CCDNoise: Poisson(electrons of source + sky) - sky, read noise
                electrons = ((stamp.astype(np.float64) + self.sky) * self.gain).clip(0.0)
                noisy = (
                    rng.poisson(electrons) / self.gain - self.sky if self.gain > 0 else stamp + 0.0
                )
                if self.read_noise > 0:
                    noisy += (self.read_noise / self.gain) * rng.standard_normal(stamp.shape)
                stamp[...] = noisy


def make_noise(
    kind: str,
    params: Mapping[str, float],
    instrument: Mapping[str, float],
    override_sigma: float | None = None,
    source: CorrelationSource | None = None,
) -> StampNoise:
    """The :class:`StampNoise` of a case from its (scalar) noise parameters."""
    if override_sigma is not None:
        return StampNoise("gaussian", sigma=override_sigma)
    if kind == "gaussian":
        return StampNoise("gaussian", sigma=params["sigma"])
    if kind == "correlated":
        return StampNoise("correlated", sigma=params["sigma"], source=source)
    if kind == "ccd":
        return StampNoise(
            "ccd",
            sky=sky_level(params["sky_mag"], instrument),
            gain=instrument["gain"],
            read_noise=params.get("read_noise", 0.0),
        )
    return StampNoise("none")
