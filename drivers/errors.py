"""The one exception hierarchy of the device layer.

Every error a driver raises is a :class:`DeviceError`; callers that only need to
know "the device failed" catch that, callers that can recover catch a subclass.
"""

from __future__ import annotations


class DeviceError(Exception):
    """Base of every device error. ``device`` names the device (e.g. ``"stage"``)."""

    def __init__(self, message: str, *, device: str = "") -> None:
        super().__init__(message)
        self.device = device

    def __str__(self) -> str:  # one line, device first
        msg = super().__str__()
        return f"{self.device}: {msg}" if self.device else msg


class DeviceConnectionError(DeviceError):
    """Raised when a transport cannot be opened, the device is not found on it,
    answers as a different device, or disappears (unplugged, USB disconnect)."""


class DeviceTimeout(DeviceError):
    """Raised when a reply, a move, an exposure or a readout does not complete
    within its time limit. Nothing in the drivers waits without one."""


class ProtocolError(DeviceError):
    """Raised when a reply is malformed, garbled, truncated, or is a refusal
    (Sigma Koki ``NG``, FW102C ``Command error ...``) the driver cannot retry."""


class LimitError(DeviceError, ValueError):
    """Raised before any byte is sent when a request leaves the allowed range
    (stage angle range, exposure range, ROI inside the sensor), and when the
    hardware reports a limit switch hit."""


class ParameterError(DeviceError, ValueError):
    """Raised before any byte is sent for a malformed request: NaN, wrong type,
    unknown filter name, negative time."""


class StateError(DeviceError):
    """Raised when a command is not valid in the device's present state
    (moving, exposing, closed, not homed)."""
