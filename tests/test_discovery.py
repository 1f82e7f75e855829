"""Device discovery: port listing, USB listing through a pyusb backend, suggested rig.yaml.

Ports are real pyserial ListPortInfo objects filled as the adapters would fill them;
USB runs on the simulated Alta camera's backend plus a few descriptor-only devices.
"""

import json
import os
from dataclasses import dataclass

import pytest
import usb.backend
import usb.core
import usb.util
import yaml
from serial.tools.list_ports_common import ListPortInfo

from rig import discovery
from rig.cli import main
from rig.config import load_config, parse_config
from sim_devices.alta_usb import AltaBackend


def _port(device, *, vid=None, pid=None, serial=None, manufacturer=None, product=None, description="n/a"):
    p = ListPortInfo(device, skip_link_detection=True)
    p.vid, p.pid, p.serial_number, p.manufacturer, p.product = vid, pid, serial, manufacturer, product
    p.description = description
    return p


WHEEL = _port("/dev/ttyUSB1", vid=0x0403, pid=0x6001, serial="TP03014244", manufacturer="FTDI",
              product="FT232R USB UART", description="FT232R USB UART")
ADAPTER = _port("/dev/ttyUSB0", vid=0x067B, pid=0x2303, manufacturer="Prolific Technology Inc.",
                product="USB-Serial Controller", description="USB-Serial Controller")
BUILTIN = _port("/dev/ttyS0")


@dataclass
class _Desc:
    """Device descriptor of a USB device that is only enumerated, never opened."""

    idVendor: int
    idProduct: int
    bus: int
    address: int
    bLength: int = 18
    bDescriptorType: int = 1
    bcdUSB: int = 0x0200
    bDeviceClass: int = 0
    bDeviceSubClass: int = 0
    bDeviceProtocol: int = 0
    bMaxPacketSize0: int = 8
    bcdDevice: int = 0x0600
    iManufacturer: int = 1
    iProduct: int = 2
    iSerialNumber: int = 3
    bNumConfigurations: int = 1
    port_number: int = 1
    port_numbers: tuple = (1,)
    speed: int = 2


class _Bus(usb.backend.IBackend):
    """A USB bus: the simulated Alta camera(s) plus descriptor-only devices of other vendors."""

    def __init__(self, cameras, others):
        self.cameras, self.others = cameras, others

    def _owner(self, dev):
        return next(b for b in self.cameras if dev in b.enumerate_devices())

    def enumerate_devices(self):
        return [d for b in self.cameras for d in b.enumerate_devices()] + list(self.others)

    def get_device_descriptor(self, dev):
        return dev if isinstance(dev, _Desc) else self._owner(dev).get_device_descriptor(dev)

    def open_device(self, dev):
        if isinstance(dev, _Desc):
            raise AssertionError("a serial adapter must not be opened over libusb")
        return self._owner(dev).open_device(dev)

    # string descriptors and closing go to the camera backend the handle came from
    def ctrl_transfer(self, handle, *args):
        return self._owner(handle.dev).ctrl_transfer(handle, *args)

    def close_device(self, handle):
        return self._owner(handle.dev).close_device(handle)

    def claim_interface(self, handle, intf):
        return self._owner(handle.dev).claim_interface(handle, intf)

    def release_interface(self, handle, intf):
        return self._owner(handle.dev).release_interface(handle, intf)


OTHERS = [_Desc(0x0403, 0x6001, bus=1, address=7), _Desc(0x046D, 0xC52B, bus=1, address=2)]


def test_ports_are_classified_and_sorted():
    ports = discovery.list_serial_ports(lambda: [BUILTIN, WHEEL, ADAPTER], by_id_dir="/nonexistent")
    assert [p.device for p in ports] == ["/dev/ttyUSB0", "/dev/ttyUSB1", "/dev/ttyS0"]
    by = {p.device: p for p in ports}
    assert by["/dev/ttyUSB1"].role == discovery.ROLE_WHEEL
    assert by["/dev/ttyUSB0"].role == discovery.ROLE_ADAPTER
    assert by["/dev/ttyS0"].role == discovery.ROLE_PORT
    assert by["/dev/ttyUSB0"].usb_id == "067b:2303"
    assert by["/dev/ttyS0"].usb_id == "" and by["/dev/ttyS0"].description == ""
    assert by["/dev/ttyUSB1"].serial_number == "TP03014244"


@pytest.mark.parametrize("serial, product, wheel", [
    ("TP01234567", "FT232R USB UART", True),
    ("A9XK2LQ", "FW102C Filter Wheel", True),
    ("A9XK2LQ", "FT232R USB UART", False),
])
def test_fw102c_heuristic(serial, product, wheel):
    p = _port("/dev/ttyUSB3", vid=0x0403, pid=0x6001, serial=serial, product=product, description=product)
    (info,) = discovery.list_serial_ports(lambda: [p], by_id_dir="/nonexistent")
    assert (info.role == discovery.ROLE_WHEEL) is wheel
    # a wheel must be an FTDI device: the same strings on a Prolific adapter are not a wheel
    q = _port("/dev/ttyUSB4", vid=0x067B, pid=0x2303, serial=serial, product=product, description=product)
    (other,) = discovery.list_serial_ports(lambda: [q], by_id_dir="/nonexistent")
    assert other.role == discovery.ROLE_ADAPTER


def test_stable_by_id_names(tmp_path):
    dev = tmp_path / "ttyUSB0"
    dev.touch()
    by_id = tmp_path / "by-id"
    by_id.mkdir()
    link = by_id / "usb-Prolific_Technology_Inc._USB-Serial_Controller-if00-port0"
    link.symlink_to(os.path.relpath(dev, by_id))
    p = _port(str(dev), vid=0x067B, pid=0x2303)
    (info,) = discovery.list_serial_ports(lambda: [p], by_id_dir=by_id)
    assert info.by_id == str(link) and info.stable_path == str(link)
    (plain,) = discovery.list_serial_ports(lambda: [BUILTIN], by_id_dir=by_id)
    assert plain.by_id is None and plain.stable_path == "/dev/ttyS0"


def test_usb_listing_opens_only_the_camera():
    bus = _Bus([AltaBackend(serial_number="A0042")], OTHERS)
    devs = discovery.list_usb_devices(bus)
    assert [d.usb_id for d in devs] == ["125c:0010", "0403:6001"]  # the mouse (046d) is not listed
    cam, ftdi = devs
    assert cam.kind == "Apogee Alta-U" and cam.access == "ok"
    assert (cam.serial_number, cam.manufacturer, cam.product) == ("A0042", "Apogee", "Alta-U")
    assert ftdi.access == "not-tried" and ftdi.serial_number is None


def test_usb_access_denied_is_reported_with_the_udev_fix():
    cam = AltaBackend()
    cam.access_denied = True
    result = discovery.scan(list, usb_backend=_Bus([cam], []), by_id_dir="/nonexistent")
    (d,) = result.cameras
    assert d.access == "denied" and "Access denied" in d.error
    text = "\n".join(discovery.format_scan(result))
    assert "access=denied" in text and discovery.UDEV_RULES in text


def test_camera_held_by_another_program_is_busy():
    backend = AltaBackend()
    other = usb.core.find(idVendor=discovery.APOGEE_VID, backend=backend)  # "another program"
    usb.util.claim_interface(other, 0)
    try:
        (cam,) = discovery.list_usb_devices(backend)
        assert cam.access == "busy" and "errno 16" in cam.error
        assert "fuser -v /dev/bus/usb/001/004" in "\n".join(discovery.format_scan(discovery.ScanResult(usb=[cam])))
    finally:
        usb.util.dispose_resources(other)
    (cam,) = discovery.list_usb_devices(backend)
    assert cam.access == "ok"  # the scan itself released what it claimed


def test_usb_listing_failure_is_reported_not_raised():
    class Broken(usb.backend.IBackend):
        def enumerate_devices(self):
            raise usb.core.USBError("bus gone", -4, 19)

    result = discovery.scan(lambda: [ADAPTER], usb_backend=Broken(), by_id_dir="/nonexistent")
    assert result.usb == [] and "USB listing failed" in result.usb_error
    assert len(result.ports) == 1
    assert "not listed" in "\n".join(discovery.format_scan(result))


def test_suggested_config_parses_and_uses_the_found_ports():
    result = discovery.scan(lambda: [BUILTIN, WHEEL, ADAPTER], usb_backend=_Bus([AltaBackend()], OTHERS),
                            by_id_dir="/nonexistent")
    base = load_config()
    text = discovery.suggest_config(result, base)
    cfg = parse_config(yaml.safe_load(text), "suggested.yaml")
    assert cfg.stage.port == "/dev/ttyUSB0"  # the USB adapter, not the motherboard port
    assert cfg.filter.driver == "fw102c" and cfg.filter.port == "/dev/ttyUSB1"
    assert cfg.camera.serial_number is None  # one camera: no need to pick
    assert "/dev/ttyS0" in text  # listed as another stage candidate
    # every non-port setting is the base configuration's
    assert cfg.stage.allowed_range_deg == base.stage.allowed_range_deg
    assert cfg.stage.zero_offset_deg == base.stage.zero_offset_deg
    assert cfg.filter.wavelengths_nm == base.filter.wavelengths_nm
    assert cfg.camera.magnification == base.camera.magnification


def test_suggestion_without_devices_says_so_instead_of_inventing_ports():
    result = discovery.ScanResult(ports=[], usb=[], usb_error="libusb not found: sudo apt-get install libusb-1.0-0")
    text = discovery.suggest_config(result, load_config())
    data = yaml.safe_load(text)
    assert "stage" not in data and data["filter"]["driver"] == "manual" and "port" not in data["filter"]
    assert "no serial port found" in text and "libusb not found" in text


def test_two_cameras_pick_one_serial_number():
    bus = _Bus([AltaBackend(serial_number="A1"), AltaBackend(serial_number="A2")], [])
    result = discovery.scan(lambda: [ADAPTER], usb_backend=bus, by_id_dir="/nonexistent")
    assert sorted(d.serial_number for d in result.cameras) == ["A1", "A2"]
    data = yaml.safe_load(discovery.suggest_config(result, load_config()))
    assert data["camera"]["serial_number"] in ("A1", "A2")


def test_cli_scan_json_runs_on_this_machine(capsys):
    assert main(["devices", "--scan", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"scan", "suggested_config"}
    assert set(out["scan"]) == {"ports", "usb", "usb_error"}
    yaml.safe_load(out["suggested_config"])  # valid YAML whatever this machine has


def test_cli_scan_text(capsys):
    assert main(["devices", "--scan"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("serial ports (") and "suggested rig.yaml entries:" in out
