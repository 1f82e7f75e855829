"""`rig doctor`: every check against injected fakes, one real Mitsuba probe, and the CLI.

Tests run as root, which bypasses permission bits: the permission checks are
exercised with an explicit unprivileged Identity instead.
"""

import importlib.metadata as md
import json
import os
import stat
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

from capture.errors import PlanError
from rig import doctor as d
from rig.cli import main
from rig.config import load_config, parse_config
from rig.discovery import APOGEE_VID, UsbDeviceInfo, list_usb_devices
from sim_devices.alta_usb import AltaBackend

ROOT = Path(__file__).resolve().parents[1]
OPERATOR = d.Identity(uid=1000, gids=frozenset({1000}), user="operator")
LLVM19 = next((lib.path for lib in d.find_libllvm_all() if lib.major == 19), None)
LLVM15 = next((lib.path for lib in d.find_libllvm_all() if lib.major == 15), None)


def _never(*args):
    raise AssertionError("the render probe must not run here")


# ----------------------------------------------------------------- one line, Python, packages


def test_check_line_is_one_line_and_carries_the_fix():
    bad = d.Check("x", "fail", "first\nsecond", "run this")
    assert "\n" not in bad.line() and bad.line().startswith("FAIL") and bad.line().endswith("-> fix: run this")
    assert "fix" not in d.Check("x", "ok", "fine", "run this").line()


@pytest.mark.parametrize("version, status", [((3, 10, 12), "fail"), ((3, 11, 0), "ok"), ((3, 13, 1), "ok")])
def test_python_version(version, status):
    c = d.check_python(version, ">=3.11")
    assert c.status == status
    assert ".".join(map(str, version)) in c.message


def test_packages_missing_and_wrong_versions_give_one_pip_command():
    installed = {"numpy": "1.20.0", "pyyaml": "6.0.3"}

    def version_of(name):
        if name not in installed:
            raise md.PackageNotFoundError(name)
        return installed[name]

    c = d.check_packages(["numpy>=1.26", "pyyaml>=6.0", "mitsuba==3.9.1", "pytest>=8; extra == 'test'"],
                         version_of, python="/venv/bin/python")
    assert c.status == "fail"
    assert "mitsuba missing" in c.message and "numpy 1.20.0" in c.message and "pyyaml" not in c.message
    assert "pytest" not in c.message  # extras are not runtime requirements
    assert c.fix == "/venv/bin/python -m pip install 'mitsuba==3.9.1' 'numpy>=1.26'"


def test_this_environment_satisfies_rigs_own_requirements():
    assert d.check_python().status == "ok"
    c = d.check_packages()
    assert c.status == "ok", c.line()
    assert "mitsuba 3.9.1" in c.message and "drjit 1.5.0" in c.message


# ----------------------------------------------------------------- libLLVM and Mitsuba


@pytest.mark.parametrize("name, major", [
    ("libLLVM-19.so", 19), ("libLLVM.so.19.1", 19), ("libLLVM-14.0.6.so.1", 14), ("libLLVM-15.so.1", 15),
    ("libLLVMX86CodeGen.a", None), ("libLLVM.so", None),
])
def test_llvm_major_from_names(name, major):
    assert d.llvm_major(f"/nowhere/{name}") == major


def test_find_libllvm_all_dedupes_links_and_skips_static_parts(tmp_path):
    lib = tmp_path / "x86_64-linux-gnu"
    lib.mkdir()
    (lib / "libLLVM.so.19.1").write_bytes(b"")
    (lib / "libLLVM-19.so").symlink_to("libLLVM.so.19.1")
    (lib / "libLLVM-15.so.1").write_bytes(b"")
    (lib / "libLLVMX86CodeGen.a").write_bytes(b"")
    l16 = tmp_path / "llvm-16" / "lib"
    l16.mkdir(parents=True)
    (l16 / "libLLVM.so").write_bytes(b"")  # unversioned name: the directory says 16
    libs = d.find_libllvm_all([str(lib), str(tmp_path / "llvm-*" / "lib")])
    assert [(Path(x.path).name, x.major) for x in libs] == [
        ("libLLVM.so.19.1", 19), ("libLLVM.so", 16), ("libLLVM-15.so.1", 15)]
    assert d.find_libllvm_all([str(tmp_path / "empty")]) == []


def test_llvm_versions_warns_about_15_and_16():
    good, bad = d.LibLLVM("/l/libLLVM.so.19.1", 19), d.LibLLVM("/l/libLLVM-15.so.1", 15)
    w = d.check_llvm_versions([good, bad])
    assert w.status == "warn" and "LLVM 15" in w.message and w.fix.startswith("export DRJIT_LIBLLVM_PATH=/l/libLLVM.so.19.1")
    assert d.check_llvm_versions([good]).status == "ok"


def test_mitsuba_cpu_without_a_good_llvm_says_what_to_install():
    c = d.check_mitsuba_cpu([d.LibLLVM("/l/libLLVM-15.so.1", 15)], None, _never)
    assert c.status == "fail" and c.fix == "sudo apt-get install libllvm19"
    c = d.check_mitsuba_cpu([d.LibLLVM("/l/libLLVM-20.so.1", 20)], None, _never)
    assert c.status == "fail" and c.fix == "export DRJIT_LIBLLVM_PATH=/l/libLLVM-20.so.1"


def test_mitsuba_cpu_refuses_an_aborting_llvm_without_running_it():
    libs = [d.LibLLVM("/l/libLLVM.so.19.1", 19), d.LibLLVM("/l/libLLVM-16.so.1", 16)]
    c = d.check_mitsuba_cpu(libs, "/l/libLLVM-16.so.1", _never)
    assert c.status == "fail" and "aborts" in c.message and c.fix == "export DRJIT_LIBLLVM_PATH=/l/libLLVM.so.19.1"


def test_mitsuba_cpu_reports_the_probe(tmp_path):
    lib = tmp_path / "libLLVM-19.so"
    lib.write_bytes(b"")
    libs = [d.LibLLVM(str(lib), 19)]
    seen = []

    def probe(variant, path):
        seen.append((variant, path))
        return d.ProbeResult(False, -6, "killed by SIGABRT: LLVM ERROR: Cannot select")

    c = d.check_mitsuba_cpu(libs, str(lib), probe)
    assert seen == [("llvm_ad_mono", str(lib))]
    assert c.status == "fail" and "SIGABRT" in c.message
    ok = d.check_mitsuba_cpu(libs, str(lib), lambda v, p: d.ProbeResult(True, 0, "RENDER-OK 0.2"))
    assert ok.status == "ok"
    missing = d.check_mitsuba_cpu(libs, str(tmp_path / "gone.so"), _never)
    assert missing.status == "fail" and "does not exist" in missing.message


@pytest.mark.skipif(LLVM19 is None, reason="needs libLLVM 19 installed")
def test_render_probe_renders_with_llvm19():
    good = d.render_probe("llvm_ad_mono", LLVM19)
    assert good.ok and good.detail.startswith("RENDER-OK"), good
    assert float(good.detail.split()[1]) > 0  # the constant emitter lights the film


@pytest.mark.skipif(LLVM15 is None, reason="needs libLLVM 15 installed")
def test_render_probe_in_a_child_process_survives_the_llvm15_abort():
    bad = d.render_probe("llvm_ad_mono", LLVM15)
    assert not bad.ok and bad.returncode == -6
    assert "SIGABRT" in bad.detail and "LLVM ERROR" in bad.detail


def test_cuda_check():
    assert d.detect_gpu(which=lambda n: None, find_library=lambda n: None) is None
    gpu = d.detect_gpu(which=lambda n: "/usr/bin/nvidia-smi", find_library=lambda n: None)
    assert "nvidia-smi" in gpu
    c = d.check_cuda(None, _never)
    assert c.status == "ok" and "CPU only" in c.message
    seen = []

    def broken(variant, lib):
        seen.append((variant, lib))
        return d.ProbeResult(False, 1, "cuda_init failed")

    # rig would pick the GPU (nvidia-smi answers), so a GPU that cannot render blocks estimation
    failed = d.check_cuda(gpu, broken, libllvm="/l/libLLVM.so.19.1")
    assert seen == [("cuda_ad_mono", "/l/libLLVM.so.19.1")]
    assert failed.status == "fail" and "cuda_init failed" in failed.message
    assert "RIG_MITSUBA_VARIANT=llvm_ad_mono" in failed.fix
    assert d.check_cuda(gpu, broken, forced_variant="llvm_ad_mono").status == "warn"
    assert d.check_cuda(gpu, lambda v, p: d.ProbeResult(True, 0, "RENDER-OK 1.0")).status == "ok"
    assert d.check_cuda(None, _never, forced_variant="cuda_ad_mono").status == "fail"


# ----------------------------------------------------------------- USB


def test_libusb_check():
    missing = d.check_libusb(lambda: None)
    assert missing.status == "fail" and missing.fix == "sudo apt-get install libusb-1.0-0"
    assert d.check_libusb(lambda: object()).status == "ok"


def test_camera_found_and_accessible_on_the_simulated_backend():
    devs = list_usb_devices(AltaBackend(serial_number="A0042"))
    c = d.check_camera(devs, required=True)
    assert c.status == "ok" and "125c:0010" in c.message and "A0042" in c.message
    assert d.check_camera(devs, required=True, serial_number="A0042").status == "ok"
    wrong = d.check_camera(devs, required=True, serial_number="A9999")
    assert wrong.status == "fail" and "A0042" in wrong.message and "serial_number" in wrong.fix


def test_camera_without_udev_permission_names_the_rules_file():
    backend = AltaBackend()
    backend.access_denied = True
    c = d.check_camera(list_usb_devices(backend), required=True)
    assert c.status == "fail" and "errno 13" in c.message
    assert "udev/99-apogee-alta.rules" in c.fix and "udevadm trigger" in c.fix
    assert (ROOT / "udev" / "99-apogee-alta.rules").read_text().count('ATTR{idVendor}=="125c"') == 1


def test_camera_absent_or_not_needed():
    assert d.check_camera([], required=True).status == "fail"
    assert d.check_camera(None, required=True, usb_error="no libusb").status == "fail"
    assert d.check_camera(None, required=False).status == "ok"
    other = UsbDeviceInfo(vendor_id=0x0403, product_id=0x6001, kind="FTDI")
    assert d.check_camera([other], required=True).status == "fail"
    broken = UsbDeviceInfo(vendor_id=APOGEE_VID, product_id=0x10, kind="Apogee Alta-U", access="error",
                           error="USBError errno 5: Input/Output Error")
    assert "Input/Output Error" in d.check_camera([broken], required=True).message


def test_camera_busy_in_another_program_names_its_node():
    import usb.core
    import usb.util

    backend = AltaBackend()
    other = usb.core.find(idVendor=APOGEE_VID, backend=backend)
    usb.util.claim_interface(other, 0)
    try:
        c = d.check_camera(list_usb_devices(backend), required=True)
    finally:
        usb.util.dispose_resources(other)
    assert c.status == "fail" and "in use by another program" in c.message
    assert c.fix.startswith("stop the program holding it (`fuser -v /dev/bus/usb/001/004`")


# ----------------------------------------------------------------- serial ports


def test_mode_bits():
    st = SimpleNamespace(st_uid=0, st_gid=20, st_mode=stat.S_IFCHR | 0o660)
    rw = os.R_OK | os.W_OK
    assert not d.mode_allows(st, rw, OPERATOR)
    assert d.mode_allows(st, rw, d.Identity(1000, frozenset({1000, 20}), "operator"))
    assert d.mode_allows(st, rw, d.Identity(0, frozenset({0}), "root"))
    # the owner class decides for the owner, even when the group would allow
    owner = SimpleNamespace(st_uid=1000, st_gid=1000, st_mode=stat.S_IFCHR | 0o060)
    assert not d.mode_allows(owner, rw, OPERATOR)
    assert d.mode_allows(SimpleNamespace(st_uid=5, st_gid=5, st_mode=0o606), rw, OPERATOR)


def test_serial_port_not_in_group_suggests_usermod(tmp_path):
    port = tmp_path / "ttyUSB0"
    port.write_bytes(b"")
    os.chown(port, 0, 20)  # group dialout on Debian
    port.chmod(0o660)
    c = d.check_serial_port("stage", str(port), OPERATOR)
    assert c.status == "fail" and c.name == "serial-stage"
    assert "operator" in c.message and "crw" not in c.message
    group = d._group_name(20)
    assert c.fix == f"sudo usermod -aG {group} $USER, then log out and back in"
    member = d.Identity(1000, frozenset({1000, 20}), "operator")
    # allowed, but a regular file is not a serial port
    assert d.check_serial_port("stage", str(port), member).status == "warn"


def test_serial_port_without_group_access_suggests_chmod(tmp_path):
    port = tmp_path / "ttyUSB0"
    port.write_bytes(b"")
    port.chmod(0o600)
    c = d.check_serial_port("filter", str(port), OPERATOR)
    assert c.status == "fail" and c.fix.startswith("sudo chmod g+rw")


def test_serial_port_character_device_ok(tmp_path):
    node = tmp_path / "ttyFAKE"
    try:
        os.mknod(node, stat.S_IFCHR | 0o660, os.makedev(1, 3))
    except PermissionError:
        pytest.skip("mknod not permitted here")
    node.chmod(0o660)  # mknod's mode went through the umask
    link = tmp_path / "by-id-link"
    link.symlink_to(node)
    c = d.check_serial_port("stage", str(link), d.Identity(1000, frozenset({0}), "operator"))
    assert c.status == "ok" and str(node) in c.message


def test_one_port_cannot_serve_stage_and_wheel(tmp_path):
    port = tmp_path / "ttyUSB0"
    port.write_bytes(b"")
    link = tmp_path / "usb-FTDI-if00-port0"
    link.symlink_to(port)
    c = d.check_serial_port("filter", str(link), taken={"stage": str(port)})
    assert c.status == "fail" and "also the stage's port" in c.message
    assert d.check_serial_port("filter", str(link), taken={"stage": "sim-shot702://x"}).status != "fail"


def test_serial_port_missing_sim_and_manual(tmp_path):
    gone = d.check_serial_port("stage", str(tmp_path / "ttyUSB9"))
    assert gone.status == "fail" and "rig devices --scan" in gone.fix
    assert d.check_serial_port("stage", "sim-shot702://default").status == "ok"
    assert d.check_serial_port("filter", None).status == "ok"


# ----------------------------------------------------------------- disk space


def test_session_size_from_the_plan():
    tiny = d.SessionSizePlan(angles=1, filters=1, exposures=1, darks_per_exposure=0, width=2, height=2)
    # 2 stacks (one angle + calibration) x (1 raw frame of 4 uint16 + 3 float32 channels of 4 pixels)
    assert tiny.total_bytes() == 2 * (1 * 4 * 2 + 3 * 4 * 4)
    assert d.session_bytes(tiny) == (tiny.total_bytes(), "plan estimate")
    default = d.SessionSizePlan()
    assert default.stacks() == 33
    assert default.bytes_per_stack() == 6 * 3 * 512 * 512 * 2 + 3 * 512 * 512 * 4


def test_session_size_from_the_capture_plan_grows_with_the_plan():
    cfg = load_config()
    small, src = d.session_bytes(d.SessionSizePlan(angles=4), cfg)
    big, _ = d.session_bytes(d.SessionSizePlan(angles=8), cfg)
    assert src == "capture plan" and big > small
    assert small >= d.SessionSizePlan(angles=4).total_bytes()  # an upper bound, with slack
    with pytest.raises(PlanError):
        d.session_bytes(d.SessionSizePlan(filters=1), cfg, filter_names=("x",))


def test_disk_space_levels(tmp_path):
    plan = d.SessionSizePlan()
    need = plan.total_bytes()

    def free(n):
        return lambda path: SimpleNamespace(free=n)

    assert d.check_disk_space(tmp_path, plan, disk_usage=free(need // 2)).status == "fail"
    assert d.check_disk_space(tmp_path, plan, disk_usage=free(need + need // 2)).status == "warn"
    ok = d.check_disk_space(tmp_path / "new" / "session", plan, disk_usage=free(10 * need))
    assert ok.status == "ok" and str(tmp_path) in ok.message  # the nearest existing parent
    low = d.check_disk_space(tmp_path, plan, disk_usage=free(need // 2))
    assert "--out" in low.fix


def test_disk_space_unwritable_dir(tmp_path):
    out = tmp_path / "ro"
    out.mkdir()
    out.chmod(0o555)
    c = d.check_disk_space(out / "sessions", who=OPERATOR, disk_usage=lambda p: SimpleNamespace(free=1 << 40))
    assert c.status == "fail" and "not writable by operator" in c.message and "--out" in c.fix
    blocked = tmp_path / "file"
    blocked.write_text("")
    assert d.check_disk_space(blocked / "x").status == "fail"


# ----------------------------------------------------------------- the command


def test_run_checks_on_a_real_config_with_fakes_only(tmp_path):
    cfg_data = yaml.safe_load((ROOT / "configs" / "rig-real.yaml").read_text())
    stage, wheel = tmp_path / "ttyUSB0", tmp_path / "ttyUSB1"
    for port in (stage, wheel):
        port.write_bytes(b"")
        os.chown(port, 0, 20)
        port.chmod(0o660)
    cfg_data["stage"]["port"], cfg_data["filter"]["port"] = str(stage), str(wheel)
    cfg = parse_config(cfg_data, "rig.yaml")
    probed = []
    checks = d.run_checks(cfg, tmp_path, d.SessionSizePlan(), usb_backend=AltaBackend(), llvm_globs=[],
                          probe=lambda v, lib: probed.append(v) or d.ProbeResult(True, 0, "RENDER-OK 1"),
                          gpu=None, who=OPERATOR)
    by = {c.name: c for c in checks}
    assert by["camera"].status == "ok"  # the simulated camera on the given backend
    assert by["serial-stage"].status == "fail" and "usermod" in by["serial-stage"].fix
    assert by["serial-filter"].status == "fail"
    assert by["llvm-versions"].message.endswith("none")
    # rendered (by the fake probe) exactly when rig's loader found a libLLVM to render with
    assert probed in ([], ["llvm_ad_mono"]) and (by["mitsuba-cpu"].status == "ok") == bool(probed)
    # tmp_path belongs to root (mode 700): the operator could not write a session there
    assert [c.name for c in checks][-1] == "disk-space" and by["disk-space"].status == "fail"
    assert "not writable by operator" in by["disk-space"].message


def test_cli_json_shape_on_the_simulated_rig(tmp_path, capsys):
    rc = main(["doctor", "--json", "--out", str(tmp_path), "--angles", "4", "--filters", "rg"])
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"config", "out", "plan", "ok", "blocking", "checks"}
    assert out["plan"]["angles"] == 4 and out["plan"]["filter_names"] == ["r", "g"]
    names = [c["name"] for c in out["checks"]]
    assert names == ["python", "packages", "llvm-versions", "mitsuba-cpu", "mitsuba-cuda", "libusb", "camera",
                     "serial-stage", "serial-filter", "disk-space"]
    for c in out["checks"]:
        assert set(c) == {"name", "status", "message", "fix"} and c["status"] in ("ok", "warn", "fail")
    assert out["blocking"] == [c["name"] for c in out["checks"] if c["status"] == "fail"]
    assert rc == (1 if out["blocking"] else 0) and out["ok"] is (rc == 0)


def test_cli_real_rig_without_devices_exits_1_one_line_per_check(tmp_path, capsys):
    cfg = yaml.safe_load((ROOT / "configs" / "rig-real.yaml").read_text())
    cfg["stage"]["port"] = str(tmp_path / "ttyUSB0")  # not plugged in
    cfg["filter"]["port"] = str(tmp_path / "ttyUSB1")
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(cfg))
    assert main(["doctor", "--config", str(path), "--out", str(tmp_path)]) == 1
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 11  # ten checks and the verdict
    stage = next(ln for ln in lines if "serial-stage" in ln)
    assert stage.startswith("FAIL") and "-> fix:" in stage
    assert lines[-1].startswith("doctor:") and "serial-stage" in lines[-1]


def test_cli_bad_filter_is_a_usage_error(capsys):
    assert main(["doctor", "--filters", "rx"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--filters 'rx': unknown filter 'x'; choose from r, g, b" in err
    assert main(["doctor", "--filters", "r,g,r"]) == 2
    assert "filter 'r' is named twice" in capsys.readouterr().err
