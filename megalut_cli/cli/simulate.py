"""`megalut simulate` (not built yet: issue #2)."""

from __future__ import annotations

import click


@click.command("simulate", short_help="(not built yet)", context_settings={"ignore_unknown_options": True})
@click.argument("args", nargs=-1, type=click.UNPROCESSED)
def command(args: tuple[str, ...]) -> None:
    """Not built yet (issue #2): exits with status 1."""
    raise click.ClickException("'megalut simulate' is not built yet (issue #2)")
