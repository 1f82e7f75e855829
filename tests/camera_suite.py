"""Shared behaviour every :class:`drivers.interfaces.Camera` implementation must show.

Use it by subclassing in a test module that provides a function-scoped
``camera`` fixture (a fresh, open camera; exposures there should be cheap):

    from camera_suite import CameraInterfaceSuite

    class TestMyCamera(CameraInterfaceSuite):
        pass
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.errors import LimitError, ParameterError
from drivers.interfaces import ROI, Camera, CoolerStatus, Frame, ShutterMode


class CameraInterfaceSuite:
    """Interface-level checks, parametrised by the ``camera`` fixture."""

    def test_is_a_camera_with_an_identity(self, camera: Camera):
        assert isinstance(camera, Camera)
        ident = camera.identity()
        assert isinstance(ident, str) and ident.strip()

    def test_sensor_facts_are_physical(self, camera: Camera):
        s = camera.sensor
        assert s.width > 0 and s.height > 0 and s.pixel_size_um > 0
        assert s.gain_e_per_adu > 0 and s.read_noise_e >= 0 and s.full_well_e > 0
        assert 0 < s.bias_adu < s.adc_max
        lo, hi = camera.exposure_range_s
        assert 0 < lo < hi

    def test_expose_returns_a_uint16_frame_with_metadata(self, camera: Camera):
        camera.set_roi(ROI(0, 0, 32, 16))
        t = max(camera.exposure_range_s[0], 1e-3)
        f = camera.expose(t)
        assert isinstance(f, Frame)
        assert f.data.dtype == np.uint16 and f.data.shape == (16, 32) == f.roi.shape
        assert f.roi == camera.roi
        assert f.exposure_s == pytest.approx(t, rel=0.01, abs=1e-5)
        assert f.start_time <= f.end_time
        assert math.isfinite(f.ccd_temp_c)
        assert f.dark is False

    def test_dark_frame_sits_near_the_bias(self, camera: Camera):
        camera.set_roi(ROI(0, 0, 64, 32))
        f = camera.expose(camera.exposure_range_s[0], dark=True)
        s = camera.sensor
        assert f.dark is True
        assert abs(float(f.data.mean()) - s.bias_adu) < 5 * max(s.read_noise_e / s.gain_e_per_adu, 1.0)

    @pytest.mark.parametrize("factor", [0.5, 2.0])
    def test_exposure_outside_the_range_is_refused(self, camera: Camera, factor):
        lo, hi = camera.exposure_range_s
        with pytest.raises(LimitError):
            camera.expose(lo * factor if factor < 1 else hi * factor)

    @pytest.mark.parametrize("bad", [math.nan, math.inf, "one", None])
    def test_malformed_exposure_is_a_parameter_error(self, camera: Camera, bad):
        with pytest.raises(ParameterError):
            camera.expose(bad)

    def test_roi_and_binning_set_the_frame_shape(self, camera: Camera):
        camera.set_roi(ROI(16, 8, 32, 16, bin_x=2, bin_y=2))
        f = camera.expose(max(camera.exposure_range_s[0], 1e-3))
        assert f.data.shape == (8, 16)
        assert f.roi.bin_x == 2 and f.roi.bin_y == 2

    @pytest.mark.parametrize("roi", [
        ROI(-1, 0, 10, 10), ROI(0, 0, 0, 10), ROI(500, 0, 100, 10), ROI(0, 0, 10, 10, bin_x=3), ROI(0, 0, 10, 10, bin_y=0),
    ])
    def test_roi_off_the_sensor_is_refused(self, camera: Camera, roi):
        before = camera.roi
        with pytest.raises(LimitError):
            camera.set_roi(roi)
        assert camera.roi == before

    def test_shutter_modes(self, camera: Camera):
        for mode in ("open", "closed", ShutterMode.NORMAL):
            camera.set_shutter(mode)
        with pytest.raises(ParameterError):
            camera.set_shutter("ajar")

    @pytest.mark.parametrize("bad", [-61.0, 39.5, math.nan])
    def test_cooler_setpoint_out_of_range(self, camera: Camera, bad):
        with pytest.raises((LimitError, ParameterError)):
            camera.set_cooler(bad)

    def test_cooler_status_and_temperature(self, camera: Camera):
        camera.set_cooler(-10.0)
        st = camera.cooler_status()
        assert isinstance(st, CoolerStatus)
        assert st.on is True and st.setpoint_c == pytest.approx(-10.0, abs=0.05)
        assert 0.0 <= st.drive_percent <= 100.0
        assert isinstance(camera.temperature(), float)
        camera.set_cooler(0.0, on=False)
        assert camera.cooler_status().on is False
