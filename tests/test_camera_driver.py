"""The Alta-U driver against its twin, through the real USB requests (pyusb with
the twin as backend; nothing patched). Statistics are checked against the
KAF-0261E model's parameters, not against numbers copied from a run."""

from __future__ import annotations

import io
import math
import time

import numpy as np
import pytest
import usb.core
from camera_suite import CameraInterfaceSuite

from drivers import alta_protocol as ap
from drivers.apogee_alta import AltaCamera
from drivers.errors import (
    DeviceConnectionError,
    DeviceTimeout,
    LimitError,
    ParameterError,
    ProtocolError,
)
from drivers.interfaces import ROI, ShutterMode
from drivers.iolog import Transcript
from sim_devices.alta_usb import AMBIENT_C, AltaBackend
from sim_devices.bench import Bench, drop_bench, set_bench
from sim_devices.ccd_sensor import CcdModel
from sim_devices.faults import FaultPlan

FAST = 1000.0  # simulated seconds per real second
S = ap.KAF0261E
READ_ADU = S.read_noise_e / S.gain_e_per_adu


@pytest.fixture
def bench_name(request):
    """A private bench per test (no light unless the test installs a scene)."""
    name = f"alta-{request.node.name}"
    set_bench(name, Bench(scene=lambda a, f, r, c: np.zeros((r.stop - r.start, c.stop - c.start))))
    yield name
    drop_bench(name)


def use_scene(name: str, fn) -> None:
    set_bench(name, Bench(scene=fn))


@pytest.fixture
def backend(bench_name):
    return AltaBackend(bench_name, time_scale=FAST, seed=11)


@pytest.fixture
def camera(backend):
    cam = AltaCamera(backend=backend)
    yield cam
    cam.close()


class TestAltaCameraInterface(CameraInterfaceSuite):
    """The shared Camera suite, run against the Alta-U driver and its twin."""


def background(f) -> float:
    """Expected dark level (ADU) of a frame: bias plus the model's dark charge."""
    return S.bias_adu + CcdModel().dark_rate(f.ccd_temp_c) * f.exposure_s * f.roi.bin_x * f.roi.bin_y / S.gain_e_per_adu


def wait_for(predicate, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} not reached within {timeout_s} s")
        time.sleep(0.005)


# ----------------------------------------------------------------- identity and transport


def test_identity_comes_from_the_id_and_firmware_registers(bench_name):
    be = AltaBackend(bench_name, time_scale=FAST, serial_number="A123", firmware=16)
    with AltaCamera(backend=be) as cam:
        assert cam.identity() == "Apogee Alta-U camera id 2 (KAF-0261E) firmware 16 serial A123"
        assert cam.firmware == 16
        assert cam.expose(1e-3, dark=True).data.shape == (512, 512)  # 27-byte status from firmware 16


def test_descriptors_seen_through_pyusb(backend):
    dev = usb.core.find(idVendor=0x125C, idProduct=0x0010, backend=backend)
    assert dev is not None and (dev.bus, dev.address, dev.port_number, dev.speed) == (1, 4, 2, 3)
    ep = dev[0][(0, 0)][0]
    assert ep.bEndpointAddress == 0x86 and ep.bmAttributes == 2
    assert dev.serial_number == "SIM0001"


def test_twin_answers_the_documented_requests_byte_for_byte(backend):
    """Raw pyusb, no driver: the request table of device-protocols.md section 2."""
    import errno

    dev = usb.core.find(idVendor=0x125C, idProduct=0x0010, backend=backend)
    assert bytes(dev.ctrl_transfer(0xC0, 0xC2, 0, 100, 2)) == b"\x02\x00"  # camera id 2: KAF-0261E
    assert bytes(dev.ctrl_transfer(0xC0, 0xC2, 0, 101, 2)) == b"\x0e\x00"  # firmware 14
    status = bytes(dev.ctrl_transfer(0xC0, 0xC0, 0, 0, 21))
    assert len(status) == 21 and ap.parse_status(status).ccd_temp_c == pytest.approx(AMBIENT_C, abs=0.03)
    assert dev.ctrl_transfer(0x40, 0xC2, 0, 55, b"\x7f\x06") == 2  # set-point -20 C
    assert bytes(dev.ctrl_transfer(0xC0, 0xC2, 0, 55, 2)) == b"\x7f\x06"
    # a 16 x 8 dark frame by hand: arm 8*(16+1) pixels, ROI, timer, CMD_A dark
    assert dev.ctrl_transfer(0x40, 0xC9, 0, 8 * 17, None) == 0
    for reg, val in ap.geometry_registers(ap.Geometry(0, 0, 16, 8)) + ap.timer_writes(ap.exposure_ticks(1e-3)):
        dev.ctrl_transfer(0x40, 0xC2, 0, int(reg), int(val).to_bytes(2, "little"))
    dev.ctrl_transfer(0x40, 0xC2, 0, 0, b"\x02\x00")
    wait_for(lambda: ap.parse_status(bytes(dev.ctrl_transfer(0xC0, 0xC0, 0, 0, 21))).image_done, 1.0, "image done")
    data = bytes(dev.read(0x86, 8 * 17 * 2, 1000))
    assert len(data) == 8 * 17 * 2
    with pytest.raises(usb.core.USBTimeoutError):
        dev.read(0x86, 2, 20)  # transfer complete: nothing more
    with pytest.raises(usb.core.USBError) as e:
        dev.ctrl_transfer(0xC0, 0xEE, 0, 0, 2)  # unknown vendor request: stall
    assert e.value.errno == errno.EPIPE


def test_select_by_serial_number(bench_name):
    be = AltaBackend(bench_name, time_scale=FAST, serial_number="B7")
    with pytest.raises(DeviceConnectionError, match="serial number 'A1'"):
        AltaCamera(backend=be, serial_number="A1")
    with AltaCamera(backend=be, serial_number="B7") as cam:
        assert "serial B7" in cam.identity()


def test_no_camera_found(backend):
    backend.disconnect()
    with pytest.raises(DeviceConnectionError, match="no Apogee Alta-U"):
        AltaCamera(backend=backend)


def test_permission_denied_names_the_udev_rule(backend):
    backend.access_denied = True
    with pytest.raises(DeviceConnectionError, match="udev") as e:
        AltaCamera(backend=backend)
    assert "\n" not in str(e.value)


def test_camera_busy_in_another_program(backend):
    first = AltaCamera(backend=backend)
    with pytest.raises(DeviceConnectionError, match="another program") as e:
        AltaCamera(backend=backend)
    assert "\n" not in str(e.value)
    first.close()
    AltaCamera(backend=backend).close()  # free again once the first one let go


def test_transcript_logs_control_and_summarised_bulk_transfers(backend):
    buf = io.StringIO()
    with AltaCamera(backend=backend, transcript=Transcript(stream=buf)) as cam:
        cam.expose(1e-3, dark=True)
    log = buf.getvalue()
    assert "REG ID = 0x0002" in log
    assert "GET_IMAGE wValue=0x0004 wIndex=0x0200" in log  # 512 * 513 pixels
    assert "REG TIMER_LOWER :=" in log and log.index("REG TIMER_LOWER :=") < log.index("REG TIMER_UPPER :=")
    assert "REG CMD_A := 0x0002" in log
    assert log.count("bulk 0x86 126976/126976 bytes") == 4 and "bulk 0x86 17408/17408 bytes" in log
    assert max(len(line) for line in log.splitlines()) < 200  # bulk data summarised, not dumped


# ----------------------------------------------------------------- frames and statistics


def test_bias_and_read_noise(camera):
    f = camera.expose(ap.MIN_EXPOSURE_S, dark=True)
    d = f.data.astype(float)
    assert d.shape == (512, 512)
    n = d.size
    assert abs(d.mean() - S.bias_adu) < 5 * READ_ADU / math.sqrt(n) + 0.5  # +0.5: ADC rounding
    assert d.std() == pytest.approx(math.hypot(READ_ADU, 1 / math.sqrt(12)), rel=0.03)


def test_dark_current_follows_the_temperature(camera, backend):
    camera.set_roi(ROI(0, 0, 128, 64))
    model = CcdModel()
    warm = camera.expose(10.0, dark=True)  # cooler off: CCD at ambient
    expected = model.dark_rate(warm.ccd_temp_c) * 10.0 / S.gain_e_per_adu
    assert warm.ccd_temp_c == pytest.approx(AMBIENT_C, abs=0.05)
    assert warm.data.mean() - S.bias_adu == pytest.approx(expected, rel=0.02)
    # shot noise of the dark charge on top of the read noise
    var = model.dark_rate(warm.ccd_temp_c) * 10.0 / S.gain_e_per_adu ** 2 + READ_ADU ** 2
    assert warm.data.std() == pytest.approx(math.sqrt(var), rel=0.06)

    camera.set_cooler(-20.0)
    wait_for(lambda: camera.cooler_status().at_temperature, 2.0, "cooler set-point")
    cold = camera.expose(10.0, dark=True)
    ratio = (warm.data.mean() - S.bias_adu) / (cold.data.mean() - S.bias_adu)
    # dark current doubles every 6 C: 2^(40/6) ~ 100
    assert ratio == pytest.approx(2 ** ((warm.ccd_temp_c - cold.ccd_temp_c) / 6.0), rel=0.15)


def test_light_frame_has_signal_and_shot_noise(camera, bench_name):
    rate = 3000.0  # e-/s per pixel, uniform
    use_scene(bench_name, lambda a, f, r, c: np.full((r.stop - r.start, c.stop - c.start), rate))
    camera.set_roi(ROI(0, 0, 64, 64))
    t = 1.0
    f = camera.expose(t)
    e = (rate + CcdModel().dark_rate(f.ccd_temp_c)) * t
    assert f.data.mean() - S.bias_adu == pytest.approx(e / S.gain_e_per_adu, rel=0.01)
    assert f.data.std() == pytest.approx(math.sqrt(e / S.gain_e_per_adu ** 2 + READ_ADU ** 2), rel=0.08)
    assert f.exposure_s == pytest.approx(t, abs=ap.EXPOSURE_TICK_S)
    assert f.extra["timer_ticks"] == ap.exposure_ticks(t)


def column_scene(col: int, rate: float):
    def scene(angle, filt, rows, cols):
        img = np.zeros((rows.stop - rows.start, cols.stop - cols.start))
        if cols.start <= col < cols.stop:
            img[:, col - cols.start] = rate
        return img
    return scene


def test_roi_places_the_scene_and_drops_the_extra_pixel(camera, bench_name):
    use_scene(bench_name, column_scene(137, 2.0e4))
    camera.set_roi(ROI(128, 64, 32, 16))
    f = camera.expose(1.0)
    assert f.data.shape == (16, 32)
    profile = f.data.mean(axis=0)
    assert int(np.argmax(profile)) == 137 - 128  # no one-pixel shift from the per-row extra pixel
    assert profile[9] - background(f) == pytest.approx(2.0e4 / S.gain_e_per_adu, rel=0.03)
    assert np.all(np.abs(np.delete(profile, 9) - background(f)) < 10)


def test_binning_sums_charge(camera, bench_name):
    use_scene(bench_name, column_scene(137, 5.0e3))
    camera.set_roi(ROI(128, 64, 32, 16, bin_x=2, bin_y=2))
    f = camera.expose(1.0)
    assert f.data.shape == (8, 16)
    profile = f.data.mean(axis=0)
    assert int(np.argmax(profile)) == (137 - 128) // 2
    # one bright column, two rows per binned pixel; the dark current of 4 pixels
    expected = (2 * 5.0e3 + 4 * CcdModel().dark_rate(f.ccd_temp_c)) / S.gain_e_per_adu
    assert profile[4] - S.bias_adu == pytest.approx(expected, rel=0.03)


def test_saturation_and_blooming_along_the_column(camera, bench_name):
    row, col = 300, 200
    rate = 1.0e7

    def spot(angle, filt, rows, cols):
        img = np.zeros((rows.stop - rows.start, cols.stop - cols.start))
        if rows.start <= row < rows.stop and cols.start <= col < cols.stop:
            img[row - rows.start, col - cols.start] = rate
        return img

    use_scene(bench_name, spot)
    camera.set_roi(ROI(190, 280, 20, 40))
    f = camera.expose(0.1)  # 1e6 e- in one pixel: 5 full wells
    c = f.data[:, col - 190].astype(int)
    assert np.all(f.data <= 65535)
    # 16-bit ADC saturates before the full well (200 ke- / 3 e-/ADU + bias > 65535)
    saturated = np.flatnonzero(c == 65535) + 280
    # 4 full wells of excess, half up and half down: 2 more full pixels each way
    np.testing.assert_array_equal(saturated, np.arange(row - 2, row + 3))
    assert np.all(f.data[:, [col - 190 - 1, col - 190 + 1]] < background(f) + 30)  # no spill sideways


def test_shutter_modes_gate_the_light(camera, bench_name):
    use_scene(bench_name, lambda a, f, r, c: np.full((r.stop - r.start, c.stop - c.start), 3.0e4))
    camera.set_roi(ROI(0, 0, 32, 32))
    f = camera.expose(0.1)
    lit = f.data.mean() - background(f)
    assert lit == pytest.approx(3.0e3 / S.gain_e_per_adu, rel=0.03)
    camera.set_shutter(ShutterMode.CLOSED)
    closed = camera.expose(0.1)
    assert closed.dark is True and abs(closed.data.mean() - background(closed)) < 1
    camera.set_shutter(ShutterMode.OPEN)
    forced = camera.expose(0.1, dark=True)
    assert forced.dark is False and forced.data.mean() - background(forced) == pytest.approx(lit, rel=0.05)
    camera.set_shutter(ShutterMode.NORMAL)
    normal = camera.expose(0.1, dark=True)
    assert abs(normal.data.mean() - background(normal)) < 1


def test_cooler_ramps_to_the_setpoint(camera):
    st = camera.cooler_status()
    assert st.on is False and st.temperature_c == pytest.approx(AMBIENT_C, abs=0.05)
    camera.set_cooler(-15.0)
    mid = camera.cooler_status()
    assert mid.on and mid.setpoint_c == pytest.approx(-15.0, abs=0.03)
    wait_for(lambda: camera.cooler_status().at_temperature, 2.0, "cooler set-point")
    assert camera.temperature() == pytest.approx(-15.0, abs=0.5)
    assert camera.cooler_status().drive_percent > 50
    camera.set_cooler(-15.0, on=False)
    wait_for(lambda: camera.temperature() > AMBIENT_C - 1, 2.0, "warm-up to ambient")
    assert camera.cooler_status().at_temperature is False


def test_frame_metadata(camera):
    camera.set_roi(ROI(10, 20, 30, 40))
    t0 = time.time()
    f = camera.expose(0.5)
    assert t0 <= f.start_time <= f.end_time <= time.time()
    assert f.roi == ROI(10, 20, 30, 40) and f.camera == camera.identity()
    assert f.ccd_temp_c == pytest.approx(AMBIENT_C, abs=0.05)
    assert f.extra["shutter"] == "normal" and f.extra["requested_exposure_s"] == 0.5


# ----------------------------------------------------------------- limits before any transfer


@pytest.mark.parametrize("call, err", [
    (lambda c: c.expose(5e-6), LimitError),
    (lambda c: c.expose(11_000.0), LimitError),
    (lambda c: c.expose(-1.0), LimitError),
    (lambda c: c.expose(math.nan), ParameterError),
    (lambda c: c.set_roi(ROI(0, 0, 512, 513)), LimitError),
    (lambda c: c.set_roi(ROI(0, 0, 160, 160, bin_x=16)), LimitError),  # beyond the binning patterns
    (lambda c: c.set_cooler(-80.0), LimitError),
    (lambda c: c.set_shutter("half"), ParameterError),
])
def test_requests_out_of_range_send_nothing(camera, backend, call, err):
    before = backend.transfers
    with pytest.raises(err):
        call(camera)
    assert backend.transfers == before


# ----------------------------------------------------------------- faults


def test_stalled_control_transfer_is_retried_once(camera, backend):
    buf = io.StringIO()
    camera._log = Transcript(stream=buf)
    backend.faults = FaultPlan({"pipe": 0.3}, seed=4)
    ok = failed = 0
    for _ in range(30):
        try:
            camera.temperature()
            ok += 1
        except ProtocolError:
            failed += 1  # two stalls in a row
    assert ok + failed == 30 and ok > failed > 0
    assert "retrying once" in buf.getvalue()


def test_permanent_stall_is_a_protocol_error(camera, backend):
    backend.faults = FaultPlan({"pipe": 1.0})
    with pytest.raises(ProtocolError, match="stalled"):
        camera.temperature()
    with pytest.raises(ProtocolError):
        camera.expose(1e-3)
    backend.faults = FaultPlan()
    assert camera.expose(1e-3).data.shape == (512, 512)


def test_disconnect_mid_readout(camera, backend):
    backend.faults = FaultPlan({"disconnect": 1.0})
    with pytest.raises(DeviceConnectionError, match="disappeared"):
        camera.expose(1e-3)
    with pytest.raises(DeviceConnectionError):
        camera.temperature()
    assert usb.core.find(idVendor=0x125C, backend=backend) is None


def test_short_bulk_read_is_detected_and_the_camera_recovers(camera, backend):
    camera.set_roi(ROI(0, 0, 128, 128))
    backend.faults = FaultPlan({"short": 1.0}, seed=2)
    with pytest.raises(ProtocolError, match="short bulk read"):
        camera.expose(1e-3)
    backend.faults = FaultPlan()
    f = camera.expose(1e-3, dark=True)
    assert f.data.shape == (128, 128) and abs(f.data.mean() - S.bias_adu) < 1


def test_exposure_that_never_finishes_times_out(bench_name):
    be = AltaBackend(bench_name, time_scale=1.0)
    with AltaCamera(backend=be) as cam:
        cam.set_roi(ROI(0, 0, 16, 16))
        t = time.monotonic()
        with pytest.raises(DeviceTimeout):
            cam.expose(5.0, timeout_s=0.2)
        assert time.monotonic() - t < 1.0
        assert cam.expose(1e-3).data.shape == (16, 16)


def test_bulk_read_without_data_times_out(camera, backend):
    camera._readout_timeout_s = 0.05
    t = time.monotonic()
    with pytest.raises(DeviceTimeout):
        camera._read_image(ap.Geometry(0, 0, 16, 16))  # nothing armed: the endpoint NAKs
    assert time.monotonic() - t < 1.0


def test_closed_camera_refuses_requests(backend):
    cam = AltaCamera(backend=backend)
    cam.close()
    with pytest.raises(DeviceConnectionError, match="closed"):
        cam.temperature()


# ----------------------------------------------------------------- the sensor model itself


def test_blooming_conserves_charge_inside_the_column():
    m = CcdModel()
    fw = S.full_well_e
    q = np.zeros((50, 3))
    q[20, 1] = 7.5 * fw
    q[24, 1] = 2.0 * fw  # a second over-full pixel in the same column
    out = m.bloom(q)
    assert out.max() <= fw
    assert out[:, 1].sum() == pytest.approx(q[:, 1].sum())
    assert np.all(out[:, [0, 2]] == 0)
    full = np.flatnonzero(out[:, 1] >= fw)
    assert np.all(np.diff(full) == 1)  # one contiguous saturated streak


def test_blooming_past_the_ends_of_the_column_is_lost():
    m = CcdModel()
    q = np.zeros((5, 1))
    q[2, 0] = 100 * S.full_well_e
    out = m.bloom(q)
    np.testing.assert_array_equal(out[:, 0], S.full_well_e)


def test_nonlinearity_hook_compresses_the_response():
    rng = np.random.default_rng(0)
    rate = np.full((8, 8), 1.5e5)
    linear = CcdModel().expose(rate, 1.0, -20.0, rng).astype(float).mean()
    soft = CcdModel(nonlinearity=lambda e: e / (1 + e / 4.0e5)).expose(rate, 1.0, -20.0, rng).astype(float).mean()
    assert soft < linear
    e = 1.5e5 + CcdModel().dark_rate(-20.0)
    assert soft - S.bias_adu == pytest.approx(e / (1 + e / 4.0e5) / S.gain_e_per_adu, rel=0.01)


def test_unreadable_serial_numbers_point_at_permissions(backend):
    backend.access_denied = True
    with pytest.raises(DeviceConnectionError, match="udev"):
        AltaCamera(backend=backend, serial_number="SIM0001")


def test_time_scale_defaults_to_the_benchs(bench_name):
    set_bench(bench_name, Bench(time_scale=250.0))
    assert AltaBackend(bench_name).clock.time_scale == 250.0
    assert AltaBackend(bench_name, time_scale=3.0).clock.time_scale == 3.0
