"""Noiseless metacal of adaptive moments behind an elliptical Moffat PSF: megalut's round
target PSF (the PSF's round-equivalent HSM sigma, det(M)^(1/4), times 1 + 2|step|) against a
target covering the PSF's major axis (the larger eigenvalue of its moment matrix, as ngmix's
fitted-Gaussian target does). 64 galaxies on a ring (Sersic n = 1.5, half-light radius 3 px,
|g| = 0.3), each under g1 = +-0.02 and g2 = +-0.02, 48-px stamps, fast engine; prints the
calibrated m and c of both targets.

    python examples/metacal/elliptical_psf_target.py 0.05    # PSF g1 = 0.05
    python examples/metacal/elliptical_psf_target.py 0.0     # a round PSF: both targets agree
"""

from __future__ import annotations

import sys

import galsim
import numpy as np

from megalut_cli.measure import metacal
from megalut_cli.measure.features import measure_stamps
from megalut_cli.measure.metacal_targets import METACAL_TARGETS, register_metacal_target
from megalut_cli.measure.metacal_targets.gauss import GaussTarget

SIZE, N_RING, STEP, SHEAR = 48, 64, 0.01, 0.02


def stamps(psf: galsim.GSObject, g1: float, g2: float) -> np.ndarray:
    """The ring of galaxies under shear (g1, g2), convolved with ``psf``, noiseless."""
    out = []
    for i in range(N_RING):
        gal = galsim.Sersic(n=1.5, half_light_radius=3.0, flux=1000.0)
        gal = gal.shear(g=0.3, beta=np.pi * i / N_RING * galsim.radians).shear(g1=g1, g2=g2)
        out.append(galsim.Convolve(gal, psf).drawImage(nx=SIZE, ny=SIZE, scale=1.0).array)
    return np.array(out)


def major_axis_sigma(psf_image: np.ndarray, step: float = STEP) -> float:
    """The sigma of a round Gaussian covering the PSF's major axis, times 1 + 2|step|."""
    res = galsim.hsm.FindAdaptiveMom(galsim.ImageD(psf_image, scale=1.0))
    g = float(np.hypot(res.observed_shape.g1, res.observed_shape.g2))
    return float(res.moments_sigma) * np.sqrt((1.0 + g) / (1.0 - g)) * (1.0 + 2.0 * abs(step))


def major_axis_target(psf_image: np.ndarray, step: float) -> GaussTarget:
    """The round Gaussian target of :func:`major_axis_sigma` (a metacal target factory)."""
    return GaussTarget(major_axis_sigma(psf_image, step))


def main() -> None:
    g_psf = float(sys.argv[1]) if len(sys.argv) > 1 else 0.05
    psf = galsim.Moffat(beta=3.0, fwhm=5.0).shear(g1=g_psf, g2=0.0)
    psf_img = psf.drawImage(nx=SIZE, ny=SIZE, scale=1.0).array
    shears = {"1+": (SHEAR, 0.0), "1-": (-SHEAR, 0.0), "2+": (0.0, SHEAR), "2-": (0.0, -SHEAR)}
    images = {k: stamps(psf, *g) for k, g in shears.items()}
    if "major-axis" not in METACAL_TARGETS:
        register_metacal_target("major-axis", major_axis_target)  # the one line a target needs
    for name, target in (("round-equivalent (megalut)", "gauss"), ("major axis", "major-axis")):
        res = {}
        for k in shears:
            versions, sigma = metacal.metacal_versions(
                images[k], psf_img, STEP, engine="fast", target=target
            )
            f = {t: measure_stamps(v, engine="fast") for t, v in versions.items()}
            r11 = np.mean((f["1p"]["adamom_g1"] - f["1m"]["adamom_g1"]) / (2 * STEP))
            r22 = np.mean((f["2p"]["adamom_g2"] - f["2m"]["adamom_g2"]) / (2 * STEP))
            res[k] = (
                np.mean(f["noshear"]["adamom_g1"]),
                np.mean(f["noshear"]["adamom_g2"]),
                r11,
                r22,
            )
        m1 = (res["1+"][0] - res["1-"][0]) / (2 * SHEAR * 0.5 * (res["1+"][2] + res["1-"][2])) - 1
        m2 = (res["2+"][1] - res["2-"][1]) / (2 * SHEAR * 0.5 * (res["2+"][3] + res["2-"][3])) - 1
        c1 = 0.5 * (res["1+"][0] + res["1-"][0]) / res["1+"][2]
        c2 = 0.5 * (res["2+"][1] + res["2-"][1]) / res["2+"][3]
        print(
            f"PSF g1 = {g_psf}: {name:27s} target sigma {sigma[0]:.4f} px: "
            f"m1 {m1:+.2e}  m2 {m2:+.2e}  c1 {c1:+.2e}  c2 {c2:+.2e}"
        )


if __name__ == "__main__":
    main()
