"""A persistent cache of arrays on disk, shared by processes and runs (docs/engines.md).

Entries are ``.npz`` files (read without pickle) named by a hash of their key, which they
also hold: a key is the text of everything the arrays depend on. Writers go through a
temporary file and a rename, so concurrent writers of one entry and readers never see a
partial file; the folder is kept under a size bound by dropping the least recently used
entries. Any failure (unwritable folder, damaged entry) only costs the recomputation.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import logging
import os
import tempfile
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

#: Environment variable naming the cache folder; ``none`` (or empty) turns the cache off.
CACHE_ENV = "MEGALUT_CACHE"
#: The cache's size bound in bytes (least recently used entries are dropped beyond it).
MAX_BYTES = 256 * 2**20
#: The array of an entry holding its key.
_KEY_FIELD = "cache_key"


def cache_dir() -> Path | None:
    """The cache folder: ``$MEGALUT_CACHE``, else ``$XDG_CACHE_HOME/megalut`` (default
    ``~/.cache/megalut``); None when ``MEGALUT_CACHE`` is ``none`` or empty."""
    value = os.environ.get(CACHE_ENV)
    if value is not None:
        return None if value.strip().lower() in ("", "none", "off") else Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "megalut"


@functools.lru_cache(maxsize=16)
def source_digest(*paths: str | os.PathLike) -> str:
    """A short digest of the files ``paths`` (the code that builds an entry), for its key:
    any change of that code names other entries."""
    source = b"".join(Path(p).read_bytes() for p in paths)
    return hashlib.sha256(source).hexdigest()[:16]


def entry_path(kind: str, key: str, folder: Path) -> Path:
    """The file of entry ``key`` of ``kind`` in ``folder``."""
    return folder / f"{kind}-{hashlib.sha256(key.encode()).hexdigest()[:32]}.npz"


def load_arrays(kind: str, key: str) -> dict[str, np.ndarray] | None:
    """The arrays stored under ``key``, or None (absent, cache off, damaged, other key)."""
    folder = cache_dir()
    if folder is None:
        return None
    path = entry_path(kind, key, folder)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except FileNotFoundError:
        return None
    except (
        OSError,
        ValueError,
        EOFError,
        KeyError,
        zipfile.BadZipFile,
    ) as err:  # damaged: recompute
        log.debug("cache: ignoring %s (%s)", path, err)
        return None
    if str(arrays.pop(_KEY_FIELD, "")) != key:
        return None
    with contextlib.suppress(OSError):
        os.utime(path)  # recently used
    return arrays


def store_arrays(
    kind: str, key: str, arrays: Mapping[str, np.ndarray], max_bytes: int = MAX_BYTES
) -> None:
    """Store ``arrays`` under ``key`` (atomically), then bound the folder's size."""
    folder = cache_dir()
    if folder is None:
        return
    path = entry_path(kind, key, folder)
    tmp = None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=path.stem + ".", suffix=".tmp", dir=folder)
        with os.fdopen(fd, "wb") as out:
            np.savez(out, **{_KEY_FIELD: np.array(key)}, **arrays)
        os.replace(tmp, path)
        tmp = None
        prune(folder, max_bytes)
    except OSError as err:
        log.debug("cache: cannot write %s (%s)", path, err)
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)


def prune(folder: Path, max_bytes: int = MAX_BYTES) -> None:
    """Drop the least recently used entries of ``folder`` until it holds ``max_bytes`` or less."""
    entries = []
    for path in folder.glob("*.npz"):
        try:
            stat = path.stat()
        except OSError:
            continue  # removed by another process meanwhile
        entries.append((stat.st_mtime, stat.st_size, path))
    total = sum(size for _, size, _ in entries)
    for _, size, path in sorted(entries):
        if total <= max_bytes:
            break
        with contextlib.suppress(OSError):  # another process may have removed it first
            path.unlink()
        total -= size
