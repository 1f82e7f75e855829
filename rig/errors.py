"""Errors of the command-line layer."""


class UsageError(ValueError):
    """Raised for bad user input: configuration files, command arguments, paths.

    The message is one line that says what is wrong, where, and how to fix it.
    """
