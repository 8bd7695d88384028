"""Options declared once, and the one vocabulary that checks config-file values.

Every config file (simulation, pipeline, GREAT3 pipeline, PSF specs, distributions) checks
its values with the ``check_*`` functions and :class:`Table`, so that a value means the
same thing everywhere and every problem is one :class:`~megalut_cli.errors.ConfigError`
naming the key. The rules:

- an integer may be written ``100`` or ``100.0`` (a float with an integer value);
- a number is an integer or a float, finite; ``true``/``false`` are not numbers;
- a relative path is relative to the file that names it (:func:`resolve_path`).

An :class:`Option` declares one option (name, type, default, range or choices, help); the
click options (``megalut_cli.cli.options.click_options``), the checks of config tables
(:meth:`Table.option`), the library's defaults and the tables of ``docs/`` come from it.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from megalut_cli.errors import ConfigError, InputError

#: Value kinds of an :class:`Option`.
KINDS = (
    "int",
    "float",
    "str",
    "bool",
    "choice",
    "str_list",
    "int_list",
    "choice_list",
    "path",
    "table",
)
#: Value kinds the reader of a table parses itself: a number or a distribution table
#: (``dist``, :mod:`megalut_cli.sim.distributions`), an expression over the columns of a
#: catalog (``expr``, :mod:`megalut_cli.expr`).
KINDS += ("dist", "expr")
#: Kinds whose values :func:`check_params` leaves to the reader (a path is resolved beside
#: the file that names it, :func:`resolve_path`).
READER_KINDS = ("dist", "expr", "path")

#: Where, in an option's help text, the command line shows its computed default
#: (``[default: ...]``, from ``default_text``); without it, the note goes at the end.
DEFAULT_MARK = "{default}"


def _is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def check_int(value: Any, key: str, minimum: int | None = None, maximum: int | None = None) -> int:
    """An integer (``3`` or ``3.0``), within ``[minimum, maximum]`` when given."""
    if not _is_number(value) or not (
        isinstance(value, numbers.Integral) or float(value).is_integer()
    ):
        raise ConfigError(f"{key}: expected an integer, got {value!r}")
    out = int(value)
    if minimum is not None and out < minimum:
        raise ConfigError(f"{key}: must be >= {minimum}, got {out}")
    if maximum is not None and out > maximum:
        raise ConfigError(f"{key}: must be <= {maximum}, got {out}")
    return out


def interval_text(
    lo: float | None, hi: float | None, lo_open: bool = False, hi_open: bool = False
) -> str:
    """``[0, 1)``, ``> 0``, ``<= 1``: the allowed range of a number, as messages and docs write
    it."""
    if lo is not None and hi is not None:
        return f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if lo is not None:
        return f"{'>' if lo_open else '>='} {lo:g}"
    if hi is not None:
        return f"{'<' if hi_open else '<='} {hi:g}"
    return "any"


def check_float(
    value: Any,
    key: str,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    hi_open: bool = False,
) -> float:
    """A finite number; within the range ``lo``..``hi`` (open ends when told) when given.

    With both ends the message names the interval (``must be in (0, 1]``), else the bound
    (``must be > 0``).
    """
    if not _is_number(value):
        raise ConfigError(f"{key}: expected a number, got {value!r}")
    out = float(value)
    if not math.isfinite(out):
        raise ConfigError(f"{key}: must be a finite number, got {value!r}")
    below = lo is not None and (out <= lo if lo_open else out < lo)
    above = hi is not None and (out >= hi if hi_open else out > hi)
    if below or above:
        interval = interval_text(lo, hi, lo_open, hi_open)
        where = f"in {interval}" if lo is not None and hi is not None else interval
        raise ConfigError(f"{key}: must be {where}, got {value!r}")
    return out


def check_choice(value: Any, key: str, choices: Sequence[str]) -> str:
    """One of ``choices``."""
    if not isinstance(value, str) or value not in choices:
        raise ConfigError(f"{key}: unknown value {value!r} (expected one of {', '.join(choices)})")
    return value


def check_bool(value: Any, key: str) -> bool:
    """``true`` or ``false``."""
    if not isinstance(value, bool):
        raise ConfigError(f"{key}: expected true or false, got {value!r}")
    return value


def check_str(value: Any, key: str, allow_empty: bool = False) -> str:
    """A non-empty string (or any string, with ``allow_empty``)."""
    if not isinstance(value, str) or not (allow_empty or value.strip()):
        raise ConfigError(
            f"{key}: expected a {'' if allow_empty else 'non-empty '}string, got {value!r}"
        )
    return value


def check_str_list(value: Any, key: str, allow_empty: bool = False) -> list[str]:
    """A list of distinct names (or one comma-separated string of them)."""
    if isinstance(value, str):
        value = [s.strip() for s in value.split(",") if s.strip()]
    if not isinstance(value, (list, tuple)) or not all(isinstance(s, str) and s for s in value):
        raise ConfigError(f"{key}: expected a list of names, got {value!r}")
    if not value and not allow_empty:
        raise ConfigError(f"{key}: the list is empty")
    dup = sorted({s for s in value if list(value).count(s) > 1})
    if dup:
        raise ConfigError(f"{key}: {dup[0]!r} given twice")
    return list(value)


def check_int_list(value: Any, key: str) -> list[int]:
    """A non-empty list of positive integers (or one integer)."""
    if isinstance(value, int) and not isinstance(value, bool):
        value = [value]
    if (
        not isinstance(value, (list, tuple))
        or not value
        or not all(isinstance(i, int) and not isinstance(i, bool) and i > 0 for i in value)
    ):
        raise ConfigError(f"{key}: expected a list of positive integers, got {value!r}")
    return list(value)


def check_choice_list(value: Any, key: str, choices: Sequence[str]) -> list[str]:
    """A list (possibly empty) of ``choices``, or one of them as a string."""
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise ConfigError(f"{key}: expected a list of names")
    return [check_choice(v, key, choices) for v in value]


def check_table(
    value: Any, key: str, allowed: set[str] | None = None, required: bool = False
) -> dict[str, Any]:
    """A table (``None``: an empty one, unless ``required``) whose keys are all in ``allowed``
    when given."""
    if value is None:
        if required:
            raise ConfigError(f"{key}: missing [{key}] table")
        return {}
    if not isinstance(value, Mapping):
        raise ConfigError(f"{key}: expected a table, got {value!r}")
    if allowed is not None:
        unknown = sorted(set(value) - allowed)
        if unknown:
            where = f"{key}.{unknown[0]}" if key else unknown[0]
            raise ConfigError(f"{where}: unknown key (allowed: {', '.join(sorted(allowed))})")
    return dict(value)


def resolve_path(text: Any, key: str, base: str | Path | None, folder: bool = False) -> Path:
    """The existing file (or ``folder``) that ``text`` names, absolute.

    The one rule for relative paths: relative to the folder ``base`` of the file that names
    them, then to the current folder (where ``KEY=VALUE`` overrides given on the command
    line are meant). ``~`` is expanded. A missing one is an :class:`InputError`.
    """
    what = "folder" if folder else "file"
    if not isinstance(text, str) or not text:
        raise ConfigError(f"{key}: expected a {what} path")
    path = Path(text).expanduser()
    if path.is_absolute():
        candidates = [path]
    else:
        candidates = ([Path(base) / path] if base is not None else []) + [Path.cwd() / path]
    for candidate in candidates:
        if candidate.is_dir() if folder else candidate.is_file():
            return candidate.resolve()
    where = (
        ""
        if path.is_absolute()
        else " (looked beside the file that names it and in the current folder)"
    )
    raise InputError(f"{key}: no such {what} {text!r}{where}")


def resolve_beside(text: Any, key: str, config_path: str | Path, folder: bool = False) -> Path:
    """:func:`resolve_path` for a path named in the file ``config_path``."""
    return resolve_path(text, key, Path(config_path).resolve().parent, folder)


@dataclass(frozen=True)
class Option:
    """One option, declared once: its config key, value kind, default, range or choices,
    and help text. ``flag`` is its command-line name (default ``--`` + the key with
    dashes; ``--x/--no-x`` for an on/off pair), ``short`` a one-letter alias (``-j``),
    ``envvar`` an environment variable that sets it; ``default_text`` replaces the default
    in help texts when it is computed (placed at :data:`DEFAULT_MARK` in ``help`` if the
    text has one)."""

    name: str
    kind: str
    default: Any
    help: str
    minimum: float | None = None
    maximum: float | None = None
    min_open: bool = False
    max_open: bool = False
    choices: tuple[str, ...] = ()
    flag: str = ""
    metavar: str | None = None
    default_text: str | None = None
    #: The allowed values as docs write them, when a check beyond the declared range (one
    #: depending on another key) is made where the option is read.
    allowed_text: str | None = None
    #: Whether a list (or a string) may be empty.
    empty_ok: bool = False
    short: str = ""
    envvar: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"option {self.name}: unknown kind {self.kind!r}")
        if self.kind in ("choice", "choice_list") and not self.choices:
            raise ValueError(f"option {self.name}: a choice needs choices")

    @property
    def cli_flag(self) -> str:
        return self.flag or "--" + self.name.replace("_", "-")

    def cli_help(self) -> str:
        """The help text of the command line: ``help`` with the computed default noted."""
        note = "" if self.default_text is None else f" [default: {self.default_text}]"
        if DEFAULT_MARK in self.help:
            return self.help.replace(DEFAULT_MARK, note)
        return self.help + note

    def doc_help(self) -> str:
        """The help text of docs tables (whose default column says the default)."""
        return self.help.replace(DEFAULT_MARK, "")

    def with_default(self, default: Any, default_text: str | None = None) -> Option:
        """The same option with another default (e.g. per command)."""
        return replace(self, default=default, default_text=default_text)

    def check(self, value: Any, key: str) -> Any:
        """``value`` checked (and converted) for the config key ``key``."""
        if value is None:
            return None
        if self.kind == "int":
            lo = None if self.minimum is None else int(self.minimum)
            hi = None if self.maximum is None else int(self.maximum)
            return check_int(value, key, lo, hi)
        if self.kind == "float":
            return check_float(value, key, self.minimum, self.maximum, self.min_open, self.max_open)
        if self.kind == "choice":
            return check_choice(value, key, self.choices)
        if self.kind == "choice_list":
            return check_choice_list(value, key, self.choices)
        if self.kind == "bool":
            return check_bool(value, key)
        if self.kind == "str":
            return check_str(value, key, self.empty_ok)
        if self.kind == "path":  # resolved by the reader (resolve_path), beside the file
            return check_str(value, key)
        if self.kind == "table":
            return check_table(value, key)
        if self.kind in ("dist", "expr"):  # parsed by the reader
            return value
        if self.kind == "str_list":
            return check_str_list(value, key, self.empty_ok)
        return check_int_list(value, key)

    def range_text(self) -> str:
        """What values are allowed, for docs tables."""
        if self.allowed_text is not None:
            return self.allowed_text
        if self.kind in ("choice", "choice_list"):
            return ", ".join(f"`{c}`" for c in self.choices)
        if self.kind in ("int", "float"):
            return interval_text(self.minimum, self.maximum, self.min_open, self.max_open)
        return {
            "bool": "true, false",
            "str": "text",
            "str_list": "names",
            "int_list": "positive integers",
            "path": "a path",
            "table": "a table",
            "dist": "*dist*",
            "expr": "an expression",
        }[self.kind]

    def default_repr(self) -> str:
        """The default as a docs table writes it."""
        if self.default_text is not None:
            return self.default_text
        if self.default is None:
            return "none"
        if isinstance(self.default, (list, tuple)):
            return (
                "["
                + ", ".join(f'"{v}"' if isinstance(v, str) else str(v) for v in self.default)
                + "]"
            )
        if isinstance(self.default, str):
            return f'"{self.default}"'
        if isinstance(self.default, bool):
            return "true" if self.default else "false"
        return str(self.default)


def docs_table(
    options: Sequence[Option], cli: bool = True, keys: bool = True, prefix: str = ""
) -> str:
    """A Markdown table of ``options``: config key (``prefix`` + name; none unless ``keys``: a
    command's options), flag (when ``cli``), default, allowed values, meaning."""
    head = ["key"] * keys + ["option"] * cli + ["default", "allowed", "meaning"]
    rows = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for o in options:
        flags = f"`{o.short}`, `{o.cli_flag}`" if o.short else f"`{o.cli_flag}`"
        cells = [f"`{prefix}{o.name}`"] * keys + [flags] * cli
        cells += [o.default_repr(), o.range_text(), o.doc_help().replace("|", "\\|")]
        rows.append("| " + " | ".join(cells) + " |")
    return "\n".join(rows)


def kinds_table(common: Sequence[Option], kinds: Mapping[str, Sequence[Option]], head: str) -> str:
    """A Markdown table of the keys of a table whose ``type`` (or ``profile``) picks a kind
    (PSF types, noise types, galaxy profiles): the ``common`` keys, then one row per key
    declaration naming the kinds (in column ``head``) that take it, a key's declarations
    together: key, kinds, default, allowed values, meaning."""
    entries: list[tuple[Option, list[str]]] = []
    for name, options in kinds.items():
        for o in options:
            same = next((names for declared, names in entries if declared == o), None)
            if same is None:
                entries.append((o, [name]))
            else:
                same.append(name)
    order = list(dict.fromkeys(o.name for o, _ in entries))
    entries.sort(key=lambda entry: order.index(entry[0].name))
    rows = [f"| key | {head} | default | allowed | meaning |", "|---|---|---|---|---|"]
    for o, names in [(o, ["all"]) for o in common] + entries:
        which = ", ".join(n if n == "all" else f"`{n}`" for n in names)
        meaning = o.doc_help().replace("|", "\\|")
        cells = [f"`{o.name}`", which, o.default_repr(), o.range_text(), meaning]
        rows.append("| " + " | ".join(cells) + " |")
    return "\n".join(rows)


@dataclass(frozen=True)
class Required:
    """A key that must be given; ``why`` is said when it is missing (``KEY: missing (WHY)``)."""

    name: str
    why: str


@dataclass(frozen=True)
class OneOf:
    """Keys of which exactly one must be given; ``text`` is said when not, naming the first
    (``KEY: TEXT``, where ``{got}`` stands for the keys given, or ``none``)."""

    names: tuple[str, ...]
    text: str


def check_params(
    data: Mapping[str, Any],
    where: str,
    options: Sequence[Option],
    rules: Sequence[Required | OneOf] = (),
    refuse: Callable[[str], str] | None = None,
) -> dict[str, Any]:
    """The one check of a config table's keys and values (GalSim's ``GetAllParams``).

    Every key of ``data`` must be one of ``options`` (``refuse(key)`` says why another is
    not taken; without it, an unknown key), the ``rules`` must hold, in their order, and
    every value given is checked by its option (those of :data:`READER_KINDS` are left to
    the reader). Returns the value of every option, its default where not given. Errors
    name ``where.KEY``.
    """

    def key(name: str) -> str:
        return f"{where}.{name}" if where else name

    names = [o.name for o in options]
    foreign = sorted(set(data) - set(names))
    if foreign:
        if refuse is not None:
            why = refuse(foreign[0])
        else:
            why = f"unknown key (allowed: {', '.join(sorted(names))})"
        raise ConfigError(f"{key(foreign[0])}: {why}")
    for rule in rules:
        if isinstance(rule, Required):
            if rule.name not in data:
                raise ConfigError(f"{key(rule.name)}: missing ({rule.why})")
            continue
        given = [k for k in rule.names if k in data]
        if len(given) != 1:
            got = ", ".join(given) or "none"
            raise ConfigError(f"{key(rule.names[0])}: " + rule.text.format(got=got))
    out: dict[str, Any] = {}
    for o in options:
        if o.name in data and o.kind not in READER_KINDS:
            out[o.name] = o.check(data[o.name], key(o.name))
        else:
            out[o.name] = data.get(o.name, o.default)
    return out


class Table:
    """Typed, key-checked access to one table of a config file (errors name the key)."""

    def __init__(self, data: Any, where: str, allowed: set[str] | None = None) -> None:
        self.data = check_table(data, where, allowed)
        self.where = where

    def key(self, name: str) -> str:
        return f"{self.where}.{name}" if self.where else name

    def option(self, option: Option, default: Any = None) -> Any:
        """The value of ``option`` (its default, or ``default`` when given, if absent)."""
        fallback = option.default if default is None else default
        return option.check(self.data.get(option.name, fallback), self.key(option.name))

    def get_int(
        self, name: str, default: int | None, minimum: int, maximum: int | None = None
    ) -> int | None:
        v = self.data.get(name, default)
        return None if v is None else check_int(v, self.key(name), minimum, maximum)

    def get_float(
        self,
        name: str,
        default: float,
        lo: float | None = None,
        hi: float | None = None,
        lo_open: bool = False,
        hi_open: bool = False,
    ) -> float:
        return check_float(self.data.get(name, default), self.key(name), lo, hi, lo_open, hi_open)

    def get_str(
        self, name: str, default: str | None, choices: Sequence[str] | None = None
    ) -> str | None:
        v = self.data.get(name, default)
        if v is None:
            return None
        v = check_str(v, self.key(name))
        return v if choices is None else check_choice(v, self.key(name), choices)

    def get_bool(self, name: str, default: bool) -> bool:
        return check_bool(self.data.get(name, default), self.key(name))

    def get_str_list(
        self, name: str, default: Sequence[str] | None, allow_empty: bool = False
    ) -> list[str] | None:
        v = self.data.get(name, default)
        return None if v is None else check_str_list(v, self.key(name), allow_empty)

    def get_int_list(self, name: str, default: Sequence[int]) -> list[int]:
        return check_int_list(self.data.get(name, default), self.key(name))
