"""Interface tests every RotationStage implementation must pass.

Use it by subclassing in a test module and providing a fixture
``make_stage(allowed: AngleRange) -> RotationStage`` that opens a fresh stage
(standing at its home angle, which must lie inside :data:`ALLOWED`) and closes
it after the test. Moves should be fast (a simulated time scale), but
:data:`SLOW_SPEED_DEG_S` must make a 100 degree move take a visible fraction of
a second in real time, so that stopping mid-move can be observed.
"""

from __future__ import annotations

import math
import random
import time

import pytest

from drivers.errors import (
    DeviceError,
    DeviceTimeout,
    LimitError,
    ParameterError,
    StateError,
)
from drivers.interfaces import AngleRange, RotationStage

ALLOWED = AngleRange(15.0, 185.0)
#: Tolerance of a reached angle: the implementation's resolution or better.
TOL_DEG = 0.005


class RotationStageSuite:
    """The shared tests; ``make_stage``, ``slow_speed_deg_s`` are fixtures of the subclass's module."""

    @pytest.fixture
    def stage(self, make_stage) -> RotationStage:
        return make_stage(ALLOWED)

    # ---------------------------------------------------------------- facts
    def test_identity_is_read(self, stage):
        ident = stage.identity()
        assert isinstance(ident, str) and ident.strip()

    def test_allowed_range_cannot_exceed_hardware(self, make_stage):
        s = make_stage(AngleRange(-1000.0, 1000.0))
        hw = type(s).hardware_range
        assert s.allowed_range.lo >= hw.lo and s.allowed_range.hi <= hw.hi
        with pytest.raises(AttributeError):
            s.allowed_range = AngleRange(-5000.0, 5000.0)  # read-only

    def test_home_angle_is_inside_the_test_range(self, stage):
        assert stage.home_angle() in ALLOWED
        assert stage.angle() == pytest.approx(stage.home_angle(), abs=TOL_DEG)

    # ---------------------------------------------------------------- moves
    @pytest.mark.parametrize("target", [ALLOWED.lo, 47.5, 90.0, 133.3333, ALLOWED.hi])
    def test_move_reaches_target(self, stage, target):
        stage.move_to(target)
        assert not stage.is_busy()
        assert stage.angle() == pytest.approx(target, abs=TOL_DEG)
        assert stage.angle() in stage.allowed_range

    def test_move_to_present_angle_is_harmless(self, stage):
        here = stage.angle()
        stage.move_to(here)
        assert stage.angle() == pytest.approx(here, abs=TOL_DEG)

    @pytest.mark.parametrize("target", [ALLOWED.lo - 0.01, ALLOWED.hi + 5.0, -90.0, 359.0, 1e9])
    def test_targets_outside_are_refused_without_moving(self, stage, target):
        before = stage.angle()
        with pytest.raises(LimitError):
            stage.move_to(target)
        assert not stage.is_busy()
        assert stage.angle() == pytest.approx(before, abs=1e-9)

    @pytest.mark.parametrize("target", [math.nan, math.inf, -math.inf, "ninety", None])
    def test_malformed_targets_are_refused_without_moving(self, stage, target):
        before = stage.angle()
        with pytest.raises(ParameterError):
            stage.move_to(target)  # type: ignore[arg-type]
        assert not stage.is_busy()
        assert stage.angle() == pytest.approx(before, abs=1e-9)

    def test_home(self, stage):
        stage.move_to(150.0)
        stage.home()
        assert stage.angle() == pytest.approx(stage.home_angle(), abs=TOL_DEG)

    def test_home_outside_the_allowed_range_is_refused(self, make_stage):
        probe = make_stage(ALLOWED)
        home = probe.home_angle()
        s = make_stage(AngleRange(home + 10.0, home + 60.0))
        with pytest.raises(LimitError):
            s.home()
        assert not s.is_busy()

    def test_start_then_wait(self, stage, slow_speed_deg_s):
        stage.set_speed(slow_speed_deg_s)
        stage.move_to(40.0, wait=False)
        assert stage.is_busy()
        with pytest.raises(StateError):
            stage.move_to(60.0)  # still moving
        stage.wait(stage.move_time_s(stage.home_angle(), 40.0))
        assert not stage.is_busy()
        assert stage.angle() == pytest.approx(40.0, abs=TOL_DEG)

    def test_stop_mid_move(self, stage, slow_speed_deg_s):
        start = stage.angle()
        stage.set_speed(slow_speed_deg_s)
        stage.move_to(ALLOWED.hi, wait=False)
        time.sleep(0.05)
        stage.stop()
        stage.wait(5.0)
        here = stage.angle()
        assert start < here < ALLOWED.hi
        stage.stop()  # stopping an idle stage is harmless
        assert stage.angle() == pytest.approx(here, abs=1e-9)

    def test_wait_times_out_and_stops_the_stage(self, stage, slow_speed_deg_s):
        stage.set_speed(slow_speed_deg_s)
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout):
            stage.move_to(ALLOWED.lo, timeout_s=0.02)
        assert time.monotonic() - t0 < 2.0
        deadline = time.monotonic() + 5.0
        while stage.is_busy():  # decelerating after the stop
            assert time.monotonic() < deadline
            time.sleep(0.01)
        assert ALLOWED.lo < stage.angle() < stage.home_angle()

    # ---------------------------------------------------------------- speed
    def test_speed(self, stage):
        stage.set_speed(5.0)
        assert stage.speed() == pytest.approx(5.0, rel=0.05)
        for bad in (0.0, -1.0, math.nan, math.inf):
            with pytest.raises(ParameterError):
                stage.set_speed(bad)
        assert stage.speed() == pytest.approx(5.0, rel=0.05)

    def test_move_time_bound(self, stage):
        short = stage.move_time_s(90.0, 91.0)
        long = stage.move_time_s(90.0, 180.0)
        assert 0 < short < long
        assert long >= 90.0 / stage.speed()

    # ---------------------------------------------------------------- safety
    def test_random_requests_never_leave_the_range(self, stage):
        rng = random.Random(7)
        for _ in range(12):
            target = rng.uniform(ALLOWED.lo - 40.0, ALLOWED.hi + 40.0)
            try:
                stage.move_to(target)
            except LimitError:
                assert target not in ALLOWED
            assert stage.angle() in stage.allowed_range

    def test_closed_stage_refuses_calls(self, make_stage):
        with make_stage(ALLOWED) as s:
            s.move_to(100.0)
        with pytest.raises(DeviceError):
            s.angle()
        s.close()  # closing twice is harmless
