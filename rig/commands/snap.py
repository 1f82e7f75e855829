"""``rig snap``: first light — point the beam, pick a filter, take frames and keep them."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("snap", help="move the stage, select a filter and take raw frames (first light)")
    p.add_argument("--config", metavar="RIG.yaml", help="rig configuration (default: the simulated rig)")
    p.add_argument("--sim", nargs="?", const="", default=None, metavar="WORLD.yaml",
                   help="use the simulated rig; optionally with a world file (default world otherwise)")
    p.add_argument("--angle", type=float, help="stage angle in degrees (default: stay where it is)")
    p.add_argument("--filter", help="filter name (default: leave the filter in place)")
    p.add_argument("--exposure", type=float, default=0.01, help="exposure time in seconds (default 0.01)")
    p.add_argument("--count", type=int, default=1, help="number of frames (default 1)")
    p.add_argument("--dark", action="store_true", help="keep the shutter closed (dark frames)")
    p.add_argument("--out", required=True, metavar="FILE.npz", help="where to keep the raw frames (must not exist)")
    p.add_argument("--log-io", metavar="FILE", help="write a byte transcript of every exchange")
    p.add_argument("--json", action="store_true", help="print frame statistics as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from capture.exr_io import write_frames
    from rig.config import load_config
    from rig.errors import UsageError
    from rig.wiring import config_is_simulated, open_rig

    out = Path(args.out)
    if out.suffix != ".npz":
        raise UsageError(f"--out {out}: raw frames are kept as .npz; give a name ending in .npz")
    if out.exists():
        raise UsageError(f"--out {out}: exists; frames are never overwritten, choose a new name")
    if not out.parent.exists():
        raise UsageError(f"--out {out}: folder {out.parent} does not exist; create it first")
    if args.count < 1:
        raise UsageError(f"--count {args.count}: must be at least 1")
    if not (math.isfinite(args.exposure) and args.exposure > 0):
        raise UsageError(f"--exposure {args.exposure:g}: give a positive exposure time in seconds, e.g. 0.01")
    cfg = load_config(args.config)
    if args.filter is not None and args.filter not in cfg.filter.positions:
        raise UsageError(f"--filter {args.filter!r}: unknown; configured filters: {', '.join(cfg.filter.positions)}")
    lo, hi = cfg.stage.allowed_range_deg
    if args.angle is not None and not (math.isfinite(args.angle) and lo <= args.angle <= hi):
        raise UsageError(f"--angle {args.angle:g}: outside the stage's allowed range [{lo:g}, {hi:g}] deg "
                         f"(allowed_range_deg in {cfg.path})")

    sim = args.sim is not None
    scene = None
    if sim or config_is_simulated(cfg):
        from rig.simbench import install_world

        scene = install_world(cfg, args.sim or None).scene
    with open_rig(cfg, sim=sim, log_io=args.log_io, scene=scene) as rig:
        # The camera's exposure range is known once it is open (the Alta reports its own).
        elo, ehi = rig.camera.exposure_range_s
        if not elo <= args.exposure <= ehi:
            raise UsageError(f"--exposure {args.exposure:g}: outside this camera's range [{elo:g}, {ehi:g}] s; "
                             "give an exposure inside it")
        try:
            if args.angle is not None:
                rig.stage.move_to(args.angle)
            if args.filter is not None:
                rig.changer.select(args.filter)
            frames = [rig.camera.expose(args.exposure, dark=args.dark) for _ in range(args.count)]
        finally:
            rig.stage.stop()
            rig.camera.set_shutter("closed")
        angle = rig.stage.angle()
        current = rig.changer.current()
    write_frames(out, frames)
    stats = []
    for fr in frames:
        d = fr.data.astype(np.float64)
        stats.append({"min": int(d.min()), "max": int(d.max()), "mean": round(float(d.mean()), 2),
                      "saturated": int((fr.data >= rig.camera.sensor.adc_max).sum()),
                      "ccd_temp_c": round(fr.ccd_temp_c, 2)})
    summary = {"out": str(out), "angle_deg": round(angle, 4), "filter": current,
               "exposure_s": frames[0].exposure_s, "dark": args.dark, "shape": list(frames[0].data.shape),
               "frames": stats}
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(f"{len(frames)} frame(s) {summary['shape'][1]}x{summary['shape'][0]} at {summary['angle_deg']} deg, "
              f"filter {current}, {frames[0].exposure_s:g} s{' dark' if args.dark else ''} -> {out}")
        for i, s in enumerate(stats):
            print(f"  frame {i}: min {s['min']} max {s['max']} mean {s['mean']} ADU, "
                  f"{s['saturated']} saturated, CCD {s['ccd_temp_c']} C")
    return 0
