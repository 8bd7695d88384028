"""m and c of the stamp route on paired scenes: one detection on the unsheared cell, stamps
around the detections (neighbours in), stamp metacal (docs/metadetect.md, ``--detect``).

    megalut simulate examples/scenes/metadetect.toml -o truth.fits --scene scenes.fits \\
        --pairs scene.n_fields=1000
    megalut measure scenes.fits --detect --metacal -o stamps.fits -j 2
    python examples/metadetect/stamp_route_bias.py stamps.fits --max-size-ratio 3

The same cuts as ``paired_bias.py`` (``flags == 0``, ``inner``, the position at least half a
stamp from the cell's edges, optionally (adamom_sigma / psf_adamom_sigma)^2 below
``--max-size-ratio``), applied to each version's own features for the selection response.
Per field and sign: the sums of g1, g2 of the noshear rows kept, of their per-object
responses (X_1p - X_1m) / (2 step), and of g under the cuts of 1p, 1m, 2p, 2m (the selection
response). Over the fields given: R = <R_obj> + R_sel (one for both signs),
g = <g> / R, m = (g1+ - g1-) / (2 g_true) - 1, c = (g+ + g-) / 2; errors from a bootstrap
over fields. The detection, made once on the unsheared image, is outside the response: that
is what metadetection adds.
"""

from __future__ import annotations

import argparse

import fitsio
import numpy as np

VERSIONS = ("noshear", "1p", "1m", "2p", "2m")


def kept(rows: np.ndarray, kind: str, size: int, min_edge: float, max_ratio: float) -> np.ndarray:
    """The rows passing the cuts on version ``kind``'s features."""
    x, y = rows["x"], rows["y"]
    edge = np.minimum.reduce([x - 0.5, y - 0.5, size + 0.5 - x, size + 0.5 - y])
    keep = (rows[f"flags_{kind}"] == 0) & (rows["flags"] == 0) & (rows["inner"] != 0)
    keep &= edge >= min_edge
    ratio = (rows[f"adamom_sigma_{kind}"] / rows[f"psf_adamom_sigma_{kind}"]) ** 2
    return keep & (ratio < max_ratio)


def field_sums(rows: np.ndarray, step: float, size: int, min_edge: float, max_ratio: float):
    """Per field and sign (axes 0, 1), the sums named in the module docstring."""
    fields, f_index = np.unique(rows["field"], return_inverse=True)
    s_index = (rows["pair_sign"] < 0).astype(int)
    out = {}

    def add(name: str, sel: np.ndarray, values: np.ndarray | None) -> None:
        acc = np.zeros((len(fields), 2))
        np.add.at(acc, (f_index[sel], s_index[sel]), 1.0 if values is None else values[sel])
        out[name] = acc

    base = kept(rows, "noshear", size, min_edge, max_ratio)
    for c in "12":
        g = rows[f"adamom_g{c}_noshear"]
        r = (rows[f"adamom_g{c}_{c}p"] - rows[f"adamom_g{c}_{c}m"]) / (2 * step)
        ok = base & np.isfinite(r)
        add(f"g{c}", ok, g)
        add(f"r{c}", ok, r)
        add(f"n{c}", ok, None)
        for kind in (f"{c}p", f"{c}m"):
            sel = kept(rows, kind, size, min_edge, max_ratio) & np.isfinite(g)
            add(f"g{c}_{kind}", sel, g)
            add(f"n{c}_{kind}", sel, None)
    return out


def estimate(s: dict[str, np.ndarray], step: float, g_true: float) -> np.ndarray:
    """m, c1, c2, R11, R22 from field sums (summed over the fields given)."""
    t = {k: v.sum(axis=0) for k, v in s.items()}
    g, resp = {}, {}
    for c in "12":
        mean_r = t[f"r{c}"].sum() / t[f"n{c}"].sum()
        sel = (
            t[f"g{c}_{c}p"].sum() / t[f"n{c}_{c}p"].sum()
            - t[f"g{c}_{c}m"].sum() / t[f"n{c}_{c}m"].sum()
        ) / (2 * step)
        resp[c] = mean_r + sel
        g[c] = t[f"g{c}"] / t[f"n{c}"] / resp[c]
    m = (g["1"][0] - g["1"][1]) / (2 * g_true) - 1.0
    return np.array([m, g["1"].mean(), g["2"].mean(), resp["1"], resp["2"]])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("catalog", nargs="+", help="catalogs of measure --detect --metacal")
    parser.add_argument("--g-true", type=float, default=0.02)
    parser.add_argument("--n-boot", type=int, default=500)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--min-edge", type=float, default=None)
    parser.add_argument("--max-size-ratio", type=float, default=np.inf)
    args = parser.parse_args()
    parts, step = [], None
    for path in args.catalog:
        rows = fitsio.read(path)
        header = fitsio.read_header(path, 1)
        step, size = float(header["MCALSTEP"]), int(header["CELLSZ"])
        edge = int(header["STAMPSZ"]) / 2 if args.min_edge is None else args.min_edge
        parts.append(field_sums(rows, step, size, edge, args.max_size_ratio))
    assert step is not None
    sums = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    value = estimate(sums, step, args.g_true)
    rng = np.random.default_rng(args.seed)
    n = len(sums["n1"])
    boot = [
        estimate({k: v[pick] for k, v in sums.items()}, step, args.g_true)
        for pick in (rng.integers(0, n, n) for _ in range(args.n_boot))
    ]
    err = np.std(boot, axis=0)
    print(f"fields {n}, noshear rows kept {int(sums['n1'].sum())}")
    print(f"R11 = {value[3]:.4f} +- {err[3]:.4f}, R22 = {value[4]:.4f} +- {err[4]:.4f}")
    print(f"m  = {value[0]:+.2e} +- {err[0]:.1e}")
    print(f"c1 = {value[1]:+.2e} +- {err[1]:.1e}")
    print(f"c2 = {value[2]:+.2e} +- {err[2]:.1e}")


if __name__ == "__main__":
    main()
