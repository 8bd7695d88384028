"""Render test cases shared by the renderer and device tests: random galaxies, PSFs, a star
field."""

from __future__ import annotations

import galsim
import numpy as np

from megalut_cli.catalog import write_image
from megalut_cli.sim.draw import get_psf
from megalut_cli.sim.psf import psf_includes_pixel

#: Sersic indices of the random galaxies: gridded and continuous.
N_VALUES = (0.5, 1.0, 1.2345, 2.5, 3.3, 4.567, 6.0)


def random_galaxies(seed: int, m: int, profile: str = "sersic") -> dict[str, np.ndarray]:
    """Corner cases first, then random galaxies (n in N_VALUES, hlr in [0.5, 12] px,
    |e| <= 0.8, |g| <= 0.2, offsets +-0.5 px); FFT sizes kept moderate for speed."""
    corners = [  # n, rad, e1, e2, g1, g2, dx, dy
        (1.0, 12.0, 0.0, -0.8, 0.2, 0.0, 0.5, -0.5),
        (0.5, 0.5, 0.8, 0.0, 0.0, -0.2, -0.5, 0.5),
        (2.5, 6.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),  # round, unsheared, centred
        (1.2345, 3.0, -0.5, 0.6, 0.14, -0.14, 0.25, 0.0),
        (4.567, 1.5, 0.3, 0.0, 0.0, 0.0, 0.0, -0.3),  # sheared by e only
        (6.0, 0.5, 0.0, 0.0, -0.1, 0.17, 0.49, 0.49),  # sheared by g only
    ]
    rng = np.random.default_rng(seed)
    rows = [c for c in corners]
    while len(rows) < m:
        n = rng.choice(N_VALUES)  # few distinct n: a new one costs GalSim (and us) ~0.1-0.3 s
        rad = rng.uniform(0.5, 12.0 if n < 2.5 else 4.0)
        e = rng.uniform(0.0, 0.8) * np.exp(2j * rng.uniform(0, np.pi))
        g = rng.uniform(0.0, 0.2) * np.exp(2j * rng.uniform(0, np.pi))
        rows.append((n, rad, e.real, e.imag, g.real, g.imag, *rng.uniform(-0.5, 0.5, 2)))
    cols = np.array(rows[:m], dtype=float).T
    out = dict(zip(("sersicn", "rad", "e1", "e2", "g1", "g2", "dx", "dy"), cols))
    out["flux"] = rng.uniform(10.0, 2000.0, m)
    out["profile"] = profile
    if profile == "gaussian":
        out["sersicn"] = None
    return out


def write_starfield(path, size=24):
    field = galsim.ImageF(3 * size, 3 * size, scale=1.0)
    for k in range(9):
        i, j = k % 3, k // 3
        b = galsim.BoundsI(i * size + 1, (i + 1) * size, j * size + 1, (j + 1) * size)
        galsim.Gaussian(sigma=1.2 + 0.2 * k, flux=50.0).shear(g1=0.02 * k, g2=-0.01 * k).drawImage(
            field[b], method="no_pixel"
        )
    write_image(path, field.array, fmt="test")
    return path


# (PSF spec, field position, [gsparams], stamp size, galaxies)
RENDER_CASES = [
    ({"type": "gaussian", "sigma": 2.0}, (0, 0), {}, 64, 16),  # fiducial
    ({"type": "gaussian", "sigma": 1.5, "g1": 0.05}, (0, 0), {}, 32, 10),
    (
        {"type": "moffat", "beta": 3.0, "fwhm": 2.5, "g1": 0.03, "g2": -0.04},
        (0, 0),
        {"folding_threshold": 0.01},
        33,
        10,
    ),
    (
        {"type": "moffat", "beta": 2.5, "half_light_radius": 0.6, "trunc": 4.0},
        (0, 0),
        {},
        32,
        8,
    ),  # Nk > N
    ({"type": "field"}, (0.3, 0.9), {}, 64, 10),
    (
        {"type": "field", "sigma_mean": 1.2},
        (1.0, 0.0),
        {"maxk_threshold": 0.002, "kvalue_accuracy": 2e-5},
        128,
        6,
    ),
    ({"type": "euclid", "size": 32}, (0, 0), {"folding_threshold": 0.02}, 33, 10),
    ({"type": "euclid", "size": 32}, (0, 0), {}, 32, 6),
    ({"type": "stamp", "stamp_size": 24, "index": 4}, (0, 0), {}, 33, 10),
    ({"type": "stamp", "stamp_size": 24, "index": 0, "pixel_scale": 0.5}, (0, 0), {}, 32, 6),
]


def render_setup(case: tuple, starfield: str) -> tuple:
    spec, (fx, fy), gsparams, size, m = case
    if spec["type"] == "stamp":
        spec = {**spec, "path": starfield}
    psf, _ = get_psf(spec, fx, fy, spec["type"] == "field", gsparams)
    method = "no_pixel" if psf_includes_pixel(spec) else "auto"
    return psf, method, gsparams, size, m
