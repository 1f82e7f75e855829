"""Simulated Apogee Alta-U (U260, KAF-0261E) as a pyusb backend.

``usb.core.find(idVendor=0x125C, idProduct=0x0010, backend=AltaBackend())``
finds one camera; the driver then talks to it through pyusb exactly as to the
real one: standard descriptors (device, configuration, interface 0 with the
bulk IN endpoint 0x86, string descriptors), the vendor requests of
:mod:`drivers.alta_protocol` (STATUS, register read/write, SOFT_RESET,
GET_IMAGE, STOP_IMAGE) and bulk reads of the image.

Physics on a simulated clock (:class:`~sim_devices.serial_twin.SimClock`,
``time_scale`` simulated seconds per real second): the exposure timer, the
shutter (normal / forced open / forced closed), the readout time of the
digitised pixels, and a thermoelectric cooler whose CCD temperature relaxes
exponentially towards the set-point (or ambient when off), limited to a maximum
difference below ambient. What the sensor sees comes from the named
:class:`~sim_devices.bench.Bench`; charge, noise and ADC from
:class:`~sim_devices.ccd_sensor.CcdModel`.

Faults (seeded :class:`~sim_devices.faults.FaultPlan`): ``pipe`` stalls a vendor
control transfer (``USBError`` EPIPE, nothing executed), ``disconnect`` makes
the camera vanish during a bulk read (ENODEV from then on, also for
enumeration), ``short`` ends a bulk read early with fewer bytes. Two handles
claiming interface 0 get EBUSY (the camera open in another process); setting
:attr:`AltaBackend.access_denied` makes ``open_device`` fail with EACCES (no
udev rule).

Hardware details this twin does not interpret: clock patterns (HRAM/VRAM),
ADC gain/offset, fan settings; those writes are stored and logged only. The
horizontal binning is inferred from the skip counts (the real camera takes it
from the loaded ROI pattern).
"""

from __future__ import annotations

import errno
import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np
import usb.backend
import usb.core

from drivers import alta_protocol as ap
from drivers.errors import ProtocolError
from sim_devices.bench import Bench, get_bench
from sim_devices.ccd_sensor import CcdModel
from sim_devices.faults import FaultPlan
from sim_devices.serial_twin import SimClock

# Readout timing (simulated seconds): *unconfirmed* model of the Alta U260 at
# its normal (16-bit) digitisation rate.
PIXEL_TIME_S = 1.0e-6  # per digitised pixel (1 MHz)
ROW_SHIFT_TIME_S = 10.0e-6  # per vertical row shift (dumped or digitised)
FLUSH_TIME_S = 512 * ROW_SHIFT_TIME_S
# Cooler model (*unconfirmed*): first-order relaxation, limited pull-down.
AMBIENT_C = 20.0
COOLER_TAU_S = 20.0
COOLER_MAX_DELTA_C = 45.0  # the TE cooler reaches at most ambient - 45 C
AT_TEMP_BAND_C = 0.5
INPUT_VOLTAGE_V = 12.0

_LANGID_EN_US = 0x0409
_STRINGS = {1: "Apogee", 2: "Alta-U"}


def _err(kind: str) -> usb.core.USBError:
    table = {
        "pipe": ("Pipe error", -9, errno.EPIPE),
        "nodev": ("No such device (it may have been disconnected)", -4, errno.ENODEV),
        "busy": ("Resource busy", -6, errno.EBUSY),
        "access": ("Access denied (insufficient permissions)", -3, errno.EACCES),
        "io": ("Input/Output Error", -1, errno.EIO),
    }
    msg, code, num = table[kind]
    return usb.core.USBError(msg, code, num)


def _timeout() -> usb.core.USBTimeoutError:
    return usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)


# --------------------------------------------------------------------------- descriptors


@dataclass
class _DeviceDescriptor:
    idVendor: int = ap.VENDOR_ID
    idProduct: int = ap.PRODUCT_ID
    bcdDevice: int = ap.DEVICE_RELEASE
    bLength: int = 18
    bDescriptorType: int = 1
    bcdUSB: int = 0x0200
    bDeviceClass: int = 0xFF
    bDeviceSubClass: int = 0
    bDeviceProtocol: int = 0
    bMaxPacketSize0: int = 64
    iManufacturer: int = 1
    iProduct: int = 2
    iSerialNumber: int = 3
    bNumConfigurations: int = 1
    bus: int = 1
    address: int = 4
    port_number: int = 2
    port_numbers: tuple[int, ...] = (2,)
    speed: int = 3  # usb.util.SPEED_HIGH


@dataclass
class _ConfigDescriptor:
    bLength: int = 9
    bDescriptorType: int = 2
    wTotalLength: int = 9 + 9 + 7
    bNumInterfaces: int = 1
    bConfigurationValue: int = 1
    iConfiguration: int = 0
    bmAttributes: int = 0x80
    bMaxPower: int = 250
    extra_descriptors: list = field(default_factory=list)


@dataclass
class _InterfaceDescriptor:
    bLength: int = 9
    bDescriptorType: int = 4
    bInterfaceNumber: int = ap.INTERFACE
    bAlternateSetting: int = 0
    bNumEndpoints: int = 1
    bInterfaceClass: int = 0xFF
    bInterfaceSubClass: int = 0
    bInterfaceProtocol: int = 0
    iInterface: int = 0
    extra_descriptors: list = field(default_factory=list)


@dataclass
class _EndpointDescriptor:
    bLength: int = 7
    bDescriptorType: int = 5
    bEndpointAddress: int = ap.BULK_IN_EP
    bmAttributes: int = 2  # bulk
    wMaxPacketSize: int = 512
    bInterval: int = 0
    bRefresh: int = 0
    bSynchAddress: int = 0
    extra_descriptors: list = field(default_factory=list)


class _Handle:
    """An open device handle (one per pyusb Device context)."""

    def __init__(self, dev: _SimCamera) -> None:
        self.dev = dev
        self.open = True


# --------------------------------------------------------------------------- camera state


@dataclass
class _Exposure:
    start: float  # simulated seconds
    exposure_s: float
    light: bool  # shutter open during the exposure
    geometry: ap.Geometry
    angle_deg: float
    filter_name: str | None
    temp_c: float
    readout_s: float

    @property
    def end(self) -> float:
        return self.start + self.exposure_s

    @property
    def done(self) -> float:
        return self.end + self.readout_s


class _SimCamera:
    """The camera behind the USB connector: registers, exposure, cooler, image buffer."""

    def __init__(self, backend: AltaBackend, serial_number: str, firmware: int) -> None:
        self.backend = backend
        self.serial_number = serial_number
        self.firmware = firmware
        self.descriptor = _DeviceDescriptor()
        self.connected = True
        self.claimed_by: _Handle | None = None
        self.regs: dict[int, int] = {}
        self.fetch_count = 0
        self.sequence = 0
        self._power_on_registers()
        # cooler: temperature relaxes from (t0, T0) towards the target
        self._cool_t0 = 0.0
        self._cool_T0 = AMBIENT_C
        self.cooler_on = False
        self.setpoint_c = ap.DEFAULT_SETPOINT_C
        self.regs[ap.Reg.TEMP_DESIRED] = ap.setpoint_to_raw(self.setpoint_c)
        self._reset_imaging()

    def _power_on_registers(self) -> None:
        self.regs[ap.Reg.ID] = ap.CAMERA_ID_KAF0261E
        self.regs[ap.Reg.FIRMWARE_REV] = self.firmware
        # full frame, no binning
        for reg, val in ap.geometry_registers(ap.Geometry(0, 0, 512, 512)):
            self.regs[int(reg)] = val

    def _reset_imaging(self) -> None:
        self.exposure: _Exposure | None = None
        self.armed_pixels = 0
        self.stream = b""
        self.stream_pos = 0
        self.flush_until = -1.0

    # -- cooler
    def _target_c(self) -> float:
        floor = AMBIENT_C - COOLER_MAX_DELTA_C
        return max(self.setpoint_c, floor) if self.cooler_on else AMBIENT_C

    def temperature(self, now: float) -> float:
        target = self._target_c()
        return target + (self._cool_T0 - target) * math.exp(-(now - self._cool_t0) / COOLER_TAU_S)

    def _retarget(self, now: float) -> None:
        self._cool_T0 = self.temperature(now)
        self._cool_t0 = now

    def drive_fraction(self, now: float) -> float:
        if not self.cooler_on:
            return 0.0
        return min(max((AMBIENT_C - self.temperature(now)) / COOLER_MAX_DELTA_C, 0.0), 1.0)

    # -- status
    def status_word(self, now: float) -> int:
        s = 0
        e = self.exposure
        if e is not None:
            if now < e.end:
                s |= ap.ST_EXPOSING
                if e.light:
                    s |= ap.ST_SHUTTER_OPEN
            if now < e.done:
                s |= ap.ST_IMAGING_ACTIVE
            else:
                s |= ap.ST_IMAGE_DONE
        if self.forced_shutter() == "open":
            s |= ap.ST_SHUTTER_OPEN
        if now < self.flush_until:
            s |= ap.ST_FLUSHING
        if self.cooler_on:
            s |= ap.ST_COOLER_ACTIVE
            if abs(self.temperature(now) - self.setpoint_c) <= AT_TEMP_BAND_C:
                s |= ap.ST_AT_TEMP
        return s

    def status_block(self, now: float) -> bytes:
        self.fetch_count = (self.fetch_count + 1) & 0xFFFFFFFF
        block = ap.StatusBlock(
            temp_heatsink=ap.temperature_to_raw(AMBIENT_C + 5.0 * self.drive_fraction(now)),
            temp_ccd=ap.temperature_to_raw(self.temperature(now)),
            cooler_drive=int(round(self.drive_fraction(now) * ap.COOLER_DRIVE_FULL_SCALE)),
            input_voltage=int(round(INPUT_VOLTAGE_V / ap.INPUT_VOLTAGE_SCALE_V)),
            tdi_counter=0,
            sequence_counter=self.sequence & 0xFFFF,
            status=self.status_word(now),
            uframe=int(now / 125e-6) & 0xFFFF,
            fetch_count=self.fetch_count,
            data_avail=int(self.exposure is not None and now >= self.exposure.done),
            most_recent_frame=self.sequence & 0xFFFF,
            ready_frame=self.sequence & 0xFFFF,
            current_frame=self.sequence & 0xFFFF,
        )
        return ap.pack_status(block, extended=self.firmware >= ap.EXTENDED_STATUS_FIRMWARE)

    def forced_shutter(self) -> str | None:
        op_a = self.regs.get(ap.Reg.OP_A, 0)
        if op_a & ap.OP_A_DISABLE_SHUTTER:  # forced closed wins over forced open
            return "closed"
        if op_a & ap.OP_A_FORCE_SHUTTER:
            return "open"
        return None

    # -- register side effects
    def read_register(self, reg: int, now: float) -> int:
        if reg == ap.Reg.STATUS:
            return self.status_word(now)
        if reg == ap.Reg.TEMP_CCD:
            return ap.temperature_to_raw(self.temperature(now))
        if reg == ap.Reg.TEMP_DRIVE:
            return int(round(self.drive_fraction(now) * ap.COOLER_DRIVE_FULL_SCALE))
        if reg == ap.Reg.SEQUENCE_COUNTER:
            return self.sequence & 0xFFFF
        return self.regs.get(reg, 0)

    def write_register(self, reg: int, value: int, now: float) -> None:
        """Store a write and act on it. Raises ``_Stall`` for commands the camera refuses."""
        if reg in (ap.Reg.STATUS, ap.Reg.ID, ap.Reg.FIRMWARE_REV):
            return  # read-only
        self.regs[reg] = value
        if reg == ap.Reg.CMD_A:
            if value & (ap.CMD_A_EXPOSE | ap.CMD_A_DARK):
                self._start_exposure(now, light=bool(value & ap.CMD_A_EXPOSE))
            elif value & ap.CMD_A_FLUSH:
                self.flush_until = now + FLUSH_TIME_S
        elif reg == ap.Reg.CMD_B:
            if value & ap.CMD_B_RESET:
                self._reset_imaging()
            if value & ap.CMD_B_END_EXPOSURE and self.exposure is not None and now < self.exposure.end:
                e = self.exposure
                e.exposure_s = now - e.start
            if value & ap.CMD_B_RAMP_TO_SETPOINT:
                self._retarget(now)
                self.cooler_on = True
            if value & ap.CMD_B_RAMP_TO_AMBIENT:
                self._retarget(now)
                self.cooler_on = False
        elif reg == ap.Reg.TEMP_DESIRED:
            self._retarget(now)
            self.setpoint_c = ap.raw_to_temperature(value)

    def _start_exposure(self, now: float, *, light: bool) -> None:
        if self.exposure is not None and now < self.exposure.done:
            raise _Stall("exposure already in progress")
        try:
            g = ap.geometry_from_registers(self.regs)
        except ProtocolError as e:  # the real camera would read garbage; the twin refuses
            raise _Stall(str(e)) from None
        ticks = ap.timer_from_registers(self.regs.get(ap.Reg.TIMER_UPPER, 0), self.regs.get(ap.Reg.TIMER_LOWER, 0))
        forced = self.forced_shutter()
        shutter_open = forced == "open" or (light and forced != "closed")
        bench = self.backend.bench
        with bench.lock:
            angle, filt = bench.stage_angle_deg, bench.filter_name
        readout = 512 * ROW_SHIFT_TIME_S + g.pixels * PIXEL_TIME_S
        self.exposure = _Exposure(now, ap.ticks_to_seconds(ticks), shutter_open, g, angle, filt,
                                  self.temperature(now), readout)
        self.stream = b""
        self.stream_pos = 0
        self.flush_until = -1.0

    # -- image data
    def data_ready(self, now: float) -> bool:
        return self.exposure is not None and now >= self.exposure.done and self.armed_pixels > 0

    def ensure_stream(self) -> None:
        """Synthesise the frame once the readout is complete (lazily, on the first bulk read)."""
        if self.stream or self.exposure is None:
            return
        e = self.exposure
        g = e.geometry
        model = self.backend.ccd
        rng = self.backend.rng
        s = model.sensor
        col_slice = slice(g.x, g.x + g.cols * g.bin_x)
        row_slice = slice(g.y, g.y + g.rows * g.bin_y)
        # whole columns, so that charge blooming from outside the ROI arrives in it
        if e.light:
            rate = np.asarray(self.backend.bench.scene(e.angle_deg, e.filter_name, slice(0, s.height), col_slice),
                              dtype=np.float64)
            shape = None
        else:
            rate, shape = None, (s.height, g.cols * g.bin_x)
        image = model.expose(rate, e.exposure_s, e.temp_c, rng, bin_x=g.bin_x, bin_y=g.bin_y, shape=shape,
                             crop=(row_slice, slice(None)))
        extra = model.read_noise_pixels(g.rows, rng)
        data = ap.frame_to_bytes(image, extra)
        # the camera sends what GET_IMAGE armed: more is cut, less never completes
        self.stream = data[: 2 * self.armed_pixels]
        self.sequence += 1


class _Stall(Exception):
    """The device answers a control request with STALL."""


# --------------------------------------------------------------------------- backend


class AltaBackend(usb.backend.IBackend):
    """pyusb backend with one simulated Alta-U camera on it.

    Args:
        bench: name of the :class:`Bench` (shared with the stage and filter twins).
        time_scale: simulated seconds per real second (100: a 1 s exposure takes 10 ms);
            None takes the bench's ``time_scale``, as the serial twins do.
        faults: seeded fault plan (kinds ``pipe``, ``disconnect``, ``short``).
        seed: seed of the sensor noise.
        serial_number: string descriptor 3.
        firmware: camera firmware revision (register 101); >= 16 gives the 27-byte status.

    Attributes:
        access_denied: when True, ``open_device`` fails with EACCES (no udev rule).
        ccd: the sensor model (swap its ``nonlinearity`` for the bench's effect).
        transfers: count of control and bulk transfers served (for tests).
    """

    def __init__(self, bench: str = "default", *, time_scale: float | None = None, faults: FaultPlan | None = None,
                 seed: int = 0, serial_number: str = "SIM0001", firmware: int = 14) -> None:
        super().__init__()
        self.bench_name = bench
        self.clock = SimClock(time_scale if time_scale is not None else get_bench(bench).time_scale)
        self.faults = faults or FaultPlan()
        self.rng = np.random.default_rng(seed)
        self.ccd = CcdModel()
        self.access_denied = False
        self.transfers = 0
        self.lock = threading.RLock()
        self.camera = _SimCamera(self, serial_number, firmware)

    @property
    def bench(self) -> Bench:
        return get_bench(self.bench_name)

    # -- enumeration and descriptors
    def enumerate_devices(self):
        with self.lock:
            return [self.camera] if self.camera.connected else []

    def get_parent(self, dev):
        return None

    def get_device_descriptor(self, dev):
        return dev.descriptor

    def get_configuration_descriptor(self, dev, config):
        if config != 0:
            raise IndexError(f"configuration {config}")
        return _ConfigDescriptor()

    def get_interface_descriptor(self, dev, intf, alt, config):
        if (intf, alt, config) != (0, 0, 0):
            raise IndexError(f"interface {intf} alt {alt} config {config}")
        return _InterfaceDescriptor()

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        if (ep, intf, alt, config) != (0, 0, 0, 0):
            raise IndexError(f"endpoint {ep}")
        return _EndpointDescriptor()

    # -- handles
    def open_device(self, dev):
        with self.lock:
            if not dev.connected:
                raise _err("nodev")
            if self.access_denied:
                raise _err("access")
            return _Handle(dev)

    def close_device(self, dev_handle):
        with self.lock:
            dev_handle.open = False
            if dev_handle.dev.claimed_by is dev_handle:
                dev_handle.dev.claimed_by = None

    def set_configuration(self, dev_handle, config_value):
        self._check(dev_handle)
        if config_value not in (0, 1):
            raise _err("io")

    def get_configuration(self, dev_handle):
        self._check(dev_handle)
        return 1

    def set_interface_altsetting(self, dev_handle, intf, altsetting):
        self._check(dev_handle)

    def claim_interface(self, dev_handle, intf):
        with self.lock:
            self._check(dev_handle)
            cam = dev_handle.dev
            if cam.claimed_by is not None and cam.claimed_by is not dev_handle and cam.claimed_by.open:
                raise _err("busy")  # the camera is open in another program
            cam.claimed_by = dev_handle

    def release_interface(self, dev_handle, intf):
        with self.lock:
            if dev_handle.dev.claimed_by is dev_handle:
                dev_handle.dev.claimed_by = None

    def is_kernel_driver_active(self, dev_handle, intf):
        return False

    def clear_halt(self, dev_handle, ep):
        self._check(dev_handle)

    def reset_device(self, dev_handle):
        with self.lock:
            self._check(dev_handle)
            dev_handle.dev._reset_imaging()

    def _check(self, dev_handle) -> None:
        if not dev_handle.open:
            raise _err("io")
        if not dev_handle.dev.connected:
            raise _err("nodev")

    def disconnect(self) -> None:
        """Unplug the camera (as the ``disconnect`` fault does)."""
        with self.lock:
            self.camera.connected = False

    # -- transfers
    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        with self.lock:
            self._check(dev_handle)
            self.transfers += 1
            cam = dev_handle.dev
            now = self.clock.now()
            kind = bmRequestType & 0x60
            if kind == 0x00:  # standard request
                return self._standard(cam, bmRequestType, bRequest, wValue, wIndex, data)
            if kind != 0x40:
                raise _err("pipe")
            if self.faults.hit("pipe"):
                raise _err("pipe")
            try:
                if bmRequestType == ap.REQ_IN:
                    if bRequest == ap.Request.STATUS and wValue == 0 and wIndex == 0:
                        return _copy_in(data, cam.status_block(now))
                    if bRequest == ap.Request.REGISTER:
                        return _copy_in(data, cam.read_register(wIndex, now).to_bytes(2, "little"))
                    raise _Stall(f"unknown IN request {bRequest:#x}")
                if bmRequestType == ap.REQ_OUT:
                    payload = bytes(data) if data is not None else b""
                    if bRequest == ap.Request.REGISTER:
                        if len(payload) != 2:
                            raise _Stall("register write without 2 data bytes")
                        cam.write_register(wIndex, int.from_bytes(payload, "little"), now)
                    elif bRequest == ap.Request.SOFT_RESET:
                        cam._reset_imaging()
                    elif bRequest == ap.Request.GET_IMAGE:
                        cam.armed_pixels = ap.pixels_from_request(wValue, wIndex)
                        cam.stream, cam.stream_pos = b"", 0
                    elif bRequest == ap.Request.STOP_IMAGE:
                        cam.armed_pixels = 0
                        cam.stream, cam.stream_pos = b"", 0
                    else:
                        raise _Stall(f"unknown OUT request {bRequest:#x}")
                    return len(payload)
            except _Stall:
                raise _err("pipe") from None
            raise _err("pipe")

    def _standard(self, cam: _SimCamera, bm: int, req: int, w_value: int, w_index: int, data) -> int:
        if bm == 0x80 and req == 0x06 and (w_value >> 8) == 3:  # GET_DESCRIPTOR(STRING)
            index = w_value & 0xFF
            if index == 0:
                body = _LANGID_EN_US.to_bytes(2, "little")
            elif index == 3:
                body = cam.serial_number.encode("utf-16-le")
            elif index in _STRINGS:
                body = _STRINGS[index].encode("utf-16-le")
            else:
                raise _err("pipe")
            return _copy_in(data, bytes([2 + len(body), 3]) + body)
        if bm == 0x80 and req == 0x08:  # GET_CONFIGURATION
            return _copy_in(data, b"\x01")
        if bm == 0x00 and req == 0x09:  # SET_CONFIGURATION
            return 0
        raise _err("pipe")

    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        deadline = None if not timeout else time.monotonic() + timeout / 1000.0
        while True:
            with self.lock:
                self._check(dev_handle)
                cam = dev_handle.dev
                if ep != ap.BULK_IN_EP:
                    raise _err("pipe")
                now = self.clock.now()
                if cam.data_ready(now):
                    cam.ensure_stream()
                    remaining = len(cam.stream) - cam.stream_pos
                    if remaining > 0:
                        self.transfers += 1
                        return self._deliver(cam, buff, remaining)
                wait_s = self._wait_hint(cam, now)
            if deadline is not None and time.monotonic() >= deadline:
                raise _timeout()  # the device NAKs: nothing to send
            time.sleep(min(wait_s, 0.005) if deadline is None else
                       max(0.0, min(wait_s, 0.005, deadline - time.monotonic())))

    def _deliver(self, cam: _SimCamera, buff, remaining: int) -> int:
        n = min(len(buff), remaining)
        if self.faults.hit("disconnect"):
            cam.connected = False
            raise _err("nodev")
        if n > 2 and self.faults.hit("short"):
            n = int(n * self.faults.uniform(0.1, 0.9)) & ~1
        mv = memoryview(buff).cast("B")
        mv[:n] = cam.stream[cam.stream_pos: cam.stream_pos + n]
        cam.stream_pos += n
        if cam.stream_pos >= len(cam.stream):  # transfer complete: back to idle
            cam.armed_pixels = 0
        return n

    def _wait_hint(self, cam: _SimCamera, now: float) -> float:
        if cam.exposure is None or cam.armed_pixels == 0:
            return 0.005
        return self.clock.real_seconds(max(cam.exposure.done - now, 0.0)) + 1e-4


def _copy_in(buff, payload: bytes) -> int:
    """Copy an IN reply into pyusb's buffer; a reply longer than the buffer is cut."""
    n = min(len(buff), len(payload))
    memoryview(buff).cast("B")[:n] = payload[:n]
    return n
