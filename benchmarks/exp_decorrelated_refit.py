"""Experiment (session 44, not part of the pipeline): do refits on the decorrelated chi^2 at
low spp avoid fitting their own render noise on the 256-px window, where the diagnosis'
fixed-seed refits do (session 41)?

    .venv/bin/python benchmarks/exp_decorrelated_refit.py [CASE] [SPP] [refits] [EXT]

CASE a synthetic suite case whose 256-px, 2048-spp result is cached (default beam_halo-1);
refits a comma list of dec-cand, dec-control, fs-cand, fs-control; EXT the candidate effect
(default: the case's own). Writes
benchmarks/results/exp_decorrelated_refit_<CASE>_<SPP>.json; a few minutes on 2 cores.

beam_halo-1 (3 %, 1 mm), the suite's recording and 4096-spp base fit; the confirmation's
training angles, yardstick and floor. For the control (material only) and the halo
candidate: a fixed-seed LM refit as the diagnosis runs it, and a decorrelated refit
(repeated Gauss-Newton steps on sum r_A r_B of two seeds, `decorrelated_step`), each
judged by its independently rendered training chi^2 (1024 spp x 4 seeds).
"""
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]
from bench_diagnose import cases, synthetic_recording
from estimate.diagnose import _free_names, _holdout, _start, _yardstick
from estimate.refit import (DEFAULT_SEED, decorrelated_chi2, decorrelated_step, evaluate, parameter_bounds,
                            recording_variance, refit, refit_columns)
from estimate.gauss_newton import secant_steps

CASE = sys.argv[1] if len(sys.argv) > 1 else "beam_halo-1"
SPP = int(sys.argv[2]) if len(sys.argv) > 2 else 512
which = sys.argv[3].split(",") if len(sys.argv) > 3 else ["dec-control", "dec-cand", "fs-control", "fs-cand"]
EXT = sys.argv[4] if len(sys.argv) > 4 else CASE.rsplit("-", 1)[0]  # the candidate (a clean case needs one)
case = [c for c in cases(False) if c["id"] == CASE][0]
t0 = time.perf_counter()
rec, make_model, truth = synthetic_recording(case, 0.0, 256)
print(f"recording {time.perf_counter() - t0:.0f} s", flush=True)
cached = json.loads((ROOT / "benchmarks/results/diagnose_cases/synthetic-v11-excess0-spp2048-base4096-cols256"
                     / f"{CASE}.json").read_text())
base = dict(cached["material_before"])
m0 = make_model([])
m1 = make_model([EXT])
n = len(rec.angles_deg)
train, _ = _holdout(n)
t = time.perf_counter()
before = evaluate(m0, base, rec, 4, spp=SPP, seed=DEFAULT_SEED, repeats=6)
yard = _yardstick(rec, before)
floor = before.residuals.noise_scale
print(f"before {time.perf_counter() - t:.0f} s; floor {np.round(floor, 3)}", flush=True)


def indep(model, p):
    return evaluate(model, p, rec, 0, spp=1024, seed=DEFAULT_SEED, repeats=4, angle_idx=train,
                    noise_variance=yard).residuals.chi2_adjusted


def dlm(model, start, free, seed, iters=8):
    idx = list(train)
    angles = [float(rec.angles_deg[i]) for i in idx]
    meas = np.asarray(rec.measured, dtype=np.float64)[idx]
    var = recording_variance(rec)[idx]
    mv = (before.model_variance * 6)[idx]
    f2 = (np.asarray(floor)[idx] ** 2)[:, None]
    bounds = [parameter_bounds(model, k) for k in free]
    theta = dict(model.validate(start))
    for k, (lo, hi) in zip(free, bounds):
        theta[k] = float(np.clip(theta[k], lo, hi))
    sb = seed + 1000

    last: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}

    def both(th):
        # The accepted trial of `decorrelated_step` is the next iteration's point: keep its
        # renders (the last pair only) instead of rendering them again.
        key = tuple(sorted(th.items()))
        if key not in last:
            last.clear()
            last[key] = (model.render_profiles(th, angles, spp=SPP, seed=seed),
                         model.render_profiles(th, angles, spp=SPP, seed=sb))
        return last[key]

    f_a, f_b = both(theta)
    hist = []
    for it in range(iters):
        _, s = decorrelated_chi2(meas, np.sqrt(var * f2), f_a, f_b)  # the scale for the weights
        sig = np.sqrt((var + s * s * mv) * f2)
        loss, s = decorrelated_chi2(meas, sig, f_a, f_b)
        steps = secant_steps(model, theta, free)
        a = refit_columns(model.jacobian(theta, angles, free, spp=SPP, seed=seed, steps=steps), f_a, s, sig)
        b = refit_columns(model.jacobian(theta, angles, free, spp=SPP, seed=sb, steps=steps), f_b, s, sig)
        new, _ = decorrelated_step(both, meas, sig, theta, s, f_a, f_b, a, b, free, bounds, halvings=3)
        hist.append(round(loss, 1))
        print(f"  it {it + 1}: dec chi2 {loss:.1f} {({k: round(v, 4) for k, v in new.items() if k in free})}", flush=True)
        if new == theta:
            break
        theta = new
        f_a, f_b = both(theta)
    return theta, hist


out = {"case": CASE, "spp": SPP, "base": base, "chi2_indep_base": indep(m0, base)}
print(f"base: indep {out['chi2_indep_base']:.1f}", flush=True)
brightest = float(np.max(before.model))
for w in which:
    t = time.perf_counter()
    model = m0 if w.endswith("control") else m1
    free = _free_names(model, [] if w.endswith("control") else [EXT])
    start = base if w.endswith("control") else _start(m1, base, EXT, brightest)
    if w.startswith("fs"):
        r = refit(model, rec, start, free, angle_idx=train, spp=SPP, seed=DEFAULT_SEED + 202, iterations=8,
                  model_variance=before.model_variance * 6, noise_scale=floor, uncertainties=False)
        p, hist = r.parameters, [r.chi2]
    else:
        p, hist = dlm(model, start, free, DEFAULT_SEED + 202)
    c = indep(model, p)
    out[w] = {"params": {k: p[k] for k in free}, "chi2_indep": c, "hist": hist, "time_s": time.perf_counter() - t}
    print(f"{w}: indep {c:.1f}  {({k: round(p[k], 4) for k in free})}  {time.perf_counter() - t:.0f} s", flush=True)
    (ROOT / f"benchmarks/results/exp_decorrelated_refit_{CASE}_{SPP}{'' if EXT in CASE else '_' + EXT}.json").write_text(json.dumps(out, indent=1))
