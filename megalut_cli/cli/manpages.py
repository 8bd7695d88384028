"""Generate the man pages in ``man/`` from the click help: ``python -m megalut_cli.cli.manpages``."""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from megalut_cli import __release_date__, __version__


def generate(target: str | Path) -> list[Path]:
    """Write ``megalut.1`` and one ``megalut-<command>.1`` per subcommand into ``target``."""
    from click_man.core import write_man_pages

    from megalut_cli.cli import main

    target = Path(target)
    target.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        write_man_pages("megalut", main, version=__version__, target_dir=tmp, date=__release_date__)
        written = []
        for page in sorted(Path(tmp).glob("*.1")):
            dest = target / page.name
            dest.write_text(page.read_text())
            written.append(dest)
    return written


if __name__ == "__main__":
    out = sys.argv[1] if len(sys.argv) > 1 else "man"
    for p in generate(out):
        print(p)
