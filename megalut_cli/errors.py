"""Exceptions raised by the library; the CLI turns them into one-line errors."""

from __future__ import annotations

from collections.abc import Callable, Mapping


class MegalutError(Exception):
    """A runtime error with a message fit for the user (exit code 1)."""

    exit_code = 1


class ConfigError(MegalutError):
    """A configuration file or option value is invalid (exit code 2)."""

    exit_code = 2


class InputError(MegalutError):
    """An input file is missing, unreadable or lacks what is needed (exit code 1)."""

    exit_code = 1


class ArgumentError(MegalutError):
    """A problem with one argument of a library call, a message that starts with its name:
    the argument's own name here, the caller's (a command-line flag) through :meth:`named`."""

    def __init__(self, argument: str, rest: str) -> None:
        super().__init__(argument + rest)
        self.argument = argument
        self.rest = rest

    def named(self, name: str) -> str:
        return name + self.rest


class ArgumentValueError(ArgumentError, ConfigError):
    """An :class:`ArgumentError` about a value that cannot be right (exit code 2)."""


class HintError(MegalutError):
    """An error whose message suggests arguments to pass: ``template`` names them as
    ``{argument}``; the library writes ``argument=True``, a caller its own words through
    :meth:`named` (the command line: its flags)."""

    def __init__(self, template: str, *arguments: str) -> None:
        self.template = template
        self.arguments = arguments
        super().__init__(self.named({a: f"{a}=True" for a in arguments}))

    def named(self, names: Mapping[str, str]) -> str:
        return self.template.format(**{a: names.get(a, a) for a in self.arguments})


def braces_escaped(text: object) -> str:
    """``text`` fit to sit in a :class:`HintError` template."""
    return str(text).replace("{", "{{").replace("}", "}}")


class OutputExistsError(MegalutError):
    """An output exists and the caller did not allow replacing it (exit code 1); the
    message names the library's argument, the command line its ``--overwrite``."""

    def __init__(self, path: object, argument: str = "overwrite=True") -> None:
        super().__init__(f"{path} exists; pass {argument} to replace it")
        self.path = path

    def named(self, argument: str) -> str:
        """The message with the caller's name for the argument (``--overwrite``)."""
        return f"{self.path} exists; use {argument} to replace it"


#: How a caller names the library's arguments in its messages, e.g. ``{"stamp_size":
#: "--stamp-size"}`` from the command line or ``{"n_cases": "sets.tp.n_cases"}`` from a
#: pipeline file; an argument missing from it is named as it is.
Names = Mapping[str, str]


def namer(names: Names | None) -> Callable[[str], str]:
    """How messages name an argument: ``names[arg]`` if given, else the argument's own name."""
    given = dict(names or {})
    return lambda arg: given.get(arg, arg)
