"""Experiment (session 83, not part of the pipeline): does a paper-simulation recording fix
sigma_t when the phase function is free? The profile of the loss over sigma_t.

    .venv/bin/python benchmarks/exp_sigma_t_profile.py [CASE] [MODEL] [--sigmas 5.4,6,6.6,7.2]
        [--pairs 8] [--pair-spp 4096] [--truth-spp 1024] [--points FILE ...]

CASE a `bench_paper_sim.py` case on the Mie-table recordings (default d0.5_s6; recorded on
first use, as the benchmark does), MODEL an exponential model (default exp7). For each
sigma_t of `--sigmas` (1/mm) the albedo and the phase are fitted to the recording with
sigma_t held there (`fit_channel(fixed=...)`, the calibrated scale, seed 0). Each fitted
point, the truth and the fits of any `--points` files (bench_paper_sim results JSON of the
same case) are then scored by the loss without render noise averaged over `--pairs` seed
pairs at 4096 spp each (`estimate.loss.decorrelated_loss`; the benchmark's "unbiased" ratio
takes one pair, whose ratio to the truth's scatters by 2-4 % on this case), as a ratio to
the truth's loss over the same pairs, with its standard error.

A profile flat within that error over a range of sigma_t means the recording cannot tell
those values apart: sigma_t trades with the phase's asymmetry at fixed sigma_a and
sigma_s (1 - g). Writes benchmarks/results/exp_sigma_t_profile_<CASE>[_spp<N>]_<MODEL>.json
(`_spp<N>` with `--truth-spp N` off the default).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_paper_sim as bps  # noqa: E402

#: samples per pixel of each render of a scoring pair (the benchmark's UNBIASED_SPP)
PAIR_SPP = bps.UNBIASED_SPP
#: the scoring pairs' seeds: 1000, 1001; 1002, 1003; ... (apart from the fits' and the benchmark's 4242)
FIRST_PAIR_SEED = 1000


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", nargs="?", default="d0.5_s6")
    ap.add_argument("model", nargs="?", default="exp7")
    ap.add_argument("--sigmas", default="5.4,6,6.6,7.2", help="held sigma_t values (1/mm), a comma list")
    ap.add_argument("--pairs", type=int, default=8, help="seed pairs of the scoring loss")
    ap.add_argument("--points", nargs="*", default=[], help="bench_paper_sim results JSON whose fits of the case to score too")
    ap.add_argument("--pair-spp", type=int, default=PAIR_SPP,
                    help=f"samples per pixel of each scoring render ({PAIR_SPP}; 16384 brings a forward medium's "
                         "ratio from +-0.25 to +-0.03)")
    ap.add_argument("--truth-spp", type=int, default=bps.DEFAULT_TRUTH_SPP,
                    help="the recording's samples per pixel (bench_paper_sim.py --truth-spp; output named for it)")
    args = ap.parse_args()
    try:
        d, s = bps.parse_one_case(args.case, "CASE")
    except ValueError as e:
        ap.error(str(e))
    if args.pair_spp < 2:
        ap.error(f"--pair-spp {args.pair_spp}: use at least 2 samples per pixel")
    bps.TRUTH_SPP = args.truth_spp
    spp_tag = "" if args.truth_spp == bps.DEFAULT_TRUTH_SPP else f"_spp{args.truth_spp}"
    if args.pair_spp != PAIR_SPP:
        spp_tag += f"_pairs{args.pair_spp}"
    from fit_overrides import settings_with

    from estimate.fit import fit_channel, forward_model
    from estimate.loss import calibrated_scale, decorrelated_loss, reference_delta

    bps.TRUTH_ENGINE, bps.TRUTH_PHASE = "light", "table"
    pb, mat = bps.case_inputs(d, s)
    fs = calibrated_scale(pb.session_path, "g", pb.beam.power()).scale
    settings = settings_with({}, seed=0, scale="calibrated")
    d_ref = reference_delta(settings.delta_range)
    fm_model = forward_model(pb, args.model)     # one for every held point
    points: dict[str, tuple[Any, dict[str, float], dict[str, Any]]] = {
        "truth": (bps.truth_forward(pb, mat), mat.parameters(), {"sigma_t": s, "albedo": bps.ALBEDO})}
    for sig in (float(x) for x in args.sigmas.split(",")):
        t0 = time.monotonic()
        f = fit_channel(pb, args.model, settings=settings, fixed={"sigma_t": sig}, forward=fm_model)
        info = {"sigma_t": sig, "albedo": f.parameters["albedo"], "albedo_se": f.uncertainties.get("albedo"),
                "fit_time_s": time.monotonic() - t0, "phase": {k: v for k, v in f.parameters.items() if k.startswith("phase.")}}
        print(f"held sigma_t {sig}: albedo {info['albedo']:.4f}, {info['fit_time_s']:.0f} s", flush=True)
        points[f"held {sig:g}"] = (fm_model, dict(f.parameters), info)
    for fn in args.points:
        for row in json.loads(Path(fn).read_text())["fits"]:
            if row["case"] == args.case:
                fm = fm_model if row["model"] == args.model else forward_model(pb, row["model"])
                points[f"{Path(fn).name}: {row['model']}"] = (fm, row["parameters"],
                                                              {"sigma_t": row["sigma_t"], "albedo": row["albedo"]})
    losses: dict[str, list[float]] = {k: [] for k in points}
    for i in range(args.pairs):
        seed = FIRST_PAIR_SEED + 2 * i
        for name, (fm, params, _) in points.items():
            a, b = fm.render_profiles_many([(params, seed), (params, seed + 1)], pb.angles_deg, spp=args.pair_spp)
            losses[name].append(decorrelated_loss(pb.measured, a, b, pb.valid, fs, d_ref))
    truth = np.array(losses["truth"])
    rows = []
    for name, (_, _, info) in points.items():
        ratio = np.array(losses[name]) / truth
        se = float(np.std(ratio, ddof=1) / np.sqrt(len(ratio))) if len(ratio) > 1 else float("nan")
        rows.append({"point": name, **info, "loss_ratio": float(ratio.mean()), "loss_ratio_se": se,
                     "losses": losses[name]})
        print(f"{name:40s} sigma_t {info['sigma_t']:.3f} albedo {info['albedo']:.4f} "
              f"loss / truth's {ratio.mean():.4f} +- {se:.4f}", flush=True)
    out = ROOT / "benchmarks" / "results" / f"exp_sigma_t_profile_{args.case}{spp_tag}_{args.model}.json"
    out.write_text(json.dumps({"case": args.case, "model": args.model, "pairs": args.pairs, "pair_spp": args.pair_spp,
                               "rows": rows}, indent=1, default=float))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
