"""Benchmark tool: the uncertainty recipe's parts against independent noise draws, offline.

`bench_coverage.py` measures one recipe per run (about 2 min a draw). This script fits the same
draws (synthetic sessions of `bench_estimate.py`'s truth, one noise seed each) once with the
defaults and keeps what the uncertainty stage saw: the arguments of
`estimate.uncertainties.sandwich_uncertainties` (the final point's residuals and every
Jacobian) and of `combined_uncertainties` (the polish points' standard error and drift). The
interval recipes are then recomputed from those inputs without re-fitting, so variants (the
cross-product floor, the meat, the polish's standard error) are compared on the same fits.

    .venv/bin/python benchmarks/coverage_variants.py capture --seeds 10-15 --dir /tmp/covvar
    .venv/bin/python benchmarks/coverage_variants.py analyse --dir /tmp/covvar

The paper simulation's fits (`bench_paper_sim.py`'s sessions, one fit each) the same way:

    .venv/bin/python benchmarks/coverage_variants.py capture-paper --seeds 0 --dir /tmp/covpaper
    .venv/bin/python benchmarks/coverage_variants.py analyse-paper --dir /tmp/covpaper
"""

from __future__ import annotations

import argparse
import math
import pickle
import shutil
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_coverage import CHANNEL, MODEL, SCALE, TRUTH_SPP
from bench_estimate import ANGLES, TRUTH

if TYPE_CHECKING:
    from estimate.problem import Problem


def _seeds(text: str) -> list[int]:
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(s) for s in text.split(",")]


def _fit_keeping_inputs(problem: Any, settings: Any) -> tuple[Any, dict[str, Any], float]:
    """`fit_channel(problem, MODEL)` with the uncertainty stage's inputs kept: the fit, those
    inputs (`kept["sandwich"]`, `kept["combined"]`) and the fit's wall time."""
    from estimate import fit

    kept: dict[str, Any] = {}
    real_sandwich, real_combined = fit.sandwich_uncertainties, fit.combined_uncertainties

    def sandwich(problem: Problem, params: Mapping[str, float], names: Sequence[str], scale: float,
                 profiles: np.ndarray, model_variance: np.ndarray, jac: Mapping[str, np.ndarray],
                 **kw: Any) -> tuple[dict[str, float], float, float]:
        kept["sandwich"] = {
            "problem": SimpleNamespace(measured=np.asarray(problem.measured), variance=np.asarray(problem.variance),
                                       valid=np.asarray(problem.valid)),
            "params": dict(params), "names": list(names), "scale": float(scale),
            "profiles": np.asarray(profiles), "model_variance": np.asarray(model_variance),
            "jac": {k: np.asarray(v) for k, v in jac.items()},
            "kw": {k: v for k, v in kw.items() if k != "covariance_out"},
        }
        kept["sandwich"]["kw"]["jac_more"] = [{k: np.asarray(v) for k, v in j.items()} for j in kw.get("jac_more", ())]
        return real_sandwich(problem, params, names, scale, profiles, model_variance, jac, **kw)

    def combined(base: Mapping[str, float], spread: Mapping[str, float], polish_se: Mapping[str, float],
                 drift: Mapping[str, float], polish_sd: Mapping[str, float], *,
                 polished: bool) -> tuple[dict[str, float], list[str]]:
        kept["combined"] = {"base": dict(base), "spread": dict(spread), "polish_se": dict(polish_se),
                            "drift": dict(drift), "polish_sd": dict(polish_sd), "polished": polished}
        return real_combined(base, spread, polish_se, drift, polish_sd, polished=polished)

    fit.sandwich_uncertainties, fit.combined_uncertainties = sandwich, combined
    try:
        t0 = time.monotonic()
        r = fit.fit_channel(problem, MODEL, settings=settings)
        return r, kept, time.monotonic() - t0
    finally:
        fit.sandwich_uncertainties, fit.combined_uncertainties = real_sandwich, real_combined


def capture(seed: int, out: Path) -> None:
    """Fit draw `seed` with the defaults; pickle the uncertainty stage's inputs and the result."""
    from synth_session import make_session

    from estimate import fit
    from estimate.problem import load_problem

    tmp = Path(tempfile.mkdtemp(prefix=f"covvar_{seed}_"))
    try:
        session = make_session(tmp / "s", {CHANNEL: TRUTH}, angles=ANGLES, spp=TRUTH_SPP, width=320,
                               scale=SCALE, seed=seed)
        r, kept, wall = _fit_keeping_inputs(load_problem(session, CHANNEL),
                                            fit.FitSettings(seed=seed, scale="calibrated"))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    kept.update(seed=seed, wall_s=wall, parameters=dict(r.parameters), uncertainties=dict(r.uncertainties),
                polish=[dict(e) for e in r.polish])
    out.mkdir(parents=True, exist_ok=True)
    (out / f"draw{seed}.pkl").write_bytes(pickle.dumps(kept))
    print(f"draw {seed}: {wall:.0f} s; " + ", ".join(f"{k} {r.parameters[k]:.4g} +- {r.uncertainties[k]:.2g}"
                                                     for k in TRUTH), flush=True)


def _interval(k: dict[str, Any], *, polish_se: bool = True, clip_b: bool = False, polish_corr: bool = False,
              fixed_b: float | None = None, **over: Any) -> tuple[dict[str, float], dict[str, dict[str, float]]]:
    """A kept fit's combined intervals, recomputed from its kept inputs with the sandwich's
    arguments changed by `over` (and the polish points' standard error left out without
    `polish_se`; the data meat's excess share clipped at 0, as until session 36, with
    `clip_b`; or set to `fixed_b`, an oracle), and the covariance that goes with them; with
    `polish_corr` the polish points' standard error carries the correlation of its steps'
    render noise there (`sandwich_uncertainties`' `render_correlation_out`)."""
    from estimate import uncertainties as un

    s = k["sandwich"]
    real = un.excess_share
    if clip_b:
        un.excess_share = lambda *a, **kw: {**(e := real(*a, **kw)), "b": max(e["b_raw"], 0.0)}
    elif fixed_b is not None:
        un.excess_share = lambda *a, **kw: {**real(*a, **kw), "b": fixed_b}
    try:
        sw: dict[str, dict[str, float]] = {}
        step: dict[str, dict[str, float]] = {}
        unc, _, _ = un.sandwich_uncertainties(s["problem"], s["params"], s["names"], s["scale"], s["profiles"],
                                              s["model_variance"], s["jac"],
                                              **{**s["kw"], "covariance_out": sw, "render_correlation_out": step,
                                                 **over})
    finally:
        un.excess_share = real
    c = k["combined"]
    out, _ = un.combined_uncertainties(unc, c["spread"], c["polish_se"] if polish_se else {}, c["drift"],
                                       c["polish_sd"], polished=c["polished"])
    names = s["names"]
    # The averaged iterates' covariance: their spread on the diagonal (none once polished).
    it_cov = np.diag([c["spread"].get(n, 0.0) ** 2 for n in names])
    pse = c["polish_se"] if polish_se and polish_corr else None
    return out, un.combined_covariance(names, out, sw, it_cov, pse, step if pse else None)


def _excess(k: dict[str, Any]) -> dict[str, float]:
    """The kept fit's data-meat excess share b (`estimate.uncertainties.excess_share`)."""
    from estimate.uncertainties import excess_share, log_residuals

    s = k["sandwich"]
    lr = log_residuals(s["problem"], s["scale"], s["profiles"], s["model_variance"], s["kw"]["delta_rel"])
    return excess_share(lr.r, lr.v_sensor, lr.v_eval, lr.valid)


#: Derived quantities scored by `analyse` (`estimate.derived`).
DERIVED = ("sigma_a", "sigma_s_reduced", "g")


def _number(x: float | str | None) -> float:
    """A value of `derived_quantities`' entries: a float (the entries' type also covers their
    unit's str and an unknown uncertainty's None)."""
    assert isinstance(x, float), x
    return x


def analyse(d: Path) -> None:
    from estimate.derived import derived_quantities

    draws = [pickle.loads(p.read_bytes()) for p in sorted(d.glob("draw*.pkl"))]
    if not draws:
        raise SystemExit(f"no draws in {d}: run `capture` first")

    variants: dict[str, dict[str, Any]] = {  # _interval's keyword arguments
        "as fitted": {},
        "data meat, b clipped at 0 (sessions 30-36)": {"data_meat": True, "clip_b": True},
        "data meat, b its posterior mean, the polish's share on the diagonal": {"data_meat": True},
        "data meat, b the truth's 1/16 (an oracle: the truth's 32768 spp against the evaluation's 2 x 1024)": {
            "data_meat": True, "fixed_b": 1 / 16},
        "b clipped, the polish's share with its steps' render correlation (tried in session 36)": {
            "data_meat": True, "clip_b": True, "polish_corr": True},
        "b its posterior mean, the polish's share with its steps' render correlation (session 37)": {
            "data_meat": True, "polish_corr": True},
        "b the oracle's 1/16, the polish's share with its steps' render correlation": {
            "data_meat": True, "fixed_b": 1 / 16, "polish_corr": True},
        "session 29's recipe (render noise in the meat too)": {"data_meat": False},
        "data meat, the Jacobians' cross products in the meat (sessions 30-33)": {"data_meat": True,
                                                                                 "meat_cross": True},
        "data meat, cross floor 0.01": {"data_meat": True, "cross_floor": 0.01},
        "data meat, cross floor 0.3": {"data_meat": True, "cross_floor": 0.3},
        "data meat, without the polish s.e.": {"data_meat": True, "polish_se": False},
        "session 29's, mean Jacobian only": {"data_meat": False, "jac_more": ()},
        "session 29's, without the polish s.e.": {"data_meat": False, "polish_se": False},
    }
    # Draws captured before session 30's recipe were fitted with data_meat off; they must
    # reproduce their own intervals (later ones did too, until the recipe changed again).
    same = [k for k in draws if not k["sandwich"]["kw"].get("data_meat")]
    if same:
        worst = max(abs(_interval(k)[0][p] / k["uncertainties"][p] - 1.0) for k in same for p in TRUTH)
        print(f"recomputed 'as fitted' against the fits' own intervals ({len(same)} draws fitted with "
              f"session 29's recipe): largest relative difference {worst:.2g}")
    print("the data meat's excess share per draw: " + "; ".join(
        f"{k['seed']}: b_raw {e['b_raw']:+.3f} +- {e['se']:.3f} -> b {e['b']:.3f}"
        for k in draws for e in [_excess(k)]))
    print(f"{len(draws)} draws (seeds {', '.join(str(k['seed']) for k in draws)}); RMS z per parameter "
          "(1 when the intervals are right), the share within 1 sigma (68 % expected) and the largest |z|; "
          "the derived quantities through the reported covariance")
    truth_derived = derived_quantities(MODEL, TRUTH)
    cols = [*TRUTH, *DERIVED]
    print("| recipe | " + " | ".join(cols) + " |")
    print("|---|" + "---|" * len(cols))
    for name, over in variants.items():
        zs: dict[str, list[float]] = {p: [] for p in cols}
        for k in draws:
            u, cov = _interval(k, **over)
            for p in TRUTH:
                if u.get(p, 0) > 0 and math.isfinite(u[p]):
                    zs[p].append((k["parameters"][p] - TRUTH[p]) / u[p])
            dq = derived_quantities(MODEL, k["parameters"], cov)
            for p in DERIVED:
                du = dq[p]["uncertainty"]
                if du:
                    zs[p].append((_number(dq[p]["value"]) - _number(truth_derived[p]["value"])) / _number(du))
        print(f"| {name} | " + " | ".join(
            f"{math.sqrt(np.mean(np.square(v))):.2f} ({100 * np.mean(np.abs(v) <= 1):.0f} %, max {np.max(np.abs(v)):.1f})"
            if v else "-" for v in zs.values()) + " |")
    print("| RMS error | " + " | ".join(f"{math.sqrt(np.mean([(k['parameters'][p] - TRUTH[p]) ** 2 for k in draws])):.3g}"
                                        for p in TRUTH) + " |")


def capture_paper(cases: list[str] | None, seed: int, out: Path) -> None:
    """Fit the paper simulation's cases (`bench_paper_sim.py`'s sessions, exp3, calibrated
    scale, as there; all eight when `cases` is None) and pickle each fit's uncertainty
    inputs, for `analyse_paper`."""
    import bench_paper_sim as paper

    from estimate import fit
    from estimate.problem import load_problem

    out.mkdir(parents=True, exist_ok=True)
    for s in paper.SIGMAS:
        for d in paper.DIAMETERS:
            name = paper.case_name(d, s)
            if (cases is not None and name not in cases) or (out / f"paper_{name}.pkl").is_file():
                continue
            ses, _ = paper.case_session(d, s)
            r, kept, wall = _fit_keeping_inputs(load_problem(ses, "g"), fit.FitSettings(seed=seed, scale="calibrated"))
            kept.update(case=name, truth={"sigma_t": s, "albedo": paper.ALBEDO}, wall_s=wall,
                        parameters=dict(r.parameters), uncertainties=dict(r.uncertainties))
            (out / f"paper_{name}.pkl").write_bytes(pickle.dumps(kept))
            print(f"{name}: {wall:.0f} s; sigma_t {r.parameters['sigma_t']:.4g} +- {r.uncertainties['sigma_t']:.2g}, "
                  f"albedo {r.parameters['albedo']:.4f} +- {r.uncertainties['albedo']:.2g}", flush=True)


def analyse_paper(d: Path) -> None:
    """Per paper case: sigma_t and albedo error over their intervals, both data meats."""
    fits = [pickle.loads(p.read_bytes()) for p in sorted(d.glob("paper_*.pkl"))]
    if not fits:
        raise SystemExit(f"no paper fits in {d}: run `capture-paper` first")
    meats = {"cross products (sessions 30-33)": {"data_meat": True, "meat_cross": True},
             "the Jacobians' mean (session 34)": {"data_meat": True}}
    print("| case | sigma_t error | " + " | ".join(f"{m}: sigma_t interval, z; albedo z" for m in meats) + " |")
    print("|---|---|" + "---|" * len(meats))
    zs: dict[str, dict[str, list[float]]] = {m: {"sigma_t": [], "albedo": []} for m in meats}
    for k in fits:
        t, p = k["truth"], k["parameters"]
        cells = []
        for m, over in meats.items():
            u, _ = _interval(k, **over)
            z = {q: (p[q] - t[q]) / u[q] for q in ("sigma_t", "albedo")}
            for q, v in z.items():
                zs[m][q].append(v)
            cells.append(f"{u['sigma_t'] / t['sigma_t']:.1%}, {z['sigma_t']:+.1f}; {z['albedo']:+.1f}")
        print(f"| {k['case']} | {p['sigma_t'] / t['sigma_t'] - 1:+.1%} | " + " | ".join(cells) + " |")
    for m in meats:
        print(f"{m}: RMS z " + ", ".join(f"{q} {math.sqrt(np.mean(np.square(v))):.2f} (largest {np.max(np.abs(v)):.1f})"
                                         for q, v in zs[m].items()))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=("capture", "analyse", "capture-paper", "analyse-paper"))
    ap.add_argument("--seeds", default="10-13", help="noise seeds, e.g. 10-15 or 3,5 (capture-paper: the fit seed)")
    ap.add_argument("--cases", default=None,
                    help="capture-paper: the paper simulation's cases, e.g. d0.5_s6,d0.3_s2 (default: all eight)")
    ap.add_argument("--dir", type=Path, default=Path(tempfile.gettempdir()) / "covvar")
    a = ap.parse_args()
    if a.what == "capture-paper":
        capture_paper(a.cases.split(",") if a.cases else None, _seeds(a.seeds)[0], a.dir)
    elif a.what == "analyse-paper":
        analyse_paper(a.dir)
    elif a.what == "capture":
        for s in _seeds(a.seeds):
            if (a.dir / f"draw{s}.pkl").is_file():
                continue
            capture(s, a.dir)
    else:
        analyse(a.dir)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
