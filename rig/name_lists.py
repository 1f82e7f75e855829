"""Lists of names given to command-line flags.

Filters go as letters or a comma list (``--channels rgb``, ``--channels r,g``); effects and
extensions as a comma list (``--effects stray_light,lens_blur``). Blank entries are dropped,
so what a list names, or that it names nothing, is the caller's to check.
"""

from __future__ import annotations

__all__ = ["split_names"]


def split_names(spec: str, letters: bool = True) -> list[str]:
    """The names in `spec`: comma-separated (any list with a comma, or every list when not
    `letters`), else one name per letter; whitespace around names and blank entries dropped."""
    if "," in spec or not letters:
        return [s.strip() for s in spec.split(",") if s.strip()]
    return [c for c in spec if not c.isspace()]
