"""Where the error of m comes from on paired metadetection scenes: the response's share,
how few images carry it, and the rows of one sheared version without a counterpart in its
opposite.

docs/metadetect.md ("Duplicates: the same light measured twice") holds the runs.

    python examples/metadetect/error_anatomy.py det.fits [det2.fits ...]

Printed, with the selection of ``paired_bias.py`` (``flags == 0``, ``inner``, half a stamp
from the edges): sigma_m from a bootstrap over fields, and again with R held at its value
on all fields (the numerator's share alone); the scatter of each image's response sum
(sum of g1 over 1p minus over 1m, over 2 step, minus R times the count) and the share of
its variance in the 1 % and 5 % of images where it is largest; the rows of 1p, 1m, 2p, 2m
with no row of the opposite version within 2 px (an object detected, kept or split in one
and not the other).
"""

from __future__ import annotations

import argparse

import fitsio
import numpy as np
from paired_bias import bootstrap, estimate, field_sums, selection
from scipy.spatial import cKDTree

OPPOSITE = {"1p": "1m", "1m": "1p", "2p": "2m", "2m": "2p"}


def unpaired(rows: np.ndarray, kinds: np.ndarray, radius: float = 2.0) -> tuple[int, int]:
    """Rows of the sheared versions with no row of the opposite version of the same image
    within ``radius`` px (unsheared positions), and the rows looked at."""
    lone = total = 0
    for kind, other in OPPOSITE.items():
        for image in np.unique(rows["image"]):
            here = rows[(rows["image"] == image) & (kinds == kind)]
            there = rows[(rows["image"] == image) & (kinds == other)]
            total += len(here)
            if not len(here):
                continue
            if not len(there):
                lone += len(here)
                continue
            dist, _ = cKDTree(np.c_[there["x"], there["y"]]).query(np.c_[here["x"], here["y"]])
            lone += int(np.sum(dist > radius))
    return lone, total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("catalog", nargs="+", help="metadetect catalog(s) of paired scenes")
    parser.add_argument("--g-true", type=float, default=0.02)
    parser.add_argument("--n-boot", type=int, default=500)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    parts, deviations, lone, total = [], [], 0, 0
    for path in args.catalog:
        rows = fitsio.read(path)
        header = fitsio.read_header(path, 1)
        step, cell_size = float(header["MDETSTEP"]), int(header["CELLSZ"])
        keep = selection(rows, step, cell_size, int(header["STAMPSZ"]) / 2)
        parts.append(field_sums(rows, keep))
        kept = rows[keep]
        kinds = np.char.strip(kept["mdet_step"].astype(str))
        n_lone, n_rows = unpaired(kept, kinds)
        lone, total = lone + n_lone, total + n_rows
        deviations.append((kept, kinds, step))
    sums = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    m, _, _, r11, _ = estimate(sums, step, args.g_true)
    full = bootstrap(sums, step, args.g_true, args.n_boot, args.seed)[0]
    rng = np.random.default_rng(args.seed)
    n_fields = len(sums["n_noshear"])
    held = []
    for _ in range(args.n_boot):
        pick = rng.integers(0, n_fields, n_fields)
        t = {k: v[pick].sum(axis=0) for k, v in sums.items()}
        g1 = t["g1_noshear"] / t["n_noshear"] / r11
        held.append((g1[0] - g1[1]) / (2 * args.g_true) - 1.0)
    print(f"fields {n_fields}: m = {m:+.2e}, sigma_m {full:.2e}; with R held {np.std(held):.2e}")
    dev = []
    for kept, kinds, step in deviations:
        for image in np.unique(kept["image"]):
            p = kept[(kept["image"] == image) & (kinds == "1p")]
            q = kept[(kept["image"] == image) & (kinds == "1m")]
            dev.append((p["adamom_g1"].sum() - q["adamom_g1"].sum()) / (2 * step) - r11 * len(q))
    dev = np.sort(np.abs(np.asarray(dev)))[::-1]
    share = np.cumsum(dev**2) / np.sum(dev**2)
    top1, top5 = share[max(len(dev) // 100, 1) - 1], share[max(len(dev) // 20, 1) - 1]
    print(
        f"images {len(dev)}: response-sum deviation rms {np.sqrt(np.mean(dev**2)):.2f}; "
        f"share of its variance in the top 1 % of images {top1:.0%}, top 5 % {top5:.0%}"
    )
    print(f"sheared-version rows without their opposite within 2 px: {lone} of {total}")


if __name__ == "__main__":
    main()
