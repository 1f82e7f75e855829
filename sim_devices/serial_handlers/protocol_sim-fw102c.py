"""pyserial URL handler for the simulated FW102C filter wheel.

URL: ``sim-fw102c://<bench>?pcount=6&timescale=100&faults=drop:0.05,garble:0.02&seed=1``

- ``<bench>``: name of the :class:`sim_devices.bench.Bench` whose filter the wheel
  sets (``default`` when empty).
- ``pcount``: 6 (FW102C, default) or 12 (FW212C).
- ``timescale``: simulated seconds per real second (default: the bench's).
- ``faults``, ``seed``: a :class:`sim_devices.faults.FaultPlan` (drop, garble, ng).
- ``pos``: starting position (default: where the bench's filter is, else 1).
- ``postime``: simulated seconds per position at high speed (default 1).
- ``idn``: the ``*idn?`` answer, percent-encoded (to simulate another device on the port).

Unknown parameters are refused so that a typo does not go unnoticed. Like the
real wheel, the twin hears only a 115200 8N1 line: with other settings nothing
gets through in either direction.

pyserial finds this module by importing ``protocol_sim-fw102c`` from the package
(``importlib`` does not mind the hyphen in a file name).
"""

from __future__ import annotations

from urllib.parse import SplitResult, parse_qs

from drivers.fw102c_protocol import BAUDRATE
from sim_devices.bench import get_bench
from sim_devices.faults import FaultPlan
from sim_devices.fw102c import IDENTITY, FW102CTwin
from sim_devices.serial_twin import SimClock, TwinSerial

PARAMS = ("pcount", "timescale", "faults", "seed", "pos", "postime", "idn")


def twin_from_url(parts: SplitResult) -> FW102CTwin:
    """Build the twin a ``sim-fw102c://`` URL describes (ValueError if it is malformed)."""
    q = parse_qs(parts.query, keep_blank_values=True)
    unknown = sorted(set(q) - set(PARAMS))
    if unknown:
        raise ValueError(f"unknown parameter(s) {', '.join(unknown)}; known: {', '.join(PARAMS)}")
    one = {k: v[-1] for k, v in q.items()}
    bench = get_bench(parts.netloc or "default")
    time_scale = float(one["timescale"]) if "timescale" in one else bench.time_scale
    faults = FaultPlan.parse(one.get("faults"), int(one.get("seed", "0")))
    return FW102CTwin(
        SimClock(time_scale),
        faults,
        bench=bench,
        pcount=int(one.get("pcount", "6")),
        position=int(one["pos"]) if "pos" in one else None,
        position_time_s=float(one.get("postime", "1.0")),
        identity=one.get("idn", IDENTITY),
    )


class Serial(TwinSerial):
    """A port with a simulated FW102C on the other end."""

    def make_twin(self, parts: SplitResult) -> FW102CTwin:
        return twin_from_url(parts)

    def _line_matches(self) -> bool:
        return (self.baudrate == BAUDRATE and self.bytesize == 8 and self.parity == "N"
                and self.stopbits == 1)

    def write(self, data: bytes) -> int:
        self._check()
        if self._line_matches():
            self.twin.write(bytes(data))
        return len(data)

    def read(self, size: int = 1) -> bytes:
        if not self._line_matches():
            self._check()
            self.twin.read_ready()  # lost on the line
        return super().read(size)

    def reset_input_buffer(self) -> None:
        # Only bytes already received are discarded, as on a real port; a prompt
        # still on its way (the wheel is turning) arrives later.
        self._check()
        self.twin.read_ready()
