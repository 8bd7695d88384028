"""Safe outputs: refuse to overwrite, write to a temporary file or folder, then rename."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from megalut_cli.errors import MegalutError, OutputExistsError
from megalut_cli.schema import Option

#: ``--overwrite``: whether an existing output may be replaced.
OVERWRITE_OPTION = Option("overwrite", "bool", False, "Replace the output file if it exists.")


def check_output(path: str | os.PathLike, overwrite: bool) -> Path:
    """Fail early, before any work, if ``path`` cannot be written as asked.

    That is: it exists and ``overwrite`` is false, it is a folder, its folder is missing or
    no file can be created in it (outputs are written to a temporary file beside them, then
    renamed).
    """
    p = Path(path)
    if p.is_dir():
        raise MegalutError(f"{p} is a directory, not a file")
    if p.exists() and not overwrite:
        raise OutputExistsError(p)
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise MegalutError(f"{p}: output folder {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise MegalutError(f"{p}: output folder {parent} is not writable")
    # Permission bits do not tell everything (root, read-only or virtual file systems such
    # as /sys): create the temporary file the writer would create, and remove it.
    try:
        fd, probe = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=parent)
    except OSError as err:
        raise MegalutError(f"{p}: cannot write in {parent} ({err.strerror or err})") from None
    os.close(fd)
    os.unlink(probe)
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
            about_tmp = tmp_path.name in str(
                getattr(err, "filename", None) or ""
            ) or tmp_path.name in str(err)
            if not about_tmp:
                raise
            why = err.strerror or str(err).replace(str(tmp_path), str(final))
            raise MegalutError(f"{final}: cannot write ({why})") from None
        if not tmp_path.exists():
            raise MegalutError(f"internal error: nothing was written for {final}")
        if final.exists() and not overwrite:  # appeared while we worked
            raise OutputExistsError(final)
        os.replace(tmp_path, final)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_json(path: str | os.PathLike, obj: Any, overwrite: bool = False) -> None:
    """Write ``obj`` as indented JSON (no NaN), atomically."""
    with atomic_output(path, overwrite) as tmp:
        tmp.write_text(json.dumps(obj, indent=1, allow_nan=False) + "\n")


def replace_folder(tmp: Path, final: Path) -> None:
    """Move the finished folder ``tmp`` to ``final``, replacing an older one whole."""
    old = None
    if final.exists():
        old = final.with_name(f".{final.name}.old-{os.getpid()}")
        os.replace(final, old)
    os.replace(tmp, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def move_into_folder(tmp: Path, final: Path) -> None:
    """Move the finished folder ``tmp`` to ``final``, replacing same-named files of an existing
    one."""
    if not final.exists():
        os.replace(tmp, final)
        return
    for src in sorted(tmp.rglob("*")):
        dest = final / src.relative_to(tmp)
        if src.is_dir():
            dest.mkdir(exist_ok=True)
        else:
            os.replace(src, dest)
    shutil.rmtree(tmp)
