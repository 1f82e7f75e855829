"""Rig configuration (``rig.yaml``): loading and validation.

Every problem becomes one :class:`~rig.errors.UsageError` line naming the file,
the key and the fix. The schema is small on purpose and documented in
``docs/rig-config.md``; example files live in ``configs/``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rig.errors import UsageError
from rig.yaml_file import read_yaml

STAGE_DRIVERS = ("sigma-koki",)
CAMERA_DRIVERS = ("apogee-alta",)
FILTER_DRIVERS = ("fw102c", "manual")
STAGE_MODELS = ("SHOT-702", "SHOT-302GS", "SHOT-304GS", "GSC-01", "GSC-02")

#: The configuration used when no ``--config`` is given (the simulated rig's).
PACKAGED_SIM_CONFIG = Path(__file__).with_name("rig-sim.yaml")


@dataclass(frozen=True)
class StageConfig:
    driver: str
    port: str
    model: str = "SHOT-702"
    axis: int = 1
    degrees_per_pulse: float = 0.005
    division: int = 2
    zero_offset_deg: float = 0.0
    allowed_range_deg: tuple[float, float] = (20.0, 180.0)
    speed_deg_s: float = 10.0


@dataclass(frozen=True)
class CameraConfig:
    driver: str
    serial_number: str | None = None
    magnification: float = 0.3
    cooler_setpoint_c: float = -20.0
    profile_row: int | None = None  # None: from the beam calibration
    collection_sr: float = 0.01  # lens collection solid angle [sr] (absolute intensity scale)
    calibration_nd: float = 1.0e-3  # transmission of the ND filter used for the straight beam


@dataclass(frozen=True)
class FilterConfig:
    driver: str
    positions: dict[str, int]
    wavelengths_nm: dict[str, float]
    port: str | None = None


@dataclass(frozen=True)
class SimConfig:
    bench: str = "default"
    time_scale: float = 100.0
    faults: str = ""
    seed: int = 0
    world: str | None = None  # world file for the rendered bench (None: default world)


@dataclass(frozen=True)
class RigConfig:
    path: str
    stage: StageConfig
    camera: CameraConfig
    filter: FilterConfig
    sim: SimConfig = field(default_factory=SimConfig)
    raw: dict = field(default_factory=dict, repr=False)


class _Reader:
    """Typed access to a nested mapping with errors that say file, key and fix."""

    def __init__(self, path: str, data: Any, prefix: str = "") -> None:
        self.path, self.data, self.prefix = path, data, prefix

    def fail(self, key: str, msg: str) -> UsageError:
        return UsageError(f"{self.path}: {self.prefix}{key}: {msg}")

    def section(self, key: str, required: bool = True) -> _Reader:
        v = self.data.get(key) if isinstance(self.data, dict) else None
        if v is None:
            if required:
                raise self.fail(key, "missing section; see configs/rig-sim.yaml for an example")
            v = {}
        if not isinstance(v, dict):
            raise self.fail(key, f"must be a mapping of settings, got {type(v).__name__}")
        return _Reader(self.path, v, f"{self.prefix}{key}.")

    def get(self, key: str, kind: type, default: Any = ..., choices: tuple | None = None) -> Any:
        if key not in self.data or self.data[key] is None:
            if default is ...:
                raise self.fail(key, f"missing; add '{key}: <{kind.__name__}>'")
            return default
        v = self.data[key]
        if kind is float and isinstance(v, int) and not isinstance(v, bool):
            v = float(v)
        if kind is str and isinstance(v, (int, float)) and not isinstance(v, bool):
            v = str(v)
        if not isinstance(v, kind) or isinstance(v, bool) and kind is not bool:
            raise self.fail(key, f"must be a {kind.__name__}, got {v!r}")
        if kind is float and isinstance(v, float) and not math.isfinite(v):
            raise self.fail(key, f"must be finite, got {v!r}")
        if choices is not None and v not in choices:
            raise self.fail(key, f"unknown value {v!r}; use one of: {', '.join(map(str, choices))}")
        return v

    def unknown_keys(self, known: set[str]) -> None:
        extra = set(self.data) - known
        if extra:
            k = sorted(extra)[0]
            raise self.fail(k, f"unknown key; known keys here: {', '.join(sorted(known))}")


def load_config(path: str | Path | None = None) -> RigConfig:
    """Read and validate a rig configuration file (default: the packaged simulated rig)."""
    p = Path(path) if path is not None else PACKAGED_SIM_CONFIG
    name = str(path) if path is not None else "rig-sim.yaml (packaged)"
    data = read_yaml(p, name, UsageError, "no such file; pass an existing rig.yaml with --config")
    if not isinstance(data, dict):
        raise UsageError(f"{name}: must be a YAML mapping with sections stage, camera, filter")
    return parse_config(data, name)


def parse_config(data: dict, name: str = "<config>") -> RigConfig:
    root = _Reader(name, data)
    root.unknown_keys({"stage", "camera", "filter", "sim"})

    s = root.section("stage")
    s.unknown_keys({f for f in StageConfig.__dataclass_fields__})
    rng = s.data.get("allowed_range_deg", [20.0, 180.0])
    if (
        not isinstance(rng, (list, tuple)) or len(rng) != 2
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in rng)
        or rng[0] >= rng[1]
    ):
        raise s.fail("allowed_range_deg", f"must be [low, high] in degrees with low < high, got {rng!r}")
    stage = StageConfig(
        driver=s.get("driver", str, choices=STAGE_DRIVERS),
        port=s.get("port", str),
        model=s.get("model", str, "SHOT-702", choices=STAGE_MODELS),
        axis=s.get("axis", int, 1),
        degrees_per_pulse=s.get("degrees_per_pulse", float, 0.005),
        division=s.get("division", int, 2),
        zero_offset_deg=s.get("zero_offset_deg", float, 0.0),
        allowed_range_deg=(float(rng[0]), float(rng[1])),
        speed_deg_s=s.get("speed_deg_s", float, 10.0),
    )
    if stage.degrees_per_pulse <= 0:
        raise s.fail("degrees_per_pulse", "must be > 0 (SGSP-120YAW: 0.005)")
    if stage.speed_deg_s <= 0:
        raise s.fail("speed_deg_s", "must be > 0")
    if stage.axis < 1:
        raise s.fail("axis", "must be >= 1")

    c = root.section("camera")
    c.unknown_keys({f for f in CameraConfig.__dataclass_fields__})
    camera = CameraConfig(
        driver=c.get("driver", str, choices=CAMERA_DRIVERS),
        serial_number=c.get("serial_number", str, None),
        magnification=c.get("magnification", float, 0.3),
        cooler_setpoint_c=c.get("cooler_setpoint_c", float, -20.0),
        profile_row=c.get("profile_row", int, None),
        collection_sr=c.get("collection_sr", float, 0.01),
        calibration_nd=c.get("calibration_nd", float, 1.0e-3),
    )
    if not 0 < camera.collection_sr < 2 * math.pi:
        raise c.fail("collection_sr", "must be in (0, 2 pi) sr (pi * NA^2 for a lens of numerical aperture NA)")
    if not 0 < camera.calibration_nd <= 1:
        raise c.fail("calibration_nd", "must be in (0, 1]: the transmission of the ND filter used during calibrate-beam")
    if camera.magnification <= 0:
        raise c.fail("magnification", "must be > 0 (telecentric lens magnification)")

    f = root.section("filter")
    f.unknown_keys({fl for fl in FilterConfig.__dataclass_fields__})
    driver = f.get("driver", str, choices=FILTER_DRIVERS)
    positions = f.get("positions", dict)
    for k, v in positions.items():
        if not isinstance(k, str) or not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise f.fail("positions", f"entry {k!r}: {v!r} must map a filter name to a position >= 1")
    wl = f.get("wavelengths_nm", dict)
    for k in positions:
        v = wl.get(k)
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not 200 <= v <= 2000:
            raise f.fail("wavelengths_nm", f"filter {k!r} needs a centre wavelength in nm (200..2000), got {v!r}")
    port = f.get("port", str, None)
    if driver == "fw102c" and port is None:
        raise f.fail("port", "the fw102c driver needs a port (e.g. /dev/ttyUSB1)")
    filt = FilterConfig(driver=driver, positions=dict(positions), wavelengths_nm={k: float(wl[k]) for k in positions}, port=port)

    m = root.section("sim", required=False)
    m.unknown_keys({fl for fl in SimConfig.__dataclass_fields__})
    sim = SimConfig(
        bench=m.get("bench", str, "default"),
        time_scale=m.get("time_scale", float, 100.0),
        faults=m.get("faults", str, ""),
        seed=m.get("seed", int, 0),
        world=m.get("world", str, None),
    )
    if sim.time_scale <= 0:
        raise m.fail("time_scale", "must be > 0 (simulated seconds per real second)")
    return RigConfig(path=name, stage=stage, camera=camera, filter=filt, sim=sim, raw=data)
