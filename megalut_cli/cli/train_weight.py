"""`megalut train-weight` (not built yet: issue #3)."""

from __future__ import annotations

import click


@click.command("train-weight", short_help="(not built yet)", context_settings={"ignore_unknown_options": True})
@click.argument("args", nargs=-1, type=click.UNPROCESSED)
def command(args: tuple[str, ...]) -> None:
    """Not built yet (issue #3): exits with status 1."""
    raise click.ClickException("'megalut train-weight' is not built yet (issue #3)")
