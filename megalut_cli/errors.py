"""Exceptions raised by the library; the CLI turns them into one-line errors."""


class MegalutError(Exception):
    """A runtime error with a message fit for the user (exit code 1)."""

    exit_code = 1


class ConfigError(MegalutError):
    """A configuration file or option value is invalid (exit code 2)."""

    exit_code = 2


class InputError(MegalutError):
    """An input file is missing, unreadable or lacks what is needed (exit code 1)."""

    exit_code = 1
