"""Experiment (session 50, not part of the pipeline): do Broyden updates of the refit's
Jacobian (`refit(jacobian_updates=BROYDEN)`) reach the same refits as central differences
at every iteration (FULL) with fewer renders?

    .venv/bin/python benchmarks/exp_broyden_refit.py [SESSION] [RUN] [CANDIDATES] [--start RUN2]

SESSION a session with an estimate run RUN (defaults: the simulated bench's recaptured
refractive-boundary session and its base fit); CANDIDATES a comma list of catalogue effects
(default refractive_boundary,angle_offset: the second pass's two longest refits in
session 49). Each candidate is refitted as a diagnosis' first round refits it: channel g,
the training angles, 256 spp, seed 1202, 8 iterations, the base evaluation's render
variance and noise floor in the weights; once with FULL and once with BROYDEN. `--start`
starts the refits from another run's parameters (a final fit, as the second pass does).
Each refit is judged by its own chi^2 and by the training chi^2 rendered independently
(the diagnosis' evaluation seeds, in the yardstick), and timed; renders are counted.
Writes benchmarks/results/exp_broyden_refit_<label>.json.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]

from estimate.diagnose import _free_names, _holdout, _render_variance, _start, _yardstick  # noqa: E402
from estimate.fit import model_phase  # noqa: E402
from estimate.forward import ForwardModel  # noqa: E402
from estimate.problem import load_problem  # noqa: E402
from estimate.refit import BROYDEN, DEFAULT_SEED, FULL, evaluate, refit  # noqa: E402
from estimate.results import read_run  # noqa: E402

BENCH = ROOT / "benchmarks/results/diagnose_cases/bench/refractive_boundary-1/session"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("session", nargs="?", default=str(BENCH))
    ap.add_argument("run", nargs="?", default="20261127T051712_exp3")
    ap.add_argument("candidates", nargs="?", default="refractive_boundary,angle_offset")
    ap.add_argument("--start", default=None, help="start the refits from this run's parameters")
    ap.add_argument("--channel", default="g")
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--modes", default=f"{FULL},{BROYDEN}")
    ap.add_argument("--label", default="bench_boundary")
    ap.add_argument("--trajectory", action="store_true", help="print every LM iteration with the renders so far")
    a = ap.parse_args()
    session = Path(a.session)
    doc = read_run(session / "estimates" / a.run)
    c = doc["channels"][a.channel]
    pb = load_problem(session, a.channel, (doc.get("settings") or {}).get("columns"))
    phase = model_phase(str(c.get("model") or "exp3"))
    models: dict[tuple[str, ...], ForwardModel] = {}
    renders = {"n": 0}

    def make_model(exts: list[str]) -> ForwardModel:
        key = tuple(exts)
        if key not in models:
            m = ForwardModel(pb.geometry, pb.beam, phase=phase, extensions=key, profile_y_shape=pb.y_shapes())
            inner = m._render_radiance

            def counted(*args, _inner=inner, **kw):
                renders["n"] += 1
                return _inner(*args, **kw)
            m._render_radiance = counted  # the experiment counts renders; the pipeline does not
            models[key] = m
        return models[key]

    class Trajectory(logging.Handler):
        """Each LM iteration's log line, with the renders counted so far."""

        def emit(self, record: logging.LogRecord) -> None:
            print(f"    [{renders['n']:4d} renders] {record.getMessage()}", flush=True)

    if a.trajectory:
        lg = logging.getLogger("estimate.refit")
        lg.setLevel(logging.DEBUG)
        lg.addHandler(Trajectory())
    base = {k: float(v) for k, v in c["parameters"].items()}
    start_params = base
    if a.start:
        start_params = {k: float(v) for k, v in read_run(session / "estimates" / a.start)["channels"][a.channel]
                        ["parameters"].items()}
    m0 = make_model([])
    before = evaluate(m0, base, pb, len(_free_names(m0, [])) + 1, spp=a.spp, seed=DEFAULT_SEED, repeats=6)
    yard = _yardstick(pb, before)
    train, _ = _holdout(len(pb.angles_deg))
    mv = _render_variance(before, 6)
    floor = before.residuals.noise_scale
    brightest = float(before.model.max())
    out = {"session": str(session), "run": a.run, "start": a.start or a.run, "spp": a.spp, "rows": []}
    for cand in a.candidates.split(","):
        m = make_model([cand])
        free = _free_names(m, [cand])
        start = _start(m, {k: v for k, v in start_params.items() if k in m.parameter_names}, cand, brightest)
        for mode in a.modes.split(","):
            renders["n"] = 0
            t = time.perf_counter()
            fit = refit(m, pb, start, free, angle_idx=train, spp=a.spp, seed=DEFAULT_SEED + 202, iterations=8,
                        model_variance=mv, noise_scale=floor, uncertainties=False, jacobian_updates=mode)
            dt = time.perf_counter() - t
            n_r = renders["n"]
            tr = evaluate(m, fit.parameters, pb, 0, spp=a.spp, seed=DEFAULT_SEED, repeats=6, angle_idx=train,
                          noise_variance=yard)
            row = {"candidate": cand, "mode": mode, "time_s": dt, "renders": n_r, "iterations": fit.iterations,
                   "chi2_refit": fit.chi2, "chi2_train_independent": tr.residuals.chi2_adjusted,
                   "parameters": fit.parameters}
            out["rows"].append(row)
            print(f"{cand:22s} {mode:8s} {dt:6.1f} s {n_r:4d} renders {fit.iterations:2d} it  chi2 {fit.chi2:9.1f}"
                  f"  independent {tr.residuals.chi2_adjusted:9.1f}  sigma_t {fit.parameters['sigma_t']:.4f}"
                  f"  albedo {fit.parameters['albedo']:.4f}", flush=True)
    dest = ROOT / f"benchmarks/results/exp_broyden_refit_{a.label}.json"
    dest.write_text(json.dumps(out, indent=1))
    print(f"wrote {dest.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
