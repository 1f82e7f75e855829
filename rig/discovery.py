"""Finding the rig's devices on this machine: serial ports, USB devices, and the
``rig.yaml`` entries that would use them.

The port lister and the USB backend are passed in (pyserial's ``comports`` and a
pyusb backend by default), so the scan runs against fakes or the simulated camera
without patching. Nothing here sends bytes to a serial port: a port's role is
guessed from what its USB adapter reports, and ``rig devices --config`` confirms
it through the device's protocol.
"""

from __future__ import annotations

import errno as _errno
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import yaml

#: USB vendor of Apogee Instruments; the Alta-U reports product 0x0010.
APOGEE_VID = 0x125C
ALTA_U_PID = 0x0010
FTDI_VID = 0x0403
PROLIFIC_VID = 0x067B
SILABS_VID = 0x10C4

#: USB vendor ids worth listing, with what they usually are on this rig.
KNOWN_USB_VENDORS: dict[int, str] = {
    APOGEE_VID: "Apogee Instruments camera",
    FTDI_VID: "FTDI USB-serial (RS-232 adapter, or the FW102C's built-in port)",
    PROLIFIC_VID: "Prolific PL2303 USB-RS232 adapter",
    SILABS_VID: "Silicon Labs CP210x USB-serial adapter",
}
_ADAPTER_VENDORS = {FTDI_VID: "FTDI", PROLIFIC_VID: "Prolific", SILABS_VID: "Silicon Labs"}
_APOGEE_PRODUCTS = {ALTA_U_PID: "Alta-U"}

#: Where udev keeps stable names of USB serial ports (they survive re-plugging,
#: unlike /dev/ttyUSB<n>, whose number depends on the order the adapters appear).
SERIAL_BY_ID_DIR = "/dev/serial/by-id"

#: The udev rules file shipped for the camera, relative to the repository root.
UDEV_RULES = "udev/99-apogee-alta.rules"

ROLE_WHEEL = "filter wheel (FW102C?)"
ROLE_ADAPTER = "USB-serial adapter"
ROLE_PORT = "serial port"


@dataclass(frozen=True)
class SerialPortInfo:
    """One serial port as pyserial lists it, with a guess of what is behind it.

    ``vid``/``pid``/``serial_number``/``manufacturer``/``product`` are None when the
    port is not a USB adapter or the adapter does not report them.
    """

    device: str
    description: str
    vid: int | None = None
    pid: int | None = None
    serial_number: str | None = None
    manufacturer: str | None = None
    product: str | None = None
    by_id: str | None = None
    role: str = ROLE_PORT

    @property
    def usb_id(self) -> str:
        """``VVVV:PPPP`` in hex, or an empty string for a non-USB port."""
        return "" if self.vid is None else f"{self.vid:04x}:{(self.pid or 0):04x}"

    @property
    def stable_path(self) -> str:
        """The path to put in ``rig.yaml``: the by-id link when there is one."""
        return self.by_id or self.device


@dataclass(frozen=True)
class UsbDeviceInfo:
    """One USB device of a known vendor.

    ``access`` is ``ok`` (opened, read its strings, claimed interface 0), ``denied``
    (the user may not open it: udev permissions), ``busy`` (another program holds it),
    ``error`` (another failure, in ``error``) or ``not-tried`` (a serial adapter: it is
    used through its tty, not over libusb).
    """

    vendor_id: int
    product_id: int
    kind: str
    bus: int | None = None
    address: int | None = None
    manufacturer: str | None = None
    product: str | None = None
    serial_number: str | None = None
    access: str = "not-tried"
    error: str = ""

    @property
    def usb_id(self) -> str:
        return f"{self.vendor_id:04x}:{self.product_id:04x}"

    @property
    def is_apogee(self) -> bool:
        return self.vendor_id == APOGEE_VID


@dataclass(frozen=True)
class ScanResult:
    """What a scan found. ``usb_error`` says why USB could not be listed (no libusb)."""

    ports: list[SerialPortInfo] = field(default_factory=list)
    usb: list[UsbDeviceInfo] = field(default_factory=list)
    usb_error: str | None = None

    @property
    def cameras(self) -> list[UsbDeviceInfo]:
        return [d for d in self.usb if d.is_apogee]

    def to_dict(self) -> dict[str, Any]:
        return {
            "ports": [{**asdict(p), "usb_id": p.usb_id} for p in self.ports],
            "usb": [{**asdict(d), "usb_id": d.usb_id} for d in self.usb],
            "usb_error": self.usb_error,
        }


def _is_fw102c(vid: int | None, serial: str | None, text: str) -> bool:
    # The FW102C has an FTDI USB-serial chip inside. Thorlabs programs its serial
    # number with a "TP" prefix (seen in public drivers that select the wheel by it);
    # the product string naming the model is reported by some units. Both are
    # heuristics: `rig devices` confirms with the wheel's `*idn?` reply.
    if vid != FTDI_VID:
        return False
    t = text.lower()
    return (serial or "").upper().startswith("TP") or any(k in t for k in ("fw102", "fw212", "filter wheel"))


def _by_id_links(by_id_dir: str | Path) -> dict[str, str]:
    """Map each real device path to its stable /dev/serial/by-id link."""
    links: dict[str, str] = {}
    d = Path(by_id_dir)
    if not d.is_dir():
        return links
    for link in sorted(d.iterdir()):
        links.setdefault(os.path.realpath(link), str(link))
    return links


def list_serial_ports(
    list_ports: Callable[[], Iterable[Any]] | None = None,
    by_id_dir: str | Path = SERIAL_BY_ID_DIR,
) -> list[SerialPortInfo]:
    """List serial ports with their USB identity and a guess of their role.

    Args:
        list_ports: returns ListPortInfo-like objects (attributes ``device``,
            ``description``, ``vid``, ``pid``, ``serial_number``, ``manufacturer``,
            ``product``); default ``serial.tools.list_ports.comports``.
        by_id_dir: directory of stable port links (``/dev/serial/by-id``).
    """
    if list_ports is None:
        from serial.tools.list_ports import comports

        list_ports = comports
    links = _by_id_links(by_id_dir)
    out = []
    for p in list_ports():
        vid = getattr(p, "vid", None)
        serial = getattr(p, "serial_number", None)
        manufacturer = getattr(p, "manufacturer", None)
        product = getattr(p, "product", None)
        description = str(getattr(p, "description", "") or "")
        if description == "n/a":  # pyserial's placeholder for a port without a description
            description = ""
        text = " ".join(str(s) for s in (description, manufacturer, product) if s)
        if _is_fw102c(vid, serial, text):
            role = ROLE_WHEEL
        elif vid is not None:
            role = ROLE_ADAPTER
        else:
            role = ROLE_PORT
        out.append(SerialPortInfo(
            device=str(p.device), description=description, vid=vid, pid=getattr(p, "pid", None),
            serial_number=serial, manufacturer=manufacturer, product=product,
            by_id=links.get(os.path.realpath(str(p.device))), role=role,
        ))
    # adapters first (the rig's devices hang off USB), then by name
    return sorted(out, key=lambda s: (s.vid is None, s.device))


def _usb_error_kind(exc: BaseException) -> str:
    """``denied`` for a permission problem, ``error`` otherwise."""
    if getattr(exc, "errno", None) == _errno.EACCES or getattr(exc, "backend_error_code", None) == -3:
        return "denied"  # -3 is LIBUSB_ERROR_ACCESS
    if getattr(exc, "errno", None) == _errno.EBUSY or getattr(exc, "backend_error_code", None) == -6:
        return "busy"  # -6 is LIBUSB_ERROR_BUSY
    # pyusb raises ValueError("The device has no langid (permission issue, ...)")
    # when it may open the device but the kernel refuses the string request.
    if isinstance(exc, ValueError) and "permission" in str(exc).lower():
        return "denied"
    return "error"


def _read_strings(dev: Any) -> tuple[dict[str, str | None], str, str]:
    """Open a device, read its string descriptors and try its interface 0; (strings, access, error)."""
    import usb.util

    strings: dict[str, str | None] = {"manufacturer": None, "product": None, "serial_number": None}
    try:
        # Opens the device: the access test. Called directly because pyusb's
        # get_string() turns a refused open into a ValueError without the errno.
        usb.util.get_langids(dev)
        for key, index in (("manufacturer", dev.iManufacturer), ("product", dev.iProduct),
                           ("serial_number", dev.iSerialNumber)):
            if index:
                strings[key] = usb.util.get_string(dev, index)
        # A program using the camera holds interface 0; claiming it then fails with
        # EBUSY. Claiming a free interface and releasing it at once changes nothing.
        usb.util.claim_interface(dev, 0)
        usb.util.release_interface(dev, 0)
        return strings, "ok", ""
    except Exception as e:  # noqa: BLE001 - every failure is reported, none is fatal to a scan
        num = getattr(e, "errno", None)
        return strings, _usb_error_kind(e), f"{e.__class__.__name__}{f' errno {num}' if num else ''}: {e}"
    finally:
        try:
            usb.util.dispose_resources(dev)
        except Exception:  # noqa: BLE001 - closing a handle that failed to open
            pass


def list_usb_devices(
    backend: Any = None,
    vendors: dict[int, str] | None = None,
    open_vendors: Sequence[int] = (APOGEE_VID,),
) -> list[UsbDeviceInfo]:
    """List USB devices of the known vendors through a pyusb backend.

    Devices of ``open_vendors`` (the camera) are opened to read their strings,
    which is also the test that the user may open them without root.

    Args:
        backend: a ``usb.backend.IBackend`` (None: pyusb's default, libusb).
        vendors: vendor id -> kind; default :data:`KNOWN_USB_VENDORS`.
        open_vendors: vendor ids whose devices are opened.

    Raises:
        usb.core.NoBackendError: no libusb on this machine (and no backend given).
    """
    import usb.core

    vendors = KNOWN_USB_VENDORS if vendors is None else vendors
    found = []
    for dev in usb.core.find(find_all=True, backend=backend):
        vid, pid = int(dev.idVendor), int(dev.idProduct)
        if vid not in vendors:
            continue
        kind = vendors[vid]
        if vid == APOGEE_VID:
            kind = f"Apogee {_APOGEE_PRODUCTS.get(pid, f'camera (product 0x{pid:04x})')}"
        strings: dict[str, str | None] = {}
        access, error = "not-tried", ""
        if vid in open_vendors:
            strings, access, error = _read_strings(dev)
        found.append(UsbDeviceInfo(vendor_id=vid, product_id=pid, kind=kind, bus=dev.bus, address=dev.address,
                                   access=access, error=error, **strings))
    return sorted(found, key=lambda d: (d.vendor_id != APOGEE_VID, d.bus or 0, d.address or 0))


def scan(
    list_ports: Callable[[], Iterable[Any]] | None = None,
    usb_backend: Any = None,
    by_id_dir: str | Path = SERIAL_BY_ID_DIR,
) -> ScanResult:
    """List serial ports and known USB devices; a missing libusb is reported, not raised."""
    ports = list_serial_ports(list_ports, by_id_dir)
    try:
        usb_devs = list_usb_devices(usb_backend)
        usb_error = None
    except Exception as e:  # noqa: BLE001 - NoBackendError, or a backend failing to enumerate
        from usb.core import NoBackendError

        usb_devs = []
        usb_error = ("libusb not found: sudo apt-get install libusb-1.0-0" if isinstance(e, NoBackendError)
                     else f"USB listing failed ({e.__class__.__name__}: {e})")
    return ScanResult(ports=ports, usb=usb_devs, usb_error=usb_error)


def usb_node(d: UsbDeviceInfo) -> str:
    """The device node of a USB device on Linux: /dev/bus/usb/BBB/DDD."""
    return f"/dev/bus/usb/{d.bus or 0:03d}/{d.address or 0:03d}"


def _camera_fix(d: UsbDeviceInfo) -> str:
    if d.access == "denied":
        return f"  -> no permission: install {UDEV_RULES} (see docs/udev.md), then re-plug the camera"
    if d.access == "busy":
        return f"  -> in use by another program: {usb_node(d)} (see `fuser -v {usb_node(d)}`)"
    if d.access == "error":
        return f"  -> could not open it: {d.error}"
    return ""


def format_scan(result: ScanResult) -> list[str]:
    """Human-readable lines: serial ports, then USB devices."""
    lines = [f"serial ports ({len(result.ports)}):"]
    for p in result.ports:
        usb = f"  USB {p.usb_id}" if p.vid is not None else ""
        extra = ", ".join(f"{k}={v}" for k, v in (("serial", p.serial_number), ("manufacturer", p.manufacturer))
                          if v)
        lines.append(f"  {p.device:<14} {p.role:<22} {p.description}{usb}{'  ' + extra if extra else ''}".rstrip())
        if p.by_id:
            lines.append(f"  {'':<14} stable name: {p.by_id}")
    if not result.ports:
        lines.append("  none (is the USB-serial adapter plugged in? `dmesg | tail` shows it appearing)")
    if result.usb_error:
        lines.append(f"USB devices: not listed: {result.usb_error}")
        return lines
    lines.append(f"USB devices of known vendors ({len(result.usb)}):")
    for d in result.usb:
        where = f"bus {d.bus} addr {d.address}" if d.bus is not None else ""
        extra = ", ".join(f"{k}={v}" for k, v in (("serial", d.serial_number), ("product", d.product)) if v)
        access = f"  access={d.access}" if d.access != "not-tried" else ""
        lines.append(f"  {d.usb_id}  {d.kind:<22} {where}{'  ' + extra if extra else ''}{access}".rstrip())
        fix = _camera_fix(d) if d.is_apogee else ""
        if fix:
            lines.append(fix)
    if not result.usb:
        lines.append("  none")
    return lines


def _flow(value: Any) -> str:
    """One YAML value on one line (scalars plain, lists and mappings in flow style)."""
    text = yaml.safe_dump([value], default_flow_style=True, width=10_000, sort_keys=False).strip()
    return text[1:-1]


def _section_yaml(name: str, body: dict[str, Any]) -> list[str]:
    return [f"{name}:"] + [f"  {k}: {_flow(v)}" for k, v in body.items()]


def suggest_config(result: ScanResult, base: Any = None) -> str:
    """``rig.yaml`` entries for what the scan found, as YAML text with comments.

    Ports come from the scan (stable by-id names when udev provides them); every
    other setting comes from ``base`` (a :class:`rig.config.RigConfig`; default:
    the packaged configuration, whose non-port settings mirror the real rig's).
    A device that was not found gets a comment saying so instead of a made-up port.
    """
    from rig.config import load_config

    cfg = base if base is not None else load_config()
    wheels = [p for p in result.ports if p.role == ROLE_WHEEL]
    others = [p for p in result.ports if p.role != ROLE_WHEEL]
    # The SHOT-702 has only RS-232: on a modern PC it sits behind a USB adapter;
    # a motherboard port (no USB identity) is the fallback.
    stage_candidates = [p for p in others if p.vid is not None] + [p for p in others if p.vid is None]

    s = cfg.stage
    lines = ["# Suggested by `rig devices --scan`; check each port with `rig devices --config <this file>`."]
    if stage_candidates:
        first = stage_candidates[0]
        what = (f"{first.description} (USB {first.usb_id})" if first.vid is not None
                else "a serial port without USB identity (motherboard or PCI card)")
        lines.append(f"# stage: {first.device}: {what}")
        if len(stage_candidates) > 1:
            lines.append("# other stage candidates: " + ", ".join(p.stable_path for p in stage_candidates[1:]))
        lines += _section_yaml("stage", {
            "driver": s.driver, "port": stage_candidates[0].stable_path, "model": s.model, "axis": s.axis,
            "degrees_per_pulse": s.degrees_per_pulse, "division": s.division,
            "zero_offset_deg": s.zero_offset_deg, "allowed_range_deg": list(s.allowed_range_deg),
            "speed_deg_s": s.speed_deg_s,
        })
    else:
        lines.append("# stage: no serial port found for the SHOT-702 controller; connect its RS-232 cable "
                     "(through a USB adapter) and scan again")

    c = cfg.camera
    cams = result.cameras
    cam: dict[str, Any] = {"driver": c.driver,
                           "serial_number": cams[0].serial_number if len(cams) > 1 else c.serial_number,
                           "magnification": c.magnification, "cooler_setpoint_c": c.cooler_setpoint_c}
    if c.profile_row is not None:
        cam["profile_row"] = c.profile_row
    if not cams:
        lines.append("# camera: no Apogee camera (USB vendor 0x125c) found" +
                     (f" ({result.usb_error})" if result.usb_error else "; power it and plug in its USB cable"))
    else:
        lines.append(f"# camera: {cams[0].kind} {cams[0].usb_id} on bus {cams[0].bus} address {cams[0].address}"
                     + (f"; {len(cams)} found: serial numbers " + ", ".join(str(d.serial_number) for d in cams)
                        if len(cams) > 1 else ""))
        if any(d.access == "denied" for d in cams):
            lines.append(f"# camera: not accessible without root; install {UDEV_RULES} (docs/udev.md)")
    lines += _section_yaml("camera", cam)

    f = cfg.filter
    filt: dict[str, Any]
    if wheels:
        lines.append(f"# filter: {wheels[0].description} ({wheels[0].device}, serial {wheels[0].serial_number})")
        filt = {"driver": "fw102c", "port": wheels[0].stable_path}
    else:
        lines.append("# filter: no FW102C found; the operator swaps filters when asked "
                     "(set driver: fw102c and its port once the wheel is connected)")
        filt = {"driver": "manual"}
    filt.update({"positions": dict(f.positions), "wavelengths_nm": dict(f.wavelengths_nm)})
    lines += _section_yaml("filter", filt)
    return "\n".join(lines) + "\n"
