"""Benchmark: one channel, 10 angles, from a session on disk to converged parameters.

The session is synthetic (tests/synth_session.py: profiles rendered by the forward model at
known exp3 parameters at --truth-spp (32768), scale 2e5 e-/s per unit, Poisson + read noise), or
`--session DIR --channel f` for a captured / simulated-bench session.
Prints a table and writes benchmarks/results/bench_estimate.json.

    .venv/bin/python benchmarks/bench_estimate.py [--session DIR --channel g] [--model exp3]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

TRUTH = {"sigma_t": 2.0, "albedo": 0.9, "phase.b1": 3.0, "phase.b2": 1.0, "phase.b3": 0.5}
ANGLES = [15.0, 30.0, 45.0, 60.0, 75.0, 105.0, 120.0, 135.0, 150.0, 165.0]


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--session")
    ap.add_argument("--channel", default="g")
    ap.add_argument("--model", default="exp3", help="exp<M>, tthg, or expauto (rig estimate --degree auto)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--truth-spp", type=int, default=32768,
                    help="samples per pixel of the synthetic session's renders (their Monte Carlo noise is "
                         "frozen into the data and not in its variance channel; 4096 until session 4)")
    ap.add_argument("--scale", choices=("calibrated", "free"), default="calibrated",
                    help="intensity scale: from the calibration and the lens (default, as rig estimate) or fitted")
    ap.add_argument("--keep-session", metavar="DIR",
                    help="write the synthetic session to DIR and keep it, or reuse the one already there "
                         "(how it was made is recorded beside it); saves ~2 min a run")
    ap.add_argument("--out", metavar="FILE", help="write the results here instead of "
                    "benchmarks/results/bench_estimate.json (for trials of other settings)")
    ap.add_argument("--setting", action="append", default=[], metavar="KEY=VALUE",
                    help="a FitSettings field to change, e.g. polish_one_sided=false (JSON values; repeatable)")
    args = ap.parse_args()
    from fit_overrides import parse_overrides, settings_with

    from estimate.errors import ModelParameterError
    from estimate.fit import fit_channel, loss_at
    from estimate.mitsuba_env import init_mitsuba
    from estimate.problem import load_problem

    # Checked before the session is made or loaded: a typo costs a line, not minutes.
    try:
        settings = settings_with(parse_overrides(args.setting), seed=args.seed, scale=args.scale)
    except (ValueError, ModelParameterError) as e:
        print(e, file=sys.stderr)
        return 2

    tmp = None
    truth = None
    if args.session:
        session = Path(args.session)
    else:
        from synth_session import make_session

        recipe = {"channel": args.channel, "truth": TRUTH, "angles": ANGLES, "truth_spp": args.truth_spp,
                  "width": 320, "scale": 2e5}
        if args.keep_session:
            where = Path(args.keep_session)
            session = where / "s"
            stamp = where / "recipe.json"
            if stamp.is_file() and json.loads(stamp.read_text()) == recipe:
                print(f"reusing the synthetic session in {session}")
            else:
                if where.exists() and any(where.iterdir()):
                    print(f"{where} holds something other than this benchmark's session; "
                          "give an empty or new folder", file=sys.stderr)
                    return 2
                where.mkdir(parents=True, exist_ok=True)
        else:
            tmp = Path(tempfile.mkdtemp(prefix="bench_estimate_"))
            session = tmp / "s"
        if not session.exists():
            t = time.monotonic()
            make_session(session, {args.channel: TRUTH}, angles=ANGLES, spp=args.truth_spp, width=recipe["width"],
                         scale=recipe["scale"])
            print(f"synthetic session written in {time.monotonic() - t:.1f} s")
            if args.keep_session:
                stamp.write_text(json.dumps(recipe))
        truth = TRUTH
    try:
        load0 = os.getloadavg()[0]
        t0 = time.monotonic()
        c0 = time.process_time()
        pb = load_problem(session, args.channel)
        t_load = time.monotonic() - t0
        extra: dict = {}
        if args.model == "expauto":
            # `rig estimate --degree auto`: on this exp3 truth every higher degree should be
            # turned away (the rule's false-positive side).
            from estimate.phase_degree import choose_degree

            choice = choose_degree(pb, settings)
            r = choice.fit
            extra = {"degree_choice": choice.to_dict()}
        else:
            r = fit_channel(pb, args.model, settings=settings)
        wall = time.monotonic() - t0
        cpu = time.process_time() - c0  # all threads; / 2 ~ the wall time on 2 free cores
        load = os.getloadavg()[0]
        out = {"session": "synthetic" if truth else str(session), "channel": args.channel, "model": r.model,
               "scale_mode": args.scale, "optimizer": r.settings["optimizer"], "settings": r.settings,
               "variant": init_mitsuba().variant(), "load_average_1min_at_start": load0,
               "n_angles": pb.n_angles, "n_px": pb.n_px, "cpu_count": os.cpu_count(), "wall_s": wall,
               "cpu_s": cpu, "load_average_1min_at_end": load,
               "load_s": t_load, "fit_s": r.time_s, "iterations": r.iterations, "stop_reason": r.stop_reason,
               "spp_schedule": r.spp_schedule, "lm_losses": r.lm_losses, "parameters": r.parameters,
               "uncertainties": r.uncertainties, "loss": r.loss, "reduced_chi2": r.reduced_chi2,
               "start": r.start, "loss_curve": r.loss_curve, "gn_trace": r.gn_trace,
               "drift": r.drift, "still_drifting": r.drifting, "polish": r.polish,
               "stage_times_s": r.stage_times_s, **extra}
        if truth:
            fs = r.scale if args.scale == "calibrated" else None
            truth_model = "exp3" if args.model == "expauto" else args.model   # TRUTH's phase
            ev = loss_at(pb, truth_model, truth, spp=r.settings["final_spp"], fixed_scale=fs)
            out["truth"] = truth
            out["truth_spp"] = args.truth_spp
            out["loss_at_truth"] = ev["loss"]
            out["reduced_chi2_at_truth"] = ev["chi2"] / r.dof
            # Fit vs truth without the renders' Monte Carlo variance (which grows with sigma_t
            # and the albedo and biases the plain loss): decorrelated losses, same seeds, 4096 spp.
            u_fit = loss_at(pb, r.model, r.parameters, spp=4096, seed=777, fixed_scale=fs)["loss_unbiased"]
            u_truth = loss_at(pb, truth_model, truth, spp=4096, seed=777, fixed_scale=fs)["loss_unbiased"]
            out["loss_unbiased"] = u_fit
            out["loss_unbiased_at_truth"] = u_truth
            out["loss_unbiased_ratio"] = u_fit / u_truth
            out["sigma_t_rel_error"] = abs(r.parameters["sigma_t"] / truth["sigma_t"] - 1)
            out["albedo_abs_error"] = abs(r.parameters["albedo"] - truth["albedo"])
        print(f"{'quantity':<24}value")
        for k in ("n_angles", "n_px", "wall_s", "cpu_s", "load_average_1min_at_start", "load_average_1min_at_end", "iterations", "stop_reason", "spp_schedule", "loss",
                  "loss_at_truth", "loss_unbiased", "loss_unbiased_at_truth", "loss_unbiased_ratio", "reduced_chi2", "reduced_chi2_at_truth", "sigma_t_rel_error", "albedo_abs_error"):
            if k in out:
                v = out[k]
                print(f"{k:<24}{v:.4g}" if isinstance(v, float) else f"{k:<24}{v}")
        print("stage wall times [s]", r.stage_times_s)
        print("parameters", {k: round(v, 4) for k, v in r.parameters.items()})
        print("uncertainties", {k: round(v, 4) for k, v in r.uncertainties.items()})
        for i, ps in enumerate(r.polish):
            print(f"polish step {i + 1}: {'kept' if ps['accepted'] else 'undone'}"
                  f"{' after ' + str(ps['halvings']) + ' halving(s)' if ps['halvings'] else ''}, loss without render "
                  f"noise {ps['loss']:.3g} -> {ps['loss_new']:.3g}, step chi2 {ps.get('step_chi2', float('nan')):.1f}, "
                  f"{ps.get('spp', '?')} spp, {ps.get('jacobians', '?')} new Jacobian(s), "
                  f"sigma_t step {ps['step'].get('sigma_t', 0.0):+.4f}"
                  + (f", at {ps['point']['sigma_t']:.4f}" if ps.get("point") and "sigma_t" in ps["point"] else ""))
        print("drift (mean step of the averaged polish points, else the last polish step, else over the last "
              "windows)", {k: round(v, 4) for k, v in r.drift.items()},
              "still drifting:", r.drifting or "none")
        out["derived"] = r.derived()
        print("derived", {k: (round(v["value"], 4), v["uncertainty"] and round(v["uncertainty"], 4))
                          for k, v in out["derived"].items()})
        res = Path(args.out) if args.out else ROOT / "benchmarks" / "results" / "bench_estimate.json"
        res.write_text(json.dumps(out, indent=1, default=float))
        print(f"wrote {res}")
    finally:
        if tmp:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
