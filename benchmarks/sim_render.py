"""Rendered bench: render time per (angle, filter) and the truth's residual Monte Carlo noise.

For the default world (its render settings) and a few angles/filters:
- cold render time of one radiance image (every tier: profile rows, band, rest of frame);
- the Monte Carlo noise of that image on the profile row, from a second render with
  another seed: var_MC = mean over pixels of (a - b)^2 / 2, compared with the sensor
  noise of the merged HDR profile row from a real bracket through the simulated camera
  (capture.bracket + matched darks + merge_hdr). The ratio mean(var_MC / var_sensor) over
  the pixels that matter (>= 1e-3 of the row's peak) is the inflation of a perfect fit's
  reduced chi^2 caused by the frozen Monte Carlo noise of the truth: chi2_r ~ 1 + ratio.

Run: .venv/bin/python benchmarks/sim_render.py [--quick]
Writes benchmarks/results/sim_render.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="two cases only")
    ap.add_argument("--spp-profile", type=int, default=None, help="override the world's spp_profile")
    args = ap.parse_args()

    from capture.bracket import BracketPolicy, acquire_bracket, acquire_darks
    from capture.hdr import MatchedDarks, NoiseModel, merge_hdr
    from drivers.interfaces import ROI
    from rig.config import load_config
    from rig.simbench import install_world
    from rig.wiring import open_rig
    from sim_devices.rendered_scene import RenderedScene
    from sim_devices.world import load_world

    cases = [(30.0, "r"), (60.0, "r"), (120.0, "r"), (150.0, "r"), (60.0, "g"), (60.0, "b")]
    if args.quick:
        cases = cases[1:3]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        world = load_world(None)
        spp = args.spp_profile or world.render.spp_profile
        world = dataclasses.replace(world, render=dataclasses.replace(world.render, cache_dir=f"{tmp}/a",
                                                                      spp_profile=spp))
        other = dataclasses.replace(world, render=dataclasses.replace(world.render, cache_dir=f"{tmp}/b",
                                                                      seed=world.render.seed + 101))
        cfg = load_config(None)
        cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, time_scale=5000.0))
        inst = install_world(cfg, None)
        scene = RenderedScene(world, magnification=cfg.camera.magnification)
        inst.scene = scene
        twin = RenderedScene(other, magnification=cfg.camera.magnification)
        _r0, _r1 = scene.profile_rows()
        prow = int(np.floor(scene.axis_px[1]))
        tiers = scene.row_tiers()
        with open_rig(cfg, sim=True, scene=scene) as rig:
            noise = NoiseModel.from_sensor(rig.camera.sensor)
            rig.camera.set_roi(ROI(0, prow - 8, 512, 16))
            for stage_angle, f in cases:
                phys = stage_angle + world.stage_zero_error_deg
                t0 = time.perf_counter()
                scene.radiance(phys, f)
                t_render = time.perf_counter() - t0
                twin.radiance(phys, f)
                a = scene.slab_image(phys, f)[prow]
                b = twin.slab_image(phys, f)[prow]
                rig.changer.select(f)
                rig.stage.move_to(stage_angle)
                # start with the peak at ~30 % of the well (the camera's shortest exposure
                # would leave 6 exposures x 4 far too short for the dim tail)
                t0 = 0.3 * rig.camera.sensor.full_well_e / float(scene.slab_image(phys, f).max())
                light, _status = acquire_bracket(rig.camera, BracketPolicy(profile_row=8, first_exposure_s=t0),
                                                noise)
                darks = acquire_darks(rig.camera, [fr.exposure_s for fr in light], 2)
                res = merge_hdr(np.stack([fr.data for fr in light]), [fr.exposure_s for fr in light],
                                MatchedDarks.from_frames(darks, noise), noise)
                var_s = res.variance[8].astype(np.float64)
                matter = (a >= 1e-3 * a.max()) & np.isfinite(var_s)
                var_mc = (a - b) ** 2 / 2.0
                ratio = float(np.mean(var_mc[matter] / var_s[matter]))
                bright = (a >= 0.1 * a.max()) & np.isfinite(var_s)
                ratio_bright = float(np.mean(var_mc[bright] / var_s[bright]))
                rel_mc = float(np.sqrt(np.mean(var_mc[matter] / a[matter] ** 2)))
                rel_s = float(np.sqrt(np.mean(var_s[matter] / a[matter] ** 2)))
                rows.append({"stage_angle_deg": stage_angle, "filter": f, "render_s": round(t_render, 3),
                             "pixels_that_matter": int(matter.sum()), "mc_rel_rms": rel_mc,
                             "sensor_rel_rms": rel_s, "mc_over_sensor_variance": ratio,
                             "mc_over_sensor_variance_bright": ratio_bright, "bright_pixels": int(bright.sum()),
                             "exposures": len(light)})
                print(f"{stage_angle:6.1f} {f}  render {t_render:6.2f} s   MC rel {rel_mc:.2e}   "
                      f"sensor rel {rel_s:.2e}   var ratio {ratio:.1f} (>=0.1 peak: {ratio_bright:.1f})   "
                      f"({int(matter.sum())} px)")
    out = {"world": "default", "render": dataclasses.asdict(world.render) | {"cache_dir": None},
           "tiers_rows_spp": tiers, "cases": rows,
           "mean_render_s": float(np.mean([r["render_s"] for r in rows])),
           "mean_mc_over_sensor_variance": float(np.mean([r["mc_over_sensor_variance"] for r in rows]))}
    print(f"mean render {out['mean_render_s']:.2f} s per (angle, filter); "
          f"mean var_MC / var_sensor on the profile row {out['mean_mc_over_sensor_variance']:.3f}")
    res_dir = ROOT / "benchmarks" / "results"
    res_dir.mkdir(parents=True, exist_ok=True)
    (res_dir / f"sim_render{'' if args.spp_profile is None else f'_spp{spp}'}.json").write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
