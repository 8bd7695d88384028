"""m and c of metadetection with adaptive moments from a paired scene (docs/metadetect.md).

    megalut simulate examples/scenes/metadetect.toml -o truth.fits --scene scenes.fits \\
        scene.n_fields=200
    megalut measure scenes.fits --metadetect -o det.fits
    python examples/metadetect/paired_bias.py det.fits --g-true 0.02

Per field and sign: the sums of ``adamom_g1``, ``adamom_g2`` over each version's rows
(``flags == 0`` and ``inner``; the same cut on every version); the response
R11 = (<g1>_1p - <g1>_1m) / (2 step), R22 alike; g = <g>_noshear / R; m and c from the
+g and -g fields: m = (g+ - g-) / (2 g_true) - 1, c = (g2+ + g2-) / 2; errors from a
bootstrap over fields.
"""

from __future__ import annotations

import argparse

import fitsio
import numpy as np

TYPES = ("noshear", "1p", "1m", "2p", "2m")


def field_sums(path: str, max_g: float = 1.0) -> tuple[dict[str, np.ndarray], float]:
    """Per field and sign (axes 0, 1: fields, + and -), per version: sums of g1, g2, counts
    (rows with ``|g| < max_g`` only, the same cut on every version)."""
    rows = fitsio.read(path)
    step = float(fitsio.read_header(path, 1)["MDETSTEP"])
    fields = np.unique(rows["field"])
    keep = (rows["flags"] == 0) & (rows["inner"] != 0)
    keep &= np.hypot(rows["adamom_g1"], rows["adamom_g2"]) < max_g
    out = {}
    step_col = np.char.strip(rows["mdet_step"].astype(str))
    f_index = np.searchsorted(fields, rows["field"])
    s_index = (rows["pair_sign"] < 0).astype(int)
    for kind in TYPES:
        sel = keep & (step_col == kind)
        for name, values in (("g1", rows["adamom_g1"]), ("g2", rows["adamom_g2"]), ("n", None)):
            acc = np.zeros((len(fields), 2))
            w = np.ones(sel.sum()) if values is None else values[sel]
            np.add.at(acc, (f_index[sel], s_index[sel]), w)
            out[f"{name}_{kind}"] = acc
    return out, step


def bias(s: dict[str, np.ndarray], step: float, g_true: float) -> tuple[float, float, float]:
    """m, c1, c2 from field sums (summed over the fields given)."""
    t = {k: v.sum(axis=0) for k, v in s.items()}  # (2,): + and -
    mean = {k: t[f"g{k[1]}_{k[0]}"] / t[f"n_{k[0]}"] for k in [(v, c) for v in TYPES for c in "12"]}
    r11 = (mean[("1p", "1")] - mean[("1m", "1")]) / (2 * step)
    r22 = (mean[("2p", "2")] - mean[("2m", "2")]) / (2 * step)
    r11, r22 = r11.mean(), r22.mean()  # one response for both signs
    g1 = mean[("noshear", "1")] / r11
    g2 = mean[("noshear", "2")] / r22
    return (g1[0] - g1[1]) / (2 * g_true) - 1.0, (g1[0] + g1[1]) / 2, (g2[0] + g2[1]) / 2


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("catalog")
    parser.add_argument("--g-true", type=float, default=0.02)
    parser.add_argument("--n-boot", type=int, default=500)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--max-g", type=float, default=1.0, help="keep rows with |g| below")
    args = parser.parse_args()
    sums, step = field_sums(args.catalog, args.max_g)
    m, c1, c2 = bias(sums, step, args.g_true)
    rng = np.random.default_rng(args.seed)
    n_fields = len(next(iter(sums.values())))
    boot = []
    for _ in range(args.n_boot):
        pick = rng.integers(0, n_fields, n_fields)  # the same fields for every sum
        boot.append(bias({k: v[pick] for k, v in sums.items()}, step, args.g_true))
    err = np.std(boot, axis=0)
    t = {k: v.sum(axis=0) for k, v in sums.items()}
    r11 = (t["g1_1p"] / t["n_1p"] - t["g1_1m"] / t["n_1m"]).mean() / (2 * step)
    print(f"fields {n_fields}, noshear rows kept {int(t['n_noshear'].sum())}, R11 {r11:.4f}")
    print(f"m  = {m:+.2e} +- {err[0]:.1e}")
    print(f"c1 = {c1:+.2e} +- {err[1]:.1e}")
    print(f"c2 = {c2:+.2e} +- {err[2]:.1e}")


if __name__ == "__main__":
    main()
