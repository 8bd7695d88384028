"""m and c of metadetection with adaptive moments from paired scenes.

docs/metadetect.md; examples/metadetect/README.md holds the runs.

    megalut simulate examples/scenes/isolated.toml -o truth.fits --scene scenes.fits \\
        scene.n_fields=200
    megalut measure scenes.fits --metadetect -o det.fits -j 1
    python examples/metadetect/paired_bias.py det.fits --g-true 0.02

Selection: one cut on each row's own columns, the same for every version (noshear, 1p, 1m,
2p, 2m), so that its response is in R; no truth is used. ``flags == 0``, ``inner``, and the
position at least ``--min-edge`` pixels (default ``STAMPSZ / 2``: no stamp holds pixels
outside the cell) from every edge of the cell, taken with its version's shear about the
cell's centre undone (as metadetect's ``unshear_positions``; ``--edge-frame version``: as
detected), so that an object has one edge distance in every version instead of crossing
the cut between 1p and 1m; optionally ``|g| < --max-g``, ``snr > --min-snr`` and
``(adamom_sigma / psf_adamom_sigma)^2 < --max-size-ratio`` (3 keeps every isolated galaxy
of examples/scenes/isolated.toml and drops the blends of examples/scenes/metadetect.toml).

Estimate: per field and sign, the sums of ``adamom_g1``, ``adamom_g2`` (``--estimator pre``:
the networks' ``pre_g1``, ``pre_g2``, after ``megalut predict``) over each version's
kept rows and their counts; over the fields, per sign, R11 = (<g1>_1p - <g1>_1m) / (2 step),
R22 alike, one response for both signs (their mean; ``--per-sign-response``: each sign its
own), g = <g>_noshear / R; m and c from the
+g and -g images: m = (g1+ - g1-) / (2 g_true) - 1, c1 = (g1+ + g1-) / 2,
c2 = (g2+ + g2-) / 2; errors from a bootstrap over fields (the +g and -g images of a field
share their galaxies and noise: a field is the unit). Several catalogs (runs with other
seeds, for ``simulate`` and ``measure`` both) are taken as one set of fields.
``--subsets K`` also prints sigma_m of the first n/2^k fields, k = K-1 ... 1.
"""

from __future__ import annotations

import argparse

import fitsio
import numpy as np

TYPES = ("noshear", "1p", "1m", "2p", "2m")
#: The shear of each version, in units of the step (g1, g2).
SHEARS = {"noshear": (0, 0), "1p": (1, 0), "1m": (-1, 0), "2p": (0, 1), "2m": (0, -1)}


def unsheared(rows: np.ndarray, step: float, cell_size: int) -> tuple[np.ndarray, np.ndarray]:
    """The rows' ``x, y``: ``measure --metadetect`` writes each detection's position with
    its version's shear about the cell's centre undone (as metadetect's
    ``unshear_positions``), so an object has one position in every version."""
    return rows["x"].astype(float), rows["y"].astype(float)


def version_positions(
    rows: np.ndarray, step: float, cell_size: int
) -> tuple[np.ndarray, np.ndarray]:
    """The rows' positions as detected in their version: ``x, y`` sheared again by the
    version's shear about the cell's centre."""
    kind = np.char.strip(rows["mdet_step"].astype(str))
    centre = (cell_size + 1) / 2.0  # 1-based: the centre the operation shears about
    dx, dy = rows["x"] - centre, rows["y"] - centre
    x, y = rows["x"].astype(float), rows["y"].astype(float)
    for version, (s1, s2) in SHEARS.items():
        g1, g2, at = s1 * step, s2 * step, kind == version
        norm = np.sqrt(1.0 - g1 * g1 - g2 * g2)
        x[at] = ((1.0 + g1) * dx[at] + g2 * dy[at]) / norm + centre
        y[at] = (g2 * dx[at] + (1.0 - g1) * dy[at]) / norm + centre
    return x, y


def selection(
    rows: np.ndarray,
    step: float,
    cell_size: int,
    min_edge: float = 0.0,
    max_g: float = np.inf,
    min_snr: float = -np.inf,
    max_size_ratio: float = np.inf,
    edge_frame: str = "unsheared",
) -> np.ndarray:
    """The rows kept: the same cut on every version, from each row's own columns only (the
    edge distance of its position unsheared, or as measured in its version)."""
    frame = unsheared if edge_frame == "unsheared" else version_positions
    x, y = frame(rows, step, cell_size)
    edge = np.minimum.reduce([x - 0.5, y - 0.5, cell_size + 0.5 - x, cell_size + 0.5 - y])
    keep = (rows["flags"] == 0) & (rows["inner"] != 0) & (edge >= min_edge)
    keep &= np.hypot(rows["adamom_g1"], rows["adamom_g2"]) < max_g
    keep &= rows["snr"] > min_snr
    keep &= (rows["adamom_sigma"] / rows["psf_adamom_sigma"]) ** 2 < max_size_ratio
    return keep


def field_sums(
    rows: np.ndarray, keep: np.ndarray, prefix: str = "adamom", fields: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Per field and sign (axes 0, 1: fields, + and -), per version: the sums of g1, g2 (the
    columns ``<prefix>_g1``, ``<prefix>_g2``) and the counts of the kept rows; ``fields``
    (sorted, holding every row's field): the fields' order, default those of the rows."""
    fields = np.unique(rows["field"]) if fields is None else fields
    step_col = np.char.strip(rows["mdet_step"].astype(str))
    f_index = np.searchsorted(fields, rows["field"])
    s_index = (rows["pair_sign"] < 0).astype(int)
    out = {}
    for kind in TYPES:
        sel = keep & (step_col == kind)
        g1, g2 = rows[f"{prefix}_g1"], rows[f"{prefix}_g2"]
        for name, values in (("g1", g1), ("g2", g2), ("n", None)):
            acc = np.zeros((len(fields), 2))
            w = np.ones(sel.sum()) if values is None else values[sel]
            np.add.at(acc, (f_index[sel], s_index[sel]), w)
            out[f"{name}_{kind}"] = acc
    return out


def estimate(
    s: dict[str, np.ndarray], step: float, g_true: float, per_sign: bool = False
) -> np.ndarray:
    """m, c1, c2, R11, R22 from field sums (summed over the fields given); ``per_sign``: each
    sign's shear calibrated by its own response (R: their mean, as printed)."""
    t = {k: v.sum(axis=0) for k, v in s.items()}  # (2,): + and -
    mean = {(v, c): t[f"g{c}_{v}"] / t[f"n_{v}"] for v in TYPES for c in "12"}
    r11 = (mean[("1p", "1")] - mean[("1m", "1")]) / (2 * step)  # (2,): each sign's
    r22 = (mean[("2p", "2")] - mean[("2m", "2")]) / (2 * step)
    if not per_sign:  # one response for both signs
        r11, r22 = np.full(2, r11.mean()), np.full(2, r22.mean())
    g1 = mean[("noshear", "1")] / r11
    g2 = mean[("noshear", "2")] / r22
    m = (g1[0] - g1[1]) / (2 * g_true) - 1.0
    return np.array([m, (g1[0] + g1[1]) / 2, (g2[0] + g2[1]) / 2, r11.mean(), r22.mean()])


def bootstrap(
    s: dict[str, np.ndarray],
    step: float,
    g_true: float,
    n_boot: int,
    seed: int,
    per_sign: bool = False,
    minus: dict[str, np.ndarray] | None = None,
    minus_step: float | None = None,
) -> np.ndarray:
    """The standard deviation of :func:`estimate` over a bootstrap of the fields; with
    ``minus`` (the sums of the same fields under a change, their step ``minus_step``,
    default ``step``), of the difference of the two estimates, both resampled with the
    same fields."""
    rng = np.random.default_rng(seed)
    n_fields = len(next(iter(s.values())))
    boot = []
    for _ in range(n_boot):
        pick = rng.integers(0, n_fields, n_fields)  # the same fields for every sum
        value = estimate({k: v[pick] for k, v in s.items()}, step, g_true, per_sign)
        if minus is not None:
            other = {k: v[pick] for k, v in minus.items()}
            value = value - estimate(other, minus_step or step, g_true, per_sign)
        boot.append(value)
    return np.std(boot, axis=0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("catalog", nargs="+", help="metadetect catalog(s) of paired scenes")
    parser.add_argument("--g-true", type=float, default=0.02)
    parser.add_argument("--n-boot", type=int, default=500)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--min-edge",
        type=float,
        default=None,
        help="keep rows at least this many pixels from every cell edge (default STAMPSZ / 2)",
    )
    parser.add_argument("--max-g", type=float, default=np.inf, help="keep rows with |g| below")
    parser.add_argument("--min-snr", type=float, default=-np.inf, help="keep rows with snr above")
    parser.add_argument(
        "--max-size-ratio",
        type=float,
        default=np.inf,
        help="keep rows with (adamom_sigma / psf_adamom_sigma)^2 below",
    )
    parser.add_argument(
        "--edge-frame",
        choices=("unsheared", "version"),
        default="unsheared",
        help="the position the edge distance is taken of: with the version's shear undone "
        "(default), or as detected in the version",
    )
    parser.add_argument(
        "--per-sign-response",
        action="store_true",
        help="calibrate each sign by its own response (default: their mean for both)",
    )
    parser.add_argument(
        "--minus",
        nargs="+",
        default=None,
        help="catalogs of the same fields under a change (one per catalog, in the same order): "
        "the difference of the estimates, errors from one bootstrap of the fields for both",
    )
    parser.add_argument("--subsets", type=int, default=1, help="sigma_m of 1/2^k of the fields")
    parser.add_argument(
        "--estimator",
        default="adamom",
        help="the shear columns <estimator>_g1, <estimator>_g2: adamom (default) or pre (the "
        "networks' unweighted predictions, after megalut predict)",
    )
    args = parser.parse_args()
    if args.minus and len(args.minus) != len(args.catalog):
        parser.error("--minus takes as many catalogs as are given, in the same order")

    def read(path: str) -> tuple[np.ndarray, np.ndarray, float, float]:
        """A catalog's rows, the rows kept, its step and its min edge."""
        rows = fitsio.read(path)
        header = fitsio.read_header(path, 1)
        step, cell_size = float(header["MDETSTEP"]), int(header["CELLSZ"])
        min_edge = int(header["STAMPSZ"]) / 2 if args.min_edge is None else args.min_edge
        keep = selection(
            rows,
            step,
            cell_size,
            min_edge,
            args.max_g,
            args.min_snr,
            args.max_size_ratio,
            args.edge_frame,
        )
        return rows, keep, step, min_edge

    parts, minus_parts, steps, minus_steps, n_rows, n_kept = [], [], set(), set(), 0, 0
    for i, path in enumerate(args.catalog):  # runs of other seeds: their fields are other fields
        rows, keep, step, min_edge = read(path)
        fields = None
        if args.minus:  # the same fields under a change: one field order for both
            other, other_keep, other_step, _ = read(args.minus[i])
            fields = np.union1d(rows["field"], other["field"])
            minus_parts.append(field_sums(other, other_keep, args.estimator, fields))
            minus_steps.add(other_step)
        parts.append(field_sums(rows, keep, args.estimator, fields))
        steps.add(step)
        n_rows, n_kept = n_rows + len(rows), n_kept + int(keep.sum())
    for kind, found in (("catalogs", steps), ("--minus catalogs", minus_steps)):
        if len(found) > 1:
            parser.error(f"the {kind} have different steps (MDETSTEP): {sorted(found)}")
    minus_step = minus_steps.pop() if minus_steps else None
    sums = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    minus = None
    if args.minus:
        minus = {k: np.concatenate([p[k] for p in minus_parts]) for k in parts[0]}
    per_sign = args.per_sign_response
    m, c1, c2, r11, r22 = estimate(sums, step, args.g_true, per_sign)
    err = bootstrap(sums, step, args.g_true, args.n_boot, args.seed, per_sign)
    n_fields = len(sums["n_noshear"])
    print(
        f"fields {n_fields}, rows kept {n_kept} of {n_rows} "
        f"(noshear {int(sums['n_noshear'].sum())}), min edge {min_edge:g} px ({args.edge_frame})"
    )
    print(f"R11 = {r11:.4f} +- {err[3]:.4f}, R22 = {r22:.4f} +- {err[4]:.4f}")
    print(f"m  = {m:+.2e} +- {err[0]:.2e}")
    print(f"c1 = {c1:+.2e} +- {err[1]:.2e}")
    print(f"c2 = {c2:+.2e} +- {err[2]:.2e}")
    if minus is not None:
        other = estimate(minus, minus_step, args.g_true, per_sign)
        diff = np.array([m, c1, c2, r11, r22]) - other
        d_err = bootstrap(
            sums, step, args.g_true, args.n_boot, args.seed, per_sign, minus, minus_step
        )
        print(f"minus (the --minus catalogs, the same fields): m = {other[0]:+.2e}, "
              f"c1 = {other[1]:+.2e}, c2 = {other[2]:+.2e}")  # fmt: skip
        for name, value, e in zip(("m", "c1", "c2", "R11", "R22"), diff, d_err):
            print(f"difference {name:3s} = {value:+.2e} +- {e:.2e}")
    for k in range(args.subsets - 1, 0, -1):
        n = n_fields >> k
        if n < 2:
            continue
        part = {key: v[:n] for key, v in sums.items()}
        e = bootstrap(part, step, args.g_true, args.n_boot, args.seed, per_sign)
        m_part = estimate(part, step, args.g_true, per_sign)[0]
        print(f"first {n} fields: m = {m_part:+.2e} +- {e[0]:.1e}")


if __name__ == "__main__":
    main()
