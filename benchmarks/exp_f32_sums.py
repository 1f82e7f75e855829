"""Probe: how far low does a single-precision scatter-add sum come out, against the same
addends summed in double precision, for the number of addends a pixel receives?

Session 92 found the light engine's single-precision sums 0.03-0.10 % low on the profiles'
bright pixels at 16384 spp, where each such pixel takes 1e5-1e6 path contributions, and moved
those sums to double precision (`estimate.light_paths`). The camera engine (`--engine camera`,
and the simulated camera by default) still accumulates its film in single precision, as
every `llvm_ad_mono` / `cuda_ad_mono` film does, but with a box filter a pixel takes only
its own spp samples. Whether that matters is a question of arithmetic, not of the scene: an
addend below half a unit in the last place of the running sum is lost, so the bias grows
with the number of addends and with their spread (many small ones beside a few large ones).

This draws positive, log-normal addends (a path tracer's samples span decades; `--sigma` is
the spread of ln v, with a fraction of zeros for paths that miss), adds them into pixels in a
random order with Dr.Jit's `scatter_reduce` in single and in double precision (the film's and
the light engine's operation, on the CPU backend), and prints the mean relative error of the
single-precision sums against the double-precision ones.

    .venv/bin/python benchmarks/exp_f32_sums.py [--addends 1024,16384,65536,1000000]
        [--sigma 1,2,3,4] [--zeros 0.5] [--pixels 64] [--seed 0] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estimate.mitsuba_env import init_mitsuba  # noqa: E402


def sum_bias(mi: Any, dr: Any, rng: np.random.Generator, addends: int, pixels: int, sigma: float,
             zeros: float) -> dict[str, float]:
    """Mean and pixel-to-pixel sd of (single-precision sum / double-precision sum - 1) over
    `pixels` pixels of `addends` log-normal addends each (a fraction `zeros` set to 0)."""
    n = addends * pixels
    v = rng.lognormal(0.0, sigma, n).astype(np.float32)
    v[rng.random(n) < zeros] = 0.0
    # A random pixel for each addend: the order in which the threads' atomic adds arrive.
    idx = rng.integers(0, pixels, n).astype(np.uint32)
    ref = np.bincount(idx, weights=v.astype(np.float64), minlength=pixels)
    s32 = dr.zeros(mi.Float, pixels)
    dr.scatter_reduce(dr.ReduceOp.Add, s32, mi.Float(v), mi.UInt32(idx))
    s64 = dr.zeros(mi.Float64, pixels)
    dr.scatter_reduce(dr.ReduceOp.Add, s64, mi.Float64(v), mi.UInt32(idx))
    r32 = np.array(s32, dtype=np.float64) / ref - 1.0
    r64 = np.array(s64, dtype=np.float64) / ref - 1.0
    return {"addends_per_pixel": addends, "sigma": sigma, "zeros": zeros, "pixels": pixels,
            "f32_bias_percent": float(r32.mean() * 100), "f32_pixel_sd_percent": float(r32.std() * 100),
            "f64_bias_percent": float(r64.mean() * 100)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--addends", default="1024,16384,65536,1000000",
                    help="comma list: addends per pixel (a camera-engine pixel takes its spp)")
    ap.add_argument("--sigma", default="1,2,3,4", help="comma list: sd of the addends' ln")
    ap.add_argument("--zeros", type=float, default=0.0, help="fraction of addends set to 0")
    ap.add_argument("--pixels", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", help="results JSON")
    args = ap.parse_args(argv)
    try:
        counts = [int(x) for x in args.addends.split(",")]
        sigmas = [float(x) for x in args.sigma.split(",")]
    except ValueError:
        print("exp_f32_sums: --addends and --sigma take comma lists of numbers, e.g. --addends 16384,65536",
              file=sys.stderr)
        return 2
    if min(counts) < 1 or min(sigmas) < 0 or args.pixels < 1 or not 0.0 <= args.zeros < 1.0:
        print("exp_f32_sums: addends and pixels must be >= 1, sigma >= 0, 0 <= zeros < 1", file=sys.stderr)
        return 2
    mi = init_mitsuba("llvm_ad_mono")
    import drjit as dr

    rng = np.random.default_rng(args.seed)
    rows = []
    for sigma in sigmas:
        for addends in counts:
            t0 = time.monotonic()
            row = sum_bias(mi, dr, rng, addends, args.pixels, sigma, args.zeros)
            row["time_s"] = time.monotonic() - t0
            rows.append(row)
            print(f"sigma {sigma:g}  addends/pixel {addends:8d}: single precision {row['f32_bias_percent']:+.5f} % "
                  f"(pixel sd {row['f32_pixel_sd_percent']:.5f} %), double {row['f64_bias_percent']:+.1e} %",
                  flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps({"seed": args.seed, "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
