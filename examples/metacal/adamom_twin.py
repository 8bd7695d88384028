"""Adaptive moments' own metacal on the rows of a predicted metacal catalog (docs/metacal.md).

Writes a catalog whose estimates are the adaptive-moment shapes of each version
(``pre_g{1,2}_<type> = adamom_g{1,2}_<type>``, responses ``mcal_r*`` from their finite
differences, no weights), with the truth, ``rea``, ``flags_*`` and ``snr_*`` of the input, so
that ``megalut evaluate`` measures adaptive moments' metacal on the same rows, with the same
failures and the same S/N selections as the networks; with ``--weights``, the networks'
weights (``pre_g*_w*``) too, for a weighted comparison:

    python examples/metacal/adamom_twin.py p-tw-4401.fits am-4401.fits
    megalut evaluate am-4401.fits --failures selection --select "snr > 15"
"""

from __future__ import annotations

import argparse
import os
import sys

import fitsio
import numpy as np

from megalut_cli.measure.metacal_defaults import TYPES

#: Header cards carried over (what ``evaluate`` reads of the set's design).
CARDS = (
    "MLFORMAT", "MLFMTVER", "SEED", "NCASES", "NREA", "STAMPSZ", "SNC", "CRN", "ANTITHET",
    "NOISE", "MEASURED", "MCALSTEP",
)  # fmt: skip


def weight_columns() -> list[str]:
    """The networks' weight columns of a predicted metacal catalog."""
    return ["pre_g1_w", "pre_g2_w"] + [f"pre_g{i}_w_{t}" for t in TYPES for i in (1, 2)]


def twin(columns: dict[str, np.ndarray], step: float) -> dict[str, np.ndarray]:
    """The twin's columns from the input's (``case, rea, tru_g*, flags*, snr*, adamom_g*_*``,
    and the weights when given)."""
    out = {c: columns[c] for c in ("case", "rea", "tru_g1", "tru_g2", "flags", "snr")}
    out.update({c: columns[c] for c in weight_columns() if c in columns})
    for t in TYPES:
        out[f"flags_{t}"], out[f"snr_{t}"] = columns[f"flags_{t}"], columns[f"snr_{t}"]
        for i in (1, 2):
            out[f"pre_g{i}_{t}"] = columns[f"adamom_g{i}_{t}"]
    out["pre_g1"], out["pre_g2"] = out["pre_g1_noshear"], out["pre_g2_noshear"]
    for i in (1, 2):
        for j in (1, 2):
            out[f"mcal_r{i}{j}"] = (columns[f"adamom_g{i}_{j}p"] - columns[f"adamom_g{i}_{j}m"]) / (
                2 * step
            )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("catalog", help="a megalut predict catalog of metacal features")
    ap.add_argument("output", help="the twin catalog to write")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing output")
    ap.add_argument("--weights", action="store_true", help="carry the networks' weights over")
    args = ap.parse_args()
    if os.path.exists(args.output) and not args.overwrite:
        sys.exit(f"adamom_twin.py: {args.output} exists (--overwrite to replace it)")
    try:
        header = fitsio.read_header(args.catalog, 1)
        names = ["case", "rea", "tru_g1", "tru_g2", "flags", "snr"] + [
            f"{c}_{t}" for t in TYPES for c in ("flags", "snr", "adamom_g1", "adamom_g2")
        ]
        names += weight_columns() if args.weights else []
        data = fitsio.read(args.catalog, 1, columns=names)
    except (OSError, ValueError) as err:
        sys.exit(f"adamom_twin.py: {args.catalog}: {err}")
    if "MCALSTEP" not in header:
        sys.exit(f"adamom_twin.py: {args.catalog} is not a metacal catalog (no MCALSTEP card)")
    columns = twin({n: data[n] for n in names}, float(header["MCALSTEP"]))
    cards = [{"name": k, "value": header[k]} for k in CARDS if k in header]
    temporary = args.output + ".tmp"
    fitsio.write(
        temporary,
        list(columns.values()),
        names=list(columns),
        header=cards,
        extname="CATALOG",
        clobber=True,
    )
    os.replace(temporary, args.output)


if __name__ == "__main__":
    main()
