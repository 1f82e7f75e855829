"""Lists of names given to command-line flags.

Filters and channels go as letters or a comma list (``--filters rgb``, ``--channels r,g``);
effects and extensions as a comma list (``--effects stray_light,lens_blur``). Blank entries
are dropped. `chosen_names` is the one reading of such a flag that the commands share: a list
that names nothing, a name given twice or (where the choices are known) an unknown name is
refused with one line, rather than read as "all", done twice or failed on later.
"""

from __future__ import annotations

from collections.abc import Sequence

from rig.errors import UsageError

__all__ = ["chosen_names", "split_names"]


def split_names(spec: str, letters: bool = True) -> list[str]:
    """The names in `spec`: comma-separated (any list with a comma, or every list when not
    `letters`), else one name per letter; whitespace around names and blank entries dropped."""
    if "," in spec or not letters:
        return [s.strip() for s in spec.split(",") if s.strip()]
    return [c for c in spec if not c.isspace()]


def chosen_names(flag: str, spec: str | None, known: Sequence[str] | None = None, *, letters: bool = True,
                 what: str = "name", example: str = "rgb", where: str = "") -> list[str] | None:
    """The names `spec` gives to `flag`, in order; None when the flag was not given (the
    caller's default, usually all of `known`).

    Args:
        flag: the flag as the user typed it, for the message (``--filters``).
        spec: the flag's value, or None when it was left out.
        known: the names that may be chosen; None when the caller checks them itself.
        letters: a list without a comma is one name per letter (filters, channels).
        what: what a name names, for the message (``"filter"``).
        example: a valid value, shown in the message.
        where: what `known` comes from, for the message (``"the configuration rig.yaml"``).

    Raises:
        UsageError: the list names nothing, names a name twice, or names one not in `known`.
    """
    if spec is None:
        return None
    names = split_names(spec, letters)
    if not names:
        raise UsageError(f"{flag} {spec!r}: names nothing; give e.g. {flag} {example}, or leave the flag out for all")
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise UsageError(f"{flag} {spec!r}: {what} {twice[0]!r} is named twice; name each once")
    if known is not None:
        unknown = [n for n in names if n not in known]
        if unknown:
            src = f" ({where})" if where else ""
            raise UsageError(f"{flag} {spec!r}: unknown {what} {unknown[0]!r}; choose from {', '.join(known)}{src}")
    return names
