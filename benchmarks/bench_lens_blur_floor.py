"""Benchmark: what keeps the true model above the noise floor on a lens-blur bench session.

The diagnosis' yardstick "after" is the true model's reduced chi^2 at the noise floor
(`bench_diagnose.truth_at_floor`). On the light-engine bench's lens-blur sessions it stood at
7.6 (session 62) where clean sessions sit at 1.1-1.2. This script takes that number apart on
one captured bench case, the true parameters held fixed and only one ingredient changed at a
time:

* `model`: as the diagnosis evaluates it (the calibrated beam map deblurred by the true PSF,
  the recording's y-shape);
* `bench beam`: the bench's own beam map in place of the deblurred calibration map;
* `bench rows`: the y-shape of the bench's own rows, blurred by the world's image effects but
  without the render noise, in place of the recording's (the lens blur deblurs either along
  y: `estimate.extensions.lens_blur.unblurred_y_shape`);

and measures the bench recording's frozen render noise: the profile tier rendered twice more
at the bench's own spp with other seeds, the mean square of their difference over the HDR
variance, halved (the variance of one render in units of the sensor's), unblurred and after
the world's 2D blur.

Needs the case captured by `bench_diagnose.py --source bench --engine light` (default
`lens_blur-1`). Writes benchmarks/results/bench_lens_blur_floor_<case>.json.

    .venv/bin/python benchmarks/bench_lens_blur_floor.py [--case lens_blur-1] [--spp 2048]
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
sys.path.insert(0, str(ROOT / "benchmarks"))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--case", default="lens_blur-1")
    ap.add_argument("--cache", default="bench-light", help="diagnose_cases sub-folder of the bench's cases")
    ap.add_argument("--spp", type=int, default=2048, help="the evaluation's spp (the diagnosis')")
    ap.add_argument("--no-frozen-noise", action="store_true",
                    help="skip the measurement of the recording's frozen render noise (two renders)")
    args = ap.parse_args()
    os.environ.setdefault("DRJIT_LIBLLVM_PATH", "/usr/lib/x86_64-linux-gnu/libLLVM-19.so")
    import yaml

    from estimate.beam import BeamProfile
    from estimate.diagnose import DEFAULT_REPEATS, DEFAULT_SEED, evaluate
    from estimate.forward import ForwardModel
    from estimate.problem import load_problem, y_shape_from_rows
    from sim_devices.rendered_scene import RenderedScene
    from sim_devices.world import load_world

    work = ROOT / "benchmarks" / "results" / "diagnose_cases" / args.cache / args.case
    if not (work / "session" / "session.yaml").is_file():
        print(f"{work}: no captured session; run benchmarks/bench_diagnose.py --source bench --engine light "
              f"--only {args.case}", file=sys.stderr)
        return 2
    raw = yaml.safe_load((work / "world.yaml").read_text())
    effects = raw.get("effects") or {}
    if "lens_blur" not in effects:
        print(f"{work / 'world.yaml'}: the world has no lens_blur; pick a case with one", file=sys.stderr)
        return 2
    world = load_world(work / "world.yaml")
    channel = "g"
    mat = raw["materials"][channel]
    truth = {"sigma_t": mat["sigma_t"], "albedo": mat["albedo"]}
    truth.update({f"phase.b{i + 1}": b for i, b in enumerate(mat["phase"].get("b", []))})
    pb = load_problem(work / "session", channel)
    params = dict(truth)
    for e, values in effects.items():
        for k, v in values.items():
            params[f"{e}.{k}"] = float(v) * (pb.beam.power() if e == "stray_light" else 1.0)
    scene = RenderedScene(world, magnification=pb.geometry.magnification)
    row = pb.geometry.row
    c0, c1 = pb.geometry.profile_columns or (0, pb.geometry.sensor_px[0])
    t0 = time.perf_counter()
    # The bench's radiance at the session's angles: its calibration put the stage's zero
    # right, so the physical angles are the planned ones (the cache is keyed by them).
    rads = {float(a): scene.radiance(float(a), channel) for a in pb.angles_deg}
    bench_rows = {a: y_shape_from_rows(scene.image_effects(r, direct=False), np.ones(r.shape, bool), row, (c0, c1))
                  for a, r in rads.items()}
    bench_beam = scene.beam_profile()

    def floor(beam: BeamProfile, shapes: dict[float, np.ndarray]) -> float:
        fm = ForwardModel(pb.geometry, beam, phase="exp3", extensions=list(effects), profile_y_shape=shapes,
                          engine="light", profile_merge_fill=pb.merge_fills(), beam_fill=pb.beam_fill)
        ev = evaluate(fm, params, pb, len(fm.parameter_names) + 1, spp=args.spp, seed=DEFAULT_SEED,
                      repeats=DEFAULT_REPEATS)
        return float(ev.residuals.reduced_chi2_adjusted)

    out: dict[str, object] = {"case": args.case, "channel": channel, "blur": effects["lens_blur"]}
    floor_chi2 = {
        "model": floor(pb.beam, pb.y_shapes()),
        "bench beam": floor(bench_beam, pb.y_shapes()),
        "bench rows": floor(pb.beam, bench_rows),
        "bench beam and rows": floor(bench_beam, bench_rows),
    }
    out["floor_chi2"] = floor_chi2
    # The recording's frozen render noise: two more renders of the profile tier at the bench's spp.
    ratios: dict[str, list[float]] = {"unblurred": [], "blurred": []}
    if args.no_frozen_noise:
        return _report(args, out, floor_chi2, effects, len(pb.angles_deg), ratios, 0, t0)
    model, mparams = scene.slab_model(channel)
    p0, p1, spp = scene.row_tiers()[0]
    cols = scene.sensor_px[0]
    for i, a in enumerate(pb.angles_deg):
        pair = []
        for k in range(2):
            img = rads[float(a)].copy()
            img[p0:p1] = model.render(mparams, [float(a)], columns=(0, cols), rows=(p0, p1), spp=spp,
                                      seed=90_001 + 31 * i + k)[0]
            pair.append(img)
        k_e = pb.measured[i].sum() / scene.image_effects(rads[float(a)], direct=False)[row, c0:c1].sum()
        sd = np.sqrt(pb.variance[i])
        d_u = (pair[0][row, c0:c1] - pair[1][row, c0:c1]) * k_e / sd
        d_b = (scene.image_effects(pair[0], direct=False)[row, c0:c1]
               - scene.image_effects(pair[1], direct=False)[row, c0:c1]) * k_e / sd
        ratios["unblurred"].append(float(np.mean(d_u ** 2) / 2.0))
        ratios["blurred"].append(float(np.mean(d_b ** 2) / 2.0))
    out["frozen_noise_variance_over_sensor"] = {k: {"per_angle": v, "mean": float(np.mean(v))}
                                               for k, v in ratios.items()}
    out["profile_tier"] = {"rows": [p0, p1], "spp": spp}
    return _report(args, out, floor_chi2, effects, len(pb.angles_deg), ratios, spp, t0)


def _report(args: argparse.Namespace, out: dict[str, object], floor_chi2: dict[str, float],
            effects: dict[str, Any], n_angles: int, ratios: dict[str, list[float]], spp: int, t0: float) -> int:
    """Print the floors (`floor_chi2`, also in `out`) and the frozen noise, write `out`."""
    out["wall_s"] = time.perf_counter() - t0
    print(f"case {args.case}, blur {effects['lens_blur']}, {n_angles} angles, {out['wall_s']:.0f} s")
    print("the true model's reduced chi^2 at the noise floor:")
    for k, chi2 in floor_chi2.items():
        print(f"  {k:22s} {chi2:6.2f}")
    if spp:
        print(f"the recording's frozen render noise (profile tier, {spp} spp), variance / the sensor's:")
    for k, v in ratios.items() if spp else ():
        print(f"  {k:10s} mean {np.mean(v):6.2f}  per angle " + " ".join(f"{x:5.1f}" for x in v))
    tag = "" if args.cache == "bench-light" else f"_{args.cache}"
    dest = ROOT / "benchmarks" / "results" / f"bench_lens_blur_floor_{args.case}{tag}.json"
    dest.write_text(json.dumps(out, indent=1))
    print(f"wrote {dest}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
