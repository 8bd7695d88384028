"""Metacalibration of plain adaptive moments (no networks), in the layout `megalut evaluate` reads.

    python examples/metacal/peers/adamom_metacal.py MCAL.fits -o OUT.fits [--overwrite]

MCAL.fits is a `megalut measure --metacal` catalog. Written: every input column, and
pre_g1 := adamom_g1, pre_g2 := adamom_g2 (the plain moments of the stamp as it is),
pre_g{1,2}_<type> := adamom_g{1,2}_<type> for the five types noshear, 1p, 1m, 2p, 2m,
mcal_rij := (pre_gi_jp - pre_gi_jm) / (2 step) with the catalog's MCALSTEP, flags_<type> as
they are. `megalut evaluate OUT.fits` then calibrates pre_g*_noshear by the mean response.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from megalut_cli.catalog import read_catalog, write_catalog

TYPES = ("noshear", "1p", "1m", "2p", "2m")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("catalog")
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    cat = read_catalog(a.catalog)
    meta = dict(cat.meta)
    history = meta.pop("HISTORY", [])
    step = meta.get("MCALSTEP")
    if step is None:
        raise SystemExit(
            f"{a.catalog}: no MCALSTEP card: not a `megalut measure --metacal` catalog"
        )
    step = float(step)
    cols = {name: np.asarray(cat[name]) for name in cat.colnames}
    for i in (1, 2):
        cols[f"pre_g{i}"] = np.asarray(cat[f"adamom_g{i}"], dtype=float)
        for kind in TYPES:
            cols[f"pre_g{i}_{kind}"] = np.asarray(cat[f"adamom_g{i}_{kind}"], dtype=float)
    for i in (1, 2):
        for j in (1, 2):
            cols[f"mcal_r{i}{j}"] = (cols[f"pre_g{i}_{j}p"] - cols[f"pre_g{i}_{j}m"]) / (2.0 * step)
    for kind in TYPES:
        if f"flags_{kind}" not in cols:
            raise SystemExit(f"{a.catalog}: no flags_{kind} column")
    write_catalog(
        a.output,
        cols,
        fmt="megalut.predictions",
        overwrite=a.overwrite,
        cards=meta,
        history=history,
    )
    r = np.nanmean(cols["mcal_r11"]), np.nanmean(cols["mcal_r22"])
    print(
        f"adamom metacal: <R11> = {r[0]:.4f}, <R22> = {r[1]:.4f} (all rows, NaN left out); "
        f"wrote {a.output}",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
