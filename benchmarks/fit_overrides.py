"""`--setting KEY=VALUE` for the benchmarks: FitSettings fields changed for a trial.

    overrides = parse_overrides(args.setting)        # ValueError: one line for the user
    settings = settings_with(overrides, seed=0, scale="calibrated")
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from estimate.fit import FitSettings


def parse_overrides(items: Iterable[str]) -> dict[str, Any]:
    """KEY=VALUE strings as a dict (values parsed as JSON, else kept as text).

    Raises:
        ValueError: an item without '=', or a key that is no FitSettings field.
    """
    from estimate.fit import FitSettings

    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--setting {item!r}: give KEY=VALUE, e.g. polish_steps=4")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    unknown = set(out) - set(FitSettings().to_dict())
    if unknown:
        raise ValueError(f"--setting: no fit setting named {', '.join(sorted(unknown))}")
    return out


def settings_with(overrides: dict[str, Any], **base: Any) -> FitSettings:
    """`FitSettings.for_variant(**base)` (what `rig estimate` starts from on this machine) with
    the overrides applied and checked as `FitSettings.from_dict` checks a results file (a bad
    value raises `ModelParameterError`, one line)."""
    from estimate.fit import FitSettings

    return FitSettings.from_dict({**FitSettings.for_variant(**base).to_dict(), **overrides}, where="--setting")


def overrides_tag(overrides: dict[str, Any]) -> str:
    """A file-name part naming the overrides ('' for none): `_final_spp-8192_polish_steps-4`."""
    return "".join(f"_{k}-{json.dumps(v) if not isinstance(v, str) else v}" for k, v in sorted(overrides.items()))
