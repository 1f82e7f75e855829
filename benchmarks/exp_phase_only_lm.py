"""Probe: the estimator's phase-only fit from its own start, at the true material, with the
default fit settings and with a variant (session 88: the Levenberg-Marquardt's samples).

`exp_phase_projection.py --phase-fit` starts the phase-only fit from the exp<M> fitted to the
Mie table itself, a start no user has. This one starts it from the estimator's own coarse
search, sigma_t and the albedo held at the truth, so the gap between the two says how much of
a free fit's excess loss is the phase optimisation's, before any trade with sigma_t. Each fit
is scored as `bench_paper_sim.unbiased_losses` scores one (ratio to the truth's loss without
render noise, `--spp` each render, the benchmark's seed pairs).

    .venv/bin/python benchmarks/exp_phase_only_lm.py [--case d0.5_s6] [--model exp7] \
        [--variant lm_degree_iterations=200 --variant lm_degree_spp_factor=16] [--spp 16384] \
        [--truth-spp 16384] [--out FILE.json]

Session 88, d 0.5 um / sigma_t 6, exp7, the LM in the monomial coefficients (the default
then): 1.71 +- 0.02 (136 s, 4 LM steps accepted); LM at 16 x final_spp (200 steps at most)
1.36 +- 0.02 (415 s, 9 steps); from the table's own exp7 fit 1.19 +- 0.04
(`exp_phase_only_lm_session88_d05s6_exp7.json`, `exp_phase_projection_session88_d05.json`).
Session 89, the LM in Legendre coefficients (the default since): d 0.5 um / sigma_t 6, exp7
1.21 +- 0.05 (126 s); d 0.5 um / sigma_t 2, exp10 1.09 +- 0.01 (77 s) against 1.37 +- 0.02 in
monomial steps (`--variant lm_basis=monomial`; `exp_phase_only_lm_session89_*.json`).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_paper_sim as bench  # noqa: E402
import exp_phase_projection as projection  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--case", default="d0.5_s6", help="a bench_paper_sim case (d0.5_s6)")
    ap.add_argument("--model", default="exp7", help="exp<M> (exp7)")
    ap.add_argument("--variant", action="append", default=[], metavar="KEY=VALUE",
                    help="fit settings of the second fit (repeat; default: the LM at 16 x final_spp, 200 steps)")
    ap.add_argument("--spp", type=int, default=16384, help="samples per pixel of each scoring render (16384)")
    ap.add_argument("--truth-spp", type=int, default=16384, help="the recordings' spp (their cache name)")
    ap.add_argument("--no-default", action="store_true", help="fit the variant only (the default's figure is known)")
    ap.add_argument("--out", default=None, help="results JSON")
    args = ap.parse_args()
    from fit_overrides import parse_overrides, settings_with

    try:
        d, s = bench.parse_one_case(args.case, "--case")
        variant = parse_overrides(args.variant or ["lm_degree_iterations=200", "lm_degree_spp_factor=16"])
    except ValueError as e:
        ap.error(str(e))
    if not args.model.startswith("exp") or not args.model[3:].isdigit():
        ap.error(f"--model {args.model!r}: give an exponential model, e.g. exp7")
    bench.TRUTH_SPP, bench.TRUTH_ENGINE, bench.TRUTH_PHASE = args.truth_spp, "light", "table"

    from estimate.fit import fit_channel
    from estimate.loss import calibrated_scale

    pb, mat = bench.case_inputs(d, s)
    scale = calibrated_scale(pb.session_path, "g", pb.beam.power()).scale
    truths = projection.truth_losses(pb, mat, args.spp, scale)
    material = {"sigma_t": s, "albedo": bench.ALBEDO}
    out: list[dict[str, Any]] = []
    runs = [("default", {}), ("variant", variant)][1 if args.no_default else 0:]
    for label, overrides in runs:
        t0 = time.monotonic()
        r = fit_channel(pb, args.model, fixed=material, settings=settings_with(overrides, seed=0, scale="calibrated"))
        scored = projection.score(pb, args.model, dict(r.parameters), args.spp, scale, truths)
        row = {"case": bench.case_name(d, s), "model": args.model, "label": label, "overrides": overrides,
               "time_s": time.monotonic() - t0, "lm_steps": r.lm_steps, "lm_losses": r.lm_losses,
               "parameters": r.parameters,
               "truth_loss_unbiased": float(np.mean(truths)), **scored}
        out.append(row)
        print(f"{row['case']} {args.model} phase only, {label} {overrides}: {scored['ratio']:.3f} +- "
              f"{scored['ratio_se']:.3f} ({row['time_s']:.0f} s, {r.lm_steps} LM steps)", flush=True)
        if args.out:
            Path(args.out).write_text(json.dumps(out, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
