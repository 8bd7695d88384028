"""Accuracy of a Piff PixelGrid model as ``measure --psf-model`` draws it, against the true PSF.

A known PSF (Moffat, beta 3.5, FWHM 3.8 px, g = (0.02, -0.05), the pixel included; the
profile of ``tests/data/make_psfex_moffat.py``) is drawn noiselessly as ``--n-stars`` stars
on a 2000-px image, at random sub-pixel positions and, for comparison, centred on pixels;
Piff fits a ``PixelGrid`` of ``--scale`` px (order-0 interpolation) to each set;
:meth:`megalut_cli.measure.psf_model.PsfModel.draw` (Piff's own ``PSF.draw``) draws the
model on odd and even stamps, and the adaptive moments of those stamps are compared with
the true PSF's; then stamp metacal (adaptive moments) of noiseless exponential galaxies
sheared by g1 = +-0.02 and seen through the true PSF on 48-px stamps, deconvolved by the
true PSF and by each model: m and c. Needs ``piff`` (``pip install 'megalut-cli[piff]'``). Run::

    PYTHONPATH=. python benchmarks/piff_pixelgrid.py [--n-stars 300] [--scale 1.0]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

#: The true PSF (pixels): that of tests/data/make_psfex_moffat.py.
BETA, FWHM, G1, G2 = 3.5, 3.8, 0.02, -0.05


def stars(n: int, centred: bool, seed: int) -> list:
    """``n`` noiseless stars of the true PSF as Piff stars (25-px cutouts of a 2000-px
    image), at uniform positions or at pixel centres."""
    import galsim
    import piff

    prof = galsim.Moffat(beta=BETA, fwhm=FWHM).shear(g1=G1, g2=G2).withFlux(1e5)
    full = galsim.ImageD(2000, 2000, wcs=galsim.PixelScale(1.0))
    out = []
    for x, y in np.random.default_rng(seed).uniform(40, 1960, (n, 2)):
        if centred:
            x, y = float(round(x)), float(round(y))
        bounds = galsim.BoundsI(int(x) - 12, int(x) + 12, int(y) - 12, int(y) + 12)
        prof.drawImage(full[bounds], center=(x, y))  # the pixel included
        weight = galsim.ImageD(bounds, init_value=1.0, wcs=full.wcs)
        data = piff.StarData(
            full[bounds].copy(), galsim.PositionD(x, y), weight=weight, properties={"chipnum": 0}
        )
        out.append(piff.Star(data, None))
    return out


def galaxy_pairs(size: int, shear: float, seed: int = 1) -> dict[int, np.ndarray]:
    """Noiseless exponentials (half-light radius 1 to 3 px, ellipticity to 0.4, four
    orientations) sheared by g1 = +-``shear``, seen through the true PSF: ``{+1, -1}`` stacks
    (the galaxies of ``tests/test_psf_model.py``'s metacal test)."""
    import galsim

    rng = np.random.default_rng(seed)
    psf = galsim.Moffat(beta=BETA, fwhm=FWHM).shear(g1=G1, g2=G2)
    galaxies = [(rng.uniform(1.0, 3.0), rng.uniform(0.05, 0.4)) for _ in range(20)]
    return {
        sign: np.array(
            [
                galsim.Convolve(
                    galsim.Exponential(half_light_radius=r)
                    .shear(e=e, beta=angle * galsim.degrees)
                    .shear(g1=sign * shear, g2=0.0),
                    psf,
                    galsim.Pixel(1.0),
                )
                .drawImage(nx=size, ny=size, scale=1.0, method="no_pixel")
                .array
                for r, e in galaxies
                for angle in (0, 45, 90, 135)
            ]
        )
        for sign in (1, -1)
    }


def metacal_bias(pairs: dict[int, np.ndarray], psf: np.ndarray, shear: float) -> tuple:
    """m, c1 and c2 of stamp metacal through ``psf`` on the paired stacks: the mean noshear
    g over the mean response, the pairs' half difference and half sum."""
    from megalut_cli.measure.metacal import metacal_features

    g = {}
    for sign, stack in pairs.items():
        f = metacal_features(
            stack, psf[None], 0.01, metacal_engine="fast", psf_index=np.zeros(len(stack), int)
        )
        r11 = ((f["adamom_g1_1p"] - f["adamom_g1_1m"]) / 0.02).mean()
        r22 = ((f["adamom_g2_2p"] - f["adamom_g2_2m"]) / 0.02).mean()
        g[sign] = (f["adamom_g1_noshear"].mean() / r11, f["adamom_g2_noshear"].mean() / r22)
    m = (g[1][0] - g[-1][0]) / (2 * shear) - 1
    return m, (g[1][0] + g[-1][0]) / 2, (g[1][1] + g[-1][1]) / 2


def main() -> None:
    import galsim
    import piff

    from megalut_cli.measure.features import measure_stamps
    from megalut_cli.measure.psf_model import load_psf_model

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n-stars", type=int, default=300)
    parser.add_argument("--scale", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=3)
    args = parser.parse_args()

    truth_profile = galsim.Convolve(
        galsim.Moffat(beta=BETA, fwhm=FWHM).shear(g1=G1, g2=G2), galsim.Pixel(1.0)
    )
    size = int(24 / args.scale) + 1
    pairs = galaxy_pairs(48, 0.02)
    truth48 = truth_profile.drawImage(nx=48, ny=48, scale=1.0, method="no_pixel").array
    m, c1, c2 = metacal_bias(pairs, truth48, 0.02)
    print(f"stamp metacal through the true PSF: m {m:+.2e}, c1 {c1:+.1e}, c2 {c2:+.1e}")
    for centred in (False, True):
        t0 = time.perf_counter()
        psf = piff.SimplePSF(
            piff.PixelGrid(scale=args.scale, size=size), piff.Polynomial(order=0), max_iter=3
        )
        psf.fit(stars(args.n_stars, centred, args.seed), {0: galsim.PixelScale(1.0)}, None)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "model.piff"
            psf.write(str(path))
            model = load_psf_model(str(path))
        for n in (47, 48):
            truth = truth_profile.drawImage(nx=n, ny=n, scale=1.0, method="no_pixel").array
            true = measure_stamps(truth[None].astype(float))
            drawn = measure_stamps(model.draw(1000.0, 1000.0, n))
            print(
                f"PixelGrid scale {args.scale} px, {args.n_stars} stars "
                f"{'at pixel centres' if centred else 'at random positions'}, {n}-px stamp: "
                f"sigma {drawn['adamom_sigma'][0] / true['adamom_sigma'][0] - 1:+.4f}, "
                f"g1 {drawn['adamom_g1'][0] - true['adamom_g1'][0]:+.5f}, "
                f"g2 {drawn['adamom_g2'][0] - true['adamom_g2'][0]:+.5f} "
                f"({time.perf_counter() - t0:.0f} s)"
            )
        m, c1, c2 = metacal_bias(pairs, model.draw(1000.0, 1000.0, 48)[0], 0.02)
        print(f"  stamp metacal through this model: m {m:+.2e}, c1 {c1:+.1e}, c2 {c2:+.1e}")


if __name__ == "__main__":
    main()
