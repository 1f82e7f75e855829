"""How a diagnosis is shown: `summary_text` (the plain-language summary printed by
`rig diagnose` and kept in the report) and `plot_diagnosis` (residual maps and profiles
before and after, written beside diagnosis.yaml).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from estimate.refit import DECORRELATED

if TYPE_CHECKING:
    from estimate.diagnose import ChannelDiagnosis

__all__ = ["REFIT_IN_PLACE", "REFIT_IN_PLACE_WHY", "plot_diagnosis", "refit_name", "summary_text"]


#: The model that stands in for the estimator's final fit where that fit is worse than the
#: base fit (`estimate.diagnose.refine_channel`), as the verdicts and the summary name it.
REFIT_IN_PLACE = "the refit kept in place of the estimator's final fit"
#: The same with why, where the second pass names the model it had to beat.
REFIT_IN_PLACE_WHY = f"{REFIT_IN_PLACE} (which fitted worse than the base fit)"


def plot_diagnosis(out_dir: Any, d: ChannelDiagnosis, problem: Any) -> list[Any]:
    """residuals_<f>.png (normalised residual maps before/after) and profiles_<f>.png
    (measured vs model before/after at the worst angles)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    evs = [("before", d.before)] + ([("after", d.after)] if d.after else [])
    fig, axes = plt.subplots(1, len(evs), figsize=(5.5 * len(evs), 3.8), squeeze=False)
    lim = 5.0
    x = np.asarray(problem.x_mm)
    for ax, (label, ev) in zip(axes[0], evs):
        im = ax.imshow(np.nan_to_num(ev.residuals.r_adjusted), aspect="auto", cmap="coolwarm", vmin=-lim, vmax=lim,
                       extent=(x[0], x[-1], len(problem.angles_deg) - 0.5, -0.5), interpolation="nearest")
        ax.set_yticks(range(len(problem.angles_deg)))
        ax.set_yticklabels([f"{a:g}" for a in problem.angles_deg], fontsize=7)
        ax.set_xlabel("x [mm]")
        ax.set_ylabel("light angle [deg]")
        ax.set_title(f"{label}: reduced chi2 {ev.residuals.reduced_chi2_adjusted:.2f} (noise floor)", fontsize=9)
    fig.colorbar(im, ax=axes[0].tolist(), label="residual / (f sigma_HDR)")
    p = out_dir / f"residuals_{d.channel}.png"
    fig.savefig(p, dpi=80)
    plt.close(fig)
    paths.append(p)
    per = d.localisation["per_angle"]
    worst = sorted(range(len(problem.angles_deg)), key=lambda i: -per[f"{problem.angles_deg[i]:g}"]["excess_sigma"])[:3]
    fig, axes = plt.subplots(1, len(worst), figsize=(4 * len(worst), 3.2), squeeze=False)
    for ax, i in zip(axes[0], worst):
        ax.semilogy(x, np.clip(problem.measured[i], 1e-6, None), ".", ms=3, color="k", label="measured")
        for label, ev in evs:
            ax.semilogy(x, np.clip(ev.scale * ev.model[i], 1e-6, None), "-", lw=1, label=f"model {label}")
        ax.set_title(f"{problem.angles_deg[i]:g} deg", fontsize=9)
        ax.set_xlabel("x [mm]")
        ax.legend(fontsize=7)
    fig.tight_layout()
    p = out_dir / f"profiles_{d.channel}.png"
    fig.savefig(p, dpi=80)
    plt.close(fig)
    paths.append(p)
    return paths


def _fmt(v: Any, u: Any = None) -> str:
    if u is None or not isinstance(u, (int, float)):
        return f"{v:.4g}"
    return f"{v:.4g} +- {u:.2g}"


def _red(region: dict[str, Any]) -> str:
    v = region.get("reduced_chi2")
    return "-" if v is None or region.get("pixels", 0) == 0 else f"{v:.2f}"


def _exit_bar_text(e: Mapping[str, Any]) -> str:
    """The rise a backward check needed, in words: the BIC price, and the dispersion it was
    multiplied by where the joint model's reduced chi^2 exceeds 1."""
    disp = float(e.get("dispersion", 1.0))
    if disp > 1.0 and "price" in e:
        return (f"its BIC price {e['price']:.1f} (k ln n) x {disp:.2f} (the reduced chi2 the model with every named "
                f"effect leaves) = {e['needed']:.1f}")
    return f"its BIC price {e['needed']:.1f} (k ln n)"


#: How the summary names the stages of `estimate.diagnose.DIAGNOSIS_STAGES`.
STAGE_WORDS = {"locate": "evaluating the fit", "screening": "screening", "confirmation": "confirming refits",
               "model": "the model with the confirmed effects", "final_fit": "the estimator's final fit"}


def refit_name(objective: str | None) -> str:
    """What the diagnosis' refits were, in words, from their objective (`estimate.refit.OBJECTIVES`)."""
    return ("decorrelated Gauss-Newton refit" if objective == DECORRELATED
            else "Levenberg-Marquardt refit")


def summary_text(doc: Mapping[str, Any]) -> str:
    """Plain-language summary of a diagnosis document (terminal and HTML report)."""
    import io

    out = io.StringIO()
    for ch, d in doc["channels"].items():
        print(f"channel {ch}: {d['verdict']}", file=out)
        stages = d.get("time_by_stage_s") or {}
        if stages:
            print(f"  time {d['time_s']:.0f} s: "
                  + ", ".join(f"{STAGE_WORDS.get(k, k)} {v:.0f} s" for k, v in stages.items()), file=out)
        if not d["significant"]:
            continue
        loc = d["localisation"]
        regions = []
        for a, b in (("front", "back"), ("grazing", "normal"), ("peak", "tails")):
            regions.append(f"{a} {_red(loc[a])} / {b} {_red(loc[b])}")
        tests = (d.get("before") or {}).get("smooth") or []
        if tests:
            print("  smooth structure (binned / per-pixel power of the residual beyond the fit; 1 = none): "
                  + "; ".join(f"{t['bin_px']} px bins {t['reduced']:.2f} (log10 p {t['log10_p']:.1f})"
                for t in tests), file=out)
        print("  where (reduced chi2 at the noise floor, by region): " + "; ".join(regions)
              + f"; left-right asymmetry {loc['asymmetry']['difference_sigma']:+.1f} sigma", file=out)
        if d.get("unconverged"):
            print(f"  {d['unconverged']}", file=out)
        cands = d["candidates"]
        if cands:
            print("  score tests (statistic / dof, share of the excess it can explain):", file=out)
            for c in cands:
                print(f"    {c['name']:<20} {c['statistic']:10.1f} / {c['dof']}   log10 p {c['log10_p']:8.1f}"
                      f"   {100 * min(1.0, c['explained']):5.1f} %", file=out)
        again = d.get("second_pass") or {}
        if again:
            # Runs before session 47 refitted only the flagged candidates (no "flagged" key).
            which = ("candidate" if "flagged" in again else "candidate the screening flagged")
            # Since session 48 a second-pass refit may start from the coarse grid (entry "start").
            where = ("from the better of the base fit and the coarse grid with the effect switched on"
                     if any("start" in e for e in d["confirmations"]) else "from the base fit")
            # Since session 55 also where the estimator's fit was not kept ("first_model" "refit").
            model = (REFIT_IN_PLACE_WHY
                     if again.get("first_model") == "refit" else "the estimator's final fit")
            print(f"  second pass: {model} dropped {', '.join(again['dropped'])}; every other "
                  f"{which} ({', '.join(again.get('refitted') or []) or 'none'}) refitted "
                  f"{where}, the held-out and no-harm tests not deciding: {again.get('outcome', '')}", file=out)
            vs = again.get("against_first")
            if vs:
                print(f"    its final fit against the first, in the base fit's noise metric: chi2 {vs['chi2_first']:.0f} "
                      f"-> {vs['chi2_second']:.0f}, gain {vs['gain']:.1f} after the dispersion {vs['dispersion']:.2f} "
                      f"and the parameters' price (needs more than {vs['needed']:g})", file=out)
        for e in d["confirmations"]:
            held = (f", held-out chi2 {e['chi2_heldout_before']:.0f} -> {e['chi2_heldout_after']:.0f}"
                    if "chi2_heldout_after" in e else "")
            mag = ""
            if "magnitude_sigma" in e:
                # magnitude_wald_sigma is None where the Wald test was not asked (it could not decide)
                by = (" (likelihood ratio)" if (e.get("magnitude_lr_sigma") or 0.0) > (e.get("magnitude_wald_sigma")
                                                                                     or 0.0) else "")
                mag = f", magnitude {e['magnitude_sigma']:.1f} sigma from absent{by}"
                if e.get("magnitude_sigma_by_effect"):
                    mag = (", magnitudes " + ", ".join(f"{k} {z:.1f}" for k, z in e["magnitude_sigma_by_effect"].items())
                           + " sigma from absent")
            pair = e.get("pair")
            tag = ("second pass: " if e.get("pass") == 2 else
                   "runner-up (no leading candidate confirmed): " if e.get("runner_up") else
                   f"pair (no candidate confirmed alone; {pair['lead']} came closest, and at its refit the "
                   f"screening flagged {e['effects'][-1]}, log10 p {pair['log10_p']:.1f}): " if pair else "")
            what = " and ".join(e["effects"]) + " together" if pair else e["effect"]
            ind = (f" ({e['delta_bic_independent']:.1f} rendered independently)"
                   if e.get("delta_bic_independent") is not None else "")
            start = e.get("start") or {}
            grid = " (started from the coarse grid)" if start.get("from") == "coarse grid" else ""
            other = start.get("other")
            if other:
                # Since session 55: a second-pass refit that failed from one start tried the other.
                grid = (f" (started from the {'coarse grid' if start.get('from') == 'coarse grid' else 'fit'}; "
                        f"from the {other['from']} it gained {other['delta_bic']:.1f}, magnitude "
                        f"{other['magnitude_sigma']:.1f} sigma)")
            cc = e.get("close_call")
            if cc:
                # Since session 52: a gain at the bar's edge decided again at more samples.
                grid += (f" (a close call at {cc['spp_first']} spp, BIC gain {cc['delta_bic_first']:.1f}: refitted "
                         f"with its control at {cc['spp']} spp"
                         + (", which decides" if cc["passed"] else f", BIC gain {cc['delta_bic']:.1f}, still short")
                         + ")")
            # A second-pass candidate the estimator fitted: what its final fit decided.
            tried = f" (fitted by the estimator: {e['final_fit_outcome']})" if e.get("final_fit_outcome") else ""
            print(f"  {tag}refit with {what}{grid}: BIC improves by {e['delta_bic']:.1f}{ind}{held}{mag}"
                  f" -> {'confirmed' if e['confirmed'] else 'not confirmed'}{tried}", file=out)
        for chk in d.get("explained_checks") or []:
            # Since session 66: a further round only where the model so far leaves more than the bar.
            # Since session 71 (not --quick): read at the estimator's fit of that model.
            at_opt = chk.get("reduced_chi2_adjusted_optimum")
            if chk.get("stage") == "estimator fit":
                what = (f" the reduced chi2 at the floor is {chk['reduced_chi2_adjusted_fit']:.3f} fitted by the "
                        f"estimator, {chk['reduced_chi2_adjusted_refit']:.3f} at the candidate's refit")
            else:
                what = (" (at the decorrelated step from its refit) the reduced chi2 at the floor is "
                        f"{chk['reduced_chi2_adjusted']:.3f}"
                        + (f" ({at_opt:.3f} at the refit's own optimum)" if at_opt is not None else ""))
            print(f"  with {', '.join(chk['after'])}{what}, "
                  + (f"at most {chk['bar']:g}: explained, no second effect looked for" if chk["explained"]
                     else f"above {chk['bar']:g}: a second effect looked for"), file=out)
        part = d.get("partial") or {}
        if part and part["share_explained"] <= 0.0:
            print(f"  not named: {', '.join(part['effects'])}: the model with "
                  f"{'it' if len(part['effects']) == 1 else 'them'} fits the whole recording no better than the model "
                  f"without (reduced chi2 at the floor {part['reduced_chi2_adjusted_before']:.2f} -> "
                  f"{part['reduced_chi2_adjusted_with']:.2f})", file=out)
        elif part:
            print(f"  not named: {', '.join(part['effects'])} removed {100 * part['share_explained']:.0f}% of the "
                  f"excess (reduced chi2 at the floor {part['reduced_chi2_adjusted_before']:.2f} -> "
                  f"{part['reduced_chi2_adjusted_with']:.2f}; needs {100 * part['min_share']:.0f}%), with "
                  + ", ".join(f"{k} {v:.4g}" for k, v in part["material_with"].items() if k in ("sigma_t", "albedo")),
                  file=out)
        for e in d.get("pruned") or []:
            final = e.get("stage") == "final fit"
            if e.get("leading"):
                # the effect that carries the most (or the only one): its magnitude alone decides
                alone = ("alone in the model" if not e["with"]
                         else f"the largest of {', '.join([e['effect'], *e['with']])}")
                print(f"  check in the estimator's fit: {e['effect']} ({alone}; setting it to absent raises chi2 by "
                      f"{e['chi2_rise']:.1f}) lies {e.get('magnitude_sigma', math.nan):.1f} sigma from absent by the "
                      f"fit's own intervals (needs more than {e.get('magnitude_needed', 1.0):g}) -> "
                      + ("dropped: its magnitude cannot be told from absent, so it is not named (it stays in the "
                         "fitted model at its fitted value)" if e["dropped"] else "kept"), file=out)
                continue
            why = ("dropped: the final fit has no use for it (it stays in the fitted model at its fitted value)"
                   if final else "dropped: its signature was borrowed from the effect added after it")
            print(f"  backward check ({'estimator' if final else 'refit'}): {e['effect']} set to absent in the model "
                  f"with {', '.join(e['with'])} raises chi2 by {e['chi2_rise']:.1f}, "
                  f"{'less than' if e['chi2_rise'] < e['needed'] else 'more than'} {_exit_bar_text(e)}"
                  + (f"; its fitted magnitude is {e['magnitude_sigma']:.1f} sigma from absent (needs more than "
                     f"{e['magnitude_needed']:g})" if "magnitude_sigma" in e else "")
                  + f" -> {why if e['dropped'] else 'kept'}", file=out)
        imp = d.get("importance") or {}
        if len(imp) >= 2:
            order = d.get("confirmed_order") or []
            print(f"  named by the chi2 each carries in the {next(iter(imp.values()))['stage']} (set to absent alone): "
                  + ", ".join(f"{e} {v['chi2_rise']:.0f}" for e, v in imp.items())
                  + (f"; the rounds added them as {', '.join(order)}" if list(imp) != order[:len(imp)] else ""),
                  file=out)
        for name, ps in d["confirmed_effects"].items():
            vals = ", ".join(f"{k.split('.', 1)[1]} = {_fmt(v['value'], v['uncertainty'])}"
                             + (f" (at the {v['at_bound']} end of its range: stopped there, not measured)"
                                if v.get("at_bound") else "") for k, v in ps.items())
            print(f"  left-out physics: {name} ({vals})", file=out)
        if d["confirmed_effects"]:
            print(f"  reduced chi2 {d['reduced_chi2_before']:.3f} -> {d['reduced_chi2_after']:.3f} (HDR variance); "
                  f"{d['reduced_chi2_adjusted_before']:.3f} -> {d['reduced_chi2_adjusted_after']:.3f} "
                  "(noise floor)", file=out)
            unc = d.get("material_uncertainty_after") or {}
            for k, before in d["material_before"].items():
                print(f"    {k:<10} {before:.4g} -> {_fmt(d['material_after'][k], unc.get(k))}", file=out)
            ff = d.get("final_fit") or {}
            lm = d.get("refit_lm") or {}
            if ff.get("kept") and lm:
                # "deferred": the joint refit was left to the final fit; the start was the
                # last confirmed candidate's refit (`estimate.diagnose.diagnose_channel`).
                which = "the last candidate's" if d.get("model_stage") == "deferred" else "the"
                print(f"  (final model fitted by the estimator, {ff['iterations']} iterations, {ff['time_s']:.0f} s; "
                      f"{which} {refit_name(d.get('refit_objective'))} had reduced chi2 {lm['reduced_chi2_adjusted']:.3f} at the floor, "
                      + ", ".join(f"{k} {v:.4g}" for k, v in lm["material"].items() if k in ("sigma_t", "albedo"))
                      + ")", file=out)
            elif ff:
                print(f"  ({ff['reason']})", file=out)
            fixed = d.get("material_fixed_seed_after") or {}
            if not ff.get("kept") and fixed:
                print("  (sigma_t, albedo and the phase after: one Gauss-Newton step on the decorrelated chi^2 of "
                      "two render seeds from the Levenberg-Marquardt refit's fixed-seed optimum ("
                      + ", ".join(f"{k} {v:.4g}" for k, v in fixed.items() if k in ("sigma_t", "albedo"))
                      + "), whose render noise biases it low in albedo; the estimator's final fit, without "
                      "--quick, is the reference)", file=out)
            elif not ff.get("kept") and d.get("refit_objective") == DECORRELATED:
                print("  (sigma_t, albedo and the phase after are the decorrelated refit's: Gauss-Newton steps on the "
                      "decorrelated chi^2 of two render seeds, which a fixed seed's render-noise bias does not reach; "
                      "the estimator's final fit, without --quick, is the reference)", file=out)
            elif not ff.get("kept"):
                spp = (doc.get("settings") or {}).get("spp")
                print("  (sigma_t, albedo and the phase after are the Levenberg-Marquardt refit's: "
                      + (f"{spp}-spp " if spp else "") + "renders at fixed seeds, whose render noise biases "
                      "them beyond their uncertainties (albedo 0.02-0.07 low at 512 spp on the synthetic proof "
                      "suite); the estimator's final fit, without --quick, does not share this bias)", file=out)
    if doc.get("refit_run"):
        print(f"refit written as estimate run {doc['refit_run']}", file=out)
    # The whole path where the session's is known: a terminal's reader may be anywhere.
    session_dir = Path(doc["session"]) if doc.get("session") else Path()
    print(f"diagnosis written to {session_dir / 'diagnoses' / doc['run_id'] / 'diagnosis.yaml'}", file=out)
    return out.getvalue().rstrip()
