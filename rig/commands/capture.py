"""``rig capture``: measure a session (stage angles x filters, one HDR stack each).

Order of work, so that bad input never moves anything:

1. check every argument without hardware: filters, angle count and ranges
   (against the configured stage range and filter positions), numbers, the
   calibration file, the output directory (not a session, not a file), or the
   manifest of ``--resume DIR`` (corrupt -> one line, exit 2; a complete
   session -> nothing to do, nothing opened);
2. open the rig (connections and queries only) and check again against what
   the devices report (allowed range, home position, exposure range, sensor);
3. create the session (directory writable, empty, enough free space) or
   resume it (lock, checksums of every completed stack);
4. set the camera ROI to a band of rows around the profile row, cool the CCD,
   then run the plan: home, move, filters, brackets, darks, merges.

Ctrl-C (or a device fault) stops the stage and closes the shutter (the
executor's cleanup); every stack completed so far stays in the session and the
command prints the ``rig capture --resume DIR`` line that continues it.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import importlib
import itertools
import json
import math
import signal
import sys
import time
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

from rig.errors import EXIT_INTERRUPTED

#: Where sessions go when no ``--out`` is given (one time-stamped directory each).
DEFAULT_SESSIONS_DIR = Path("sessions")
#: Rows read around the profile row by default (the KAF-0261E reads 512; a band
#: saves readout time and disk, and still holds the spot's vertical extent).
DEFAULT_BAND_ROWS = 32
#: Nominal slab thickness when none is given, mm (the paper's slabs; recorded in the session).
DEFAULT_THICKNESS_MM = 1.0
#: Longest wait for the CCD to reach its cooler set-point before capturing anyway, s.
DEFAULT_COOL_TIMEOUT_S = 900.0


def register(sub: argparse._SubParsersAction) -> None:
    from capture.bracket import (
        DEFAULT_FIRST_EXPOSURE_S,
        DEFAULT_MAX_EXPOSURE_S,
        BracketPolicy,
    )
    from capture.hdr import MergeOptions
    from capture.plan import AngleSpec

    plan, bracket = AngleSpec(), BracketPolicy()
    p = sub.add_parser(
        "capture",
        help="capture HDR stacks at N stage angles through each filter into a session directory",
        description="Capture a session: N stage angles (front- and back-lighting) x filters, an automatic "
        "exposure bracket with matched darks per stack, merged to float32 OpenEXR. Ctrl-C stops cleanly; "
        "continue with --resume DIR.",
    )
    g = p.add_argument_group("plan")
    g.add_argument("--angles", type=int, metavar="N", help=f"number of stage angles (default {plan.n_angles})")
    g.add_argument("--filters", metavar="LIST", help=f"filters, e.g. rgb or r,g,b (default {''.join(plan.filters)})")
    g.add_argument("--front-angles", type=int, metavar="N", help="how many of the angles light the front (default: half, rounded up)")
    g.add_argument("--front-range", type=float, nargs=2, metavar=("LO", "HI"),
                   help="front-lighting angles, deg (default {:g} {:g})".format(*plan.front_range_deg))
    g.add_argument("--back-range", type=float, nargs=2, metavar=("LO", "HI"),
                   help="back-lighting angles, deg (default {:g} {:g})".format(*plan.back_range_deg))
    g.add_argument("--cone", type=float, metavar="DEG",
                   help=f"half-angle of the camera's cone the plan avoids, deg (default {plan.cone_half_angle_deg:g})")
    b = p.add_argument_group("exposure bracket")
    b.add_argument("--first-exposure", type=float, metavar="S", help=f"first (short) exposure, s (default {DEFAULT_FIRST_EXPOSURE_S:g})")
    b.add_argument("--max-exposure", type=float, metavar="S",
                   help=f"longest exposure, s (default {DEFAULT_MAX_EXPOSURE_S:g} or the camera's longest if shorter)")
    b.add_argument("--max-exposures", type=int, metavar="N", help=f"most light frames per stack (default {bracket.max_exposures})")
    b.add_argument("--target-snr", type=float, metavar="SNR",
                   help=f"SNR the dim profile pixels should reach (default {bracket.target_snr:g})")
    b.add_argument("--darks", type=int, metavar="N", help=f"dark frames per exposure time (default {bracket.n_darks})")
    b.add_argument("--saturation-headroom", type=float, metavar="F",
                   help=f"share of the sensor's range above bias trusted as linear: raw samples above it count as "
                        f"saturated and are left out of the merge (default {MergeOptions.saturation_headroom:g}); "
                        f"lower it for a sensor whose response bends, or whose wells clip at uneven levels, "
                        f"below that (docs/operator-guide.md)")
    r = p.add_argument_group("camera and geometry")
    r.add_argument("--calibration", metavar="CALDIR", help="beam calibration (rig calibrate-beam output); copied into the session")
    r.add_argument("--thickness-mm", type=float, metavar="MM", help=f"nominal slab thickness, mm (default {DEFAULT_THICKNESS_MM:g})")
    r.add_argument("--full-frame", action="store_true", help="read all 512 rows instead of a band around the profile row")
    r.add_argument("--band-rows", type=int, metavar="N", help=f"rows read around the profile row (default {DEFAULT_BAND_ROWS})")
    r.add_argument("--cool-timeout", type=float, default=DEFAULT_COOL_TIMEOUT_S, metavar="S",
                   help="longest wait for the CCD to reach its set-point before capturing anyway, s")
    o = p.add_argument_group("session and rig")
    o.add_argument("--out", metavar="DIR", help="new session directory (default: sessions/<UTC time>)")
    o.add_argument("--resume", metavar="DIR", help="continue an interrupted session (completed stacks are never redone)")
    o.add_argument("--config", metavar="RIG.yaml", help="rig configuration (default: the simulated rig)")
    o.add_argument("--sim", nargs="?", const="", default=None, metavar="WORLD.yaml",
                   help="use the simulated twins; optionally a world file for the rendered bench")
    o.add_argument("--log-io", metavar="FILE", help="write a byte transcript of every device exchange")
    o.add_argument("--json", action="store_true", help="print a JSON summary on stdout (progress goes to stderr)")
    o.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


# --------------------------------------------------------------------------- checks without hardware


@dataclass
class _Request:
    """The checked request (nothing opened yet)."""

    cfg: Any  # rig.config.RigConfig
    spec: Any  # capture.plan.AngleSpec (None when resuming)
    bracket: Any  # capture.bracket.BracketPolicy (None when resuming)
    out: Path
    resume: Any  # capture.session.Session opened read-only, or None
    calibration: Path | None
    beam_center_px: tuple[float, float] | None
    stage_offset_deg: float  # stage angle - world angle: the calibration's rotation_zero_deg - 180
    thickness_mm: float
    band_rows: int | None  # None: full frame
    sim: bool
    world: str | None
    #: MergeOptions.saturation_headroom: --saturation-headroom (or the default) for a new
    #: session; a resumed one's is that of the saturation level its noise model recorded
    saturation_headroom: float


def _usage(msg: str) -> Exception:
    from rig.errors import UsageError

    return UsageError(msg)


def _positive(name: str, value: float | None) -> None:
    if value is not None and not (math.isfinite(value) and value > 0):
        raise _usage(f"{name} must be a positive number, got {value:g}")


def _read_calibration(path: str, filters: tuple[str, ...] = ()) -> tuple[Path, tuple[float, float], float]:
    """The calibration source (directory or calibration.yaml), its beam centre ``beam.center_px``
    [x, y] in pixels, and the stage offset ``rotation_zero_deg - 180`` (degrees). Each of
    ``filters`` must have its beam map there (``rig estimate`` needs it)."""
    import yaml

    from capture.plan import MAX_STAGE_OFFSET_DEG
    from capture.session import CALIBRATION_MAIN

    src = Path(path)
    main = src / CALIBRATION_MAIN if src.is_dir() else src
    if not main.is_file():
        raise _usage(f"--calibration {path}: no {CALIBRATION_MAIN} there; pass the directory 'rig calibrate-beam' wrote")
    try:
        data = yaml.safe_load(main.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as e:
        raise _usage(f"--calibration {main}: unreadable ({' '.join(str(e).split())[:200]})") from None
    centre = (data.get("beam") or {}).get("center_px") if isinstance(data, dict) and isinstance(data.get("beam"), dict) else None
    if (not isinstance(centre, (list, tuple)) or len(centre) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in centre)):
        raise _usage(f"--calibration {main}: beam.center_px must be [x, y] in pixels, got {centre!r}")
    zero = data.get("rotation_zero_deg")
    if isinstance(zero, bool) or not isinstance(zero, (int, float)) or not math.isfinite(zero) \
            or abs(zero - 180.0) > MAX_STAGE_OFFSET_DEG:
        raise _usage(f"--calibration {main}: rotation_zero_deg must be the stage angle of the beam into the lens "
                     f"(within {MAX_STAGE_OFFSET_DEG:g} deg of 180), got {zero!r}; rerun rig calibrate-beam")
    maps = data["beam"].get("filters")
    for f in filters if isinstance(maps, dict) and maps else ():  # a calibration with beam maps: one per filter
        entry = maps.get(f)
        if not isinstance(entry, dict) or not (main.parent / str(entry.get("map"))).is_file():
            raise _usage(f"--calibration {main}: no beam map for filter {f!r}, which rig estimate needs; "
                         f"calibrate it too (rig calibrate-beam --filters ...) or leave it out of --filters")
    return src, (float(centre[0]), float(centre[1])), float(zero) - 180.0


def _default_out() -> Path:
    stamp = _dt.datetime.now(_dt.UTC).strftime("%Y%m%d-%H%M%SZ")
    out = DEFAULT_SESSIONS_DIR / stamp
    k = 2
    while out.exists():
        out = DEFAULT_SESSIONS_DIR / f"{stamp}-{k}"
        k += 1
    return out


def _check_out_dir(out: Path) -> None:
    """Cheap checks before opening anything; Session.create repeats them with a write probe and the space check."""
    from capture.session import MANIFEST_NAME

    if out.exists() and not out.is_dir():
        raise _usage(f"--out {out} exists and is not a directory")
    if (out / MANIFEST_NAME).exists():
        raise _usage(f"{out} already holds a session; continue it with --resume {out} or choose a new directory")
    existing = out
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise _usage(f"cannot create {out}: {existing} is not a directory")


def _check(args: argparse.Namespace) -> _Request:
    from capture.bracket import DEFAULT_FIRST_EXPOSURE_S, BracketPolicy
    from capture.hdr import MergeOptions, headroom_of
    from capture.plan import AngleSpec, make_plan
    from capture.session import Session
    from drivers.interfaces import AngleRange
    from rig import wiring
    from rig.config import load_config
    from rig.name_lists import chosen_names

    cfg = load_config(args.config)
    sim = args.sim is not None
    world = (args.sim or cfg.sim.world) if sim else None
    for name in ("first_exposure", "max_exposure", "target_snr", "thickness_mm", "cool_timeout"):
        _positive("--" + name.replace("_", "-"), getattr(args, name))
    for name in ("max_exposures", "darks", "band_rows"):
        v = getattr(args, name)
        if v is not None and v < 1:
            raise _usage(f"--{name.replace('_', '-')} must be >= 1, got {v}")
    h = args.saturation_headroom
    if h is not None and not (math.isfinite(h) and 0.0 < h <= 1.0):
        raise _usage(f"--saturation-headroom must lie in (0, 1] (a share of the sensor's range above bias), got {h:g}")
    if args.full_frame and args.band_rows is not None:
        raise _usage("--full-frame and --band-rows exclude each other")
    wiring.check_log_io(args.log_io)

    if args.resume:
        if args.out:
            raise _usage("--out and --resume exclude each other (the session stays where it is)")
        plan_opts = ("angles", "filters", "front_angles", "front_range", "back_range", "cone", "first_exposure",
                     "max_exposure", "max_exposures", "target_snr", "darks", "calibration", "thickness_mm", "band_rows",
                     "saturation_headroom")
        given = [o for o in plan_opts if getattr(args, o) is not None] + (["full_frame"] if args.full_frame else [])
        if given:
            raise _usage(f"--resume continues the session's own plan; drop --{given[0].replace('_', '-')}")
        session = Session.open(args.resume)  # corrupt or missing manifest: SessionError, exit 2
        stage_range = AngleRange(*cfg.stage.allowed_range_deg)
        sp = session.plan
        outside = [a for i, a in enumerate(sp.angles_deg) if sp.stage_angle(i) not in stage_range]
        if outside:
            raise _usage(f"angle {outside[0]:g} deg of {args.resume} (stage angle "
                         f"{outside[0] + sp.stage_offset_deg:g} deg) is outside the stage's allowed range "
                         f"[{stage_range.lo:g}, {stage_range.hi:g}] deg of {cfg.path}")
        unknown = [f for f in session.plan.filters if f not in cfg.filter.positions]
        if unknown:
            raise _usage(f"filter {unknown[0]!r} of {args.resume} is not configured in {cfg.path}")
        # The merge records the headroom its saturation level stands for: the session's.
        sess_noise, sess_sensor = session.noise_model(), session.sensor()
        kept = (headroom_of(sess_noise, sess_sensor) if sess_noise is not None and sess_sensor is not None
                else MergeOptions.saturation_headroom)
        return _Request(cfg, None, None, session.path, session, None, None, sp.stage_offset_deg, 0.0, None, sim, world,
                        kept)

    defaults = AngleSpec()
    named = chosen_names("--filters", args.filters, list(cfg.filter.positions), what="filter",
                         where=f"the configuration {cfg.path}")
    spec = AngleSpec(
        n_angles=args.angles if args.angles is not None else defaults.n_angles,
        filters=tuple(named) if named is not None else defaults.filters,
        n_front=args.front_angles,
        front_range_deg=tuple(args.front_range) if args.front_range else defaults.front_range_deg,  # type: ignore[arg-type]
        back_range_deg=tuple(args.back_range) if args.back_range else defaults.back_range_deg,  # type: ignore[arg-type]
        cone_half_angle_deg=args.cone if args.cone is not None else defaults.cone_half_angle_deg,
    )
    chosen = {"first_exposure_s": args.first_exposure if args.first_exposure is not None else DEFAULT_FIRST_EXPOSURE_S,
              "max_exposure_s": args.max_exposure, "max_exposures": args.max_exposures,
              "target_snr": args.target_snr, "n_darks": args.darks}
    bracket = replace(BracketPolicy(), **{k: v for k, v in chosen.items() if v is not None})
    # (a filter the rig lacks is make_plan's to name)
    known = tuple(f for f in spec.filters if f in cfg.filter.positions)
    calibration, centre, offset = _read_calibration(args.calibration, known) if args.calibration else (None, None, 0.0)
    # the plan (its stage angles) against the configured range and filters: errors before anything opens
    make_plan(spec, available_filters=list(cfg.filter.positions), stage_range=AngleRange(*cfg.stage.allowed_range_deg),
              bracket=bracket, exposure_range_s=None, stage_offset_deg=offset)
    out = Path(args.out) if args.out else _default_out()
    _check_out_dir(out)
    thickness = args.thickness_mm if args.thickness_mm is not None else DEFAULT_THICKNESS_MM
    band = None if args.full_frame else (args.band_rows or DEFAULT_BAND_ROWS)
    return _Request(cfg, spec, bracket, out, None, calibration, centre, offset, thickness, band, sim, world,
                    MergeOptions.saturation_headroom if h is None else h)


# --------------------------------------------------------------------------- with the rig


def _install_scene(cfg: Any, world: str | None) -> tuple[str, Any]:
    """Put the simulated world on the bench before the twins open; returns (what the camera
    sees, the scene for ``open_rig``).

    ``rig.simbench.install_world`` (the rendered bench; a bad world file is a one-line
    UsageError) is used when it is installed; without it the bench keeps the analytic
    spot of :mod:`sim_devices.bench`, which cannot honour a world file.
    """
    try:
        simbench = importlib.import_module("rig.simbench")
    except ModuleNotFoundError as e:
        if e.name != "rig.simbench":
            raise
        if world:
            raise _usage(f"--sim {world}: this installation has no rendered bench (rig/simbench.py); use --sim alone") from None
        return "analytic spot (sim_devices.bench)", None
    installed = simbench.install_world(cfg, world or None)
    return f"rendered world {getattr(installed, 'name', '') or ''}".strip(), installed.scene


def _profile_row(req: _Request, sensor: Any) -> tuple[int, str]:
    """Sensor row (unbinned) through the scattering spot, and where it came from."""
    if req.beam_center_px is not None:
        x, y = req.beam_center_px
        if not (0 <= x < sensor.width and 0 <= y < sensor.height):
            raise _usage(f"--calibration: beam centre ({x:g}, {y:g}) px lies outside the {sensor.width}x{sensor.height} sensor")
        return round(y), "calibration beam.center_px"
    if req.cfg.camera.profile_row is not None:
        row = req.cfg.camera.profile_row
        if not 0 <= row < sensor.height:
            raise _usage(f"{req.cfg.path}: camera.profile_row {row} outside the sensor's {sensor.height} rows")
        return int(row), "rig.yaml camera.profile_row"
    return sensor.height // 2, "sensor centre"


def _band_roi(row: int, band: int | None, sensor: Any) -> Any:
    from drivers.interfaces import ROI

    if band is None:
        return ROI(0, 0, sensor.width, sensor.height)
    if band > sensor.height:
        raise _usage(f"--band-rows {band} exceeds the sensor's {sensor.height} rows (use --full-frame)")
    y0 = min(max(row - band // 2, 0), sensor.height - band)
    return ROI(0, y0, sensor.width, band)


def _check_with_devices(rig: Any, plan_angles: tuple[float, ...]) -> None:
    """What only the opened devices can tell: home inside the allowed range, angles a stage count apart."""
    from capture.errors import PlanError

    stage = rig.stage
    home = stage.home_angle()
    rng = stage.allowed_range
    if home not in rng:
        raise _usage(f"the stage's home ({home:g} deg) lies outside its allowed range [{rng.lo:g}, {rng.hi:g}] deg; "
                     "fix zero_offset_deg or allowed_range_deg in rig.yaml")
    step = getattr(stage, "degrees_per_count", None)
    if step:
        ordered = sorted(plan_angles)
        gaps = [b - a for a, b in itertools.pairwise(ordered)]
        if gaps and min(gaps) < step:
            raise PlanError(f"{len(plan_angles)} angles are too many for the ranges: neighbours {min(gaps):.2g} deg apart, "
                            f"finer than the stage's step of {step:g} deg")


def _cool(camera: Any, setpoint_c: float, timeout_s: float, say: Any) -> None:
    """Switch the cooler on and wait (real seconds) until the CCD is at its set-point."""
    camera.set_cooler(setpoint_c, on=True)
    deadline = time.monotonic() + timeout_s
    st = camera.cooler_status()
    if not st.at_temperature:
        say(f"cooling the CCD to {setpoint_c:g} C (now {st.temperature_c:.1f} C)")
    while not st.at_temperature:
        if time.monotonic() > deadline:
            say(f"warning: CCD at {st.temperature_c:.1f} C, not at its {setpoint_c:g} C set-point after {timeout_s:g} s; "
                "capturing anyway (darks are matched per stack)")
            return
        time.sleep(0.05)
        st = camera.cooler_status()


def _rig_snapshot(cfg: Any) -> dict[str, Any]:
    """The configuration as loaded, without the simulated world's file (its truth stays out of sessions)."""
    snap = json.loads(json.dumps(cfg.raw, default=str))
    if isinstance(snap.get("sim"), dict):
        snap["sim"].pop("world", None)
    return {"source": cfg.path, **snap}


def _resume_hint(args: argparse.Namespace, path: Path) -> str:
    parts = ["rig capture --resume", str(path)]
    if args.config:
        parts += ["--config", args.config]
    if args.sim is not None:
        parts += ["--sim"] + ([args.sim] if args.sim else [])
    return " ".join(parts)


def run(args: argparse.Namespace) -> int:
    req = _check(args)
    if req.resume is not None and req.resume.complete:
        s = req.resume.summary()
        if args.json:
            print(json.dumps({**s, "completed": [], "skipped": [r.id for r in req.resume.stacks()], "elapsed_s": 0.0}, indent=2))
        else:
            print(f"{req.out}: all {s['stacks_total']} stacks are complete; nothing to do")
        return 0

    # a service manager's SIGTERM stops a capture as cleanly as Ctrl-C (stage stopped, shutter closed)
    previous = {sig: signal.signal(sig, _raise_interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    _SIGNALS.clear()
    try:
        return _run_checked(args, req)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


#: Signals received during this capture (see _raise_interrupt).
_SIGNALS: list[int] = []


def _raise_interrupt(signum: int, frame: Any) -> None:
    _SIGNALS.append(signum)
    raise KeyboardInterrupt


def _run_checked(args: argparse.Namespace, req: _Request) -> int:
    from capture.errors import CaptureError
    from capture.executor import run_capture
    from capture.hdr import MergeOptions, NoiseModel
    from capture.plan import make_plan
    from capture.session import Session
    from drivers.errors import DeviceError
    from drivers.interfaces import ROI
    from rig import wiring

    err = sys.stderr

    def say(msg: str) -> None:
        print(msg, file=err)

    uses_sim = req.sim or wiring.config_is_simulated(req.cfg)
    scene, scene_fn = _install_scene(req.cfg, req.world) if uses_sim else (None, None)
    rig = wiring.open_rig(req.cfg, sim=req.sim, log_io=args.log_io, scene=scene_fn)
    session = None
    try:
        cam, stage, changer = rig.camera, rig.stage, rig.changer
        sensor = cam.sensor
        devices = {"stage": stage.identity(), "camera": cam.identity(), "filter": changer.identity()}
        merge = MergeOptions(saturation_headroom=req.saturation_headroom)
        if req.resume is None:
            row, row_source = _profile_row(req, sensor)
            roi = _band_roi(row, req.band_rows, sensor)
            frame_row = (row - roi.y) // roi.bin_y
            plan = make_plan(req.spec, available_filters=changer.names(), stage_range=stage.allowed_range,
                             bracket=replace(req.bracket, profile_row=frame_row), exposure_range_s=cam.exposure_range_s,
                             stage_offset_deg=req.stage_offset_deg)
            _check_with_devices(rig, plan.angles_deg)
            mag = req.cfg.camera.magnification
            geometry = {
                "thickness_mm": req.thickness_mm,
                "magnification": mag,
                # telecentric: one sensor pixel covers pitch / magnification of the slab's face
                "pixel_pitch_mm": sensor.pixel_size_um * 1e-3 / mag * roi.bin_x,
                "pixel_pitch_y_mm": sensor.pixel_size_um * 1e-3 / mag * roi.bin_y,
                "profile_row": row,
                "profile_row_in_frame": frame_row,
                "profile_row_source": row_source,
                "beam_center_px": list(req.beam_center_px) if req.beam_center_px else None,
                "camera_roi": {f.name: getattr(roi, f.name) for f in fields(ROI)},
            }
            noise = NoiseModel.from_sensor(sensor, headroom=merge.saturation_headroom)
            extra = {"command": "rig capture", "simulated": rig.simulated,
                     "options": {"band_rows": req.band_rows, "full_frame": req.band_rows is None}}
            declared = getattr(scene_fn, "render_noise", None)
            if callable(declared):
                # The rendered world's frozen Monte Carlo noise, which the HDR variance does
                # not hold and which is correlated along a row with the light engine
                # (sim_devices.rendered_scene.RenderedScene.render_noise).
                extra["render_noise"] = declared()
            cam.set_roi(roi)
            session = Session.create(req.out, plan=plan, frame_shape=roi.shape, rig_config=_rig_snapshot(req.cfg),
                                     devices=devices, sensor=sensor, noise=noise, geometry=geometry,
                                     calibration=req.calibration, extra=extra)
        else:
            geo = req.resume.geometry()
            roi = ROI(**geo["camera_roi"]) if geo.get("camera_roi") else ROI(0, 0, sensor.width, sensor.height)
            _check_with_devices(rig, req.resume.plan.angles_deg)
            plan = req.resume.plan
            bad = [f for f in plan.filters if f not in changer.names()]
            if bad:
                raise _usage(f"filter {bad[0]!r} of the session is not on the filter changer")
            cam.set_roi(roi)
            session = Session.resume(req.out, devices=devices)
            noise = None  # the session's own
            for kind, ident in devices.items():
                was = session.devices.get(kind)
                if was is not None and was != ident:
                    say(f"note: the {kind} is now '{ident}'; the session began with '{was}' (both are recorded)")
        total = len(plan.keys())
        done_before = total - len(session.pending_keys())
        if not args.json:
            what = "resuming" if req.resume is not None else "capturing"
            print(f"{what} {session.path}: {len(plan.angles_deg)} angles x {len(plan.filters)} filters, "
                  f"{done_before}/{total} stacks done{f'; scene: {scene}' if scene else ''}", file=err)
            if plan.stage_offset_deg:
                print(f"stage angles = world angles {plan.stage_offset_deg:+.4f} deg (the calibrated rotation zero)",
                      file=err)
            elif req.calibration is None and req.resume is None:
                print("note: no --calibration: the stage angles are taken as world angles (the rotation zero is "
                      "unknown; rig estimate needs a calibration anyway)", file=err)
        _cool(cam, req.cfg.camera.cooler_setpoint_c, args.cool_timeout, say)
        progress: Any = False
        if not args.no_progress:
            if args.json:
                from rich.console import Console

                progress = Console(stderr=True)
            else:
                progress = True
        summary = run_capture(session, stage, cam, changer, progress=progress, noise=noise, merge=merge)
    except BaseException as e:
        if session is None:
            raise
        total = len(session.plan.keys())
        done = total - len(session.pending_keys())
        where = f"{done}/{total} stacks saved in {session.path}; continue with: {_resume_hint(args, session.path)}"
        # a library may wrap the KeyboardInterrupt our handler raised (drjit turns it into a
        # RuntimeError inside a render of the simulated bench): the signal decides, not the type
        if isinstance(e, KeyboardInterrupt) or (_SIGNALS and isinstance(e, Exception)):
            print(f"rig capture: interrupted; {where}", file=err)
            return EXIT_INTERRUPTED
        if isinstance(e, (DeviceError, CaptureError)):
            notes = "".join(f" ({' '.join(n.split())})" for n in getattr(e, "__notes__", []))
            print(f"rig capture: error: {' '.join(str(e).split())}{notes}; {where}", file=err)
            return 3 if isinstance(e, DeviceError) else 2
        raise
    finally:
        if session is not None:
            session.close()
        rig.close()

    s = session.summary()
    if args.json:
        print(json.dumps({**s, **summary.to_dict(), "path": str(session.path), "scene": scene}, indent=2))
    else:
        low = [st for st in summary.stacks if st.get("min_snr", 0.0) < plan.bracket.target_snr]
        print(f"{session.path}: {s['stacks_done']}/{s['stacks_total']} stacks complete "
              f"({len(summary.completed)} captured now) in {summary.elapsed_s:.1f} s")
        if low:
            worst = min(low, key=lambda st: st["min_snr"])
            print(f"note: {len(low)} stack(s) stopped below the target SNR {plan.bracket.target_snr:g} "
                  f"(lowest {worst['min_snr']:.1f} in {worst['id']}: {worst['reason']})")
    return 0

