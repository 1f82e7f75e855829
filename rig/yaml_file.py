"""Reading a YAML file that a user names (a rig configuration, a simulated world).

Every way such a read can fail becomes one line naming the file, what is wrong and how to
fix it, raised as the caller's own error class; the contents are checked by the caller.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml


def read_yaml(path: Path, name: str, error: type[Exception], missing: str) -> Any:
    """The parsed contents of `path` (any YAML value; the caller checks its shape).

    Args:
        path: the file.
        name: how messages name it (the path as given, or a packaged default's name).
        error: the exception class raised, with a one-line message.
        missing: what to say after "<name>: " when the file does not exist.

    Raises:
        error: the file is missing, unreadable (a directory, no permission, not UTF-8) or
            not valid YAML (the message gives the line of the first problem).
    """
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(f"{name}: {missing}") from None
    except (IsADirectoryError, PermissionError, UnicodeDecodeError) as e:
        raise error(f"{name}: cannot read ({e.__class__.__name__}); pass a readable YAML file") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        raise error(f"{name}:{where}: not valid YAML ({getattr(e, 'problem', e)})") from None
