"""Peak memory of ``megalut simulate`` against the size of the catalog it writes.

Usage: python benchmarks/simulate_memory.py [--measure] [N_CASES ...]
(from the root of the source tree to measure: it imports ``megalut_cli`` from there)

Each size runs ``megalut simulate examples/fiducial/tp.toml`` (1000 realizations per case,
``-j 1``, truth only unless ``--measure``) in a fresh process and reports that process's
peak resident memory (``ru_maxrss``) beside the size of the catalog file. With the catalog
streamed to the file (``sim.simulate.simulate_chunks``) the peak does not grow with the size.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

CHILD = """
import json, resource, sys
from megalut_cli.cli import main
sys.argv = ["megalut", "-q", "simulate", "examples/fiducial/tp.toml", "-o", sys.argv[1],
            "--n-cases", sys.argv[2], "--n-realizations", "1000", "--seed", "1", "-j", "1",
            "--overwrite"] + sys.argv[3:]
try:
    main()
except SystemExit as e:
    if e.code:
        raise
import megalut_cli
print(megalut_cli.__file__, file=sys.stderr)
print(json.dumps(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("n_cases", nargs="*", type=int, default=[250, 1000, 4000])
    ap.add_argument("--measure", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "c.fits")
        for n in args.n_cases:
            extra = ["--measure"] if args.measure else []
            res = subprocess.run(
                [sys.executable, "-c", CHILD, out, str(n), *extra],
                capture_output=True,
                text=True,
                check=True,
            )
            peak = json.loads(res.stdout.strip().splitlines()[-1])
            if n == args.n_cases[0]:
                print(f"megalut_cli from {res.stderr.strip().splitlines()[-1]}\n")
                print("| rows | catalog (MB) | peak RSS (MB) |\n|---|---|---|")
            print(f"| {n * 1000:,} | {os.path.getsize(out) / 2**20:.0f} | {peak:.0f} |")


if __name__ == "__main__":
    main()
