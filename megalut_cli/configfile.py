"""Config files: reading TOML, applying dotted ``key=value`` overrides, and naming a key of an
error message where the user wrote it (simulation and pipeline files)."""

from __future__ import annotations

import copy
import hashlib
import os
import re
import sys
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from megalut_cli.errors import ConfigError, InputError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib


def parse_override(text: str) -> tuple[list[str], Any]:
    """``"galaxy.rad.max=6"`` -> (["galaxy", "rad", "max"], 6); values are TOML values
    (``psf.type=moffat`` gives the string ``"moffat"``)."""
    if "=" not in text:
        raise ConfigError(f"override {text!r}: expected KEY=VALUE (e.g. noise.sigma=0.5)")
    key, value = text.split("=", 1)
    key = key.strip()
    parts = key.split(".")
    if not key or any(not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_-]*", p) for p in parts):
        raise ConfigError(f"override {text!r}: bad key {key!r} (expected dotted names)")
    value = value.strip()
    try:
        parsed = tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        parsed = value  # bare words are strings
    return parts, parsed


def apply_overrides(raw: dict[str, Any], overrides: Sequence[str]) -> dict[str, Any]:
    """Return a copy of ``raw`` with dotted ``key=value`` overrides applied."""
    out = copy.deepcopy(raw)
    for text in overrides:
        parts, value = parse_override(text)
        node = out
        for i, p in enumerate(parts[:-1]):
            child = node.get(p)
            if child is None:
                child = node[p] = {}
            if not isinstance(child, dict):
                where = ".".join(parts[: i + 1])
                raise ConfigError(f"override {text!r}: {where} is not a table")
            node = child
        node[parts[-1]] = value
    return out


def read_toml(path: str | os.PathLike) -> tuple[dict[str, Any], str]:
    """Parse a TOML file; return ``(data, sha256 of its bytes)``."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    data = p.read_bytes()
    try:
        raw = tomllib.loads(data.decode("utf-8"))
    except UnicodeDecodeError:
        raise ConfigError(f"{p}: not a text (UTF-8) TOML file") from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{p}: invalid TOML ({err})") from None
    return raw, hashlib.sha256(data).hexdigest()


# --------------------------------------------------------------------------- where a key is written
#: A dotted key at the start of a message (``sets.tp``, ``noise.sigam``, ``sets.*.config``).
MESSAGE_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_-]*(?:\.[A-Za-z0-9_*-]+)*")
#: A table header line of a TOML file (``[simulation.noise]``); arrays of tables are not headers
#: here.
_HEADER = re.compile(r"^\s*\[(?!\[)\s*([^\[\]]+?)\s*\]\s*(?:#.*)?$")


@dataclass(frozen=True)
class ConfigSource:
    """A config file as the user wrote it: how to name it, its table and its text."""

    name: str
    raw: Mapping[str, Any]
    text: str


def config_source(path: str | os.PathLike, name: str | None = None) -> ConfigSource | None:
    """The TOML file ``path`` as a :class:`ConfigSource` named ``name`` (default: ``path`` as
    given); None when it cannot be read."""
    try:
        text = Path(path).read_text()
        raw = tomllib.loads(text)
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return None
    return ConfigSource(str(path) if name is None else name, raw, text)


def _headers(text: str) -> set[tuple[str, ...]]:
    out = set()
    for line in text.splitlines():
        m = _HEADER.match(line)
        if m:
            out.add(tuple(p.strip().strip("\"'") for p in m.group(1).split(".")))
    return out


def table_key(text: str, parts: Sequence[str]) -> str:
    """``parts`` as the file ``text`` writes it: under its deepest table header
    (``[simulation.noise] sigam``), a table by its header (``[pretrain]``), else dotted."""
    headers = _headers(text)
    if tuple(parts) in headers:
        return f"[{'.'.join(parts)}]"
    for i in range(len(parts) - 1, 0, -1):
        if tuple(parts[:i]) in headers:
            return f"[{'.'.join(parts[:i])}] {'.'.join(parts[i:])}"
    return ".".join(parts)


def has_key(raw: Any, parts: Sequence[str]) -> bool:
    """Whether the nested tables ``raw`` hold the dotted key ``parts``."""
    for p in parts:
        if not isinstance(raw, Mapping) or p not in raw:
            return False
        raw = raw[p]
    return True


def override_for(parts: Sequence[str], overrides: Sequence[str]) -> str | None:
    """The last ``KEY=VALUE`` override that sets ``parts``, a table above it or a part of its
    value (``galaxy.rad.min=-1`` for ``galaxy.rad``)."""
    for text in reversed(overrides):
        try:
            key, _ = parse_override(text)
        except ConfigError:
            continue
        n = min(len(key), len(parts))
        if list(parts[:n]) == key[:n]:
            return text
    return None


def written_at(
    parts: Sequence[str], sources: Sequence[ConfigSource], overrides: Sequence[str]
) -> str | None:
    """Where ``parts`` is given: the dotted key of a ``KEY=VALUE`` override (as the command line
    writes it), else ``FILE: [table] key`` of the first source that has it; None if nowhere."""
    if override_for(parts, overrides) is not None:
        return ".".join(parts)
    for src in sources:
        if has_key(src.raw, parts):
            return f"{src.name}: {table_key(src.text, parts)}"
    return None


def message_keys(
    message: str, top: Collection[str], names: Collection[str] = ()
) -> tuple[list[str], str]:
    """The dotted keys that ``message`` starts with (``sets.tp: noise.sigam: unknown key`` ->
    ``(["sets.tp", "noise.sigam"], "unknown key")``), the first one a key of ``top``; none when
    the message starts with one of ``names`` (a file's name)."""
    keys: list[str] = []
    rest = message
    if any(message.startswith(f"{n}: ") for n in names):
        return keys, message
    while True:
        head, sep, tail = rest.partition(": ")
        if (
            not sep
            or not MESSAGE_KEY.fullmatch(head)
            or (not keys and head.split(".")[0] not in top)
        ):
            break
        keys.append(head)
        rest = tail
    return keys, rest


def where_written(
    message: str,
    sources: Sequence[ConfigSource],
    overrides: Sequence[str] = (),
    top: Collection[str] | None = None,
) -> str:
    """A config error ``message`` (``galaxy.rad: ... must be > 0``) naming its key where the user
    wrote it: the override (``galaxy.rad``), else the file and its table (``tp.toml: [galaxy]
    rad: ... must be > 0``), the first of ``sources`` when none gives it. ``top``: the
    top-level keys a message may start with (default: those of the first source). ``message``
    is returned as it is when it starts with no such key."""
    if not sources:
        return message
    keys, rest = message_keys(
        message, set(sources[0].raw) if top is None else top, [s.name for s in sources]
    )
    if not keys:
        return message
    parts = ".".join(keys).split(".")
    found = written_at(parts, sources, overrides)
    if found is None and "*" not in parts:
        found = f"{sources[0].name}: {table_key(sources[0].text, parts)}"
    return message if found is None else f"{found}: {rest}"
