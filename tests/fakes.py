"""Small in-memory devices for capture tests: honest subclasses of the driver interfaces.

They keep no bytes and no timing, but they obey the interfaces' checks (the
public methods of the ABCs run unchanged) and the camera follows a linear CCD
noise model: bias, gain, Poisson photo- and dark electrons, Gaussian read
noise, full-well clipping with blooming along columns, ADC clipping at 65535.
A shared :class:`FakeBench` tells the camera the stage angle, the filter and
whether the shutter is closed; its ``scene(angle, filter)`` returns the true
radiance in e-/s of the full sensor.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from drivers.errors import DeviceTimeout
from drivers.interfaces import (
    ROI,
    AngleRange,
    Camera,
    CoolerStatus,
    FilterChanger,
    Frame,
    RotationStage,
    SensorInfo,
    ShutterMode,
)

Scene = Callable[[float, str], np.ndarray]

TEST_SENSOR = SensorInfo(
    model="fake KAF-0261E",
    width=512,
    height=512,
    pixel_size_um=20.0,
    gain_e_per_adu=3.0,
    bias_adu=1000.0,
    read_noise_e=15.0,
    full_well_e=200_000.0,
    adc_max=65535,
    dark_current_e_per_s=2.0,
)


def small_sensor(rows: int = 48, cols: int = 64) -> SensorInfo:
    """The test sensor cut down to a few pixels, for fast executor tests."""
    return SensorInfo(**{**TEST_SENSOR.__dict__, "width": cols, "height": rows})


def bloom(electrons: np.ndarray, full_well: float) -> np.ndarray:
    """Charge above full well spills half up, half down the column until absorbed (no anti-blooming);
    what reaches the ends of a column drains into the serial register and is lost."""
    q = electrons.astype(np.float64)
    for _ in range(q.shape[0] + 1):
        excess = np.maximum(q - full_well, 0.0)
        if not excess.any():
            break
        q -= excess
        q[1:] += 0.5 * excess[:-1]
        q[:-1] += 0.5 * excess[1:]
    return np.minimum(q, full_well)


def simulate_frame(
    rng: np.random.Generator,
    radiance_e_per_s: np.ndarray | float,
    exposure_s: float,
    sensor: SensorInfo,
    *,
    dark: bool = False,
    shape: tuple[int, int] | None = None,
    bias_map: np.ndarray | None = None,
    with_bloom: bool = True,
) -> np.ndarray:
    """One raw uint16 frame of the noise model (photo-electrons only when ``dark`` is False)."""
    shp = np.shape(radiance_e_per_s) if shape is None else shape
    mean_e = sensor.dark_current_e_per_s * exposure_s + (0.0 if dark else np.maximum(radiance_e_per_s, 0.0) * exposure_s)
    e = rng.poisson(np.broadcast_to(mean_e, shp)).astype(np.float64)
    if with_bloom:
        e = bloom(e, sensor.full_well_e)
    else:
        e = np.minimum(e, sensor.full_well_e)
    e += rng.normal(0.0, sensor.read_noise_e, shp)
    bias = sensor.bias_adu if bias_map is None else bias_map
    adu = np.rint(bias + e / sensor.gain_e_per_adu)
    return np.clip(adu, 0, sensor.adc_max).astype(np.uint16)


@dataclass
class FakeBench:
    """Shared state of the fake devices."""

    scene: Scene
    angle_deg: float = 0.0
    filter_name: str | None = None
    shutter: ShutterMode = ShutterMode.NORMAL
    log: list[tuple] = field(default_factory=list)


class FakeStage(RotationStage):
    """Instant stage; every call is logged on the bench."""

    def __init__(self, bench: FakeBench, allowed: AngleRange = AngleRange(-10.0, 190.0)) -> None:
        super().__init__(allowed, settle_margin_s=0.1)
        self.bench = bench
        self.stops = 0

    def identity(self) -> str:
        return "FAKE-STAGE 1.0"

    def angle(self) -> float:
        return self.bench.angle_deg

    def is_busy(self) -> bool:
        return False

    def speed(self) -> float:
        return 20.0

    def acceleration_time_s(self) -> float:
        return 0.1

    def home_angle(self) -> float:
        return 0.0

    def _do_home(self) -> None:
        self.bench.log.append(("home",))
        self.bench.angle_deg = 0.0

    def _do_move_to(self, angle_deg: float) -> None:
        self.bench.log.append(("move", angle_deg))
        self.bench.angle_deg = angle_deg

    def _do_stop(self) -> None:
        self.stops += 1
        self.bench.log.append(("stop",))

    def _do_set_speed(self, deg_per_s: float) -> None:
        self.bench.log.append(("speed", deg_per_s))


class FakeCamera(Camera):
    """Noise-model camera. ``fail_at``/``interrupt_at``: exposure index that raises DeviceTimeout/KeyboardInterrupt."""

    def __init__(
        self,
        bench: FakeBench,
        sensor: SensorInfo = TEST_SENSOR,
        *,
        seed: int = 0,
        exposure_range_s: tuple[float, float] = (0.001, 3600.0),
        fail_at: int | None = None,
        interrupt_at: int | None = None,
    ) -> None:
        super().__init__(sensor, exposure_range_s)
        self.bench = bench
        self.rng = np.random.default_rng(seed)
        self.fail_at = fail_at
        self.interrupt_at = interrupt_at
        self.exposures: list[tuple[float, bool, float, str | None]] = []  # (t, dark, angle, filter)
        self.shutter_calls: list[ShutterMode] = []
        self.clock = 1.7e9

    def identity(self) -> str:
        return "FAKE Alta U260 #1"

    def temperature(self) -> float:
        return -20.0

    def cooler_status(self) -> CoolerStatus:
        return CoolerStatus(True, -20.0, -20.0, True, 40.0)

    def _do_expose(self, seconds: float, dark: bool, timeout_s: float) -> Frame:
        n = len(self.exposures)
        if self.fail_at is not None and n == self.fail_at:
            raise DeviceTimeout("image not ready within the time limit", device="camera")
        if self.interrupt_at is not None and n == self.interrupt_at:
            raise KeyboardInterrupt
        b = self.bench
        self.exposures.append((seconds, dark, b.angle_deg, b.filter_name))
        b.log.append(("expose", seconds, dark))
        closed = dark or b.shutter == ShutterMode.CLOSED
        roi = self.roi
        full = b.scene(b.angle_deg, b.filter_name or "")
        rad = full[roi.y : roi.y + roi.height, roi.x : roi.x + roi.width]
        data = simulate_frame(self.rng, rad, seconds, self.sensor, dark=closed)
        start = self.clock
        self.clock += seconds + 0.5
        return Frame(data, seconds, dark, self.temperature(), start, self.clock, roi, camera=self.identity())

    def _do_set_roi(self, roi: ROI) -> None:
        if roi.bin_x != 1 or roi.bin_y != 1:
            raise NotImplementedError("the fake camera does not bin")

    def _do_set_shutter(self, mode: ShutterMode) -> None:
        self.shutter_calls.append(mode)
        self.bench.shutter = mode
        self.bench.log.append(("shutter", mode.value))

    def _do_set_cooler(self, setpoint_c: float, on: bool) -> None:
        self.bench.log.append(("cooler", setpoint_c, on))


class FakeWheel(FilterChanger):
    """Instant filter wheel."""

    def __init__(self, bench: FakeBench, positions: dict[str, int] | None = None) -> None:
        super().__init__(positions or {"r": 1, "g": 2, "b": 3})
        self.bench = bench
        self._pos = 1

    def identity(self) -> str:
        return "FAKE FW102C 1.0"

    def _do_select(self, position: int, timeout_s: float | None) -> None:
        self._pos = position
        self.bench.filter_name = self.current()
        self.bench.log.append(("filter", self.bench.filter_name))

    def _do_current(self) -> int:
        return self._pos


def spot_scene(rows: int, cols: int, *, spot_row: int | None = None, peak_e_per_s: float = 2.0e6) -> Scene:
    """A scattering spot: exponential fall-off from a centre that moves with the angle, per-filter power.

    The profile row spans about four decades, like a translucent slab's.
    """
    r0 = rows // 2 if spot_row is None else spot_row
    y, x = np.mgrid[0:rows, 0:cols]
    power = {"r": 1.0, "g": 0.6, "b": 0.3}

    def scene(angle_deg: float, filt: str) -> np.ndarray:
        cx = cols / 2 + 0.1 * cols * np.sin(np.radians(angle_deg))
        d = np.hypot((x - cx) * 1.0, (y - r0) * 2.0)
        falloff = 1.0 if angle_deg < 90 else 0.5
        return peak_e_per_s * power.get(filt, 1.0) * falloff * np.exp(-d / 4.0) + 50.0

    return scene


def make_rig(rows: int = 48, cols: int = 64, *, seed: int = 0, **camera_kw) -> tuple[FakeBench, FakeStage, FakeCamera, FakeWheel]:
    """A bench with a spot scene and the three fake devices on a small sensor."""
    bench = FakeBench(spot_scene(rows, cols))
    cam = FakeCamera(bench, small_sensor(rows, cols), seed=seed, **camera_kw)
    return bench, FakeStage(bench), cam, FakeWheel(bench)
