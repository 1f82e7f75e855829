"""One abstract interface per device kind.

Each public method checks units and ranges, then calls a protected ``_do_*``
method that the concrete driver implements (the python-microscope pattern).
No bytes leave the computer for a request that fails its checks.

Units: degrees, seconds, degrees Celsius, micrometres for pixel pitch,
electrons and ADU for the sensor.
"""

from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from drivers.errors import DeviceTimeout, LimitError, ParameterError, StateError


def _finite(value: float, what: str, device: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"{what} must be a number, got {value!r}", device=device) from None
    if not math.isfinite(v):
        raise ParameterError(f"{what} must be finite, got {value!r}", device=device)
    return v


# --------------------------------------------------------------------------- stage


@dataclass(frozen=True)
class AngleRange:
    """Closed interval of stage angles in degrees, ``lo <= angle <= hi``."""

    lo: float
    hi: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.lo) and math.isfinite(self.hi)) or self.lo >= self.hi:
            raise ParameterError(f"invalid angle range [{self.lo}, {self.hi}]", device="stage")

    def __contains__(self, angle: float) -> bool:
        return self.lo - 1e-9 <= angle <= self.hi + 1e-9

    def intersect(self, other: AngleRange) -> AngleRange:
        return AngleRange(max(self.lo, other.lo), min(self.hi, other.hi))


class RotationStage(ABC):
    """A motorised rotation stage, angles in degrees.

    The allowed range is fixed when the stage object is made and no call can
    leave it: every target (including home) is checked before a byte is sent.
    Moves between two angles inside the range stay inside it because the stage
    moves monotonically along absolute pulses (no wrap-around).

    Args:
        allowed: the interval the stage may occupy; intersected with the
            hardware's own travel (``hardware_range``) so that no configuration
            can widen it.
        settle_margin_s: extra time on top of the kinematic time allowed for a move.
    """

    device_name = "stage"
    #: The widest range the mechanism may ever be driven to (cable wrap etc.).
    hardware_range: AngleRange = AngleRange(-180.0, 360.0)
    poll_interval_s: float = 0.01

    def __init__(self, allowed: AngleRange, *, settle_margin_s: float = 2.0) -> None:
        self._allowed = allowed.intersect(self.hardware_range)
        self._settle_margin_s = settle_margin_s

    # -- facts
    @property
    def allowed_range(self) -> AngleRange:
        """The allowed angle interval (degrees); read-only."""
        return self._allowed

    @abstractmethod
    def identity(self) -> str:
        """Model and firmware read from the device, e.g. ``"SHOT-702 V1.03"``."""

    # -- motion
    def home(self, *, timeout_s: float | None = None) -> None:
        """Drive to the mechanical origin and wait (blocking)."""
        home = self.home_angle()
        if home not in self._allowed:
            raise LimitError(
                f"home position {home:.3f} deg is outside the allowed range "
                f"[{self._allowed.lo}, {self._allowed.hi}]",
                device=self.device_name,
            )
        start = self.angle()
        self._do_home()
        self.wait(timeout_s if timeout_s is not None else self.move_time_s(start, home))

    def move_to(self, angle_deg: float, *, wait: bool = True, timeout_s: float | None = None) -> None:
        """Move to an absolute angle in degrees.

        Args:
            angle_deg: target, inside :attr:`allowed_range`.
            wait: block until the stage reports ready (default) or return at once.
            timeout_s: limit for the wait; default from distance, speed and acceleration.

        Raises:
            LimitError: target outside the allowed range (nothing sent), or a limit
                switch was hit during the move.
            DeviceTimeout: the move did not finish in time (the stage is stopped).
        """
        target = _finite(angle_deg, "target angle", self.device_name)
        if target not in self._allowed:
            raise LimitError(
                f"target {target:.3f} deg is outside the allowed range "
                f"[{self._allowed.lo}, {self._allowed.hi}]; change the plan or 'allowed_range_deg' in rig.yaml",
                device=self.device_name,
            )
        if self.is_busy():
            raise StateError("stage is still moving", device=self.device_name)
        start = self.angle()
        self._do_move_to(target)
        if wait:
            self.wait(timeout_s if timeout_s is not None else self.move_time_s(start, target))

    def wait(self, timeout_s: float) -> None:
        """Block until the stage is ready; stop it and raise DeviceTimeout after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while self.is_busy():
            if time.monotonic() > deadline:
                self.stop()
                raise DeviceTimeout(f"move did not finish within {timeout_s:.1f} s", device=self.device_name)
            time.sleep(self.poll_interval_s)
        self._check_limit_switch()

    def move_time_s(self, start_deg: float, end_deg: float) -> float:
        """Upper bound of the time a move takes: trapezoidal profile plus a margin."""
        speed = self.speed()
        accel_s = self.acceleration_time_s()
        return abs(end_deg - start_deg) / speed + 2 * accel_s + self._settle_margin_s

    def stop(self) -> None:
        """Decelerate and stop; safe to call at any time, also when idle."""
        self._do_stop()

    def set_speed(self, deg_per_s: float) -> None:
        """Set the maximum speed in degrees per second (> 0)."""
        v = _finite(deg_per_s, "speed", self.device_name)
        if v <= 0:
            raise ParameterError(f"speed must be > 0 deg/s, got {v}", device=self.device_name)
        self._do_set_speed(v)

    # -- implementation hooks
    @abstractmethod
    def angle(self) -> float:
        """Current angle in degrees, read from the controller."""

    @abstractmethod
    def is_busy(self) -> bool:
        """True while the stage moves."""

    @abstractmethod
    def speed(self) -> float:
        """Maximum speed in degrees per second."""

    @abstractmethod
    def acceleration_time_s(self) -> float:
        """Ramp time from rest to maximum speed, seconds."""

    @abstractmethod
    def home_angle(self) -> float:
        """Angle (degrees) the stage reports after homing."""

    @abstractmethod
    def _do_home(self) -> None: ...

    @abstractmethod
    def _do_move_to(self, angle_deg: float) -> None: ...

    @abstractmethod
    def _do_stop(self) -> None: ...

    @abstractmethod
    def _do_set_speed(self, deg_per_s: float) -> None: ...

    def _check_limit_switch(self) -> None:
        """Raise LimitError if the last move ended on a limit switch (override)."""

    def close(self) -> None:
        """Release the transport."""

    def __enter__(self) -> RotationStage:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------- camera


class ShutterMode(str, Enum):
    """``normal``: open during light exposures only; ``open``/``closed``: forced."""

    NORMAL = "normal"
    OPEN = "open"
    CLOSED = "closed"


@dataclass(frozen=True)
class SensorInfo:
    """Facts of a sensor. Unconfirmed values are simulator defaults, marked as such in config."""

    model: str
    width: int  # imaging pixels
    height: int
    pixel_size_um: float
    gain_e_per_adu: float
    bias_adu: float
    read_noise_e: float
    full_well_e: float
    adc_max: int = 65535
    dark_current_e_per_s: float = 1.0  # at the default cooler set-point


@dataclass(frozen=True)
class ROI:
    """Region of interest in unbinned sensor pixels; ``x, y`` is the top-left corner."""

    x: int = 0
    y: int = 0
    width: int = 512
    height: int = 512
    bin_x: int = 1
    bin_y: int = 1

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the frame this ROI reads."""
        return self.height // self.bin_y, self.width // self.bin_x


@dataclass
class Frame:
    """One read-out frame and what is known about it."""

    data: np.ndarray  # uint16, shape roi.shape
    exposure_s: float
    dark: bool
    ccd_temp_c: float
    start_time: float  # unix seconds
    end_time: float
    roi: ROI
    camera: str = ""
    extra: dict = field(default_factory=dict)


@dataclass(frozen=True)
class CoolerStatus:
    on: bool
    setpoint_c: float
    temperature_c: float
    at_temperature: bool
    drive_percent: float


class Camera(ABC):
    """A cooled scientific camera.

    Args:
        sensor: the sensor's facts (pixel pitch, gain, bias, noise, full well).
        exposure_range_s: (min, max) exposure the hardware accepts.
    """

    device_name = "camera"

    def __init__(self, sensor: SensorInfo, exposure_range_s: tuple[float, float]) -> None:
        self.sensor = sensor
        self.exposure_range_s = exposure_range_s
        self._roi = ROI(0, 0, sensor.width, sensor.height)

    @abstractmethod
    def identity(self) -> str:
        """Model, camera id and firmware read from the device."""

    def expose(self, seconds: float, *, dark: bool = False, timeout_s: float | None = None) -> Frame:
        """Take one frame.

        Args:
            seconds: exposure time in seconds, inside :attr:`exposure_range_s`.
            dark: keep the shutter closed (dark or bias frame).
            timeout_s: limit for exposure + readout; default exposure + 30 s.

        Returns:
            The uint16 frame with its metadata.
        """
        t = _finite(seconds, "exposure time", self.device_name)
        lo, hi = self.exposure_range_s
        if not lo <= t <= hi:
            raise LimitError(f"exposure {t} s outside [{lo}, {hi}] s", device=self.device_name)
        return self._do_expose(t, bool(dark), timeout_s if timeout_s is not None else t + 30.0)

    @property
    def roi(self) -> ROI:
        return self._roi

    def set_roi(self, roi: ROI) -> None:
        """Read only this region (unbinned pixel coordinates) with the given binning."""
        s = self.sensor
        ok = (
            roi.x >= 0 and roi.y >= 0 and roi.width > 0 and roi.height > 0
            and roi.x + roi.width <= s.width and roi.y + roi.height <= s.height
            and roi.bin_x >= 1 and roi.bin_y >= 1
            and roi.width % roi.bin_x == 0 and roi.height % roi.bin_y == 0
        )
        if not ok:
            raise LimitError(f"ROI {roi} does not fit the {s.width}x{s.height} sensor", device=self.device_name)
        self._do_set_roi(roi)
        self._roi = roi

    def set_shutter(self, mode: ShutterMode | str) -> None:
        try:
            m = ShutterMode(mode)
        except ValueError:
            raise ParameterError(f"unknown shutter mode {mode!r} (normal, open, closed)", device=self.device_name) from None
        self._do_set_shutter(m)

    def set_cooler(self, setpoint_c: float, *, on: bool = True) -> None:
        """Switch the cooler on at ``setpoint_c`` (degrees C) or off."""
        t = _finite(setpoint_c, "cooler set-point", self.device_name)
        if not -60.0 <= t <= 39.0:
            raise LimitError(f"cooler set-point {t} C outside [-60, 39] C", device=self.device_name)
        self._do_set_cooler(t, on)

    @abstractmethod
    def temperature(self) -> float:
        """CCD temperature in degrees C."""

    @abstractmethod
    def cooler_status(self) -> CoolerStatus: ...

    @abstractmethod
    def _do_expose(self, seconds: float, dark: bool, timeout_s: float) -> Frame: ...

    @abstractmethod
    def _do_set_roi(self, roi: ROI) -> None: ...

    @abstractmethod
    def _do_set_shutter(self, mode: ShutterMode) -> None: ...

    @abstractmethod
    def _do_set_cooler(self, setpoint_c: float, on: bool) -> None: ...

    def close(self) -> None:
        """Close the shutter if possible and release the device."""

    def __enter__(self) -> Camera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------- filters


class FilterChanger(ABC):
    """Named filter positions (``r``, ``g``, ``b``, ...).

    Args:
        positions: filter name -> device position (1-based on a wheel).
    """

    device_name = "filter"

    def __init__(self, positions: Mapping[str, int]) -> None:
        if not positions:
            raise ParameterError("no filter positions configured", device=self.device_name)
        if len(set(positions.values())) != len(positions):
            raise ParameterError(f"two filters share a position in {dict(positions)}", device=self.device_name)
        self.positions = dict(positions)

    def names(self) -> list[str]:
        return list(self.positions)

    def select(self, name: str, *, timeout_s: float | None = None) -> None:
        """Put filter ``name`` in the beam and wait until it is there."""
        if name not in self.positions:
            raise ParameterError(
                f"unknown filter {name!r}; configured: {', '.join(self.positions)}", device=self.device_name
            )
        self._do_select(self.positions[name], timeout_s)

    def current(self) -> str | None:
        """Name of the filter in the beam, or None if the position has no name."""
        pos = self._do_current()
        for n, p in self.positions.items():
            if p == pos:
                return n
        return None

    @abstractmethod
    def identity(self) -> str: ...

    @abstractmethod
    def _do_select(self, position: int, timeout_s: float | None) -> None: ...

    @abstractmethod
    def _do_current(self) -> int: ...

    def close(self) -> None:
        """Release the transport."""

    def __enter__(self) -> FilterChanger:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
