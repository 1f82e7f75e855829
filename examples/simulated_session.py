"""The whole job from Python on the simulated rig: calibrate, capture, estimate, diagnose, report.

    .venv/bin/python examples/simulated_session.py OUTDIR [--quick]

``--quick`` renders the default world at a few samples per pixel and fits with few
iterations and samples on a narrower profile window (what the test suite runs); without it
the default world and settings are used.
Every step is the same code path as the ``rig`` command of the same name (``rig.api``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from rig import api


def cheap_world(out: Path) -> Path:
    """A copy of the default world rendered at a few samples per pixel (fast, noisier)."""
    from sim_devices.world import write_quick_world

    return write_quick_world(out / "world-quick.yaml", cache_dir=out / "render-cache", spp_profile=64)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="new directory for the calibration, session and report")
    ap.add_argument("--quick", action="store_true", help="low render quality and few iterations (for tests)")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=False)
    sim: bool | Path = cheap_world(a.out) if a.quick else True
    angles, filters = (4, "g") if a.quick else (10, "rgb")
    # Quick: few iterations, one polish step at 128 spp, a 64-pixel profile window.
    fit_args = (["--max-iterations", "4", "--spp-max", "128", "--polish-steps", "1", "--final-spp", "128",
                 "--columns", "64"] if a.quick else [])

    cal = api.calibrate_beam(a.out / "calibration", filters=filters, sim=sim)
    print(f"rotation zero {cal['rotation_zero_deg']:.3f} deg, beam centre {cal['center_px']}")

    summary = api.capture(a.out / "session", angles=angles, filters=filters,
                          calibration=a.out / "calibration", sim=sim)
    print(f"captured {len(summary['completed'])} stacks; checksums OK: {api.info(a.out / 'session')['checksums_ok']}")

    results = api.estimate(a.out / "session", extra_args=fit_args)
    print(json.dumps(results, indent=1, default=float)[:2000])

    diagnosis = api.diagnose(a.out / "session", extra_args=(["--spp", "64", "--no-plots"] if a.quick else []))
    for ch, d in diagnosis.get("channels", {}).items():
        print(f"channel {ch}: significant mismatch: {d.get('significant')}")

    print(f"report: {api.report(a.out / 'session')}")


if __name__ == "__main__":
    main()
