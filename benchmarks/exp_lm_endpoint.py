"""Probe: where a paper-simulation fit's end point stands, by its noise budget and by fresh-seed
Gauss-Newton steps from it.

Two questions about a fit of `bench_paper_sim.py` (a cached fit row of one case recorded by the
light engine from the Mie table):

1. **Noise budget.** How far should its sigma_t and albedo scatter, and from which noise? At
   the fit's parameters, the log residuals' Jacobian A (the light engine's score columns,
   two renders at `--spp`; printed with their mean's matrix and with their cross product,
   see the code) and each pixel's variance in log units give the
   linear sandwich sd of each parameter, e^T (A^T A)^-1 A^T D A (A^T A)^-1 e, for D = the
   HDR (sensor) variance, the recording's own frozen render noise (a render at its truth
   spp) and the noise of the LM's renders at its last stage's spp (its fixed-seed optimum
   holds that noise as signal); with each angle's share of sigma_t's variance.
2. **Fresh-seed Gauss-Newton chain** (`--chain N`): N full Gauss-Newton steps in the fit's
   coordinates (log sigma_t, logit albedo, ...), each from two new renders at `--spp`, with
   the decorrelated gradient (J_A^T r_B + J_B^T r_A) / 2 and the mean Jacobian's matrix (or
   `--gradient mean`: J^T r of the two renders' means, whose expectation also holds the
   gradient of the renders' variance, as the plain loss's does). Where the fit sits at the
   optimum, the chain's points scatter about it by their two renders' noise taken through
   the matrix.

    .venv/bin/python benchmarks/exp_lm_endpoint.py FIT.json [--spp 8192] [--chain 4]
        [--gradient decorrelated|mean] [--seed 1001] [--out benchmarks/results/exp_lm_endpoint_<case>.json]

Session 91, exp10 on d 0.5 um / sigma_t 6 (sigma_t +3.27 %, `docs/estimation-log.md`): with the mean
matrix the budget grew with the Jacobians' spp (the LM's part 0.20 % at 1024 spp, 0.55 % at
16384; the recording's own render noise 0.28 % to 0.77 %), so it is a lower bound there; the
cross matrix was still too noisy at 16384 spp. Chained decorrelated steps moved sigma_t by about
1.5 points each.
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


def _row(path: str, row: int) -> dict:
    doc = json.loads(Path(path).read_text())
    return doc["fits"][row] if isinstance(doc, dict) and "fits" in doc else doc


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("fit", help="a bench_paper_sim fit row (JSON): its cached fit file or a results file")
    ap.add_argument("--row", type=int, default=0, help="which of a results file's fits (0)")
    ap.add_argument("--spp", type=int, default=8192, help="spp of each of the two renders per point (8192)")
    ap.add_argument("--chain", type=int, default=0, help="fresh-seed Gauss-Newton steps to chain (0: the budget only)")
    ap.add_argument("--gradient", choices=("decorrelated", "mean"), default="decorrelated",
                    help="the chain's gradient: decorrelated (default) or mean (J^T r of the renders' means)")
    ap.add_argument("--seed", type=int, default=1001, help="first render seed (each point takes the next two)")
    ap.add_argument("--truth-spp", type=int, default=16384, help="the recording's truth spp (its cache name)")
    ap.add_argument("--out", default=None, help="results JSON")
    args = ap.parse_args()
    if args.spp < 2 or args.chain < 0:
        ap.error("--spp must be at least 2 and --chain at least 0")
    try:
        r = _row(args.fit, args.row)
    except (OSError, ValueError, KeyError, IndexError) as e:
        ap.error(f"{args.fit}: not a bench_paper_sim fit row ({e})")
    if r.get("truth_engine") != "light" or r.get("truth_phase") != "table":
        ap.error("the fit must be of a case recorded by the light engine from the Mie table")
    bench.TRUTH_SPP, bench.TRUTH_ENGINE, bench.TRUTH_PHASE = args.truth_spp, "light", "table"
    from estimate.fit import FitSettings, forward_model, reference_delta
    from estimate.loss import calibrated_scale, log_hdr_variance, log_measured, log_residual
    from estimate.polish import log_residual_columns
    from estimate.transforms import transform_for

    d, s = r["diameter_um"], r["sigma_t_true"]
    pb, _ = bench.case_inputs(d, s)
    p = dict(r["parameters"])
    names = list(p)
    fm = forward_model(pb, r["model"])
    angles = [float(a) for a in pb.angles_deg]
    tr = [transform_for(n, fm.specs[n], None, 0.5 * pb.measured.shape[-1] * pb.geometry.pixel_mm) for n in names]
    scale = calibrated_scale(pb.session_path, "g", pb.beam.power()).scale
    valid = np.asarray(pb.valid, bool)
    lm, dlt = log_measured(pb.measured, valid, scale, reference_delta(FitSettings().delta_range))
    n_v = int(valid.sum())
    stages = r.get("lm_stages") or []
    lm_spp = int(stages[-1]["spp"]) if stages else 0   # the LM's last stage (0: no LM)

    def point(q: dict, seed: int) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
        """Two renders at `args.spp` (seeds seed, seed + 1): their profiles, log residuals and
        Jacobians of the log residuals in the fit's coordinates."""
        z = [t.to_z(q[n]) for n, t in zip(names, tr)]
        profs = fm.render_profiles_many([(q, seed), (q, seed + 1)], angles, spp=args.spp)
        mats, res = [], []
        for prof, sd in zip(profs, (seed, seed + 1)):
            jac = fm.jacobian(q, angles, names, spp=args.spp, seed=sd)
            mats.append(log_residual_columns(jac, prof, valid, dlt, names, tr, z))
            res.append(log_residual(lm, prof, valid, dlt).ravel())
        return profs, res, mats

    def rel(q: dict) -> str:
        return f"sigma_t {100 * (q['sigma_t'] / s - 1):+.2f} %, albedo {q['albedo'] - bench.ALBEDO:+.4f}"

    t0 = time.monotonic()
    print(f"{r['case']} {r['model']}: from {rel(p)}", flush=True)
    profs, res, mats = point(p, args.seed)
    # one render's variance at args.spp, in log units, from the two renders' difference
    logs = [np.log(np.clip(q, 0, None) + dlt) for q in profs]
    d_one = np.where(valid, 0.5 * (logs[0] - logs[1]) ** 2, 0.0).ravel()
    d_sensor = np.where(valid, log_hdr_variance(pb.measured, pb.variance, scale, dlt), 0.0).ravel()
    sources = {"sensor": d_sensor, f"recording's render noise ({args.truth_spp} spp)": d_one * args.spp / args.truth_spp}
    if lm_spp:
        # the LM's optimum carries the noise of the mean of its two half-spp renders
        sources[f"LM's renders ({lm_spp} spp)"] = d_one * args.spp / lm_spp
    x_per_z = {n: abs(t.dx_dz(t.to_z(p[n]))) for n, t in zip(names, tr)}
    ang = np.repeat(np.arange(len(angles)), pb.measured.shape[-1])
    # The budget with two matrices. The mean Jacobian's Gram matrix holds its render noise's
    # Gram matrix too, largest along the weak sigma_t / phase directions, which shrinks
    # (A^T A)^-1 there and the budget with it (it grows with the Jacobians' spp). The two
    # renders' cross product A_A^T A_B has no such term in expectation (as `gn_polish`'s
    # `cross`), but at a few thousand spp it is itself too noisy along those directions.
    a = 0.5 * (mats[0] + mats[1])
    h_cross = 0.5 * (mats[0].T @ mats[1] + mats[1].T @ mats[0])
    influence = {"mean": (np.linalg.solve(a.T @ a, a.T),) * 2,
                 "cross": (np.linalg.solve(h_cross, mats[0].T), np.linalg.solve(h_cross, mats[1].T))}
    budget = []
    for matrix, (infl_a, infl_b) in influence.items():
        print(f"  budget with the {matrix} matrix of two {args.spp}-spp Jacobians", flush=True)
        for label, dv in sources.items():
            var = (infl_a * infl_b) @ dv
            w0 = infl_a[0] * infl_b[0] * dv
            shares = [float(w0[ang == i].sum() / w0.sum()) for i in range(len(angles))]
            sd_sigma = float(np.sqrt(max(var[0], 0.0)) * x_per_z["sigma_t"] / s)
            sd_albedo = float(np.sqrt(max(var[1], 0.0)) * x_per_z["albedo"])
            budget.append({"matrix": matrix, "source": label, "sigma_t_sd_rel": sd_sigma, "albedo_sd": sd_albedo,
                           "sigma_t_share_by_angle": shares})
            print(f"    {label:40s} sigma_t sd {100 * sd_sigma:.2f} %, albedo sd {sd_albedo:.4f}; "
                  f"by angle {' '.join(f'{x:.2f}' for x in shares)}", flush=True)
    chain = []
    q = p
    for k in range(args.chain):
        if k > 0:
            profs, res, mats = point(q, args.seed + 2 * k)
        a = 0.5 * (mats[0] + mats[1])
        if args.gradient == "decorrelated":
            g = 0.5 * (mats[0].T @ res[1] + mats[1].T @ res[0])
        else:
            g = a.T @ (0.5 * (res[0] + res[1]))
        dz = -np.linalg.solve(a.T @ a, g)
        loss = float(res[0] @ res[1] / n_v)
        z_new = [t.clamp_z(t.to_z(q[n]) + float(dz_)) for n, t, dz_ in zip(names, tr, dz)]
        q = {**q, **{n: t.to_x(zz) for n, t, zz in zip(names, tr, z_new)}}
        chain.append({"loss_before": loss, "sigma_t": q["sigma_t"], "albedo": q["albedo"]})
        print(f"  step {k + 1}: decorrelated loss before it {loss:.3e}; lands at {rel(q)}", flush=True)
    print(f"  ({time.monotonic() - t0:.0f} s)", flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps({"case": r["case"], "model": r["model"], "spp": args.spp,
                                              "gradient": args.gradient, "start": {"sigma_t": p["sigma_t"],
                                                                                    "albedo": p["albedo"]},
                                              "budget": budget, "chain": chain}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
