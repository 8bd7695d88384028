"""Draw a MEDS file of known world-frame shear seen through rotated, flipped and distorted
Jacobians, with an elliptical PSF that varies over the field, in one or several epochs.

    python examples/world-frame/make_meds.py -o world.meds.fits [--n-objects 16000]
        [--epochs 1] [--seed 1]

Galaxies of the fiducial population (Sérsic n 1–4, half-light radius 2–8 px, surface
brightness 1–15, intrinsic ellipticities of mode 0.2, in 90° pairs) are sheared by one
world-frame shear (``--g1``, ``--g2``; default +0.02, −0.01), convolved with a Gaussian PSF
of sigma 2 px whose world-frame ellipticity turns over the field (``|e| = --psf-e``, default
0.03, its angle following the object's position), and drawn by GalSim into 64-px cutouts
through each pair's own Jacobian: a pixel scale of 0.2", a rotation by any angle, a flip of
the axes for half of them, and a residual shear of the pixel grid (``--eta`` rms per
component, default 0.01), written as the MEDS ``dudrow .. dvdcol``. Noise sigma 1, weight
maps, the PSF drawn through the same Jacobian as PSF cutouts, positions ``ra, dec`` on a
1 deg² field. The true world shear rides along as ``tru_g1, tru_g2``; the PSF's world
ellipticity (of the first epoch) as ``tru_psf_g1, tru_psf_g2``.

With ``--epochs N`` > 1 each object has N single-epoch cutouts, each through its own
Jacobian, with its own PSF (the ellipticity pattern turned by 360°/N per epoch) and noise
sigma 1, and an ideal coadd as cutout 0: the galaxy convolved with the mean of the epochs'
PSFs, drawn north up (``dudcol = dvdrow = 0.2``, no distortion) with noise sigma 1/sqrt(N),
its PSF cutout that mean PSF (an ideal coadd: no resampling, no correlated noise). See
README.md here.
"""

from __future__ import annotations

import argparse

import galsim
import numpy as np

from megalut_cli.measure.meds import write_meds

#: Cutout size, pixel scale (arcsec) and PSF sigma (pixels): the fiducial setup's.
SIZE, SCALE, PSF_SIGMA = 64, 0.2, 2.0


def jacobian(phi: float, flip: bool, eta: np.ndarray) -> np.ndarray:
    """``SCALE R(phi) F (1 + eta)``: ``[[dudcol, dudrow], [dvdcol, dvdrow]]``."""
    rot = np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
    par = np.diag([1.0, -1.0]) if flip else np.eye(2)
    dist = np.array([[1 + eta[0], eta[1]], [eta[1], 1 - eta[0]]])
    return SCALE * rot @ par @ dist


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--n-objects", type=int, default=16000, help="objects (pairs: even)")
    ap.add_argument("--g1", type=float, default=0.02)
    ap.add_argument("--g2", type=float, default=-0.01)
    ap.add_argument("--psf-e", type=float, default=0.03, help="PSF world ellipticity |e|")
    ap.add_argument("--eta", type=float, default=0.01, help="rms residual shear of the grid")
    ap.add_argument("--epochs", type=int, default=1, help="single-epoch cutouts per object")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    n_pairs = args.n_objects // 2
    n = 2 * n_pairs
    ra = np.repeat(rng.uniform(150.0, 151.0, n_pairs), 2)
    dec = np.repeat(rng.uniform(2.0, 3.0, n_pairs), 2)
    psf_angle = np.pi * (ra - 150.0) + 2.0 * np.pi * (dec - 2.0)  # turns over the field
    psf_g = args.psf_e * np.array([np.cos(psf_angle), np.sin(psf_angle)])
    n_cut = args.epochs + (1 if args.epochs > 1 else 0)
    images = np.empty((n, n_cut, SIZE, SIZE), np.float32)
    weights = np.empty((n, n_cut, SIZE, SIZE), np.float32)
    psfs = np.empty((n, n_cut, SIZE, SIZE), np.float32)
    jacs = np.empty((n, n_cut, 2, 2))
    noise = galsim.BaseDeviate(args.seed)
    for p in range(n_pairs):
        nser = round(rng.uniform(1.0, 4.0), 1)
        rad = rng.uniform(2.0, 8.0) * SCALE
        flux = rng.uniform(1.0, 15.0) * np.pi * (rad / SCALE) ** 2
        ell = min(rng.rayleigh(0.2), 0.6)
        beta = rng.uniform(0.0, np.pi)
        i = 2 * p
        offset = rng.uniform(-0.5, 0.5, 2)
        epochs = []
        for e in range(args.epochs):
            turn = 2 * np.pi * e / args.epochs
            c, s = np.cos(turn), np.sin(turn)
            eg = (c * psf_g[0, i] - s * psf_g[1, i], s * psf_g[0, i] + c * psf_g[1, i])
            psf = galsim.Gaussian(sigma=PSF_SIGMA * SCALE).shear(g1=eg[0], g2=eg[1])
            phi, flip = rng.uniform(0.0, 2 * np.pi), rng.random() < 0.5
            epochs.append((psf, jacobian(phi, flip, rng.normal(0, args.eta, 2)), 1.0))
        if args.epochs > 1:  # the ideal coadd, first
            mean_psf = galsim.Sum([psf for psf, _, _ in epochs]) / args.epochs
            epochs.insert(0, (mean_psf, SCALE * np.eye(2), 1.0 / np.sqrt(args.epochs)))
        for k in range(2):  # the pair: the same galaxy turned by 90 degrees
            gal = galsim.Sersic(n=nser, half_light_radius=rad, flux=flux)
            gal = gal.shear(g=ell, beta=(beta + k * np.pi / 2) * galsim.radians)
            gal = gal.shear(g1=args.g1, g2=args.g2)
            for cut, (psf, jac, sigma) in enumerate(epochs):
                wcs = galsim.JacobianWCS(jac[0, 0], jac[0, 1], jac[1, 0], jac[1, 1])
                img = galsim.Convolve(gal, psf).drawImage(nx=SIZE, ny=SIZE, wcs=wcs, offset=offset)
                img.addNoise(galsim.GaussianNoise(noise, sigma=sigma))
                images[i + k, cut] = img.array
                weights[i + k, cut] = 1.0 / sigma**2
                psfs[i + k, cut] = psf.drawImage(nx=SIZE, ny=SIZE, wcs=wcs).array
                jacs[i + k, cut] = jac
    write_meds(
        args.output,
        [list(c) for c in images],
        weights=[list(c) for c in weights],
        psfs=[list(c) for c in psfs],
        first_is_coadd=args.epochs > 1,
        ra=ra,
        dec=dec,
        jacobians=jacs,
        pixel_scale=SCALE,
        extra={
            "tru_g1": np.full(n, args.g1),
            "tru_g2": np.full(n, args.g2),
            "tru_psf_g1": psf_g[0],
            "tru_psf_g2": psf_g[1],
        },
        overwrite=args.overwrite,
    )
    print(f"wrote {args.output}: {n} objects, {n_cut} cutout(s) each")


if __name__ == "__main__":
    main()
