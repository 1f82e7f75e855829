"""``rig diagnose SESSION/``: where a fit and the recording disagree, and which physics is missing.

    rig diagnose SESSION/ [--fit RUN] [--effects a,b,...] [--channels rgb] [--spp N]
                 [--refits fixed-seed|decorrelated] [--engine light|camera] [--quick] [--json]

Diagnoses the latest estimate run (or `--fit RUN`: a run id under SESSION/estimates/ or its
path): tests the whole fit against the noise (the HDR variance scaled by an empirical
noise floor per angle, which absorbs white pixel noise the HDR variance misses: fixed-pattern
noise, PRNU, the simulated bench's frozen render noise; significant = smooth structure in
the residuals or a candidate's score test), locates the mismatch, screens the eight
catalogue extensions with score tests, confirms the leading ones by refitting (held-out
light angles, BIC), and fits the final model with the confirmed effects by the estimator
itself, with the fit run's settings (`--quick`: the Levenberg-Marquardt refit). Writes
SESSION/diagnoses/<run_id>/diagnosis.yaml with residual plots, and the refit as a new
estimate run. See estimate/diagnose.py.
"""

from __future__ import annotations

import argparse
import json
import sys

from rig.errors import UsageError
from rig.name_lists import chosen_names


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("diagnose", help="locate a fit/recording mismatch, name the left-out physics, refit")
    p.add_argument("session", metavar="SESSION", help="session directory with an estimate run")
    p.add_argument("--fit", default=None, metavar="RUN", help="estimate run to diagnose (default: the latest)")
    p.add_argument("--effects", default=None, metavar="A,B",
                   help="candidate extensions to test (default: all eight)")
    p.add_argument("--channels", default=None, help="channels to diagnose, e.g. rgb or r,g (default: all of the fit)")
    p.add_argument("--spp", type=int, default=None,
                   help="samples per pixel of the diagnosis renders (the light engine: 2048 on the CPU and a GPU; "
                        "the camera engine: 256 on the CPU, 2048 on a GPU)")
    p.add_argument("--seed", type=int, default=1000, help="base render seed (1000)")
    p.add_argument("--quick", action="store_true",
                   help="skip the estimator's final fit of the confirmed effects (on the simulated bench it saves "
                        "about 2 min of a 9-11 min diagnosis per channel on 2 cores); the Levenberg-Marquardt refit "
                        "is then the final model: a fast first look. It cannot walk a base fit that is far off (a left-out boundary: sigma_t 57 %% high) "
                        "to the data, and an effect may then stand in for the real one: confirmed effects are named "
                        "only if that model removes at least half of the excess reduced chi2 at the noise floor, "
                        "else no cause is named; the full run is the reference")
    p.add_argument("--refits", choices=("fixed-seed", "decorrelated"), default="fixed-seed",
                   help="what the confirmation's refits minimise: the chi2 of one render seed (fixed-seed, "
                        "Levenberg-Marquardt; its optimum leans towards quieter renders, so a 256-px window wants "
                        "about 2048 spp) or the decorrelated chi2 of two seeds (decorrelated, Gauss-Newton; no such "
                        "lean, so fewer spp serve: see docs/diagnosis-log.md, session 45)")
    p.add_argument("--engine", choices=("camera", "light"), default=None,
                   help="the forward model's render engine for the diagnosis' models: light paths from the beam "
                        "(light: much less render noise a second, 2048 spp by default) or Mitsuba's prbvolpath from "
                        "the camera (camera); default: the fit's own, light for rig estimate's default fits "
                        "(docs/diagnosis-log.md, sessions 61-68)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    p.add_argument("--json", action="store_true", help="print the diagnosis as JSON")
    p.add_argument("--no-progress", action="store_true",
                   help="no live status line on the terminal during the estimator's final fit")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from estimate.diagnose import run_diagnosis
    from estimate.extensions import EXTENSIONS
    from estimate.results import check_writable
    from rig.fit_progress import FitProgress

    session = Path(args.session)
    if not (session / "session.yaml").is_file():
        raise UsageError(f"{session}: not a session directory (no session.yaml)")
    effects = chosen_names("--effects", args.effects, sorted(EXTENSIONS), letters=False, what="effect",
                           example="stray_light,lens_blur")
    channels = chosen_names("--channels", args.channels, what="channel", example="rg")
    if args.spp is not None and args.spp < 16:
        raise UsageError(f"--spp {args.spp}: use at least 16 samples per pixel (default 2048 with the light engine; 256 on the CPU and 2048 on a GPU with the camera engine)")
    for kind in ("diagnoses", "estimates"):  # the diagnosis and its refit run: fail now, not after the renders
        check_writable(session, kind)
    log = None if args.json else (lambda s: print(s, file=sys.stderr))
    with FitProgress(enabled=not (args.json or args.no_progress)) as live:
        doc = run_diagnosis(session, args.fit, effects=effects, channels=channels, spp=args.spp,
                            seed=args.seed, plots=not args.no_plots, log=log, refine=not args.quick,
                            fit_progress=live.channel, refit_objective=args.refits, engine=args.engine)
    if args.json:
        print(json.dumps(doc, indent=1, default=float))
    else:
        print(doc["summary"])
    return 0
