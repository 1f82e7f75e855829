"""`rig estimate SESSION/`: fit sigma_t, albedo and the phase function per channel.

    rig estimate SESSION/ [--model exp|tthg|both] [--degree 3|M|auto] [--degree-max 7] [--channels rgb]
                          [--columns 256] [--allow-partial] [--max-iterations N] [--seed S]
                          [--extensions a,b] [--scale calibrated|free] [--time-limit S] [--json] [--diagnose]

The intensity scale is calibrated by default (`--scale calibrated`: the beam power
measured by `rig calibrate-beam`, the calibration ND transmission `camera.calibration_nd`
and the lens's collection solid angle `camera.collection_sr` of the rig configuration,
see estimate/loss.py); `--scale free` fits it per channel. Each model is one run: SESSION/estimates/<UTC time>_<model>/ (never overwritten), see
estimate/results.py and CONTRACTS.md. Channels are fitted one after another: the renderer
already uses every core.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import sys
from pathlib import Path
from typing import Any

from rig.errors import UsageError
from rig.name_lists import chosen_names

#: Reduced chi^2 (HDR variance) above which the summary points at `rig diagnose`: the clean
#: `make demo` session reaches 4-16, 1 % of its pixels (the recording's render fireflies)
#: carrying 65-70 % of it (session 54).
CHI2_HINT = 2.0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("estimate", help="estimate scattering parameters per channel from a session")
    p.add_argument("session", metavar="SESSION", help="session directory written by rig capture")
    p.add_argument("--model", choices=("exp", "tthg", "both"), default="exp",
                   help="phase model: exponential (exp, default), two-term HG (tthg) or both")
    p.add_argument("--degree", default="3",
                   help="degree M of the exponential phase function (3, the paper's), or auto: fit degrees 3, 4, ... "
                        "and keep the one the recording supports (estimate/phase_degree.py; a few fits a channel). "
                        "On recordings near sensor noise of forward-scattering media degree 3 cannot take the "
                        "phase's shape; 10 met the paper simulation's targets on all 8 of its cases (minutes a "
                        "channel on 2 cores; README, Estimation)")
    p.add_argument("--degree-spp-max", type=int, default=None,
                   help="with --degree auto: largest samples per pixel of the renders that compare the degrees "
                        "(they start at twice the final spp and double while their noise exceeds the recording's; "
                        "default 32 x the final spp; lower it for a quicker, coarser comparison on a CPU)")
    p.add_argument("--degree-max", type=int, default=None,
                   help="with --degree auto: the highest degree tried (default 7, the largest the paper evaluated; "
                        "up to 12). The search still stops after two degrees in a row that gain nothing, so only "
                        "media whose phase keeps gaining pay for the extra fits. Each degree starts from the one "
                        "below's optimum: on the paper simulation's d 0.5 um / sigma_t 6 medium that chain kept "
                        "exp7 at +9.5 %% in sigma_t, where exp10 from its own start ends at +1 to +4 %% "
                        "(docs/estimation-log.md, sessions 89-93); a fixed --degree 10 is the surer choice there. On "
                        "its d 0.5 um / sigma_t 2 medium --degree-max 10 kept exp9 and met the targets the "
                        "default's exp7 misses, in 43 min on 2 cores (session 94)")
    p.add_argument("--channels", default=None, help="filters to fit, e.g. rgb or r,g (default: all of the plan)")
    p.add_argument("--columns", type=int, default=None, help="profile window width in pixels (256)")
    p.add_argument("--extensions", default=None, help="forward-model extensions to include, comma separated "
                   "(default: none)")
    p.add_argument("--allow-partial", action="store_true", help="fit the stacks present when some are missing")
    p.add_argument("--max-iterations", type=int, default=None, help="stochastic optimiser iterations before the Gauss-Newton polish (default 10, Adam); "
                   "with --polish-steps 0, at most this many (default 80: 10 Adam, then Gauss-Newton)")
    p.add_argument("--spp-max", type=int, default=None, help="largest samples per pixel of the optimiser's iterations (128); with it set, the "
                   "Gauss-Newton polish and the final evaluation use twice that (else --final-spp's default) and the "
                   "uncertainties at most that")
    p.add_argument("--final-spp", type=int, default=None,
                   help="samples per pixel of the Gauss-Newton polish and the final evaluation (1024 on the CPU, "
                        "8192 on a GPU, where a fit at 8192 takes less than one at 1024 on 2 CPU cores and gives "
                        "honest intervals at sigma_t 6 /mm; 8192 on 2 cores took about 14 min a channel with the "
                        "camera engine, far less with the light engine)")
    p.add_argument("--polish-steps", type=int, default=None,
                   help="full Gauss-Newton steps at the final spp after the iterations (4, up to twice that while the "
                        "last ones still walk; the result averages the last three points); 0: none, fewer for a "
                        "quicker look")
    p.add_argument("--engine", choices=("light", "camera"), default="light",
                   help="how the forward model renders the slab: light paths from the beam connected to the "
                        "camera (light, default; about ten times faster and less noisy on the profile row) or "
                        "Mitsuba's prbvolpath from the camera (camera)")
    p.add_argument("--time-limit", type=float, default=None, metavar="SECONDS",
                   help="wall-clock budget of each fit's optimisation (its iterations, Gauss-Newton polish and "
                        "Levenberg-Marquardt steps; the evaluation and uncertainties run after it); with "
                        "--degree auto, of each degree's fit. Default: none")
    p.add_argument("--seed", type=int, default=0, help="random seed (renders, delta draws)")
    p.add_argument("--scale", choices=("calibrated", "free"), default="calibrated",
                   help="measured/rendered intensity scale: from the calibrated beam power and the lens's "
                        "collection solid angle (calibrated, default) or fitted per channel (free)")
    p.add_argument("--json", action="store_true", help="print the results as JSON")
    p.add_argument("--no-progress", action="store_true",
                   help="no live status line (stage, iteration, spp, loss) on the terminal while fitting")
    p.add_argument("--diagnose", action="store_true", help="run the diagnosis on the new fit (estimate.diagnose)")
    p.set_defaults(func=run)


def _channels(spec: str | None, available: list[str]) -> list[str]:
    """The channels `--channels` names (all of the session's when left out); a name the
    session lacks is the run's to name, with the session's channels."""
    names = chosen_names("--channels", spec, what="channel", example="rg")
    return available if names is None else names


def run(args: argparse.Namespace) -> int:
    from estimate.fit import FitSettings, fit_channel, model_phase
    from estimate.loss import calibrated_scale
    from estimate.problem import load_problem, session_channels
    from estimate.results import check_writable, new_run_dir, write_run
    from rig.fit_progress import FitProgress

    session = Path(args.session)
    auto = str(args.degree).strip().lower() == "auto"
    degree = 3
    if not auto:
        try:
            degree = int(str(args.degree))
        except ValueError:
            raise UsageError(f"--degree {args.degree}: use a whole number 0..12 or auto") from None
        if degree < 0 or degree > 12:
            raise UsageError(f"--degree {args.degree}: use 0..12 or auto")
    if args.degree_spp_max is not None:
        if not auto:
            raise UsageError(f"--degree-spp-max {args.degree_spp_max}: only --degree auto compares degrees; "
                             "add --degree auto or leave the flag out")
        if args.degree_spp_max < 1:
            raise UsageError(f"--degree-spp-max {args.degree_spp_max}: use a positive number of samples per pixel")
    if args.degree_max is not None:
        from estimate.phase_degree import DEGREE_LIMIT, MIN_DEGREE

        if not auto:
            raise UsageError(f"--degree-max {args.degree_max}: only --degree auto searches degrees; "
                             f"add --degree auto, or give the degree itself with --degree {args.degree_max}")
        if not MIN_DEGREE <= args.degree_max <= DEGREE_LIMIT:
            raise UsageError(f"--degree-max {args.degree_max}: use {MIN_DEGREE}..{DEGREE_LIMIT} "
                             f"(the search starts at exp{MIN_DEGREE})")
    if args.max_iterations is not None and args.max_iterations < 1:
        raise UsageError("--max-iterations must be >= 1")
    if args.columns is not None and args.columns < 2:
        raise UsageError(f"--columns {args.columns}: use at least 2 pixels (default 256)")
    if args.time_limit is not None and not (math.isfinite(args.time_limit) and args.time_limit > 0):
        raise UsageError(f"--time-limit {args.time_limit:g}: give a positive number of seconds, e.g. 60")
    if args.seed < 0:
        raise UsageError(f"--seed {args.seed}: use a whole number >= 0")
    if args.polish_steps is not None and not 0 <= args.polish_steps <= 20:
        raise UsageError(f"--polish-steps {args.polish_steps}: use 0..20")
    if args.spp_max is not None and args.spp_max < 1:
        raise UsageError(f"--spp-max {args.spp_max}: use a positive number of samples per pixel")
    if args.final_spp is not None and args.final_spp < 2:
        # The polish renders two independent halves of this budget.
        raise UsageError(f"--final-spp {args.final_spp}: use at least 2 samples per pixel (default 1024 on the "
                         "CPU, 8192 on a GPU)")
    if args.diagnose and importlib.util.find_spec("estimate.diagnose") is None:
        raise UsageError("--diagnose needs estimate.diagnose, which this installation does not have")
    available = session_channels(session)
    channels = _channels(args.channels, available)
    from estimate.extensions import EXTENSIONS

    # Checked before the problems load and the first fit starts.
    exts = chosen_names("--extensions", args.extensions, sorted(EXTENSIONS), letters=False, what="extension",
                        example="stray_light,lens_blur") or []
    # Load every problem first: bad input fails before any fitting.
    problems = {c: load_problem(session, c, args.columns, allow_partial=args.allow_partial) for c in channels}
    check_writable(session)  # a read-only session fails now, not after the fits
    narrow = sorted({pb.n_px for pb in problems.values()})
    if args.columns is not None and narrow[0] < args.columns and not args.json:
        print(f"note: --columns {args.columns} is wider than the stacks' window; fitting {narrow[0]} pixels",
              file=sys.stderr)
    corr = next((pb.angle_correction_deg for pb in problems.values() if pb.angle_correction_deg), 0.0)
    if corr:
        print(f"note: {session} was captured before capture applied the calibrated rotation zero; its angles are "
              f"taken as the recorded ones {corr:+.4f} deg (180 - rotation_zero_deg)", file=sys.stderr)
    scales = ({c: calibrated_scale(session, c, problems[c].beam.power()) for c in channels}
              if args.scale == "calibrated" else {})
    models = ["exp", "tthg"] if args.model == "both" else [args.model]
    from estimate.mitsuba_env import default_variant

    variant = default_variant()
    settings = FitSettings.for_variant(variant, seed=args.seed, scale=args.scale, engine=args.engine)
    if args.max_iterations is not None:
        settings.max_iterations = args.max_iterations
        settings.iterations_before_polish = args.max_iterations
    if args.polish_steps is not None:
        settings.polish_steps = args.polish_steps
    settings.time_limit_s = args.time_limit
    if args.spp_max is not None:
        settings.spp_max = max(settings.spp_start, args.spp_max)
        settings.lm_spp = settings.final_spp = 2 * settings.spp_max
    if args.final_spp is not None:
        settings.lm_spp = settings.final_spp = args.final_spp
    if args.spp_max is not None or args.final_spp is not None:
        # A budget, not only the iterations': the uncertainties' Jacobian (512 spp by
        # default) never uses more samples than the final evaluation.
        settings.uncertainty_spp = min(settings.uncertainty_spp, settings.final_spp)
    out: dict[str, Any] = {"session": str(session), "runs": []}
    if not args.json:
        print(f"rendering with Mitsuba's {variant}; the polish and final evaluation at "
              f"{settings.final_spp} spp", file=sys.stderr, flush=True)
    for m in models:
        by_degree = auto and m == "exp"
        phase = "expauto" if by_degree else model_phase(m, degree)
        fits = []
        choices: dict[str, Any] = {}
        with FitProgress(enabled=not (args.json or args.no_progress)) as live:
            for c in channels:
                def fit_one(ph: str, start: Any, _c: str = c) -> Any:
                    if not args.json:
                        print(f"fitting channel {_c} ({ph}) ...", file=sys.stderr, flush=True)
                    progress, on_stage = live.channel(_c, ph)
                    f = fit_channel(problems[_c], ph, extensions=exts, settings=settings, start=start,
                                    scale_calibration=scales.get(_c), progress=progress, on_stage=on_stage)
                    if not args.json:
                        steps = sum(1 for e in f.polish if e.get("accepted"))
                        lm = (f" + {f.lm_steps} Levenberg-Marquardt steps at fixed seeds, up to {f.lm_spp} spp"
                              if f.lm_steps else "")
                        print(f"  {_c}: {sum(f.stage_times_s.values()):.0f} s, {f.iterations} iterations "
                              f"+ {steps} polish steps{lm}, {f.stop_reason}", file=sys.stderr, flush=True)
                    return f

                if by_degree:
                    from estimate.phase_degree import MAX_DEGREE, choose_degree

                    log = None if args.json else (lambda s: print(s, file=sys.stderr, flush=True))
                    choice = choose_degree(problems[c], settings, fit=fit_one, extensions=exts, log=log,
                                           max_spp=args.degree_spp_max,
                                           max_degree=MAX_DEGREE if args.degree_max is None else args.degree_max)
                    choices[c] = choice
                    fits.append(choice.fit)
                    if not args.json:
                        print(f"  {c}: {choice.outcome}", file=sys.stderr, flush=True)
                else:
                    fits.append(fit_one(phase, None))
        choice_docs = {c: ch.to_dict() for c, ch in choices.items()}
        run_dir = new_run_dir(session, phase)
        write_run(run_dir, session, fits, problems,
                  {"columns": int(problems[channels[0]].n_px), "iterations": settings.max_iterations,
                   "spp_schedule": {f.channel: f.spp_schedule for f in fits},
                   "delta": {"range_rel": list(settings.delta_range), "reference_rel": fits[0].delta_rel},
                   "seed": settings.seed, "scale": args.scale,
                   "scale_calibration": {c: sc.to_dict() for c, sc in scales.items()},
                   "loss": "mean (log(I_meas/scale + delta) - log(I_model + delta))^2",
                   "fit": settings.to_dict(),
                   **({"model": phase, "degree": "auto", "degree_choice": choice_docs} if by_degree else {})})
        out["runs"].append({"run_id": run_dir.name, "path": str(run_dir), "model": phase,
                            "channels": {f.channel: f.summary() for f in fits},
                            **({"degree_choice": choice_docs} if by_degree else {})})
        if not args.json:
            print(f"run {run_dir}")
            for f in fits:
                p = f.parameters
                u = f.uncertainties
                label = f"{f.channel} ({f.model})" if by_degree else f.channel
                print(f"  {label}: sigma_t {p['sigma_t']:.4g} +- {u.get('sigma_t', float('nan')):.2g} /mm, "
                      f"albedo {p['albedo']:.4f} +- {u.get('albedo', float('nan')):.2g}, "
                      + ", ".join(f"{k[6:]} {v:.4g}" for k, v in p.items() if k.startswith("phase."))
                      + f"; reduced chi2 {f.reduced_chi2:.3g} ({f.iterations} it, {f.time_s:.0f} s, {f.stop_reason})")
                dv = f.derived()
                pm = {k: f"{d['value']:.4g} +- {d['uncertainty']:.2g}" if d["uncertainty"] is not None
                      else f"{d['value']:.4g}" for k, d in dv.items()}
                print(f"     sigma_a {pm['sigma_a']} /mm, sigma_s' {pm['sigma_s_reduced']} /mm, g {pm['g']}")
                ext = [k for k in f.free if "." in k and not k.startswith("phase.")]
                if ext:
                    print("     " + ", ".join(f"{k} {p[k]:.4g} +- {u.get(k, float('nan')):.2g}"
                                           + (" (solved each iteration)" if k in f.solved else "") for k in ext))
                if f.drifting:
                    # After the fixed-seed LM (degree 5 and more) the drift is its last step;
                    # its samples follow --final-spp, and the iterations' flags do not reach it.
                    more = ("samples per pixel for the polish and its Levenberg-Marquardt (--final-spp)"
                            if f.lm_steps else
                            "samples per pixel (--spp-max) or iterations (--max-iterations)")
                    print(f"     warning: {', '.join(f.drifting)} still drifting when the fit stopped "
                          f"(uncertainties include the last drift); more {more} move it further")
            if not args.diagnose and any(f.reduced_chi2 > CHI2_HINT for f in fits):
                print(f"  note: the reduced chi2 counts only the HDR variance; pixel noise it does not hold "
                      f"(fixed-pattern noise, dust; on the simulated rig the recording's frozen render noise) "
                      f"raises it too. `rig diagnose {session}` tells that from a mismatch the model leaves.")
        if args.diagnose:
            from estimate import diagnose  # type: ignore[attr-defined]

            log = None if args.json else (lambda m: print(m, file=sys.stderr))
            with FitProgress(enabled=not (args.json or args.no_progress)) as live:
                doc = diagnose.run_diagnosis(session, fit_run=run_dir, log=log, fit_progress=live.channel)
            if args.json:
                out.setdefault("diagnoses", []).append(doc)
            else:
                print(doc["summary"])
    if args.json:
        print(json.dumps(out, indent=1, default=float))
    return 0
