"""Safe output files: refuse to overwrite, write to a temporary file, then rename."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from megalut_cli.errors import MegalutError


def check_output(path: str | os.PathLike, overwrite: bool) -> Path:
    """Fail early, before any work, if ``path`` cannot be written as asked.

    That is: it exists and ``overwrite`` is false, it is a folder, its folder is missing or
    not writable (outputs are written to a temporary file beside them, then renamed).
    """
    p = Path(path)
    if p.is_dir():
        raise MegalutError(f"{p} is a directory, not a file")
    if p.exists() and not overwrite:
        raise MegalutError(f"{p} exists; use --overwrite to replace it")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise MegalutError(f"{p}: output folder {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise MegalutError(f"{p}: output folder {parent} is not writable")
    return p


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it to ``path`` only on success.

    An exception (or interrupt) inside the block removes the temporary file, so a
    failed or interrupted run never leaves a half-written output.
    """
    final = check_output(path, overwrite)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{final.name}.", suffix=".tmp", dir=final.parent or ".")
    except OSError as err:
        raise MegalutError(f"{final}: cannot write ({err.strerror or err})") from None
    os.close(fd)
    os.unlink(tmp)  # writers (fitsio, h5py) want to create the file themselves
    tmp_path = Path(tmp)
    try:
        try:
            yield tmp_path
        except OSError as err:  # e.g. disk full: name the user's file, not the hidden temporary one
            about_tmp = tmp_path.name in str(getattr(err, "filename", None) or "") or tmp_path.name in str(err)
            if not about_tmp:
                raise
            why = err.strerror or str(err).replace(str(tmp_path), str(final))
            raise MegalutError(f"{final}: cannot write ({why})") from None
        if not tmp_path.exists():
            raise MegalutError(f"internal error: nothing was written for {final}")
        if final.exists() and not overwrite:  # appeared while we worked
            raise MegalutError(f"{final} exists; use --overwrite to replace it")
        os.replace(tmp_path, final)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()
