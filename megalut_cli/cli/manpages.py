"""Generate the man pages in ``man/`` from the click help: ``python -m megalut_cli.cli.manpages``.

The pages are laid out by click-man's :class:`~click_man.man.ManPage`; the help texts are
turned into roff here, since click-man copies them raw: click's ``\\b`` blocks (examples)
become no-fill blocks instead of being refilled, and ``\\``, ``-`` and lines starting
with ``.`` or ``'`` are escaped. ``pip install`` puts the pages under the environment's
``share/man/man1`` (``[tool.setuptools.data-files]`` in ``pyproject.toml``).
"""

from __future__ import annotations

import sys
import tempfile
from collections.abc import Iterator
from inspect import cleandoc
from pathlib import Path

import click

from megalut_cli import __release_date__, __version__
from megalut_cli.cli import main

#: Longest line of an example block: a man page indents it by 7 columns, and an 80-column
#: terminal must show it whole (long commands continue on the next line after ``\``).
MAX_EXAMPLE_WIDTH = 72


def roff_escape(line: str) -> str:
    """One line of text as roff prints it literally (``\\``, ``-``, leading ``.``/``'``)."""
    line = line.replace("\\", r"\e").replace("-", r"\-")
    return r"\&" + line if line.startswith((".", "'")) else line


def help_to_roff(text: str) -> str:
    """A click help text as roff: paragraphs filled, ``\\b`` blocks kept line by line."""
    out: list[str] = []
    block: list[str] = []
    verbatim = False
    for line in cleandoc(text).split("\n") + [""]:
        if line.strip() == "\b":
            verbatim = True
            continue
        if line.strip():
            block.append(line)
            continue
        if block:
            if verbatim:
                out += [".nf", *(roff_escape(b) for b in block), ".fi"]
            else:
                out += [roff_escape(b.strip()) for b in block]
            out.append("")  # click-man turns blank lines into .PP
        block, verbatim = [], False
    return "\n".join(out).rstrip("\n")


def example_blocks(text: str) -> Iterator[str]:
    """The lines of the ``\\b`` blocks of a click help text."""
    verbatim = False
    for line in cleandoc(text or "").split("\n"):
        if line.strip() == "\b":
            verbatim = True
        elif not line.strip():
            verbatim = False
        elif verbatim:
            yield line


def iter_commands(cli: click.Command, name: str = "megalut") -> Iterator[click.Context]:
    """Contexts of ``cli`` and of its subcommands (recursively), hidden ones left out."""
    ctx = click.Context(cli, info_name=name)
    stack = [ctx]
    while stack:
        ctx = stack.pop(0)
        yield ctx
        for sub_name, sub in subcommands(ctx):
            stack.append(click.Context(sub, info_name=sub_name, parent=ctx))


def subcommands(ctx: click.Context) -> list[tuple[str, click.Command]]:
    """The visible subcommands of a group (loaded), in its order; none for a command."""
    group = ctx.command
    if not isinstance(group, click.Group):
        return []
    found = ((name, group.get_command(ctx, name)) for name in group.list_commands(ctx))
    return [(name, sub) for name, sub in found if sub is not None and not sub.hidden]


def man_page(ctx: click.Context) -> str:
    """The roff source of the man page of ``ctx.command``."""
    from click_man.core import get_short_help_str
    from click_man.man import ManPage

    page = ManPage(ctx.command_path)
    page.version = __version__
    page.date = __release_date__
    page.short_help = roff_escape(get_short_help_str(ctx.command))
    page.description = help_to_roff(ctx.command.help or "")
    page.synopsis = " ".join(ctx.command.collect_usage_pieces(ctx))
    page.options = []
    for param in ctx.command.params:
        if isinstance(param, click.Option) and not param.hidden:
            record = param.get_help_record(ctx)
            if record is not None:
                page.options.append((record[0], roff_escape(record[1])))
    commands = subcommands(ctx)
    if commands:
        page.commands = [(k, roff_escape(get_short_help_str(v))) for k, v in commands]
    # no hyphenation, ragged right: option names and paths stay whole
    title, rest = str(page).split("\n", 1)
    return f"{title}\n.nh\n.ad l\n{rest}"


def generate(target: str | Path) -> list[Path]:
    """Write ``megalut.1`` and one ``megalut-<command>.1`` per subcommand into ``target``."""
    target = Path(target)
    target.mkdir(parents=True, exist_ok=True)
    written = []
    with tempfile.TemporaryDirectory(dir=target) as tmp:
        for ctx in iter_commands(main):
            name = ctx.command_path.replace(" ", "-") + ".1"
            staged = Path(tmp) / name
            staged.write_text(man_page(ctx))
            written.append((staged, target / name))
        for staged, dest in written:
            staged.replace(dest)
    return [dest for _, dest in written]


if __name__ == "__main__":
    out = sys.argv[1] if len(sys.argv) > 1 else "man"
    for p in generate(out):
        print(p)
