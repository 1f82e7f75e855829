"""Benchmark: the lens blur of a single profile row against the 2D blur of the whole frame.

The estimator renders one sensor row, so it cannot blur in 2D; the simulated bench blurs
its full frame. Both blur the *same* bench radiance here (the cached, unblurred scene of
a bench session's world), so the comparison isolates the blur model from Monte Carlo
noise and from the material:

* `lsf`: the line-spread function (the estimator before session 13);
* `as recorded`: weighted by the recording's y-shape as it is (`Problem.y_shape`, what
  `rig estimate` and `rig diagnose` used up to session 63);
* `recorded`: that shape deblurred along y by the PSF first (`lens_blur.unblurred_y_shape`,
  since session 64);
* `unblurred`: weighted by the y-shape of the bench's own unblurred rows, the very rows (render
  noise included) that the 2D blur mixes in: what a shape estimated from the recording could
  reach at best.

Each is divided by the bench's 2D blur (plus the world's stray light) in 16-pixel bins of
the central 128 pixels around the spot; the table gives the largest |ratio - 1| per angle.
Needs the bench case captured by `bench_diagnose.py --source bench` (default
`stray_light+lens_blur`; `--cache bench-light` for the light-engine bench's cases). Writes
benchmarks/results/bench_profile_blur.json (`_<cache>_<case>` appended for other caches).

    .venv/bin/python benchmarks/bench_profile_blur.py [--case stray_light+lens_blur]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
BIN_PX = 16
#: Bins compared: the central 128 pixels of the 256-pixel profile (the spot and its
#: shoulders; the far tails hold too little light for a ratio of frozen-noise renders).
CENTRAL = (64, 192)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--case", default="stray_light+lens_blur")
    ap.add_argument("--channel", default="g")
    ap.add_argument("--cache", default="bench", help="diagnose_cases sub-folder: bench (camera engine) or bench-light")
    args = ap.parse_args()
    os.environ.setdefault("DRJIT_LIBLLVM_PATH", "/usr/lib/x86_64-linux-gnu/libLLVM-19.so")
    from estimate.extensions.lens_blur import LensBlur, _weighted_profile, profile_weights
    from estimate.extensions.stray_light import StrayLight
    from estimate.problem import load_problem, y_shape_from_rows
    from sim_devices.rendered_scene import RenderedScene
    from sim_devices.world import load_world

    work = ROOT / "benchmarks" / "results" / "diagnose_cases" / args.cache / args.case
    if not (work / "session" / "session.yaml").is_file():
        print(f"{work}: no captured session; run benchmarks/bench_diagnose.py --source bench --only {args.case}",
              file=sys.stderr)
        return 2
    world = load_world(work / "world.yaml")
    if "lens_blur" not in world.effects:
        print(f"{work / 'world.yaml'}: the world has no lens_blur; pick a case with one", file=sys.stderr)
        return 2
    pb = load_problem(work / "session", args.channel)
    y_shape = pb.y_shape
    assert y_shape is not None  # load_problem always measures it
    # The scene at the session's own pixel scale (the rig's magnification, from the geometry).
    scene = RenderedScene(world, magnification=pb.geometry.magnification)
    row = pb.geometry.row
    c0, c1 = pb.geometry.profile_columns or (0, pb.geometry.sensor_px[0])
    blur = {**{p.name: p.neutral for p in LensBlur.parameters}, **world.effects["lens_blur"]}
    stray = world.effects.get("stray_light")
    t0 = time.perf_counter()
    rows: list[dict[str, Any]] = []
    for i, angle in enumerate(pb.angles_deg):
        rad = scene.radiance(float(angle), args.channel)
        bench = scene.image_effects(rad, direct=False)[row, c0:c1]
        prof = rad[row, c0:c1][None, None, :]
        # (shape, whether it is the blurred recording's, to be deblurred first)
        shapes = {"lsf": (None, True), "as recorded": (y_shape[i:i + 1], False),
                  "recorded": (y_shape[i:i + 1], True),
                  "unblurred": (y_shape_from_rows(rad, np.ones(rad.shape, bool), row, (c0, c1))[None], False)}
        entry: dict[str, Any] = {"angle_deg": float(angle)}
        for name, (h, recorded) in shapes.items():
            if h is None or recorded:
                out = LensBlur.apply(prof, blur, pixel_mm=pb.geometry.pixel_mm, profile_only=True, y_shape=h)
            else:
                out = _weighted_profile(prof[:, 0], profile_weights(blur, h, recorded=False), False)[:, None, :]
            if stray:
                out = StrayLight.apply(out, stray, pixel_mm=pb.geometry.pixel_mm, profile_only=True)
            m = out[0, 0]
            ratios = [float(m[b:b + BIN_PX].sum() / bench[b:b + BIN_PX].sum())
                      for b in range(CENTRAL[0], CENTRAL[1], BIN_PX)]
            entry[name] = {"bin_ratios": ratios, "max_abs_error": float(max(abs(r - 1.0) for r in ratios))}
        rows.append(entry)
    wall = time.perf_counter() - t0
    names = ("lsf", "as recorded", "recorded", "unblurred")
    summary = {name: float(max(r[name]["max_abs_error"] for r in rows)) for name in names}
    print(f"case {args.case}, blur {blur}, {len(rows)} angles, {wall:.1f} s")
    print(f"{'angle':>6} " + " ".join(f"{n:>11}" for n in names) + "   (largest |profile / 2D - 1| over 16-px bins)")
    for r in rows:
        print(f"{r['angle_deg']:6.0f} " + " ".join(f"{r[n]['max_abs_error']:11.3f}" for n in names))
    print(f"{'all':>6} " + " ".join(f"{summary[n]:11.3f}" for n in names))
    suffix = "" if args.cache == "bench" else f"_{args.cache}_{args.case}"
    dest = ROOT / "benchmarks" / "results" / f"bench_profile_blur{suffix}.json"
    dest.write_text(json.dumps({"case": args.case, "channel": args.channel, "blur": blur, "angles": rows,
                                "max_abs_error": summary, "wall_s": wall, "bin_px": BIN_PX,
                                "central_px": list(CENTRAL)}, indent=1))
    print(f"wrote {dest}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
