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
pairs of seeds (the same seeds for every degree, so most of the render noise is common to
all and cancels in their differences), and its chi^2 is taken in the noise-floor metric of
`estimate.residuals` (the HDR variance scaled per angle by the empirical white-noise factor
f of the degree-3 fit's residuals, one f for all degrees: what the recording's pixel noise
is does not depend on the model). The Bayesian information criterion

    BIC_M = chi^2_adjusted(M) + (free parameters of M) ln(pixels)

then decides: a degree replaces the best one so far only when it lowers the BIC by more than
`BIC_MARGIN` plus twice the standard error of that difference over the seed pairs (the render
noise the common seeds leave). The search stops after `PATIENCE` degrees in a row that do
not, or at `MAX_DEGREE` (the largest the paper evaluated). On the paper simulation's
recordings (`benchmarks/bench_paper_sim.py --models expauto`) and on recordings of an exp3
truth (`benchmarks/bench_estimate.py --degree auto`) the figures are in the README.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from estimate.errors import ModelParameterError
from estimate.evaluation import evaluate
from estimate.fit import FitResult, FitSettings, forward_model
from estimate.loss import reference_delta
from estimate.problem import Problem
from estimate.residuals import noise_floor, normalised_residuals

__all__ = ["BIC_MARGIN", "EVAL_SEEDS", "MAX_DEGREE", "MIN_DEGREE", "PATIENCE", "DegreeChoice", "DegreeStep",
           "choose_degree", "degree_chi2"]

#: The first degree tried (the paper's) and the largest (the largest the paper evaluated).
MIN_DEGREE = 3
MAX_DEGREE = 7
#: A higher degree must lower the BIC by more than this (2 ln of a Bayes factor of about 150,
#: "very strong" on Kass and Raftery's scale; `estimate.diagnose.BIC_STRONG` for effects) ...
BIC_MARGIN = 10.0
#: ... plus this many standard errors of the difference over the seed pairs.
SE_MULTIPLE = 2.0
#: Seed pairs each degree's parameters are rendered at for the comparison.
EVAL_SEEDS = 4
#: Stop after this many degrees in a row that do not beat the best so far.
PATIENCE = 2
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
        chi2_adjusted: chi^2 in the noise-floor metric, mean over the seed pairs.
        chi2_adjusted_seeds: the same per seed pair.
        free: fitted parameters (the scale counts when it is fitted).
        bic: chi2_adjusted + free ln(pixels).
        gain: BIC of the best degree before this one minus this one's (positive: better).
        gain_se: standard error of `gain` over the seed pairs.
        accepted: it became the best degree.
    """

    degree: int
    fit: FitResult
    chi2_adjusted: float
    chi2_adjusted_seeds: list[float]
    free: int
    bic: float
    gain: float = float("nan")
    gain_se: float = float("nan")
    accepted: bool = False

    def to_dict(self) -> dict[str, Any]:
        f = self.fit
        return {"degree": self.degree, "model": f.model, "chi2_adjusted": self.chi2_adjusted,
                "chi2_adjusted_seeds": list(self.chi2_adjusted_seeds), "free": self.free, "bic": self.bic,
                "gain": self.gain, "gain_se": self.gain_se, "accepted": self.accepted,
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
    """

    chosen: int
    steps: list[DegreeStep]
    pixels: int
    noise_scale: list[float] = field(default_factory=list)
    stopped: str = ""
    seeds: int = EVAL_SEEDS

    @property
    def fit(self) -> FitResult:
        """The chosen degree's fit."""
        return next(s.fit for s in self.steps if s.degree == self.chosen)

    def to_dict(self) -> dict[str, Any]:
        return {"chosen": self.chosen, "rule": f"BIC in the noise-floor metric; a higher degree replaces the best "
                f"so far when it gains more than {BIC_MARGIN:g} + {SE_MULTIPLE:g} standard errors over "
                f"{self.seeds} common seed pairs", "pixels": self.pixels,
                "noise_scale": list(self.noise_scale), "stopped": self.stopped,
                "steps": [s.to_dict() for s in self.steps]}

    def describe(self) -> str:
        """One line per degree for the terminal."""
        lines = []
        for s in self.steps:
            mark = "kept" if s.degree == self.chosen else ("better" if s.accepted else "")
            gain = "" if math.isnan(s.gain) else f", BIC gain {s.gain:+.1f} +- {s.gain_se:.1f}"
            lines.append(f"exp{s.degree}: chi2 at the noise floor {s.chi2_adjusted:.1f}{gain}, sigma_t "
                         f"{s.fit.parameters['sigma_t']:.4g}, albedo {s.fit.parameters['albedo']:.4f}"
                         + (f"  <- {mark}" if mark else ""))
        return "\n".join(lines) + f"\n({self.stopped})"


def _free_count(fit: FitResult) -> int:
    return len(fit.free) + (1 if fit.scale_mode == "free" else 0)


def degree_chi2(problem: Problem, fit: FitResult, settings: FitSettings, *, seeds: int = EVAL_SEEDS,
                extensions: Sequence[str] = (), noise_scale: np.ndarray | None = None
                ) -> tuple[list[float], np.ndarray]:
    """chi^2 of a fit in the noise-floor metric at `seeds` seed pairs common to every degree.

    The fit's parameters (extensions' too) are rendered with its own phase model at
    `settings.final_spp`, its scale as fitted when calibrated and profiled otherwise.
    `noise_scale`: f per angle (None: estimated from this fit's first pair, `noise_floor`).
    Returns (chi^2 per seed pair, f).
    """
    delta = reference_delta(settings.delta_range)
    fm = forward_model(problem, fit.model, extensions, settings.engine)
    fixed_scale = fit.scale if fit.scale_mode == "calibrated" else None
    f = noise_scale
    row = []
    for k in range(seeds):
        ev = evaluate(fm, problem, fit.parameters, spp=settings.final_spp, seed=_EVAL_SEED + 1_000 * k,
                      delta_rel=delta, fixed_scale=fixed_scale)
        r = normalised_residuals(problem.measured, problem.variance, ev["profiles"], ev["scale"],
                                 ev["model_variance"])
        r = np.where(problem.valid, r, np.nan)
        if f is None:
            f, _ = noise_floor(r)
        row.append(float(np.nansum((r / f[:, None]) ** 2)))
    assert f is not None
    return row, f


def choose_degree(problem: Problem, fit: FitFn, settings: FitSettings, *, extensions: Sequence[str] = (),
                  min_degree: int = MIN_DEGREE, max_degree: int = MAX_DEGREE, seeds: int = EVAL_SEEDS,
                  log: Callable[[str], None] | None = None) -> DegreeChoice:
    """Fit exp<min_degree>, exp<min_degree + 1>, ... and keep the degree the BIC rule picks
    (module docstring). `fit(phase, start)` fits one degree; each starts from the previous
    degree's parameters with the new coefficient at 0."""
    if not 0 <= min_degree <= max_degree:
        raise ModelParameterError(f"degrees {min_degree}..{max_degree}: need 0 <= first <= last")
    if seeds < 2:
        raise ModelParameterError(f"{seeds} seed pairs: the comparison's standard error needs at least 2")
    steps: list[DegreeStep] = []
    best: DegreeStep | None = None
    f_ref: np.ndarray | None = None
    pixels = int(np.sum(problem.valid))
    misses = 0
    stopped = f"reached exp{max_degree}, the largest tried"
    start: dict[str, float] | None = None
    for m in range(min_degree, max_degree + 1):
        res = fit(f"exp{m}", start)
        chi, f_ref = degree_chi2(problem, res, settings, seeds=seeds, extensions=extensions, noise_scale=f_ref)
        free = _free_count(res)
        step = DegreeStep(m, res, float(np.mean(chi)), chi, free, float(np.mean(chi)) + free * math.log(pixels))
        if best is None:
            step.accepted = True
            best = step
        else:
            d = np.asarray(best.chi2_adjusted_seeds) - np.asarray(chi) + (best.free - free) * math.log(pixels)
            step.gain = float(np.mean(d))
            step.gain_se = float(np.std(d, ddof=1) / math.sqrt(d.size))
            if step.gain > BIC_MARGIN + SE_MULTIPLE * step.gain_se:
                step.accepted = True
                best = step
                misses = 0
            else:
                misses += 1
        steps.append(step)
        if log:
            log(f"  exp{m}: chi2 at the noise floor {step.chi2_adjusted:.1f}"
                + ("" if math.isnan(step.gain) else f", BIC gain {step.gain:+.1f} +- {step.gain_se:.1f}")
                + (" (better)" if step.accepted and len(steps) > 1 else ""))
        if misses >= PATIENCE:
            stopped = f"stopped after {PATIENCE} degrees in a row that gained no more than the margin"
            break
        start = dict(res.parameters)
        start[f"phase.b{m + 1}"] = 0.0
    assert best is not None and f_ref is not None
    return DegreeChoice(best.degree, steps, pixels, [float(x) for x in f_ref], stopped, seeds)

