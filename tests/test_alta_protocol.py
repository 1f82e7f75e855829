"""Alta-U byte protocol: conversions and layouts checked against the documented
protocol (shared/reference/device-protocols.md section 2), plus fuzzing of every
reply parser (malformed input -> ProtocolError only)."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers import alta_protocol as ap
from drivers.errors import LimitError, ProtocolError

# ----------------------------------------------------------------- exposure timer


def test_exposure_ticks_follow_the_documented_formula():
    # floor(t / 2.56 us) + 3
    assert ap.exposure_ticks(1.0) == 390_625 + 3
    assert ap.exposure_ticks(10e-6) == 3 + 3
    assert ap.exposure_ticks(0.1) == 39_062 + 3
    assert ap.exposure_ticks(10_990.0) == 4_292_968_750 + 3  # still a 32-bit count


@pytest.mark.parametrize("bad", [9.9e-6, 0.0, -1.0, 10_990.5, math.nan, math.inf])
def test_exposure_outside_range_is_a_limit_error(bad):
    with pytest.raises(LimitError):
        ap.exposure_ticks(bad)


def test_timer_written_low_word_to_reg5_then_high_word_to_reg4():
    ticks = ap.exposure_ticks(1.0)  # 390628 = 0x0005F5E4
    assert ap.timer_writes(ticks) == [(ap.Reg.TIMER_LOWER, 0xF5E4), (ap.Reg.TIMER_UPPER, 0x0005)]
    assert (ap.Reg.TIMER_LOWER, ap.Reg.TIMER_UPPER) == (5, 4)
    assert ap.timer_from_registers(0x0005, 0xF5E4) == ticks


@given(st.floats(min_value=ap.MIN_EXPOSURE_S, max_value=ap.MAX_EXPOSURE_S))
def test_ticks_round_trip_within_one_tick(t):
    back = ap.ticks_to_seconds(ap.exposure_ticks(t))
    assert t - ap.EXPOSURE_TICK_S <= back <= t + 1e-9 * t


# ----------------------------------------------------------------- temperatures


def test_setpoint_conversion_and_clamping():
    # reg 55 = T / 0.025146 + 2458
    assert ap.setpoint_to_raw(0.0) == 2458
    assert ap.setpoint_to_raw(-20.0) == round(-20.0 / 0.025146 + 2458) == 1663
    assert ap.setpoint_to_raw(-100.0) == ap.setpoint_to_raw(-60.0)
    assert ap.setpoint_to_raw(80.0) == ap.setpoint_to_raw(39.0)
    with pytest.raises(LimitError):
        ap.setpoint_to_raw(math.nan)


def test_ccd_temperature_conversion():
    assert ap.raw_to_temperature(2458) == 0.0
    assert ap.raw_to_temperature(1663) == pytest.approx(-19.991, abs=1e-3)
    for t in (-45.0, -20.0, 0.0, 25.0):
        assert ap.raw_to_temperature(ap.temperature_to_raw(t)) == pytest.approx(t, abs=ap.TEMP_SCALE_C / 2 + 1e-9)


# ----------------------------------------------------------------- status block

# Golden blocks laid out as documented: TempHeatSink, TempCcd, CoolerDrive,
# InputVoltage, TdiCounter, SequenceCounter, Status (uint16 LE), uFrame (uint16),
# [extended: MostRecentFrame, ReadyFrame, CurrentFrame], FetchCount (uint32), DataAvailFlag (uint8).
GOLDEN_21 = bytes.fromhex("2b0a7f060008ab0a0000070008c034122a00000001")
GOLDEN_27 = bytes.fromhex("2b0a7f060008ab0a00000700490034120500060007000403020100")


def test_golden_basic_status_block():
    s = ap.parse_status(GOLDEN_21)
    assert len(GOLDEN_21) == 21 and not s.extended
    assert (s.temp_heatsink, s.temp_ccd, s.cooler_drive, s.input_voltage) == (0x0A2B, 0x067F, 0x0800, 0x0AAB)
    assert (s.tdi_counter, s.sequence_counter, s.uframe, s.fetch_count, s.data_avail) == (0, 7, 0x1234, 42, 1)
    assert s.status == 0xC008
    assert s.image_done and s.has(ap.ST_COOLER_ACTIVE) and s.has(ap.ST_AT_TEMP) and not s.has(ap.ST_EXPOSING)
    assert s.ccd_temp_c == pytest.approx(-19.991, abs=1e-3)
    assert s.drive_percent == pytest.approx(50.01, abs=0.01)
    assert ap.pack_status(s, extended=False) == GOLDEN_21


def test_golden_extended_status_block():
    s = ap.parse_status(GOLDEN_27)
    assert len(GOLDEN_27) == 27 and s.extended
    assert s.status == 0x0049  # exposing, image done, shutter open
    assert s.has(ap.ST_EXPOSING) and s.has(ap.ST_SHUTTER_OPEN) and s.image_done
    assert (s.most_recent_frame, s.ready_frame, s.current_frame) == (5, 6, 7)
    assert s.fetch_count == 0x01020304 and s.data_avail == 0
    assert ap.pack_status(s, extended=True) == GOLDEN_27


def test_status_length_depends_on_firmware():
    assert ap.status_length(14) == 21
    assert ap.status_length(16) == 27


@pytest.mark.parametrize("n", [0, 1, 20, 22, 26, 28, 64])
def test_status_of_wrong_length_is_a_protocol_error(n):
    with pytest.raises(ProtocolError):
        ap.parse_status(bytes(n))


@settings(max_examples=300)
@given(st.binary(max_size=64))
def test_status_parser_fuzz(data):
    try:
        s = ap.parse_status(data)
    except ProtocolError:
        assert len(data) not in (21, 27)
    else:
        assert len(data) in (21, 27)
        assert ap.pack_status(s, extended=s.extended) == data
        assert -62.0 < s.ccd_temp_c < 42.0 and 0.0 <= s.drive_percent <= 100.0


@given(st.binary(max_size=8), st.integers(0, 255))
def test_register_parser_fuzz(data, reg):
    try:
        v = ap.parse_register(data, reg)
    except ProtocolError:
        assert len(data) != 2
    else:
        assert len(data) == 2 and 0 <= v <= 0xFFFF


# ----------------------------------------------------------------- readout geometry


def test_image_request_carries_rows_times_cols_plus_one():
    g = ap.Geometry(0, 0, 512, 512)
    assert g.pixels == 512 * 513 and g.nbytes == 2 * 512 * 513
    assert ap.image_request(g.pixels) == (0x0004, 0x0200)  # wValue high, wIndex low
    assert ap.pixels_from_request(0x0004, 0x0200) == 262_656


def test_chunks_of_at_most_126976_bytes():
    sizes = ap.chunk_sizes(2 * 512 * 513)
    assert sizes == [126_976] * 4 + [17_408]
    assert ap.chunk_sizes(100) == [100]
    assert ap.chunk_sizes(126_976) == [126_976]


def test_first_pixel_of_every_row_is_dropped():
    rows, cols = 3, 4
    stream = np.arange(rows * (cols + 1), dtype="<u2").reshape(rows, cols + 1)
    img = ap.frame_from_bytes(stream.tobytes(), rows, cols)
    assert img.dtype == np.uint16 and img.shape == (rows, cols)
    np.testing.assert_array_equal(img, stream[:, 1:])
    extra = np.array([7, 8, 9], dtype=np.uint16)
    assert ap.frame_to_bytes(img, extra)[:2] == (7).to_bytes(2, "little")
    np.testing.assert_array_equal(ap.frame_from_bytes(ap.frame_to_bytes(img, extra), rows, cols), img)


@given(st.binary(max_size=80), st.integers(1, 6), st.integers(1, 6))
def test_frame_parser_fuzz(data, rows, cols):
    try:
        img = ap.frame_from_bytes(data, rows, cols)
    except ProtocolError:
        assert len(data) != 2 * rows * (cols + 1)
    else:
        assert img.shape == (rows, cols)


def test_golden_roi_registers_follow_libapogee_region_balancing():
    regs = dict(ap.geometry_registers(ap.Geometry(x=100, y=100, cols=64, rows=50)))
    assert (regs[ap.Reg.PREROI_SKIP_COUNT], regs[ap.Reg.ROI_COUNT], regs[ap.Reg.POSTROI_SKIP_COUNT]) == (100, 65, 348)
    # 100 rows before the ROI: A1 one row binned 30, A2 70 single rows
    assert (regs[ap.Reg.A1_ROW_COUNT], regs[ap.Reg.A1_VBINNING]) == (1, 30)
    assert (regs[ap.Reg.A2_ROW_COUNT], regs[ap.Reg.A2_VBINNING]) == (70, 1)
    assert (regs[ap.Reg.A3_ROW_COUNT], regs[ap.Reg.A3_VBINNING]) == (50, 0x1001)
    # 362 rows after it: A4 one row binned 292, A5 70 rows
    assert (regs[ap.Reg.A4_ROW_COUNT], regs[ap.Reg.A4_VBINNING]) == (1, 292)
    assert (regs[ap.Reg.A5_ROW_COUNT], regs[ap.Reg.A5_VBINNING]) == (70, 1)


roi_strategy = st.builds(
    lambda bx, by, c, r, fx, fy: ap.Geometry(
        x=int(fx * (512 - c * bx)), y=int(fy * (512 - r * by)), cols=c, rows=r, bin_x=bx, bin_y=by),
    st.integers(1, ap.MAX_BIN_X), st.integers(1, 8), st.integers(1, 64), st.integers(1, 64),
    st.floats(0, 1), st.floats(0, 1),
)


@given(roi_strategy)
def test_geometry_registers_round_trip(g):
    assert ap.geometry_from_registers({int(k): v for k, v in ap.geometry_registers(g)}) == g


@given(st.dictionaries(st.sampled_from([int(r) for r in ap.Reg]), st.integers(0, 0xFFFF), max_size=20))
def test_geometry_decoder_fuzz(regs):
    try:
        g = ap.geometry_from_registers(regs)
    except ProtocolError:
        return
    assert g.cols >= 1 and g.rows >= 1 and g.bin_x >= 1 and g.bin_y >= 1


def test_roi_off_sensor_is_a_limit_error():
    with pytest.raises(LimitError):
        ap.geometry_registers(ap.Geometry(x=500, y=0, cols=20, rows=10))
    with pytest.raises(LimitError):
        ap.geometry_registers(ap.Geometry(x=0, y=0, cols=16, rows=16, bin_x=ap.MAX_BIN_X + 1))
