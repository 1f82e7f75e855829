# ruff: noqa: N999 - pyserial finds handlers as protocol_<scheme>, and the scheme has a hyphen
"""pyserial URL handler ``sim-shot702://<bench>?<options>``: a simulated Sigma Koki
controller (:class:`~sim_devices.shot702.Shot702Twin`) behind a serial port.

Options (all optional)::

    model=SHOT-702        SHOT-702, SHOT-302GS, SHOT-304GS, GSC-01, GSC-02
    timescale=100         simulated seconds per real second (default: the bench's)
    faults=drop:0.05      comma list of kind:rate (drop, garble, ng, limit)
    seed=1                seed of the fault generator
    zero_offset_deg=0     world angle of the mechanical origin
    start_deg=<deg>       world angle at power-on (default: the origin)
    degrees_per_pulse=0.005, division=2, axis=1 (the rotation axis)
    limits=-72000:72000   limit switch counts from the origin (default: none)
    stray_nul=1           a NUL byte before the first reply
    version=V1.00         what ``?:V`` answers

Twins opened with the same bench name drive the same bench.
"""

from __future__ import annotations

from urllib.parse import SplitResult, parse_qs

from sim_devices.bench import get_bench
from sim_devices.faults import FaultPlan
from sim_devices.serial_twin import SimClock, TwinSerial
from sim_devices.shot702 import Shot702Twin

_KEYS = {"model", "timescale", "faults", "seed", "zero_offset_deg", "start_deg", "degrees_per_pulse",
         "division", "axis", "limits", "stray_nul", "version"}


def _one(q: dict[str, list[str]], key: str) -> str | None:
    v = q.get(key)
    return None if v is None else v[-1]


def twin_from_url(parts: SplitResult) -> Shot702Twin:
    """Build the twin a ``sim-shot702://`` URL describes; ValueError for a bad option."""
    q = parse_qs(parts.query, keep_blank_values=True)
    unknown = set(q) - _KEYS
    if unknown:
        raise ValueError(f"unknown option(s) {', '.join(sorted(unknown))}; known: {', '.join(sorted(_KEYS))}")
    bench = parts.netloc or "default"
    timescale = _one(q, "timescale")
    clock = SimClock(float(timescale) if timescale else get_bench(bench).time_scale)
    limits = _one(q, "limits")
    limits_pulses = None
    if limits:
        lo, sep, hi = limits.partition(":")
        if not sep:
            raise ValueError(f"limits must be '<minus>:<plus>' counts, got {limits!r}")
        limits_pulses = (int(lo), int(hi))
    start = _one(q, "start_deg")
    return Shot702Twin(
        clock,
        FaultPlan.from_query(parts.query),
        model=_one(q, "model") or "SHOT-702",
        bench=bench,
        degrees_per_pulse=float(_one(q, "degrees_per_pulse") or 0.005),
        division=int(_one(q, "division") or 2),
        zero_offset_deg=float(_one(q, "zero_offset_deg") or 0.0),
        start_deg=float(start) if start else None,
        limits_pulses=limits_pulses,
        rotation_axis=int(_one(q, "axis") or 1),
        stray_nul=(_one(q, "stray_nul") or "0") not in ("0", "false", "no", ""),
        version=_one(q, "version") or "V1.00",
    )


class Serial(TwinSerial):
    """The serial port ``serial.serial_for_url('sim-shot702://...')`` returns."""

    def make_twin(self, parts: SplitResult) -> Shot702Twin:
        return twin_from_url(parts)
