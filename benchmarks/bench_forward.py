"""Forward-model benchmark (issue 4; issue 3's plugin-cost ratio).

10 stage angles x 256-pixel profile row at 128 spp, slab d = 1 mm, sigma_t = 2 /mm,
albedo 0.9:
- exponential phase (Python plugin) of degree 3, index-matched: forward, forward+backward;
- the same with Mitsuba's built-in `hg` (g = 0.5), in the same run: ratio exp / builtin.
  For a like-for-like cost the exponential coefficients are the least-squares fit of
  log HG(0.5) (same scattering statistics, so the same path lengths);
- exponential with `refractive_boundary` (n = 1.45);
- variance: relative standard deviation over seeds of the profile peak and of the tail
  20 px from the peak, at 128 spp.
"forward+backward" is `ForwardModel.value_and_grad` with an L2 loss: the forward render,
the adjoint (path replay) pass for albedo and the phase coefficients, and one extra forward
render for the one-sided finite difference of sigma_t. Timings: median of several runs,
`dr.sync_thread()` before each clock read; also the process CPU time / 2 (what 2 idle
cores would need with perfect parallel scaling), since other processes share the cores. Run: `.venv/bin/python benchmarks/bench_forward.py`.
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estimate.beam import BeamProfile
from estimate.forward import ForwardModel
from estimate.geometry import RigGeometry

ANGLES = [15.0, 30.0, 45.0, 60.0, 75.0, 105.0, 120.0, 135.0, 150.0, 165.0]
SPP = 128
REPEATS = 5
G = 0.5


def exp3_fit_of_hg(g: float) -> list[float]:
    """b1..b3 of the least-squares fit of log HG(g) on a uniform mu grid."""
    mu = np.linspace(-1, 1, 401)
    log_hg = np.log((1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * mu) ** 1.5))
    a = np.vander(mu, 4, increasing=True)
    coef, *_ = np.linalg.lstsq(a, log_hg, rcond=None)
    return [float(c) for c in coef[1:]]


def timed(fn: Callable[[], object], cpu: list[float]) -> float:
    """Wall seconds of fn(); appends the process CPU seconds (all threads) to `cpu`."""
    import drjit as dr

    dr.sync_thread()
    t0 = time.perf_counter()
    c0 = time.process_time()
    fn()
    dr.sync_thread()
    cpu.append(time.process_time() - c0)
    return time.perf_counter() - t0


def main() -> int:
    load_start = os.getloadavg()[0]  # other processes on the 2 cores inflate the timings
    geometry = RigGeometry(thickness_mm=1.0, magnification=0.5, profile_columns=(128, 384))
    beam = BeamProfile.gaussian(0.5)
    b = exp3_fit_of_hg(G)
    cases = {
        "exp3": (ForwardModel(geometry, beam, phase="exp3"),
                 {"sigma_t": 2.0, "albedo": 0.9, "phase.b1": b[0], "phase.b2": b[1], "phase.b3": b[2]}),
        "hg_builtin": (ForwardModel(geometry, beam, phase="hg"),
                       {"sigma_t": 2.0, "albedo": 0.9, "phase.g": G}),
        "exp3_refractive": (ForwardModel(geometry, beam, phase="exp3", extensions=["refractive_boundary"]),
                            {"sigma_t": 2.0, "albedo": 0.9, "phase.b1": b[0], "phase.b2": b[1],
                             "phase.b3": b[2], "refractive_boundary.n": 1.45}),
    }
    target = {name: m.render_profiles(p, ANGLES, spp=SPP, seed=999) * 1.1 for name, (m, p) in cases.items()}

    def loss_for(name: str) -> Callable[[np.ndarray], tuple[float, np.ndarray]]:
        t = target[name]

        def loss(prof: np.ndarray) -> tuple[float, np.ndarray]:
            r = prof - t
            return float((r * r).sum()), 2.0 * r
        return loss

    # warm-up: compile / load every kernel once
    for name, (m, p) in cases.items():
        m.value_and_grad(p, ANGLES, loss_for(name), spp=SPP, seed=0, fd_parameters=False)

    times: dict[str, dict[str, list[float]]] = {n: {"forward": [], "forward_backward": []} for n in cases}
    cpu: dict[str, dict[str, list[float]]] = {n: {"forward": [], "forward_backward": []} for n in cases}
    for rep in range(REPEATS):  # interleaved, so load changes hit every case alike
        for name, (m, p) in cases.items():
            # timed() calls each lambda at once: they see this iteration's m, p, name and rep.
            times[name]["forward"].append(timed(
                lambda: m.render_profiles(p, ANGLES, spp=SPP, seed=rep),
                cpu[name]["forward"]))
            times[name]["forward_backward"].append(timed(
                lambda: m.value_and_grad(
                    p, ANGLES, loss_for(name), spp=SPP, seed=rep, fd_parameters=False),
                cpu[name]["forward_backward"]))
    med = {n: {k: statistics.median(v) for k, v in d.items()} for n, d in times.items()}
    # CPU seconds / 2: the wall time on 2 otherwise idle cores if the work parallelises
    # perfectly (a lower bound; the wall times above include other processes' load).
    med_cpu_half = {n: {k: statistics.median(v) / 2 for k, v in d.items()} for n, d in cpu.items()}

    # variance at 128 spp (index-matched exp3)
    m, p = cases["exp3"]
    ref = m.render_profiles(p, ANGLES, spp=4096, seed=12345)
    runs = np.stack([m.render_profiles(p, ANGLES, spp=SPP, seed=100 + s) for s in range(16)])
    variance = []
    for k, phi in enumerate(ANGLES):
        peak = int(np.argmax(ref[k]))
        tail = peak + 20 if peak + 20 < ref.shape[1] else peak - 20
        vp = runs[:, k, peak]
        vt = runs[:, k, tail]
        variance.append({"angle_deg": phi, "peak_px": peak, "tail_px": tail,
                         "peak_rel_std": float(vp.std(ddof=1) / vp.mean()),
                         "tail_rel_std": float(vt.std(ddof=1) / vt.mean()),
                         "tail_over_peak": float(ref[k, tail] / ref[k, peak])})

    ratios = {
        "exp_over_builtin_forward": med["exp3"]["forward"] / med["hg_builtin"]["forward"],
        "exp_over_builtin_forward_backward": med["exp3"]["forward_backward"] / med["hg_builtin"]["forward_backward"],
        "refractive_over_index_matched_forward": med["exp3_refractive"]["forward"] / med["exp3"]["forward"],
        "refractive_over_index_matched_forward_backward":
            med["exp3_refractive"]["forward_backward"] / med["exp3"]["forward_backward"],
    }
    load_start_end = [load_start, os.getloadavg()[0]]
    result = {
        "config": {"angles_deg": ANGLES, "pixels": 256, "spp": SPP, "repeats": REPEATS,
                   "thickness_mm": 1.0, "sigma_t": 2.0, "albedo": 0.9, "hg_g": G, "exp3_b": b,
                   "pixel_mm": geometry.pixel_mm, "beam": "gaussian 1/e^2 radius 0.5 mm",
                   "max_depth": 64, "variant": m.mi.variant(),
                   "cpu_count": os.cpu_count(), "machine": platform.processor() or platform.machine(),
                   "load_average_1min_start_end": load_start_end},
        "median_s": med,
        "median_cpu_s_over_2": med_cpu_half,
        "all_s": times,
        "ratios": ratios,
        "targets": {"forward_s": 0.4, "forward_backward_s": 1.2, "refractive_factor": 2.0, "exp_over_builtin": 1.2},
        "variance_128spp": variance,
    }
    print(f"load average (1 min) at start / end: {load_start_end}")
    print(f"{'case':<18}{'forward [s]':>14}{'fwd+bwd [s]':>14}{'fwd cpu/2':>12}{'f+b cpu/2':>12}")
    for n, d in med.items():
        c = med_cpu_half[n]
        print(f"{n:<18}{d['forward']:>14.3f}{d['forward_backward']:>14.3f}"
              f"{c['forward']:>12.3f}{c['forward_backward']:>12.3f}")
    for key, ratio in ratios.items():
        print(f"{key:<48}{ratio:>8.2f}")
    print(f"{'angle':>6}{'peak px':>9}{'peak rel std':>14}{'tail rel std':>14}{'tail/peak':>11}")
    for v in variance:
        print(f"{v['angle_deg']:>6.0f}{v['peak_px']:>9d}{v['peak_rel_std']:>14.3f}{v['tail_rel_std']:>14.3f}"
              f"{v['tail_over_peak']:>11.3g}")
    out = Path(__file__).resolve().parent / "results" / "bench_forward.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
