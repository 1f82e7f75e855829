"""The exponential phase function's degree, chosen by the recording (`rig estimate --degree auto`).

The paper fits the exponential function of degree 3, and the estimator's default stays
there. Degree 3 cannot follow every medium: the near-Rayleigh phase of small particles
(1 + mu^2 has a mu^4 term in its logarithm's series) is 2 % off in ln p at best, and the
paper simulation's forward-peaked d 0.5 um media tens of percent (`docs/estimation-log.md`,
session 65). On low-noise recordings that shows as a loss above the noise floor while the
material still comes out right (d 0.01 um / sigma_t 2: 1.67 x the floor), or as a biased
sigma_t where the misfit phase trades against it (d 0.5 um: -3 %, +11 %). Raising the degree
is then the first thing to try; this module does it with a stated rule rather than by hand.

The degrees are nested (exp<M> is exp<M+1> with b_{M+1} = 0), so each fit starts from the
previous degree's optimum with the new coefficient at 0 and needs no coarse search. Each
degree's fit is compared on the same footing: its parameters are rendered at `EVAL_SEEDS`
pairs of independent seeds (the same seeds for every degree; at 2 x the final spp, or more
where the recording is quieter than such renders: `comparison_spp`), its chi^2 is the product of
the pair's residuals (no render-variance term: `degree_chi2`), weighted by one
metric for all degrees: the HDR variance plus the first degree's render variance, scaled per
angle by the empirical white-noise factor f of its residuals (`estimate.residuals`; what the
recording's pixel noise is does not depend on the model). The Bayesian information criterion

    BIC_M = chi^2_adjusted(M) + (free parameters of M) ln(pixels)

then decides: a degree replaces the best one so far only when it lowers the BIC by more than
`BIC_MARGIN` plus twice the standard error of that difference over the seed pairs (the render
noise the common seeds leave). A close call, a gain within `CLOSE_SE` standard errors of that
bar or one the rule would take that the error without the pairing does not hold up, is
rendered at more seed pairs (`CLOSE_SEEDS` in all, for both degrees) and decided again: with
four pairs the standard error is itself known to a factor of about two (three degrees of
freedom), and on the paper simulation's d 0.5 um / sigma_t 6 the same call went either way
between runs (`docs/estimation-log.md`, sessions 80 and 81). The search stops after
`PATIENCE` degrees in a row that do not gain, or at `MAX_DEGREE` (the largest the paper
evaluated; `rig estimate --degree-max` allows up to `DEGREE_LIMIT`). The figures on the paper
simulation's recordings (`benchmarks/bench_paper_sim.py --models expauto`) are in the README,
those on recordings of an exp3 truth (`benchmarks/bench_estimate.py --model expauto`) in
`docs/estimation-log.md` (sessions 77 and 81).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, get_args

import numpy as np

from estimate.errors import ModelParameterError
from estimate.evaluation import smoothed_along_rows
from estimate.fit import FitResult, FitSettings, fit_channel, forward_model
from estimate.loss import profile_scale, reference_delta
from estimate.problem import Problem
from estimate.residuals import noise_floor

__all__ = ["BIC_MARGIN", "CLOSE_SE", "CLOSE_SEEDS", "DEGREE_LIMIT", "EVAL_RENDER_RATIO", "EVAL_SEEDS", "EVAL_SPP_FACTOR",
           "EVAL_SPP_MAX_FACTOR", "MAX_DEGREE", "MIN_DEGREE", "PATIENCE", "START_FROM", "DegreeChoice",
           "DegreeStep", "Metric", "StartFrom", "choose_degree", "comparison_spp", "degree_chi2"]

#: The first degree tried (the paper's) and the largest by default (the largest the paper
#: evaluated; `rig estimate --degree-max` raises it up to `DEGREE_LIMIT`, the highest degree
#: `rig estimate` fits at all).
MIN_DEGREE = 3
MAX_DEGREE = 7
DEGREE_LIMIT = 12
#: A higher degree must lower the BIC by more than this (2 ln of a Bayes factor of about 150,
#: "very strong" on Kass and Raftery's scale; `estimate.diagnose.BIC_STRONG` for effects) ...
BIC_MARGIN = 10.0
#: ... plus this many standard errors of the difference over the seed pairs.
SE_MULTIPLE = 2.0
#: Seed pairs each degree's parameters are rendered at for the comparison, each render at
#: this many times the fits' final spp: the comparison's render noise is what limits the
#: gains the rule can resolve (at sigma_t 6 on the paper simulation, +-30-170 of chi^2 at
#: 1 x 1024 spp), and these renders cost far less than the fits.
EVAL_SEEDS = 4
EVAL_SPP_FACTOR = 2
#: Where the recording is quieter than those renders, the comparison is rendered again at more
#: spp: the smallest power-of-two multiple of the first spp at which the render variance of
#: one pair's mean, s^2 v_render, comes to at most `EVAL_RENDER_RATIO` x the HDR variance on
#: average over the pixels, capped at `EVAL_SPP_MAX_FACTOR` x the fits' final spp. Near
#: sensor noise the render variance otherwise fills the weights (12 x the HDR variance on the
#: paper simulation's d 0.3 um / sigma_t 2 at 16384 spp) and shrinks every gain with them:
#: there own-start exp7's gain over exp3 was -42 +- 22 at 2048 spp and +136 +- 15 at 32768
#: (`benchmarks/exp_degree_eval_spp.py`, `docs/estimation-log.md`, session 86).
EVAL_RENDER_RATIO = 1.0
EVAL_SPP_MAX_FACTOR = 32
#: A gain within this many of its standard errors of the bar (BIC_MARGIN + SE_MULTIPLE SE), or
#: above the bar but not by the unpaired error, is a close call, and is decided again over
#: this many seed pairs in all (the standard error falls by 2 and is itself known to about
#: 20 % rather than 40 %). At the paper simulation's sigma_t 6 the 24 more renders at 2048 spp
#: take 16-28 s a degree on 2 cores.
CLOSE_SE = 2.0
CLOSE_SEEDS = 16
#: Stop after this many degrees in a row that do not beat the best so far.
PATIENCE = 2
#: Where each degree's fit starts: "below", the previous degree's optimum with the new
#: coefficient at 0 (the default), or "own", the estimator's own coarse start, as `--degree M`
#: fits it. On the paper simulation's forward media recorded near sensor noise, own-start fits
#: of single degrees came 1.1-6 x nearer the noise floor than the "below" chain's, but the whole
#: search with "own" met the targets on the same 4 of 8 cases: the rule's chi^2, limited by its
#: comparison renders' noise, did not see the gains (`docs/estimation-log.md`, session 85). So
#: the default stays "below"; "own" is kept for measuring the starts again once it can.
StartFrom = Literal["below", "own"]
START_FROM: tuple[StartFrom, ...] = get_args(StartFrom)
#: Base seed of the comparison renders (apart from the fits' own).
_EVAL_SEED = 515_151

#: fit(phase, start) -> FitResult: one channel's fit of phase model "exp<M>" from `start`
#: (None: the estimator's own start).
FitFn = Callable[[str, Mapping[str, float] | None], FitResult]


@dataclass
class DegreeStep:
    """One degree's fit and its place in the comparison.

    Attributes:
        degree: M of exp<M>.
        fit: the fit.
        chi2_adjusted_seeds: chi^2 in the noise-floor metric per seed pair (`EVAL_SEEDS`, or
            `CLOSE_SEEDS` once the degree took part in a close call).
        free: fitted parameters (the scale counts when it is fitted).
        ln_pixels: ln of the comparison's pixels (the BIC's price of a parameter).
        gain: BIC of the best degree before this one minus this one's (positive: better).
        gain_se: standard error of `gain` over the seed pairs.
        gain_pairs: seed pairs `gain` was taken over (more than `EVAL_SEEDS` after a close call).
        accepted: it became the best degree.
    """

    degree: int
    fit: FitResult
    chi2_adjusted_seeds: list[float]
    free: int
    ln_pixels: float
    gain: float = float("nan")
    gain_se: float = float("nan")
    gain_pairs: int = 0
    accepted: bool = False

    @property
    def chi2_adjusted(self) -> float:
        """chi^2 in the noise-floor metric, mean over the seed pairs."""
        return float(np.mean(self.chi2_adjusted_seeds))

    @property
    def bic(self) -> float:
        """chi2_adjusted + free ln(pixels)."""
        return self.chi2_adjusted + self.free * self.ln_pixels

    def to_dict(self) -> dict[str, Any]:
        f = self.fit
        return {"degree": self.degree, "model": f.model, "chi2_adjusted": self.chi2_adjusted,
                "chi2_adjusted_seeds": list(self.chi2_adjusted_seeds), "seed_pairs": len(self.chi2_adjusted_seeds),
                "free": self.free, "bic": self.bic,
                "gain": self.gain, "gain_se": self.gain_se, "gain_pairs": self.gain_pairs, "accepted": self.accepted,
                "reduced_chi2": f.reduced_chi2, "loss_unbiased": f.loss_unbiased,
                "sigma_t": f.parameters["sigma_t"], "albedo": f.parameters["albedo"], "time_s": f.time_s}


@dataclass
class DegreeChoice:
    """The degrees tried on one channel and the one kept.

    Attributes:
        chosen: the degree kept.
        steps: every degree fitted, in order.
        pixels: pixels of the comparison (the n of ln n).
        noise_scale: f per angle (the degree-3 fit's), >= 1.
        stopped: why the search ended.
        seeds: seed pairs of each comparison; close_seeds: of a close call's.
        start_from: where each degree's fit started (`START_FROM`).
        spp: samples per pixel of the comparison renders (`comparison_spp`).
        render_ratio_first: s^2 v_render / var of the first renders, at `EVAL_SPP_FACTOR` x
            the final spp (`Metric.render_ratio`); render_ratio: at `spp`.
    """

    chosen: int
    steps: list[DegreeStep]
    pixels: int
    noise_scale: list[float] = field(default_factory=list)
    stopped: str = ""
    seeds: int = EVAL_SEEDS
    close_seeds: int = CLOSE_SEEDS
    start_from: StartFrom = "below"
    spp: int = 0
    render_ratio_first: float = float("nan")
    render_ratio: float = float("nan")

    @property
    def fit(self) -> FitResult:
        """The chosen degree's fit."""
        return next(s.fit for s in self.steps if s.degree == self.chosen)

    def to_dict(self) -> dict[str, Any]:
        return {"chosen": self.chosen, "rule": f"BIC in the noise-floor metric; a higher degree replaces the best "
                f"so far when it gains more than {BIC_MARGIN:g} + {SE_MULTIPLE:g} standard errors over "
                f"{self.seeds} common seed pairs ({self.close_seeds} when the gain is within {CLOSE_SE:g} "
                f"standard errors of that bar)", "pixels": self.pixels,
                "noise_scale": list(self.noise_scale), "stopped": self.stopped, "seeds": self.seeds,
                "close_seeds": self.close_seeds, "start_from": self.start_from, "spp": self.spp,
                "render_ratio_first": self.render_ratio_first, "render_ratio": self.render_ratio,
                "steps": [s.to_dict() for s in self.steps]}

    @property
    def outcome(self) -> str:
        """The search's end in one line: the degree kept, why it stopped, the comparison spp."""
        return f"kept exp{self.chosen} ({self.stopped}; compared at {self.spp} spp)"

    def describe(self) -> str:
        """One line per degree for the terminal."""
        lines = []
        for s in self.steps:
            mark = "kept" if s.degree == self.chosen else ("better" if s.accepted else "")
            gain = "" if math.isnan(s.gain) else f", BIC gain {s.gain:+.1f} +- {s.gain_se:.1f}"
            if s.gain_pairs > self.seeds:
                gain += f" ({s.gain_pairs} seed pairs)"
            lines.append(f"exp{s.degree}: chi2 at the noise floor {s.chi2_adjusted:.1f}{gain}, sigma_t "
                         f"{s.fit.parameters['sigma_t']:.4g}, albedo {s.fit.parameters['albedo']:.4f}"
                         + (f"  <- {mark}" if mark else ""))
        return "\n".join(lines) + f"\n{self.outcome}"


def _free_count(fit: FitResult) -> int:
    return len(fit.free) + (1 if fit.scale_mode == "free" else 0)


@dataclass(frozen=True)
class Metric:
    """The weights every degree's chi^2 is taken with: 1 / (f^2 (var + s^2 v_render)) per
    pixel (0 where unused), from the first degree's renders; f per angle."""

    weights: np.ndarray
    noise_scale: np.ndarray
    #: Samples per pixel of every comparison render made with this metric.
    spp: int
    #: Mean over the used pixels of s^2 v_render / var: the render variance of one pair's
    #: mean at `spp` over the HDR variance (what `comparison_spp` scales the spp by).
    render_ratio: float = float("nan")


def degree_chi2(problem: Problem, fit: FitResult, settings: FitSettings, *, seeds: int = EVAL_SEEDS,
                extensions: Sequence[str] = (), metric: Metric | None = None,
                first: int = 0, spp: int | None = None) -> tuple[list[float], Metric]:
    """chi^2 of a fit without its renders' noise, at `seeds` seed pairs common to every degree
    (pairs first, first + 1, ...: a close call adds pairs to those already rendered).

    The fit's parameters (extensions' too) are rendered with its own phase model at the
    metric's spp (without a metric: `spp`, or `EVAL_SPP_FACTOR` x `settings.final_spp`), twice per pair with independent seeds A and B, and

        chi^2 = sum_valid w (m - s I_A) (m - s I_B)

    with m the recording and s the fit's scale (calibrated) or the one profiled on the pair's
    mean (free). The product of two independent residuals has no render-variance term (the
    decorrelated loss of `estimate.loss`, in chi^2 form), so each degree is judged by how far
    its model is from the recording rather than by how noisy its renders are. The weights w
    are the same for every degree (`metric`; None: made from this fit's renders): the HDR
    variance var plus the render variance v_render of one render's mean (the sample variance
    of all 2 x `seeds` renders, smoothed along the row), scaled per angle by the noise-floor
    factor f (`estimate.residuals.noise_floor` of the residuals in that variance). Without
    the render variance in them the pixels where the render noise dominates (the peaks at
    sigma_t 6) weigh most, and their noise made the chi^2 of the paper simulation's
    d 0.01 um / sigma_t 6 scatter by +-700 between seed pairs. Returns (chi^2 per seed pair,
    the metric).
    """
    delta = reference_delta(settings.delta_range)
    fm = forward_model(problem, fit.model, extensions, settings.engine)
    reqs = []
    for k in range(first, first + seeds):
        sa = _EVAL_SEED + 1_000 * k
        reqs += [(fit.parameters, sa), (fit.parameters, sa + 7_777)]
    if metric is not None:
        spp = metric.spp
    elif spp is None:
        spp = EVAL_SPP_FACTOR * settings.final_spp
    renders = np.stack(fm.render_profiles_many(reqs, problem.angles_deg, spp=spp))
    m, var, valid = problem.measured, problem.variance, problem.valid
    scales = [fit.scale if fit.scale_mode == "calibrated"
              else profile_scale(m, 0.5 * (renders[2 * k] + renders[2 * k + 1]), valid, delta) for k in range(seeds)]
    if metric is None:
        # The variance of one pair's mean (what the recording is compared with), smoothed:
        # one pixel's sample variance over a few renders is itself noisy.
        vr = smoothed_along_rows(np.var(renders, axis=0, ddof=1)) / 2.0
        s0 = float(np.mean(scales))
        den = np.where(valid & (var > 0), var + s0 ** 2 * vr, np.inf)
        mean = renders.mean(axis=0)
        f, _ = noise_floor(np.where(valid, (m - s0 * mean) / np.sqrt(den), np.nan))
        used = np.isfinite(den)
        ratio = float(np.mean(s0 ** 2 * vr[used] / var[used])) if np.any(used) else float("nan")
        metric = Metric(np.where(used, 1.0 / den, 0.0) / (f ** 2)[:, None], f, spp, ratio)
    row = [float(np.sum(metric.weights * (m - sk * renders[2 * k]) * (m - sk * renders[2 * k + 1])))
           for k, sk in enumerate(scales)]
    return row, metric


def comparison_spp(metric: Metric, max_spp: int) -> int:
    """The comparison renders' spp for a recording whose first comparison (at `metric.spp`)
    left `metric.render_ratio`: `metric.spp` doubled until the render variance, which falls as
    1 / spp, is at most `EVAL_RENDER_RATIO` x the HDR variance on average, or as long as it
    stays within `max_spp` (never below `metric.spp`)."""
    spp, ratio = metric.spp, metric.render_ratio
    cap = max(metric.spp, max_spp)
    while math.isfinite(ratio) and ratio > EVAL_RENDER_RATIO and 2 * spp <= cap:
        spp, ratio = 2 * spp, ratio / 2
    return spp


def choose_degree(problem: Problem, settings: FitSettings, *, fit: FitFn | None = None,
                  extensions: Sequence[str] = (), min_degree: int = MIN_DEGREE, max_degree: int = MAX_DEGREE,
                  seeds: int = EVAL_SEEDS, close_seeds: int = CLOSE_SEEDS, start_from: StartFrom = "below",
                  max_spp: int | None = None,
                  log: Callable[[str], None] | None = None) -> DegreeChoice:
    """Fit exp<min_degree>, exp<min_degree + 1>, ... and keep the degree the BIC rule picks
    (module docstring). `fit(phase, start)` fits one degree (None: `fit_channel` with
    `settings` and `extensions`); with `start_from` "below" each starts from the previous
    degree's parameters with the new coefficient at 0, with "own" from the estimator's own
    start (`START_FROM`). Each degree is compared at `seeds` seed pairs, a close call at
    `close_seeds` (a value no larger than `seeds`: close calls are not rendered again). The
    comparison renders are at `EVAL_SPP_FACTOR` x the final spp, or more where the recording is
    quieter than they are (`comparison_spp`, up to `max_spp`; None: `EVAL_SPP_MAX_FACTOR` x
    the final spp)."""
    if fit is None:
        def fit(phase: str, start: Mapping[str, float] | None) -> FitResult:
            return fit_channel(problem, phase, extensions=extensions, start=start, settings=settings)
    if not 0 <= min_degree <= max_degree:
        raise ModelParameterError(f"degrees {min_degree}..{max_degree}: need 0 <= first <= last")
    if start_from not in START_FROM:
        raise ModelParameterError(f"start {start_from!r}: choose from {', '.join(START_FROM)}")
    if seeds < 2:
        raise ModelParameterError(f"{seeds} seed pairs: the comparison's standard error needs at least 2")
    if max_spp is not None and max_spp < 1:
        raise ModelParameterError(f"comparison renders of at most {max_spp} spp: use a positive number")
    close_seeds = max(close_seeds, seeds)
    steps: list[DegreeStep] = []
    best: DegreeStep | None = None
    metric: Metric | None = None
    pixels = int(np.sum(problem.valid))
    ln_pixels = math.log(pixels)
    misses = 0
    probe: Metric | None = None
    stopped = f"reached exp{max_degree}, the largest tried"
    start: dict[str, float] | None = None

    def extend(step: DegreeStep) -> None:
        """Render `step` at the seed pairs it lacks up to `close_seeds`."""
        have = len(step.chi2_adjusted_seeds)
        if have < close_seeds:
            more, _ = degree_chi2(problem, step.fit, settings, seeds=close_seeds - have, extensions=extensions,
                                  metric=metric, first=have)
            step.chi2_adjusted_seeds = step.chi2_adjusted_seeds + [float(x) for x in more]

    def compare(best: DegreeStep, step: DegreeStep) -> None:
        """`step`'s BIC gain over `best` and its standard error, over their common seed pairs."""
        n = min(len(best.chi2_adjusted_seeds), len(step.chi2_adjusted_seeds))
        d = (np.asarray(best.chi2_adjusted_seeds[:n]) - np.asarray(step.chi2_adjusted_seeds[:n])
             + (best.free - step.free) * ln_pixels)
        step.gain, step.gain_se, step.gain_pairs = float(np.mean(d)), float(np.std(d, ddof=1) / math.sqrt(n)), n

    def close(best: DegreeStep, step: DegreeStep) -> bool:
        """A call to decide again over more pairs: a gain near the bar, or one the rule would
        take that the unpaired standard error does not hold up."""
        bar = BIC_MARGIN + SE_MULTIPLE * step.gain_se
        if abs(step.gain - bar) < CLOSE_SE * step.gain_se:
            return True
        # The paired error over four pairs has three degrees of freedom and can come out far
        # too small by chance (session 81: +134 +- 20 on a case whose paired error is near
        # 65-100). The common seeds correlate the degrees' chi^2 positively, so the error
        # without the pairing bounds the paired one from above: a gain that only the paired
        # error makes significant is checked over more pairs before it becomes the best,
        # which every later degree must beat. (A refused gain needs no such check: the next
        # degree is compared with the same best.)
        n = step.gain_pairs
        a, b = np.asarray(best.chi2_adjusted_seeds[:n]), np.asarray(step.chi2_adjusted_seeds[:n])
        unpaired = math.sqrt((np.var(a, ddof=1) + np.var(b, ddof=1)) / n)
        return step.gain > bar and step.gain - SE_MULTIPLE * unpaired <= BIC_MARGIN

    for m in range(min_degree, max_degree + 1):
        res = fit(f"exp{m}", start if start_from == "below" else None)
        first_metric = metric is None
        chi, metric = degree_chi2(problem, res, settings, seeds=seeds, extensions=extensions, metric=metric)
        if first_metric:
            probe = metric
            spp = comparison_spp(metric, EVAL_SPP_MAX_FACTOR * settings.final_spp if max_spp is None else max_spp)
            if spp > metric.spp:
                if log:
                    log(f"  the comparison renders' variance at {metric.spp} spp is {metric.render_ratio:.1f} x "
                        f"the recording's: comparing at {spp} spp")
                chi, metric = degree_chi2(problem, res, settings, seeds=seeds, extensions=extensions, spp=spp)
        step = DegreeStep(m, res, [float(x) for x in chi], _free_count(res), ln_pixels)
        note = ""
        if best is None:
            step.accepted = True
            best = step
        else:
            compare(best, step)
            if close_seeds > seeds and close(best, step):
                extend(best)
                extend(step)
                compare(best, step)
                note = f" over {step.gain_pairs} seed pairs (a close call)"
            if step.gain > BIC_MARGIN + SE_MULTIPLE * step.gain_se:
                step.accepted = True
                best = step
                misses = 0
            else:
                misses += 1
        steps.append(step)
        if log:
            log(f"  exp{m}: chi2 at the noise floor {step.chi2_adjusted:.1f}"
                + ("" if math.isnan(step.gain) else f", BIC gain {step.gain:+.1f} +- {step.gain_se:.1f}{note}")
                + (" (better)" if step.accepted and len(steps) > 1 else ""))
        if misses >= PATIENCE:
            stopped = f"stopped after {PATIENCE} degrees in a row that gained no more than the margin"
            break
        start = dict(res.parameters)
        start[f"phase.b{m + 1}"] = 0.0
    assert best is not None and metric is not None and probe is not None
    return DegreeChoice(best.degree, steps, pixels, [float(x) for x in metric.noise_scale], stopped, seeds,
                        close_seeds, start_from, metric.spp, probe.render_ratio, metric.render_ratio)
