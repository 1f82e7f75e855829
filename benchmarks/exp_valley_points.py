"""Probe: which of several fitted points of one paper-simulation case does the loss prefer,
scored on common seed pairs?

Two fits of the same recording that end at different sigma_t along the sigma_t / phase valley
(e.g. the estimator's own fit and a fit started from the Mie table's projection) can have
losses without render noise whose ratios to the truth's differ by less than either ratio's
standard error. Their *difference* at common seeds is what decides which the family prefers,
and what a fixed-seed optimiser compares. This scores each point's loss without render noise
(`estimate.fit.loss_at`'s "loss_unbiased": two independent renders per seed pair, `--spp`
each, the calibrated scale) at `--pairs` seed pairs shared by all points and the truth, and
prints each point's ratio to the truth's and its paired difference to the first point, with
standard errors over the pairs.

    .venv/bin/python benchmarks/exp_valley_points.py FIT.json [FIT.json ...] [--key free_refit]
        [--degree M] [--pairs 8] [--spp 16384] [--first 1000] [--out FILE.json]

Each FIT is a `bench_paper_sim.py` fit row (its cached fit JSON) or an
`exp_phase_projection.py` results file (`--key` picks its point: sad_fit, phase_only or
free_refit; `--degree` its row, where it holds several). All must be of one case, recorded by
the light engine from the Mie table.
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


def load_point(path: str, key: str, degree: int | None = None) -> dict[str, Any]:
    """(case, model, parameters, label) of one fit file. An `exp_phase_projection` file holds a
    row per degree: `degree` picks one, and is needed where it holds more than one. A
    `bench_paper_sim` fit row must be of `degree` where one is given."""
    doc = json.loads(Path(path).read_text())
    wanted = None if degree is None else f"exp{degree}"
    if isinstance(doc, list):   # exp_phase_projection's rows, one per degree
        held = ", ".join(str(r.get("model", "?")) for r in doc) or "no rows"
        rows = [r for r in doc if wanted is None or r.get("model") == wanted]
        if len(rows) != 1:
            raise ValueError(f"{path}: no {wanted or 'fit'} row (it holds {held})" if not rows
                             else f"{path} holds {held}: pick one with --degree")
        row, point, label = rows[0], rows[0].get(key), f"{Path(path).name}:{rows[0]['model']}:{key}"
        if point is None:
            raise ValueError(f"{path}: no {key!r} point in its {row['model']} row")
    else:
        if "parameters" not in doc or "case" not in doc:
            raise ValueError(f"{path}: not a bench_paper_sim fit row")
        if wanted is not None and doc["model"] != wanted:
            raise ValueError(f"{path} is an {doc['model']} fit, not {wanted}")
        row, point, label = doc, doc, Path(path).name
    return {"case": row["case"], "diameter_um": row["diameter_um"], "sigma_t_true": row["sigma_t_true"],
            "model": row["model"], "parameters": dict(point["parameters"]), "label": label}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("fits", nargs="+", help="fit files of one case (the first is the reference of the differences)")
    ap.add_argument("--key", default="free_refit", help="exp_phase_projection files: which point (free_refit)")
    ap.add_argument("--degree", type=int, default=None,
                    help="exp_phase_projection files of several degrees: which degree's row")
    ap.add_argument("--pairs", type=int, default=8, help="seed pairs (8)")
    ap.add_argument("--spp", type=int, default=16384, help="spp of each render (16384)")
    ap.add_argument("--first", type=int, default=bench.UNBIASED_SEED, help="first pair's seed")
    ap.add_argument("--truth-spp", type=int, default=16384, help="the recording's truth spp (its cache name)")
    ap.add_argument("--out", default=None, help="results JSON")
    args = ap.parse_args()
    if args.pairs < 2 or args.spp < 2:
        ap.error("--pairs and --spp must be at least 2")
    try:
        points = [load_point(f, args.key, args.degree) for f in args.fits]
    except (OSError, ValueError, KeyError) as e:
        ap.error(f"{e}")
    if len({p["case"] for p in points}) != 1:
        ap.error("the fits are of different cases: " + ", ".join(sorted({p["case"] for p in points})))
    bench.TRUTH_SPP, bench.TRUTH_ENGINE, bench.TRUTH_PHASE = args.truth_spp, "light", "table"
    from estimate.loss import calibrated_scale

    d, s = points[0]["diameter_um"], points[0]["sigma_t_true"]
    pb, mat = bench.case_inputs(d, s)
    scale = calibrated_scale(pb.session_path, "g", pb.beam.power()).scale
    t0 = time.monotonic()
    truth = np.array(bench.pair_losses(pb, mat.model, mat.parameters(), args.spp, scale,
                                       forward=bench.truth_forward(pb, mat), pairs=args.pairs, first=args.first))
    print(f"{points[0]['case']}: truth's loss {truth.mean():.4g} over {args.pairs} pairs "
          f"({time.monotonic() - t0:.0f} s)", flush=True)
    rows = []
    ref: np.ndarray | None = None
    for p in points:
        t0 = time.monotonic()
        losses = np.array(bench.pair_losses(pb, p["model"], p["parameters"], args.spp, scale,
                                            pairs=args.pairs, first=args.first))
        ratio, ratio_se = bench.loss_ratio(losses, truth)
        row = {"label": p["label"], "model": p["model"], "sigma_t": p["parameters"]["sigma_t"],
               "albedo": p["parameters"]["albedo"], "sigma_t_rel_error": p["parameters"]["sigma_t"] / s - 1.0,
               "losses": losses.tolist(), "ratio": ratio, "ratio_se": ratio_se}
        line = (f"  {p['label']}: sigma_t {100 * row['sigma_t_rel_error']:+.2f} %, loss / truth's "
                f"{row['ratio']:.3f} +- {row['ratio_se']:.3f}")
        if ref is None:
            ref = losses
        else:
            diff = (losses - ref) / truth
            row["diff_to_first"] = float(diff.mean())
            row["diff_to_first_se"] = float(diff.std(ddof=1) / np.sqrt(args.pairs))
            line += f"; minus the first's {row['diff_to_first']:+.4f} +- {row['diff_to_first_se']:.4f}"
        rows.append(row)
        print(line + f" ({time.monotonic() - t0:.0f} s)", flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps({"case": points[0]["case"], "pairs": args.pairs, "spp": args.spp,
                                              "first_seed": args.first, "truth_losses": truth.tolist(),
                                              "points": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
