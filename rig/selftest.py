"""Hardware self-test (``rig selftest``): every device exercised briefly and safely.

Each check returns a :class:`CheckResult`: a name (``stage.home``), ``ok`` /
``warn`` / ``fail``, the values it measured, what was expected, and a one-line
fix. The checks:

- identity of the stage controller, the camera and the filter changer;
- stage: home, a few small moves (``step`` degrees either side of a point
  inside the allowed range, computed from ``stage.allowed_range``; never a
  target outside it) with every position read back, then back to where it
  started;
- filter changer: every configured filter selected and read back, then the
  filter that was in the beam put back;
- camera: cooler switched on at the configured set-point and watched for a
  bounded time (a CCD still cooling is reported, not waited for); two bias
  frames (shortest exposure, shutter closed) give the bias level and the read
  noise; dark frames at a few exposures give the dark current, compared with
  the sensor's value at the measured CCD temperature; a short light frame and
  a dark frame of the same length show whether the shutter opens (light above
  dark) and closes (no light in the dark frame).

Whatever happens (a device fault, Ctrl-C), a ``finally`` stops the stage and
forces the shutter closed. A device that raises is marked failed and its
remaining checks are reported as not run; the other devices are still tested.
Every result is also written to the byte transcript of the run, so the one
file the lab sends when asking for help holds the exchanges and the verdicts.

Expected sensor values come from :class:`capture.hdr.NoiseModel` built from the
camera's :class:`~drivers.interfaces.SensorInfo`. Several of those are
unconfirmed for the real KAF-0261E (read noise, dark current), so the bands
here catch gross faults (a dead amplifier, a cooler that does not cool, a
shutter that sticks), not calibration-grade deviations.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from capture.hdr import NoiseModel
from drivers import alta_protocol
from drivers.errors import (
    DeviceConnectionError,
    DeviceError,
    DeviceTimeout,
    LimitError,
    ProtocolError,
    StateError,
)
from drivers.interfaces import (
    ROI,
    AngleRange,
    Camera,
    FilterChanger,
    Frame,
    RotationStage,
    ShutterMode,
)
from drivers.iolog import Transcript

if TYPE_CHECKING:
    from rig.config import RigConfig
    from rig.wiring import Rig

Status = Literal["ok", "warn", "fail"]

#: Name of the transcript's entries written by the self-test itself.
TRANSCRIPT_NAME = "selftest"

#: Silicon dark current roughly doubles every 6 C (the usual rule of thumb for
#: CCDs near -20 C); used to carry the sensor's dark current from its reference
#: temperature to the temperature the dark frames were taken at.
DARK_DOUBLING_C = 6.0
#: Temperature at which ``SensorInfo.dark_current_e_per_s`` holds (the Alta's
#: default cooler set-point, see drivers/alta_protocol.py).
DARK_REFERENCE_C = alta_protocol.DEFAULT_SETPOINT_C
#: A pixel deviating more than this many robust sigmas from the median is a hot
#: pixel or a cosmic-ray hit, left out of levels and noise.
CLIP_SIGMA = 5.0
#: Median absolute deviation to standard deviation for Gaussian noise.
MAD_TO_SIGMA = 1.4826
#: Variance (ADU^2) the ADC's rounding adds to every pixel: a uniform error of one ADU width.
QUANTISATION_VAR_ADU2 = 1.0 / 12.0


# --------------------------------------------------------------------------- results


@dataclass(frozen=True)
class CheckResult:
    """Outcome of one check.

    Attributes:
        name: ``<device>.<check>``, e.g. ``stage.home``, ``camera.read_noise``.
        status: ``ok``, ``warn`` (worth a look, does not block) or ``fail``.
        message: what was measured, in words.
        measured: the measured values (JSON-ready numbers and strings, units in the key).
        expected: the expectation and its tolerance, in words.
        fix: one line saying what to do (empty when ok).
    """

    name: str
    status: Status
    message: str
    measured: Mapping[str, Any] = field(default_factory=dict)
    expected: str = ""
    fix: str = ""

    @property
    def device(self) -> str:
        return self.name.split(".", 1)[0]

    def line(self) -> str:
        """One line: status, name, measurement, expectation and, unless ok, the fix."""
        text = f"{self.status.upper():<4}  {self.name:<16} {self.message}"
        if self.expected:
            text += f" (expected {self.expected})"
        if self.fix and self.status != "ok":
            text += f"  -> fix: {self.fix}"
        return " ".join(text.splitlines())

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "status": self.status, "message": self.message,
                "measured": dict(self.measured), "expected": self.expected, "fix": self.fix}


@dataclass
class SelfTestReport:
    """All results of one run, in the order they were taken."""

    results: list[CheckResult]
    config_path: str = ""
    simulated: bool = False
    transcript_path: str | None = None

    @property
    def ok(self) -> bool:
        """True when no check failed (warnings allowed)."""
        return not any(r.status == "fail" for r in self.results)

    def counts(self) -> dict[str, int]:
        return {s: sum(r.status == s for r in self.results) for s in ("ok", "warn", "fail")}

    def summary(self) -> str:
        c = self.counts()
        failed = [r.name for r in self.results if r.status == "fail"]
        text = f"selftest: {c['ok']} ok, {c['warn']} warn, {c['fail']} fail"
        if failed:
            text += f"; failed: {', '.join(failed)}"
        if self.transcript_path:
            text += f"; transcript: {self.transcript_path}"
        return text

    def to_dict(self) -> dict[str, Any]:
        return {"config": self.config_path, "simulated": self.simulated, "transcript": self.transcript_path,
                "ok": self.ok, "counts": self.counts(), "checks": [r.to_dict() for r in self.results]}


@dataclass(frozen=True)
class SelfTestOptions:
    """What the self-test does and how much deviation it accepts.

    Attributes:
        stage_step_deg: size of the small moves either side of the test point, degrees
            (shrunk to a quarter of the allowed range when that is narrow).
        stage_tolerance_deg: largest accepted difference between a target and the angle
            read back; None: one position count of the controller (its resolution), or
            ``FALLBACK_STAGE_TOLERANCE_DEG`` for a driver that does not report one.
        cooler_wait_s: longest time to watch the cooler approach its set-point, seconds.
        cooler_poll_s: interval between cooler readings, seconds.
        cooler_min_drop_c: a CCD that cooled by at least this much while watched is
            "still cooling" (warn) rather than "not cooling" (fail), degrees C.
        setpoint_tolerance_c: accepted difference between the set-point written and
            read back (the register holds 0.025 C steps), degrees C.
        dark_exposures_s: exposures of the dark frames, seconds (the bias frames give t = 0).
        light_exposure_s: exposure of the shutter test's light and dark frames, seconds
            (long enough for a mechanical shutter to open fully).
        bias_warn_frac, bias_fail_frac: accepted relative deviation of the bias level.
        noise_warn_ratio, noise_fail_ratio: accepted factor between measured and
            expected read noise (either way).
        dark_warn_ratio, dark_fail_ratio: dark current above this many times the
            expected value (plus three times its measurement uncertainty) warns / fails.
        light_sigma: a pixel is lit when it exceeds the dark level by this many noise sigmas.
        min_lit_pixels: pixels that must be lit for "light seen" (a beam spot lights
            hundreds; a few can be cosmic rays).
    """

    stage_step_deg: float = 2.0
    stage_tolerance_deg: float | None = None
    cooler_wait_s: float = 60.0
    cooler_poll_s: float = 0.5
    cooler_min_drop_c: float = 0.5
    setpoint_tolerance_c: float = 0.5
    dark_exposures_s: tuple[float, ...] = (1.0, 4.0)
    light_exposure_s: float = 0.1
    bias_warn_frac: float = 0.2
    bias_fail_frac: float = 0.5
    noise_warn_ratio: float = 1.4
    noise_fail_ratio: float = 2.0
    dark_warn_ratio: float = 3.0
    dark_fail_ratio: float = 10.0
    light_sigma: float = 6.0
    min_lit_pixels: int = 20

    def __post_init__(self) -> None:
        positive = {"stage_step_deg": self.stage_step_deg, "cooler_poll_s": self.cooler_poll_s,
                    "light_exposure_s": self.light_exposure_s, "light_sigma": self.light_sigma}
        for k, v in positive.items():
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{k} must be > 0, got {v!r}")
        if self.stage_tolerance_deg is not None and not self.stage_tolerance_deg > 0:
            raise ValueError(f"stage_tolerance_deg must be > 0, got {self.stage_tolerance_deg!r}")
        if not self.cooler_wait_s >= 0:
            raise ValueError(f"cooler_wait_s must be >= 0, got {self.cooler_wait_s!r}")
        if not self.dark_exposures_s or any(not (math.isfinite(t) and t > 0) for t in self.dark_exposures_s):
            raise ValueError(f"dark_exposures_s must be positive times, got {self.dark_exposures_s!r}")
        if not (0 < self.bias_warn_frac <= self.bias_fail_frac):
            raise ValueError("need 0 < bias_warn_frac <= bias_fail_frac")
        if not (1 < self.noise_warn_ratio <= self.noise_fail_ratio):
            raise ValueError("need 1 < noise_warn_ratio <= noise_fail_ratio")
        if not (1 < self.dark_warn_ratio <= self.dark_fail_ratio):
            raise ValueError("need 1 < dark_warn_ratio <= dark_fail_ratio")
        if self.min_lit_pixels < 1:
            raise ValueError("min_lit_pixels must be >= 1")


# --------------------------------------------------------------------------- frame statistics


def _clip_mask(a: np.ndarray) -> np.ndarray:
    """Pixels within CLIP_SIGMA robust sigmas of the median (hot pixels, cosmic rays out)."""
    med = float(np.median(a))
    mad = float(np.median(np.abs(a - med)))
    sigma = MAD_TO_SIGMA * mad
    if sigma == 0.0:  # integer data narrower than one ADU: keep what sits on the median
        sigma = max(float(np.std(a)), 0.5)
    return np.abs(a - med) <= CLIP_SIGMA * sigma


def level_adu(data: np.ndarray) -> float:
    """Mean level of a frame in ADU with outliers (hot pixels, cosmic rays, a small spot) left out."""
    a = np.asarray(data, dtype=np.float64).ravel()
    return float(a[_clip_mask(a)].mean())


def read_noise_adu(bias_a: np.ndarray, bias_b: np.ndarray) -> float:
    """Read noise in ADU from two bias frames.

    The difference of two frames cancels the fixed pattern (bias structure,
    hot pixels) and holds twice the read noise variance plus twice the
    rounding variance of the ADC (1/12 ADU^2 per frame), which is removed.
    """
    d = np.asarray(bias_a, dtype=np.float64).ravel() - np.asarray(bias_b, dtype=np.float64).ravel()
    kept = d[_clip_mask(d)]
    var = float(kept.var(ddof=1)) / 2.0 - QUANTISATION_VAR_ADU2
    return math.sqrt(max(var, 0.0))


def expected_dark_rate(sensor_rate_e_per_s: float, temp_c: float, reference_c: float = DARK_REFERENCE_C,
                       doubling_c: float = DARK_DOUBLING_C) -> float:
    """Dark current (e-/s/pixel) at ``temp_c`` from its value at ``reference_c``, doubling every ``doubling_c``."""
    return sensor_rate_e_per_s * 2.0 ** ((temp_c - reference_c) / doubling_c)


def fit_dark_line(exposures_s: Sequence[float], levels_adu: Sequence[float]) -> tuple[float, float]:
    """Least-squares line ``level = intercept + slope * t``; returns (slope ADU/s, intercept ADU)."""
    t = np.asarray(exposures_s, dtype=np.float64)
    y = np.asarray(levels_adu, dtype=np.float64)
    slope, intercept = np.polyfit(t, y, 1)
    return float(slope), float(intercept)


# --------------------------------------------------------------------------- stage


def stage_test_points(allowed: AngleRange, around: float, step_deg: float) -> tuple[float, float]:
    """(centre, step) of the small moves: ``centre - step``, ``centre``, ``centre + step`` all
    lie inside ``allowed``. The centre is the point of the range nearest ``around`` (the
    home angle) that leaves room for a step either way; a range narrower than four
    steps shrinks the step to a quarter of it."""
    step = min(step_deg, (allowed.hi - allowed.lo) / 4.0)
    centre = min(max(around, allowed.lo + step), allowed.hi - step)
    return centre, step


def stage_resolution_deg(stage: RotationStage) -> float | None:
    """Angle of one position count when the driver says (Sigma Koki: ``degrees_per_count``)."""
    v = getattr(stage, "degrees_per_count", None)
    return float(v) if isinstance(v, (int, float)) and v > 0 else None


#: Read-back tolerance for a stage whose driver does not report its resolution, degrees.
FALLBACK_STAGE_TOLERANCE_DEG = 0.01
#: Names of the results :func:`check_stage_motion` yields, in order.
STAGE_CHECKS = ("stage.home", "stage.moves", "stage.return")


def check_stage_motion(stage: RotationStage, options: SelfTestOptions) -> Iterator[CheckResult]:
    """Home, small moves inside the allowed range with read-back, and back to the start.

    Yields ``stage.home``, ``stage.moves`` and ``stage.return``. Raises the device's
    error if the stage faults (the caller reports it); targets never leave
    ``stage.allowed_range``.
    """
    r = stage.allowed_range
    res = stage_resolution_deg(stage)
    if options.stage_tolerance_deg is not None:
        tol = options.stage_tolerance_deg
    elif res is not None:
        tol = res + 1e-9  # a target is rounded to a count, and nudged by one at a range edge
    else:
        tol = FALLBACK_STAGE_TOLERANCE_DEG
    rng_text = f"[{r.lo:g}, {r.hi:g}] deg"
    start = stage.angle()

    home = stage.home_angle()
    if home not in r:
        yield CheckResult(
            "stage.home", "fail", f"home angle {home:.3f} deg is outside the allowed range {rng_text}; not homed",
            {"home_deg": home, "allowed_deg": [r.lo, r.hi]}, f"home inside {rng_text}",
            "correct stage.zero_offset_deg in rig.yaml (the angle of the origin), or include it in "
            "allowed_range_deg if the cable wrap allows")
        return
    t0 = time.monotonic()
    stage.home()
    took = time.monotonic() - t0
    got = stage.angle()
    err = got - home
    yield CheckResult(
        "stage.home", "ok" if abs(err) <= tol else "fail",
        f"homed in {took:.2f} s, reads {got:.4f} deg",
        {"angle_deg": round(got, 6), "home_deg": home, "error_deg": round(err, 6), "seconds": round(took, 3)},
        f"{home:.4f} +/- {tol:.4f} deg",
        "the controller's count after homing is not 0: check stage.division and stage.zero_offset_deg "
        "against the controller's settings")

    centre, step = stage_test_points(r, home, options.stage_step_deg)
    targets = [centre, centre + step, centre - step, centre]
    errors: list[float] = []
    t0 = time.monotonic()
    for target in targets:
        stage.move_to(target)
        errors.append(stage.angle() - target)
    took = time.monotonic() - t0
    worst = max(abs(e) for e in errors)
    yield CheckResult(
        "stage.moves", "ok" if worst <= tol else "fail",
        f"{len(targets)} moves around {centre:.3f} deg (+/-{step:g} deg) in {took:.2f} s, "
        f"largest read-back error {worst:.4f} deg",
        {"targets_deg": [round(t, 6) for t in targets], "errors_deg": [round(e, 6) for e in errors],
         "seconds": round(took, 3)},
        f"every read-back within {tol:.4f} deg, all targets inside {rng_text}",
        "the controller does not stop at the commanded count: check stage.degrees_per_pulse and "
        "stage.division against the controller's settings")

    if start in r:
        stage.move_to(start)
        back = stage.angle()
        err = back - start
        yield CheckResult(
            "stage.return", "ok" if abs(err) <= tol else "fail",
            f"back at {back:.4f} deg (started at {start:.4f} deg)",
            {"angle_deg": round(back, 6), "start_deg": round(start, 6), "error_deg": round(err, 6)},
            f"{start:.4f} +/- {tol:.4f} deg",
            "the stage did not return to its start: run `rig selftest` again and send the transcript")
    else:
        # The start angle is the controller's count before homing; outside the range
        # it cannot be driven back to, so the stage stays at the test point.
        yield CheckResult(
            "stage.return", "warn",
            f"started at {start:.4f} deg, outside the allowed range {rng_text}; left at {stage.angle():.4f} deg",
            {"angle_deg": round(stage.angle(), 6), "start_deg": round(start, 6)},
            f"a start inside {rng_text}",
            "nothing to do if the controller had not been homed since power-on; otherwise check allowed_range_deg")


# --------------------------------------------------------------------------- filters


def filter_check_names(changer: FilterChanger) -> list[str]:
    """Names of the results :func:`check_filters` yields, in order (``filter.restore`` is
    only reported when putting the original filter back fails)."""
    from drivers.manual_filter import ManualFilterChanger

    if isinstance(changer, ManualFilterChanger):
        return ["filter.positions"]
    return [f"filter.{n}" for n in changer.names()] + ["filter.restore"]


def check_filters(changer: FilterChanger) -> Iterator[CheckResult]:
    """Every configured filter selected and read back (``filter.<name>``), then the
    filter that was in the beam put back. A manual changer is not driven (the operator
    is the device)."""
    from drivers.manual_filter import ManualFilterChanger

    if isinstance(changer, ManualFilterChanger):
        yield CheckResult("filter.positions", "ok", "manual changer: nothing to drive (the operator changes filters)",
                          {"filters": changer.names()})
        return
    original = changer.current()
    for name in changer.names():
        t0 = time.monotonic()
        changer.select(name)
        took = time.monotonic() - t0
        back = changer.current()
        pos = changer.positions[name]
        yield CheckResult(
            f"filter.{name}", "ok" if back == name else "fail",
            f"selected position {pos} in {took:.2f} s, reads back {back!r}",
            {"position": pos, "read_back": back, "seconds": round(took, 3)},
            f"{name!r}",
            "the wheel stands at another position than commanded: check filter.positions in rig.yaml "
            "and the wheel's position count (6 or 12)")
    if original is not None and changer.current() != original:
        changer.select(original)


# --------------------------------------------------------------------------- camera


def check_identity(role: str, device: Any, expected: str) -> CheckResult:
    """``<role>.identity``: what the device says it is, and that it names ``expected``."""
    ident = device.identity()
    ok = expected.lower() in ident.lower()
    return CheckResult(
        f"{role}.identity", "ok" if ok else "fail", ident, {"identity": ident}, f"a {expected}",
        f"another device answers for the {role}: run `rig devices --scan` and fix the {role} entry in rig.yaml")


def check_cooler(camera: Camera, setpoint_c: float, options: SelfTestOptions, *,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep) -> CheckResult:
    """``camera.cooler``: switch the cooler on at ``setpoint_c`` and watch it for at most
    ``options.cooler_wait_s`` seconds. The cooler is left on (a capture wants it so)."""
    before = camera.cooler_status()
    camera.set_cooler(setpoint_c, on=True)
    t0 = clock()
    st = camera.cooler_status()
    first_c = before.temperature_c
    while not st.at_temperature and clock() - t0 < options.cooler_wait_s:
        sleep(min(options.cooler_poll_s, max(0.0, options.cooler_wait_s - (clock() - t0))))
        st = camera.cooler_status()
    waited = clock() - t0
    drop = first_c - st.temperature_c
    measured = {"temperature_c": round(st.temperature_c, 2), "setpoint_c": round(st.setpoint_c, 3),
                "drive_percent": round(st.drive_percent, 1), "cooler_on": st.on,
                "at_temperature": st.at_temperature, "waited_s": round(waited, 2), "cooled_by_c": round(drop, 2)}
    expected = f"cooler on, CCD at {setpoint_c:g} C within {options.cooler_wait_s:g} s"
    if not st.on:
        return CheckResult("camera.cooler", "fail", "the cooler reports off after being switched on", measured,
                           expected, "check the camera's 12 V power supply (the cooler needs it), then power-cycle it")
    if abs(st.setpoint_c - setpoint_c) > options.setpoint_tolerance_c:
        return CheckResult("camera.cooler", "fail", f"set-point reads back {st.setpoint_c:.2f} C, not {setpoint_c:g} C",
                           measured, expected, "power-cycle the camera and run `rig selftest` again")
    where = f"CCD {st.temperature_c:.2f} C, set-point {st.setpoint_c:.2f} C, drive {st.drive_percent:.0f}%"
    if st.at_temperature:
        return CheckResult("camera.cooler", "ok", f"{where}, at temperature after {waited:.1f} s", measured, expected)
    if drop >= options.cooler_min_drop_c:
        return CheckResult("camera.cooler", "warn", f"{where}: still cooling (down {drop:.1f} C in {waited:.0f} s); "
                           "the dark check below uses the present temperature", measured, expected,
                           "let the camera reach its set-point (a few minutes) before a capture")
    if st.temperature_c < st.setpoint_c:
        return CheckResult("camera.cooler", "warn", f"{where}: below the set-point, warming towards it", measured,
                           expected, "wait a minute for the temperature to settle")
    if st.drive_percent >= 99.0:
        return CheckResult("camera.cooler", "warn", f"{where}: full drive and not reaching the set-point", measured,
                           expected, "raise camera.cooler_setpoint_c in rig.yaml (the cooler cannot pull this far "
                           "below the room temperature) or improve the airflow around the camera")
    return CheckResult("camera.cooler", "fail", f"{where}: the cooler is on but the CCD does not cool", measured,
                       expected, "check the camera's power supply and fan, then power-cycle the camera")


@dataclass(frozen=True)
class BiasPair:
    """Two bias frames and what was measured from them (ADU)."""

    a: Frame
    b: Frame
    level_adu: float
    read_noise_adu: float


def _bias_band(expected: float, options: SelfTestOptions) -> str:
    return f"{expected:g} ADU +/-{options.bias_warn_frac:.0%} (fail beyond +/-{options.bias_fail_frac:.0%})"


def check_bias_and_noise(camera: Camera, options: SelfTestOptions) -> tuple[list[CheckResult], BiasPair]:
    """``camera.bias`` and ``camera.read_noise`` from two bias frames (the shortest
    exposure, shutter closed); read noise = std(a - b) / sqrt(2) * gain."""
    nm = NoiseModel.from_sensor(camera.sensor)
    t_min = camera.exposure_range_s[0]
    a = camera.expose(t_min, dark=True)
    b = camera.expose(t_min, dark=True)
    la, lb = level_adu(a.data), level_adu(b.data)
    level = 0.5 * (la + lb)
    noise_adu = read_noise_adu(a.data, b.data)
    noise_e = noise_adu * nm.gain_e_per_adu
    pair = BiasPair(a, b, level, noise_adu)

    dev = abs(level - nm.bias_adu) / nm.bias_adu
    status: Status = "ok" if dev <= options.bias_warn_frac else "warn" if dev <= options.bias_fail_frac else "fail"
    bias = CheckResult(
        "camera.bias", status, f"bias level {level:.1f} ADU (frames {la:.1f} and {lb:.1f}) at {t_min:g} s",
        {"bias_adu": round(level, 2), "frame_levels_adu": [round(la, 2), round(lb, 2)], "exposure_s": t_min,
         "ccd_temp_c": round(a.ccd_temp_c, 2)},
        _bias_band(nm.bias_adu, options),
        "the camera's offset differs from the sensor facts: power-cycle the camera; if it stays, "
        "measure the bias and correct bias_adu for this camera (drivers/alta_protocol.py KAF0261E)")

    ratio = noise_e / nm.read_noise_e if nm.read_noise_e > 0 else math.inf
    far = max(ratio, 1.0 / ratio) if ratio > 0 else math.inf
    status = "ok" if far <= options.noise_warn_ratio else "warn" if far <= options.noise_fail_ratio else "fail"
    noise = CheckResult(
        "camera.read_noise", status,
        f"read noise {noise_e:.2f} e- ({noise_adu:.3f} ADU at {nm.gain_e_per_adu:g} e-/ADU) from two bias frames",
        {"read_noise_e": round(noise_e, 3), "read_noise_adu": round(noise_adu, 4), "gain_e_per_adu": nm.gain_e_per_adu},
        f"{nm.read_noise_e:g} e- within x{options.noise_warn_ratio:g} (fail beyond x{options.noise_fail_ratio:g})",
        "noise far from the sensor's: check the camera's grounding and USB/power cables (pick-up), "
        "let it cool, and power-cycle it")
    return [bias, noise], pair


def check_dark(camera: Camera, bias: BiasPair, options: SelfTestOptions) -> CheckResult:
    """``camera.dark``: dark frames at ``options.dark_exposures_s``; the dark current is the
    slope of the level against exposure (bias frames at t = 0), compared with the
    sensor's value carried to the measured CCD temperature."""
    nm = NoiseModel.from_sensor(camera.sensor)
    g = nm.gain_e_per_adu
    frames = [camera.expose(t, dark=True) for t in options.dark_exposures_s]
    t_bias = bias.a.exposure_s
    times = [t_bias, t_bias] + [f.exposure_s for f in frames]
    levels = [level_adu(bias.a.data), level_adu(bias.b.data)] + [level_adu(f.data) for f in frames]
    slope, intercept = fit_dark_line(times, levels)
    rate = slope * g
    temp = float(np.mean([f.ccd_temp_c for f in frames]))
    expected_rate = expected_dark_rate(nm.dark_current_e_per_s, temp)
    # Uncertainty of the rate: the larger of the bias drift between the two bias
    # frames and the statistical error of a frame mean, over the longest exposure.
    n_pix = bias.a.data.size
    drift = abs(levels[0] - levels[1])
    level_err = max(drift, bias.read_noise_adu / math.sqrt(n_pix))
    rate_err = g * math.sqrt(2.0) * level_err / max(times)
    warn_at = options.dark_warn_ratio * expected_rate + 3.0 * rate_err
    fail_at = options.dark_fail_ratio * expected_rate + 3.0 * rate_err
    measured = {"dark_current_e_per_s": round(rate, 4), "expected_e_per_s": round(expected_rate, 4),
                "uncertainty_e_per_s": round(rate_err, 4), "ccd_temp_c": round(temp, 2),
                "exposures_s": [round(t, 6) for t in times], "levels_adu": [round(v, 3) for v in levels],
                "intercept_adu": round(intercept, 3)}
    expected = (f"{expected_rate:.3g} e-/s/pixel at {temp:.1f} C (sensor {nm.dark_current_e_per_s:g} at "
                f"{DARK_REFERENCE_C:g} C, x2 per {DARK_DOUBLING_C:g} C), at most x{options.dark_warn_ratio:g}")
    msg = (f"dark current {rate:.3g} +/- {rate_err:.2g} e-/s/pixel at {temp:.1f} C from "
           f"{len(frames)} dark frames ({', '.join(f'{f.exposure_s:g}' for f in frames)} s)")
    if rate > fail_at:
        return CheckResult("camera.dark", "fail", msg, measured, expected,
                           "far more dark signal than the sensor makes: check that the cooler works (camera.cooler) "
                           "and that no light reaches the sensor with the shutter closed (cover the lens and rerun)")
    if rate > warn_at:
        return CheckResult("camera.dark", "warn", msg, measured, expected,
                           "let the CCD reach its set-point; cover the lens to rule out a light leak")
    if rate < -3.0 * rate_err:
        return CheckResult("camera.dark", "warn", msg + "; the level falls with exposure", measured, expected,
                           "the bias drifts: let the camera warm up for 15 minutes after power-on and rerun")
    return CheckResult("camera.dark", "ok", msg, measured, expected)


def count_lit(frame: np.ndarray, reference: np.ndarray, pedestal_adu: float, threshold_adu: float) -> int:
    """Pixels of ``frame`` above ``reference + pedestal`` by more than ``threshold_adu``."""
    d = np.asarray(frame, dtype=np.float64) - np.asarray(reference, dtype=np.float64) - pedestal_adu
    return int(np.count_nonzero(d > threshold_adu))


def check_shutter(camera: Camera, bias: BiasPair, options: SelfTestOptions) -> CheckResult:
    """``camera.shutter``: a light frame and a dark frame of ``options.light_exposure_s``.

    Light above the dark level in the light frame shows the shutter opens; none in
    the dark frame shows it closes. No light at all is a warning (the beam may be
    off); light in the dark frame is a failure (a shutter that stays open).
    """
    nm = NoiseModel.from_sensor(camera.sensor)
    g = nm.gain_e_per_adu
    t = options.light_exposure_s
    light = camera.expose(t, dark=False)
    dark = camera.expose(t, dark=True)
    ref = bias.a.data
    pedestal = level_adu(dark.data) - bias.level_adu  # dark signal of this exposure, ADU
    # noise of (frame - bias frame): two read noises, two roundings, the dark's shot noise
    sigma = math.sqrt(2.0 * bias.read_noise_adu ** 2 + 2.0 * QUANTISATION_VAR_ADU2 + max(pedestal, 0.0) / g)
    thr = options.light_sigma * sigma
    lit_light = count_lit(light.data, ref, pedestal, thr)
    lit_dark = count_lit(dark.data, ref, pedestal, thr)
    diff = light.data.astype(np.float64) - dark.data.astype(np.float64)
    peak = float(diff.max())
    saturated = int(np.count_nonzero(light.data >= nm.saturation_adu))
    measured = {"exposure_s": light.exposure_s, "lit_pixels_light": lit_light, "lit_pixels_dark": lit_dark,
                "peak_signal_adu": round(peak, 1), "saturated_pixels": saturated, "threshold_adu": round(thr, 2)}
    expected = (f"light frame: >= {options.min_lit_pixels} pixels {options.light_sigma:g} sigma above dark; "
                "dark frame: none")
    found = (f"{lit_light} pixels lit in the {t:g} s light frame (peak {peak:.0f} ADU above dark"
             f"{f', {saturated} saturated' if saturated else ''}), {lit_dark} in the dark frame")
    if lit_dark >= options.min_lit_pixels and lit_dark >= 0.5 * lit_light:
        return CheckResult("camera.shutter", "fail", f"{found}: light reaches the sensor with the shutter closed",
                           measured, expected,
                           "the shutter stays open (or light leaks in): power-cycle the camera; if it persists, "
                           "the shutter needs service")
    if lit_light < options.min_lit_pixels:
        return CheckResult("camera.shutter", "warn", f"{found}: no light seen", measured, expected,
                           "switch the beam on and point it at the slab (ignore this if the beam is meant to be "
                           "off); if the beam is on, the shutter may not open")
    if lit_dark >= options.min_lit_pixels:
        return CheckResult("camera.shutter", "warn", f"{found}: some light in the dark frame", measured, expected,
                           "shield the camera from room light (a light leak) and rerun")
    return CheckResult("camera.shutter", "ok", f"{found}: the shutter opens and closes", measured, expected)


# --------------------------------------------------------------------------- running the checks


def fault_fix(err: DeviceError) -> str:
    """One line saying what to do after a device raised during a check."""
    who = err.device or "device"
    if isinstance(err, DeviceConnectionError):
        return f"check the {who}'s cable and power, then run `rig selftest` again"
    if isinstance(err, DeviceTimeout):
        return f"the {who} stopped answering in time: check its cable and power; send the transcript if it persists"
    if isinstance(err, LimitError):
        if who == "stage":
            return "a limit was reached: check the stage's travel and cable wrap, and allowed_range_deg in rig.yaml"
        return f"a request outside what the {who} can do: check its entry in rig.yaml"
    if isinstance(err, ProtocolError):
        return f"the {who} refused or garbled a command: power-cycle it and rerun; send the transcript if it persists"
    if isinstance(err, StateError):
        return f"the {who} was busy or stopped by someone else: let it finish, then run `rig selftest` again"
    return "run `rig selftest` again and send the transcript with the report"


class _Run:
    """Collects results, writes them to the transcript and tells the caller as they come."""

    def __init__(self, transcript: Transcript | None, on_result: Callable[[CheckResult], None] | None) -> None:
        self.results: list[CheckResult] = []
        self.broken: dict[str, str] = {}  # device -> the check it failed in
        self._transcript = transcript
        self._on_result = on_result

    def note(self, text: str) -> None:
        if self._transcript is not None:
            self._transcript.record(TRANSCRIPT_NAME, "!", text)

    def add(self, result: CheckResult) -> None:
        self.results.append(result)
        self.note(result.line())
        if self._on_result is not None:
            self._on_result(result)

    def not_run(self, name: str, device: str) -> None:
        self.add(CheckResult(name, "fail", f"not run: the {device} failed in {self.broken[device]}",
                             fix="fix that failure first"))

    def guarded(self, device: str, name: str, produce: Callable[[], Any]) -> Any:
        """Run ``produce`` (which adds results); a device error becomes a fail result named
        ``name`` and marks the device broken, so its later checks are reported as not run."""
        if device in self.broken:
            self.not_run(name, device)
            return None
        try:
            return produce()
        except DeviceError as e:
            self._fault(device, name, e)
            return None

    def each(self, device: str, names: Sequence[str], results: Callable[[], Iterator[CheckResult]]) -> None:
        """Like :meth:`guarded` for a generator yielding the checks ``names`` in order: a
        fault is reported under the name of the check that was running, and the checks
        after it as not run."""
        done = 0
        if device not in self.broken:
            try:
                for r in results():
                    self.add(r)
                    done += 1
                return
            except DeviceError as e:
                self._fault(device, names[min(done, len(names) - 1)], e)
                done += 1
        for name in names[done:]:
            self.not_run(name, device)

    def _fault(self, device: str, name: str, e: DeviceError) -> None:
        self.broken[device] = name
        self.add(CheckResult(name, "fail", str(e), {"error": type(e).__name__}, fix=fault_fix(e)))


def expected_identities(cfg: RigConfig, camera: Camera) -> dict[str, str]:
    """What each device's identity must name: the stage model, the sensor, the wheel."""
    wheel = {"fw102c": "FW102C", "manual": "manual"}.get(cfg.filter.driver, cfg.filter.driver)
    return {"stage": cfg.stage.model, "camera": camera.sensor.model, "filter": wheel}


def _make_safe(rig: Rig, roi: ROI, run: _Run) -> None:
    """Stop the stage and force the shutter closed; failures are reported, never raised."""
    actions: list[tuple[str, str, Callable[[], None], str]] = [
        ("safety.stage", "stop the stage", rig.stage.stop,
         "make sure the stage stands still (STOP on the controller's front panel) before touching the rig"),
        ("safety.shutter", "close the shutter", lambda: rig.camera.set_shutter(ShutterMode.CLOSED),
         "the shutter closes when the camera is idle or power-cycled: check it before the next exposure"),
        ("safety.roi", "restore the camera's region of interest", lambda: rig.camera.set_roi(roi),
         "nothing to do: the next program sets its own region of interest"),
    ]
    done = []
    for name, what, act, fix in actions:
        try:
            act()
            done.append(what)
        except DeviceError as e:
            run.add(CheckResult(name, "fail", f"could not {what}: {e}", {"error": type(e).__name__}, fix=fix))
    run.note(f"safety: {'; '.join(done) if done else 'nothing could be done'}")


def run_selftest(rig: Rig, options: SelfTestOptions | None = None, *,
                 on_result: Callable[[CheckResult], None] | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep) -> SelfTestReport:
    """Run every check on an opened rig.

    Args:
        rig: the opened devices (:func:`rig.wiring.open_rig`); results go to its transcript.
        options: what to do and the accepted deviations.
        on_result: called with each result as it is taken (e.g. to print it).
        clock, sleep: time source and wait used while watching the cooler.

    Returns:
        The report. A device fault becomes a fail result; Ctrl-C and other
        exceptions propagate, after the stage was stopped and the shutter closed.
    """
    opts = options or SelfTestOptions()
    run = _Run(rig.transcript, on_result)
    cfg = rig.config
    stage, camera, changer = rig.stage, rig.camera, rig.changer
    run.note(f"start: config {cfg.path}, {'simulated' if rig.simulated else 'real'} rig")
    roi = camera.roi
    try:
        expected = expected_identities(cfg, camera)
        for role, dev in (("stage", stage), ("camera", camera), ("filter", changer)):
            def identity(r: str = role, d: Any = dev) -> None:
                run.add(check_identity(r, d, expected[r]))

            run.guarded(role, f"{role}.identity", identity)
        run.each("stage", STAGE_CHECKS, lambda: check_stage_motion(stage, opts))
        run.each("filter", filter_check_names(changer), lambda: check_filters(changer))

        def cooler() -> None:
            run.add(check_cooler(camera, cfg.camera.cooler_setpoint_c, opts, clock=clock, sleep=sleep))

        run.guarded("camera", "camera.cooler", cooler)

        def bias() -> BiasPair:
            camera.set_roi(ROI(0, 0, camera.sensor.width, camera.sensor.height))
            results, pair = check_bias_and_noise(camera, opts)
            for r in results:
                run.add(r)
            return pair

        pair = run.guarded("camera", "camera.bias", bias)
        if pair is not None:
            run.guarded("camera", "camera.dark", lambda: run.add(check_dark(camera, pair, opts)))
            run.guarded("camera", "camera.shutter", lambda: run.add(check_shutter(camera, pair, opts)))
        else:
            for name in ("camera.dark", "camera.shutter"):
                run.add(CheckResult(name, "fail", "not run: no bias frames (camera.bias failed)",
                                    fix="fix that failure first"))
    finally:
        _make_safe(rig, roi, run)
    report = SelfTestReport(run.results, cfg.path, rig.simulated)
    run.note(report.summary())
    return report


# --------------------------------------------------------------------------- opening the rig


def default_transcript_path(directory: str | Path = ".", now: datetime | None = None) -> Path:
    """``selftest-<UTC time>.log`` in ``directory``, with a counter if that name is taken."""
    stamp = (now or datetime.now(UTC)).strftime("%Y%m%dT%H%M%SZ")
    base = Path(directory)
    path = base / f"selftest-{stamp}.log"
    n = 1
    while path.exists():
        path = base / f"selftest-{stamp}-{n}.log"
        n += 1
    return path


def device_label(role: str, cfg: RigConfig) -> str:
    """The device as the lab knows it: kind and port, e.g. ``filter wheel (FW102C on /dev/ttyUSB1)``."""
    if role == "stage":
        return f"stage ({cfg.stage.model} on {cfg.stage.port})"
    if role == "filter":
        if cfg.filter.driver == "manual":
            return "filter (manual changer)"
        return f"filter wheel (FW102C on {cfg.filter.port})"
    if role == "camera":
        sn = f", serial {cfg.camera.serial_number}" if cfg.camera.serial_number else ""
        return (f"camera (Apogee Alta-U, USB {alta_protocol.VENDOR_ID:04x}:{alta_protocol.PRODUCT_ID:04x}{sn})")
    return role or "device"


def describe_open_problem(err: DeviceError, cfg: RigConfig, *, sim: bool = False) -> DeviceConnectionError:
    """The error of a device that cannot be opened, re-worded as one line naming the
    device and the fix: ``<device (kind, port)>: <what is wrong> -> fix: <what to do>``."""
    from drivers.apogee_alta import BUSY_HINT, UDEV_HINT
    from rig.doctor import UDEV_FIX, check_serial_port

    role = err.device
    what = str(err.args[0]) if err.args else str(err)
    fix = ""
    if role == "camera":
        if what == UDEV_HINT:
            what = "no permission to open the camera without root (no udev rule for USB vendor 125c)"
            fix = UDEV_FIX
        elif what == BUSY_HINT:
            what = "the camera is in use by another program (MaxIm DL, an INDI server, another rig process)"
            fix = ("close that program (`fuser -v /dev/bus/usb/*/*` names it) or re-plug the camera, "
                   "then run `rig selftest` again")
        elif isinstance(err, DeviceConnectionError):
            fix = "check the camera's power and USB cable; `rig doctor` checks USB access, `rig devices --scan` lists it"
    elif role in ("stage", "filter") and isinstance(err, DeviceConnectionError):
        port = cfg.stage.port if role == "stage" else cfg.filter.port
        access = check_serial_port(role, port) if not sim else None
        if access is not None and access.status == "fail":
            what, fix = access.message, access.fix
        else:
            kind = f"{cfg.stage.model} controller" if role == "stage" else "FW102C wheel"
            fix = (f"`rig devices --scan` lists the ports: set {role}.port in rig.yaml to the {kind}'s port, "
                   "and check its cable and that it is switched on")
    if not fix:
        fix = fault_fix(err)
    return DeviceConnectionError(f"{what} -> fix: {fix}", device=device_label(role, cfg))


OpenRig = Callable[..., "Rig"]


def selftest_from_config(cfg: RigConfig, *, sim: bool = False, transcript_path: str | Path,
                         options: SelfTestOptions | None = None,
                         on_result: Callable[[CheckResult], None] | None = None,
                         open_rig: OpenRig | None = None) -> SelfTestReport:
    """Open the rig of ``cfg`` with a byte transcript at ``transcript_path``, run every
    check, close the rig.

    Args:
        open_rig: ``(cfg, *, sim, log_io) -> Rig``; default :func:`rig.wiring.open_rig`.

    Raises:
        DeviceConnectionError: a device cannot be opened (wrong device on the port,
            camera busy, no permission, ...); the message is one line naming the
            device and the fix, and is also written to the transcript.
    """
    if open_rig is None:
        from rig.wiring import open_rig as _open

        open_rig = _open
    path = str(transcript_path)
    header = Transcript(path)
    header.record(TRANSCRIPT_NAME, "!", f"rig selftest at {datetime.now(UTC).isoformat(timespec='seconds')}"
                  f", config {cfg.path}{', --sim' if sim else ''}")
    header.close()
    try:
        rig = open_rig(cfg, sim=sim, log_io=path)
    except DeviceError as e:
        problem = describe_open_problem(e, cfg, sim=sim)
        note = Transcript(path)
        note.record(TRANSCRIPT_NAME, "!", f"cannot open: {problem}")
        note.close()
        raise problem from None
    with rig:
        report = run_selftest(rig, options, on_result=on_result)
    report.transcript_path = path
    return report
