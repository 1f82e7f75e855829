"""Experiment: would tracing light from the beam render the profiles with less noise per
second than the forward model's camera paths?

The forward model (`estimate.forward`, Mitsuba's `prbvolpath`) traces paths from the
orthographic camera and, at every vertex in the slab, connects to the collimated beam
(next-event estimation). A vertex adds light only where it lies inside the beam's narrow
column (a Gaussian of sigma 0.25 mm on the bench), so a pixel in the tails, millimetres
from the spot, gets light only from the few camera paths that wander into that column:
at 128 spp its relative standard deviation is 15-50 % (`docs/forward-model.md`).

The dual estimator starts every path in the beam and connects each scattering vertex to
the orthographic camera. The camera sees a vertex along one direction (+z), so that
connection is deterministic, as the camera path's connection to the beam is: the
vertex's contribution is
    w * albedo * p(mu) * exp(-sigma_t * depth) / A_pixel
in the pixel it projects to (w the path's power, mu the cosine between its direction and
+z, depth the vertex's distance below the front face). Every vertex lands in some pixel,
so the samples are spent where the light is.

This script renders one profile row with both, for the index-matched slab (no refractive
boundary, no halo, no band: the plain exp3 model) at a front-lit and a back-lit angle:
the light tracer written here directly in Dr.Jit (a loop over bounces, evaluated each
bounce), and `ForwardModel._render_radiance`. It checks that the two agree in expectation
(the mean of many seeds, pixel by pixel, against their combined standard errors) and
compares their per-pixel relative standard deviation and time per render. Not used by
the estimator; the numbers are in `docs/forward-model.md`.

    .venv/bin/python benchmarks/exp_light_tracing.py [--seeds 8] [--spp 256] [--paths 2000000]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from estimate.beam import BeamProfile, beam_frame  # noqa: E402
from estimate.geometry import PixelWindow, RigGeometry  # noqa: E402
from estimate.mitsuba_phase import inverse_cdf_table  # noqa: E402
from estimate.phase_exponential import ExponentialPhase  # noqa: E402

if TYPE_CHECKING:
    from estimate.forward import ForwardModel

#: the bench's beam (benchmarks/worlds/*: a Gaussian of sigma 0.25 mm)
BEAM_SIGMA_MM = 0.25


def light_trace(geo: RigGeometry, window: PixelWindow, phi_deg: float, sigma_t: float, albedo: float,
                b: list[float], n_paths: int, seed: int, *, power: float = 1.0, max_depth: int = 64,
                rr_depth: int = 16, marginal_y: bool = False) -> np.ndarray:
    """Radiance of `window` (H, W) lit by a Gaussian beam of `power`, by light tracing.

    Index-matched slab -D <= z <= 0, |x|, |y| <= half width; paths that leave it are lost
    (nothing reflects them back). Russian roulette from `rr_depth` as in prbvolpath (survival
    probability the path's weight relative to its start, at most 0.95).

    `marginal_y`: the slab and the medium do not change along y (the beam's v axis), so a
    path's lateral displacement in y does not depend on where in the beam it started.
    Every path then starts at v = 0 and each vertex, displaced by dy, adds to the window's
    rows the beam's mass of v that would put it there: the Gaussian's mass over
    [y_lo - dy, y_hi - dy]. Every vertex then adds to the profile row instead of the few
    that land in it (a 66-um row against the beam's and the light's spread in y)."""
    import drjit as dr
    from drjit.llvm import PCG32, Bool, Float, UInt64
    from drjit.llvm import UInt32 as U

    D = geo.thickness_mm
    hw = geo.half_width_mm
    pitch = geo.pixel_mm
    cx, cy = geo.center_px
    H, W = window.height, window.width
    d, e_u, e_v = beam_frame(phi_deg)
    rng = PCG32(n_paths, initstate=UInt64(seed))
    # Gaussian irradiance exp(-r^2 / (2 sigma^2)): r by the inverse of its radial CDF.
    r = BEAM_SIGMA_MM * dr.sqrt(-2.0 * dr.log(1.0 - rng.next_float32()))
    s_, c_ = dr.sincos(2.0 * math.pi * rng.next_float32())
    u, v = r * c_, r * s_
    if marginal_y:
        # u from its marginal (a Gaussian of sigma); v integrated at the connection.
        u = BEAM_SIGMA_MM * math.sqrt(2.0) * dr.erfinv(2.0 * rng.next_float32() - 1.0)
        v = dr.zeros(Float, n_paths)
    p0 = [u * float(e_u[i]) + v * float(e_v[i]) for i in range(3)]
    # Where the beam line p0 + s d meets the lit face (front z = 0 when the source is on the
    # camera's side, d_z > 0; else the back face z = -D).
    z_face = 0.0 if d[2] > 0 else -D
    s = (z_face - p0[2]) / float(d[2])
    px, py, pz = p0[0] + s * float(d[0]), p0[1] + s * float(d[1]), Float(z_face) + 0.0 * s
    wx, wy, wz = Float(-float(d[0])), Float(-float(d[1])), Float(-float(d[2]))
    weight = dr.full(Float, power / n_paths, n_paths)
    active = dr.full(Bool, True, n_paths)
    image = dr.zeros(Float, H * W)
    table = Float(inverse_cdf_table(b))
    k = dr.width(table) - 1
    b0 = ExponentialPhase(b).b0
    inv_area = 1.0 / (pitch * pitch)
    for depth in range(max_depth):
        t = -dr.log(1.0 - rng.next_float32()) / sigma_t
        px, py, pz = px + t * wx, py + t * wy, pz + t * wz
        active &= (pz <= 0.0) & (pz >= -D) & (dr.abs(px) <= hw) & (dr.abs(py) <= hw)
        # The camera's connection: the scattered radiance towards +z, attenuated to the face.
        mu = wz
        poly = Float(0.0)
        for bi in reversed(b):
            poly = (poly + bi) * mu
        col = dr.floor(px / pitch + cx) - window.col0
        if marginal_y:
            if H != 1:
                raise ValueError("marginal_y renders one row")
            # The row spans y in [y_lo, y_hi]; the start v that puts this vertex there.
            y_hi = -(window.row0 - cy) * pitch
            y_lo = y_hi - pitch
            z_hi = (y_hi - py) / (BEAM_SIGMA_MM * math.sqrt(2.0))
            z_lo = (y_lo - py) / (BEAM_SIGMA_MM * math.sqrt(2.0))
            mass = 0.5 * (dr.erf(z_hi) - dr.erf(z_lo))
            row = dr.zeros(Float, n_paths)
        else:
            mass = Float(1.0)
            row = dr.floor(-py / pitch + cy) - window.row0
        seen = active & (col >= 0) & (col < W) & (row >= 0) & (row < H)
        contrib = weight * albedo * dr.exp(b0 + poly + sigma_t * pz) * inv_area * mass
        dr.scatter_reduce(dr.ReduceOp.Add, image, contrib, U(dr.maximum(row * W + col, 0)), seen)
        weight = weight * albedo
        # The next direction from the phase function's inverse-CDF table.
        x = rng.next_float32() * k
        i = U(dr.clip(dr.floor(x), 0, k - 1))
        f = x - Float(i)
        m = dr.clip(dr.lerp(dr.gather(Float, table, i), dr.gather(Float, table, i + 1), f), -1.0, 1.0)
        st = dr.safe_sqrt(1.0 - m * m)
        sp, cp = dr.sincos(2.0 * math.pi * rng.next_float32())
        # Frame around w (Duff et al.'s branchless basis).
        sign = dr.select(wz >= 0.0, 1.0, -1.0)
        a = -1.0 / (sign + wz)
        bb = wx * wy * a
        t1 = (1.0 + sign * wx * wx * a, sign * bb, -sign * wx)
        t2 = (bb, sign + wy * wy * a, -wy)
        lx, ly = st * cp, st * sp
        wx, wy, wz = (lx * t1[0] + ly * t2[0] + m * wx, lx * t1[1] + ly * t2[1] + m * wy,
                      lx * t1[2] + ly * t2[2] + m * wz)
        if depth + 1 >= rr_depth:
            q = dr.minimum(weight * n_paths / power, 0.95)
            survive = rng.next_float32() < q
            active &= survive
            weight = dr.select(survive, weight / dr.maximum(q, 1e-12), 0.0)
        dr.eval(px, py, pz, wx, wy, wz, weight, active, rng.state, image)
        if depth % 8 == 7 and not dr.any(active):
            break
    return np.array(image, dtype=np.float64).reshape(H, W)


def camera_trace(model: ForwardModel, values: dict[str, float], window: PixelWindow, phi_deg: float, spp: int,
                 seed: int) -> np.ndarray:
    """The forward model's radiance of `window` (H, W) at one angle."""
    return model._render_radiance(values, [phi_deg], window, spp, seed)[0]


def summarise(stack: np.ndarray, ref: np.ndarray, x_mm: np.ndarray) -> dict[str, float]:
    """Relative standard deviation of one render, by region of the reference profile."""
    sd = stack.std(axis=0, ddof=1)
    rel = sd / np.maximum(ref, 1e-30)
    peak = ref.max()
    out = {}
    for name, lo, hi in (("peak (> 0.3 max)", 0.3, 2.0), ("shoulder (0.03-0.3)", 0.03, 0.3),
                         ("tail (0.003-0.03)", 0.003, 0.03), ("far tail (3e-4-3e-3)", 3e-4, 0.003)):
        sel = (ref > lo * peak) & (ref <= hi * peak)
        out[name] = float(np.median(rel[sel])) if sel.any() else float("nan")
    out["far tail x_mm"] = float(np.max(np.abs(x_mm[(ref > 3e-4 * peak)])))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--spp", type=int, default=256, help="camera paths' samples per pixel")
    ap.add_argument("--paths", type=int, default=2_000_000, help="light paths a render")
    ap.add_argument("--angles", default="30,150")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "exp_light_tracing.json"))
    args = ap.parse_args(argv)

    from estimate.forward import ForwardModel
    from estimate.mitsuba_env import init_mitsuba
    variant = init_mitsuba()
    geo = RigGeometry(thickness_mm=1.0, magnification=0.3, profile_columns=(128, 384))
    beam = BeamProfile.gaussian(radius_mm=2.0 * BEAM_SIGMA_MM, power=1.0)
    model = ForwardModel(geo, beam, phase="exp3")
    values = model.validate({"sigma_t": 2.0, "albedo": 0.9, "phase.b1": 3.0, "phase.b2": 1.0, "phase.b3": 0.5})
    b = [values["phase.b1"], values["phase.b2"], values["phase.b3"]]
    window = geo.window()
    x_mm = np.asarray(geo.pixel_x_mm(window))
    report: dict = {"variant": variant.variant() if hasattr(variant, "variant") else str(variant), "window_px": window.width, "spp": args.spp, "paths": args.paths,
                    "seeds": args.seeds, "parameters": values, "angles": {}}
    estimators = {
        "camera": lambda phi, seed: camera_trace(model, values, window, phi, args.spp, seed)[0],
        "light": lambda phi, seed: light_trace(geo, window, phi, values["sigma_t"], values["albedo"], b,
                                               args.paths, seed)[0],
        "light_marginal_y": lambda phi, seed: light_trace(geo, window, phi, values["sigma_t"], values["albedo"],
                                                          b, args.paths, seed, marginal_y=True)[0],
    }
    regions = (("peak", 0.3, 2.0), ("shoulder", 0.03, 0.3), ("tail", 0.003, 0.03), ("far tail", 3e-4, 0.003))
    for phi in (float(a) for a in args.angles.split(",")):
        for fn in estimators.values():
            fn(phi, 999)  # kernel compilation, not timed
        stacks: dict[str, list[np.ndarray]] = {k: [] for k in estimators}
        times: dict[str, list[float]] = {k: [] for k in estimators}
        for s in range(args.seeds):   # interleaved, so load changes hit all alike
            for k, fn in estimators.items():
                t0 = time.perf_counter()
                stacks[k].append(fn(phi, s))
                times[k].append(time.perf_counter() - t0)
        arr = {k: np.array(v) for k, v in stacks.items()}
        # The reference profile: the mean of every render of every estimator.
        ref = np.mean([a.mean(0) for a in arr.values()], axis=0)
        entry: dict = {}
        cam = arr["camera"]
        for k, a in arr.items():
            t = float(np.median(times[k]))
            var = a.var(0, ddof=1)
            e = {"time_s": t, "sum_over_camera_sum": float(a.mean(0).sum() / cam.mean(0).sum()),
                 "rel_sd": summarise(a, ref, x_mm)}
            if k != "camera":
                se = np.sqrt(cam.var(0, ddof=1) / len(cam) + var / len(a))
                sig = ref > 1e-3 * ref.max()
                z = (cam.mean(0) - a.mean(0))[sig] / np.maximum(se[sig], 1e-30)
                e["z_rms_vs_camera"] = float(np.sqrt(np.mean(z ** 2)))
                # Efficiency 1 / (variance x time) relative to the camera paths': > 1 is better.
                gain = cam.var(0, ddof=1) * float(np.median(times["camera"])) / np.maximum(var * t, 1e-300)
                for name, lo, hi in regions:
                    sel = (ref > lo * ref.max()) & (ref <= hi * ref.max())
                    e[f"efficiency_vs_camera_{name}"] = float(np.median(gain[sel])) if sel.any() else float("nan")
            entry[k] = e
        report["angles"][str(phi)] = entry
        print(json.dumps({phi: entry}, indent=1), flush=True)
    Path(args.out).write_text(json.dumps(report, indent=1) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
