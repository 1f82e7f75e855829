"""``rig doctor``: checks of the machine, each one line with the exact fix.

Every check is a function returning a :class:`Check`. What a check reads from the
machine (file system, process identity, device lists, a subprocess runner) is a
parameter with the real thing as default, so each check runs against fakes.
A ``fail`` blocks a run; a ``warn`` is worth fixing but does not.
"""

from __future__ import annotations

import ctypes.util
import glob
import grp
import importlib.metadata as md
import os
import pwd
import re
import shutil
import signal
import stat
import subprocess
import sys
import textwrap
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

from rig.discovery import APOGEE_VID, UDEV_RULES, UsbDeviceInfo, usb_node

Status = Literal["ok", "warn", "fail"]

#: Where Dr.Jit looks for libLLVM (its own list), plus the usual other places.
LLVM_SEARCH_GLOBS: tuple[str, ...] = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib/wsl/lib",
    "/usr/lib/llvm-*/lib",
    "/usr/lib64",
    "/usr/local/lib",
)
#: LLVM majors that load but abort the process at the first render ("LLVM ERROR:
#: Cannot select ... fminimum"): a hard abort, not an exception.
ABORTING_LLVM = (15, 16)
#: Oldest LLVM known to work with drjit 1.5 (14 is refused as too old).
MIN_LLVM = 19

UDEV_FIX = (f"sudo cp {UDEV_RULES} /etc/udev/rules.d/ && sudo udevadm control --reload-rules "
            "&& sudo udevadm trigger, then re-plug the camera (docs/udev.md)")


@dataclass(frozen=True)
class Check:
    """Outcome of one check: ``fix`` says exactly what to run (empty when ok)."""

    name: str
    status: Status
    message: str
    fix: str = ""

    def line(self) -> str:
        """One line: status, name, message and, unless ok, the fix."""
        text = f"{self.status.upper():<4}  {self.name:<14} {self.message}"
        if self.fix and self.status != "ok":
            text += f"  -> fix: {self.fix}"
        return " ".join(text.split("\n"))

    def to_dict(self) -> dict[str, str]:
        return asdict(self)


# --------------------------------------------------------------------------- Python


def _rig_requirements() -> tuple[str | None, list[str]]:
    """(Requires-Python, runtime requirements) of the installed ``rig``, or of pyproject.toml."""
    try:
        meta = md.metadata("rig")
        reqs = md.requires("rig") or []
        python = meta["Requires-Python"] if "Requires-Python" in meta else None
        return python, [r for r in reqs if "extra ==" not in r]
    except md.PackageNotFoundError:
        import tomllib

        project = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]
        return project.get("requires-python"), list(project.get("dependencies", []))


def _no_packaging(name: str) -> Check | None:
    """A fail check when the ``packaging`` library (version rules) is missing."""
    try:
        import packaging.requirements  # noqa: F401
    except ImportError:
        return Check(name, "fail", "the 'packaging' library is missing, versions cannot be compared",
                     f"{sys.executable} -m pip install packaging")
    return None


def check_python(version: Sequence[int] | None = None, requires: str | None = None) -> Check:
    """The interpreter satisfies ``requires-python`` (default: from rig's metadata)."""
    if (broken := _no_packaging("python")) is not None:
        return broken
    from packaging.specifiers import SpecifierSet

    v = ".".join(str(x) for x in (version or sys.version_info)[:3])
    spec = requires if requires is not None else (_rig_requirements()[0] or "")
    if SpecifierSet(spec).contains(v, prereleases=True):
        return Check("python", "ok", f"Python {v} ({sys.executable}) satisfies '{spec}'")
    return Check("python", "fail", f"Python {v} does not satisfy '{spec}'",
                 f"install Python {spec} (Debian 12: apt-get install python3 python3-venv) and run `make setup`")


def check_packages(
    requirements: Iterable[str] | None = None,
    version_of: Callable[[str], str] = md.version,
    python: str = sys.executable,
) -> Check:
    """Every runtime requirement is installed at an allowed version.

    Args:
        requirements: PEP 508 strings (default: rig's own, from its metadata).
        version_of: installed version of a distribution; raises PackageNotFoundError.
        python: the interpreter named in the fix.
    """
    if (broken := _no_packaging("packages")) is not None:
        return broken
    from packaging.requirements import Requirement

    reqs = [Requirement(r) for r in (requirements if requirements is not None else _rig_requirements()[1])]
    reqs = [r for r in reqs if r.marker is None or r.marker.evaluate({"extra": ""})]
    missing: list[Requirement] = []
    wrong: list[tuple[Requirement, str]] = []
    good: list[tuple[Requirement, str]] = []
    for r in reqs:
        try:
            v = version_of(r.name)
        except md.PackageNotFoundError:
            missing.append(r)
            continue
        (good if r.specifier.contains(v, prereleases=True) else wrong).append((r, v))
    if not missing and not wrong:
        return Check("packages", "ok", f"{len(good)} requirements satisfied: "
                     + ", ".join(f"{r.name} {v}" for r, v in good))
    problems = [f"{r.name} missing (needs '{r.specifier or 'any'}')" for r in missing]
    problems += [f"{r.name} {v} (needs '{r.specifier}')" for r, v in wrong]
    to_install = " ".join(f"'{r}'" for r in missing + [r for r, _ in wrong])
    return Check("packages", "fail", "; ".join(problems), f"{python} -m pip install {to_install}")


# --------------------------------------------------------------------------- Mitsuba


@dataclass(frozen=True)
class LibLLVM:
    """A libLLVM shared library found on disk (``path`` is the resolved file)."""

    path: str
    major: int | None


def llvm_major(path: str) -> int | None:
    """Major LLVM version from a library's name: libLLVM-19.so, libLLVM.so.19.1, libLLVM-14.0.6.so.1."""
    for name in (os.path.basename(path), os.path.basename(os.path.realpath(path))):
        m = re.fullmatch(r"libLLVM-(\d+)(?:\.\d+)*\.so(?:\.\d+)*", name) or \
            re.fullmatch(r"libLLVM\.so\.(\d+)(?:\.\d+)*", name)
        if m:
            return int(m.group(1))
    m = re.search(r"/llvm-(\d+)/", path)
    return int(m.group(1)) if m else None


def find_libllvm_all(search_globs: Iterable[str] = LLVM_SEARCH_GLOBS) -> list[LibLLVM]:
    """Every libLLVM shared library in the search directories (glob patterns), one per file."""
    seen: dict[str, LibLLVM] = {}
    for pattern in search_globs:
        for d in sorted(glob.glob(pattern)):
            for p in sorted(glob.glob(os.path.join(d, "libLLVM*.so*"))):
                name = os.path.basename(p)
                if not (name.startswith("libLLVM-") or name.startswith("libLLVM.so")) or not os.path.isfile(p):
                    continue
                real = os.path.realpath(p)
                major = llvm_major(p)
                if real not in seen or seen[real].major is None:
                    seen[real] = LibLLVM(real, major)
    return sorted(seen.values(), key=lambda lib: (-(lib.major or 0), lib.path))


def rig_libllvm(env: Mapping[str, str] = os.environ) -> str | None:
    """The libLLVM that rig's own Mitsuba set-up will use: ``DRJIT_LIBLLVM_PATH`` if set,
    else what :func:`estimate.mitsuba_env.find_libllvm` picks."""
    if env.get("DRJIT_LIBLLVM_PATH"):
        return env["DRJIT_LIBLLVM_PATH"]
    try:
        from estimate.mitsuba_env import find_libllvm
    except ImportError:  # estimation not installed: the newest good one on disk
        good = [lib for lib in find_libllvm_all() if (lib.major or 0) >= MIN_LLVM]
        return good[0].path if good else None
    return find_libllvm()


def check_llvm_versions(libs: Sequence[LibLLVM]) -> Check:
    """Warn when an LLVM that aborts Mitsuba (15/16) is installed next to a good one."""
    found = ", ".join(f"{lib.major or '?'} ({lib.path})" for lib in libs) or "none"
    bad = [lib for lib in libs if lib.major in ABORTING_LLVM]
    if bad:
        good = [lib for lib in libs if (lib.major or 0) >= MIN_LLVM]
        pin = f"export DRJIT_LIBLLVM_PATH={good[0].path}" if good else "sudo apt-get install libllvm19"
        return Check("llvm-versions", "warn",
                     f"LLVM {'/'.join(str(lib.major) for lib in bad)} installed; it aborts the process at "
                     f"the first render if Dr.Jit picks it (found: {found})",
                     f"{pin} in scripts that import mitsuba directly (rig pins it itself)")
    return Check("llvm-versions", "ok", f"libLLVM found: {found}")


_RENDER_PROBE = textwrap.dedent("""\
    import sys
    import mitsuba as mi
    mi.set_variant(sys.argv[1])
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "path"},
        "sensor": {"type": "orthographic", "film": {"type": "hdrfilm", "width": 4, "height": 4,
                   "rfilter": {"type": "box"}}},
        "emitter": {"type": "constant"}, "shape": {"type": "sphere"}})
    import numpy as np
    value = float(np.asarray(mi.render(scene, spp=4)).mean())
    print(f"RENDER-OK {value!r}", flush=True)
""")


_ANSI = re.compile(r"\x1b\[[0-9;]*m")


@dataclass(frozen=True)
class ProbeResult:
    """Outcome of a render in a child process: ``detail`` is the most telling output line."""

    ok: bool
    returncode: int | None
    detail: str


def render_probe(variant: str, libllvm: str | None = None, *, python: str = sys.executable,
                 timeout_s: float = 120.0) -> ProbeResult:
    """Import Mitsuba, set ``variant`` and render a 4x4 scene in a child process.

    A child process because LLVM 15/16 abort the whole process at the first render.
    """
    env = dict(os.environ)
    if libllvm is not None:
        env["DRJIT_LIBLLVM_PATH"] = libllvm
    try:
        cp = subprocess.run([python, "-c", _RENDER_PROBE, variant], capture_output=True, text=True,
                            timeout=timeout_s, env=env)
    except subprocess.TimeoutExpired:
        return ProbeResult(False, None, f"no result within {timeout_s:g} s")
    out = _ANSI.sub("", (cp.stdout or "") + (cp.stderr or ""))  # Mitsuba colours its log lines
    lines = [ln.strip() for ln in out.splitlines() if ln.strip()]
    done = [ln[ln.index("RENDER-OK"):] for ln in lines if "RENDER-OK" in ln]
    if cp.returncode == 0 and done:
        return ProbeResult(True, 0, done[-1])
    llvm_errors = [ln for ln in lines if "LLVM ERROR" in ln]
    errors = [ln for ln in lines if "Error" in ln or "error" in ln]
    # LLVM prints its reason once, then a long dump; a Python failure ends with its exception.
    detail = llvm_errors[0] if llvm_errors else (errors or lines or ["no output"])[-1]
    if cp.returncode < 0:
        try:
            sig = signal.Signals(-cp.returncode).name
        except ValueError:
            sig = f"signal {-cp.returncode}"
        detail = f"killed by {sig}: {detail}"
    return ProbeResult(False, cp.returncode, detail[:300])


def check_mitsuba_cpu(
    libs: Sequence[LibLLVM],
    selected: str | None,
    probe: Callable[[str, str | None], ProbeResult] = render_probe,
) -> Check:
    """Mitsuba's CPU backend: a libLLVM >= 19 is found, chosen, and renders (in a child process).

    Args:
        libs: the libLLVM files on this machine (:func:`find_libllvm_all`).
        selected: the one rig will load (:func:`rig_libllvm`), or None.
        probe: renders with a variant and a libLLVM path.
    """
    good = [lib for lib in libs if (lib.major or 0) >= MIN_LLVM]
    if selected is None:
        if good:
            return Check("mitsuba-cpu", "fail",
                         f"rig's loader found no libLLVM 19, but LLVM {good[0].major} is at {good[0].path}",
                         f"export DRJIT_LIBLLVM_PATH={good[0].path}")
        return Check("mitsuba-cpu", "fail", f"no libLLVM >= {MIN_LLVM} found (Mitsuba's llvm_* variants need one)",
                     "sudo apt-get install libllvm19")
    major = llvm_major(selected)
    if major in ABORTING_LLVM or (major is not None and major < MIN_LLVM):
        why = "aborts the process at the first render" if major in ABORTING_LLVM else "is too old for drjit"
        target = f"export DRJIT_LIBLLVM_PATH={good[0].path}" if good else "sudo apt-get install libllvm19"
        return Check("mitsuba-cpu", "fail", f"DRJIT_LIBLLVM_PATH={selected} is LLVM {major}, which {why}", target)
    if not os.path.exists(selected):
        return Check("mitsuba-cpu", "fail", f"libLLVM {selected} does not exist",
                     "unset DRJIT_LIBLLVM_PATH or point it at libLLVM 19; sudo apt-get install libllvm19")
    res = probe("llvm_ad_mono", selected)
    if res.ok:
        return Check("mitsuba-cpu", "ok", f"llvm_ad_mono renders with {selected} (LLVM {major})")
    return Check("mitsuba-cpu", "fail", f"llvm_ad_mono with {selected} failed: {res.detail}",
                 "sudo apt-get install --reinstall libllvm19, then "
                 f"{sys.executable} -m pip install --force-reinstall 'mitsuba==3.9.1' 'drjit==1.5.0'")


def detect_gpu(which: Callable[[str], str | None] = shutil.which,
               find_library: Callable[[str], str | None] = ctypes.util.find_library) -> str | None:
    """How an NVIDIA GPU shows itself (nvidia-smi or libcuda), or None."""
    smi, cuda = which("nvidia-smi"), find_library("cuda")
    if smi is None and cuda is None:
        return None
    return " and ".join(x for x in (f"nvidia-smi at {smi}" if smi else "", f"libcuda ({cuda})" if cuda else "") if x)


def check_cuda(
    gpu: str | None,
    probe: Callable[[str, str | None], ProbeResult] = render_probe,
    *,
    forced_variant: str | None = None,
    libllvm: str | None = None,
) -> Check:
    """With a GPU, the ``cuda_ad_mono`` variant renders; without one, CPU only is fine.

    rig picks ``cuda_ad_mono`` whenever ``nvidia-smi`` answers, unless
    ``RIG_MITSUBA_VARIANT`` (``forced_variant``) says otherwise, so a GPU that is
    present but cannot render blocks estimation.

    Args:
        gpu: how the GPU shows itself (:func:`detect_gpu`), None without one.
        probe: renders with a variant and a libLLVM path.
        forced_variant: the value of ``RIG_MITSUBA_VARIANT``, if set.
        libllvm: the libLLVM the child process loads (Dr.Jit loads it for every variant).
    """
    forced_cpu = bool(forced_variant and not forced_variant.startswith("cuda"))
    if gpu is None:
        if forced_variant and not forced_cpu:
            return Check("mitsuba-cuda", "fail", f"RIG_MITSUBA_VARIANT={forced_variant} but no NVIDIA GPU is present",
                         "unset RIG_MITSUBA_VARIANT (or set it to llvm_ad_mono)")
        return Check("mitsuba-cuda", "ok", "no NVIDIA GPU (no nvidia-smi, no libcuda): CPU only")
    res = probe("cuda_ad_mono", libllvm)
    if res.ok:
        return Check("mitsuba-cuda", "ok", f"cuda_ad_mono renders ({gpu})")
    fix = ("make `nvidia-smi` list the GPU (install or update the NVIDIA driver), "
           "or export RIG_MITSUBA_VARIANT=llvm_ad_mono to estimate on the CPU")
    if forced_cpu:
        return Check("mitsuba-cuda", "warn", f"GPU present ({gpu}) but cuda_ad_mono failed: {res.detail}; "
                     f"RIG_MITSUBA_VARIANT={forced_variant} keeps estimation on the CPU", fix)
    return Check("mitsuba-cuda", "fail", f"GPU present ({gpu}) but cuda_ad_mono failed: {res.detail}", fix)


# --------------------------------------------------------------------------- USB


def check_libusb(get_backend: Callable[[], Any] | None = None) -> Check:
    """pyusb finds the libusb-1.0 library."""
    if get_backend is None:
        import usb.backend.libusb1

        get_backend = usb.backend.libusb1.get_backend
    backend = get_backend()
    if backend is None:
        return Check("libusb", "fail", "pyusb finds no libusb-1.0 library (the camera is on USB)",
                     "sudo apt-get install libusb-1.0-0")
    return Check("libusb", "ok", f"libusb-1.0 backend available ({type(backend).__module__})")


def check_camera(devices: Sequence[UsbDeviceInfo] | None, *, required: bool,
                 serial_number: str | None = None, usb_error: str | None = None) -> Check:
    """The Apogee camera (vendor 0x125C) is on USB and opens without root.

    Args:
        devices: USB devices found (:func:`rig.discovery.list_usb_devices`), None if not listed.
        required: the configuration uses the real camera (not the simulated one).
        serial_number: the configured camera serial number, if any.
        usb_error: why USB could not be listed.
    """
    if not required:
        return Check("camera", "ok", "simulated camera: no USB device needed")
    if devices is None:
        fix = ("sudo apt-get install libusb-1.0-0" if "libusb" in (usb_error or "")
               else "re-plug the camera and check that `lsusb` lists the USB bus")
        return Check("camera", "fail", f"cannot list USB devices: {usb_error}", fix)
    cams = [d for d in devices if d.vendor_id == APOGEE_VID]
    if serial_number is not None:
        others = [d for d in cams if d.serial_number not in (None, serial_number)]
        cams = [d for d in cams if d.serial_number in (None, serial_number)]
        if not cams and others:
            return Check("camera", "fail", f"no Apogee camera with serial {serial_number}; found "
                         + ", ".join(str(d.serial_number) for d in others),
                         "set camera.serial_number in rig.yaml to one of those (or null)")
    if not cams:
        return Check("camera", "fail", "no Apogee camera (USB vendor 0x125c) found",
                     "power the camera, plug its USB cable in, and check `lsusb -d 125c:`")
    d = cams[0]
    where = f"{d.kind} {d.usb_id} on bus {d.bus} address {d.address}"
    if d.access == "denied":
        return Check("camera", "fail", f"{where} is not accessible without root ({d.error or 'access denied'})",
                     UDEV_FIX)
    if d.access == "busy":
        return Check("camera", "fail", f"{where} is in use by another program ({d.error})",
                     f"stop the program holding it (`fuser -v {usb_node(d)}` names it), or re-plug the camera")
    if d.access == "error":
        return Check("camera", "fail", f"{where} could not be opened: {d.error}",
                     "power-cycle the camera and re-plug its USB cable; then run `rig doctor` again")
    serial = f", serial {d.serial_number}" if d.serial_number else ""
    return Check("camera", "ok", f"{where} opens without root{serial}")


# --------------------------------------------------------------------------- serial ports


@dataclass(frozen=True)
class Identity:
    """Who is checking access: user id, group ids and user name."""

    uid: int
    gids: frozenset[int]
    user: str

    @classmethod
    def current(cls) -> Identity:
        uid = os.geteuid()
        try:
            user = pwd.getpwuid(uid).pw_name
        except KeyError:
            user = str(uid)
        return cls(uid, frozenset(os.getgroups()) | {os.getegid()}, user)


def mode_allows(st: os.stat_result, want: int, who: Identity) -> bool:
    """Whether the permission bits grant ``want`` (os.R_OK|os.W_OK...) to ``who``.

    Root passes (it bypasses the bits). ACLs are not read: see :func:`check_serial_port`.
    """
    if who.uid == 0:
        return True
    # POSIX: the owner class applies to the owner even when the group class would allow more.
    shift = 6 if st.st_uid == who.uid else 3 if st.st_gid in who.gids else 0
    bits = (st.st_mode >> shift) & 0o7
    need = (4 if want & os.R_OK else 0) | (2 if want & os.W_OK else 0) | (1 if want & os.X_OK else 0)
    return bits & need == need


def _group_name(gid: int) -> str:
    try:
        return grp.getgrgid(gid).gr_name
    except KeyError:
        return str(gid)


def _listed_in_group(user: str, gid: int) -> bool:
    """The user is in the group database's member list (may not be active in this login yet)."""
    try:
        g = grp.getgrgid(gid)
    except KeyError:
        return False
    try:
        primary = pwd.getpwnam(user).pw_gid == gid
    except KeyError:
        primary = False
    return primary or user in g.gr_mem


def check_serial_port(role: str, port: str | None, who: Identity | None = None,
                      taken: Mapping[str, str | None] | None = None) -> Check:
    """A configured serial port exists and the user may read and write it.

    Args:
        role: ``stage`` or ``filter`` (names the check).
        port: the configured port (a device path, or a ``sim-*://`` URL).
        who: identity to check the permission bits for; None checks the running process
            with ``os.access`` (which also honours ACLs, e.g. udev's uaccess).
        taken: ports of the other devices (role -> port): one port cannot serve two devices.
    """
    name = f"serial-{role}"
    if port is None:
        return Check(name, "ok", f"{role}: no serial port configured (manual)")
    if "://" in port:
        return Check(name, "ok", f"{role}: {port} is a URL (simulated twin or network port), no device node")
    if not os.path.exists(port):
        return Check(name, "fail", f"{role} port {port} does not exist",
                     "plug the adapter in, run `rig devices --scan` and put the port it lists in rig.yaml")
    real = os.path.realpath(port)
    for other, other_port in (taken or {}).items():
        if other_port and "://" not in other_port and os.path.realpath(other_port) == real:
            return Check(name, "fail", f"{role} port {port} is also the {other}'s port ({other_port})",
                         "run `rig devices --scan` and give each device its own port in rig.yaml")
    st = os.stat(real)
    want = os.R_OK | os.W_OK
    allowed = os.access(real, want) if who is None else mode_allows(st, want, who)
    label = f"{port}" + (f" -> {real}" if real != port else "")
    if allowed:
        if not stat.S_ISCHR(st.st_mode):
            return Check(name, "warn", f"{role} port {label} is not a character device (not a serial port)",
                         "run `rig devices --scan` and use a /dev/tty* or /dev/serial/by-id/* path")
        return Check(name, "ok", f"{role} port {label} is readable and writable")
    who = who or Identity.current()
    group = _group_name(st.st_gid)
    if st.st_gid not in who.gids and _listed_in_group(who.user, st.st_gid):
        fix = f"log out and back in (or run `newgrp {group}`): {who.user} was added to {group} after this login"
    elif st.st_gid not in who.gids and st.st_mode & 0o060 == 0o060:
        fix = f"sudo usermod -aG {group} $USER, then log out and back in"
    else:
        fix = f"sudo chmod g+rw {real} (and check the udev rule that sets its mode)"
    return Check(name, "fail", f"{role} port {label} is not readable and writable by {who.user} "
                 f"(mode {stat.filemode(st.st_mode)}, group {group})", fix)


# --------------------------------------------------------------------------- disk space


@dataclass(frozen=True)
class SessionSizePlan:
    """What one capture session writes, for the disk space estimate.

    Defaults: 10 light angles, 3 filters, brackets of up to 6 exposures with 2 matched
    dark frames per exposure time, raw frames 512 x 512 uint16 (Alta U260), each merged
    image three float32 channels (radiance, variance, mask), and the beam calibration
    (one bracket per filter, slab removed). Files are counted uncompressed, so the
    estimate is an upper bound.
    """

    angles: int = 10
    filters: int = 3
    exposures: int = 6
    darks_per_exposure: int = 2
    width: int = 512
    height: int = 512
    raw_bytes_per_pixel: int = 2
    hdr_channels: int = 3
    hdr_bytes_per_channel: int = 4
    calibration_stacks_per_filter: int = 1

    def stacks(self) -> int:
        return self.filters * (self.angles + self.calibration_stacks_per_filter)

    def bytes_per_stack(self) -> int:
        pixels = self.width * self.height
        raw = self.exposures * (1 + self.darks_per_exposure) * pixels * self.raw_bytes_per_pixel
        return raw + pixels * self.hdr_channels * self.hdr_bytes_per_channel

    def total_bytes(self) -> int:
        return self.stacks() * self.bytes_per_stack()


def session_bytes(size: SessionSizePlan, cfg: Any = None, filter_names: Sequence[str] | None = None) -> tuple[int, str]:
    """Bytes one session needs and where the number comes from.

    With a rig configuration, the capture package plans the session (its angles within
    the stage's allowed range, its bracket policy) and estimates its size
    (:func:`capture.session.estimate_session_bytes`), plus the calibration stacks;
    otherwise (or if the capture package is not importable) :meth:`SessionSizePlan.total_bytes`.

    Raises:
        capture.errors.PlanError: the plan itself is impossible (e.g. an unknown filter).
    """
    if cfg is None:
        return size.total_bytes(), "plan estimate"
    try:
        from capture.bracket import BracketPolicy
        from capture.plan import AngleSpec, make_plan
        from capture.session import estimate_session_bytes
        from drivers.interfaces import AngleRange
    except ImportError:
        return size.total_bytes(), "plan estimate"
    names = tuple(filter_names) if filter_names is not None else tuple(cfg.filter.positions)
    bracket = BracketPolicy(max_exposures=size.exposures, n_darks=size.darks_per_exposure)
    plan = make_plan(AngleSpec(n_angles=size.angles, filters=names), available_filters=tuple(cfg.filter.positions),
                     stage_range=AngleRange(*cfg.stage.allowed_range_deg), bracket=bracket)
    n_stacks = len(plan.keys()) + len(names) * size.calibration_stacks_per_filter
    return estimate_session_bytes(plan, (size.height, size.width), n_stacks=n_stacks), "capture plan"


def _existing_parent(path: Path) -> Path:
    p = path.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def _mb(n: float) -> str:
    return f"{n / 1e9:.2f} GB" if n >= 1e9 else f"{n / 1e6:.0f} MB"


def check_disk_space(
    out_dir: str | Path,
    plan: SessionSizePlan = SessionSizePlan(),
    *,
    headroom: float = 2.0,
    disk_usage: Callable[[str], Any] = shutil.disk_usage,
    who: Identity | None = None,
    need_bytes: int | None = None,
) -> Check:
    """The output directory (or its nearest existing parent) is writable and has room.

    Fails below one session's estimate; warns below ``headroom`` sessions (a resumed or
    repeated run, calibration redone).

    Args:
        out_dir: where sessions are written (need not exist yet).
        plan: the session to estimate (see :class:`SessionSizePlan`).
        headroom: sessions' worth of space below which a warning is given.
        disk_usage: returns an object with ``free`` (bytes) for a path.
        who: identity for the permission bits; None: ``os.access`` for this process.
        need_bytes: bytes of one session (default: ``plan.total_bytes()``; see :func:`session_bytes`).
    """
    out = Path(out_dir)
    base = _existing_parent(out)
    need = need_bytes if need_bytes is not None else plan.total_bytes()
    what = f"{plan.angles} angles x {plan.filters} filters x {plan.exposures} exposures"
    if not base.is_dir():
        return Check("disk-space", "fail", f"{out} is under {base}, which is not a directory",
                     "pass --out with a directory path")
    want = os.W_OK | os.X_OK
    ok = os.access(base, want) if who is None else mode_allows(os.stat(base), want, who)
    if not ok:
        user = (who or Identity.current()).user
        return Check("disk-space", "fail", f"{base} is not writable by {user}",
                     f"pass --out with a directory you own, or: sudo chown {user} {base}")
    free = int(disk_usage(str(base)).free)
    msg = f"{_mb(free)} free in {base}; one session ({what}) needs about {_mb(need)}"
    if free < need:
        return Check("disk-space", "fail", msg, f"free {_mb(need - free)} in {base} or pass --out on a larger disk")
    if free < headroom * need:
        return Check("disk-space", "warn", msg + f", less than {headroom:g} sessions' worth",
                     f"free {_mb(headroom * need - free)} in {base} before a second session")
    return Check("disk-space", "ok", msg)


# --------------------------------------------------------------------------- all


def run_checks(
    cfg: Any,
    out_dir: str | Path,
    plan: SessionSizePlan,
    *,
    usb_backend: Any = None,
    llvm_globs: Iterable[str] = LLVM_SEARCH_GLOBS,
    probe: Callable[[str, str | None], ProbeResult] = render_probe,
    gpu: str | None | Literal["detect"] = "detect",
    who: Identity | None = None,
    filter_names: Sequence[str] | None = None,
) -> list[Check]:
    """Every check, in the order they are printed, for a rig configuration."""
    from rig.discovery import list_usb_devices

    checks = [check_python(), check_packages()]
    libs = find_libllvm_all(llvm_globs)
    checks.append(check_llvm_versions(libs))
    selected = rig_libllvm()
    checks.append(check_mitsuba_cpu(libs, selected, probe))
    checks.append(check_cuda(detect_gpu() if gpu == "detect" else gpu, probe,
                             forced_variant=os.environ.get("RIG_MITSUBA_VARIANT"), libllvm=selected))

    stage_port = cfg.stage.port
    filter_port = cfg.filter.port if cfg.filter.driver == "fw102c" else None
    real_rig = "://" not in stage_port  # a simulated rig has no USB camera (as in `rig devices`)
    libusb = check_libusb() if usb_backend is None else Check("libusb", "ok", "USB backend given")
    checks.append(libusb)
    devices: list[UsbDeviceInfo] | None = None
    usb_error = None
    if real_rig and libusb.status == "ok":
        try:
            devices = list_usb_devices(usb_backend)
        except Exception as e:  # noqa: BLE001 - reported as the camera check's failure
            usb_error = f"{e.__class__.__name__}: {e}"
    elif real_rig:
        usb_error = "libusb missing"
    checks.append(check_camera(devices, required=real_rig, serial_number=cfg.camera.serial_number,
                               usb_error=usb_error))
    checks.append(check_serial_port("stage", stage_port, who))
    checks.append(check_serial_port("filter", filter_port, who, taken={"stage": stage_port}))
    need, _ = session_bytes(plan, cfg, filter_names)
    checks.append(check_disk_space(out_dir, plan, who=who, need_bytes=need))
    return checks
