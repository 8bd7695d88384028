"""Rerun README's "A tour of the subcommands" and compare (or rewrite) the table it prints.

The commands are read from README's tour block (the ``sh`` block that starts with
``E=examples/fiducial``) and run as they stand, with bash, in a temporary folder; the
``unweighted`` table that the last command (``megalut evaluate``) prints is compared with
the one README shows below the block: cases and rows exactly, m and c within a tenth of
their quoted errors (training may differ in the last digits between machines).

    python tools/readme_tour.py           # run, compare, exit 1 when README differs
    python tools/readme_tour.py --write   # run and put the printed table into README

About a minute on 2 cores (the commands use ``-j 2``). ``tests/test_readme_tour.py``
(marked slow) runs the comparison.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
#: The tour's commands: the sh block whose first line sets E.
_BLOCK = re.compile(r"```sh\n(E=examples/fiducial[^\n]*\n.*?)```", re.S)
#: The table README shows after the tour: the first plain block after it starting "unweighted".
_TABLE = re.compile(r"```\n(unweighted \(per-case averages\)\n.*?)```", re.S)
_ROW = re.compile(r"^\s+(g1|g2)\s+(\S+) ± (\S+)\s+(\S+) ± (\S+)\s+(\d+)\s+(\d+)\s+(\S+)\s*$")


def tour_commands(text: str) -> str:
    """The shell text of README's tour block."""
    m = _BLOCK.search(text)
    if m is None:
        raise SystemExit("README.md: no tour block (```sh starting with E=examples/fiducial)")
    return m.group(1)


def readme_table(text: str) -> tuple[str, tuple[int, int]]:
    """The table README shows after the tour block, and its span in ``text``."""
    start = _BLOCK.search(text).end()
    m = _TABLE.search(text, start)
    if m is None:
        raise SystemExit("README.md: no 'unweighted' table after the tour block")
    return m.group(1), m.span(1)


def rows(table: str) -> dict[str, tuple[float, float, float, float, int, int]]:
    """``{component: (m, m_err, c, c_err, cases, rows)}`` of a printed table's first section."""
    out = {}
    for line in table.splitlines():
        m = _ROW.match(line)
        if m and m.group(1) not in out:
            g, mv, me, cv, ce, cases, n = m.groups()[:7]
            out[g] = (float(mv), float(me), float(cv), float(ce), int(cases), int(n))
    return out


def run_tour(text: str) -> tuple[str, float]:
    """Run the tour's commands in a temporary folder; (the evaluate table printed, seconds)."""
    script = tour_commands(text).replace(
        "E=examples/fiducial", f"E={ROOT / 'examples' / 'fiducial'}", 1
    )
    with tempfile.TemporaryDirectory(prefix="megalut-tour-") as tmp:
        t0 = time.perf_counter()
        res = subprocess.run(
            ["bash", "-e", "-c", script],
            cwd=tmp,
            capture_output=True,
            text=True,
            env={
                **os.environ,
                "MEGALUT_NPROC": "2",  # this Python's megalut first
                "PATH": os.pathsep.join(
                    [str(Path(sys.executable).parent), os.environ.get("PATH", "")]
                ),
            },
        )
        seconds = time.perf_counter() - t0
    if res.returncode != 0:
        sys.stderr.write(res.stderr[-4000:])
        raise SystemExit(f"the tour's commands failed (exit {res.returncode})")
    m = re.search(r"unweighted \(per-case averages\)\n(?:.+\n)+", res.stdout)
    if m is None:
        raise SystemExit("the tour's evaluate printed no 'unweighted' table:\n" + res.stdout)
    return m.group(0), seconds


def differences(printed: str, documented: str) -> list[str]:
    """What differs between the table a run printed and the one README shows."""
    new, old = rows(printed), rows(documented)
    if set(new) != set(old) or not new:
        return [f"components {sorted(new)} printed, {sorted(old)} in README"]
    out = []
    for g in new:
        (m1, _, c1, _, k1, n1), (m0, me0, c0, ce0, k0, n0) = new[g], old[g]
        if (k1, n1) != (k0, n0):
            out.append(f"{g}: {k1} cases, {n1} rows printed; README has {k0}, {n0}")
        if abs(m1 - m0) > 0.1 * me0 or abs(c1 - c0) > 0.1 * ce0:
            out.append(
                f"{g}: m {m1:+.2e}, c {c1:+.2e} printed; README has m {m0:+.2e}, c {c0:+.2e}"
            )
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", action="store_true", help="put the printed table into README.md")
    args = ap.parse_args(argv)
    text = README.read_text()
    printed, seconds = run_tour(text)
    print(printed, end="")
    print(f"(the tour ran in {seconds:.0f} s)", file=sys.stderr)
    documented, (a, b) = readme_table(text)
    diff = differences(printed, documented)
    if args.write:
        if printed != documented:
            README.write_text(text[:a] + printed + text[b:])
            print("README.md: table updated", file=sys.stderr)
        return 0
    for line in diff:
        print(f"README.md differs: {line}", file=sys.stderr)
    return 1 if diff else 0


if __name__ == "__main__":
    sys.exit(main())
