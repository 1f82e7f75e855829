"""Thorlabs FW102C / FW212C motorised filter wheel over a serial port.

The wheel echoes each command, sends its reply and then the prompt ``"> "``;
every exchange is read up to the prompt with a deadline (see
:mod:`drivers.fw102c_protocol`). The port is opened from a URL, so the same
driver talks to ``/dev/ttyUSB1``, a pty, or the twin ``sim-fw102c://bench``.

Recovery. The protocol has no checksum; what the driver can check is the echo,
the framing and the range of every value. Queries (``*idn?``, ``pcount?``,
``pos?``, ``speed?``) are idempotent and are retried after a timeout or a
garbled exchange. ``pos=N`` is absolute, so after a lost or garbled answer the
driver reads the position back and sends ``pos=N`` again only if the wheel is
not there. A refusal (``Command error ...`` with a correct echo) is the wheel's
considered answer and is never retried.

Travel time. The wheel is taken to turn the short way round: odemis
``tlfw.py`` (in use on real FW102Cs) bounds a move by
``1 s + 2 x min(|a-b|, n-|a-b|) x (1 s per position, 2 s at speed=0)``,
which would time out on long-way moves if the wheel did not. *Unconfirmed*
against Thorlabs documentation; the timeout keeps the same factor of 2.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Mapping
from typing import TypeVar

from drivers import fw102c_protocol as proto
from drivers.errors import (
    DeviceConnectionError,
    DeviceError,
    DeviceTimeout,
    LimitError,
    ParameterError,
    ProtocolError,
    StateError,
)
from drivers.interfaces import FilterChanger
from drivers.iolog import Transcript
from drivers.serial_link import SerialLink

T = TypeVar("T")


def _text(e: DeviceError) -> str:
    """The message of an error without its device prefix (for nesting in another)."""
    return str(e.args[0]) if e.args else str(e)


class FW102C(FilterChanger):
    """A Thorlabs FW102C (6 positions) or FW212C (12 positions) filter wheel.

    Args:
        url: port for ``serial.serial_for_url`` (``/dev/ttyUSB1``, ``sim-fw102c://default``).
        positions: filter name -> wheel position (1-based); checked against the
            wheel's ``pcount?`` when the port is opened.
        transcript: optional byte log of every exchange (``--log-io``).
        position_time_s: seconds the wheel needs per position at high speed
            (twice that at ``speed=0``); sets the move timeouts.
        retries: extra attempts for an idempotent query or a ``pos=N`` whose
            answer was lost or garbled.

    Raises:
        DeviceConnectionError: the port cannot be opened, nothing answers as an
            FW102C, or the device identifies as something else.
        LimitError: a configured position is beyond the wheel's position count.
        ParameterError: bad arguments (nothing opened).
    """

    #: Reply deadline of a query, seconds. At 115200 baud an exchange takes ~1 ms;
    #: the margin covers USB-serial latency and a slow host.
    reply_timeout_s: float = 0.5
    #: Safety factor on the expected travel time of a move (odemis uses 2).
    move_safety_factor: float = 2.0

    def __init__(
        self,
        url: str,
        *,
        positions: Mapping[str, int],
        transcript: Transcript | None = None,
        position_time_s: float = 1.0,
        retries: int = 2,
    ) -> None:
        super().__init__(positions)
        for name, p in self.positions.items():
            if isinstance(p, bool) or not isinstance(p, int) or p < 1:
                raise ParameterError(f"filter {name!r}: position must be an integer >= 1, got {p!r}",
                                     device=self.device_name)
        if not (isinstance(position_time_s, (int, float)) and math.isfinite(position_time_s) and position_time_s > 0):
            raise ParameterError(f"position_time_s must be > 0 s, got {position_time_s!r}", device=self.device_name)
        if isinstance(retries, bool) or not isinstance(retries, int) or retries < 0:
            raise ParameterError(f"retries must be an integer >= 0, got {retries!r}", device=self.device_name)
        self.url = url
        self.position_time_s = float(position_time_s)
        self.retries = retries
        self._log = transcript
        self._lock = threading.RLock()
        self._closed = False
        self._link = SerialLink(
            url, device=self.device_name, transcript=transcript,
            baudrate=proto.BAUDRATE, bytesize=8, parity="N", stopbits=1, rtscts=False, xonxoff=False,
        )
        try:
            self._open()
        except BaseException:
            self._link.close()
            self._closed = True
            raise

    # ------------------------------------------------------------------ open

    def _open(self) -> None:
        # A lone CR makes the wheel drop half a command left in its input by an
        # earlier program (odemis does the same); whatever it answers is discarded.
        self._link.write(proto.CR)
        try:
            self._link.read_until(proto.PROMPT, self.reply_timeout_s)
        except DeviceTimeout:
            pass
        self._link.reset_input()

        try:
            idn = self._query(proto.idn_query(), proto.parse_identity, "identity")
        except (DeviceTimeout, ProtocolError) as e:
            raise DeviceConnectionError(
                f"nothing on port {self.url} answers as a FW102C filter wheel ({_text(e)}); "
                "check the port, the cable and that the wheel is switched on", device=self.device_name
            ) from None
        if not proto.is_fw102c(idn):
            raise DeviceConnectionError(f"port {self.url} answers as {idn!r}, not a FW102C", device=self.device_name)
        self._identity = idn
        self._pcount = self._query(proto.pcount_query(), proto.parse_pcount, "position count")
        bad = {n: p for n, p in self.positions.items() if p > self._pcount}
        if bad:
            raise LimitError(
                f"filter positions {bad} do not exist on this {self._pcount}-position wheel; "
                "fix 'filter.positions' in rig.yaml", device=self.device_name)
        try:
            self._high_speed = bool(self._query(proto.speed_query(), lambda r: proto.parse_flag(r, "speed"), "speed"))
        except ProtocolError:
            # A firmware without ``speed?`` refuses it: assume the slow speed, the safe side for timeouts.
            self._high_speed = False
        self._position: int | None = None
        self._position = self._read_position_confirmed()

    # ------------------------------------------------------------------ facts

    def identity(self) -> str:
        """The ``*idn?`` answer read when the port was opened."""
        return self._identity

    @property
    def position_count(self) -> int:
        """Positions of the fitted wheel (``pcount?``): 6 or 12."""
        return self._pcount

    @property
    def high_speed(self) -> bool:
        """True if the wheel runs at ``speed=1`` (as read at open)."""
        return self._high_speed

    def travel(self, start: int | None, end: int) -> int:
        """Positions the wheel passes going from ``start`` to ``end`` the short way
        round; half the wheel when the start is unknown."""
        n = self._pcount
        if start is None:
            return n // 2
        d = abs(end - start) % n
        return min(d, n - d)

    def move_timeout_s(self, start: int | None, end: int) -> float:
        """Deadline in seconds for the prompt after ``pos=end`` issued at ``start``."""
        per_position = self.position_time_s * (1.0 if self._high_speed else 2.0)
        return self.reply_timeout_s + self.move_safety_factor * self.travel(start, end) * per_position

    # ------------------------------------------------------------------ exchanges

    def _check_open(self) -> None:
        if self._closed:
            raise StateError("the filter wheel port is closed", device=self.device_name)

    def _note(self, event: str) -> None:
        if self._log is not None:
            self._log.record(self.device_name, "!", event)

    def _transact(self, cmd: bytes, timeout_s: float) -> proto.Exchange:
        """Send one command and read its exchange; the echo is checked first."""
        self._link.write(cmd)
        raw = self._link.read_until(proto.PROMPT, timeout_s)
        ex = proto.parse_exchange(raw)
        proto.check_echo(ex, cmd)
        return ex

    def _refused(self, cmd: bytes, ex: proto.Exchange, what: str) -> ProtocolError:
        return ProtocolError(
            f"{what}: the wheel refused {cmd.decode('ascii').strip()!r} with 'Command error {ex.error}'",
            device=self.device_name,
        )

    def _query(self, cmd: bytes, parse: Callable[[str], T], what: str) -> T:
        """An idempotent query, retried after a timeout or a garbled exchange."""
        with self._lock:
            self._check_open()
            last: DeviceError | None = None
            for attempt in range(self.retries + 1):
                try:
                    ex = self._transact(cmd, self.reply_timeout_s)
                except (DeviceTimeout, ProtocolError) as e:
                    last = e
                    self._link.reset_input()
                    self._note(f"{what}: attempt {attempt + 1} failed ({e})")
                    continue
                if ex.error is not None:
                    raise self._refused(cmd, ex, what)
                try:
                    return parse(ex.reply)
                except ProtocolError as e:
                    last = e
                    self._note(f"{what}: attempt {attempt + 1} garbled ({e})")
            assert last is not None
            raise type(last)(f"{what}: no valid answer after {self.retries + 1} attempts; last: {_text(last)}",
                             device=self.device_name) from None

    def _read_position(self) -> int:
        return self._query(proto.pos_query(), lambda r: proto.parse_position(r, self._pcount), "position")

    # ------------------------------------------------------------------ FilterChanger hooks

    def _read_position_confirmed(self) -> int:
        """``pos?``, trusted at once only when it agrees with the last known position.

        A bit flip can turn one digit into another and pass every check, so a
        reading that is new (after open, after a failed move, or different from
        the last known position; the front-panel buttons can turn the wheel) is
        taken only once two successive reads agree.
        """
        pos = self._read_position()
        if pos == self._position:
            return pos
        for _ in range(self.retries + 1):
            again = self._read_position()
            if again == pos:
                return pos
            pos = again
        raise ProtocolError("successive position reads disagree", device=self.device_name)

    def _do_current(self) -> int:
        with self._lock:
            self._position = self._read_position_confirmed()
            return self._position

    def _do_select(self, position: int, timeout_s: float | None) -> None:
        with self._lock:
            self._check_open()
            cmd = proto.pos_set(position)
            last: DeviceError | None = None
            for attempt in range(self.retries + 1):
                deadline = timeout_s if timeout_s is not None else self.move_timeout_s(self._position, position)
                self._position = None  # unknown until the prompt (or a read-back) says otherwise
                try:
                    ex = self._transact(cmd, deadline)
                except (DeviceTimeout, ProtocolError) as e:
                    # The answer was lost or garbled, or the command was corrupted on
                    # the way in: find out where the wheel is before anything else.
                    last = e
                    self._link.reset_input()
                    self._note(f"select {position}: attempt {attempt + 1} failed ({e}); reading back")
                    try:
                        self._position = self._read_position_confirmed()
                    except DeviceError:
                        raise last from None
                    if self._position == position:
                        return
                    continue
                if ex.error is not None:
                    raise self._refused(cmd, ex, f"select position {position}")
                self._position = position
                return
            assert last is not None
            raise type(last)(
                f"wheel did not reach position {position} after {self.retries + 1} attempts; last: {_text(last)}",
                device=self.device_name) from None

    def close(self) -> None:
        """Release the port (the wheel stays where it is)."""
        with self._lock:
            if not self._closed:
                self._closed = True
                self._link.close()
