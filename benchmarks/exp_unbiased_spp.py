"""Probe: the paper simulation's unbiased loss ratio (fit / truth) of cached fits at several spp.

`bench_paper_sim.unbiased_losses` scores a fit by the product of the log residuals of two
independent renders, which has no render-variance term; but each render's noise still enters
through the logarithm (E log(I + delta) < log(E I + delta)), so at too few spp the ratio
scatters between seed pairs. This renders the truth and every given fit at the same seed
pairs at each spp and prints the ratio and its standard error over the pairs, so that one
can see whether a ratio above the loss target is the fit's or the evaluation's.

    .venv/bin/python benchmarks/exp_unbiased_spp.py 4096,16384 FIT.json [FIT.json ...] \
        [--truth-spp 16384] [--out benchmarks/results/exp_unbiased_spp_<case>.json]

FIT.json: rows of `bench_paper_sim.py` (its cached fit files or the `fits` of a results
file, `--row N` picks one there) of one case, recorded by the light engine from the Mie table.
Session 87, d 0.5 um / sigma_t 2: exp7, exp8 and exp10 at 1.39-1.43 +- 0.25-0.27 at 4096 spp
and 1.41-1.47 +- 0.03 at 16384 (`docs/estimation-log.md`).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_paper_sim as bench  # noqa: E402

#: Seed pairs and their first seeds, as `bench_paper_sim.unbiased_losses`.
PAIRS = bench.UNBIASED_PAIRS


def _rows(paths: list[str], row: int) -> list[dict]:
    out = []
    for p in paths:
        doc = json.loads(Path(p).read_text())
        out.append(doc["fits"][row] if isinstance(doc, dict) and "fits" in doc else doc)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("spps", help="comma list of samples per pixel, e.g. 4096,16384")
    ap.add_argument("fits", nargs="+", help="bench_paper_sim fit rows (JSON) of one case")
    ap.add_argument("--row", type=int, default=0, help="which of a results file's fits (0)")
    ap.add_argument("--truth-spp", type=int, default=16384, help="the recording's truth spp (its cache name)")
    ap.add_argument("--out", default=None, help="results JSON")
    args = ap.parse_args()
    try:
        spps = [int(x) for x in args.spps.split(",")]
    except ValueError:
        ap.error(f"spps {args.spps!r}: give whole numbers, e.g. 4096,16384")
    if any(s < 2 for s in spps):
        ap.error(f"spps {args.spps!r}: use at least 2 samples per pixel")
    rows = _rows(args.fits, args.row)
    cases = {(r["diameter_um"], r["sigma_t_true"]) for r in rows}
    if len(cases) != 1 or any(r.get("truth_engine") != "light" or r.get("truth_phase") != "table" for r in rows):
        ap.error("the fits must be of one case, recorded by the light engine from the Mie table")
    bench.TRUTH_SPP, bench.TRUTH_ENGINE, bench.TRUTH_PHASE = args.truth_spp, "light", "table"
    from estimate.loss import calibrated_scale

    (d, s), = cases
    pb, mat = bench.case_inputs(d, s)
    scale = calibrated_scale(pb.session_path, "g", pb.beam.power()).scale
    truth_forward = bench.truth_forward(pb, mat)
    out = []
    for spp in spps:
        t0 = time.monotonic()
        truths = bench.pair_losses(pb, mat.model, mat.parameters(), spp, scale, forward=truth_forward, pairs=PAIRS)
        fits = [bench.pair_losses(pb, r["model"], r["parameters"], spp, scale, pairs=PAIRS) for r in rows]
        tr = np.asarray(truths)
        for r, f in zip(rows, fits):
            ratios = np.asarray(f) / tr
            line = {"case": r["case"], "spp": spp, "model": r["model"], "source": r.get("requested_model", r["model"]),
                    "sigma_t": r["parameters"]["sigma_t"], "ratio": float(np.mean(f) / np.mean(tr)),
                    "ratio_se": float(np.std(ratios, ddof=1) / np.sqrt(PAIRS)),
                    "loss_unbiased": float(np.mean(f)), "loss_unbiased_at_truth": float(np.mean(tr))}
            out.append(line)
            print(f"{line['case']} {line['source']} -> {line['model']} at {spp} spp: unbiased loss / floor "
                  f"{line['ratio']:.3f} +- {line['ratio_se']:.3f}", flush=True)
        print(f"  ({time.monotonic() - t0:.0f} s)", flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
