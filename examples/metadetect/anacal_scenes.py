"""AnaCal with its own detection on paired scenes: m, c, counts, shear noise, CPU (issue 42).

    megalut simulate examples/scenes/metadetect.toml -o truth.fits --scene scenes.fits \\
        --pairs scene.n_fields=200
    python examples/metadetect/anacal_scenes.py scenes.fits --truth truth.fits [-o cat.fits]
        [--sigma-arcsec 0.40 | --kernel-psf-ratio 1.2] [--snr-min 5] [--omega-f 0.417]
        [--omega-v 0.0208] [--c0 2.30] [--image-bound 0] [--seed 1] [--n-boot 500]
        [--fields N] [--no-noise-array]

SCENES is a paired `megalut simulate --scene --pairs` file (docs/scenes.md): image 2k is
field k at +g, image 2k+1 the same galaxies and noise at -g. Every image is one cell for
AnaCal (`anacal` 0.8.3, Li & Mandelbaum; not a megalut dependency): `anacal.task.Task`
detects the peaks of the PSF-deconvolved image re-smoothed by a Gaussian of sigma * sqrt(2)
and measures, at each peak, the FPFS shape of the image re-smoothed by sigma (e1, e2 =
(M_xx - M_yy, 2 M_xy) / (M_0 + c0)) with its analytic shear response; the detection gives
each peak a smooth selection weight wsel (peak above its 80 neighbours within 5 px, peak
flux above snr_min sigma_det, peak above the local background by 5 sigma_det; smooth steps
of widths omega_v, omega_f) with its analytic shear response dwsel/dg. The shear of a set of
rows is AnaCal's estimator g_i = sum(wsel e_i) / sum(wsel de_i/dg_i + dwsel/dg_i e_i).

Settings (the production settings of AnaCal's survey pipeline xlens for LSST-like images,
0.8.3 API, carried over to these images in units of their own noise, anacal.md):
kernel sigma_arcsec = 0.40 arcsec (detection 0.40 sqrt 2), snr_peak_min = 5, no model fit
(num_epochs = 0, force_center), omega_f = 0.417 sigma_det, omega_v = 0.0208 sigma_det
(sigma_det: the noise of the detection image, anacal.detector.coadd_smoothed_variance),
c0 = 2.30 sigma(M_0) (sigma(M_0) = AnaCal's Gaussian flux error / (4 pi sigma_arcsec^2));
noise handling: AnaCal's renoising noise-bias correction with a pure-noise image of the
same variance (the variance doubled inside AnaCal), white, from --seed and the field (the
same for both signs of a pair), or the scene's NOISE cube when there is one; the noise
variance of each image is 1 / median(WGT). The thresholds (sigma_det, sigma(M_0)) are fixed
for the file from the median variance and the first image's PSF. The PSF (odd side,
centred on the central pixel) is padded to 64 px, centred on pixel (32, 32) as AnaCal wants.
One AnaCal cell per image, padded by at least the background kernel's reach.
``--kernel-psf-ratio R`` sets the kernel to R times the PSF's sigma instead (the adaptive
moments' sigma of the first image's PSF; xlens' kernel is 1.18 times its PSF's sigma); a
kernel not above the PSF's sigma is warned about (the deconvolution blows up, anacal.md run
(i)).

Output (stdout): m (g_true = IMAGES.tru_g1 of the + image), c1, c2, from the pairs: m = sum_f
(E1+ - E1-) / sum_f g_f (R1+ + R1-) - 1, c_i = sum (Ei+ + Ei-) / sum (Ri+ + Ri-) (E, R: a
cell's sums of wsel e and of its response), errors from a bootstrap over fields (the same
fields for both signs); counts: truth galaxies, detected rows (wsel > 1e-5, AnaCal's floor),
rows with wsel > 0.5, and N = sum(wsel) (the usable objects: each row counts by its weight);
shear noise per object sigma_gamma = sqrt(N) x the standard error (bootstrap over fields) of
the calibrated mean shear of the + images alone, N = sum(wsel) of those images, per component
(the component with a shear, g1 here, also carries the response's noise x |g|: the other one is
the shear noise per object); the area-normalized shear noise SE x sqrt(A) (A: the + images'
area) and n_eff = 0.26^2 / (A SE^2), the number density of galaxies of shape noise 0.26 per
component that would give the same error (the galaxies here are round, so this is pixel and
blending noise only); CPU (time.process_time) of the AnaCal calls per detected row, per unit of
sum(wsel) and per truth galaxy, and of the whole script. With --truth, each + image's
detections are matched to its truth galaxies (nearest within --match-radius px): the weight of
matched and unmatched rows and the truth galaxies with no matched row of wsel > 0.5. -o writes
the catalog (one row per detection, FITS 1-based x, y in the image).
"""

from __future__ import annotations

import os

for _v in (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import fitsio  # noqa: E402
import numpy as np  # noqa: E402

try:  # an experiment-only import: not a megalut dependency
    import anacal
except ImportError:
    raise SystemExit("anacal_scenes.py needs anacal: pip install anacal==0.8.3") from None

PSF_NPIX = 64  # AnaCal's stamp size (even); the PSF is centred on pixel PSF_NPIX // 2
SIGMA_REF = 0.26  # shape noise per component for n_eff
KEEP = (
    "wsel",
    "dwsel_dg1",
    "dwsel_dg2",
    "fpfs_e1",
    "fpfs_e2",
    "fpfs_de1_dg1",
    "fpfs_de1_dg2",
    "fpfs_de2_dg1",
    "fpfs_de2_dg2",
    "fpfs_m0",
    "fpfs_m2",
    "flux",
    "flux_gauss0",
    "flux_gauss0_err",
    "bkg",
)


def padded_psf(psf: np.ndarray, npix: int = PSF_NPIX) -> np.ndarray:
    """An odd PSF image centred on its central pixel, as AnaCal wants it: ``npix`` square
    (even), centred on pixel ``(npix // 2, npix // 2)``, unit sum."""
    p = np.asarray(psf, dtype=np.float64)
    side = p.shape[0]
    if p.shape != (side, side) or side % 2 == 0:
        raise SystemExit(f"the PSF must be square with an odd side, got {p.shape}")
    if side >= npix:  # keep the central npix - 1 pixels
        lo = (side - (npix - 1)) // 2
        p, side = p[lo : lo + npix - 1, lo : lo + npix - 1], npix - 1
    out = np.zeros((npix, npix))
    lo = npix // 2 - side // 2
    out[lo : lo + side, lo : lo + side] = p
    return out / out.sum()


def psf_sigma(psf: np.ndarray, iterations: int = 50) -> float:
    """The adaptive moments' sigma (pixels) of a PSF image: the Gaussian weight matched to
    the profile, sigma^2 = (Mxx + Myy) / 2 of the weighted moments times 2, iterated."""
    p = np.asarray(psf, dtype=np.float64)
    yy, xx = np.indices(p.shape, dtype=np.float64)
    f = p.sum()
    xc, yc = (p * xx).sum() / f, (p * yy).sum() / f
    s2 = 4.0
    for _ in range(iterations):
        w = p * np.exp(-((xx - xc) ** 2 + (yy - yc) ** 2) / (2.0 * s2))
        xc, yc = (w * xx).sum() / w.sum(), (w * yy).sum() / w.sum()
        m = (w * ((xx - xc) ** 2 + (yy - yc) ** 2)).sum() / w.sum() / 2.0
        s2_new = 2.0 * m
        if abs(s2_new - s2) < 1e-10 * s2:
            break
        s2 = s2_new
    return float(np.sqrt(s2))


def noise_levels(psf: np.ndarray, variance: float, sigma: float, scale: float, renoise: bool):
    """(sigma_det, sigma_M0): the noise of AnaCal's detection image and of its FPFS M_0, for
    pixel noise ``variance`` (doubled by the renoising, as AnaCal does)."""
    var = variance * (2.0 if renoise else 1.0)
    sig_det = sigma * np.sqrt(2.0)
    w = anacal.detector.band_weights(scale, sig_det, psf, [var])
    std_det = float(np.sqrt(anacal.detector.coadd_smoothed_variance(scale, sig_det, psf, [var], w)))
    flux_err = float(np.sqrt(var * anacal.task.gaussian_flux_variance(psf, 0.0, sigma, scale)))
    return std_det, flux_err / (4.0 * np.pi * sigma**2)


def one_cell(n: int, scale: float) -> list:
    """One AnaCal cell holding the whole ``n`` x ``n`` image, padded by at least the reach of
    the detector's background kernel (3 arcsec; AnaCal demands cell_overlap >= 2 reach)."""
    overlap = 2 * (int(3.0 / scale) + 2)
    side = n + overlap + (n + overlap) % 2
    cells = anacal.geometry.get_cell_list(
        img_nx=n, img_ny=n, cell_nx=side, cell_ny=side, cell_overlap=overlap, scale=scale
    )
    if len(cells) != 1:
        raise SystemExit(f"expected one AnaCal cell for a {n}-px image, got {len(cells)}")
    return cells


def pair_index(images: np.ndarray, fields: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(field ids, (n_fields, 2) image indices of the + and - image of each field)."""
    sign = np.asarray(images["pair_sign"])
    field = np.asarray(images["field"])
    ids = np.unique(field)
    if fields is not None:
        ids = ids[:fields]
    idx = np.full((len(ids), 2), -1)
    for k, f in enumerate(ids):
        for j, s in enumerate((1, -1)):
            hit = np.flatnonzero((field == f) & (sign == s))
            if len(hit) != 1:
                raise SystemExit(
                    f"field {f}: {len(hit)} images of sign {s:+d} (need a paired file)"
                )
            idx[k, j] = hit[0]
    return ids, idx


def bias(s: dict[str, np.ndarray], g1: np.ndarray, g2: np.ndarray) -> dict[str, float]:
    """m1 (m2 where g2 is not zero), c1, c2 from per-field sums (axis 1: + and - image)."""
    out = {}
    for i, g in ((1, g1), (2, g2)):
        e, r = s[f"e{i}"], s[f"r{i}"]
        rsum = r[:, 0] + r[:, 1]
        out[f"c{i}"] = float((e[:, 0] + e[:, 1]).sum() / rsum.sum())
        if np.any(g != 0):
            out[f"m{i}"] = float((e[:, 0] - e[:, 1]).sum() / (g * rsum).sum() - 1.0)
    return out


def one_sign(s: dict[str, np.ndarray]) -> np.ndarray:
    """Calibrated mean shear (g1, g2) of the + images."""
    return np.array(
        [s["e1"][:, 0].sum() / s["r1"][:, 0].sum(), s["e2"][:, 0].sum() / s["r2"][:, 0].sum()]
    )


def match(
    x: np.ndarray, y: np.ndarray, w: np.ndarray, tx: np.ndarray, ty: np.ndarray, radius: float
) -> tuple[float, float, int, int, np.ndarray]:
    """Detections (x, y, weights w) against truth (tx, ty): (weight of matched rows, weight
    of unmatched rows, truth galaxies with no matched row of w > 0.5, with two or more, the
    offsets of the matched rows)."""
    if len(tx) == 0 or len(x) == 0:
        return 0.0, float(w.sum()), len(tx), 0, np.zeros((0, 2))
    d2 = (x[:, None] - tx[None, :]) ** 2 + (y[:, None] - ty[None, :]) ** 2
    near = np.argmin(d2, axis=1)
    ok = d2[np.arange(len(x)), near] <= radius**2
    strong = ok & (w > 0.5)
    count = np.bincount(near[strong], minlength=len(tx))
    off = np.stack([x[ok] - tx[near[ok]], y[ok] - ty[near[ok]]], axis=1)
    return (
        float(w[ok].sum()),
        float(w[~ok].sum()),
        int((count == 0).sum()),
        int((count > 1).sum()),
        off,
    )


def main(argv: list[str] | None = None) -> int:
    t_cpu0, t_wall0 = time.process_time(), time.time()
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenes", help="paired scene file of `megalut simulate --scene --pairs`")
    ap.add_argument("--truth", help="its truth table (-o of simulate): match the detections")
    ap.add_argument("-o", "--output", help="write the detections here (FITS table)")
    ap.add_argument("--sigma-arcsec", type=float, default=0.40, help="kernel sigma (arcsec)")
    ap.add_argument(
        "--kernel-psf-ratio",
        type=float,
        default=None,
        help="kernel sigma = this times the PSF's sigma (instead of --sigma-arcsec)",
    )
    ap.add_argument("--snr-min", type=float, default=5.0, help="peak threshold, sigma_det")
    ap.add_argument("--omega-f", type=float, default=0.417, help="flux step width, sigma_det")
    ap.add_argument("--omega-v", type=float, default=0.0208, help="peak step width, sigma_det")
    ap.add_argument("--c0", type=float, default=2.30, help="FPFS c0 in units of sigma(M_0)")
    ap.add_argument("--image-bound", type=int, default=0, help="no peaks this close to edges (px)")
    ap.add_argument("--no-noise-array", action="store_true", help="no noise-bias correction")
    ap.add_argument("--seed", type=int, default=1, help="seed of the renoising images")
    ap.add_argument("--n-boot", type=int, default=500)
    ap.add_argument("--fields", type=int, default=None, help="use the first N fields only")
    ap.add_argument("--match-radius", type=float, default=2.0, help="truth matching (px)")
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    if a.output and os.path.exists(a.output) and not a.overwrite:
        raise SystemExit(f"{a.output} exists (use --overwrite)")

    fits = fitsio.FITS(a.scenes)
    hdr = fits["SCI"].read_header()
    images = fits["IMAGES"].read()
    scale = float(hdr["PIXSCALE"])
    n = int(fits["SCI"].get_dims()[-1])
    has_noise_cube = "NOISE" in fits
    ids, idx = pair_index(images, a.fields)
    g1 = np.asarray(images["tru_g1"], dtype=float)[idx[:, 0]]
    g2 = np.asarray(images["tru_g2"], dtype=float)[idx[:, 0]]
    renoise = not a.no_noise_array

    def read(name: str, i: int) -> np.ndarray:
        return fits[name][i : i + 1, :, :][0]

    variances = np.array([1.0 / np.median(read("WGT", int(i))) for i in idx.ravel()])
    variance_ref = float(np.median(variances))
    psf_ref = padded_psf(read("PSF", int(idx[0, 0])))
    sigma_psf = psf_sigma(psf_ref) * scale  # arcsec
    if a.kernel_psf_ratio is not None:
        a.sigma_arcsec = round(a.kernel_psf_ratio * sigma_psf, 4)
    if a.sigma_arcsec <= 1.01 * sigma_psf:
        print(
            f'warning: kernel {a.sigma_arcsec}" is {a.sigma_arcsec / sigma_psf:.2f} times the '
            f"PSF's sigma {sigma_psf:.3f}\": the deconvolution blows up",
            file=sys.stderr,
        )
    std_det, std_m0 = noise_levels(psf_ref, variance_ref, a.sigma_arcsec, scale, renoise)
    omega_f, omega_v, c0 = a.omega_f * std_det, a.omega_v * std_det, a.c0 * std_m0
    task = anacal.task.Task(
        scale=scale,
        sigma_arcsec=a.sigma_arcsec,
        snr_peak_min=a.snr_min,
        omega_f=omega_f,
        omega_v=omega_v,
        stamp_size=PSF_NPIX,
        image_bound=a.image_bound,
        num_epochs=0,
        force_size=False,
        force_center=True,
        fpfs_c0=c0,
        mag_zero=anacal.task.THRESHOLD_REF_MAG_ZERO,  # thresholds used as given
    )
    cells = one_cell(n, scale)
    print(
        f'anacal {anacal.__version__}: {len(ids)} paired fields of {n} px at {scale}"/px; '
        f'kernel {a.sigma_arcsec}" (detection {a.sigma_arcsec * np.sqrt(2):.3f}"; PSF sigma '
        f'{sigma_psf:.4f}"), '
        f"snr_min {a.snr_min}, noise variance {variance_ref:.4g} (median over images), "
        f"sigma_det {std_det:.4g}, omega_f {omega_f:.4g}, omega_v {omega_v:.4g}, "
        f"sigma(M0) {std_m0:.4g}, c0 {c0:.4g}, renoising "
        + ("off" if not renoise else ("NOISE cube" if has_noise_cube else f"white, seed {a.seed}"))
        + f", image_bound {a.image_bound}",
        file=sys.stderr,
    )

    truth = None
    if a.truth:
        t = fitsio.read(a.truth, columns=["image", "x", "y"])
        truth = {int(i): (t["x"][t["image"] == i], t["y"][t["image"] == i]) for i in idx[:, 0]}
    names = ("e1", "r1", "e2", "r2", "rows", "rows05", "wsum")
    sums = {k: np.zeros((len(ids), 2)) for k in names}
    cpu = 0.0
    tables = []
    m_stats = np.zeros(4)  # matched weight, unmatched weight, missed galaxies, multiply hit
    offsets = []
    for k, field in enumerate(ids):
        noise = None
        if renoise:
            if has_noise_cube:
                noise = np.ascontiguousarray(read("NOISE", int(idx[k, 0])), dtype=np.float32)
            else:
                rng = np.random.default_rng(np.random.SeedSequence([a.seed, int(field)]))
                sd = float(np.sqrt(variances[2 * k]))
                noise = rng.normal(0.0, sd, (n, n)).astype(np.float32)
        for j in range(2):
            i = int(idx[k, j])
            img = np.ascontiguousarray(read("SCI", i), dtype=np.float32)
            psf = padded_psf(read("PSF", i))
            c = time.process_time()
            cat = task.process_image(
                img, psf, variance=float(variances[2 * k + j]), cell_list=cells, noise_array=noise
            )
            cpu += time.process_time() - c
            w = cat["wsel"]
            sums["e1"][k, j] = np.sum(w * cat["fpfs_e1"])
            sums["e2"][k, j] = np.sum(w * cat["fpfs_e2"])
            sums["r1"][k, j] = np.sum(w * cat["fpfs_de1_dg1"] + cat["dwsel_dg1"] * cat["fpfs_e1"])
            sums["r2"][k, j] = np.sum(w * cat["fpfs_de2_dg2"] + cat["dwsel_dg2"] * cat["fpfs_e2"])
            sums["rows"][k, j] = len(cat)
            sums["rows05"][k, j] = np.sum(w > 0.5)
            sums["wsum"][k, j] = np.sum(w)
            x = cat["x1"] / scale + 1.0  # FITS 1-based pixel of the image
            y = cat["x2"] / scale + 1.0
            if truth is not None and j == 0:
                tx, ty = truth[i]
                res = match(x, y, w, tx, ty, a.match_radius)
                m_stats += res[:4]
                offsets.append(res[4])
            if a.output:
                rows = np.zeros(
                    len(cat),
                    dtype=[
                        ("image", "i4"),
                        ("field", "i4"),
                        ("pair_sign", "i2"),
                        ("x", "f8"),
                        ("y", "f8"),
                    ]
                    + [(c_, "f8") for c_ in KEEP],
                )
                rows["image"], rows["field"] = i, field
                rows["pair_sign"] = images["pair_sign"][i]
                rows["x"], rows["y"] = x, y
                for c_ in KEEP:
                    rows[c_] = cat[c_]
                tables.append(rows)

    est = bias(sums, g1, g2)
    sg = one_sign(sums)
    rng = np.random.default_rng(a.seed)
    boot, boot_sg = [], []
    for _ in range(a.n_boot):
        pick = rng.integers(0, len(ids), len(ids))
        s = {key: v[pick] for key, v in sums.items()}
        boot.append([bias(s, g1[pick], g2[pick])[key] for key in est])
        boot_sg.append(one_sign(s))
    err = dict(zip(est, np.std(boot, axis=0)))
    se = np.std(boot_sg, axis=0)
    tot = {key: v.sum(axis=0) for key, v in sums.items()}  # (+, -)
    n_true = int(np.sum(images["n_gal"][idx[:, 0]]))
    area = len(ids) * (n * scale / 60.0) ** 2  # arcmin^2 of the + images
    n_sel = float(tot["wsum"][0])
    sigma_gamma = se * np.sqrt(n_sel)
    n_eff = SIGMA_REF**2 / (area * se**2)
    rows_all = float(tot["rows"].sum())
    r_mean = (tot["r1"].sum() / tot["wsum"].sum(), tot["r2"].sum() / tot["wsum"].sum())

    for key in est:
        print(f"{key} = {est[key]:+.3e} +- {err[key]:.1e}")
    print(
        f"g_true1 {g1.mean():+.4f}; fields {len(ids)}; truth galaxies {n_true} per sign; "
        f"rows (wsel > 1e-5) {int(tot['rows'][0])} (+), {int(tot['rows'][1])} (-); "
        f"wsel > 0.5: {int(tot['rows05'][0])} (+); N = sum(wsel) {n_sel:.1f} (+), "
        f"{tot['wsum'][1]:.1f} (-); <R11> = sum R1 / sum wsel {r_mean[0]:.4f}, "
        f"<R22> {r_mean[1]:.4f}"
    )
    print(
        f"one sign (+): g = ({sg[0]:+.5f}, {sg[1]:+.5f}) +- ({se[0]:.1e}, {se[1]:.1e}); "
        f"sigma_gamma = sqrt(N) SE = ({sigma_gamma[0]:.4f}, {sigma_gamma[1]:.4f}), "
        f"per truth galaxy sqrt(N_true) SE = ({se[0] * np.sqrt(n_true):.4f}, "
        f"{se[1] * np.sqrt(n_true):.4f}); SE sqrt(A) = ({se[0] * np.sqrt(area):.4f}, "
        f"{se[1] * np.sqrt(area):.4f}) arcmin over A = {area:.1f} arcmin^2; "
        f"n_eff(0.26) = ({n_eff[0]:.0f}, {n_eff[1]:.0f}) per arcmin^2"
    )
    if truth is not None:
        off = np.concatenate(offsets) if offsets else np.zeros((0, 2))
        print(
            f"truth match (+ images, {a.match_radius} px): sum wsel matched {m_stats[0]:.1f}, "
            f"unmatched {m_stats[1]:.1f}; truth galaxies with no matched row of wsel > 0.5: "
            f"{int(m_stats[2])} of {n_true}, with two or more: {int(m_stats[3])}; "
            f"median offset of matched rows ({np.median(off[:, 0]) if len(off) else np.nan:+.3f}, "
            f"{np.median(off[:, 1]) if len(off) else np.nan:+.3f}) px"
        )
    cpu_all = time.process_time() - t_cpu0
    print(
        f"CPU: AnaCal {cpu:.2f} s for {len(ids) * 2} images: {1e3 * cpu / rows_all:.3f} ms per "
        f"detected row, {1e3 * cpu / tot['wsum'].sum():.3f} ms per unit of sum(wsel), "
        f"{1e3 * cpu / (2 * n_true):.3f} ms per truth galaxy, {1e3 * cpu / (2 * len(ids)):.1f} "
        f"ms per image; whole script {cpu_all:.2f} s CPU, {time.time() - t_wall0:.2f} s wall"
    )
    if a.output:
        out = np.concatenate(tables) if tables else np.zeros(0)
        cards = [
            {"name": "ANVERS", "value": anacal.__version__, "comment": "anacal version"},
            {"name": "ANSIGMA", "value": a.sigma_arcsec, "comment": "kernel sigma, arcsec"},
            {"name": "ANSNR", "value": a.snr_min, "comment": "snr_peak_min"},
            {"name": "ANOMF", "value": omega_f, "comment": "omega_f (image units)"},
            {"name": "ANOMV", "value": omega_v, "comment": "omega_v (image units)"},
            {"name": "ANC0", "value": c0, "comment": "fpfs_c0 (M_0 units)"},
            {"name": "ANSTDDET", "value": std_det, "comment": "sigma_det"},
            {"name": "ANRENOIS", "value": renoise, "comment": "renoising noise-bias correction"},
            {"name": "ANSEED", "value": a.seed, "comment": "seed of the renoising images"},
        ]
        fitsio.write(a.output, out, header=cards, clobber=True)
        print(f"wrote {a.output} ({len(out)} rows)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
