"""Experiment (session 86, not part of the pipeline): does the degree rule see the gains of
better fits once its comparison renders are quieter than the recording?

    .venv/bin/python benchmarks/exp_degree_eval_spp.py CASE DEGREES SPPS [--truth-spp 16384]

CASE a `bench_paper_sim.py` case on the Mie-table recordings of the light engine (recorded on
first use, as the benchmark does), DEGREES a comma list (the first is the reference, e.g.
3,5), SPPS a comma list of the comparison renders' samples per pixel (e.g. 2048,8192,32768).
Each degree is fitted from the estimator's own start (`choose_degree(start_from="own")`'s
fits; cached under benchmarks/results/exp_degree_eval_spp/ as pickles). Then, for every spp,
the metric is made from the first degree's renders at that spp (`degree_chi2`, 4 seed
pairs) and each later degree's BIC gain over the first, with its standard error over the
pairs, is printed with what the metric is made of: the render variance of one pair's mean
over the HDR variance (s^2 v_render / var) over the valid pixels. Writes
benchmarks/results/exp_degree_eval_spp_<CASE>.json.
"""

from __future__ import annotations

import argparse
import json
import math
import pickle
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_paper_sim as bps  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case")
    ap.add_argument("degrees")
    ap.add_argument("spps")
    ap.add_argument("--truth-spp", type=int, default=16384)
    ap.add_argument("--seeds", type=int, default=4, help="seed pairs per spp")
    args = ap.parse_args()
    from fit_overrides import settings_with

    from estimate.fit import fit_channel
    from estimate.phase_degree import _free_count, degree_chi2

    bps.TRUTH_SPP = args.truth_spp
    bps.TRUTH_ENGINE, bps.TRUTH_PHASE = "light", "table"
    d, s = (float(x) for x in args.case[1:].split("_s"))
    pb, _ = bps.case_inputs(d, s)
    st = settings_with({}, seed=0, scale="calibrated")
    cache = ROOT / "benchmarks" / "results" / "exp_degree_eval_spp"
    cache.mkdir(parents=True, exist_ok=True)
    degrees = [int(x) for x in args.degrees.split(",")]
    fits = {}
    for m in degrees:
        f = cache / f"{bps.case_key(d, s)}_exp{m}_own.pkl"
        if f.exists():
            fits[m] = pickle.loads(f.read_bytes())
            continue
        t0 = time.monotonic()
        fits[m] = fit_channel(pb, f"exp{m}", settings=st)
        f.write_bytes(pickle.dumps(fits[m]))
        print(f"exp{m}: sigma_t {fits[m].parameters['sigma_t']:.4f} loss {fits[m].loss:.1f} "
              f"({time.monotonic() - t0:.0f} s)", flush=True)
    ln_pixels = math.log(int(np.sum(pb.valid)))
    rows = []
    for spp in (int(x) for x in args.spps.split(",")):
        t0 = time.monotonic()
        ref = fits[degrees[0]]
        c0, metric = degree_chi2(pb, ref, st, seeds=args.seeds, spp=spp)
        ok = metric.weights > 0
        f2 = (metric.noise_scale ** 2)[:, None] * np.ones_like(metric.weights)
        var = pb.variance
        srv = np.where(ok, 1.0 / np.where(ok, metric.weights * f2, 1.0) - var, np.nan)[ok]
        ratio = srv / var[ok]
        gains: dict[str, dict] = {}
        row: dict[str, object] = {"spp": spp, "ratio_mean": float(np.mean(ratio)), "ratio_median": float(np.median(ratio)),
               "ratio_p90": float(np.quantile(ratio, 0.9)), "noise_scale": [float(x) for x in metric.noise_scale],
               f"chi2_exp{degrees[0]}": c0, "gains": gains}
        for m in degrees[1:]:
            cm, _ = degree_chi2(pb, fits[m], st, seeds=args.seeds, metric=metric)
            dd = (np.asarray(c0) - np.asarray(cm)
                  + (_free_count(ref) - _free_count(fits[m])) * ln_pixels)
            gains[f"exp{m}"] = {"gain": float(dd.mean()), "se": float(dd.std(ddof=1) / math.sqrt(len(dd))),
                                       "chi2": cm}
        took = time.monotonic() - t0
        row["time_s"] = took
        rows.append(row)
        print(f"spp {spp}: s^2 v_r / var mean {np.mean(ratio):.2f} median {np.median(ratio):.2f} "
              f"p90 {np.quantile(ratio, 0.9):.2f}; exp{degrees[0]} chi2 {np.mean(c0):.1f}; "
              + "; ".join(f"{k} gain {v['gain']:+.1f} +- {v['se']:.1f}" for k, v in gains.items())
              + f" ({took:.0f} s)", flush=True)
    out = ROOT / "benchmarks" / "results" / f"exp_degree_eval_spp_{args.case}.json"
    out.write_text(json.dumps({"case": args.case, "truth_spp": args.truth_spp, "degrees": degrees,
                               "fits": {f"exp{m}": {"sigma_t": r.parameters["sigma_t"],
                                                     "albedo": r.parameters["albedo"], "loss": r.loss}
                                        for m, r in fits.items()},
                               "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
