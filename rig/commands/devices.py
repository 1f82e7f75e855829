"""``rig devices``: find and probe every configured device through its protocol."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from typing import Any


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("devices", help="probe the configured stage, camera and filter changer")
    p.add_argument("--config", metavar="RIG.yaml", help="rig configuration (default: the simulated rig)")
    p.add_argument("--sim", action="store_true", help="use the simulated twins whatever the ports say")
    p.add_argument("--log-io", metavar="FILE", help="write a byte transcript of every exchange")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--scan", action="store_true",
                   help="list serial ports and known USB devices and suggest rig.yaml entries (sends no bytes)")
    p.set_defaults(func=run)


def _scan(args: argparse.Namespace) -> int:
    from rig import discovery
    from rig.config import load_config

    base = load_config(args.config)  # settings other than ports come from it
    result = discovery.scan()
    suggestion = discovery.suggest_config(result, base)
    if args.json:
        print(json.dumps({"scan": result.to_dict(), "suggested_config": suggestion}, indent=2))
    else:
        print("\n".join(discovery.format_scan(result)))
        print("\nsuggested rig.yaml entries:")
        print(suggestion, end="")
    return 0


def _probe(name: str, opener: Callable[[], Any], describe: Callable[[Any], dict]) -> dict:
    from drivers.errors import DeviceError

    try:
        dev = opener()
    except DeviceError as e:
        return {"device": name, "ok": False, "error": str(e)}
    try:
        return {"device": name, "ok": True, **describe(dev)}
    except DeviceError as e:
        return {"device": name, "ok": False, "error": str(e)}
    finally:
        dev.close()


def run(args: argparse.Namespace) -> int:
    if args.scan:
        return _scan(args)
    from rig import wiring
    from rig.config import load_config

    cfg = load_config(args.config)
    sim = bool(args.sim)
    if sim or wiring.config_is_simulated(cfg):
        wiring.prepare_bench(cfg)
    tr = wiring.open_transcript(args.log_io)
    # the camera is simulated when the serial devices are (a simulated rig has no USB camera)
    cam_sim = sim or wiring.config_is_simulated(cfg)

    def stage_info(s: Any) -> dict:
        r = s.allowed_range
        return {"identity": s.identity(), "angle_deg": round(s.angle(), 4), "busy": s.is_busy(),
                "allowed_range_deg": [r.lo, r.hi], "speed_deg_s": s.speed()}

    def camera_info(c: Any) -> dict:
        st = c.cooler_status()
        return {"identity": c.identity(), "sensor": f"{c.sensor.model} {c.sensor.width}x{c.sensor.height} "
                f"{c.sensor.pixel_size_um} um", "ccd_temp_c": round(st.temperature_c, 2),
                "cooler_on": st.on, "setpoint_c": st.setpoint_c}

    def changer_info(f: Any) -> dict:
        return {"identity": f.identity(), "current": f.current(), "positions": f.positions}

    results = [
        _probe("stage", lambda: wiring.open_stage(cfg, sim=sim, transcript=tr), stage_info),
        _probe("camera", lambda: wiring.open_camera(cfg, sim=cam_sim, transcript=tr), camera_info),
        _probe("filter", lambda: wiring.open_changer(cfg, sim=sim, transcript=tr), changer_info),
    ]
    if tr is not None:
        tr.close()
    if args.json:
        print(json.dumps({"config": cfg.path, "simulated": cam_sim, "devices": results}, indent=2))
    else:
        print(f"config: {cfg.path}{'  (simulated twins)' if cam_sim else ''}")
        for r in results:
            if r["ok"]:
                rest = ", ".join(f"{k}={v}" for k, v in r.items() if k not in ("device", "ok", "identity"))
                print(f"  {r['device']:<7} OK    {r['identity']}  [{rest}]")
            else:
                print(f"  {r['device']:<7} FAIL  {r['error']}")
    return 0 if all(r["ok"] for r in results) else 3
