"""Experiment (session 82, not part of the pipeline): on a paper-simulation case, is a miss in
sigma_t the recording's (it cannot tell sigma_t from the phase) or the optimiser's (a better
point of the same phase family exists and the fit does not reach it)?

    .venv/bin/python benchmarks/exp_table_phase_start.py [CASE] [DEGREES]

CASE a `bench_paper_sim.py` case on the Mie-table recordings (default d0.5_s6; recorded on
first use, as the benchmark does), DEGREES a comma list (default 7,12). For each degree M, the
exponential function of degree M is fitted to the case's Mie table by `estimate.phase_fit`
(its ln p over the table's angles: not to the recording), and then:

- `fixed`: sigma_t and the albedo fitted to the recording with the phase held there;
- `at_truth`: that phase rendered at the true sigma_t and albedo;
- `free` (the first degree only): a free expM fit started from that phase, with sigma_t and
  the albedo started at exp3's point of session 82 (`--start-sigma-t`, `--start-albedo`).

Every loss is the loss without render noise over the truth's (4096 spp, seed 4242, the
calibrated scale: `bench_paper_sim.unbiased_losses`' measure). Writes
benchmarks/results/exp_table_phase_start_<CASE>[_spp<N>].json (`_spp<N>` with `--truth-spp N`
off the default); about 6 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_paper_sim as bps  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", nargs="?", default="d0.5_s6")
    ap.add_argument("degrees", nargs="?", default="7,12")
    ap.add_argument("--start-sigma-t", type=float, default=6.63, help="the free fit's start (1/mm)")
    ap.add_argument("--start-albedo", type=float, default=0.91, help="the free fit's start")
    ap.add_argument("--truth-spp", type=int, default=bps.DEFAULT_TRUTH_SPP,
                    help="the recording's samples per pixel (bench_paper_sim.py --truth-spp; output named for it)")
    args = ap.parse_args()
    bps.TRUTH_SPP = args.truth_spp
    spp_tag = "" if args.truth_spp == bps.DEFAULT_TRUTH_SPP else f"_spp{args.truth_spp}"
    from fit_overrides import settings_with

    from estimate.fit import fit_channel, loss_at
    from estimate.loss import calibrated_scale
    from estimate.mie import mie_poly
    from estimate.phase_fit import fit_model

    d, s = (float(x) for x in args.case[1:].split("_s"))   # bench_paper_sim.case_name's form
    bps.TRUTH_ENGINE, bps.TRUTH_PHASE = "light", "table"
    pb, mat = bps.case_inputs(d, s)
    fs = calibrated_scale(pb.session_path, "g", pb.beam.power()).scale

    def unbiased_loss(model: str, params: dict[str, float], forward: Any = None) -> float:
        ev = loss_at(pb, model, params, spp=bps.UNBIASED_SPP, seed=4242, fixed_scale=fs, forward=forward)
        return float(ev["loss_unbiased"])

    floor = unbiased_loss(mat.model, mat.parameters(), bps.truth_forward(pb, mat))
    truth = {"sigma_t": s, "albedo": bps.ALBEDO}
    rows: list[dict[str, Any]] = []
    for i, m in enumerate(int(x) for x in args.degrees.split(",")):
        model = f"exp{m}"
        tf = fit_model(mie_poly(d), model)
        phase = {f"phase.b{k}": float(tf.params["b"][k]) for k in range(1, m + 1)}
        row: dict[str, Any] = {"degree": m, "table_sad": tf.sad, "at_truth": unbiased_loss(model, {**truth, **phase}) / floor}
        t0 = time.monotonic()
        f = fit_channel(pb, model, settings=settings_with({}, seed=0, scale="calibrated"), fixed=phase)
        row["fixed"] = {"sigma_t": f.parameters["sigma_t"], "albedo": f.parameters["albedo"],
                        "sigma_t_se": f.uncertainties.get("sigma_t"), "loss": unbiased_loss(model, f.parameters) / floor,
                        "time_s": time.monotonic() - t0}
        if i == 0:
            t0 = time.monotonic()
            start = {**phase, "sigma_t": args.start_sigma_t, "albedo": args.start_albedo}
            g = fit_channel(pb, model, settings=settings_with({}, seed=0, scale="calibrated"), start=start)
            row["free"] = {"start": start, "sigma_t": g.parameters["sigma_t"], "albedo": g.parameters["albedo"],
                           "sigma_t_se": g.uncertainties.get("sigma_t"), "loss": unbiased_loss(model, g.parameters) / floor,
                           "phase": {k: v for k, v in g.parameters.items() if k.startswith("phase.")},
                           "time_s": time.monotonic() - t0}
        print(json.dumps(row, default=float), flush=True)
        rows.append(row)
    out = ROOT / "benchmarks" / "results" / f"exp_table_phase_start_{args.case}{spp_tag}.json"
    out.write_text(json.dumps({"case": args.case, "rows": rows}, indent=1, default=float))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
