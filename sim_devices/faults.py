"""Seeded fault injection for the twins.

A :class:`FaultPlan` is parsed from a URL query (``?faults=drop:0.05,garble:0.02&seed=3``)
or built directly; each ``hit(kind)`` draws from its own seeded generator, so a
run with the same seed and the same exchanges injects the same faults.

Kinds used by the twins: ``drop`` (a reply never comes), ``garble`` (one reply byte
corrupted), ``ng`` (a refusal instead of the normal reply), ``limit`` (stage: a limit
switch is hit mid-move), ``pipe`` (USB: a control transfer stalls), ``disconnect``
(USB: the device vanishes mid-readout), ``short`` (USB: a bulk read returns fewer bytes).
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field
from urllib.parse import parse_qs

KNOWN = ("drop", "garble", "ng", "limit", "pipe", "disconnect", "short")


@dataclass
class FaultPlan:
    rates: dict[str, float] = field(default_factory=dict)
    seed: int = 0
    counts: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for k, r in self.rates.items():
            if k not in KNOWN:
                raise ValueError(f"unknown fault kind {k!r}; known: {', '.join(KNOWN)}")
            if not 0.0 <= r <= 1.0:
                raise ValueError(f"fault rate for {k!r} must be in [0, 1], got {r}")
        self._rng = random.Random(self.seed)

    @classmethod
    def parse(cls, spec: str | None, seed: int = 0) -> FaultPlan:
        """``"drop:0.05,garble:0.02"`` -> FaultPlan."""
        rates: dict[str, float] = {}
        for part in (spec or "").split(","):
            part = part.strip()
            if not part:
                continue
            kind, _, rate = part.partition(":")
            rates[kind.strip()] = float(rate) if rate else 1.0
        return cls(rates, seed)

    @classmethod
    def from_query(cls, query: str) -> FaultPlan:
        q = parse_qs(query)
        seed = int(q.get("seed", ["0"])[0])
        return cls.parse(q.get("faults", [""])[0], seed)

    def hit(self, kind: str) -> bool:
        """True if a fault of this kind happens now (always draws, to keep sequences stable)."""
        u = self._rng.random()
        if u < self.rates.get(kind, 0.0):
            self.counts[kind] = self.counts.get(kind, 0) + 1
            return True
        return False

    def garble(self, data: bytes) -> bytes:
        """Corrupt one byte of ``data`` (a bit flip that never yields the terminator)."""
        if not data:
            return data
        i = self._rng.randrange(len(data))
        b = data[i] ^ (1 << self._rng.randrange(7))
        if b in (0x0A, 0x0D, 0x3E):  # keep framing, corrupt content
            b ^= 0x40
        return data[:i] + bytes([b]) + data[i + 1 :]

    def uniform(self, lo: float, hi: float) -> float:
        return self._rng.uniform(lo, hi)
