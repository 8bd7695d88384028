"""The option tables of ``docs/*.md``, generated from the declarations:
``python -m megalut_cli.doctables``.

A table sits between ``<!-- table: NAME -->`` and ``<!-- end table -->`` lines; NAME is a
key of :data:`TABLES`. Running this module rewrites them; ``tests/test_schema.py`` checks
that the docs are current.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Callable
from pathlib import Path

from megalut_cli.measure.options import ALL_MEASURE_OPTIONS
from megalut_cli.nn.options import POINT_OPTIONS, WEIGHT_OPTIONS, train_options
from megalut_cli.pipeline.config import PIPELINE_OPTIONS, REFERENCE_OPTIONS, SET_OPTIONS
from megalut_cli.pipeline.great3_file import BRANCH_OPTIONS, OUTPUT_OPTIONS, TOP_OPTIONS
from megalut_cli.pipeline.great3_file import SET_OPTIONS as GREAT3_SET_OPTIONS
from megalut_cli.schema import Option, docs_table, kinds_table
from megalut_cli.shear.options import (
    ALL_CALIBRATE_OPTIONS,
    ALL_PREDICT_OPTIONS,
    EVALUATE_OPTIONS,
)
from megalut_cli.sim.config import GSPARAMS_OPTIONS, INSTRUMENT_OPTIONS, STRUCTURE_OPTIONS
from megalut_cli.sim.galaxy_config import GALAXY_OPTION
from megalut_cli.sim.noise_config import NOISE_KINDS, NOISE_OPTIONS
from megalut_cli.sim.options import ALL_SIMULATE_OPTIONS
from megalut_cli.sim.profiles import GALAXY_PROFILES
from megalut_cli.sim.psf import PSF_REGISTRY, PSF_TYPES
from megalut_cli.sim.scene_config import SCENE_OPTIONS


def models_table(
    head: str, rows: dict[str, list[str]], columns: tuple[str, ...] = ("model",)
) -> str:
    """A Markdown table of the kinds of a table (``head``: ``type``, ``profile``), one row each."""
    lines = [f"| `{head}` | " + " | ".join(columns) + " |", "|" + "---|" * (len(columns) + 1)]
    lines += [f"| `{name}` | " + " | ".join(cells) + " |" for name, cells in rows.items()]
    return "\n".join(lines)


def galaxy_profiles_table() -> str:
    """The registered galaxy profiles: what each is, what draws it, its own truth columns."""
    rows = {
        name: [
            p.help,
            "the fast engine (GalSim with knots)" if p.fast else "GalSim",
            ", ".join(f"`{c}`" for c in p.truth_columns) or "—",
        ]
        for name, p in GALAXY_PROFILES.items()
    }
    return models_table("profile", rows, ("model", "drawn by", "its truth columns"))


#: ``psf.type``, for the docs (the types registered by :mod:`megalut_cli.sim.psf`).
PSF_TYPE = Option(
    "type", "choice", None, "the PSF model", choices=PSF_TYPES, default_text="required"
)

#: Generated tables by name.
TABLES: dict[str, Callable[[], str]] = {
    "train-common": lambda: docs_table(train_options("point")),
    "train-point": lambda: docs_table(POINT_OPTIONS),
    "train-weight": lambda: docs_table(WEIGHT_OPTIONS),
    "structure": lambda: docs_table(STRUCTURE_OPTIONS, cli=False),
    "instrument": lambda: docs_table(INSTRUMENT_OPTIONS, cli=False),
    "gsparams": lambda: docs_table(GSPARAMS_OPTIONS, cli=False),
    "scene": lambda: docs_table(SCENE_OPTIONS, cli=False, prefix="scene."),
    "galaxy-profiles": galaxy_profiles_table,
    "galaxy": lambda: kinds_table(
        (GALAXY_OPTION,), {n: p.options for n, p in GALAXY_PROFILES.items()}, "profiles"
    ),
    "psf-types": lambda: models_table("type", {n: [t.help] for n, t in PSF_REGISTRY.items()}),
    "psf": lambda: kinds_table(
        (PSF_TYPE,), {n: t.options for n, t in PSF_REGISTRY.items()}, "types"
    ),
    "noise-types": lambda: models_table("type", {n: [t.help] for n, t in NOISE_KINDS.items()}),
    "noise": lambda: kinds_table(
        NOISE_OPTIONS, {n: t.options for n, t in NOISE_KINDS.items()}, "types"
    ),
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
    "calibrate": lambda: docs_table(ALL_CALIBRATE_OPTIONS, keys=False),
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
