"""The session directory: the contract between capture, calibrate and estimate.

Layout (documented in ``docs/session-format.md``)::

    DIR/session.yaml        the manifest (format name + version, plan, stack states, checksums)
    DIR/raw/a03_g.npz       raw uint16 frames of a stack (light + matched darks) with metadata
    DIR/hdr/a03_g.exr       merged float32 OpenEXR: radiance (e-/s), variance, mask
    DIR/calibration/...     copy of the beam calibration the session was captured with
    DIR/session.lock        advisory lock held while a capture writes (flock; freed on any exit)

Crash safety: every file is written atomically (:mod:`capture.atomic`); a
stack's files are written first and the manifest then marks it ``done`` with
their SHA-256, so a stack is either done with verified files or pending (its
stray files are simply rewritten on resume). A done stack is never written
again.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import fcntl
import importlib.metadata
import math
import os
import shutil
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field, is_dataclass
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from capture.atomic import (
    atomic_write_bytes,
    atomic_write_text,
    fsync_dir,
    is_temp_name,
    remove_stale_temps,
    sha256_file,
)
from capture.errors import SessionError
from capture.exr_io import ExrImage, read_exr, read_frames, write_exr, write_frames
from capture.hdr import HdrResult, NoiseModel
from capture.plan import CapturePlan, StackKey
from drivers.interfaces import Frame, SensorInfo

FORMAT_NAME = "rig-session"
FORMAT_VERSION = 1
MANIFEST_NAME = "session.yaml"
LOCK_NAME = "session.lock"
RAW_DIR = "raw"
HDR_DIR = "hdr"
CALIBRATION_DIR = "calibration"
CALIBRATION_MAIN = "calibration.yaml"

PENDING = "pending"
DONE = "done"


def software_version() -> str:
    """Version of the installed ``rig`` distribution (``unknown`` when run from a bare tree)."""
    try:
        return importlib.metadata.version("rig")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds")


def _plain(obj: Any) -> Any:
    """Convert to YAML-safe builtins (dataclasses, enums, paths, numpy scalars, tuples)."""
    if is_dataclass(obj) and not isinstance(obj, type):
        return _plain(asdict(obj))
    if isinstance(obj, Mapping):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [_plain(v) for v in obj]
    if isinstance(obj, Enum):
        return _plain(obj.value)
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, float) and not math.isfinite(obj):
        return str(obj)
    return obj


def _one_line(err: BaseException) -> str:
    text = " ".join(str(err).split())
    return text[:300] if text else type(err).__name__


@dataclass(frozen=True)
class FileRecord:
    """A file of the session, relative to its directory, with its SHA-256 and size in bytes."""

    file: str
    sha256: str
    bytes: int


@dataclass
class StackRecord:
    """One stack's entry in the manifest."""

    key: StackKey
    angle_deg: float
    state: str = PENDING
    files: dict[str, FileRecord] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)
    completed: str | None = None

    @property
    def id(self) -> str:
        return self.key.id

    @property
    def done(self) -> bool:
        return self.state == DONE

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.key.id,
            "angle_index": self.key.angle_index,
            "angle_deg": float(self.angle_deg),
            "filter": self.key.filter,
            "state": self.state,
            "completed": self.completed,
            "files": {k: asdict(v) for k, v in self.files.items()},
            "info": _plain(self.info),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> StackRecord:
        key = StackKey(int(d["angle_index"]), str(d["filter"]))
        if d.get("id", key.id) != key.id:
            raise ValueError(f"stack id {d.get('id')!r} does not match angle index and filter ({key.id})")
        state = str(d["state"])
        if state not in (PENDING, DONE):
            raise ValueError(f"stack {key.id} has unknown state {state!r}")
        files = {str(k): FileRecord(str(v["file"]), str(v["sha256"]), int(v["bytes"])) for k, v in (d.get("files") or {}).items()}
        if state == DONE and not {"raw", "hdr"} <= files.keys():
            raise ValueError(f"stack {key.id} is done but lists no raw/hdr files")
        return cls(key, float(d["angle_deg"]), state, files, dict(d.get("info") or {}), d.get("completed"))


def estimate_session_bytes(plan: CapturePlan, frame_shape: tuple[int, int], n_stacks: int | None = None) -> int:
    """Upper bound of the disk space a session needs, bytes.

    Per stack: the most light frames the bracket may take, each with its
    matched darks, as uncompressed uint16, plus three float32 EXR channels
    (uncompressed); 10 % and 1 MiB of slack for manifests and metadata.
    """
    rows, cols = frame_shape
    n = len(plan.keys()) if n_stacks is None else n_stacks
    b = plan.bracket
    raw = b.max_exposures * (1 + b.n_darks) * rows * cols * 2
    hdr = 3 * rows * cols * 4
    return int(1.1 * n * (raw + hdr)) + (1 << 20)


class Session:
    """A session directory. Make one with :meth:`create`, :meth:`resume` or :meth:`open`.

    ``create`` and ``resume`` hold the session lock until :meth:`close` (or the
    process ends); ``open`` is read-only and takes no lock.
    """

    def __init__(self, path: Path, manifest: dict[str, Any], stacks: list[StackRecord], *, writable: bool) -> None:
        self.path = path
        self._m = manifest
        self._stacks = {s.key: s for s in stacks}
        self._writable = writable
        self._lock_fd: int | None = None

    # ------------------------------------------------------------------ making
    @classmethod
    def create(
        cls,
        path: str | os.PathLike[str],
        *,
        plan: CapturePlan,
        frame_shape: tuple[int, int],
        rig_config: Mapping[str, Any] | None = None,
        devices: Mapping[str, str] | None = None,
        sensor: SensorInfo | None = None,
        noise: NoiseModel | None = None,
        geometry: Mapping[str, Any] | None = None,
        calibration: str | os.PathLike[str] | None = None,
        extra: Mapping[str, Any] | None = None,
    ) -> Session:
        """Create a new session directory with every stack pending.

        Args:
            path: the directory; created if missing, else it must be empty.
            plan: the checked capture plan.
            frame_shape: (rows, cols) of the frames the camera will read (its ROI), for the space check.
            rig_config: snapshot of the rig configuration (YAML-safe mapping).
            devices: identity string per device (``stage``, ``camera``, ``filter``).
            sensor: the camera's sensor facts.
            noise: the noise model the merges use.
            geometry: rig geometry the estimator needs (slab thickness etc., from rig.yaml).
            calibration: a beam-calibration file or directory to copy into the session.
            extra: further YAML-safe facts to keep (e.g. the command line).

        Raises:
            SessionError: the directory holds a session or other files, cannot be
                written, or lacks the space the plan may need.
        """
        p = Path(path)
        if p.exists() and not p.is_dir():
            raise SessionError(f"{p} exists and is not a directory")
        if p.is_dir():
            entries = [e.name for e in p.iterdir()]
            if MANIFEST_NAME in entries:
                raise SessionError(f"{p} already holds a session; continue it with --resume {p} or choose a new directory")
            if entries and not cls._is_unborn(p):
                raise SessionError(f"{p} is not empty and is not a session; choose a new or empty directory")
        existing = p
        while not existing.exists() and existing != existing.parent:
            existing = existing.parent
        if not existing.is_dir():
            raise SessionError(f"cannot create {p}: {existing} is not a directory")
        cls._check_space(existing, estimate_session_bytes(plan, frame_shape))
        made = not p.exists()
        try:
            p.mkdir(parents=True, exist_ok=True)
            probe = p / ".write-probe"
            atomic_write_text(probe, "probe")
            probe.unlink()
            for d in (RAW_DIR, HDR_DIR):
                (p / d).mkdir(exist_ok=True)
            fsync_dir(p)  # the new entries survive a power cut
            fsync_dir(p.parent)
        except OSError as e:
            if made:
                shutil.rmtree(p, ignore_errors=True)
            raise SessionError(f"cannot write to {p}: {_one_line(e)}") from None

        stacks = [StackRecord(k, plan.angles_deg[k.angle_index]) for k in plan.keys()]
        now = _now()
        manifest: dict[str, Any] = {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "software": {"name": "rig", "version": software_version()},
            "created": now,
            "updated": now,
            "resumed": [],
            "frame_shape": [int(frame_shape[0]), int(frame_shape[1])],
            "rig": _plain(rig_config or {}),
            "devices": _plain(devices or {}),
            "sensor": _plain(sensor) if sensor is not None else None,
            "noise_model": noise.to_dict() if noise is not None else None,
            "geometry": _plain(geometry or {}),
            "plan": plan.to_dict(),
            "calibration": None,
            "extra": _plain(extra or {}),
            "stacks": [],
        }
        s = cls(p, manifest, stacks, writable=True)
        s._lock()
        try:
            remove_stale_temps(p)  # of a create interrupted before its manifest
            if calibration is not None:
                s.attach_calibration(calibration, _save=False)
            s._save()
        except BaseException:
            s.close()
            raise
        return s

    @staticmethod
    def _is_unborn(path: Path) -> bool:
        """True for what a create interrupted before its first manifest leaves: empty
        ``raw/`` and ``hdr/``, the lock, the write probe and temporary files only."""
        for e in path.iterdir():
            if e.name in (RAW_DIR, HDR_DIR) and e.is_dir():
                if any(not is_temp_name(f.name) for f in e.iterdir()):
                    return False
            elif not (e.name in (LOCK_NAME, ".write-probe") or is_temp_name(e.name)):
                return False
        return True

    @staticmethod
    def _check_space(path: Path, need: int) -> None:
        try:
            free = shutil.disk_usage(path).free
        except OSError as e:
            raise SessionError(f"cannot read the free space of {path}: {_one_line(e)}") from None
        if free < need:
            raise SessionError(
                f"not enough space in {path}: the plan may need {need / 2**20:.1f} MiB, {free / 2**20:.1f} MiB free"
            )

    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> Session:
        """Open a session for reading (estimation, ``rig info``); takes no lock.

        Raises:
            SessionError: no such directory, no manifest, or a corrupt or unsupported manifest.
        """
        p = Path(path)
        if not p.is_dir():
            raise SessionError(f"{p} is not a session directory (it does not exist or is not a directory)")
        mpath = p / MANIFEST_NAME
        if not mpath.is_file():
            raise SessionError(f"{p} is not a session: {MANIFEST_NAME} is missing")
        try:
            text = mpath.read_text(encoding="utf-8")
            m = yaml.safe_load(text)
        except (OSError, UnicodeDecodeError, yaml.YAMLError) as e:
            raise SessionError(f"corrupt manifest {mpath}: {_one_line(e)}") from None
        if not isinstance(m, dict) or m.get("format") != FORMAT_NAME:
            raise SessionError(f"corrupt manifest {mpath}: not a {FORMAT_NAME} manifest")
        version = m.get("format_version")
        if not isinstance(version, int) or version < 1:
            raise SessionError(f"corrupt manifest {mpath}: bad format_version {version!r}")
        if version > FORMAT_VERSION:
            raise SessionError(
                f"{mpath} has format version {version}; this rig reads up to {FORMAT_VERSION} (update rig)"
            )
        try:
            plan = CapturePlan.from_dict(m["plan"])
            stacks = [StackRecord.from_dict(d) for d in m["stacks"]]
            expected = {k: plan.angles_deg[k.angle_index] for k in plan.keys()}
            got = {s.key for s in stacks}
            if got != set(expected) or len(stacks) != len(expected):
                raise ValueError("the stack list does not match the plan")
            for s in stacks:
                if not math.isclose(s.angle_deg, expected[s.key], abs_tol=1e-9):
                    raise ValueError(f"stack {s.id} angle {s.angle_deg} does not match the plan")
            for k in ("created", "updated", "software"):
                if k not in m:
                    raise KeyError(k)
        except (KeyError, TypeError, ValueError, IndexError, AttributeError) as e:
            what = f"missing {e}" if isinstance(e, KeyError) else _one_line(e)
            raise SessionError(f"corrupt manifest {mpath}: {what}") from None
        return cls(p, m, stacks, writable=False)

    @classmethod
    def resume(cls, path: str | os.PathLike[str], *, plan: CapturePlan | None = None, devices: Mapping[str, str] | None = None) -> Session:
        """Open a session to continue capturing.

        Removes temporary files of interrupted writes, checks the files of every
        done stack against their checksums and the remaining space, and records
        the resumption (time, device identities).

        Raises:
            SessionError: as :meth:`open`; also when ``plan`` differs from the
                session's plan, a done stack's file is missing or corrupt, the
                session is locked by another process, or space is short.
        """
        s = cls.open(path)
        # compared as plans, not dicts: a manifest written before a plan field existed
        # (e.g. stage_offset_deg) reads back with that field's default
        if plan is not None and plan != CapturePlan.from_dict(s._m["plan"]):
            raise SessionError(f"{s.path} was planned with other angles, filters or bracket; resume it without changing the plan")
        s._writable = True
        s._lock()
        try:
            remove_stale_temps(s.path)
            problems = s.verify()
            if problems:
                raise SessionError(f"{s.path}: {problems[0]}" + (f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""))
            pending = len(s.pending_keys())
            if pending:
                shape = tuple(s._m.get("frame_shape") or (512, 512))
                s._check_space(s.path, estimate_session_bytes(s.plan, shape, pending))  # type: ignore[arg-type]
            s._m.setdefault("resumed", []).append({"time": _now(), "devices": _plain(devices or {})})
            s._save()
        except BaseException:
            s.close()
            raise
        return s

    # ------------------------------------------------------------------ lock
    def _lock(self) -> None:
        fd = os.open(self.path / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise SessionError(f"{self.path} is in use by another capture (session.lock is held)") from None
        self._lock_fd = fd

    def close(self) -> None:
        """Release the session lock (the manifest is already saved)."""
        if self._lock_fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._lock_fd)
            self._lock_fd = None
        self._writable = False

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.close()

    # ------------------------------------------------------------------ facts
    @property
    def plan(self) -> CapturePlan:
        return CapturePlan.from_dict(self._m["plan"])

    @property
    def manifest(self) -> dict[str, Any]:
        """A copy of the manifest as read/written (plain YAML types)."""
        return yaml.safe_load(yaml.safe_dump(self._m))

    @property
    def format_version(self) -> int:
        return int(self._m["format_version"])

    @property
    def devices(self) -> dict[str, str]:
        return dict(self._m.get("devices") or {})

    @property
    def rig_config(self) -> dict[str, Any]:
        return dict(self._m.get("rig") or {})

    def geometry(self) -> dict[str, Any]:
        """Rig geometry recorded at creation (from rig.yaml; e.g. slab thickness in mm)."""
        return dict(self._m.get("geometry") or {})

    def sensor(self) -> SensorInfo | None:
        d = self._m.get("sensor")
        return SensorInfo(**d) if d else None

    def noise_model(self) -> NoiseModel | None:
        d = self._m.get("noise_model")
        return NoiseModel.from_dict(d) if d else None

    def render_noise(self) -> dict[str, Any] | None:
        """The simulated camera's declared frozen render noise (``extra.render_noise``,
        docs/session-format.md); None for a real camera or an older session."""
        d = (self._m.get("extra") or {}).get("render_noise")
        return dict(d) if isinstance(d, dict) else None

    def stacks(self) -> list[StackRecord]:
        """Every stack in plan order."""
        return [self._stacks[k] for k in self.plan.keys()]

    def stack(self, key: StackKey | str) -> StackRecord:
        k = self._key(key)
        return self._stacks[k]

    def done_keys(self) -> frozenset[StackKey]:
        return frozenset(k for k, s in self._stacks.items() if s.done)

    def pending_keys(self) -> list[StackKey]:
        return [k for k in self.plan.keys() if not self._stacks[k].done]

    @property
    def complete(self) -> bool:
        return not self.pending_keys()

    def _key(self, key: StackKey | str) -> StackKey:
        if isinstance(key, StackKey):
            if key not in self._stacks:
                raise SessionError(f"{self.path} has no stack {key.id}")
            return key
        for k in self._stacks:
            if k.id == key:
                return k
        raise SessionError(f"{self.path} has no stack {key!r}")

    # ------------------------------------------------------------------ writing
    def _save(self) -> None:
        self._m["updated"] = _now()
        self._m["stacks"] = [self._stacks[k].to_dict() for k in self.plan.keys()]
        text = "# rig session manifest; see docs/session-format.md\n" + yaml.safe_dump(self._m, sort_keys=False, allow_unicode=True)
        try:
            atomic_write_text(self.path / MANIFEST_NAME, text)
        except OSError as e:
            raise SessionError(f"cannot write the manifest of {self.path}: {_one_line(e)}") from None

    def _file_record(self, rel: str, sha: str) -> FileRecord:
        return FileRecord(rel, sha, (self.path / rel).stat().st_size)

    def write_stack(
        self,
        key: StackKey,
        *,
        frames: Sequence[Frame],
        hdr: HdrResult,
        info: Mapping[str, Any] | None = None,
        attributes: Mapping[str, str | int | float] | None = None,
    ) -> StackRecord:
        """Write a completed stack: raw frames, HDR image, then the manifest entry (done).

        Raises:
            SessionError: the session is read-only, the stack is already done
                (never overwritten), or a file cannot be written.
        """
        if not self._writable:
            raise SessionError(f"{self.path} is open read-only")
        k = self._key(key)
        rec = self._stacks[k]
        if rec.done:
            raise SessionError(f"stack {k.id} of {self.path} is already complete; it is never overwritten")
        raw_rel = f"{RAW_DIR}/{k.id}.npz"
        hdr_rel = f"{HDR_DIR}/{k.id}.exr"
        attrs: dict[str, str | int | float] = {
            "rig_stack": k.id,
            "rig_angle_deg": float(rec.angle_deg),
            "rig_filter": k.filter,
            "rig_radiance_units": "e-/s",
            "rig_variance_units": "(e-/s)^2",
        }
        attrs.update(attributes or {})
        try:
            (self.path / RAW_DIR).mkdir(exist_ok=True)
            (self.path / HDR_DIR).mkdir(exist_ok=True)
            raw_sha = write_frames(self.path / raw_rel, frames)
            hdr_sha = write_exr(self.path / hdr_rel, hdr.channels(), attrs, meta=_plain(info or {}))
            files = {"raw": self._file_record(raw_rel, raw_sha), "hdr": self._file_record(hdr_rel, hdr_sha)}
        except OSError as e:
            raise SessionError(f"cannot write stack {k.id} in {self.path}: {_one_line(e)}") from None
        rec.files = files
        rec.info = dict(_plain(info or {}))
        rec.state = DONE
        rec.completed = _now()
        try:
            self._save()
        except BaseException:
            rec.state, rec.completed, rec.files = PENDING, None, {}
            raise
        return rec

    # ------------------------------------------------------------------ calibration
    def attach_calibration(self, source: str | os.PathLike[str], *, _save: bool = True) -> None:
        """Copy a beam calibration (a file, or a directory of files) into ``calibration/``.

        The session then carries the calibration it was captured with; every
        copied file is checksummed in the manifest.
        """
        if not self._writable:
            raise SessionError(f"{self.path} is open read-only")
        src = Path(source)
        if src.is_file():
            pairs = [(src, src.name)]
        elif src.is_dir():
            pairs = [(f, f.relative_to(src).as_posix()) for f in sorted(src.rglob("*")) if f.is_file() and f.name != LOCK_NAME]
        else:
            raise SessionError(f"calibration {src} does not exist")
        if not pairs:
            raise SessionError(f"calibration {src} holds no files")
        files = {}
        try:
            for f, rel in pairs:
                dest = self.path / CALIBRATION_DIR / rel
                dest.parent.mkdir(parents=True, exist_ok=True)
                sha = atomic_write_bytes(dest, f.read_bytes())
                files[rel] = {"sha256": sha, "bytes": dest.stat().st_size}
        except OSError as e:
            raise SessionError(f"cannot copy calibration {src} into {self.path}: {_one_line(e)}") from None
        self._m["calibration"] = {"source": str(src.resolve()), "attached": _now(), "files": files}
        if _save:
            self._save()

    @property
    def calibration_dir(self) -> Path | None:
        """The session's copy of its calibration, or None."""
        return self.path / CALIBRATION_DIR if self._m.get("calibration") else None

    def load_calibration(self) -> dict[str, Any]:
        """Parse ``calibration/calibration.yaml`` (written by ``rig calibrate-beam``).

        Raises:
            SessionError: the session has no calibration or it is unreadable.
        """
        cal = self._m.get("calibration")
        if not cal:
            raise SessionError(f"{self.path} references no beam calibration")
        p = self.path / CALIBRATION_DIR / CALIBRATION_MAIN
        try:
            d = yaml.safe_load(p.read_text(encoding="utf-8"))
        except (OSError, yaml.YAMLError) as e:
            raise SessionError(f"cannot read calibration {p}: {_one_line(e)}") from None
        if not isinstance(d, dict):
            raise SessionError(f"calibration {p} is not a mapping")
        return d

    # ------------------------------------------------------------------ reading
    def load_hdr(self, key: StackKey | str) -> ExrImage:
        """The merged image of a done stack: channels ``radiance`` (e-/s), ``variance`` ((e-/s)^2), ``mask``."""
        rec = self.stack(key)
        if not rec.done:
            raise SessionError(f"stack {rec.id} of {self.path} is not captured yet")
        return read_exr(self.path / rec.files["hdr"].file)

    def find(self, angle_deg: float, filter: str) -> StackRecord:
        """The stack planned at ``angle_deg`` (degrees, within 1e-6) through ``filter``."""
        for rec in self.stacks():
            if rec.key.filter == filter and math.isclose(rec.angle_deg, angle_deg, abs_tol=1e-6):
                return rec
        raise SessionError(f"{self.path} has no stack at {angle_deg:g} deg through filter {filter!r}")

    def load_raw(self, key: StackKey | str) -> list[Frame]:
        """The raw frames (light, then matched darks) of a done stack."""
        rec = self.stack(key)
        if not rec.done:
            raise SessionError(f"stack {rec.id} of {self.path} is not captured yet")
        return read_frames(self.path / rec.files["raw"].file)

    def iter_hdr(self, *, filter: str | None = None) -> Iterator[tuple[StackRecord, ExrImage]]:
        """Done stacks in plan order with their HDR images, optionally of one filter."""
        for rec in self.stacks():
            if rec.done and (filter is None or rec.key.filter == filter):
                yield rec, self.load_hdr(rec.key)

    # ------------------------------------------------------------------ checking
    def verify(self) -> list[str]:
        """Check every recorded file against its checksum; return one line per problem (empty = sound)."""
        problems: list[str] = []

        def check(rel: str, sha: str) -> None:
            p = self.path / rel
            if not p.is_file():
                problems.append(f"{rel} is missing")
                return
            try:
                got = sha256_file(p)
            except OSError as e:
                problems.append(f"{rel} is unreadable: {_one_line(e)}")
                return
            if got != sha:
                problems.append(f"{rel} is corrupt (checksum mismatch)")

        for rec in self.stacks():
            if rec.done:
                for fr in rec.files.values():
                    check(fr.file, fr.sha256)
        cal = self._m.get("calibration")
        if cal:
            for rel, fd in (cal.get("files") or {}).items():
                check(f"{CALIBRATION_DIR}/{rel}", fd["sha256"])
        return problems

    def summary(self) -> dict[str, Any]:
        """A short YAML/JSON-safe summary (for ``rig info`` and ``--json``)."""
        done = [s for s in self.stacks() if s.done]
        return {
            "path": str(self.path),
            "format_version": self.format_version,
            "software": self._m.get("software"),
            "created": self._m.get("created"),
            "updated": self._m.get("updated"),
            "angles_deg": list(self.plan.angles_deg),
            "filters": list(self.plan.filters),
            "stacks_total": len(self._stacks),
            "stacks_done": len(done),
            "complete": self.complete,
            "devices": self.devices,
            "calibration": bool(self._m.get("calibration")),
        }
