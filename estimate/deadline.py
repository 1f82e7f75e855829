"""A fit's wall-clock budget (`FitSettings.time_limit_s`), shared by its stages.

The stochastic iterations, the Gauss-Newton polish and the Levenberg-Marquardt polish each
ask `Deadline.passed()` before starting another unit of work (an iteration, a step), so a
fit ends within about one unit's time of its budget; the final evaluation and the
uncertainties still run, since a result without them would be no result.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

__all__ = ["Deadline"]


@dataclass
class Deadline:
    """`at`: the time.monotonic() (s) after which no new unit of work starts (None: no
    limit). `hit` names the stages that stopped on it, in order."""

    at: float | None = None
    hit: list[str] = field(default_factory=list)

    @classmethod
    def after(cls, seconds: float | None, start: float | None = None) -> Deadline:
        """The deadline `seconds` after `start` (default: now)."""
        if seconds is None:
            return cls()
        return cls((time.monotonic() if start is None else start) + float(seconds))

    def passed(self, stage: str) -> bool:
        """True once the budget is spent; records `stage` as stopped by it (once)."""
        if self.at is None or time.monotonic() < self.at:
            return False
        if stage not in self.hit:
            self.hit.append(stage)
        return True
