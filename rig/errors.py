"""Errors and exit statuses of the command-line layer."""

#: Exit status of a run stopped by Ctrl-C or SIGTERM (128 + SIGINT, as shells report it).
EXIT_INTERRUPTED = 130


class UsageError(ValueError):
    """Raised for bad user input: configuration files, command arguments, paths.

    The message is one line that says what is wrong, where, and how to fix it.
    """
