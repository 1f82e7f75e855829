"""Base of the serial twins, their pyserial adapter and a pty server.

A :class:`SerialTwin` is a passive byte machine: bytes from the host go to
``handle``; replies are queued with an optional delay in *simulated* seconds and
become readable when the simulated clock passes that time. Physical state (a
moving stage, a turning wheel) is computed lazily from the same clock, so a
``time_scale`` of 100 makes everything 100x faster without changing behaviour.

:class:`TwinSerial` adapts a twin to ``serial.SerialBase`` for URL handlers;
:func:`serve_on_pty` exposes a twin on a pseudo-terminal so an unmodified client
in another process (``serial.Serial('/dev/pts/N')``) can talk to it.
"""

from __future__ import annotations

import heapq
import itertools
import os
import threading
import time
from abc import ABC, abstractmethod
from urllib.parse import urlsplit

import serial

from sim_devices.faults import FaultPlan


class SimClock:
    """Simulated seconds = real monotonic seconds x time_scale, from creation."""

    def __init__(self, time_scale: float = 1.0) -> None:
        if not time_scale > 0:
            raise ValueError(f"time_scale must be > 0, got {time_scale}")
        self.time_scale = time_scale
        self._t0 = time.monotonic()

    def now(self) -> float:
        return (time.monotonic() - self._t0) * self.time_scale

    def real_seconds(self, sim_seconds: float) -> float:
        return sim_seconds / self.time_scale


class SerialTwin(ABC):
    """A device that answers bytes with bytes, on a simulated clock."""

    def __init__(self, clock: SimClock, faults: FaultPlan | None = None) -> None:
        self.clock = clock
        self.faults = faults or FaultPlan()
        self._out: list[tuple[float, int, bytes]] = []
        self._seq = itertools.count()
        self._inbuf = bytearray()
        self.lock = threading.RLock()

    # -- host side
    def write(self, data: bytes) -> None:
        with self.lock:
            self._inbuf += data
            self.consume(self._inbuf)

    def read_ready(self, size: int | None = None) -> bytes:
        """Bytes whose time has come, in queue order; at most ``size`` bytes."""
        with self.lock:
            now = self.clock.now()
            out = bytearray()
            while self._out and self._out[0][0] <= now and (size is None or len(out) < size):
                t, seq, chunk = heapq.heappop(self._out)
                if size is not None and len(out) + len(chunk) > size:
                    take = size - len(out)
                    # the rest keeps its own place in the queue (same time and sequence)
                    heapq.heappush(self._out, (t, seq, chunk[take:]))
                    chunk = chunk[:take]
                out += chunk
            return bytes(out)

    def pending(self) -> int:
        with self.lock:
            now = self.clock.now()
            return sum(len(c) for t, _, c in self._out if t <= now)

    def clear_output(self) -> None:
        with self.lock:
            self._out.clear()

    # -- twin side
    def reply(self, data: bytes, delay_s: float = 0.0) -> None:
        """Queue ``data`` to become readable ``delay_s`` simulated seconds from now."""
        self.reply_at(self.clock.now() + delay_s, data)

    def reply_at(self, t_sim: float, data: bytes) -> None:
        """Queue ``data`` to become readable at simulated time ``t_sim``; equal times keep call order."""
        heapq.heappush(self._out, (t_sim, next(self._seq), data))

    @abstractmethod
    def consume(self, buf: bytearray) -> None:
        """Parse complete commands out of ``buf`` (delete what was used) and act on them."""


class TwinSerial(serial.SerialBase):
    """pyserial port backed by a twin. Subclasses set ``make_twin(url_parts) -> SerialTwin``."""

    def make_twin(self, parts) -> SerialTwin:  # pragma: no cover - overridden
        raise NotImplementedError

    def open(self) -> None:
        if self._port is None:
            raise serial.SerialException("Port must be configured before it can be used.")
        if self.is_open:  # type: ignore[has-type]  # SerialBase sets it in __init__; pyserial has no stubs
            raise serial.SerialException("Port is already open.")
        try:
            self.twin = self.make_twin(urlsplit(self._port))
        except ValueError as e:
            raise serial.SerialException(f"invalid twin URL {self._port!r}: {e}") from None
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    def from_url(self, url: str) -> str:
        return url

    def _reconfigure_port(self) -> None:
        pass

    @property
    def in_waiting(self) -> int:
        self._check()
        return self.twin.pending()

    def read(self, size: int = 1) -> bytes:
        self._check()
        deadline = None if self._timeout is None else time.monotonic() + self._timeout
        out = bytearray()
        while len(out) < size:
            out += self.twin.read_ready(size - len(out))
            if len(out) >= size:
                break
            if deadline is not None and time.monotonic() >= deadline:
                break
            time.sleep(0.0005)
        return bytes(out)

    def write(self, data: bytes) -> int:
        self._check()
        self.twin.write(bytes(data))
        return len(data)

    def reset_input_buffer(self) -> None:
        self._check()
        self.twin.clear_output()

    def reset_output_buffer(self) -> None:
        self._check()

    def _check(self) -> None:
        if not self.is_open:
            raise serial.PortNotOpenError()

    # modem lines: the twins use none of them
    def _update_break_state(self) -> None: ...
    def _update_rts_state(self) -> None: ...
    def _update_dtr_state(self) -> None: ...
    cts = dsr = ri = cd = property(lambda self: True)


def serve_on_pty(twin: SerialTwin) -> tuple[str, threading.Event]:
    """Serve ``twin`` on a new pseudo-terminal; returns (device path, stop event).

    The pty is put in raw mode so CR/LF pass unchanged.
    """
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    stop = threading.Event()

    def pump() -> None:
        os.set_blocking(master, False)
        while not stop.is_set():
            try:
                data = os.read(master, 4096)
                if data:
                    twin.write(data)
            except BlockingIOError:
                pass
            except OSError:
                break
            out = twin.read_ready()
            if out:
                os.write(master, out)
            time.sleep(0.001)
        os.close(master)
        os.close(slave)

    threading.Thread(target=pump, name=f"pty-{path}", daemon=True).start()
    return path, stop
