"""Benchmark: do the reported uncertainties cover the errors over independent noise draws?

`bench_estimate.py` fits one synthetic session; its error against its uncertainty is one draw.
This script makes --draws synthetic sessions of the same truth (exp3, sigma_t 2 /mm, albedo 0.9,
10 angles; tests/synth_session.py), each with its own noise seed (sensor noise and the frozen
Monte Carlo noise of the 32768-spp truth renders), fits each once with `rig estimate`'s defaults
(the calibrated scale; fit seed = draw seed), and compares the spread of the estimates with the reported 1-sigma
uncertainties, per parameter and for the derived sigma_a, sigma_s' and g:

- z = (estimate - truth) / uncertainty per draw; the fraction with |z| <= 1 (68 % expected) and
  |z| <= 2 (95 %), and the RMS of z (1 when the uncertainties are right);
- the RMS error against the RMS reported uncertainty.

Each draw's result is kept in benchmarks/results/bench_coverage.json as soon as its fit ends, so
an interrupted run goes on where it stopped (`--fresh` starts again). About 100 s a draw on 2 cores
(session 61: 90 s of it the 32768-spp truth renders, 10 s the fit with the light engine).

    .venv/bin/python benchmarks/bench_coverage.py [--draws 8] [--fresh]
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_estimate import ANGLES, TRUTH

RESULT = ROOT / "benchmarks" / "results" / "bench_coverage.json"
CHANNEL = "g"
MODEL = "exp3"
TRUTH_SPP = 32768
SCALE = 2e5  # e-/s per unit radiance, as bench_estimate.py
DERIVED = ("sigma_a", "sigma_s_reduced", "g")


def _git_rev() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def fit_draw(seed: int, overrides: dict | None = None, truth_engine: str = "camera") -> dict:
    """Make the synthetic session of noise seed `seed`, fit it, return the errors and uncertainties.
    `overrides`: FitSettings fields changed for a trial (`--setting`)."""
    from fit_overrides import settings_with
    from synth_session import make_session

    from estimate.fit import FitSettings, fit_channel
    from estimate.problem import load_problem

    tmp = Path(tempfile.mkdtemp(prefix=f"bench_coverage_{seed}_"))
    try:
        session = make_session(tmp / "s", {CHANNEL: TRUTH}, angles=ANGLES, spp=TRUTH_SPP, width=320,
                               scale=SCALE, seed=seed, engine=truth_engine)
        t0 = time.monotonic()
        st = (settings_with(overrides, seed=seed, scale="calibrated") if overrides
              else FitSettings(seed=seed, scale="calibrated"))
        r = fit_channel(load_problem(session, CHANNEL), MODEL, settings=st)
        wall = time.monotonic() - t0
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    derived = r.derived()
    # Parts of the interval (fit_channel adds, in quadrature to the larger of the sandwich and the
    # Fisher bound, the iterates' spread, the polish points' standard error and any drift): which
    # one sets the width where the coverage is off.
    return {"seed": seed, "wall_s": wall, "parameters": r.parameters, "uncertainties": r.uncertainties,
            "derived": {k: derived[k] for k in DERIVED}, "polish_steps": len(r.polish),
            "reduced_chi2": r.reduced_chi2, "parts": {"fisher": r.fisher_uncertainties,
                                                      "sandwich": r.sandwich_uncertainties,
                                                      "optimizer_spread": r.optimizer_spread,
                                                      "polish_se": r.polish_se, "drift": r.drift}}


def _number(x: float | str | None) -> float:
    """A value of `derived_quantities`' entries: a float (the entries' type also covers their
    unit's str and an unknown uncertainty's None)."""
    assert isinstance(x, float), x
    return x


def summarise(draws: list[dict]) -> dict[str, dict[str, float]]:
    """Per quantity: mean error, RMS error, RMS reported uncertainty, RMS z, coverage at 1 and 2 sigma."""
    from estimate.derived import derived_quantities

    truth_derived = derived_quantities(MODEL, TRUTH)
    rows: dict[str, dict[str, float]] = {}
    for name in list(TRUTH) + list(DERIVED):
        errs, uncs = [], []
        for d in draws:
            if name in TRUTH:
                value, unc, true = d["parameters"][name], d["uncertainties"].get(name), TRUTH[name]
            else:
                value, unc, true = d["derived"][name]["value"], d["derived"][name]["uncertainty"], \
                    _number(truth_derived[name]["value"])
            if unc is None or not math.isfinite(unc) or unc <= 0:
                continue
            errs.append(value - true)
            uncs.append(unc)
        if not errs:
            continue
        n = len(errs)
        z = [e / u for e, u in zip(errs, uncs)]
        rows[name] = {"n": n, "truth": TRUTH[name] if name in TRUTH else _number(truth_derived[name]["value"]),
                      "mean_error": sum(errs) / n,
                      "rms_error": math.sqrt(sum(e * e for e in errs) / n),
                      "rms_uncertainty": math.sqrt(sum(u * u for u in uncs) / n),
                      "rms_z": math.sqrt(sum(v * v for v in z) / n),
                      "within_1sigma": sum(abs(v) <= 1 for v in z) / n,
                      "within_2sigma": sum(abs(v) <= 2 for v in z) / n}
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=8, help="number of noise draws (seeds 0 .. draws-1)")
    ap.add_argument("--fresh", action="store_true", help="forget the draws already in the result file")
    ap.add_argument("--out", type=Path, default=RESULT, help=f"result file (default {RESULT.relative_to(ROOT)})")
    ap.add_argument("--setting", action="append", default=[], metavar="KEY=VALUE",
                    help="a FitSettings field to change, e.g. engine=camera (JSON values; repeatable)")
    ap.add_argument("--truth-engine", choices=("camera", "light"), default="camera",
                    help="the render engine of the sessions' truth profiles (camera: not the estimator's "
                         "default, and with the frozen Monte Carlo noise of its 32768-spp renders)")
    args = ap.parse_args()
    from fit_overrides import parse_overrides
    try:
        overrides = parse_overrides(args.setting)
    except ValueError as e:
        print(f"bench_coverage: {e}", file=sys.stderr)
        return 2
    rev = _git_rev()
    out: Path = args.out
    state = {"draws": []} if args.fresh or not out.exists() else json.loads(out.read_text())
    done = {d["seed"] for d in state["draws"]}
    for seed in range(args.draws):
        if seed in done:
            continue
        d = fit_draw(seed, overrides, args.truth_engine)
        d["git"] = rev
        d["setting_overrides"] = overrides
        d["truth_engine"] = args.truth_engine
        state["draws"].append(d)
        err = d["parameters"]["sigma_t"] / TRUTH["sigma_t"] - 1
        print(f"draw {seed}: sigma_t {d['parameters']['sigma_t']:.4f} +- {d['uncertainties']['sigma_t']:.4f} "
              f"({err:+.1%}), albedo {d['parameters']['albedo']:.4f} +- {d['uncertainties']['albedo']:.4f}, "
              f"{d['wall_s']:.0f} s", flush=True)
        state["summary"] = summarise(state["draws"])
        out.write_text(json.dumps(state, indent=1, default=float))
    state["summary"] = summarise(state["draws"])
    out.write_text(json.dumps(state, indent=1, default=float))
    print(f"{'quantity':<16}{'n':>3}{'truth':>9}{'mean err':>10}{'rms err':>10}{'rms unc':>10}{'rms z':>7}"
          f"{'|z|<=1':>8}{'|z|<=2':>8}")
    for name, s in state["summary"].items():
        print(f"{name:<16}{s['n']:>3}{s['truth']:>9.4g}{s['mean_error']:>10.4g}{s['rms_error']:>10.4g}"
              f"{s['rms_uncertainty']:>10.4g}{s['rms_z']:>7.2f}{s['within_1sigma']:>8.0%}{s['within_2sigma']:>8.0%}")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
