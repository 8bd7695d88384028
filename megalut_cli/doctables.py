"""The option tables of ``docs/*.md``, generated from the declarations: ``python -m megalut_cli.doctables``.

A table sits between ``<!-- table: NAME -->`` and ``<!-- end table -->`` lines; NAME is a
key of :data:`TABLES`. Running this module rewrites them; ``tests/test_schema.py`` checks
that the docs are current.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Callable
from pathlib import Path

from megalut_cli.great3.pipeline import BRANCH_OPTIONS, OUTPUT_OPTIONS, TOP_OPTIONS
from megalut_cli.great3.pipeline import SET_OPTIONS as GREAT3_SET_OPTIONS
from megalut_cli.measure.options import ALL_MEASURE_OPTIONS
from megalut_cli.nn.options import POINT_OPTIONS, WEIGHT_OPTIONS, train_options
from megalut_cli.pipeline_config import PIPELINE_OPTIONS, REFERENCE_OPTIONS, SET_OPTIONS
from megalut_cli.schema import docs_table
from megalut_cli.shear.options import ALL_PREDICT_OPTIONS, EVALUATE_OPTIONS
from megalut_cli.sim.config import GSPARAMS_OPTIONS, INSTRUMENT_OPTIONS, STRUCTURE_OPTIONS
from megalut_cli.sim.options import ALL_SIMULATE_OPTIONS

#: Generated tables by name.
TABLES: dict[str, Callable[[], str]] = {
    "train-common": lambda: docs_table(train_options("point")),
    "train-point": lambda: docs_table(POINT_OPTIONS),
    "train-weight": lambda: docs_table(WEIGHT_OPTIONS),
    "structure": lambda: docs_table(STRUCTURE_OPTIONS, cli=False),
    "instrument": lambda: docs_table(INSTRUMENT_OPTIONS, cli=False),
    "gsparams": lambda: docs_table(GSPARAMS_OPTIONS, cli=False),
    "evaluate": lambda: docs_table(EVALUATE_OPTIONS),
    "pipeline": lambda: docs_table(PIPELINE_OPTIONS, cli=False),
    "pipeline-sets": lambda: docs_table(SET_OPTIONS, cli=False),
    "pipeline-reference": lambda: docs_table(REFERENCE_OPTIONS, cli=False),
    "great3-branch": lambda: docs_table(BRANCH_OPTIONS, cli=False, prefix="branch."),
    "great3-top": lambda: docs_table(TOP_OPTIONS, cli=False),
    "great3-sets": lambda: docs_table(GREAT3_SET_OPTIONS, cli=False),
    "great3-output": lambda: docs_table(OUTPUT_OPTIONS, cli=False, prefix="output."),
    "measure": lambda: docs_table(ALL_MEASURE_OPTIONS, keys=False),
    "predict": lambda: docs_table(ALL_PREDICT_OPTIONS, keys=False),
    "simulate": lambda: docs_table(ALL_SIMULATE_OPTIONS, keys=False),
}

_BLOCK = re.compile(r"(<!-- table: ([\w-]+) -->\n)(.*?)(<!-- end table -->)", re.S)


def render(text: str) -> str:
    """``text`` with every generated table block rewritten."""

    def fill(m: re.Match[str]) -> str:
        name = m.group(2)
        if name not in TABLES:
            raise KeyError(f"unknown generated table {name!r}")
        return f"{m.group(1)}{TABLES[name]()}\n{m.group(4)}"

    return _BLOCK.sub(fill, text)


def docs_files(root: Path) -> list[Path]:
    """The docs pages that hold generated tables."""
    return sorted(p for p in (root / "docs").glob("*.md") if _BLOCK.search(p.read_text()))


def main(root: Path) -> int:
    for path in docs_files(root):
        text = path.read_text()
        new = render(text)
        if new != text:
            path.write_text(new)
            print(f"updated {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path.cwd()))
