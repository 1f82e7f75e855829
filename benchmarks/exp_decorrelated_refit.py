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
(repeated Gauss-Newton steps on sum r_A r_B of two seeds), each judged by its independently
rendered training chi^2 (1024 spp x 4 seeds).

Session 44 ran its own loop of `decorrelated_step` (weights moving with the scale, no
stopping rule; its JSON files and the table in docs/diagnosis-log.md are from that loop).
Since session 45 the decorrelated refits are `refit(objective=DECORRELATED)`, the diagnosis'
own (`rig diagnose --refits decorrelated`), dividing by the data's noise (the yardstick).
"""
import json
import sys
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]
from bench_diagnose import cases, synthetic_recording

from estimate.diagnose import (
    _free_names,
    _holdout,
    _render_variance,
    _start,
    _yardstick,
)
from estimate.model_protocols import ProfileModel
from estimate.refit import DECORRELATED, DEFAULT_SEED, evaluate, refit

CASE = sys.argv[1] if len(sys.argv) > 1 else "beam_halo-1"
SPP = int(sys.argv[2]) if len(sys.argv) > 2 else 512
which = sys.argv[3].split(",") if len(sys.argv) > 3 else ["dec-control", "dec-cand", "fs-control", "fs-cand"]
EXT = sys.argv[4] if len(sys.argv) > 4 else CASE.rsplit("-", 1)[0]  # the candidate (a clean case needs one)
case = next(c for c in cases(False) if c["id"] == CASE)
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


def indep(model: ProfileModel, p: Mapping[str, float]) -> float:
    return evaluate(model, p, rec, 0, spp=1024, seed=DEFAULT_SEED, repeats=4, angle_idx=train,
                    noise_variance=yard).residuals.chi2_adjusted


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
                  model_variance=_render_variance(before, 6), noise_scale=floor, uncertainties=False)
        p, hist = r.parameters, [r.chi2]
    else:
        r = refit(model, rec, start, free, angle_idx=train, spp=SPP, seed=DEFAULT_SEED + 202, iterations=8,
                  model_variance=_render_variance(before, 6), noise_scale=floor, uncertainties=False,
                  objective=DECORRELATED, noise_variance=yard)
        p, hist = r.parameters, [r.chi2]
    c = indep(model, p)
    out[w] = {"params": {k: p[k] for k in free}, "chi2_indep": c, "hist": hist, "time_s": time.perf_counter() - t}
    print(f"{w}: indep {c:.1f}  {({k: round(p[k], 4) for k in free})}  {time.perf_counter() - t:.0f} s", flush=True)
    (ROOT / f"benchmarks/results/exp_decorrelated_refit_{CASE}_{SPP}{'' if EXT in CASE else '_' + EXT}.json").write_text(json.dumps(out, indent=1))
