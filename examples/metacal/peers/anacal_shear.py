"""AnaCal (FPFS shear with its analytic response; Li & Mandelbaum) on megalut's stamps.

    python examples/metacal/peers/anacal_shear.py STAMPS.fits MEASURED.fits --psf PSF.fits
        -o OUT.fits [--sigma-shapelets 4.0] [--c0-factor 4] [--noise-sigma S]
        [--centre adamom|stamp|truth] [--no-noise-array] [--seed 5] [--chunk 256] [--overwrite]

STAMPS is a megalut stamp image (`megalut simulate --stamps`), MEASURED the catalog of
`megalut measure STAMPS CATALOG` (plain): its stamp centres `x, y` locate the stamps, its
adaptive-moment centroid `adamom_x, adamom_y` (FITS 1-based, in STAMPS) is where AnaCal
measures each galaxy (a stamp whose moments failed is measured at its centre; it is kept,
so that nothing is selected), its `skymad` sets the level of AnaCal's noise image. PSF is
one PSF image in megalut's convention (`--psf` of `megalut measure`: centred on the stamp's
true centre, e.g. (31.5, 31.5) 0-based for 64 px); it is moved by Fourier phase to the pixel
(npix // 2, npix // 2) that AnaCal takes as the PSF centre, and normalized.

Every stamp is measured alone: it is placed, with a zero border, in its own cell of a row of
cells, and one AnaCal forced measurement (`anacal.fpfs.process_image`, one shapelet kernel,
detection = the centroids) runs over a chunk of such cells, so that AnaCal's 64-pixel window
never sees a neighbouring stamp. AnaCal's noise-bias correction is used: a pure-noise image
(white, sigma = the stamp's skymad, one field per stamp from --seed and the realization in a
common-random-number set, else the row, so that paired real/twin sets share them) is measured
rotated by 90 degrees and added.

Output: every column of MEASURED, plus
  anacal_e1, anacal_e2, anacal_de1_dg1, anacal_de2_dg2, anacal_m00, anacal_s2n,
  anacal_x, anacal_y (where it measured, FITS 1-based in STAMPS), anacal_flags
  (1: no centroid (adaptive moments failed), measured at the stamp centre; 2: non-finite
  AnaCal output);
and the columns through which `megalut evaluate` calibrates it like metacal, by the mean
response: pre_g1_noshear := e1, pre_g2_noshear := e2, mcal_r11 := de1/dg1,
mcal_r22 := de2/dg2, mcal_r12 = mcal_r21 := 0, flags_noshear (and flags_1p, ..., flags_2m,
the same: there are no sheared images) := anacal_flags & 2, and
pre_g1, pre_g2 := e / <R> (R the catalog's mean response: a per-galaxy estimate for other
uses; evaluate does not read it in this mode). Header: MCALSTEP = 0.01 (unused without a
selection or weights), the input's cards (CRN, SNC, ...), and the AnaCal settings.
The CPU time of the AnaCal part (time.process_time, one thread) is logged and written
to the header (ANCPUGAL: seconds per galaxy).

Defaults (README.md, "AnaCal: the settings"): kernel sigma 4 px (2 x the PSF sigma of the
fiducial setup), c0 = 4 x std(m00) of prepare_covariance at the median skymad.
"""

from __future__ import annotations

import os

for _v in (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "NUMBA_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import anacal  # noqa: E402
import fitsio  # noqa: E402
import numpy as np  # noqa: E402

from megalut_cli.catalog import read_catalog, write_catalog  # noqa: E402
from megalut_cli.measure.stamps import (  # noqa: E402
    catalog_origins,
    cut_stamps,
    image_info,
    read_rows,
    stamp_size_of,
)

#: Nominal pixel scale handed to AnaCal. Only sigma_shapelets / pixel_scale matters for the
#: shapes (checked: scale 1 and 0.2 give e to 7e-8 and R to 5e-6); AnaCal refuses kernels of 3 or
#: more "arcsec", so the pixel is called 0.2 arcsec to allow kernels of 3 pixels and more.
PIXEL_SCALE = 0.2
STEP = 0.01
FLAG_NO_CENTROID = 1
FLAG_NONFINITE = 2


def centred_psf(path: str, npix: int) -> np.ndarray:
    """The PSF image of ``path`` as AnaCal wants it: ``npix`` square, centred on pixel
    ``(npix // 2, npix // 2)`` (0-based), unit sum."""
    psf = np.asarray(fitsio.read(path), dtype=np.float64)
    ny, nx = psf.shape
    if ny != nx or ny > npix:
        raise SystemExit(
            f"{path}: the PSF image must be square and at most {npix} pixels, got {nx}x{ny}"
        )
    if ny < npix:  # pad symmetrically (same parity assumed, as megalut requires)
        if (npix - ny) % 2:
            raise SystemExit(
                f"{path}: PSF stamp of {ny} px and galaxy stamps of {npix} px differ in parity"
            )
        p = (npix - ny) // 2
        psf = np.pad(psf, p)
    shift = npix // 2 - (npix - 1) / 2.0  # 0.5 for even stamps, 0 for odd
    if shift:
        k = 2.0 * np.pi * np.fft.fftfreq(npix)
        kr = 2.0 * np.pi * np.fft.rfftfreq(npix)
        phase = np.exp(-1j * (k[:, None] * shift + kr[None, :] * shift))
        psf = np.fft.irfft2(np.fft.rfft2(psf) * phase, s=psf.shape)
    return psf / psf.sum()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("stamps")
    ap.add_argument(
        "catalog", help="catalog of `megalut measure STAMPS ...` (adamom_x, adamom_y, skymad)"
    )
    ap.add_argument("--psf", required=True)
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument(
        "--sigma-shapelets",
        type=float,
        default=4.0,
        help="FPFS shapelet kernel sigma in pixels (default 4.0 = 2 x the PSF sigma of 2 px)",
    )
    ap.add_argument(
        "--c0-factor",
        type=float,
        default=4.0,
        help="c0 = factor x std(m00) of AnaCal's prepare_covariance (default 4)",
    )
    ap.add_argument(
        "--noise-sigma",
        type=float,
        default=None,
        help="pixel noise sigma for the covariance and c0 (default: the median skymad)",
    )
    ap.add_argument(
        "--centre",
        choices=("adamom", "stamp", "truth"),
        default="adamom",
        help="where to measure: the adaptive-moment centroid, the stamp centre, or (diagnostic "
        "only, simulations) the true centre x + tru_dx, y + tru_dy",
    )
    ap.add_argument(
        "--no-noise-array", action="store_true", help="no noise image (no noise-bias correction)"
    )
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--chunk", type=int, default=256, help="stamps per AnaCal call")
    ap.add_argument("--pad", type=int, default=12, help="zero border around each stamp, pixels")
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)

    t_wall, t_cpu = time.time(), time.process_time()
    cat = read_catalog(a.catalog)
    meta = dict(cat.meta)
    history = meta.pop("HISTORY", [])
    info = image_info(a.stamps)
    size = stamp_size_of(info, None)
    n = len(cat)
    origins = catalog_origins(np.asarray(cat["x"]), np.asarray(cat["y"]), size, 1)
    psf = centred_psf(a.psf, size)

    ax = np.asarray(cat["adamom_x"], dtype=float) - origins[:, 0]  # 0-based in the stamp
    ay = np.asarray(cat["adamom_y"], dtype=float) - origins[:, 1]
    ok = np.isfinite(ax) & np.isfinite(ay) & (np.asarray(cat["flags"]) == 0)
    centre = (size - 1) / 2.0
    if a.centre == "stamp":
        ok[:] = False
    elif a.centre == "truth":
        ax = (
            np.asarray(cat["x"], dtype=float)
            + np.asarray(cat["tru_dx"], dtype=float)
            - origins[:, 0]
        )
        ay = (
            np.asarray(cat["y"], dtype=float)
            + np.asarray(cat["tru_dy"], dtype=float)
            - origins[:, 1]
        )
        ok = np.isfinite(ax) & np.isfinite(ay)
    px = np.where(ok, ax, centre)
    py = np.where(ok, ay, centre)
    flags = np.where(ok, 0, FLAG_NO_CENTROID).astype(np.int32)
    skymad = (
        np.asarray(cat["skymad"], dtype=float) if "skymad" in cat.colnames else np.full(n, np.nan)
    )
    sigma = a.noise_sigma if a.noise_sigma is not None else float(np.nanmedian(skymad))
    noise_sig = np.where(np.isfinite(skymad) & (skymad > 0), skymad, sigma)
    crn = meta.get("CRN") is True
    keys = np.asarray(cat["rea"]) if crn else np.arange(n)

    # AnaCal set-up, once: the covariance of the modes (galaxy + rotated noise image), c0.
    sig = a.sigma_shapelets * PIXEL_SCALE
    cfg = anacal.fpfs.FpfsConfig(npix=size, sigma_shapelets1=sig)
    task = anacal.fpfs.FpfsTask(
        npix=size,
        pixel_scale=PIXEL_SCALE,
        sigma_shapelets=sig,
        psf_array=psf,
        kmax_thres=cfg.kmax_thres,
    )
    task.prepare_covariance(variance=sigma**2)
    std_m00 = float(task.std_m00)
    cfg.c0 = a.c0_factor * std_m00
    mag_zero = anacal.task.THRESHOLD_REF_MAG_ZERO  # c0 is then used as given (ratio 1)
    print(
        f"anacal {anacal.__version__}: {n} stamps of {size} px, kernel sigma {a.sigma_shapelets} "
        f"px, noise sigma {sigma:.4g}, std(m00) {std_m00:.4g}, c0 = {a.c0_factor} x std(m00) = "
        f"{cfg.c0:.4g}, centre {a.centre} ({int((~ok).sum())} at the stamp centre), "
        f"noise image {not a.no_noise_array}",
        file=sys.stderr,
    )

    out = {k: np.full(n, np.nan) for k in ("e1", "e2", "de1_dg1", "de2_dg2", "m00", "s2n")}
    cell = size + 2 * a.pad
    cpu_anacal = 0.0
    # Stamps in the order of the image rows they sit in (each band of rows read once).
    order = np.lexsort((origins[:, 0], origins[:, 1]))
    for start in range(0, n, a.chunk):
        idx = order[start : start + a.chunk]
        y0 = int(origins[idx, 1].min()) - 1
        y1 = int(origins[idx, 1].max()) - 1 + size
        stamps = cut_stamps(read_rows(info, y0, y1), y0, origins[idx], size)
        c0 = time.process_time()
        m = len(idx)
        gal = np.zeros((cell, cell * m), dtype=np.float32)
        noise = None if a.no_noise_array else np.zeros_like(gal)
        for j, i in enumerate(idx):
            sl = (slice(a.pad, a.pad + size), slice(j * cell + a.pad, j * cell + a.pad + size))
            gal[sl] = stamps[j]
            if noise is not None:
                rng = np.random.default_rng(np.random.SeedSequence([a.seed, int(keys[i])]))
                noise[sl] = rng.normal(0.0, noise_sig[i], (size, size))
        det = np.zeros(m, dtype=[("y", "f8"), ("x", "f8")])
        det["y"] = a.pad + py[idx]
        det["x"] = np.arange(m) * cell + a.pad + px[idx]
        res = anacal.fpfs.process_image(
            fpfs_config=cfg,
            pixel_scale=PIXEL_SCALE,
            noise_variance=sigma**2,
            mag_zero=mag_zero,
            gal_array=gal,
            psf_array=psf,
            noise_array=noise,
            detection=det,
        )
        cpu_anacal += time.process_time() - c0
        for k in out:
            out[k][idx] = res["s2n_fpfs1" if k == "s2n" else f"fpfs1_{k}"]

    bad = (
        ~np.isfinite(out["e1"])
        | ~np.isfinite(out["e2"])
        | ~np.isfinite(out["de1_dg1"])
        | ~np.isfinite(out["de2_dg2"])
    )
    flags |= np.where(bad, FLAG_NONFINITE, 0).astype(np.int32)
    good = ~bad
    r11, r22 = float(np.mean(out["de1_dg1"][good])), float(np.mean(out["de2_dg2"][good]))

    cols = {name: np.asarray(cat[name]) for name in cat.colnames}
    for k, v in out.items():
        cols[f"anacal_{k}"] = v
    cols["anacal_x"] = px + origins[:, 0]
    cols["anacal_y"] = py + origins[:, 1]
    cols["anacal_flags"] = flags
    cols["pre_g1"] = out["e1"] / r11
    cols["pre_g2"] = out["e2"] / r22
    cols["pre_g1_noshear"] = out["e1"]
    cols["pre_g2_noshear"] = out["e2"]
    cols["mcal_r11"] = out["de1_dg1"]
    cols["mcal_r12"] = np.zeros(n)
    cols["mcal_r21"] = np.zeros(n)
    cols["mcal_r22"] = out["de2_dg2"]
    for kind in ("noshear", "1p", "1m", "2p", "2m"):  # no sheared images: one flag for all versions
        cols[f"flags_{kind}"] = (flags & FLAG_NONFINITE).astype(np.int32)
    per_gal = cpu_anacal / max(n, 1)
    cards = {k: v for k, v in meta.items() if k not in ("MCALSTEP", "MCALSEED")}
    cards.update(
        {
            "MCALSTEP": (STEP, "metacal step card for megalut evaluate (AnaCal: analytic R)"),
            "ANVERS": (anacal.__version__, "anacal version"),
            "ANSIGPX": (a.sigma_shapelets, "AnaCal shapelet kernel sigma, pixels"),
            "ANC0": (cfg.c0, "AnaCal c0 (flux units of the stamps)"),
            "ANC0FAC": (a.c0_factor, "c0 / std(m00)"),
            "ANSTDM00": (std_m00, "std(m00) of prepare_covariance"),
            "ANNOISE": (sigma, "noise sigma for the covariance"),
            "ANCENTRE": (a.centre, "where AnaCal measures"),
            "ANNOIMG": (not a.no_noise_array, "noise image for the noise-bias correction"),
            "ANSEED": (a.seed, "seed of the noise images"),
            "ANCPUGAL": (per_gal, "AnaCal CPU seconds per galaxy"),
        }
    )
    if os.path.exists(a.output) and not a.overwrite:
        raise SystemExit(f"{a.output} exists (use --overwrite)")
    write_catalog(
        a.output,
        cols,
        fmt="megalut.predictions",
        overwrite=a.overwrite,
        cards=cards,
        history=history,
    )
    print(
        f"anacal: <R11> = {r11:.4f}, <R22> = {r22:.4f}, {int(bad.sum())} non-finite; "
        f"CPU {cpu_anacal:.2f} s in AnaCal ({1e3 * per_gal:.3f} ms per galaxy), "
        f"{time.process_time() - t_cpu:.2f} s CPU and {time.time() - t_wall:.2f} s wall in all; "
        f"wrote {a.output}",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
