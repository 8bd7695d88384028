"""What carries the error of a paired metadetection test (examples/metadetect/README.md).

    python examples/metadetect/diagnose.py det.fits truth.fits [--max-size-ratio 3]

Diagnostics only: rows are matched to each other and to the truth by position, which the
estimate (paired_bias.py) never does. Rows are kept by paired_bias.py's selection (the same
options). Positions are compared with each version's shear about the cell's centre undone, and
between the +g and -g images of a lensed scene (truth card ``SHEARPOS``) with the image's
own shear undone too (the source positions).

1. Rows that enter or leave the selection between 1p and 1m (R11) and between the +g and
   -g images (noshear): how many, why (the other version's row at that place is flagged,
   fails a cut, or was not detected), their edge distance, and the error they put on R11
   (their sums scattered over a bootstrap of the fields, against the rows kept in both).
2. Per galaxy, kept in all ten rows of its field (five versions, two signs): the response
   R11 = (g1_1p - g1_1m) / (2 step) (mean of the two signs; the rms of their difference),
   the pair's response (g1_noshear(+) - g1_noshear(-)) / (2 g_true), the scatter of R11 in
   bins of the distance r from the cell's centre, and sigma_m per galaxy: the rms of
   R_pair - R11 <R_pair> / <R11> over <R11>.
"""

from __future__ import annotations

import argparse

import fitsio
import numpy as np
from paired_bias import TYPES, selection, unsheared, version_positions
from scipy.spatial import cKDTree

from megalut_cli.sim.scene import lensed_positions


def source_positions(
    x: np.ndarray, y: np.ndarray, g1: np.ndarray, g2: np.ndarray, size: int
) -> tuple[np.ndarray, np.ndarray]:
    """Positions with each row's lensed scene image's shear (g1, g2) about the cell's centre
    undone: the scene's lensing by (-g1, -g2)."""
    sx, sy = x.astype(float), y.astype(float)
    for s1, s2 in set(zip(g1.tolist(), g2.tolist())):
        at = (g1 == s1) & (g2 == s2)
        sx[at], sy[at] = lensed_positions(x[at], y[at], -s1, -s2, size)
    return sx, sy


def load(path: str, args: argparse.Namespace, lensed: bool) -> dict:
    rows = fitsio.read(path)
    header = fitsio.read_header(path, 1)
    step, size = float(header["MDETSTEP"]), int(header["CELLSZ"])
    min_edge = int(header["STAMPSZ"]) / 2 if args.min_edge is None else args.min_edge
    keep = selection(
        rows, step, size, min_edge, args.max_g, -np.inf, args.max_size_ratio, args.edge_frame
    )
    x, y = unsheared(rows, step, size)
    kind = np.char.strip(rows["mdet_step"].astype(str))
    edge = np.minimum.reduce([x - 0.5, y - 0.5, size + 0.5 - x, size + 0.5 - y])
    # each cut alone, for the reasons of a change (the edge in the frame of the selection)
    ex, ey = (x, y) if args.edge_frame == "unsheared" else version_positions(rows, step, size)
    cuts = {
        "edge": np.minimum.reduce([ex - 0.5, ey - 0.5, size + 0.5 - ex, size + 0.5 - ey])
        >= min_edge,
        "size": (rows["adamom_sigma"] / rows["psf_adamom_sigma"]) ** 2 < args.max_size_ratio,
        "|g|": np.hypot(rows["adamom_g1"], rows["adamom_g2"]) < args.max_g,
    }
    sx, sy = source_positions(x, y, rows["tru_g1"], rows["tru_g2"], size) if lensed else (x, y)
    return dict(
        rows=rows,
        keep=keep,
        x=x,
        y=y,
        sx=sx,
        sy=sy,
        kind=kind,
        step=step,
        size=size,
        edge=edge,
        cuts=cuts,
    )


def nearest(d: dict, a: np.ndarray, b: np.ndarray, radius: float) -> np.ndarray:
    """For rows ``a``: the index of the nearest row of ``b`` within ``radius`` (at their
    source positions), else -1."""
    if len(a) == 0 or len(b) == 0:
        return np.full(len(a), -1)
    dist, j = cKDTree(np.c_[d["sx"][b], d["sy"][b]]).query(np.c_[d["sx"][a], d["sy"][a]])
    return np.where(dist < radius, b[np.minimum(j, len(b) - 1)], -1)


def transitions(d: dict, pairs: list[tuple[int, int, str, str]], radius: float, n_boot: int):
    """Rows kept in one version and not at that place in the other, per field."""
    rows, keep, kind = d["rows"], d["keep"], d["kind"]
    fields = np.unique(rows["field"])
    f_of = {f: i for i, f in enumerate(fields)}
    only = {"a": [], "b": []}
    sums = np.zeros((len(fields), 3))  # matched difference, only-a sum, only-b sum
    counts = np.zeros((len(fields), 2))  # kept rows of a, of b
    reasons: dict[str, int] = {}
    by_image = {i: np.flatnonzero(rows["image"] == i) for i in np.unique(rows["image"])}
    for img_a, img_b, va, vb in pairs:
        ia, ib = by_image.get(img_a, np.zeros(0, int)), by_image.get(img_b, np.zeros(0, int))
        a = ia[(kind[ia] == va) & keep[ia]]
        b = ib[(kind[ib] == vb) & keep[ib]]
        fi = f_of[rows["field"][ia[0] if len(ia) else ib[0]]]
        ja, jb = nearest(d, a, b, radius), nearest(d, b, a, radius)
        both = ja >= 0
        sums[fi, 0] += np.sum(rows["adamom_g1"][a[both]] - rows["adamom_g1"][ja[both]])
        sums[fi, 1] += rows["adamom_g1"][a[~both]].sum()
        sums[fi, 2] += rows["adamom_g1"][b[jb < 0]].sum()
        counts[fi] += len(a), len(b)
        for side, lost, other_img, other_kind in (
            ("a", a[~both], ib, vb),
            ("b", b[jb < 0], ia, va),
        ):
            only[side].extend(lost)
            cand = other_img[kind[other_img] == other_kind]
            there = nearest(d, lost, cand, radius)
            for j in there:
                if j < 0:
                    why = "not detected there"
                elif rows["flags"][j] != 0:
                    why = f"flags {rows['flags'][j]} there"
                else:
                    failed = [name for name, ok in d["cuts"].items() if not ok[j]]
                    why = "fails " + (" and ".join(failed) or "inner") + " there"
                reasons[why] = reasons.get(why, 0) + 1
    rng = np.random.default_rng(1)
    boot = []
    for _ in range(n_boot):
        pick = rng.integers(0, len(fields), len(fields))
        parts = sums[pick].sum(axis=0) / counts[pick, 0].sum()
        boot.append([*parts, parts[0] + parts[1] - parts[2]])
    return only, reasons, np.std(boot, axis=0), counts[:, 0].sum()


def describe(d: dict, idx: list, label: str) -> str:
    idx = np.asarray(idx, dtype=int)
    if not len(idx):
        return f"{label}: 0 rows"
    g = np.hypot(d["rows"]["adamom_g1"][idx], d["rows"]["adamom_g2"][idx])
    return (
        f"{label}: {len(idx)} rows, rms g1 {np.sqrt(np.mean(d['rows']['adamom_g1'][idx] ** 2)):.3f}"
        f", |g| max {g.max():.2f}, within 24 px of an edge {np.mean(d['edge'][idx] < 24):.2f}"
    )


def per_galaxy(d: dict, truth: np.ndarray, radius: float, g_true: float) -> None:
    rows, keep, kind = d["rows"], d["keep"], d["kind"]
    plus = truth[truth["pair_sign"] > 0]
    gal = {(int(f), int(g)): k for k, (f, g) in enumerate(zip(plus["field"], plus["galaxy"]))}
    g1 = np.full((len(plus), 2, 5), np.nan)
    for img in np.unique(truth["image"]):
        t = truth[truth["image"] == img]
        sel = np.flatnonzero((rows["image"] == img) & keep)
        if not len(sel):
            continue
        dist, j = cKDTree(np.c_[t["x"], t["y"]]).query(np.c_[d["x"][sel], d["y"][sel]])
        for r, q, ok in zip(sel, j, dist < radius):
            if ok:
                k = gal[(int(t["field"][q]), int(t["galaxy"][q]))]
                g1[k, int(rows["pair_sign"][r] < 0), TYPES.index(kind[r])] = rows["adamom_g1"][r]
    full = np.isfinite(g1).all(axis=(1, 2))
    r11_signs = (g1[full, :, 1] - g1[full, :, 2]) / (2 * d["step"])
    r11 = r11_signs.mean(axis=1)
    pair = (g1[full, 0, 0] - g1[full, 1, 0]) / (2 * g_true)
    c = (d["size"] + 1) / 2.0
    r = np.hypot(plus["x"][full] - c, plus["y"][full] - c)
    per = np.std(pair - r11 * pair.mean() / r11.mean()) / r11.mean()
    print(
        f"galaxies in all ten rows: {full.sum()} of {len(plus)}; R11 per galaxy: mean "
        f"{r11.mean():.4f}, rms {r11.std():.3f}; pair response: mean {pair.mean():.4f}, rms "
        f"{pair.std():.3f}; sigma_m per galaxy {per:.3f}, over sqrt(n) "
        f"{per / np.sqrt(full.sum()):.1e}; R11 of the +g image minus the -g image's: rms "
        f"{np.std(r11_signs[:, 0] - r11_signs[:, 1]):.3f}"
    )
    for lo, hi in ((0, 25), (25, 50), (50, 75), (75, 100), (100, 125), (125, 200)):
        s = (r >= lo) & (r < hi)
        if s.sum() > 2:
            print(f"  r in [{lo}, {hi}) px: {s.sum():5d} galaxies, R11 rms {r11[s].std():.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("catalog")
    parser.add_argument("truth")
    parser.add_argument("--g-true", type=float, default=0.02)
    parser.add_argument("--radius", type=float, default=2.0, help="matching radius, px")
    parser.add_argument("--min-edge", type=float, default=None)
    parser.add_argument("--edge-frame", choices=("unsheared", "version"), default="unsheared")
    parser.add_argument("--max-g", type=float, default=np.inf)
    parser.add_argument("--max-size-ratio", type=float, default=np.inf)
    parser.add_argument("--n-boot", type=int, default=300)
    args = parser.parse_args()
    lensed = bool(fitsio.read_header(args.truth, 1).get("SHEARPOS", False))
    d = load(args.catalog, args, lensed)
    rows = d["rows"]
    images = rows["image"]
    sign = {int(i): int(s) for i, s in zip(images, rows["pair_sign"])}
    field = {int(i): int(f) for i, f in zip(images, rows["field"])}
    by_field: dict[int, dict[int, int]] = {}
    for i, f in field.items():
        by_field.setdefault(f, {})[sign[i]] = i
    print(f"{args.catalog}: {len(rows)} rows, kept {int(d['keep'].sum())}")
    for label, pairs in (
        ("1p vs 1m", [(i, i, "1p", "1m") for i in field]),
        (
            "noshear +g vs -g",
            [(s[1], s[-1], "noshear", "noshear") for s in by_field.values() if len(s) == 2],
        ),
    ):
        only, reasons, err, n = transitions(d, pairs, args.radius, args.n_boot)
        scale = 2 * d["step"] if label.startswith("1p") else 1.0
        print(f"{label}: {int(n)} kept rows in the first")
        print("  " + describe(d, only["a"], "only in the first"))
        print("  " + describe(d, only["b"], "only in the second"))
        print(f"  why: {reasons}")
        print(
            f"  bootstrap sigma of the mean difference (/ 2 step for R11): all "
            f"{err[3] / scale:.4f}; of the rows kept in both {err[0] / scale:.4f}, only in the "
            f"first {err[1] / scale:.4f}, only in the second {err[2] / scale:.4f}"
        )
    per_galaxy(d, fitsio.read(args.truth), args.radius, args.g_true)


if __name__ == "__main__":
    main()
