"""Byte-level twin of the Thorlabs FW102C / FW212C filter wheel.

Speaks the bytes of :mod:`drivers.fw102c_protocol`: echo, reply, prompt. The
wheel turns the short way round at ``position_time_s`` simulated seconds per
position (twice that at ``speed=0``), and the prompt after ``pos=N`` becomes
readable only when it has arrived. Commands are handled one after the other:
one sent while the wheel turns is answered after the move (as a single-threaded
controller would). While the wheel turns, the bench's ``filter_name`` is None;
on arrival it becomes ``bench.filter_by_position[N]``.

Each open is a power-on: settings not given in the URL start at the firmware
defaults (high speed, sensors off, trigger input), and the wheel starts where
the bench says its filter is (else at position 1).

Faults (seeded, one draw of each kind per command):
``drop``: the command is carried out but nothing of its exchange comes back;
``garble``: one byte is corrupted, either of the command as received (the
wheel then echoes the corrupted text and usually refuses it) or of the
exchange sent back; ``ng``: a valid command is refused with ``Command error``.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

from drivers import fw102c_protocol as proto
from drivers.errors import ProtocolError
from sim_devices.bench import Bench
from sim_devices.faults import FaultPlan
from sim_devices.serial_twin import SerialTwin, SimClock

IDENTITY = "THORLABS FW102C/FW212C Filter Wheel version 1.07"


@dataclass(frozen=True)
class _Move:
    start: int
    target: int
    t_start: float  # simulated seconds
    t_end: float


class FW102CTwin(SerialTwin):
    """Simulated FW102C.

    Args:
        clock: the simulated clock (its time scale makes moves fast in tests).
        faults: seeded fault plan (drop, garble, ng).
        bench: the bench whose ``filter_name`` the wheel sets; None for none.
        pcount: positions of the fitted wheel, 6 (FW102C) or 12 (FW212C).
        position: starting position; default from the bench, else 1.
        position_time_s: simulated seconds per position at high speed.
        identity: the ``*idn?`` answer (a test can make the port answer as another device).
    """

    def __init__(
        self,
        clock: SimClock,
        faults: FaultPlan | None = None,
        *,
        bench: Bench | None = None,
        pcount: int = 6,
        position: int | None = None,
        position_time_s: float = 1.0,
        identity: str = IDENTITY,
    ) -> None:
        super().__init__(clock, faults)
        if pcount not in proto.POSITION_COUNTS:
            raise ValueError(f"pcount must be 6 or 12, got {pcount}")
        if not position_time_s > 0:
            raise ValueError(f"position_time_s must be > 0, got {position_time_s}")
        self.bench = bench
        self.slots = pcount  # the physical wheel
        self.pcount = pcount  # what the firmware is set to
        if position is None:
            position = self._position_from_bench() or 1
        if not 1 <= position <= pcount:
            raise ValueError(f"start position {position} outside 1..{pcount}")
        self.position = position  # where the wheel is once the last accepted move ends
        self.position_time_s = position_time_s
        self.identity = identity
        self.settings = {"speed": 1, "sensors": 0, "trig": 0}
        self.saved: dict[str, int] = {}
        self.moves: list[_Move] = []
        self._busy_until = 0.0
        self._bench_state: tuple[str, int | None] | None = None
        self.log: list[bytes] = []  # command lines as received (after any inbound garble)
        self._sync_bench()

    # ------------------------------------------------------------------ physics

    def _position_from_bench(self) -> int | None:
        if self.bench is None or self.bench.filter_name is None:
            return None
        for pos, name in self.bench.filter_by_position.items():
            if name == self.bench.filter_name and 1 <= pos <= self.slots:
                return pos
        return None

    def travel(self, start: int, end: int) -> int:
        """Positions passed going the short way round."""
        d = abs(end - start) % self.pcount
        return min(d, self.pcount - d)

    def seconds_per_position(self) -> float:
        return self.position_time_s * (1.0 if self.settings["speed"] else 2.0)

    def wheel_at(self, t: float) -> int | None:
        """Position at simulated time ``t``, or None while the wheel is between positions."""
        with self.lock:
            for m in reversed(self.moves):
                if m.t_start <= t:
                    return m.target if t >= m.t_end else None
            return self.moves[0].start if self.moves else self.position

    def _sync_bench(self) -> None:
        """Put the filter in the beam (or None while turning) on the bench."""
        if self.bench is None:
            return
        with self.lock:
            now = self.clock.now()
            pos = self.wheel_at(now)
            while len(self.moves) > 1 and self.moves[1].t_end <= now:
                self.moves.pop(0)  # keep one finished move: it says where the wheel is
            state = ("moving", None) if pos is None else ("at", pos)
            if state == self._bench_state:
                return  # only changes are written, so others may set the bench in between
            self._bench_state = state
            with self.bench.lock:
                self.bench.filter_name = None if pos is None else self.bench.filter_by_position.get(pos)

    def _sync_at(self, t: float) -> None:
        """Update the bench at simulated time ``t`` even if nobody reads the port then."""
        delay = self.clock.real_seconds(t - self.clock.now())
        if delay <= 0:
            self._sync_bench()
            return
        timer = threading.Timer(delay, self._sync_bench)
        timer.daemon = True
        timer.start()

    # ------------------------------------------------------------------ host side

    def read_ready(self, size: int | None = None) -> bytes:
        out = super().read_ready(size)
        self._sync_bench()  # after the read: a prompt seen implies the bench is updated
        return out

    # ------------------------------------------------------------------ command handling

    def consume(self, buf: bytearray) -> None:
        while proto.CR in buf:
            i = buf.index(proto.CR)
            line = bytes(buf[:i])
            del buf[: i + 1]
            self._handle(line)

    def _handle(self, line: bytes) -> None:
        drop = self.faults.hit("drop")
        garble = self.faults.hit("garble")
        refuse = self.faults.hit("ng")
        garble_inbound = garble and self.faults.uniform(0.0, 1.0) < 0.5
        if garble_inbound:
            line = self.faults.garble(line)
        self.log.append(line)
        t0 = max(self.clock.now(), self._busy_until)
        echo_time, done_time = t0, t0
        try:
            cmd = proto.parse_command(line)
        except ProtocolError:
            cmd = None
        reply: str | None
        error: str | None
        if cmd is None:
            reply, error = None, proto.NOT_DEFINED
        elif refuse:
            reply, error = None, proto.ARG_INVALID if cmd.kind == "=" else proto.NOT_DEFINED
        else:
            reply, error, done_time = self._execute(cmd, t0)
        self._busy_until = done_time
        if drop:
            return
        echo_len = len(line) + len(proto.CR)
        data = proto.format_exchange(line, reply, error)
        if garble and not garble_inbound:
            data = self.faults.garble(data)
        self.reply_at(echo_time, data[:echo_len])
        self.reply_at(done_time, data[echo_len:])

    def _execute(self, cmd: proto.Command, t0: float) -> tuple[str | None, str | None, float]:
        """Act on a well-formed command at simulated time ``t0``: (reply, error, time of the prompt)."""
        name, kind, arg = cmd.name, cmd.kind, cmd.arg
        if kind == "?":
            if name == "*idn":
                return self.identity, None, t0
            if name == "pos":
                return str(self.position), None, t0
            if name == "pcount":
                return str(self.pcount), None, t0
            if name in self.settings:
                return str(self.settings[name]), None, t0
            return None, proto.NOT_DEFINED, t0
        if kind == "=":
            if name == "pos":
                target = _int_arg(arg)
                if target is None or not 1 <= target <= self.pcount:
                    return None, proto.ARG_INVALID, t0
                t_end = t0 + self.travel(self.position, target) * self.seconds_per_position()
                self.moves.append(_Move(self.position, target, t0, t_end))
                self.position = target
                self._sync_at(t0)
                self._sync_at(t_end)
                return None, None, t_end
            if name == "pcount":
                n = _int_arg(arg)
                if n not in proto.POSITION_COUNTS:
                    return None, proto.ARG_INVALID, t0
                self.pcount = n
                if self.position > n:
                    self.position = 1  # twin choice: the controller re-references to 1
                return None, None, t0
            if name in self.settings:
                v = _int_arg(arg)
                if v not in (0, 1):
                    return None, proto.ARG_INVALID, t0
                self.settings[name] = v
                return None, None, t0
            return None, proto.NOT_DEFINED, t0
        if name == "save":
            self.saved = {**self.settings, "pcount": self.pcount}
            return None, None, t0
        return None, proto.NOT_DEFINED, t0


def _int_arg(text: str) -> int | None:
    try:
        return proto.parse_uint(text, "argument")
    except ProtocolError:
        return None
