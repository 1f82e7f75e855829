"""``rig info DIR``: what a session holds, and whether its files are intact.

Prints the plan, progress, devices, geometry and calibration of a session and
checks every recorded file against its SHA-256 in the manifest. Exit codes:
0 sound (complete or not), 1 a file is missing or corrupt (each named on
stderr), 2 no session there or its manifest is corrupt.
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import json
import os
import sys
from pathlib import Path
from typing import Any

#: Exit status when a recorded file fails its checksum (2 stays "bad input").
EXIT_CORRUPT = 1


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("info", help="summarise a session and verify its checksums",
                       description="Summarise a session directory and verify every file against the manifest's "
                       "checksums (exit 1 naming each missing or corrupt file).")
    p.add_argument("dir", metavar="DIR", help="session directory (rig capture --out)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run)


def _capture_running(path: Path) -> bool:
    """True while a capture holds the session's lock (flock, freed when that process ends)."""
    from capture.session import LOCK_NAME

    lock = path / LOCK_NAME
    if not lock.is_file():
        return False
    try:
        fd = os.open(lock, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return False
    finally:
        with contextlib.suppress(OSError):
            os.close(fd)
    return False


def describe(session: Any) -> dict[str, Any]:
    """Everything ``rig info`` reports about an open session (JSON-safe)."""
    m = session.manifest
    plan = session.plan
    stacks = []
    for rec in session.stacks():
        b = (rec.info or {}).get("bracket") or {}
        stacks.append({
            "id": rec.id, "angle_deg": rec.angle_deg, "filter": rec.key.filter, "state": rec.state,
            "completed": rec.completed, "exposures": len(b.get("exposures_s") or []),
            "longest_exposure_s": max(b.get("exposures_s") or [0.0]),
            "min_snr": b.get("min_snr"), "peak_unsaturated": b.get("peak_unsaturated"), "reason": b.get("reason"),
        })
    cal = m.get("calibration")
    calibration = None
    if cal:
        calibration = {"source": cal.get("source"), "attached": cal.get("attached"), "files": sorted(cal.get("files") or {})}
        try:
            beam = (session.load_calibration().get("beam") or {})
            calibration["beam_center_px"] = beam.get("center_px")
        except Exception as e:  # noqa: BLE001 - reported, not fatal: the checksums say more
            calibration["error"] = " ".join(str(e).split())
    pending = [s["id"] for s in stacks if s["state"] != "done"]
    return {
        **session.summary(),
        "n_front": plan.n_front,
        "bracket": plan.bracket.to_dict(),
        "frame_shape": m.get("frame_shape"),
        "geometry": session.geometry(),
        "resumed": len(m.get("resumed") or []),
        "pending": pending,
        "capture_running": _capture_running(session.path),
        "calibration": calibration,
        "stacks": stacks,
    }


def _print(d: dict[str, Any], problems: list[str]) -> None:
    angles = ", ".join(f"{a:g}" for a in d["angles_deg"])
    print(f"session  {d['path']}  (format v{d['format_version']}, rig {(d.get('software') or {}).get('version', '?')})")
    print(f"created  {d['created']}   updated {d['updated']}   resumed {d['resumed']}x"
          + ("   [capture running]" if d["capture_running"] else ""))
    print(f"plan     {len(d['angles_deg'])} angles ({d['n_front']} front) [{angles}] deg x filters {','.join(d['filters'])}")
    b = d["bracket"]
    print(f"bracket  first {b['first_exposure_s']:g} s, max {b['max_exposure_s']:g} s, <= {b['max_exposures']} frames, "
          f"target SNR {b['target_snr']:g}, {b['n_darks']} darks per exposure")
    state = "complete" if d["complete"] else f"{len(d['pending'])} pending: {' '.join(d['pending'][:12])}" + (" ..." if len(d["pending"]) > 12 else "")
    print(f"progress {d['stacks_done']}/{d['stacks_total']} stacks done, {state}")
    for k, v in (d["devices"] or {}).items():
        print(f"device   {k:<7}{v}")
    g = d["geometry"] or {}
    if g:
        roi = g.get("camera_roi") or {}
        print(f"geometry thickness {g.get('thickness_mm', '?')} mm, pixel {g.get('pixel_pitch_mm', float('nan')):.4g} mm, "
              f"profile row {g.get('profile_row', '?')} ({g.get('profile_row_source', '?')}), "
              f"ROI y {roi.get('y', '?')}+{roi.get('height', '?')} rows")
    cal = d["calibration"]
    if cal:
        centre = cal.get("beam_center_px")
        # The calibration keeps the fitted centre at full float precision; 0.01 px is well below its error.
        extra = (f", beam centre ({', '.join(f'{float(c):.2f}' for c in centre)}) px"
                 if isinstance(centre, (list, tuple)) and centre else "")
        print(f"calib.   {cal['source']} ({len(cal['files'])} files{extra})" + (f"  [{cal['error']}]" if cal.get("error") else ""))
    else:
        print("calib.   none attached")
    print(f"{'stack':<8}{'angle':>8} {'state':<8}{'frames':>7}{'longest s':>11}{'min SNR':>9}  reason")
    for s in d["stacks"]:
        snr = f"{s['min_snr']:.1f}" if isinstance(s["min_snr"], (int, float)) else "-"
        print(f"{s['id']:<8}{s['angle_deg']:>8.2f} {s['state']:<8}{s['exposures']:>7}{s['longest_exposure_s']:>11.4g}{snr:>9}  {s['reason'] or ''}")
    print("checksums OK" if not problems else f"checksums FAILED: {len(problems)} problem(s)")


def run(args: argparse.Namespace) -> int:
    from capture.session import Session

    session = Session.open(args.dir)  # SessionError -> one line, exit 2
    problems = session.verify()
    d = describe(session)
    d["checksums_ok"] = not problems
    d["problems"] = problems
    if args.json:
        print(json.dumps(d, indent=2, default=str))
    else:
        _print(d, problems)
    for p in problems:
        print(f"rig info: error: {Path(args.dir) / p}", file=sys.stderr)
    return EXIT_CORRUPT if problems else 0
