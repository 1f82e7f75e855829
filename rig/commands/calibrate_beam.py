"""``rig calibrate-beam``: rotation zero, beam centre, 2D profile, widths and relative power per filter."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calibrate-beam", help="calibrate the beam (slab removed): rotation zero, centre, "
                                              "profile and power per filter")
    p.add_argument("--filters", default=None, metavar="rgb",
                   help="filters to calibrate: letters (rgb) or comma-separated names (default: all configured)")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="new or empty calibration directory (default: calibration-<UTC time>)")
    p.add_argument("--sim", nargs="?", const="", default=None, metavar="WORLD.yaml",
                   help="use the simulated rig; optionally with a world file (default world otherwise)")
    p.add_argument("--config", metavar="RIG.yaml", help="rig configuration (default: the simulated rig)")
    p.add_argument("--log-io", metavar="FILE", help="write a byte transcript of every device exchange")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.set_defaults(func=run)


def parse_filters(text: str | None, known: list[str], where: str = "") -> tuple[str, ...]:
    """'rgb' / 'r,g,b' -> ('r', 'g', 'b'); None -> every configured filter.

    Raises:
        UsageError: a list naming nothing, or an unknown or repeated filter name.
    """
    from rig.name_lists import chosen_names

    names = chosen_names("--filters", text, known, what="filter", where=where)
    return tuple(known) if names is None else tuple(names)


def run(args: argparse.Namespace) -> int:
    import datetime as dt

    from calibrate.beam import BeamCalibrationSettings, calibrate_beam, check_output_dir
    from capture.session import software_version
    from rig import wiring
    from rig.config import load_config
    from rig.errors import UsageError

    cfg = load_config(args.config)
    filters = parse_filters(args.filters, list(cfg.filter.positions), f"the configuration {cfg.path}")
    out = args.out or f"calibration-{dt.datetime.now(dt.UTC).strftime('%Y%m%dT%H%M%SZ')}"
    sim = args.sim is not None or wiring.config_is_simulated(cfg)
    scene = None
    if sim:
        from rig.simbench import SimOperator, install_world

        installed = install_world(cfg, args.sim or None)
        operator: Any = SimOperator(installed)
        scene = installed.scene
    else:
        if not sys.stdin.isatty():
            raise UsageError("calibrate-beam asks the operator to remove the slab; run it at a terminal "
                             "(or use --sim)")
        from rig.simbench import TerminalOperator

        operator = TerminalOperator()
    wiring.check_log_io(args.log_io)
    check_output_dir(out)  # before any device is opened or moved
    settings = BeamCalibrationSettings(
        filters=filters,
        pixel_pitch_mm=0.020 / cfg.camera.magnification,
        stage_resolution_deg=cfg.stage.degrees_per_pulse / max(1, cfg.stage.division),
    )
    quiet = bool(args.json)

    def progress(msg: str) -> None:
        if not quiet:
            print(f"  {msg}", file=sys.stderr)

    with wiring.open_rig(cfg, sim=sim, log_io=args.log_io, scene=scene) as rig:
        devices = {"stage": rig.stage.identity(), "camera": rig.camera.identity(),
                   "filter": rig.changer.identity()}
        rig.stage.home()
        doc = calibrate_beam(rig.stage, rig.camera, rig.changer, out, settings, operator,
                             devices=devices, software=f"rig {software_version()}", progress=progress)
    beam = doc["beam"]
    summary = {
        "calibration": str(out),
        "rotation_zero_deg": doc["rotation_zero_deg"],
        "rotation_zero_uncertainty_deg": doc["rotation_zero_uncertainty_deg"],
        "center_px": beam["center_px"],
        "filters": {f: {"width_mm": v["width_mm"], "relative_power": v["relative_power"],
                        "power_e_per_s": v["power_e_per_s"]} for f, v in beam["filters"].items()},
    }
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(f"calibration written to {out}")
    print(f"rotation zero: {doc['rotation_zero_deg']:.4f} +- {doc['rotation_zero_uncertainty_deg']:.4f} deg "
          "(stage angle of the beam straight into the lens)")
    print(f"beam centre:   ({beam['center_px'][0]:.2f}, {beam['center_px'][1]:.2f}) px")
    for f, v in beam["filters"].items():
        print(f"  {f}: width {v['width_mm'][0]:.4f} x {v['width_mm'][1]:.4f} mm (1 sigma), "
              f"relative power {v['relative_power']:.4f}, {v['power_e_per_s']:.4g} e-/s")
    return 0
