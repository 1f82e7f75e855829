"""Byte protocol of the Apogee Alta-U camera (U260, Kodak KAF-0261E) over USB.

Pure functions and constants, no I/O: the driver (``drivers/apogee_alta.py``)
and the simulated twin (``sim_devices/alta_usb.py``) both use this module, so
that what one encodes the other decodes by the same rules.

Sources: ``shared/reference/device-protocols.md`` section 2, which follows
libapogee 3.x (``CamHelpers.h`` register map, ``GenOneLinuxUSB.cpp`` transfers,
``CcdAcqParams.cpp`` ROI registers, ``CameraStatusRegs.h`` status block).

Conventions: vendor control requests carry 16-bit words little-endian; register
reads and writes put the register number in ``wIndex`` and 0 in ``wValue``.
Malformed replies raise :class:`drivers.errors.ProtocolError` and nothing else;
requests outside the hardware's range raise :class:`drivers.errors.LimitError`.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from drivers.errors import LimitError, ProtocolError
from drivers.interfaces import SensorInfo

DEVICE = "camera"

# --------------------------------------------------------------------------- USB identity

VENDOR_ID = 0x125C  # Apogee
PRODUCT_ID = 0x0010  # Alta-U (Cypress FX2 with Apogee firmware)
DEVICE_RELEASE = 0x0011  # bcdDevice of a programmed Alta-U (libapogee ALTA_USB_DID)
INTERFACE = 0
BULK_IN_EP = 0x86  # image data
REQ_IN = 0xC0  # bmRequestType: vendor, device, device-to-host
REQ_OUT = 0x40  # bmRequestType: vendor, device, host-to-device
CTRL_TIMEOUT_MS = 10_000  # libapogee uses 10 s for every control transfer
MAX_CHUNK_BYTES = 0x1F000  # 126,976: the Alta-U FX2 image buffer; one bulk read at most this


class Request(IntEnum):
    """Vendor ``bRequest`` codes."""

    STATUS = 0xC0  # IN, 21-byte status block (27 on firmware >= 16)
    REGISTER = 0xC2  # IN read / OUT write, wIndex = register, 2 data bytes
    SOFT_RESET = 0xC8  # OUT, no data
    GET_IMAGE = 0xC9  # OUT, wValue = high 16 bits, wIndex = low 16 bits of the pixel count
    STOP_IMAGE = 0xCA  # OUT, no data


class Reg(IntEnum):
    """Camera controller (CamCon FPGA) registers."""

    CMD_A = 0
    CMD_B = 1
    OP_A = 2
    OP_B = 3
    TIMER_UPPER = 4
    TIMER_LOWER = 5
    CLAMP_COUNT = 13
    PREROI_SKIP_COUNT = 14
    ROI_COUNT = 15
    POSTROI_SKIP_COUNT = 16
    OVERSCAN_COUNT = 17
    A1_ROW_COUNT = 30
    A1_VBINNING = 31
    A2_ROW_COUNT = 32
    A2_VBINNING = 33
    A3_ROW_COUNT = 34
    A3_VBINNING = 35
    A4_ROW_COUNT = 36
    A4_VBINNING = 37
    A5_ROW_COUNT = 38
    A5_VBINNING = 39
    SCRATCH = 53
    TEMP_DESIRED = 55
    STATUS = 91
    TEMP_HEATSINK = 93
    TEMP_CCD = 94
    TEMP_DRIVE = 95
    INPUT_VOLTAGE = 96
    ID = 100
    FIRMWARE_REV = 101
    TDI_COUNTER = 104
    SEQUENCE_COUNTER = 105


# CMD_A bits
CMD_A_EXPOSE = 0x0001  # light frame: shutter opens for the exposure (normal shutter mode)
CMD_A_DARK = 0x0002  # dark frame: shutter stays closed
CMD_A_FLUSH = 0x0010  # clear the array continuously until the next exposure
# CMD_B bits
CMD_B_RESET = 0x0002  # reset counters and FIFOs, abort an exposure
CMD_B_END_EXPOSURE = 0x0080
CMD_B_RAMP_TO_SETPOINT = 0x0200  # cooler on, regulate to TEMP_DESIRED
CMD_B_RAMP_TO_AMBIENT = 0x0400  # cooler off (ramp back to ambient)
# OP_A bits
OP_A_FORCE_SHUTTER = 0x0800  # shutter forced open
OP_A_DISABLE_SHUTTER = 0x1000  # shutter forced closed
# STATUS (register 91 and the status block) bits
ST_EXPOSING = 0x0001
ST_IMAGING_ACTIVE = 0x0002
ST_DATA_HALTED = 0x0004
ST_IMAGE_DONE = 0x0008
ST_FLUSHING = 0x0010
ST_SHUTTER_OPEN = 0x0040
ST_PATTERN_ERROR = 0x0080
ST_AT_TEMP = 0x4000
ST_COOLER_ACTIVE = 0x8000
# Vertical region binning word (A1..A5 _VBINNING)
VBIN_COUNT_MASK = 0x0FFF
VBIN_DIGITIZE = 0x1000  # the region whose rows are digitised (the ROI)
VBIN_FASTDUMP = 0x4000

CAMERA_ID_MASK = 0x7F
CAMERA_ID_KAF0261E = 2  # Alta U260 (reg 100 & 0x7F)
EXTENDED_STATUS_FIRMWARE = 16  # firmware revision from which STATUS returns 27 bytes
MAX_BIN_X = 8  # horizontal binning patterns in the camera files; *unconfirmed* for the U260
MAX_BIN_Y = 64  # *unconfirmed*; libapogee caps vertical binning per platform

# libapogee: the ROI horizontal count includes one extra pixel per row (the
# "pixel shift" of the readout pipeline); that pixel comes first in every row
# and is dropped by the host in 16-bit mode.
PIXEL_SHIFT = 1

# Vertical region balancing (libapogee CcdAcqParams::CalcVerticalValues, firmware >= 11):
# pre- and post-ROI regions longer than 70 rows are split into a binned dump region.
MAX_A2_A5_ROWS = 70
A1_BIN_MAX = 50
A4_BIN_MAX = 2048

# --------------------------------------------------------------------------- sensor

#: KAF-0261E facts. Pixel pitch, format, gain and bias from the Alta U260 data;
#: read noise, full well and dark current are *unconfirmed* simulator defaults.
KAF0261E = SensorInfo(
    model="KAF-0261E",
    width=512,
    height=512,
    pixel_size_um=20.0,
    gain_e_per_adu=3.0,
    bias_adu=250.0,
    read_noise_e=15.0,  # unconfirmed
    full_well_e=200_000.0,  # unconfirmed
    adc_max=65535,
    dark_current_e_per_s=3.0,  # unconfirmed: "a few e-/s/pixel" at the -20 C default set-point
)
DEFAULT_SETPOINT_C = -20.0

# --------------------------------------------------------------------------- exposure timer

EXPOSURE_TICK_S = 2.56e-6
EXPOSURE_OFFSET_TICKS = 3
MIN_EXPOSURE_S = 10e-6
MAX_EXPOSURE_S = 10_990.0


def exposure_ticks(seconds: float) -> int:
    """Timer count for an exposure of ``seconds``: floor(t / 2.56 us) + 3.

    Raises:
        LimitError: outside 10 us .. 10,990 s (or not finite).
    """
    t = float(seconds)
    if not (math.isfinite(t) and MIN_EXPOSURE_S <= t <= MAX_EXPOSURE_S):
        raise LimitError(f"exposure {seconds} s outside [{MIN_EXPOSURE_S}, {MAX_EXPOSURE_S}] s", device=DEVICE)
    # a small epsilon so that exact multiples of the tick are not floored one short
    ticks = math.floor(t / EXPOSURE_TICK_S + 1e-9) + EXPOSURE_OFFSET_TICKS
    if ticks > 0xFFFFFFFF:
        raise LimitError(f"exposure {seconds} s does not fit the 32-bit timer", device=DEVICE)
    return ticks


def ticks_to_seconds(ticks: int) -> float:
    """Exposure time (s) that a timer count programs: the inverse of :func:`exposure_ticks`."""
    if not 0 <= ticks <= 0xFFFFFFFF:
        raise ProtocolError(f"timer count {ticks} is not a 32-bit value", device=DEVICE)
    return max(ticks - EXPOSURE_OFFSET_TICKS, 0) * EXPOSURE_TICK_S


def timer_writes(ticks: int) -> list[tuple[Reg, int]]:
    """Register writes that program the timer: low word to reg 5 first, then high word to reg 4."""
    return [(Reg.TIMER_LOWER, ticks & 0xFFFF), (Reg.TIMER_UPPER, (ticks >> 16) & 0xFFFF)]


def timer_from_registers(upper: int, lower: int) -> int:
    return ((upper & 0xFFFF) << 16) | (lower & 0xFFFF)


# --------------------------------------------------------------------------- temperatures

TEMP_OFFSET_RAW = 2458
TEMP_SCALE_C = 0.025146  # degrees C per count
MIN_SETPOINT_C = -60.0
MAX_SETPOINT_C = 39.0
TEMP_RAW_MASK = 0x0FFF  # 12-bit temperature ADC


def setpoint_to_raw(temp_c: float) -> int:
    """Register 55 value for a set-point in C, clamped to -60..+39 C (the hardware's range)."""
    t = float(temp_c)
    if not math.isfinite(t):
        raise LimitError(f"cooler set-point {temp_c!r} is not a finite temperature", device=DEVICE)
    t = min(max(t, MIN_SETPOINT_C), MAX_SETPOINT_C)
    return int(round(t / TEMP_SCALE_C + TEMP_OFFSET_RAW))


def raw_to_temperature(raw: int) -> float:
    """CCD temperature in C from the 12-bit sensor count: (raw - 2458) * 0.025146."""
    return ((int(raw) & TEMP_RAW_MASK) - TEMP_OFFSET_RAW) * TEMP_SCALE_C


def temperature_to_raw(temp_c: float) -> int:
    """Inverse of :func:`raw_to_temperature`, clipped to the 12-bit ADC (used by the twin)."""
    return int(min(max(round(temp_c / TEMP_SCALE_C + TEMP_OFFSET_RAW), 0), TEMP_RAW_MASK))


# Cooler drive and input voltage scales: libapogee Alta values as remembered, *unconfirmed*.
COOLER_DRIVE_FULL_SCALE = 4095  # raw drive count at 100 %
INPUT_VOLTAGE_SCALE_V = 0.00439453  # volts per count (12 bits)


def drive_percent(raw: int) -> float:
    return min(max((int(raw) & 0x0FFF) * 100.0 / COOLER_DRIVE_FULL_SCALE, 0.0), 100.0)


# --------------------------------------------------------------------------- status block

_BASIC = struct.Struct("<8HIB")  # 21 bytes
_EXTENDED = struct.Struct("<11HIB")  # 27 bytes


def status_length(firmware: int) -> int:
    """Size of the STATUS reply for a camera firmware revision (register 101)."""
    return _EXTENDED.size if firmware >= EXTENDED_STATUS_FIRMWARE else _BASIC.size


@dataclass(frozen=True)
class StatusBlock:
    """The STATUS vendor request reply (libapogee ``BasicStatus`` / ``AdvStatus``).

    Raw register words; use the properties for physical values.
    """

    temp_heatsink: int  # reg 93
    temp_ccd: int  # reg 94
    cooler_drive: int  # reg 95
    input_voltage: int  # reg 96
    tdi_counter: int  # reg 104
    sequence_counter: int  # reg 105
    status: int  # reg 91
    uframe: int  # USB micro-frame the data was captured on (125 us units)
    fetch_count: int  # times the host fetched this block
    data_avail: int
    most_recent_frame: int | None = None  # extended block only (firmware >= 16)
    ready_frame: int | None = None
    current_frame: int | None = None

    @property
    def ccd_temp_c(self) -> float:
        return raw_to_temperature(self.temp_ccd)

    @property
    def heatsink_temp_c(self) -> float:
        """Heat-sink temperature, assuming the CCD conversion (*unconfirmed*)."""
        return raw_to_temperature(self.temp_heatsink)

    @property
    def drive_percent(self) -> float:
        return drive_percent(self.cooler_drive)

    @property
    def input_voltage_v(self) -> float:
        return (self.input_voltage & 0x0FFF) * INPUT_VOLTAGE_SCALE_V

    def has(self, bit: int) -> bool:
        return bool(self.status & bit)

    @property
    def image_done(self) -> bool:
        return self.has(ST_IMAGE_DONE)

    @property
    def extended(self) -> bool:
        return self.most_recent_frame is not None


def parse_status(data: bytes | bytearray | memoryview) -> StatusBlock:
    """Parse a 21- or 27-byte status block.

    Raises:
        ProtocolError: any other length (truncated or garbled reply).
    """
    try:
        raw = bytes(data)
    except (TypeError, ValueError):
        raise ProtocolError(f"status reply is not bytes: {type(data).__name__}", device=DEVICE) from None
    if len(raw) == _BASIC.size:
        th, tc, dr, iv, tdi, seq, st, uf, fetch, avail = _BASIC.unpack(raw)
        return StatusBlock(th, tc, dr, iv, tdi, seq, st, uf, fetch, avail)
    if len(raw) == _EXTENDED.size:
        th, tc, dr, iv, tdi, seq, st, uf, mrf, rf, cf, fetch, avail = _EXTENDED.unpack(raw)
        return StatusBlock(th, tc, dr, iv, tdi, seq, st, uf, fetch, avail, mrf, rf, cf)
    raise ProtocolError(
        f"status reply of {len(raw)} bytes; expected {_BASIC.size} or {_EXTENDED.size}", device=DEVICE
    )


def pack_status(block: StatusBlock, *, extended: bool) -> bytes:
    """Encode a status block (the twin's side of :func:`parse_status`)."""
    head = (
        block.temp_heatsink, block.temp_ccd, block.cooler_drive, block.input_voltage,
        block.tdi_counter, block.sequence_counter, block.status, block.uframe,
    )
    if extended:
        frames = (block.most_recent_frame or 0, block.ready_frame or 0, block.current_frame or 0)
        return _EXTENDED.pack(*head, *frames, block.fetch_count, block.data_avail)
    return _BASIC.pack(*head, block.fetch_count, block.data_avail)


def parse_register(data: bytes | bytearray | memoryview, reg: int) -> int:
    """A register read reply: exactly 2 bytes, uint16 little-endian."""
    raw = bytes(data)
    if len(raw) != 2:
        raise ProtocolError(f"register {reg} read returned {len(raw)} bytes, expected 2", device=DEVICE)
    return int.from_bytes(raw, "little")


def pack_register(value: int) -> bytes:
    if not 0 <= value <= 0xFFFF:
        raise LimitError(f"register value {value} is not a 16-bit word", device=DEVICE)
    return int(value).to_bytes(2, "little")


# --------------------------------------------------------------------------- ROI and readout geometry


@dataclass(frozen=True)
class Geometry:
    """What the camera digitises: ``rows`` x ``cols`` binned pixels starting at
    unbinned (``x``, ``y``), binned ``bin_x`` x ``bin_y``."""

    x: int
    y: int
    cols: int  # binned columns delivered to the host (after dropping the extra pixel)
    rows: int  # binned rows
    bin_x: int = 1
    bin_y: int = 1

    @property
    def pixels(self) -> int:
        """Pixels the camera sends: rows * (cols + 1), the extra pixel per row included."""
        return self.rows * (self.cols + PIXEL_SHIFT)

    @property
    def nbytes(self) -> int:
        return 2 * self.pixels


def geometry_registers(g: Geometry, sensor: SensorInfo = KAF0261E) -> list[tuple[Reg, int]]:
    """Register writes for an ROI with binning (libapogee ``GetPostVer11Settings``).

    Horizontal: pre-ROI skip and post-ROI skip in unbinned columns, ROI count in
    binned pixels plus the extra pixel. Vertical: regions A1..A5 of (row count,
    binning word); A3 is digitised, A1/A2 dump the rows before the ROI and A4/A5
    the rows after it. The real camera also needs the horizontal ROI pattern for
    ``bin_x`` loaded into HRAM (from Apogee's camera configuration files); that is
    not part of this protocol module.
    """
    check_geometry(g, sensor)
    post = sensor.width - g.x - g.cols * g.bin_x
    writes: list[tuple[Reg, int]] = [
        (Reg.PREROI_SKIP_COUNT, g.x),
        (Reg.ROI_COUNT, g.cols + PIXEL_SHIFT),
        (Reg.POSTROI_SKIP_COUNT, post),
    ]
    a1, a2 = _balance(g.y, A1_BIN_MAX)
    after = sensor.height - g.y - g.rows * g.bin_y
    a4, a5 = _balance(after, A4_BIN_MAX)
    writes += [
        (Reg.A1_ROW_COUNT, a1[0]), (Reg.A1_VBINNING, a1[1]),
        (Reg.A2_ROW_COUNT, a2[0]), (Reg.A2_VBINNING, a2[1]),
        (Reg.A3_ROW_COUNT, g.rows), (Reg.A3_VBINNING, g.bin_y | VBIN_DIGITIZE),
        (Reg.A4_ROW_COUNT, a4[0]), (Reg.A4_VBINNING, a4[1]),
        (Reg.A5_ROW_COUNT, a5[0]), (Reg.A5_VBINNING, a5[1]),
    ]
    return writes


def _balance(rows: int, top_max_bin: int) -> tuple[tuple[int, int], tuple[int, int]]:
    """Split ``rows`` dumped rows into a binned top region and an unbinned bottom
    region of at most 70 rows (libapogee ``BalanceSections``); (rows, bin) pairs."""
    if rows <= MAX_A2_A5_ROWS:
        return (0, 0), (rows, 1)
    top_rows = rows - MAX_A2_A5_ROWS
    if top_rows < top_max_bin:
        return (1, top_rows), (MAX_A2_A5_ROWS, 1)
    return (top_rows // top_max_bin, top_max_bin), (MAX_A2_A5_ROWS + top_rows % top_max_bin, 1)


def check_geometry(g: Geometry, sensor: SensorInfo = KAF0261E) -> None:
    """Raise LimitError unless the ROI lies on the sensor with supported binning."""
    ok = (
        g.x >= 0 and g.y >= 0 and g.cols >= 1 and g.rows >= 1
        and 1 <= g.bin_x <= MAX_BIN_X and 1 <= g.bin_y <= MAX_BIN_Y
        and g.x + g.cols * g.bin_x <= sensor.width and g.y + g.rows * g.bin_y <= sensor.height
    )
    if not ok:
        raise LimitError(
            f"ROI {g} does not fit the {sensor.width}x{sensor.height} sensor "
            f"(binning at most {MAX_BIN_X}x{MAX_BIN_Y})",
            device=DEVICE,
        )


def geometry_from_registers(regs: dict[int, int], sensor: SensorInfo = KAF0261E) -> Geometry:
    """Decode the geometry the registers describe (the twin's side of :func:`geometry_registers`).

    Raises:
        ProtocolError: the skip counts and regions do not add up to the sensor,
            no region (or more than one) is marked digitised, or binning is zero.
    """
    r = lambda reg: int(regs.get(int(reg), 0))
    pre, count, post = r(Reg.PREROI_SKIP_COUNT), r(Reg.ROI_COUNT), r(Reg.POSTROI_SKIP_COUNT)
    cols = count - PIXEL_SHIFT
    if cols < 1:
        raise ProtocolError(f"ROI count {count} leaves no columns", device=DEVICE)
    span = sensor.width - pre - post
    if span < cols or span % cols:
        raise ProtocolError(
            f"horizontal skips {pre}+{post} and ROI count {count} do not add up to {sensor.width} columns",
            device=DEVICE,
        )
    bin_x = span // cols
    regions = [(r(Reg.A1_ROW_COUNT + 2 * i), r(Reg.A1_VBINNING + 2 * i)) for i in range(5)]
    digitised = [i for i, (_, word) in enumerate(regions) if word & VBIN_DIGITIZE]
    if len(digitised) != 1:
        raise ProtocolError(f"{len(digitised)} vertical regions marked digitised, expected 1", device=DEVICE)
    k = digitised[0]
    rows, bin_y = regions[k][0], regions[k][1] & VBIN_COUNT_MASK
    if rows < 1 or bin_y < 1:
        raise ProtocolError(f"digitised region of {rows} rows binned {bin_y}", device=DEVICE)
    y = sum(n * (w & VBIN_COUNT_MASK) for n, w in regions[:k])
    total = sum(n * (w & VBIN_COUNT_MASK) for n, w in regions)
    if total != sensor.height:
        raise ProtocolError(f"vertical regions cover {total} rows, the sensor has {sensor.height}", device=DEVICE)
    return Geometry(x=pre, y=y, cols=cols, rows=rows, bin_x=bin_x, bin_y=bin_y)


def image_request(pixels: int) -> tuple[int, int]:
    """(wValue, wIndex) of GET_IMAGE: high and low 16 bits of the pixel count."""
    if not 0 < pixels <= 0xFFFFFFFF:
        raise LimitError(f"pixel count {pixels} out of range", device=DEVICE)
    return (pixels >> 16) & 0xFFFF, pixels & 0xFFFF


def pixels_from_request(w_value: int, w_index: int) -> int:
    return ((w_value & 0xFFFF) << 16) | (w_index & 0xFFFF)


def chunk_sizes(nbytes: int, max_chunk: int = MAX_CHUNK_BYTES) -> list[int]:
    """Bulk read sizes for ``nbytes``: full chunks of ``max_chunk`` then the rest."""
    if nbytes < 0 or max_chunk <= 0:
        raise LimitError(f"cannot split {nbytes} bytes in chunks of {max_chunk}", device=DEVICE)
    full, rest = divmod(nbytes, max_chunk)
    return [max_chunk] * full + ([rest] if rest else [])


def frame_from_bytes(raw: bytes | bytearray | memoryview, rows: int, cols: int) -> np.ndarray:
    """uint16 image (rows x cols) from the bulk data of rows*(cols+1) LE pixels,
    dropping the first pixel of every row.

    Raises:
        ProtocolError: the data is not exactly rows*(cols+1)*2 bytes.
    """
    expected = 2 * rows * (cols + PIXEL_SHIFT)
    buf = memoryview(raw).cast("B") if not isinstance(raw, bytes) else raw
    if len(buf) != expected:
        raise ProtocolError(f"image data of {len(buf)} bytes, expected {expected}", device=DEVICE)
    data = np.frombuffer(buf, dtype="<u2").reshape(rows, cols + PIXEL_SHIFT)
    return np.ascontiguousarray(data[:, PIXEL_SHIFT:]).astype(np.uint16, copy=False)


def frame_to_bytes(image: np.ndarray, extra: np.ndarray) -> bytes:
    """Bulk stream for an image (rows x cols uint16) with ``extra`` (rows,) pixels
    put first in every row (the twin's side of :func:`frame_from_bytes`)."""
    rows, cols = image.shape
    out = np.empty((rows, cols + PIXEL_SHIFT), dtype="<u2")
    out[:, 0] = extra
    out[:, PIXEL_SHIFT:] = image
    return out.tobytes()


REGISTER_NAMES = {int(r): r.name for r in Reg}


def describe_register(reg: int) -> str:
    return REGISTER_NAMES.get(reg, f"reg{reg}")
