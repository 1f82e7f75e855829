"""``rig diagnose SESSION/``: where a fit and the recording disagree, and which physics is missing.

    rig diagnose SESSION/ [--fit RUN] [--effects a,b,...] [--channels rgb] [--spp 256] [--json]

Diagnoses the latest estimate run (or `--fit RUN`: a run id under SESSION/estimates/ or its
path): tests the whole fit against the noise, locates the mismatch, screens the eight
catalogue extensions with score tests, confirms the leading ones by refitting (held-out
light angles, BIC), and refits with the confirmed effects. Writes
SESSION/diagnoses/<run_id>/diagnosis.yaml with residual plots, and the refit as a new
estimate run. See estimate/diagnose.py.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from rig.errors import UsageError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("diagnose", help="locate a fit/recording mismatch, name the left-out physics, refit")
    p.add_argument("session", metavar="SESSION", help="session directory with an estimate run")
    p.add_argument("--fit", default=None, metavar="RUN", help="estimate run to diagnose (default: the latest)")
    p.add_argument("--effects", default=None, metavar="A,B",
                   help="candidate extensions to test (default: all eight)")
    p.add_argument("--channels", default=None, help="channels to diagnose, e.g. rgb or r,g (default: all of the fit)")
    p.add_argument("--spp", type=int, default=256, help="samples per pixel of the diagnosis renders (256)")
    p.add_argument("--seed", type=int, default=1000, help="base render seed (1000)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    p.add_argument("--json", action="store_true", help="print the diagnosis as JSON")
    p.set_defaults(func=run)


def _list(spec: str | None, split_letters: bool) -> list[str] | None:
    if not spec:
        return None
    if "," in spec or not split_letters:
        return [s.strip() for s in spec.split(",") if s.strip()]
    return list(spec.strip())


def _fmt(v: Any, u: Any = None) -> str:
    if u is None or not isinstance(u, (int, float)):
        return f"{v:.4g}"
    return f"{v:.4g} +- {u:.2g}"


def _red(region: dict[str, Any]) -> str:
    v = region.get("reduced_chi2")
    return "-" if v is None or region.get("pixels", 0) == 0 else f"{v:.2f}"


def print_summary(doc: dict[str, Any], out: Any = sys.stdout) -> None:
    """Plain-language summary of a diagnosis document."""
    for ch, d in doc["channels"].items():
        print(f"channel {ch}: {d['verdict']}", file=out)
        if not d["significant"]:
            continue
        loc = d["localisation"]
        regions = []
        for a, b in (("front", "back"), ("grazing", "normal"), ("peak", "tails")):
            regions.append(f"{a} {_red(loc[a])} / {b} {_red(loc[b])}")
        print("  where (reduced chi2 by region): " + "; ".join(regions)
              + f"; left-right asymmetry {loc['asymmetry']['difference_sigma']:+.1f} sigma", file=out)
        if d.get("unconverged"):
            print(f"  {d['unconverged']}", file=out)
        cands = d["candidates"]
        if cands:
            print("  score tests (statistic / dof, share of the excess it can explain):", file=out)
            for c in cands:
                print(f"    {c['name']:<20} {c['statistic']:10.1f} / {c['dof']}   log10 p {c['log10_p']:8.1f}"
                      f"   {100 * min(1.0, c['explained']):5.1f} %", file=out)
        for e in d["confirmations"]:
            held = (f", held-out chi2 {e['chi2_heldout_before']:.0f} -> {e['chi2_heldout_after']:.0f}"
                    if "chi2_heldout_after" in e else "")
            print(f"  refit with {e['effect']}: BIC improves by {e['delta_bic']:.1f}{held}"
                  f" -> {'confirmed' if e['confirmed'] else 'not confirmed'}", file=out)
        for name, ps in d["confirmed_effects"].items():
            vals = ", ".join(f"{k.split('.', 1)[1]} = {_fmt(v['value'], v['uncertainty'])}" for k, v in ps.items())
            print(f"  left-out physics: {name} ({vals})", file=out)
        if d["confirmed_effects"]:
            print(f"  reduced chi2 {d['reduced_chi2_before']:.3f} -> {d['reduced_chi2_after']:.3f}", file=out)
            unc = d.get("material_uncertainty_after") or {}
            for k, before in d["material_before"].items():
                print(f"    {k:<10} {before:.4g} -> {_fmt(d['material_after'][k], unc.get(k))}", file=out)
    if doc.get("refit_run"):
        print(f"refit written as estimate run {doc['refit_run']}", file=out)
    print(f"diagnosis written to diagnoses/{doc['run_id']}/diagnosis.yaml", file=out)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from estimate.diagnose import run_diagnosis
    from estimate.extensions import EXTENSIONS

    session = Path(args.session)
    if not (session / "session.yaml").is_file():
        raise UsageError(f"{session}: not a session directory (no session.yaml)")
    effects = _list(args.effects, split_letters=False)
    for e in effects or ():
        if e not in EXTENSIONS:
            raise UsageError(f"--effects: unknown effect {e!r}; known: {', '.join(sorted(EXTENSIONS))}")
    if args.spp < 16:
        raise UsageError("--spp must be >= 16")
    log = None if args.json else (lambda s: print(s, file=sys.stderr))
    doc = run_diagnosis(session, args.fit, effects=effects, channels=_list(args.channels, True), spp=args.spp,
                        seed=args.seed, plots=not args.no_plots, log=log)
    if args.json:
        print(json.dumps(doc, indent=1, default=float))
    else:
        print_summary(doc)
    return 0
