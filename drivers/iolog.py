"""Byte transcripts of device exchanges (``--log-io``), for debugging a real rig."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import TextIO


class Transcript:
    """Appends one line per transfer: time, device, direction, bytes (repr).

    Thread-safe; the file is flushed after every line so a crash loses nothing.
    """

    def __init__(self, path: str | Path | None = None, stream: TextIO | None = None) -> None:
        self._lock = threading.Lock()
        self._own = path is not None
        self._f: TextIO | None = open(path, "a", encoding="utf-8") if path is not None else stream
        self._t0 = time.monotonic()

    def record(self, device: str, direction: str, data: bytes | str) -> None:
        """``direction`` is ``">"`` (to the device), ``"<"`` (from it) or ``"!"`` (an event)."""
        if self._f is None:
            return
        if isinstance(data, bytes):
            text = repr(data)[2:-1]
        else:
            text = data
        with self._lock:
            self._f.write(f"{time.monotonic() - self._t0:10.4f} {device:<8} {direction} {text}\n")
            self._f.flush()

    def close(self) -> None:
        if self._own and self._f is not None:
            self._f.close()
        self._f = None
