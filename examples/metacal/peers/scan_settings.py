"""How AnaCal's two settings change its noise (not its bias) on part of set A.

    python examples/metacal/peers/scan_settings.py WORKDIR [--rea 1000]

Runs anacal_shear.py on the rows of WORKDIR/A-meas.fits with rea < --rea (4 shears x 500
galaxy pairs by default) for shapelet kernels sigma_h = 2.5, 3, 4, 5 px and c0 = 2, 4, 8 x
std(m00), and prints the mean response <R>, the shear error per galaxy
sigma_g = std(e - <R> g) / <R> and the relative scatter of the per-galaxy response
std(R) / <R> (which, in a common-random-number set, does not average out over the shears).
The settings were chosen on these numbers only (no bias is computed here): see README.md.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import anacal_shear  # noqa: E402

from megalut_cli.catalog import read_catalog, write_catalog  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("workdir")
    ap.add_argument("--rea", type=int, default=1000)
    a = ap.parse_args(argv)
    W = a.workdir
    cat = read_catalog(os.path.join(W, "A-meas.fits"))
    meta = dict(cat.meta)
    history = meta.pop("HISTORY", [])
    sub = cat[np.asarray(cat["rea"]) < a.rea]
    sub_path = os.path.join(W, "scan-meas.fits")
    out_path = os.path.join(W, "scan-anacal.fits")
    write_catalog(
        sub_path,
        {n: np.asarray(sub[n]) for n in sub.colnames},
        fmt=str(meta.get("MLFORMAT")),
        overwrite=True,
        cards=meta,
        history=history,
    )
    print(f"{len(sub)} stamps (rea < {a.rea} of {os.path.join(W, 'A-meas.fits')})\n")
    print("| sigma_h (px) | c0 / std(m00) | <R> | sigma_g per galaxy | std(R) / <R> |")
    print("|---|---|---|---|---|")
    for sig in (2.5, 3.0, 4.0, 5.0):
        for fac in (2.0, 4.0, 8.0):
            with contextlib.redirect_stderr(io.StringIO()):
                anacal_shear.main(
                    [
                        os.path.join(W, "A-stamps.fits"),
                        sub_path,
                        "--psf",
                        os.path.join(W, "psf.fits"),
                        "-o",
                        out_path,
                        "--overwrite",
                        "--sigma-shapelets",
                        str(sig),
                        "--c0-factor",
                        str(fac),
                        "--seed",
                        "5",
                    ]
                )
            c = read_catalog(out_path)
            vals = []
            for i in (1, 2):
                e = np.asarray(c[f"anacal_e{i}"])
                r = np.asarray(c[f"anacal_de{i}_dg{i}"])
                g = np.asarray(c[f"tru_g{i}"])
                R = r.mean()
                vals.append((R, np.std(e - R * g) / R, r.std() / R))
            R, sg, sr = np.mean(vals, axis=0)
            print(f"| {sig:.1f} | {fac:.0f} | {R:.4f} | {sg:.4f} | {sr:.3f} |")
    os.remove(sub_path)
    os.remove(out_path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
