"""Pixel noise of the simulated stamps (sky-subtracted images).

- ``gaussian``: stationary Gaussian noise of standard deviation ``sigma`` (ADU), the
  paper's background-limited toy model;
- ``ccd``: GalSim ``CCDNoise``: Poisson noise of the source plus a sky level that has
  been subtracted, and Gaussian read noise, with the sky level from a magnitude per
  arcsec^2: ``F_sky = pix^2 * t / G * 10^(-0.4 (m_sky - Zp))`` (ADU per pixel);
- ``none``: noiseless stamps.

``override_sigma`` replaces any of these by Gaussian noise of that sigma (low-noise
pretraining sets, Sect. 6 of the paper).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import galsim
import numpy as np


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

    def __init__(self, kind: str, *, sigma: float = 0.0, sky: float = 0.0, gain: float = 1.0, read_noise: float = 0.0):
        self.kind = kind
        self.sigma = float(sigma)
        self.sky = float(sky)
        self.gain = float(gain)
        self.read_noise = float(read_noise)

    @property
    def sky_sigma(self) -> float:
        """Standard deviation (ADU) of the background noise of a pixel without source."""
        if self.kind == "gaussian":
            return self.sigma
        if self.kind == "ccd":
            return math.sqrt(self.sky / self.gain + (self.read_noise / self.gain) ** 2)
        return 0.0

    def add(self, image: galsim.Image, seed: int) -> None:
        if self.kind == "gaussian":
            if self.sigma > 0:
                image.addNoise(galsim.GaussianNoise(galsim.BaseDeviate(int(seed)), sigma=self.sigma))
        elif self.kind == "ccd":
            image.addNoise(
                galsim.CCDNoise(
                    galsim.BaseDeviate(int(seed)),
                    sky_level=self.sky,
                    gain=self.gain,
                    read_noise=self.read_noise,
                )
            )


    def add_batch(self, stamps: np.ndarray, seeds: np.ndarray) -> None:
        """Add the noise to float32 ``stamps`` ``(n, S, S)`` in place (the fast engine).

        Stamp ``i`` gets its own realization from numpy's PCG64 generator seeded with
        ``seeds[i]`` (the same per-stamp seed that the GalSim engine gives GalSim), so the
        noise never depends on how stamps are batched or which worker draws them.
        """
        if self.kind == "none":
            return
        for stamp, seed in zip(stamps, np.asarray(seeds, dtype=np.int64).tolist()):
            rng = np.random.Generator(np.random.PCG64(seed))
            if self.kind == "gaussian":
                if self.sigma > 0:
                    stamp += np.float32(self.sigma) * rng.standard_normal(stamp.shape, dtype=np.float32)
            elif self.kind == "ccd":  # as GalSim's CCDNoise: Poisson(electrons of source + sky) - sky, read noise
                electrons = ((stamp.astype(np.float64) + self.sky) * self.gain).clip(0.0)
                noisy = rng.poisson(electrons) / self.gain - self.sky if self.gain > 0 else stamp + 0.0
                if self.read_noise > 0:
                    noisy += (self.read_noise / self.gain) * rng.standard_normal(stamp.shape)
                stamp[...] = noisy


def make_noise(
    kind: str,
    params: Mapping[str, float],
    instrument: Mapping[str, float],
    override_sigma: float | None = None,
) -> StampNoise:
    """The :class:`StampNoise` of a case from its (scalar) noise parameters."""
    if override_sigma is not None:
        return StampNoise("gaussian", sigma=override_sigma)
    if kind == "gaussian":
        return StampNoise("gaussian", sigma=params["sigma"])
    if kind == "ccd":
        return StampNoise(
            "ccd",
            sky=sky_level(params["sky_mag"], instrument),
            gain=instrument["gain"],
            read_noise=params.get("read_noise", 0.0),
        )
    return StampNoise("none")
