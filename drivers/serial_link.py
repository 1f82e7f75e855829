"""A serial connection opened from a URL, with deadlines on every read.

Drivers own one :class:`SerialLink`; the URL chooses a real port
(``/dev/ttyUSB0``, ``COM3``), a pty, or a simulated twin (``sim-shot702://...``)
through ``serial.serial_for_url`` — no code patches ``serial.Serial``.
"""

from __future__ import annotations

import termios
import time

import serial

from drivers.errors import DeviceConnectionError, DeviceTimeout
from drivers.iolog import Transcript


class SerialLink:
    """Owns a pyserial port; reads until a terminator within a deadline.

    Args:
        url: anything ``serial.serial_for_url`` accepts.
        device: name used in errors and the transcript.
        transcript: optional byte log.
        **settings: baudrate, bytesize, parity, stopbits, rtscts, ...
    """

    def __init__(self, url: str, *, device: str, transcript: Transcript | None = None, **settings: object) -> None:
        self.device = device
        self.url = url
        self._log = transcript
        self._buf = bytearray()
        try:
            self._port = serial.serial_for_url(url, timeout=0.05, write_timeout=2.0, **settings)
        except (serial.SerialException, ValueError, OSError) as e:
            raise DeviceConnectionError(f"cannot open port {url!r}: {e}", device=device) from None

    def write(self, data: bytes) -> None:
        if self._log:
            self._log.record(self.device, ">", data)
        try:
            self._port.write(data)
            self._port.flush()
        except serial.SerialTimeoutException:
            raise DeviceTimeout(f"write to {self.url} timed out", device=self.device) from None
        except (serial.SerialException, OSError) as e:
            raise DeviceConnectionError(f"write to {self.url} failed: {e}", device=self.device) from None

    def read_until(self, terminator: bytes, timeout_s: float) -> bytes:
        """Bytes up to and including ``terminator``; DeviceTimeout if it does not come in time.

        The bytes read before a timeout are kept in the error message (``partial``)
        and logged, so a garbled exchange can be diagnosed.
        """
        buf = self._buf
        deadline = time.monotonic() + timeout_s
        while terminator not in buf:
            if time.monotonic() > deadline:
                partial = bytes(buf)
                buf.clear()
                if self._log:
                    self._log.record(self.device, "!", f"timeout after {timeout_s:.2f} s, partial={partial!r}")
                raise DeviceTimeout(
                    f"no complete reply within {timeout_s:.2f} s (got {partial!r})", device=self.device
                )
            try:
                chunk = self._port.read(max(1, self._port.in_waiting))
            except (serial.SerialException, OSError) as e:
                raise DeviceConnectionError(f"read from {self.url} failed: {e}", device=self.device) from None
            buf += chunk
        idx = buf.index(terminator) + len(terminator)
        out = bytes(buf[:idx])
        del buf[:idx]  # what follows belongs to the next reply
        if self._log:
            self._log.record(self.device, "<", out)
        return out

    def reset_input(self) -> None:
        """Discard unread input (after a timeout or garbled reply, before a retry)."""
        self._buf.clear()
        try:
            self._port.reset_input_buffer()
        except (serial.SerialException, OSError, termios.error) as e:
            # termios.error is what a vanished pty / USB adapter raises on flush
            raise DeviceConnectionError(f"port {self.url} is gone: {e}", device=self.device) from None

    def close(self) -> None:
        try:
            self._port.close()
        except (serial.SerialException, OSError):
            pass
