"""Peers on the same paired scenes: m, c, usable objects, shear noise, n_eff and CPU.

Metadetection with adaptive moments (``measure --metadetect``), the same detections with the
networks (``predict``, unweighted and weighted) and AnaCal with its own detection
(``anacal_scenes.py -o``), all three on one paired scene file (docs/metadetect.md, "Peers on
the same scenes"):

    megalut simulate examples/scenes/blends.toml -o truth.fits --scene scenes.fits \\
        scene.n_fields=100 --seed 42 -j 1
    /usr/bin/time megalut measure scenes.fits --metadetect --stamp-size 64 -o det.fits -j 1
    /usr/bin/time megalut predict det.fits --model fiducial-metacal-d4 -o pred.fits
    /usr/bin/time python examples/metadetect/anacal_scenes.py scenes.fits --truth truth.fits \\
        --kernel-psf-ratio 1.2 -o anacal.fits
    python examples/metadetect/peers.py scenes.fits --moments det.fits --networks pred.fits \\
        --anacal anacal.fits --cpu-measure 48.5 --cpu-predict 0.9 --cpu-anacal 7.1

The fields are those of SCENES (IMAGES: field, pair_sign, tru_g1, n_gal); a field without a
usable row in a product counts with zero rows there. The same bootstrap resamples of the
fields (megalut's ``resample_counts``, the +g and -g images of a field together) give every
error of every estimator.

- m, c: moments and networks as ``megalut evaluate`` computes them (``flags == 0``,
  ``inner``, finite estimate; R from each version's catalog means; one estimate per image; a
  fit against the true shears), with megalut's own functions; AnaCal as ``anacal_scenes.py``:
  m = sum_f (E1+ - E1-) / sum_f g_f (R1+ + R1-) - 1, c_i = sum (Ei+ + Ei-) / sum (Ri+ + Ri-),
  E: an image's sum of wsel e, R: of wsel de/dg + dwsel/dg e.
- Usable objects per image: the noshear rows kept (moments, networks); for AnaCal
  N = sum(wsel), each row counting by its selection weight (its rows, wsel > 1e-5, also shown).
- Shear noise, one definition for all three: the +g images alone, per component i, each
  image's calibrated sum E_f = sum_rows w e_i / R_i (R_i the whole set's response: megalut's
  R_ii, AnaCal's sum R / sum wsel) and weight W_f = sum_rows w (w = 1, the networks' weight,
  or wsel); the one-sign mean shear g = sum E_f / sum W_f has the variance over fields
  SE^2 = F / (F - 1) sum_f (E_f - g W_f)^2 / (sum_f W_f)^2 (the ratio estimator's; for rows
  of equal weight, the spread of the fields' mean shears times sqrt(n_f)). sigma_gamma =
  SE sqrt(N), N the usable objects of the +g images, per object and component;
  n_eff = 0.26^2 / (A SE^2) per arcmin^2 (A: the +g images' area), the density of galaxies of
  shape noise 0.26 per component that gives the same error: it does not depend on how the
  usable objects are counted. Given as the mean of the two components' SE^2 (g2, with no
  shear, and g1); its error from the bootstrap, and its ratio to the first estimator's with
  the error of the same resamples (the estimators share their scenes: the ratio is known
  better than either).
- CPU: the seconds given (e.g. user + sys of /usr/bin/time around each command) per detected
  object (noshear rows as written, both signs; AnaCal's rows) and per image (250 px).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import fitsio
import numpy as np

from megalut_cli.measure.metacal_defaults import MDET_COLUMN, MDET_STEP_CARD, TYPES
from megalut_cli.shear.bootstrap import resample_counts
from megalut_cli.shear.metadetect import bias_from_sums, image_sums

SIGMA_REF = 0.26  # shape noise per component for n_eff
NOSHEAR = TYPES.index("noshear")


@dataclass
class Scenes:
    """The fields of a paired scene file: ids, true g1 of the +g image, truth galaxies per
    image (F, 2), the area of one image (arcmin^2)."""

    fields: np.ndarray
    g1: np.ndarray
    n_gal: np.ndarray
    area: float


@dataclass
class Result:
    """One estimator on the scenes: (value, error) of m, c1, c2, R11; usable objects and
    detected rows (F, 2); the +g images' calibrated sums E and weights W (F, 2 components)."""

    name: str
    m: tuple[float, float]
    c1: tuple[float, float]
    c2: tuple[float, float]
    r11: float
    usable: np.ndarray
    detected: np.ndarray
    rows: np.ndarray
    e: np.ndarray
    w: np.ndarray
    cpu: float | None = None


def read_scenes(path: str) -> Scenes:
    """The fields of a paired scene file (every field must have both signs)."""
    with fitsio.FITS(path) as f:
        images = f["IMAGES"].read()
        scale = float(f["SCI"].read_header()["PIXSCALE"])
        side = int(f["SCI"].get_dims()[-1])
    fields = np.unique(images["field"])
    g1, n_gal = np.zeros(len(fields)), np.zeros((len(fields), 2))
    for j, sign in enumerate((1, -1)):
        at = images["pair_sign"] == sign
        k = np.searchsorted(fields, images["field"][at])
        if len(k) != len(fields):
            raise SystemExit(f"{path}: not a paired scene file (sign {sign:+d})")
        n_gal[k, j] = images["n_gal"][at]
        if sign == 1:
            g1[k] = images["tru_g1"][at]
    return Scenes(fields, g1, n_gal, (side * scale / 60.0) ** 2)


def place(sc: Scenes, fields: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Per-field ``values`` (axis 0 over ``fields``) on the scene's fields (zero elsewhere)."""
    out = np.zeros((len(sc.fields), *values.shape[1:]))
    k = np.searchsorted(sc.fields, fields)
    if np.any(sc.fields[np.minimum(k, len(sc.fields) - 1)] != fields):
        raise SystemExit("a catalog holds fields that the scene file does not")
    out[k] = values
    return out


def spread(values: np.ndarray) -> float:
    """The standard deviation of bootstrap values (NaN-free)."""
    return float(np.nanstd(values, ddof=1))


def metadetect(
    sc: Scenes, path: str, weighted: bool, counts: list[np.ndarray], name: str
) -> Result:
    """m, c, counts and the +g images' sums of a metadetection catalog (moments or
    networks), evaluated as ``megalut evaluate`` does."""
    cols = fitsio.read(path)
    step = float(fitsio.read_header(path, 1)[MDET_STEP_CARD])
    have = set(cols.dtype.names)
    est = ("pre_g1", "pre_g2") if {"pre_g1", "pre_g2"} <= have else ("adamom_g1", "adamom_g2")
    columns = {k: cols[k] for k in cols.dtype.names}
    version = np.char.strip(cols[MDET_COLUMN].astype("U"))
    keep = (cols["flags"] == 0) & (cols["inner"] != 0)
    for c in est:
        keep &= np.isfinite(cols[c])
    wcols = (f"{est[0]}_w", f"{est[1]}_w") if weighted else None
    s = image_sums(columns, keep, est, wcols)
    n = image_sums(columns, keep, est, None)  # unweighted: the row counts
    sums, weights = place(sc, s.fields, s.sums), place(sc, s.fields, s.weights)
    true = place(sc, s.fields, s.true)
    true[~np.isfinite(true)] = 0.0
    true[..., 0] = sc.g1[:, None] * np.array([1.0, -1.0])
    value = bias_from_sums(sums, weights, true, step)  # R11, R22, m1, c1, m2, c2
    boot = np.concatenate(
        [
            bias_from_sums(
                np.einsum("fb,fsvc->bfsvc", b, sums),
                np.einsum("fb,fsvc->bfsvc", b, weights),
                true,
                step,
            )
            for b in counts
        ]
    )
    at = version == "noshear"
    detected = np.zeros((len(sc.fields), 2))
    f_index = np.searchsorted(sc.fields, cols["field"][at])
    np.add.at(detected, (f_index, (cols["pair_sign"][at] < 0).astype(int)), 1)
    r = value[:2]
    return Result(
        name,
        (float(value[2]), spread(boot[:, 2])),
        (float(value[3]), spread(boot[:, 3])),
        (float(value[5]), spread(boot[:, 5])),
        float(r[0]),
        place(sc, n.fields, n.weights[:, :, NOSHEAR, 0]),
        detected,
        place(sc, n.fields, n.weights[:, :, NOSHEAR, 0]),
        sums[:, 0, NOSHEAR, :] / r,
        weights[:, 0, NOSHEAR, :],
    )


def anacal_bias(s: dict[str, np.ndarray], g1: np.ndarray) -> np.ndarray:
    """(m1, c1, c2) of AnaCal's per-image sums (``(..., F, 2)``: a leading axis of
    resamples allowed, the multiplicities already applied)."""
    e1, e2, r1, r2 = s["e1"], s["e2"], s["r1"], s["r2"]
    m = (e1[..., 0] - e1[..., 1]).sum(-1) / (g1 * (r1[..., 0] + r1[..., 1])).sum(-1) - 1.0
    c1 = (e1[..., 0] + e1[..., 1]).sum(-1) / (r1[..., 0] + r1[..., 1]).sum(-1)
    c2 = (e2[..., 0] + e2[..., 1]).sum(-1) / (r2[..., 0] + r2[..., 1]).sum(-1)
    return np.stack([m, c1, c2], axis=-1)


def anacal(sc: Scenes, path: str, counts: list[np.ndarray]) -> Result:
    """m, c, counts and the +g images' sums of an ``anacal_scenes.py -o`` catalog."""
    cat = fitsio.read(path)
    f = np.searchsorted(sc.fields, cat["field"])
    j = (cat["pair_sign"] < 0).astype(int)
    w = cat["wsel"]
    per_row = {
        "e1": w * cat["fpfs_e1"],
        "e2": w * cat["fpfs_e2"],
        "r1": w * cat["fpfs_de1_dg1"] + cat["dwsel_dg1"] * cat["fpfs_e1"],
        "r2": w * cat["fpfs_de2_dg2"] + cat["dwsel_dg2"] * cat["fpfs_e2"],
        "w": w,
        "rows": np.ones(len(cat)),
    }
    s = {}
    for k, v in per_row.items():
        s[k] = np.zeros((len(sc.fields), 2))
        np.add.at(s[k], (f, j), v)
    value = anacal_bias(s, sc.g1)
    boot = np.concatenate(
        [
            anacal_bias({k: np.einsum("fb,fs->bfs", b, v) for k, v in s.items()}, sc.g1)
            for b in counts
        ]
    )
    r = np.array([s["r1"].sum(), s["r2"].sum()]) / s["w"].sum()  # response per unit of wsel
    return Result(
        "AnaCal",
        (float(value[0]), spread(boot[:, 0])),
        (float(value[1]), spread(boot[:, 1])),
        (float(value[2]), spread(boot[:, 2])),
        float(r[0]),
        s["w"],
        s["rows"],
        s["rows"],
        np.stack([s["e1"][:, 0], s["e2"][:, 0]], axis=1) / r,
        np.stack([s["w"][:, 0], s["w"][:, 0]], axis=1),
    )


def one_sign_se2(e: np.ndarray, w: np.ndarray, mult: np.ndarray | None = None) -> np.ndarray:
    """SE^2 of the one-sign mean shear sum E / sum W per component (``e, w``: (F, 2)), from
    the fields' residuals; ``mult`` (F, b): bootstrap multiplicities -> (b, 2)."""
    if mult is None:
        mult = np.ones((len(e), 1))
    n = len(e)
    se, sw = np.einsum("fb,fc->bc", mult, e), np.einsum("fb,fc->bc", mult, w)
    g = se / sw
    res2 = (e[None] - g[:, None, :] * w[None]) ** 2  # (b, F, 2)
    return n / (n - 1) * np.einsum("fb,bfc->bc", mult, res2) / sw**2


def noise(sc: Scenes, r: Result, counts: list[np.ndarray]) -> dict:
    """sigma_gamma per object and n_eff (mean of the components' SE^2), with bootstrap
    errors, each component's sigma_gamma, and the bootstrap SE^2 (``boot``)."""
    n_plus = float(r.usable[:, 0].sum())
    area = len(sc.fields) * sc.area
    se2 = one_sign_se2(r.e, r.w)[0]
    boot = np.concatenate([one_sign_se2(r.e, r.w, b) for b in counts]).mean(axis=1)
    sig = np.sqrt(se2.mean() * n_plus)
    neff = SIGMA_REF**2 / (area * se2.mean())
    return {
        "sigma": float(sig),
        "sigma_err": spread(np.sqrt(boot * n_plus)),
        "neff": float(neff),
        "neff_err": spread(SIGMA_REF**2 / (area * boot)),
        "sigma_g1": float(np.sqrt(se2[0] * n_plus)),
        "sigma_g2": float(np.sqrt(se2[1] * n_plus)),
        "se2": float(se2.mean()),
        "boot": boot,
    }


def pm(v: tuple[float, float], digits: int = 3) -> str:
    """``value ± error`` with a true minus sign."""
    return f"{v[0]:+.{digits}f} ± {v[1]:.{digits}f}".replace("-", "−")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenes", help="the paired scene file the catalogs were made from")
    ap.add_argument("--moments", help="measure --metadetect catalog (adaptive moments)")
    ap.add_argument("--networks", help="predict catalog of the same detections")
    ap.add_argument("--anacal", help="anacal_scenes.py -o catalog of the same scenes")
    ap.add_argument("--cpu-measure", type=float, help="CPU seconds of measure")
    ap.add_argument("--cpu-predict", type=float, help="CPU seconds of predict")
    ap.add_argument("--cpu-anacal", type=float, help="CPU seconds of anacal_scenes.py")
    ap.add_argument("--n-boot", type=int, default=500)
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args(argv)
    sc = read_scenes(a.scenes)
    counts = resample_counts(a.seed, len(sc.fields), a.n_boot)
    results: list[Result] = []
    if a.moments:
        results.append(metadetect(sc, a.moments, False, counts, "metadetection, moments"))
        results[-1].cpu = a.cpu_measure
    if a.networks:
        cpu = None if a.cpu_measure is None else a.cpu_measure + (a.cpu_predict or 0.0)
        for weighted in (False, True):
            name = "metadetection, networks " + ("weighted" if weighted else "unweighted")
            results.append(metadetect(sc, a.networks, weighted, counts, name))
            results[-1].cpu = cpu
    if a.anacal:
        results.append(anacal(sc, a.anacal, counts))
        results[-1].cpu = a.cpu_anacal
    if not results:
        ap.error("give at least one of --moments, --networks, --anacal")
    n_img = 2 * len(sc.fields)
    print(
        f"{a.scenes}: {len(sc.fields)} paired fields, {sc.n_gal.mean():.1f} truth galaxies per "
        f"image, {sc.area:.4f} arcmin^2 per image; errors: bootstrap over fields ({a.n_boot})"
    )
    head = (
        "| estimator | m | c1 | c2 | R11 | usable / image | detected / image | "
        "σ_γ (g1; g2) | n_eff(0.26) /arcmin² | n_eff / first | CPU ms / detected; / image |"
    )
    print(head)
    print("|" + "---|" * head.count(" | ") + "---|")
    noises = [noise(sc, r, counts) for r in results]
    for r, nz in zip(results, noises):
        ratio = noises[0]["se2"] / nz["se2"]  # the same resamples: a paired error
        ratio_err = spread(noises[0]["boot"] / nz["boot"])
        cpu = (
            "–"
            if r.cpu is None
            else f"{1e3 * r.cpu / r.detected.sum():.2f}; {1e3 * r.cpu / n_img:.0f}"
        )
        usable = f"{r.usable.sum() / n_img:.2f}"
        if r.name == "AnaCal":
            usable += f" (rows {r.rows.sum() / n_img:.2f})"
        print(
            f"| {r.name} | {pm(r.m)} | {pm(r.c1, 4)} | {pm(r.c2, 4)} | {r.r11:.3f} | {usable} | "
            f"{r.detected.sum() / n_img:.2f} | {nz['sigma']:.3f} ± {nz['sigma_err']:.3f} "
            f"({nz['sigma_g1']:.3f}; {nz['sigma_g2']:.3f}) | {nz['neff']:.0f} ± "
            f"{nz['neff_err']:.0f} | {ratio:.2f} ± {ratio_err:.2f} | {cpu} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
