"""Safe output files: refuse to overwrite, write to a temporary file, then rename."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from megalut_cli.errors import MegalutError


def check_output(path: str | os.PathLike, overwrite: bool) -> Path:
    """Fail early if ``path`` exists and ``overwrite`` is false, or its folder is missing."""
    p = Path(path)
    if p.exists() and not overwrite:
        raise MegalutError(f"{p} exists; use --overwrite to replace it")
    if p.is_dir():
        raise MegalutError(f"{p} is a directory, not a file")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise MegalutError(f"output folder {parent} does not exist")
    return p


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it to ``path`` only on success.

    An exception (or interrupt) inside the block removes the temporary file, so a
    failed or interrupted run never leaves a half-written output.
    """
    final = check_output(path, overwrite)
    fd, tmp = tempfile.mkstemp(prefix=f".{final.name}.", suffix=".tmp", dir=final.parent or ".")
    os.close(fd)
    os.unlink(tmp)  # writers (fitsio, h5py) want to create the file themselves
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if not tmp_path.exists():
            raise MegalutError(f"internal error: nothing was written for {final}")
        if final.exists() and not overwrite:  # appeared while we worked
            raise MegalutError(f"{final} exists; use --overwrite to replace it")
        os.replace(tmp_path, final)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()
