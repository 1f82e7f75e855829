"""Apogee Alta-U camera (U260, Kodak KAF-0261E) over pyusb.

The transport is whatever pyusb backend is passed in: ``None`` picks libusb
(the real camera), :class:`sim_devices.alta_usb.AltaBackend` the twin. The byte
protocol lives in :mod:`drivers.alta_protocol`.

One exposure (libapogee's minimum sequence):

1. reset (CMD_B reset, then the scratch writes libapogee found the FPGA needs as
   a delay), flush;
2. arm the image transfer: GET_IMAGE with rows*(cols+1) pixels;
3. write the ROI registers (horizontal skips and count, vertical regions with binning);
4. write the exposure timer, low word first;
5. CMD_A expose (shutter per OP_A) or dark;
6. poll STATUS until image-done, within the caller's timeout;
7. bulk-read endpoint 0x86 in chunks of at most 126,976 bytes, then drop the
   first pixel of every row.

USB errors are mapped to the device errors: a timeout to DeviceTimeout, a stall
(EPIPE) on a control transfer is cleared and retried once where repeating the
request is harmless, then ProtocolError; a vanished device, missing permission
or a camera held by another program to DeviceConnectionError with a hint.
"""

from __future__ import annotations

import errno
import time
from collections.abc import Callable
from typing import Any

import usb.core
import usb.util

from drivers import alta_protocol as ap
from drivers.errors import (
    DeviceConnectionError,
    DeviceError,
    DeviceTimeout,
    ProtocolError,
)
from drivers.interfaces import ROI, Camera, CoolerStatus, Frame, SensorInfo, ShutterMode
from drivers.iolog import Transcript

UDEV_HINT = (
    "no permission to open the camera: install a udev rule, e.g. /etc/udev/rules.d/99-apogee.rules with "
    'SUBSYSTEM=="usb", ATTRS{idVendor}=="125c", MODE="0666", then run '
    "'sudo udevadm control --reload && sudo udevadm trigger' and replug the camera"
)
BUSY_HINT = "the camera is in use by another program (MaxIm DL, an INDI server, another rig process): close it and retry"

# Requests a stall may be retried for: reads, and writes that set a value rather
# than trigger an action. CMD_A (starts an exposure), CMD_B (reset, cooler
# commands) and GET_IMAGE are not repeated blindly.
_NO_RETRY_REGS = {int(ap.Reg.CMD_A), int(ap.Reg.CMD_B)}


class AltaCamera(Camera):
    """Apogee Alta-U with a KAF-0261E sensor.

    Args:
        backend: pyusb backend (None: libusb, the real camera).
        serial_number: pick the camera with this USB serial number when several are attached.
        sensor: the sensor's facts (gain, bias, noise, full well).
        transcript: byte log of every control and bulk transfer (``--log-io``).
        readout_timeout_s: limit for one bulk read of image data, seconds.

    Raises:
        DeviceConnectionError: no Alta-U found, no permission, camera busy, or the
            camera reports a different sensor.
    """

    device_name = "camera"
    poll_interval_s: float = 0.005
    flush_before_exposure: bool = True

    def __init__(self, *, backend: Any = None, serial_number: str | None = None, sensor: SensorInfo = ap.KAF0261E,
                 transcript: Transcript | None = None, readout_timeout_s: float = 30.0) -> None:
        super().__init__(sensor, (ap.MIN_EXPOSURE_S, ap.MAX_EXPOSURE_S))
        self._log = transcript
        self._readout_timeout_s = float(readout_timeout_s)
        self._shutter = ShutterMode.NORMAL
        self._last_status: bytes | None = None
        self._dev = self._open(backend, serial_number)
        try:
            raw_id = self._read_reg(ap.Reg.ID)
            self._firmware = self._read_reg(ap.Reg.FIRMWARE_REV)
            self._camera_id = raw_id & ap.CAMERA_ID_MASK
            if self._camera_id != ap.CAMERA_ID_KAF0261E:
                raise DeviceConnectionError(
                    f"Apogee camera id {self._camera_id} is not an Alta U260 (KAF-0261E, id {ap.CAMERA_ID_KAF0261E}); "
                    "check the 'camera' entry in rig.yaml", device=self.device_name)
            self._status_len = ap.status_length(self._firmware)
        except BaseException:
            self._release()
            raise

    # ------------------------------------------------------------------ connection
    def _open(self, backend: Any, serial_number: str | None) -> Any:
        try:
            found = list(usb.core.find(find_all=True, idVendor=ap.VENDOR_ID, idProduct=ap.PRODUCT_ID, backend=backend))
        except usb.core.NoBackendError:
            raise DeviceConnectionError(
                "no USB backend: install libusb-1.0 (apt-get install libusb-1.0-0)", device=self.device_name) from None
        except usb.core.USBError as e:
            raise self._map_open_error(e) from None
        if not found:
            raise DeviceConnectionError(
                f"no Apogee Alta-U (USB {ap.VENDOR_ID:04x}:{ap.PRODUCT_ID:04x}) found; is it plugged in and powered?",
                device=self.device_name)
        dev = None
        sn: str | None = None
        serials = []
        for d in found:
            try:
                sn = d.serial_number
            except usb.core.USBError as e:
                if e.errno in (errno.EACCES, errno.EBUSY):
                    raise self._map_open_error(e) from None
                sn = None
            except ValueError:  # pyusb: no language ids, typically no permission to open the device
                sn = None
            serials.append(sn)
            if serial_number is None or sn == serial_number:
                dev = d
                break
        if dev is None:
            unreadable = " (unreadable serial numbers usually mean no permission: " + UDEV_HINT + ")" \
                if None in serials else ""
            raise DeviceConnectionError(
                f"no Alta-U with serial number {serial_number!r}; found {', '.join(map(str, serials))}{unreadable}",
                device=self.device_name)
        self._serial = sn
        try:
            try:
                cfg = dev.get_active_configuration()
            except usb.core.USBError:
                cfg = None
            if cfg is None:
                dev.set_configuration()
            usb.util.claim_interface(dev, ap.INTERFACE)
        except usb.core.USBError as e:
            usb.util.dispose_resources(dev)
            raise self._map_open_error(e) from None
        self._record("!", f"opened Alta-U serial {self._serial} bus {dev.bus} address {dev.address}")
        return dev

    def _map_open_error(self, e: usb.core.USBError) -> DeviceError:
        if e.errno == errno.EACCES:
            return DeviceConnectionError(UDEV_HINT, device=self.device_name)
        if e.errno == errno.EBUSY:
            return DeviceConnectionError(BUSY_HINT, device=self.device_name)
        return self._map_error(e, "opening the camera")

    def _map_error(self, e: usb.core.USBError, what: str) -> DeviceError:
        if isinstance(e, usb.core.USBTimeoutError) or e.errno == errno.ETIMEDOUT:
            return DeviceTimeout(f"USB timeout while {what}", device=self.device_name)
        if e.errno == errno.EPIPE:
            return ProtocolError(f"the camera stalled {what} (USB pipe error)", device=self.device_name)
        if e.errno in (errno.ENODEV, errno.ENOENT, errno.EIO, errno.ESHUTDOWN):
            return DeviceConnectionError(f"the camera disappeared while {what} ({e.strerror}); check the USB cable "
                                         "and power", device=self.device_name)
        return DeviceConnectionError(f"USB error while {what}: {e}", device=self.device_name)

    def _release(self) -> None:
        dev = getattr(self, "_dev", None)
        if dev is None:
            return
        try:
            usb.util.release_interface(dev, ap.INTERFACE)
        except (usb.core.USBError, ValueError):
            pass  # the device may be gone; the handle is closed below either way
        usb.util.dispose_resources(dev)
        self._dev = None

    def close(self) -> None:
        """Return the shutter to normal (closed when idle) and release the camera."""
        if getattr(self, "_dev", None) is None:
            return
        try:
            if self._shutter is not ShutterMode.NORMAL:
                self._do_set_shutter(ShutterMode.NORMAL)
        except DeviceError as e:
            self._record("!", f"could not restore the shutter on close: {e}")
            raise
        finally:
            self._release()
            self._record("!", "closed")

    # ------------------------------------------------------------------ transfers
    def _record(self, direction: str, text: str) -> None:
        if self._log is not None:
            self._log.record(self.device_name, direction, text)

    def _control(self, what: str, call: Callable[[], Any], *, retry: bool) -> Any:
        if getattr(self, "_dev", None) is None:
            raise DeviceConnectionError("the camera is closed", device=self.device_name)
        for attempt in (1, 2):
            try:
                return call()
            except usb.core.USBError as e:
                if e.errno == errno.EPIPE and retry and attempt == 1:
                    # a stalled control request executed nothing; endpoint 0 clears itself
                    # with the next setup packet, so repeating is safe for idempotent requests
                    self._record("!", f"stall on {what}; retrying once")
                    continue
                self._record("!", f"{what} failed: {e}")
                raise self._map_error(e, what) from None
        raise AssertionError("unreachable")

    def _read_reg(self, reg: int) -> int:
        name = ap.describe_register(reg)
        data = self._control(f"reading {name}", lambda: self._dev.ctrl_transfer(
            ap.REQ_IN, ap.Request.REGISTER, 0, int(reg), 2, ap.CTRL_TIMEOUT_MS), retry=True)
        value = ap.parse_register(data, int(reg))
        self._record("<", f"REG {name} = {value:#06x}")
        return value

    def _write_reg(self, reg: int, value: int) -> None:
        name = ap.describe_register(reg)
        payload = ap.pack_register(value)
        self._record(">", f"REG {name} := {value:#06x}")
        n = self._control(f"writing {name}", lambda: self._dev.ctrl_transfer(
            ap.REQ_OUT, ap.Request.REGISTER, 0, int(reg), payload, ap.CTRL_TIMEOUT_MS),
            retry=int(reg) not in _NO_RETRY_REGS)
        if n != len(payload):
            raise ProtocolError(f"register write of {name} sent {n} of 2 bytes", device=self.device_name)

    def _request_out(self, request: ap.Request, w_value: int = 0, w_index: int = 0, *, retry: bool) -> None:
        self._record(">", f"{request.name} wValue={w_value:#06x} wIndex={w_index:#06x}")
        self._control(request.name, lambda: self._dev.ctrl_transfer(
            ap.REQ_OUT, int(request), w_value, w_index, None, ap.CTRL_TIMEOUT_MS), retry=retry)

    def _status(self) -> ap.StatusBlock:
        data = self._control("reading STATUS", lambda: self._dev.ctrl_transfer(
            ap.REQ_IN, ap.Request.STATUS, 0, 0, self._status_len, ap.CTRL_TIMEOUT_MS), retry=True)
        raw = bytes(data)
        if raw != self._last_status:  # the log keeps changes only, not every poll
            self._record("<", f"STATUS {raw.hex()}")
            self._last_status = raw
        if len(raw) != self._status_len:
            raise ProtocolError(f"status reply of {len(raw)} bytes, expected {self._status_len}",
                                device=self.device_name)
        return ap.parse_status(raw)

    # ------------------------------------------------------------------ identity and state
    def identity(self) -> str:
        return (f"Apogee Alta-U camera id {self._camera_id} ({self.sensor.model}) "
                f"firmware {self._firmware} serial {self._serial}")

    @property
    def firmware(self) -> int:
        return self._firmware

    def temperature(self) -> float:
        return self._status().ccd_temp_c

    def cooler_status(self) -> CoolerStatus:
        st = self._status()
        setpoint = ap.raw_to_temperature(self._read_reg(ap.Reg.TEMP_DESIRED))
        return CoolerStatus(
            on=st.has(ap.ST_COOLER_ACTIVE),
            setpoint_c=setpoint,
            temperature_c=st.ccd_temp_c,
            at_temperature=st.has(ap.ST_AT_TEMP),
            drive_percent=st.drive_percent,
        )

    def _do_set_cooler(self, setpoint_c: float, on: bool) -> None:
        self._write_reg(ap.Reg.TEMP_DESIRED, ap.setpoint_to_raw(setpoint_c))
        self._write_reg(ap.Reg.CMD_B, ap.CMD_B_RAMP_TO_SETPOINT if on else ap.CMD_B_RAMP_TO_AMBIENT)

    def _do_set_shutter(self, mode: ShutterMode) -> None:
        op_a = self._read_reg(ap.Reg.OP_A) & ~(ap.OP_A_FORCE_SHUTTER | ap.OP_A_DISABLE_SHUTTER)
        if mode is ShutterMode.OPEN:
            op_a |= ap.OP_A_FORCE_SHUTTER
        elif mode is ShutterMode.CLOSED:
            op_a |= ap.OP_A_DISABLE_SHUTTER
        self._write_reg(ap.Reg.OP_A, op_a)
        self._shutter = mode

    @property
    def shutter(self) -> ShutterMode:
        return self._shutter

    def _do_set_roi(self, roi: ROI) -> None:
        # registers are written with every exposure; here only the hardware's binning limits
        ap.check_geometry(self._geometry(roi), self.sensor)

    @staticmethod
    def _geometry(roi: ROI) -> ap.Geometry:
        rows, cols = roi.shape
        return ap.Geometry(x=roi.x, y=roi.y, cols=cols, rows=rows, bin_x=roi.bin_x, bin_y=roi.bin_y)

    # ------------------------------------------------------------------ exposure
    def _reset(self, flush: bool) -> None:
        self._write_reg(ap.Reg.CMD_B, ap.CMD_B_RESET)
        # libapogee: "a little delay before we start flushing ... found by trial and error"
        for value in (0x8086, 0x8088) * 3:
            self._write_reg(ap.Reg.SCRATCH, value)
        if flush:
            self._write_reg(ap.Reg.CMD_A, ap.CMD_A_FLUSH)
            for value in (0x8086, 0x8088):
                self._write_reg(ap.Reg.SCRATCH, value)

    def _do_expose(self, seconds: float, dark: bool, timeout_s: float) -> Frame:
        roi = self.roi
        g = self._geometry(roi)
        ap.check_geometry(g, self.sensor)
        ticks = ap.exposure_ticks(seconds)  # LimitError before any transfer
        w_value, w_index = ap.image_request(g.pixels)
        deadline = time.monotonic() + timeout_s

        self._reset(self.flush_before_exposure)
        temp_start = self.temperature()
        self._request_out(ap.Request.GET_IMAGE, w_value, w_index, retry=False)
        try:
            for reg, value in ap.geometry_registers(g, self.sensor):
                self._write_reg(reg, value)
            for reg, value in ap.timer_writes(ticks):
                self._write_reg(reg, value)
            t_start = time.time()
            self._write_reg(ap.Reg.CMD_A, ap.CMD_A_DARK if dark else ap.CMD_A_EXPOSE)
            self._wait_image_done(deadline, seconds)
            t_done = time.monotonic()
            raw = self._read_image(g)
            t_end = time.time()
            download_s = time.monotonic() - t_done
        except DeviceError as e:
            self._abort(e)
            raise
        data = ap.frame_from_bytes(raw, g.rows, g.cols)
        self._record("!", f"frame {g.rows}x{g.cols} read, {len(raw)} bytes")
        temp_end = self.temperature()
        light_blocked = self._shutter is ShutterMode.CLOSED or (dark and self._shutter is not ShutterMode.OPEN)
        return Frame(
            data=data,
            exposure_s=ap.ticks_to_seconds(ticks),
            dark=light_blocked,
            ccd_temp_c=temp_start,
            start_time=t_start,
            end_time=t_end,
            roi=roi,
            camera=self.identity(),
            extra={"requested_exposure_s": seconds, "ccd_temp_end_c": temp_end, "shutter": self._shutter.value,
                   "timer_ticks": ticks, "download_s": download_s},
        )

    def _wait_image_done(self, deadline: float, seconds: float) -> None:
        while True:
            st = self._status()
            if st.image_done:
                return
            if time.monotonic() > deadline:
                raise DeviceTimeout(f"image not done within the time limit ({seconds} s exposure); status "
                                    f"{st.status:#06x}", device=self.device_name)
            time.sleep(self.poll_interval_s)

    def _read_image(self, g: ap.Geometry) -> bytearray:
        out = bytearray()
        timeout_ms = max(1, int(self._readout_timeout_s * 1000))
        for size in ap.chunk_sizes(g.nbytes):
            what = f"reading image data ({len(out)} of {g.nbytes} bytes done)"
            try:
                chunk = self._dev.read(ap.BULK_IN_EP, size, timeout_ms)
            except usb.core.USBError as e:
                self._record("!", f"bulk 0x86 read of {size} bytes failed: {e}")
                raise self._map_error(e, what) from None
            self._record("<", f"bulk 0x86 {len(chunk)}/{size} bytes")
            if len(chunk) != size:
                raise ProtocolError(f"short bulk read: {len(chunk)} of {size} bytes "
                                    f"({len(out) + len(chunk)} of {g.nbytes} bytes of the frame)",
                                    device=self.device_name)
            out += chunk
        return out

    def _abort(self, cause: DeviceError) -> None:
        """Stop a failed transfer and reset the camera so that the next exposure can start."""
        if isinstance(cause, DeviceConnectionError):
            return  # the camera is gone; nothing to talk to
        try:
            self._request_out(ap.Request.STOP_IMAGE, retry=True)
            try:
                self._dev.clear_halt(ap.BULK_IN_EP)
            except usb.core.USBError as e:
                raise self._map_error(e, "clearing the bulk endpoint") from None
            self._reset(flush=True)
        except DeviceError as e:
            cause.add_note(f"cleanup after the failure also failed: {e}")
            self._record("!", f"cleanup failed: {e}")
