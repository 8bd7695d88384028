"""Provenance recorded in every output: software versions, command line, dates."""

from __future__ import annotations

import datetime as _dt
import hashlib
import os
import shlex
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from megalut_cli import __version__

CREATOR = f"megalut {__version__}"


def utc_now() -> str:
    """Current UTC time in ISO format (``SOURCE_DATE_EPOCH`` is honoured for reproducible files)."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    if epoch is not None:
        when = _dt.datetime.fromtimestamp(int(epoch), tz=_dt.timezone.utc)
    else:
        when = _dt.datetime.now(tz=_dt.timezone.utc)
    return when.replace(microsecond=0, tzinfo=None).isoformat()


_COMMAND: list[str] | None = None


def set_command_line(argv: list[str]) -> None:
    """Record the command being run (the CLI calls this; defaults to ``sys.argv``)."""
    global _COMMAND
    _COMMAND = list(argv)


def command_line() -> str:
    """The command line of this process, as a shell-quoted string."""
    if _COMMAND is not None:
        argv = _COMMAND
    else:
        argv = [Path(sys.argv[0]).name if sys.argv else "python", *sys.argv[1:]]
    return " ".join([argv[0], *(shlex.quote(a) for a in argv[1:])])


def software_versions() -> dict[str, str]:
    """Versions of the libraries that shape results."""
    import importlib.metadata  # 20 ms: only where provenance is written

    versions = {"megalut": __version__, "python": sys.version.split()[0]}
    for name in ("numpy", "scipy", "galsim", "astropy", "fitsio", "h5py"):
        mod = sys.modules.get(name)
        if mod is not None:
            versions[name] = getattr(mod, "__version__", "unknown")
            continue
        try:  # the installed distribution's version: no import (GalSim's costs 0.5 s)
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:  # pragma: no cover - all are dependencies
            continue
    return versions


def own_or_parent(provenance: Mapping[str, Any], key: str) -> Mapping[str, Any] | None:
    """The non-empty mapping a provenance record holds under ``key`` (a model's: what its own
    training recorded), else its ``parent``'s (a weight-trained model's: its point
    training's); None when neither holds one."""
    for record in (provenance, provenance.get("parent")):
        if isinstance(record, Mapping) and isinstance(record.get(key), Mapping) and record[key]:
            return record[key]
    return None


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """Hex sha256 digest of a file."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def recorded_path(path: str | os.PathLike, base: str | os.PathLike | None = None) -> str:
    """How provenance names a file, without the absolute paths of this machine: relative to
    ``base`` (a pipeline's work folder) when the file is inside it, else relative to the
    current folder when inside that, else its name alone (its sha256, recorded beside it,
    identifies it)."""
    p = Path(os.path.abspath(path))
    for folder in ([Path(os.path.abspath(base))] if base is not None else []) + [Path.cwd()]:
        try:
            return p.relative_to(folder).as_posix()
        except ValueError:
            continue
    return p.name


def shown_path(recorded: str) -> str:
    """A recorded path as ``megalut info`` shows it: as recorded, but an absolute path (of
    the machine that made the file, in files made before :func:`recorded_path`) by its name."""
    text = str(recorded)
    return (Path(text).name or text) if os.path.isabs(text) or text.startswith("~") else text


def shown_command(argv: str) -> str:
    """A recorded command line as ``megalut info`` shows it: every absolute path in it (an
    argument, or the value of ``--opt=/path``) by its name (:func:`shown_path`)."""
    try:
        args = shlex.split(str(argv))
    except ValueError:
        return str(argv)

    def shown(arg: str) -> str:
        key, sep, value = arg.partition("=")
        if sep and key.startswith("-") and value:
            return f"{key}={shown_path(value)}"
        return shown_path(arg)

    return " ".join([args[0], *(shlex.quote(shown(a)) for a in args[1:])]) if args else str(argv)
