"""The simulated world: the ground truth the rendered bench shows the camera.

A world file (YAML, schema in docs/world-format.md) sets what a real rig would hide
from its operator: the slab's material per filter, its thickness and size, the beam's
profile and power per filter, the optics (magnification, where the rotation axis is
imaged, the lens's collection solid angle and telecentric acceptance), sensor
parameters, the stage's hidden zero error, the left-out effects by their forward-model
names with magnitudes, and render settings.

Every problem becomes one :class:`WorldError` line naming the file, the key and the fix.
Nothing here is ever written into a session or a calibration.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from estimate.extensions import EXTENSIONS
from rig.yaml_file import read_yaml

if TYPE_CHECKING:
    from estimate.phase_tabulated import TabulatedPhase

__all__ = [
    "DEFAULT_WORLD_PATH",
    "EFFECT_NAMES",
    "BeamSpec",
    "Material",
    "Optics",
    "RenderSettings",
    "World",
    "WorldError",
    "load_world",
    "parse_world",
]

#: The documented default world (clean: every left-out effect off).
DEFAULT_WORLD_PATH = Path(__file__).resolve().parent.parent / "worlds" / "default.yaml"

#: Effects a world may switch on: the forward model's extension names.
EFFECT_NAMES = tuple(sorted(EXTENSIONS))

PHASE_TYPES = ("exp", "hg", "tthg", "mie")
BEAM_TYPES = ("gaussian", "disk", "map")
SENSOR_KEYS = ("read_noise_e", "dark_current_e_per_s", "gain_e_per_adu", "bias_adu", "full_well_e")


class WorldError(ValueError):
    """A world file is missing, unreadable or invalid (one line: file, key, fix)."""


@dataclass(frozen=True)
class Material:
    """Ground-truth material of one filter channel.

    Attributes:
        sigma_t: extinction coefficient [1/mm].
        albedo: single-scattering albedo.
        phase: the phase-function mapping as written in the world file.
        model: forward-model phase name ("exp<M>", "hg", "tthg"; "table" for a Mie phase
            rendered from its table, `render.mie_phase: table`).
        phase_params: forward-model parameters of the phase ("phase.b1", ...; none for a table).
        phase_table: the rendered table of model "table" (`estimate.phase_tabulated`), else None.
    """

    sigma_t: float
    albedo: float
    phase: dict
    model: str
    phase_params: dict[str, float]
    phase_table: TabulatedPhase | None = None

    def parameters(self) -> dict[str, float]:
        """Forward-model parameters sigma_t, albedo and the phase's."""
        return {"sigma_t": self.sigma_t, "albedo": self.albedo, **self.phase_params}


@dataclass(frozen=True)
class BeamSpec:
    """The beam: profile shape (shared by the filters) and power per filter.

    Attributes:
        profile: {"type": "gaussian", "sigma_mm"} | {"type": "disk", "radius_mm", "edge_mm"}
            | {"type": "map", "file", "pitch_mm"}.
        offset_mm: (u, v) of the profile's centre from the rotation axis [mm].
        power_e_per_s: per filter, the beam's rate if all of it were detected [e-/s].
    """

    profile: dict
    offset_mm: tuple[float, float]
    power_e_per_s: dict[str, float]


@dataclass(frozen=True)
class Optics:
    """Camera optics of the simulated rig.

    Attributes:
        magnification: lens magnification; None = the rig configuration's.
        axis_px: (column, row) continuous pixel coordinate where the rotation axis on the
            front face is imaged; None = sensor centre.
        collection_sr: solid angle the telecentric lens collects from each object point
            [sr]; scattered radiance -> e-/s per pixel = L * P * pixel_area * collection_sr.
        acceptance_sigma_deg: a collimated beam pointed into the lens tilted by delta is
            transmitted with exp(-delta^2 / 2 sigma^2) (the aperture stop clips it).
        calibration_nd: transmission of the neutral-density filter in the beam while it
            points straight into the lens (calibration only).
    """

    magnification: float | None = None
    axis_px: tuple[float, float] | None = None
    collection_sr: float = 0.01
    acceptance_sigma_deg: float = 0.5
    calibration_nd: float = 1e-3


@dataclass(frozen=True)
class RenderSettings:
    """How the truth is rendered (see sim_devices/rendered_scene.py).

    Attributes:
        spp_profile: samples per pixel on the profile rows.
        profile_halfwidth_rows: rows on each side of the axis row rendered at spp_profile.
        spp_band: samples per pixel on the band around them.
        band_halfwidth_rows: rows on each side of the axis row rendered at spp_band.
        spp_outside: samples per pixel for the rest of the frame (0: left dark).
        seed: base seed; each image's row tiers render with seeds drawn from it
            (`RenderedScene.image_seed`).
        cache_dir: disk cache of radiance images; None = $RIG_SIM_CACHE or ~/.cache/rig/sim-renders.
        mie_degree: degree of the exponential phase fitted to a Mie table (`mie_phase: exp`).
        mie_phase: how a Mie phase function is rendered: "exp" (the default: the exponential
            function of `mie_degree` fitted to its table in ln p) or "table" (the table itself,
            ln p linear in the angle: the faithful truth; for 0.5-um particles the exp8 fit is
            9 % rms off the table).
        max_depth: path length limit.
        engine: the forward model's render engine (`estimate.forward.ENGINES`): "camera"
            (Mitsuba's prbvolpath, the default: not the estimator's own) or "light" (paths
            from the beam: far less frozen Monte Carlo noise at the same cost, closer to a
            real recording, which has none).
    """

    spp_profile: int = 1024
    profile_halfwidth_rows: int = 2
    spp_band: int = 32
    band_halfwidth_rows: int = 16
    spp_outside: int = 1
    seed: int = 1
    cache_dir: str | None = None
    mie_degree: int = 8
    mie_phase: str = "exp"
    max_depth: int = 64
    engine: str = "camera"

    def cache_path(self) -> Path:
        if self.cache_dir:
            return Path(self.cache_dir).expanduser()
        env = os.environ.get("RIG_SIM_CACHE")
        return Path(env).expanduser() if env else Path.home() / ".cache" / "rig" / "sim-renders"


@dataclass(frozen=True)
class World:
    """A parsed world. `truth_hash` identifies everything that changes a render."""

    source: str
    name: str
    thickness_mm: float
    half_width_mm: float
    materials: dict[str, Material]
    beam: BeamSpec
    optics: Optics
    sensor: dict[str, float]
    stage_zero_error_deg: float
    effects: dict[str, dict[str, float]]
    render: RenderSettings
    raw: dict = field(default_factory=dict, repr=False)

    @property
    def filters(self) -> list[str]:
        return list(self.materials)

    def effect_values(self) -> dict[str, float]:
        """All effect parameters as forward-model names "<effect>.<param>"."""
        return {f"{e}.{k}": v for e, vals in self.effects.items() for k, v in vals.items()}

    def truth_hash(self) -> str:
        """SHA-256 over the canonical truth and render settings (cache key base)."""
        d = {"thickness_mm": self.thickness_mm, "half_width_mm": self.half_width_mm,
             "materials": {f: m.parameters() | {"model": m.model}
                           | ({"table": m.phase_table.key()} if m.phase_table is not None else {})
                           for f, m in self.materials.items()},
             "beam": asdict(self.beam), "optics": asdict(self.optics), "effects": self.effects,
             # (the engine only when not the camera's, so the caches of earlier worlds stay valid)
             "render": {k: v for k, v in asdict(self.render).items()
                        if k != "cache_dir" and not (k == "engine" and v == "camera")
                        and not (k == "mie_phase" and v == "exp")}}
        if self.beam.profile.get("type") == "map":
            d["beam_map_sha"] = hashlib.sha256(Path(self.beam.profile["file"]).read_bytes()).hexdigest()
        return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()


class _R:
    """Typed reader of one mapping with file/key/fix errors."""

    def __init__(self, src: str, data: Any, prefix: str = "") -> None:
        self.src, self.data, self.prefix = src, data, prefix

    def fail(self, key: str, msg: str) -> WorldError:
        return WorldError(f"{self.src}: {self.prefix}{key}: {msg}")

    def section(self, key: str, required: bool = False) -> _R:
        v = self.data.get(key)
        if v is None:
            if required:
                raise self.fail(key, "missing section; see worlds/default.yaml for an example")
            v = {}
        if not isinstance(v, dict):
            raise self.fail(key, f"must be a mapping, got {type(v).__name__}")
        return _R(self.src, v, f"{self.prefix}{key}.")

    def num(self, key: str, default: Any = ..., lo: float = -math.inf, hi: float = math.inf,
            lo_open: bool = False) -> float:
        v = self.data.get(key)
        if v is None:
            if default is ...:
                raise self.fail(key, "missing; add a number")
            return default
        if isinstance(v, str):
            # PyYAML (YAML 1.1) reads 4.0e10 (no exponent sign) as text, not a float
            try:
                v = float(v)
            except ValueError:
                pass
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.fail(key, f"must be a finite number, got {v!r}")
        if v < lo or v > hi or (lo_open and v == lo):
            rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}]"
            raise self.fail(key, f"{v!r} is outside {rng}")
        return float(v)

    def integer(self, key: str, default: int, lo: int = 0) -> int:
        v = self.data.get(key, default)
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            raise self.fail(key, f"must be an integer >= {lo}, got {v!r}")
        return int(v)

    def pair(self, key: str, default: Any) -> tuple[float, float] | None:
        v = self.data.get(key, default)
        if v is None:
            return None
        if (not isinstance(v, (list, tuple)) or len(v) != 2
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
            raise self.fail(key, f"must be [x, y] (two numbers), got {v!r}")
        return float(v[0]), float(v[1])

    def known(self, keys: set[str]) -> None:
        extra = sorted(set(self.data) - keys)
        if extra:
            raise self.fail(extra[0], f"unknown key; known keys here: {', '.join(sorted(keys))}")


def _phase(r: _R, degree: int, mie_phase: str = "exp") -> tuple[str, dict[str, float], TabulatedPhase | None]:
    """Forward-model phase name, parameters and table (None unless a Mie phase is rendered
    from its table) from a world phase mapping."""
    t = r.data.get("type")
    if t not in PHASE_TYPES:
        raise r.fail("type", f"unknown phase type {t!r}; use one of: {', '.join(PHASE_TYPES)}")
    if t == "exp":
        r.known({"type", "b"})
        b = r.data.get("b")
        if (not isinstance(b, list) or not b
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in b)):
            raise r.fail("b", f"must be a non-empty list of numbers [b1, b2, ...], got {b!r}")
        return f"exp{len(b)}", {f"phase.b{i + 1}": float(x) for i, x in enumerate(b)}, None
    if t == "hg":
        r.known({"type", "g"})
        return "hg", {"phase.g": r.num("g", lo=-0.999, hi=0.999)}, None
    if t == "tthg":
        r.known({"type", "g_forward", "g_backward", "w_forward"})
        return "tthg", {"phase.g_forward": r.num("g_forward", lo=-0.999, hi=0.999),
                        "phase.g_backward": r.num("g_backward", lo=-0.999, hi=0.999),
                        "phase.w_forward": r.num("w_forward", lo=0.0, hi=1.0)}, None
    r.known({"type", "dispersion", "diameter_um", "spread", "n_particle", "n_medium", "wavelength_nm"})
    from estimate.errors import EstimateError
    from estimate.mie import MieSettings, mie_mono, mie_poly
    from estimate.phase_fit import fit_model

    disp = r.data.get("dispersion", "mono")
    if disp not in ("mono", "poly"):
        raise r.fail("dispersion", f"unknown value {disp!r}; use mono or poly")
    try:
        settings = MieSettings(wavelength_nm=r.num("wavelength_nm", 600.0),
                               n_particle=r.num("n_particle", 1.377), n_medium=r.num("n_medium", 1.333))
        d = r.num("diameter_um", lo=0.0, lo_open=True)
        table = mie_mono(d, settings) if disp == "mono" else mie_poly(d, r.num("spread", 0.1), settings)
        if mie_phase == "table":
            from estimate.phase_tabulated import TabulatedPhase

            tab = TabulatedPhase.from_table(table)
            return "table", {}, tab
        fit = fit_model(table, f"exp{degree}")
    except EstimateError as e:
        raise r.fail("type", f"Mie phase function: {e}") from None
    if not fit.ok:
        raise r.fail("type", f"cannot fit exp{degree} to this Mie phase function: {fit.message}")
    b = [float(x) for x in fit.params["b"]][1:]
    return f"exp{degree}", {f"phase.b{i + 1}": x for i, x in enumerate(b)}, None


def _effects(r: _R) -> dict[str, dict[str, float]]:
    out: dict[str, dict[str, float]] = {}
    for name in r.data:
        if name not in EXTENSIONS:
            raise r.fail(str(name), f"unknown effect; use one of: {', '.join(EFFECT_NAMES)}")
        er = r.section(name)
        specs = {p.name: p for p in EXTENSIONS[name].parameters}
        er.known(set(specs))
        out[name] = {}
        for pname, spec in specs.items():
            v = er.num(pname, spec.neutral, lo=spec.lower, hi=spec.upper, lo_open=spec.open_lower)
            out[name][pname] = v
    if "sensor_nonlinearity" in out and not out["sensor_nonlinearity"]["compression"] < 1.0 / 3.0:
        raise r.fail("sensor_nonlinearity.compression", "must be < 1/3 (the response must stay monotonic)")
    return out


def parse_world(data: Any, source: str = "<world>", base_dir: Path | None = None) -> World:
    """Validate a world mapping (as read from YAML).

    Raises:
        WorldError: one line naming source, key and fix.
    """
    if not isinstance(data, dict):
        raise WorldError(f"{source}: must be a YAML mapping with sections slab, materials, beam")
    root = _R(source, data)
    root.known({"name", "slab", "materials", "beam", "optics", "sensor", "stage", "effects", "render"})
    rs = root.section("render")
    rs.known(set(RenderSettings.__dataclass_fields__))
    cache = rs.data.get("cache_dir")
    if cache is not None and not isinstance(cache, str):
        raise rs.fail("cache_dir", f"must be a path string, got {cache!r}")
    engine = rs.data.get("engine", "camera")
    if engine not in ("camera", "light"):
        raise rs.fail("engine", f"must be camera or light, got {engine!r}")
    mie_phase = rs.data.get("mie_phase", "exp")
    if mie_phase not in ("exp", "table"):
        raise rs.fail("mie_phase", f"must be exp (the exp<mie_degree> fit) or table (the Mie table itself), "
                                   f"got {mie_phase!r}")
    render = RenderSettings(
        spp_profile=rs.integer("spp_profile", 1024, 1), profile_halfwidth_rows=rs.integer("profile_halfwidth_rows", 2),
        spp_band=rs.integer("spp_band", 32, 1), band_halfwidth_rows=rs.integer("band_halfwidth_rows", 16),
        spp_outside=rs.integer("spp_outside", 1, 0), seed=rs.integer("seed", 1),
        cache_dir=cache, mie_degree=rs.integer("mie_degree", 8, 1), max_depth=rs.integer("max_depth", 64, 1),
        engine=str(engine), mie_phase=str(mie_phase))

    s = root.section("slab", required=True)
    s.known({"thickness_mm", "half_width_mm"})
    thickness = s.num("thickness_mm", lo=0.0, lo_open=True)
    half_width = s.num("half_width_mm", 12.5, lo=0.0, lo_open=True)

    m = root.section("materials", required=True)
    if not m.data:
        raise m.fail("", "needs one entry per filter, e.g. r: {sigma_t: 2.0, albedo: 0.9, phase: {...}}")
    materials = {}
    for f in m.data:
        fr = m.section(str(f))
        fr.known({"sigma_t", "albedo", "phase"})
        ph = fr.section("phase", required=True)
        model, pp, tab = _phase(ph, render.mie_degree, render.mie_phase)
        materials[str(f)] = Material(fr.num("sigma_t", lo=0.0, lo_open=True), fr.num("albedo", lo=0.0, hi=1.0),
                                     dict(ph.data), model, pp, tab)

    b = root.section("beam", required=True)
    b.known({"profile", "offset_mm", "power_e_per_s"})
    p = b.section("profile", required=True)
    kind = p.data.get("type")
    if kind not in BEAM_TYPES:
        raise p.fail("type", f"unknown beam profile {kind!r}; use one of: {', '.join(BEAM_TYPES)}")
    if kind == "gaussian":
        p.known({"type", "sigma_mm"})
        prof: dict = {"type": kind, "sigma_mm": p.num("sigma_mm", lo=0.0, lo_open=True)}
    elif kind == "disk":
        p.known({"type", "radius_mm", "edge_mm"})
        prof = {"type": kind, "radius_mm": p.num("radius_mm", lo=0.0, lo_open=True),
                "edge_mm": p.num("edge_mm", 0.02, lo=0.0, lo_open=True)}
    else:
        p.known({"type", "file", "pitch_mm"})
        fname = p.data.get("file")
        if not isinstance(fname, str):
            raise p.fail("file", "must name a .npy file holding a 2D irradiance map (rows = +y)")
        fpath = Path(fname) if Path(fname).is_absolute() or base_dir is None else base_dir / fname
        try:
            arr = np.load(fpath, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise p.fail("file", f"cannot read {fpath} ({e.__class__.__name__}); give a .npy 2D array") from None
        if arr.ndim != 2 or min(arr.shape) < 2 or not np.all(np.isfinite(arr)) or np.any(arr < 0):
            raise p.fail("file", f"{fpath} must hold a finite, non-negative 2D array of at least 2x2")
        prof = {"type": kind, "file": str(fpath), "pitch_mm": p.num("pitch_mm", lo=0.0, lo_open=True)}
    pw = b.data.get("power_e_per_s")
    if not isinstance(pw, dict):
        raise b.fail("power_e_per_s", "must map every filter to the beam's rate in e-/s, e.g. {r: 4.0e10}")
    power = {}
    pr = b.section("power_e_per_s")
    for f in materials:
        if f not in pw:
            raise pr.fail(f, f"missing; every filter of materials needs a beam power ({', '.join(materials)})")
        power[f] = pr.num(f, lo=0.0, lo_open=True)
    pr.known(set(materials))
    beam = BeamSpec(prof, b.pair("offset_mm", [0.0, 0.0]) or (0.0, 0.0), power)

    o = root.section("optics")
    o.known(set(Optics.__dataclass_fields__))
    mag = o.data.get("magnification")
    optics = Optics(
        magnification=None if mag is None else o.num("magnification", lo=0.0, lo_open=True),
        axis_px=o.pair("axis_px", None),
        collection_sr=o.num("collection_sr", 0.01, lo=0.0, lo_open=True),
        acceptance_sigma_deg=o.num("acceptance_sigma_deg", 0.5, lo=0.0, lo_open=True),
        calibration_nd=o.num("calibration_nd", 1e-3, lo=0.0, hi=1.0, lo_open=True))

    se = root.section("sensor")
    se.known(set(SENSOR_KEYS))
    sensor = {k: se.num(k, lo=0.0, lo_open=k in ("gain_e_per_adu", "full_well_e")) for k in SENSOR_KEYS if k in se.data}

    st = root.section("stage")
    st.known({"zero_error_deg"})
    zero_error = st.num("zero_error_deg", 0.0, lo=-5.0, hi=5.0)

    effects = _effects(root.section("effects"))
    name = data.get("name", Path(source).stem)
    return World(source=source, name=str(name), thickness_mm=thickness, half_width_mm=half_width,
                 materials=materials, beam=beam, optics=optics, sensor=sensor,
                 stage_zero_error_deg=zero_error, effects=effects, render=render, raw=data)


def load_world(path: str | os.PathLike[str] | None = None) -> World:
    """Read and validate a world file (None: the documented default world)."""
    p = Path(path) if path is not None else DEFAULT_WORLD_PATH
    src = str(path) if path is not None else f"{DEFAULT_WORLD_PATH.name} (default world)"
    data = read_yaml(p, src, WorldError, "no such world file; pass an existing WORLD.yaml (see worlds/)")
    return parse_world(data, src, p.parent)


def beam_map(world: World, pitch_mm: float | None = None) -> tuple[np.ndarray, float]:
    """The world's beam irradiance normalised to unit power [1/mm^2] on a centred grid.

    Returns (map [nv, nu] with rows increasing with +v, pitch_mm); the map's middle
    sample sits at the beam's offset from the axis.
    """
    prof = world.beam.profile
    if prof["type"] == "map":
        e = np.load(prof["file"], allow_pickle=False).astype(np.float64)
        pitch = float(prof["pitch_mm"])
    else:
        if prof["type"] == "gaussian":
            size = prof["sigma_mm"]
            extent = 5.0 * size
        else:
            size = prof["radius_mm"]
            extent = size + 6.0 * prof["edge_mm"]
        pitch = pitch_mm or size / 20.0
        n = math.ceil(extent / pitch)
        c = np.arange(-n, n + 1) * pitch
        uu, vv = np.meshgrid(c, c)
        r = np.hypot(uu, vv)
        if prof["type"] == "gaussian":
            e = np.exp(-0.5 * (r / prof["sigma_mm"]) ** 2)
        else:
            # soft edge: a logistic fall-off of width edge_mm around the radius
            e = 1.0 / (1.0 + np.exp(np.clip((r - prof["radius_mm"]) / prof["edge_mm"], -50, 50)))
    total = e.sum() * pitch ** 2
    if not total > 0:
        raise WorldError(f"{world.source}: beam.profile: the beam map has no power")
    return e / total, pitch


def check_filters(world: World, filters: Mapping[str, Any] | list[str]) -> None:
    """Every rig filter needs a material and a beam power in the world."""
    missing = [f for f in filters if f not in world.materials]
    if missing:
        raise WorldError(f"{world.source}: materials: no entry for filter {missing[0]!r} of the rig; "
                         f"add one (the world has {', '.join(world.materials)})")


def write_quick_world(path: str | os.PathLike[str], *, cache_dir: str | os.PathLike[str],
                      spp_profile: int = 16, source: str | os.PathLike[str] | None = None) -> Path:
    """Write a copy of a world (default: the default world) rendered at a few samples per pixel,
    with its render cache in ``cache_dir``: the same physics, noisier and fast. Tests, benchmarks of
    robustness and the quick example use it. Returns ``path``."""
    import yaml

    data = yaml.safe_load(Path(source or DEFAULT_WORLD_PATH).read_text(encoding="utf-8"))
    data.setdefault("render", {}).update(spp_profile=spp_profile, spp_band=4, band_halfwidth_rows=4,
                                         spp_outside=0, cache_dir=str(cache_dir))
    out = Path(path)
    out.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return out
