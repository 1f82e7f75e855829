"""Fit sigma_t, albedo and the phase function of one channel by differentiable rendering.

`fit_channel(problem, model)` runs the stages below. This module holds the settings, the
result and the loop; the stages' parts live beside it: `estimate.start` (1),
`estimate.gauss_newton` (3), `estimate.polish` (5), `estimate.evaluation` (6) and
`estimate.uncertainties` (7).

1. start: `estimate.start.coarse_start` (joint grid over a few phase shapes x sigma_t x albedo,
   at 32 spp) unless `start` gives sigma_t and albedo;
2. Adam on unconstrained variables (`estimate.transforms`: log sigma_t, logit albedo,
   exp coefficients clamped to +-200, tanh for HG g, logit for the lobe weight), gradient
   from the reverse-mode pass of the log loss (`estimate.loss`; `ForwardModel.linearize`
   keeps each render's paths for its replay, so a render is traced once) with delta drawn at random per
   iteration and the scale profiled out; every iteration uses new seeds. By default
   (`decorrelated`) the loss is mean(r_A r_B) over two independent half-spp renders A, B
   (r = log(m + delta) - log(I + delta)): the plain loss's expectation contains the
   render's Monte Carlo variance of log I, which pulled fits towards less noisy parameters
   (albedo 0.9 -> 0.5 on the paper's d = 0.5 um case); the product's does not.
   Additive parameters (a stray-light offset and slope: `ForwardModel.additive_parameters`)
   are not stepped: like a free scale they are solved exactly on each iteration's two
   renders (bounded least squares on the log residuals, no render), their columns are
   projected out of the Gauss-Newton matrix, and the final evaluation solves them once more;
3. after `adam_iterations` (10) Adam steps, Gauss-Newton steps (`optimizer="adam+gn"`):
   z <- z - gn_step (2/n A^T A)^-1 g_avg, with g_avg a running mean (momentum 0.7) of the
   reverse-mode gradients and A = d r / d z from a finite-difference Jacobian with large
   steps (`gn_jacobian`, re-estimated every `gn_jacobian_every` iterations at
   `gn_jacobian_spp`); steps are capped at 5 Adam step sizes. sigma_t and the phase
   coefficients form a curved, strongly correlated valley (condition number of A ~40);
   Adam's per-parameter steps crossed it slowly, overshot from the coarse start and, on the
   benchmark's synthetic session, stopped 9-11 % high in sigma_t after 80 iterations and
   146 s. Two things make the Gauss-Newton steps cross the valley (session 14):
   the Jacobian's log-space columns are smoothed along the row (`gn_smooth_px`, 3 px)
   before A^T A is formed, because the finite differences' per-pixel Monte Carlo noise adds
   its own Gram matrix, which inflated the valley's eigenvalue up to 63x at 256 spp (2-6x
   after smoothing) and so shortened the steps along it as much; and each eigen-direction
   of the step is shrunk by its averaged gradient's signal / (signal + noise) (`gn_snr`,
   `snr_step`), so the longer steps do not turn gradient noise into excursions along b2
   against b3. On the benchmark session the fit then ended 1-3 % from the truth's sigma_t
   (seed 0 twice) and 5-6 % (seeds 1, 2), against 15 % before, in the same ~75 iterations.
   Since session 15 the matrix is that of the loss averaged over delta (`gn_delta_nodes`
   midpoints of log delta), matching the momentum-averaged gradient, which mixes the
   iterations' random deltas: with the iteration's own delta the matrix's weakest
   eigenvalue changed by up to 25x between iterations, and a large-delta matrix applied to
   small-delta gradients threw b2 and b3 to -5 / +5 (seeds 3 and 4 ended 22 % and 13 % high).
   With it the benchmark's fits ended 2-7.5 % high at seeds 0-5 (session 15), still walking
   down the valley when the iterations stopped: along the valley the averaged gradient is
   mostly Monte Carlo noise, and the shrunk steps advance ~0.4 % of sigma_t per iteration;
4. progressive samples per pixel: start at `spp_start` (128); the loss at the reference
   delta is tracked; when over the last 2 x `window` iterations its fitted slope is not
   significantly negative (above -2 standard errors from the scatter of the losses about
   the line, i.e. the Monte Carlo noise of the loss), the fit has flattened at this spp: spp
   doubles and the step shrinks (x0.85, Adam); when it flattens at `spp_max` (128 since
   session 25; 256 before) the iterations stop ("converged"). Their result is the average of the last `window` iterates
   (2 x `window` for Gauss-Newton), which averages the Monte Carlo noise of the steps; when
   they still drift (`iterate_drift`), the end of their linear trend instead, since their mean
   lags the last iterate by half the window's drift (session 16: 1.3-2.9 % of sigma_t on
   the benchmark);
   Since session 28 the iterations hand over to the polish after `iterations_before_polish`
   (10: the Adam steps alone) whenever there is a polish; the Gauss-Newton iterations and
   the flattening test above run only without one (`polish_steps` = 0) or with
   `iterations_before_polish` = None. On the benchmark (seed 0) the Gauss-Newton
   iterations took 15 iterations (26 s) to end at sigma_t 2.6 (truth 2.0; the coarse start
   had 2.0): the polish then needed eight steps. Started from the tenth Adam iterate, the
   damped polish crossed the valley in as many or fewer steps: seeds 0-3 120, 96, 90 and
   91 s a fit (session 27's recipe 82-143 s), sigma_t +2.0, -2.2, -0.2, -1.0 % (+1.8,
   -2.1, -0.3, -2.2 %). The spp rises from 128 to `final_spp` when the Adam steps end,
   and the polish's steps are then judged against their Monte Carlo noise;
5. Gauss-Newton polish (`gn_polish`, `polish_steps` = 4): full, unshrunk Gauss-Newton steps
   at `final_spp` (two 1024-spp renders per step and a new matrix from the cross product of
   two 512-spp Jacobians, `polish_cross`; since session 25 forward and backward differences
   against half of each render, `polish_one_sided`), which walk down the valley several % of sigma_t
   per step where the iterations crawled (benchmark, session 16: from 2.38 to 1.98 in four
   steps; truth 2.0). It replaced the iterations' 512-spp stage in the time budget, and
   since session 25 their 256-spp stage too: a one-sided polish step costs ~14 s on 2 cores,
   about ten 256-spp iterations, and walks further than those (benchmark seeds 0-3: 110-155 s
   a fit, sigma_t +2.1, -0.8, -0.2, -2.6 %; with the 256-spp stage and central Jacobians
   169-293 s, +0.3, +0.8, -1.1, +2.3 %). Near
   the optimum its steps scatter by 3-5 % of sigma_t (the gradient's noise at 2 x 1024 spp
   along the valley), so the result is the mean of the points after steps 2-4
   (`polish_average_from`, `polish_average`). Each step's chi^2 against its render noise
   and that of the point it starts from (`step_chi2`) tells a move from that scatter; while
   any of the last three is a move (above the 0.1 % quantile, `polish_continue_p`) the
   polish goes on, up to `polish_max_steps` (2 x `polish_steps`), and averages its last
   three points, each weighed by its own noise. Since session 27 a step whose loss rises
   beyond its noise is retried with more Levenberg-Marquardt damping (`polish_damped`), and
   the per-parameter caps are 15 of Adam's last learning rates (`polish_cap_lr`; 5 before):
   benchmark seeds 0-3 82-143 s, sigma_t +1.8, -2.1, -0.3, -2.2 % (the session-25 recipe
   on the same session: 146 s, +2.4 % at seed 0; session 25: 110-155 s). Optionally (`polish_settled_spp` > 1, off by default; session
   19) a step after a noise-sized one keeps the matrix and renders its gradient at that
   many times the spp. A Levenberg-Marquardt polish (`lm_polish`) on the log residuals at
   fixed seeds may follow (since session 83 the decorrelated loss of two renders,
   `lm_decorrelated`) (`lm_plan`): on request (`lm_iterations`), and by default for
   exponential phases of degree 5 and more (`lm_from_degree`: 60 steps at most at 4 x
   `final_spp`). With common random numbers the renders are not smooth in the parameters
   (free flights crossing the slab boundary flip) and its finite-difference Jacobian is
   noisy: on exp3 fits it gained < 10 % of the loss for ~45 s (session 79: nothing on four
   paper-simulation cases). But the coefficients of a higher-degree phase have a long,
   ill-conditioned optimum that the polish's averaged stochastic steps only crawl down, and
   there the deterministic steps walk it (session 79, d 0.5 um / sigma_t 2 on its Mie
   table: exp7 from 2.2 x to 1.08 x the noise floor's loss, sigma_t from -2.5 % to
   -0.5 %). Since session 89 its phase steps are taken in the Legendre coefficients of the
   same exponent (`lm_basis`): Marquardt's damping diag(J^T J) is blind to the near
   collinearity of the monomial columns mu^i, and in monomial steps the LM stopped early
   (d 0.5 um / sigma_t 6, exp7, sigma_t held at the truth: 1.71 x the floor, against 1.21 x
   in Legendre steps). Since session 90 it raises its spp while its optimum still owes more
   than `lm_excess_target` of the noise floor to fitting its own renders' noise
   (`lm_noise_excess`; up to `lm_spp_max_factor` x `final_spp`). After it, the result is the LM's point: its uncertainties take fresh Jacobians
   there and its last step as the drift, not the polish points' scatter;
6. final evaluation at `final_spp` with two seeds: fitted profiles (their mean), the model's
   own Monte Carlo variance per pixel ((p1 - p2)^2 / 4, the variance of the mean of two),
   scale, loss at the reference delta, chi^2 with var_meas + s^2 var_model;
7. uncertainties: the sandwich covariance of the log-loss estimator
   (`sandwich_uncertainties`: Gauss-Newton curvature of the log loss, the sensor and render
   noise propagated through it, times the log-space reduced chi^2 when > 1; since session
   30, when the result averaged polish points, the data's noise alone, its excess sized from
   the residuals (since session 37 the excess share's posterior mean given that it is not
   negative, `excess_share`) and times their pixel correlation (`uncertainty_data_meat`), because the
   points' standard error below carries the render noise; the curvature
   from the cross products of independent Jacobians, the polish's last ones (since session
   28; before, and still when the polish averaged fewer than two points, one more at the
   final point), since one Monte Carlo Jacobian's own noise fakes curvature along the
   sigma_t / phase valley and narrowed sigma_t's interval up to 20x there), never below
   the linear Fisher bound (`fisher_uncertainties`: F = J^T W J with J the Jacobian of
   s * I_model, W = 1 / (var_meas + s^2 var_model), times the reduced chi^2 when > 1; kept
   in `FitResult.fisher_uncertainties`). The Fisher bound alone was 4-25x smaller than the
   real errors: the log loss is not the variance-weighted fit the bound describes, and the
   residuals exceed the noise. Without a polish, the standard deviation of the averaged
   iterates (the stochastic optimiser's own spread, `FitResult.optimizer_spread`) is added
   in quadrature (after a polish the result is not theirs; since session 28), and so is
   the last polish step (`FitResult.drift`; without a polish, the iterates' drift): the
   fit still moved that much at its end. When the polish's points are averaged, their mean
   step is the drift and their mean's standard error is added instead; the drift is then
   added only where it stands out of the points' own scatter (`combined_uncertainties`).
   Parameters whose drift exceeds their uncertainty (with averaged polish points: combined
   with the points' own scatter) are reported as still drifting.

The scale (measured = scale * rendered) is either profiled out per channel
(`FitSettings.scale = "free"`, the paper's normalisation made cleaner) or taken from the
calibration (`"calibrated"`: beam power through the ND filter / ND transmission x pixel
area x the lens's collection solid angle / the rendered beam map's power,
`estimate.loss.calibrated_scale`). A free scale
is nearly degenerate with the albedo: on a 6-angle synthetic problem the free fit's albedo
came out 0.10 low, the calibrated one's within 0.006 (same data, same settings).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np
from scipy.stats import chi2 as chi2_dist

from estimate.deadline import Deadline
from estimate.errors import ModelParameterError
from estimate.evaluation import evaluate, solve_additive
from estimate.forward import ENGINES, ForwardModel, check_engine
from estimate.gauss_newton import (
    gn_inverse,
    gn_jacobian,
    predicted_decrease,
    secant_steps,
    snr_step,
)
from estimate.loss import (
    DEFAULT_DELTA_RANGE,
    ScaleCalibration,
    calibrated_scale,
    log_loss,
    log_measured,
    log_residual,
    profile_scale,
    reference_delta,
)
from estimate.phase_tabulated import TabulatedPhase
from estimate.polish import (
    LM_BASES,
    LMStage,
    averaged_point_count,
    first_averaged_point,
    gn_polish,
    lm_polish,
    polish_average,
)
from estimate.problem import Problem
from estimate.start import coarse_start
from estimate.transforms import Transform, transform_for
from estimate.uncertainties import (
    combined_covariance,
    combined_uncertainties,
    fisher_uncertainties,
    iterate_drift,
    sandwich_uncertainties,
    window_estimate,
    window_scatter,
)

# evaluate, fisher_uncertainties, sandwich_uncertainties and secant_steps live in estimate.evaluation,
# estimate.uncertainties and estimate.gauss_newton; they are re-exported here, where callers met them first.
__all__ = ["FitResult", "FitSettings", "evaluate", "fisher_uncertainties", "finite_number", "fit_channel", "forward_model", "lm_plan",
           "model_phase", "sandwich_uncertainties", "secant_steps"]


def finite_number(x: Any) -> bool:
    """True for an int or float that is finite (not a bool, None, str or NaN): what a
    hand-edited YAML's numeric entries are checked with (`FitSettings`, `estimate.diagnose`)."""
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


#: samples per pixel of the polish and the final evaluation on the CPU (`llvm_ad_*` variants)
CPU_FINAL_SPP = 1024
#: ... and on a GPU (`cuda_ad_*`), where renders cost about a tenth: session 39 on an H200, the
#: paper simulation's four sigma_t-6 cases on 16384-spp recordings, two seeds. At 8192 the
#: loss reached its floor (unbiased ratio <= 1.10) on 7 of 8 fits (3 of 8 at 1024), the
#: sigma_t intervals held the errors (RMS z 1.0; 1.7 at 1024, errors to 2.7 sigma), in 32-44 s
#: a fit (6-12 s at 1024). sigma_t itself was no closer to the truth (see docs/estimation-log.md).
GPU_FINAL_SPP = 8192


@dataclass
class FitSettings:
    """Optimiser settings (defaults: the paper's exp3 fit within ~2 min on 2 cores).

    `FitSettings.for_variant` gives the defaults for the Mitsuba variant in use (more samples
    per pixel on a GPU); `rig estimate` starts from those.
    """

    max_iterations: int = 80
    #: with a polish (polish_steps > 0), the iterations hand over to it after this many
    #: (None: only when the loss flattens at spp_max or max_iterations is reached)
    iterations_before_polish: int | None = 10
    spp_start: int = 128
    spp_max: int = 128               # the iterations' largest spp (the polish and final evaluation: final_spp)
    final_spp: int = CPU_FINAL_SPP   # the polish's and final evaluation's spp (for_variant: more on a GPU)
    start_spp: int = 32               # coarse joint grid (estimate.start)
    window: int = 8
    lr_scale: float = 1.0
    lr_decay: float = 0.85
    delta_range: tuple[float, float] = DEFAULT_DELTA_RANGE
    seed: int = 0
    time_limit_s: float | None = None  # wall-clock budget (s) of the iterations and polishes (estimate.deadline)
    lm_iterations: int = 0           # LM polish steps at most (stops when a step gains < 0.1 % or none is accepted)
    optimizer: str = "adam+gn"       # "adam": Adam throughout; "adam+gn": Adam first, then Gauss-Newton steps
    gn_step: float = 0.3             # fraction of the Gauss-Newton step taken per iteration
    gn_jacobian_every: int = 15      # iterations between re-estimates of the Gauss-Newton matrix
    gn_jacobian_spp: int = 256
    gn_momentum: float = 0.7
    gn_smooth_px: float = 3.0        # Gaussian smoothing (px) of the Jacobian's log-space columns along the row
    gn_snr: bool = True              # shrink each Gauss-Newton eigen-direction by its gradient's signal/(signal+noise)
    gn_delta_nodes: int = 6          # Gauss-Newton matrix averaged over this many deltas (0: the iteration's delta)
    adam_iterations: int = 10        # "adam+gn": Adam iterations before the Gauss-Newton steps
    polish_steps: int = 4            # full Gauss-Newton steps at final_spp after the iterations (0: none)
    polish_jacobian_every: int = 1   # polish steps between re-estimates of its Jacobian
    polish_cross: bool = True        # polish matrix from two half-spp Jacobians' cross product (see gn_polish)
    polish_one_sided: bool = True    # those Jacobians as forward / backward differences against half renders
    polish_average_from: int = 2     # the result: mean of the points after polish steps >= this (1-based; 0: last point)
    polish_max_steps: int | None = None   # polish steps in all while its last points still walk (None: 2 x polish_steps)
    polish_continue_p: float = 0.001  # a step is still a move when its noise chi^2 exceeds this upper quantile
    polish_settled_spp: int = 1      # > 1: after a noise-sized polish step, renders at this x final_spp, last Jacobians kept
    polish_jacobian_spp: int | None = None  # spp of the polish's Jacobians (the two halves' sum; None: final_spp)
    polish_damped: bool = True       # Levenberg-Marquardt damping of polish steps whose loss rises (see gn_polish)
    polish_cap_lr: float = 15.0      # the polish's per-parameter step cap (z), in Adam's last learning rates
    uncertainty_spp: int = 512       # the uncertainties' Jacobian at the final point (two without a polish)
    #: render a central Jacobian at the final point for the uncertainties even when the
    #: polish's last ones (two steps' or more) are there
    uncertainty_final_jacobian: bool = False
    #: when the result is the mean of polish points, the sandwich's meat holds the data's
    #: noise alone (`sandwich_uncertainties(data_meat=True)`); the points' standard error
    #: carries the render noise. False: the render noise in both (session 29's recipe)
    uncertainty_data_meat: bool = True
    #: that data meat from the cross products of the Jacobians, as sessions 30-33 had it
    #: (False: from their mean, whose noise the polish's gradient carries;
    #: `sandwich_uncertainties(meat_cross=...)`)
    uncertainty_meat_cross: bool = False
    #: the reported covariance gives the polish points' standard error the correlation of the
    #: render noise their steps carry (`combined_covariance(polish_correlation=...)`, session
    #: 37); False: that share on the diagonal (session 36)
    uncertainty_polish_correlation: bool = True
    decorrelated: bool = True
    #: solve additive parameters (stray-light offset and slope) exactly at every iteration
    #: instead of stepping them (decorrelated mode only; see fit_channel)
    profile_additive: bool = True
    lm_spp: int = 1024
    #: exp<M> fits of degree M >= this end the polish with the fixed-seed Levenberg-Marquardt
    #: (`lm_polish`) when `lm_iterations` is 0: `lm_degree_iterations` steps at most, at
    #: `lm_degree_spp_factor` x `final_spp` (None: never). From degree 5 on, the optimum of
    #: the phase's coefficients lies along a long, ill-conditioned valley that the stochastic
    #: polish only crawls down (session 79, paper simulation d 0.5 um / sigma_t 2 on the Mie
    #: table itself: exp7 ended at 2.2 x the noise floor's loss, with it at 1.08 x; on four
    #: exp3 cases it gained nothing). At 1024 spp the same LM stalled at 1.28 x on the
    #: renders' noise.
    lm_from_degree: int | None = 5
    #: the LM minimises the decorrelated loss of two half-spp renders (`lm_polish`'s
    #: `decorrelated`, session 83); False: the plain loss of one render (sessions 79-82),
    #: which rewards parameters that render with less noise
    lm_decorrelated: bool = True
    lm_degree_iterations: int = 60
    #: On the 16384-spp recordings of d 0.5 um (session 88, exp7 from its own start, unbiased
    #: loss / floor at 16384 spp) 16 instead of 4 took sigma_t 2 from 1.44 to 1.27 x (the
    #: family's reach there: 1.30 x at the true material) and sigma_t 6 from 1.39 to 1.29 x, at
    #: 2.4-3.8 x the fit's time. Since session 90 this is the first stage's spp only: the LM
    #: goes on at more spp while its noise share is above `lm_excess_target`.
    lm_degree_spp_factor: int = 4
    #: the coordinates of the LM's steps for an exponential phase (`lm_polish`'s `basis`):
    #: "legendre" (the same exponent's Legendre coefficients) or "monomial" (the paper's b_i,
    #: sessions 79-88). On the 16384-spp paper-simulation recordings (session 89, exp7 from the
    #: estimator's own start, unbiased loss / floor at 16384 spp) Legendre steps took d 0.5 um /
    #: sigma_t 6 from 1.39 x and sigma_t +6.3 % to 1.17 x and +3.3 % in the same time (with
    #: sigma_t held at the truth: 1.71 -> 1.21 x), left d 0.5 um / sigma_t 2 at 1.44 x and were
    #: level or a little lower (0.95-1.01 against 0.96-1.03 x) on the six other cases.
    lm_basis: str = "legendre"
    #: the LM raises its spp (powers of two, up to `lm_spp_max_factor` x `final_spp`) until
    #: the loss its optimum owes to fitting its own renders' noise (`lm_noise_excess`) is at
    #: most this share of the recording's noise floor (None: one stage at the planned spp).
    #: On the 16384-spp paper-simulation recording of d 0.5 um / sigma_t 2 (session 90; the
    #: unbiased loss over the truth's at 16384 spp) exp10's LM at 4 x final_spp ended at
    #: 1.19 x, its excess there 0.35; at 16 x (excess about 0.09) at 1.00 x; at 32 x (0.04)
    #: at 1.01 x, in 1.8 x the time of 16 x. On d 0.5 um / sigma_t 6 the excess at 4 x was
    #: 0.79 and the loss 1.15 x; at 16 x 1.19 x; at 32 x (excess 0.11) 1.05 x.
    lm_excess_target: float | None = 0.1
    lm_spp_max_factor: int = 32
    uncertainties: bool = True
    scale: str = "free"              # "free": fitted (profiled) per channel; "calibrated": from the beam power
    #: the forward model's render engine (`estimate.forward.ENGINES`): "light" (paths from
    #: the beam, `estimate.light_paths`: on the bench's synthetic session a fit took 10 s
    #: against the camera engine's 99 s, with a quarter of its uncertainty) or "camera"
    #: (Mitsuba's prbvolpath from the camera)
    engine: str = "light"

    @classmethod
    def for_variant(cls, variant: str | None = None, **kw: Any) -> FitSettings:
        """The defaults for a Mitsuba variant (None: `estimate.mitsuba_env.default_variant()`,
        the one `init_mitsuba` will pick): `final_spp` = `GPU_FINAL_SPP` on a `cuda_*` variant,
        `CPU_FINAL_SPP` otherwise; keyword arguments set fields as in the constructor (an
        explicit `final_spp` wins)."""
        if "final_spp" not in kw:
            from estimate.mitsuba_env import renders_on_gpu

            kw["final_spp"] = GPU_FINAL_SPP if renders_on_gpu(variant) else CPU_FINAL_SPP
        return cls(**kw)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["delta_range"] = list(self.delta_range)
        return d

    @classmethod
    def from_dict(cls, recorded: Mapping[str, Any], where: str = "settings") -> FitSettings:
        """Settings as `to_dict` wrote them (e.g. a results.yaml `settings.fit`, which a
        person may have edited). Unknown keys (from a newer version) are ignored; a value of
        the wrong type or out of range raises `ModelParameterError` naming the key and
        `where` (one line for the user)."""
        out: dict[str, Any] = {}
        defaults = cls()
        for f in fields(cls):
            if f.name not in recorded:
                continue
            v = recorded[f.name]
            default = getattr(defaults, f.name)

            def bad(expected: str, _n: str = f.name, _v: Any = v) -> ModelParameterError:
                return ModelParameterError(f"{where}: fit setting {_n} = {_v!r} is not {expected}; "
                                           "correct it or delete the key to use the default")

            if f.name == "time_limit_s":
                if v is not None and not (finite_number(v) and v > 0):
                    raise bad("a positive number of seconds or null")
            elif f.name == "polish_max_steps":
                if v is not None and not (isinstance(v, int) and not isinstance(v, bool) and v >= 0):
                    raise bad("a whole number >= 0 or null")
            elif f.name == "lm_from_degree":
                if v is not None and not (isinstance(v, int) and not isinstance(v, bool) and v >= 0):
                    raise bad("a whole number >= 0 or null (null: no Levenberg-Marquardt by degree)")
            elif f.name == "lm_excess_target":
                if v is not None and not (finite_number(v) and v > 0):
                    raise bad("a positive share of the noise floor or null (null: the LM at one spp)")
                v = None if v is None else float(v)
            elif f.name == "iterations_before_polish":
                if v is not None and not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
                    raise bad("a whole number >= 1 or null (null: until the loss flattens)")
            elif f.name == "polish_jacobian_spp":
                if v is not None and not (isinstance(v, int) and not isinstance(v, bool) and v >= 2):
                    raise bad("a whole number >= 2 or null (null: final_spp)")
            elif f.name == "delta_range":
                if not (isinstance(v, list | tuple) and len(v) == 2 and all(finite_number(x) and x > 0 for x in v)
                        and v[0] <= v[1]):
                    raise bad("a pair [low, high] of positive numbers")
                v = (float(v[0]), float(v[1]))
            elif isinstance(default, bool):
                if not isinstance(v, bool):
                    raise bad("true or false")
            elif isinstance(default, int):
                least = 0 if f.name in ("seed", "lm_iterations", "adam_iterations", "gn_delta_nodes", "polish_steps") else 1
                if not (isinstance(v, int) and not isinstance(v, bool)) or v < least:
                    raise bad(f"a whole number >= {least}")
            elif f.name == "polish_continue_p":
                if not (finite_number(v) and 0 < v < 1):
                    raise bad("a probability between 0 and 1")
                v = float(v)
            elif f.name == "gn_smooth_px":
                if not (finite_number(v) and v >= 0):
                    raise bad("a number of pixels >= 0 (0: no smoothing)")
                v = float(v)
            elif isinstance(default, float):
                if not (finite_number(v) and v > 0):
                    raise bad("a positive number")
                v = float(v)
            elif f.name == "engine":
                if v not in ENGINES:
                    raise bad(f"a render engine ({' or '.join(ENGINES)})")
            elif f.name == "lm_basis":
                if v not in LM_BASES:
                    raise bad(f"an LM basis ({' or '.join(LM_BASES)})")
            elif isinstance(default, str) and not isinstance(v, str):
                raise bad("a word")
            out[f.name] = v
        return cls(**out)


@dataclass
class FitResult:
    """Outcome of `fit_channel`; parameters use ForwardModel names."""

    channel: str
    model: str                       # "exp3" | "tthg" | ...
    extensions: list[str]
    parameters: dict[str, float]
    uncertainties: dict[str, float]
    fixed: dict[str, float]
    scale: float
    scale_uncertainty: float
    loss: float                      # at the reference delta, final spp
    delta_rel: float
    chi2: float
    dof: int
    reduced_chi2: float
    iterations: int
    time_s: float
    stop_reason: str
    spp_schedule: list[list[int]]    # [iteration, spp] where the spp changed
    loss_curve: list[float]          # reference-delta loss per iteration
    angles_deg: list[float]
    fitted: np.ndarray               # (N, W) rendered profiles (model units, not scaled)
    model_variance: np.ndarray       # (N, W) MC variance of `fitted`
    start: dict[str, float]
    #: the LM's stages (`estimate.polish.LMStage.to_dict`): spp, steps, losses, stop, noise_excess
    lm_stages: list[dict[str, Any]] = field(default_factory=list)
    settings: dict[str, Any] = field(default_factory=dict)
    scale_mode: str = "free"
    scale_calibration: dict[str, Any] | None = None   # ScaleCalibration.to_dict() when calibrated
    fisher_uncertainties: dict[str, float] = field(default_factory=dict)   # before the sandwich
    optimizer_spread: dict[str, float] = field(default_factory=dict)       # sd of the iterates about their mean or trend
    #: the parts of `uncertainties` (1 sigma, parameter units): the sandwich alone (before the
    #: Fisher bound's floor) and the averaged polish points' standard error
    sandwich_uncertainties: dict[str, float] = field(default_factory=dict)
    polish_se: dict[str, float] = field(default_factory=dict)
    #: the loss without its Monte Carlo variance term (estimate.loss.decorrelated_loss), final spp
    loss_unbiased: float = float("nan")
    #: covariance of the free parameters {a: {b: cov}}, its diagonal = uncertainties^2
    covariance: dict[str, dict[str, float]] = field(default_factory=dict)
    #: change of each parameter between the last `window` iterates' mean and the mean of the
    #: `window` iterates two windows earlier, or, after a Gauss-Newton polish, its last step
    #: (parameter units; added to the uncertainties)
    drift: dict[str, float] = field(default_factory=dict)
    #: parameters whose drift is significant (> DRIFT_T x its standard error; after a polish:
    #: its last step exceeds the parameter's uncertainty): the fit stopped while still
    #: moving, the result is biased towards its start
    drifting: list[str] = field(default_factory=list)
    #: per Gauss-Newton iteration: [iteration, predicted decrease of the loss, its noise part]
    gn_trace: list[list[float]] = field(default_factory=list)
    #: additive parameters (stray-light offset, slope) solved on every iteration's render
    #: (`FitSettings.profile_additive`) rather than stepped by the optimiser
    solved: list[str] = field(default_factory=list)
    #: the Gauss-Newton polish after the iterations (`gn_polish`): per step {loss, loss_new,
    #: accepted, halvings, step, step_chi2, point (when accepted)}
    polish: list[dict[str, Any]] = field(default_factory=list)
    #: wall seconds per stage: start (coarse search), iterations, polish, evaluation,
    #: uncertainties (their sum is about `time_s`)
    stage_times_s: dict[str, float] = field(default_factory=dict)

    @property
    def free(self) -> list[str]:
        return [k for k in self.parameters if k not in self.fixed]

    @property
    def lm_steps(self) -> int:
        """Accepted steps of the fixed-seed Levenberg-Marquardt (0: none ran, or it moved
        nothing, and the result is the polish's)."""
        return sum(int(g["steps"]) for g in self.lm_stages)

    @property
    def lm_losses(self) -> list[float]:
        """The LM's loss at its last stage's start, then after each accepted step ([]: no LM ran)."""
        return [float(x) for x in self.lm_stages[-1]["losses"]] if self.lm_stages else []

    @property
    def lm_spp(self) -> int:
        """The samples per pixel of the LM's last stage (0: no LM ran)."""
        return int(self.lm_stages[-1]["spp"]) if self.lm_stages else 0

    def summary(self) -> dict[str, Any]:
        """JSON-safe per-channel summary (the `--json` shape)."""
        return {"model": self.model, "sigma_t": self.parameters["sigma_t"], "albedo": self.parameters["albedo"],
                "phase": {k: v for k, v in self.parameters.items() if k.startswith("phase.")},
                "parameters": dict(self.parameters), "uncertainties": dict(self.uncertainties),
                "scale": self.scale, "loss": self.loss, "loss_unbiased": self.loss_unbiased,
                "chi2": self.chi2, "dof": self.dof,
                "reduced_chi2": self.reduced_chi2, "iterations": self.iterations, "time_s": self.time_s,
                "stop_reason": self.stop_reason, "extensions": list(self.extensions),
                "derived": self.derived(), "drifting": list(self.drifting), "solved": list(self.solved)}

    def derived(self) -> dict[str, dict[str, float | str | None]]:
        """sigma_s, sigma_a, g, sigma_s' and the transport albedo with 1-sigma uncertainties
        (`estimate.derived.derived_quantities`)."""
        from estimate.derived import derived_quantities

        return derived_quantities(self.model, self.parameters, self.covariance)


def model_phase(model: str, degree: int = 3) -> str:
    """CLI model name -> ForwardModel phase name ("exp" -> "exp<degree>")."""
    if model in ("exp", "exponential"):
        return f"exp{int(degree)}"
    if model.startswith("exp") and model[3:].isdigit():
        return model
    if model in ("tthg", "hg"):
        return model
    raise ModelParameterError(f"unknown model {model!r}; use exp, exp<M>, tthg or hg")


def lm_plan(settings: FitSettings, phase: str) -> tuple[int, int]:
    """The Levenberg-Marquardt polish a fit of `phase` ("exp<M>", "tthg", ...) gets: (steps at
    most, samples per pixel); (0, 0) for none. An explicit `lm_iterations` wins; otherwise
    exp<M> with M >= `lm_from_degree` gets `lm_degree_iterations` steps at
    `lm_degree_spp_factor` x `final_spp`."""
    if settings.lm_iterations > 0:
        return settings.lm_iterations, settings.lm_spp
    if settings.lm_from_degree is not None and phase.startswith("exp") and phase[3:].isdigit() \
            and int(phase[3:]) >= settings.lm_from_degree:
        return settings.lm_degree_iterations, settings.lm_degree_spp_factor * settings.final_spp
    return 0, 0


def forward_model(problem: Problem, phase: str, extensions: Sequence[str] = (), engine: str = "light",
                  phase_table: TabulatedPhase | None = None) -> ForwardModel:
    """The forward model of `problem`'s rig, slab and recording for a phase model name
    ("exp<M>", "tthg", "hg"; "table" with `phase_table`, a simulated truth) and extensions,
    rendering with `engine`."""
    return ForwardModel(problem.geometry, problem.beam, phase=phase, extensions=extensions,
                        profile_y_shape=problem.y_shapes(), engine=engine,
                        profile_merge_fill=problem.merge_fills(), beam_fill=problem.beam_fill,
                        phase_table=phase_table)


class _Adam:
    def __init__(self, lrs: np.ndarray, b1: float = 0.9, b2: float = 0.999, eps: float = 1e-8) -> None:
        self.lr = lrs.astype(float)
        self.b1, self.b2, self.eps = b1, b2, eps
        self.m = np.zeros_like(self.lr)
        self.v = np.zeros_like(self.lr)
        self.t = 0

    def step(self, z: np.ndarray, g: np.ndarray) -> np.ndarray:
        self.t += 1
        self.m = self.b1 * self.m + (1 - self.b1) * g
        self.v = self.b2 * self.v + (1 - self.b2) * g * g
        mh = self.m / (1 - self.b1 ** self.t)
        vh = self.v / (1 - self.b2 ** self.t)
        return z - self.lr * mh / (np.sqrt(vh) + self.eps)


def _flattened(losses: Sequence[float], window: int) -> bool:
    """True when the loss no longer decreases significantly: over the last 2 x `window`
    iterations the fitted slope is above -2 standard errors (the errors from the scatter of
    the losses about the line, i.e. the Monte Carlo noise of the loss)."""
    n = 2 * window
    if len(losses) < n:
        return False
    y = np.asarray(losses[-n:], dtype=float)
    x = np.arange(n, dtype=float)
    slope, icpt = np.polyfit(x, y, 1)
    resid = y - (slope * x + icpt)
    se = float(np.sqrt(np.sum(resid ** 2) / (n - 2) / np.sum((x - x.mean()) ** 2)))
    return slope > -2.0 * se


#: The stages of `fit_channel`, in order (`FitResult.stage_times_s`, `on_stage`).
STAGES = ("start", "iterations", "polish", "evaluation", "uncertainties", "done")


def fit_channel(problem: Problem, model: str = "exp3", *, extensions: Sequence[str] = (),
                start: Mapping[str, float] | None = None, fixed: Mapping[str, float] | None = None,
                settings: FitSettings | None = None, forward: ForwardModel | None = None,
                progress: Callable[[int, float, int], None] | None = None,
                scale_calibration: ScaleCalibration | None = None,
                on_stage: Callable[[str], None] | None = None) -> FitResult:
    """Fit one channel.

    Args:
        problem: from `estimate.problem.load_problem`.
        model: phase model, "exp<M>" (e.g. "exp3"), "tthg" or "hg" ("exp" = exp3).
        extensions: ForwardModel extensions to include (their parameters are fitted
            unless fixed).
        start: starting values (any subset); with both sigma_t and albedo given the coarse
            search is skipped.
        fixed: parameters held at the given values (not fitted, no uncertainty).
        settings: optimiser settings.
        forward: a ready ForwardModel for this problem (else built).
        progress: called after each iteration as progress(iteration (from 1), reference loss, spp).
        on_stage: called with each stage's name as it begins ("start", "iterations",
            "polish", "evaluation", "uncertainties"), and with "done" at the end.
        scale_calibration: the measured scale for `settings.scale == "calibrated"` (else
            `estimate.loss.calibrated_scale` of the problem's session).

    Raises:
        DataError: calibrated scale without a beam power in the session's calibration.
    """
    st = settings or FitSettings.for_variant()
    t0 = time.monotonic()
    # The budget covers the iterations and both polishes; the final evaluation and the
    # uncertainties always run (up to session 79 it stopped the iterations alone, and an
    # exp7 fit's LM could run 60 steps past it).
    deadline = Deadline.after(st.time_limit_s, t0)
    stage_times: dict[str, float] = {}
    t_stage = t0

    def stage_done(name: str) -> None:
        nonlocal t_stage
        now = time.monotonic()
        stage_times[name] = stage_times.get(name, 0.0) + now - t_stage
        t_stage = now
        if on_stage:
            on_stage(STAGES[STAGES.index(name) + 1])
    if on_stage:
        on_stage(STAGES[0])
    phase = model_phase(model)
    check_engine(st.engine)   # a hand-edited results.yaml's too, before any work
    fm = forward or forward_model(problem, phase, extensions, st.engine)
    fixed = dict(fixed or {})
    fm.validate(fixed)
    if st.scale not in ("free", "calibrated"):
        raise ModelParameterError(f"unknown scale mode {st.scale!r}; use free or calibrated")
    cal: ScaleCalibration | None = None
    if st.scale == "calibrated":
        cal = scale_calibration or calibrated_scale(problem.session_path, problem.channel, problem.beam.power())
    fixed_scale = cal.scale if cal is not None else None
    d_ref = reference_delta(st.delta_range)
    base = fm.default_parameters()
    base.update(fixed)
    if start is not None and "sigma_t" in start and "albedo" in start:
        init = dict(base)
        init.update(start)
        init.update(fixed)
    else:
        b = dict(base)
        b.update(start or {})
        init, _ = coarse_start(fm, problem, b, spp=st.start_spp, seed=st.seed + 99_991, delta_rel=d_ref,
                               fixed=fixed, scale=fixed_scale)
    init = fm.validate(init)
    stage_done("start")
    names = [n for n in fm.parameter_names if n not in fixed]
    peak = None
    radiance_valued = [n for n in names if fm.specs[n].unit.startswith("radiance")]
    if radiance_valued:
        # Radiance-valued extension parameters (stray-light offset and slope, full-well
        # radiance) live in the render's units, whose scale depends on pixel size and beam:
        # their steps are taken relative to the render's peak, and a level parameter left at
        # its placeholder (the full well: 1.0) starts at the peak (the brightest pixel fills
        # the well), where the compression acts on the spot and not on the whole profile.
        peak = float(np.nanmax(fm.render_profiles(init, problem.angles_deg, spp=32, seed=st.seed + 77_777)))
        for n in radiance_valued:
            spec = fm.specs[n]
            if spec.neutral != 0.0 and n not in (start or {}) and init[n] == spec.neutral and peak > 0:
                init[n] = peak
    half_width_mm = 0.5 * problem.measured.shape[-1] * problem.geometry.pixel_mm
    # Additive parameters (a stray-light offset and slope) are solved exactly on every
    # iteration's render (`solve_additive`, like a free scale) instead of being stepped: as
    # optimiser variables they are nearly degenerate with the albedo and b2 in the tails, so
    # the Gauss-Newton matrix's weak direction turned each re-estimate of its noisy
    # Jacobian into a jump (bench stray_light-2, started at the truth: offset +-30 %, slope
    # x2 every 10 iterations, ending at offset -10 %, slope +49 %).
    solved = [n for n in fm.additive_parameters() if n in names] \
        if st.profile_additive and st.decorrelated else []
    stepped = [n for n in names if n not in solved]
    # The columns do not depend on the parameters (nothing follows an additive effect).
    solved_cols = fm.additive_columns(init, len(problem.angles_deg), solved) if solved else {}
    sol = {n: float(init[n]) for n in solved}
    tr: list[Transform] = [transform_for(n, fm.specs[n], peak, half_width_mm) for n in stepped]
    z = np.array([t.to_z(init[n]) for n, t in zip(stepped, tr)])
    adam = _Adam(np.array([t.lr for t in tr]) * st.lr_scale)
    rng = np.random.default_rng(st.seed)

    def params_of(zv: np.ndarray) -> dict[str, float]:
        p = dict(init)
        p.update(sol)
        p.update({n: t.to_x(float(zz)) for n, t, zz in zip(stepped, tr, zv)})
        return p

    def x_row(zv: np.ndarray) -> list[float]:
        """One iterate in parameter units, in `names` order."""
        p = params_of(zv)
        return [float(p[n]) for n in names]

    spp = int(st.spp_start)
    schedule = [[0, spp]]
    curve: list[float] = []
    history: list[np.ndarray] = []
    x_history: list[list[float]] = []
    since_change = 0
    stop = "max_iterations"
    scale = fixed_scale
    it = 0
    lo, hi = math.log(st.delta_range[0]), math.log(st.delta_range[1])
    if st.optimizer not in ("adam", "adam+gn"):
        raise ModelParameterError(f"unknown optimizer {st.optimizer!r}; use adam or adam+gn")
    mode = "adam"
    gn_jac: dict[str, np.ndarray] | None = None
    gn_jac_it = 0
    g_avg: np.ndarray | None = None
    gn_grads: list[np.ndarray] = []
    gn_trace: list[list[float]] = []
    # Columns of image-space parameters are not smoothed: exact ones carry no Monte Carlo noise
    # to smooth away, and a blur's column changes sign within a few pixels (rendered, with a
    # deblurred beam map: `ForwardModel.deblurs_beam`, common random numbers keep it sharp).
    exact_columns = {n for n in stepped if fm.acts_in_image(n)}
    gn_nodes = [math.exp(lo + (k + 0.5) / st.gn_delta_nodes * (hi - lo)) for k in range(st.gn_delta_nodes)]
    hand_over = st.iterations_before_polish if st.polish_steps > 0 and stepped else None
    for it in range(1, st.max_iterations + 1):
        p = params_of(z)
        delta_rel = math.exp(rng.uniform(lo, hi))
        seed_a = st.seed * 100_003 + 2 * it
        half = max(1, spp // 2)
        if st.decorrelated:
            # Two independent half-spp renders A, B; loss mean(rA * rB) with r = log(m + delta)
            # - log(I + delta): its expectation has no Monte Carlo variance term, which would
            # otherwise reward parameters whose renders are less noisy (e.g. low albedo).
            # Each render keeps its paths for the gradient's replay below (`linearize`): the
            # cotangent of A needs B's residuals, so neither is known before both are rendered.
            lin_a = fm.linearize(p, problem.angles_deg, spp=half, seed=seed_a)
            lin_b = fm.linearize(p, problem.angles_deg, spp=half, seed=seed_a + 1)
            pa, pb_ = lin_a.profiles, lin_b.profiles
            if solved:
                shift = solve_additive(fm, problem, p, solved, 0.5 * (pa + pb_), delta_rel, fixed_scale,
                                       scale_guess=scale, columns=solved_cols)
                pa, pb_ = pa + shift, pb_ + shift
                # (The linearizations keep the previous additive values: the last image-space
                # effect adds them, so the pull-back through the chain does not depend on them.)
                sol.update({n: p[n] for n in solved})
            mean = 0.5 * (pa + pb_)
            if fixed_scale is None:
                scale = profile_scale(problem.measured, mean, problem.valid, delta_rel, guess=scale)
            assert scale is not None  # the calibration's, or profiled just now
            curve_loss = log_loss(problem.measured, mean, problem.valid, scale, d_ref)[0]
            m = problem.measured / scale
            mm, dl = log_measured(problem.measured, problem.valid, scale, delta_rel)
            ra, rb = (log_residual(mm, q, problem.valid, dl) for q in (pa, pb_))
            n_v = max(1, int(problem.valid.sum()))
            cot_a = np.where(problem.valid & (pa >= 0), -rb / (np.clip(pa, 0, None) + dl) / n_v, 0.0)
            cot_b = np.where(problem.valid & (pb_ >= 0), -ra / (np.clip(pb_, 0, None) + dl) / n_v, 0.0)
            ga = lin_a.vjp(cot_a)
            gb = lin_b.vjp(cot_b)
            grads = {k: ga.get(k, 0.0) + gb.get(k, 0.0) for k in set(ga) | set(gb)}
        else:
            ref: dict[str, float] = {}

            def loss_fn(prof: np.ndarray, delta_rel: float = delta_rel, ref: dict[str, float] = ref
                        ) -> tuple[float, np.ndarray]:
                nonlocal scale
                s = fixed_scale if fixed_scale is not None else profile_scale(
                    problem.measured, prof, problem.valid, delta_rel, guess=scale)
                scale = s
                ref["loss"] = log_loss(problem.measured, prof, problem.valid, s, d_ref)[0]
                return log_loss(problem.measured, prof, problem.valid, s, delta_rel)

            _, _, grads = fm.value_and_grad(p, problem.angles_deg, loss_fn, spp=spp, seed=seed_a)
            curve_loss = ref["loss"]
        g = np.array([grads.get(n, 0.0) * t.dx_dz(float(zz)) for n, t, zz in zip(stepped, tr, z)])
        g = np.where(np.isfinite(g), g, 0.0)
        if mode == "gn":
            if gn_jac is None or it - gn_jac_it >= st.gn_jacobian_every:
                gn_jac = gn_jacobian(fm, problem, p, stepped, spp=st.gn_jacobian_spp,
                                     seed=st.seed * 100_003 + 70_000 + it)
                gn_jac_it = it
            # Gradients are averaged over iterations (momentum): a single one's Monte Carlo
            # noise is 2-4x its mean per component at 512 spp (albedo worst), and
            # H^-1 amplifies it along the weakly determined valley direction.
            g_avg = g if g_avg is None else st.gn_momentum * g_avg + (1.0 - st.gn_momentum) * g
            # The matrix of the delta-averaged loss, whose gradient g_avg estimates: a
            # midpoint rule over log delta at `gn_delta_nodes` nodes (0: this iteration's delta).
            m_max = dl / delta_rel
            gn_dl = [max(q * m_max, 1e-30) for q in gn_nodes] if gn_nodes else dl
            h_inv = gn_inverse(gn_jac, stepped, tr, z, problem, mean, gn_dl, m, fixed_scale is None,
                               profiled_columns=list(solved_cols.values()), smooth_px=st.gn_smooth_px,
                               exact=exact_columns)
            gn_grads.append(g)
            recent = gn_grads[-2 * st.window:]
            gn_trace.append([it, *predicted_decrease(h_inv, g_avg, recent, st.gn_momentum)])
            dz = -st.gn_step * (snr_step(h_inv, g_avg, recent, st.gn_momentum) if st.gn_snr else h_inv @ g_avg)
            cap = 5.0 * adam.lr / st.lr_scale
            z = z + np.clip(dz, -cap, cap)
        else:
            z = adam.step(z, g)
            if st.optimizer == "adam+gn" and st.decorrelated and it >= st.adam_iterations:
                mode = "gn"
        z = np.array([t.clamp_z(float(zz)) for t, zz in zip(tr, z)])
        curve.append(curve_loss)
        history.append(z.copy())
        x_history.append(x_row(z))
        since_change += 1
        if progress:
            progress(it, curve_loss, spp)
        if deadline.passed("iterations"):
            stop = "time_limit"
            break
        if hand_over is not None and it >= hand_over:
            stop = f"handed to the polish after {it} iterations"
            break
        if since_change >= 3 * st.window and _flattened(curve[-since_change:], st.window):
            if spp >= st.spp_max:
                stop = "converged"
                break
            spp = min(st.spp_max, spp * 2)
            adam.lr = adam.lr * st.lr_decay
            schedule.append([it, spp])
            since_change = 0
    n_avg = min(len(history), st.window * (2 if mode == "gn" else 1))
    drift, drifting = iterate_drift(x_history, names, st.window)
    # Iterates that still drift are summarised by the end of their linear trend: their mean
    # lags the last iterate by half the window's drift (the benchmark, seed 0: mean of the
    # last 16 iterates sigma_t 2.172, last iterate 2.126, trend end 2.115; truth 2.0).
    trend = bool(drifting) and n_avg >= 4
    z_final = window_estimate(history[-n_avg:], trend) if history else z
    if x_history:
        x_end = window_estimate(x_history[-n_avg:], trend)
        sol.update({n: float(x_end[names.index(n)]) for n in solved})
    final = params_of(z_final)
    stage_done("iterations")
    polish: list[dict[str, Any]] = []
    polish_jacobians: list[list[dict[str, np.ndarray]]] = []
    if st.polish_steps > 0 and stepped:
        caps = st.polish_cap_lr * adam.lr / st.lr_scale     # 3x the iterations' step cap
        final, polish, _ = gn_polish(fm, problem, final, stepped, tr, steps=st.polish_steps, spp=st.final_spp,
                                     jacobian_spp=st.polish_jacobian_spp or st.final_spp,
                                     seed=st.seed * 100_003 + 30_000,
                                     delta_nodes=gn_nodes or [d_ref], reference_delta_rel=d_ref,
                                     fixed_scale=fixed_scale, solved=solved, solved_columns=solved_cols,
                                     smooth_px=st.gn_smooth_px, exact=exact_columns, caps=caps, scale_guess=scale,
                                     jacobian_every=st.polish_jacobian_every, cross=st.polish_cross,
                                     max_steps=2 * st.polish_steps if st.polish_max_steps is None
                                     else st.polish_max_steps,
                                     chi2_continue=float(chi2_dist.isf(st.polish_continue_p, len(stepped))),
                                     keep_last=averaged_point_count(st.polish_steps, st.polish_average_from),
                                     settled_spp_factor=st.polish_settled_spp, one_sided=st.polish_one_sided,
                                     jacobians_out=polish_jacobians, damped=st.polish_damped,
                                     deadline=deadline)
    # After the polish, the drift is its last step: what the fit still moved by at the end
    # (and `drifting` those parameters whose last step exceeds their uncertainty); when its
    # later points are averaged, their mean step and the mean's standard error instead.
    accepted = [e for e in polish if e["accepted"]]
    polished = bool(accepted) and st.uncertainties
    polish_se: dict[str, float] = {}
    polish_sd: dict[str, float] = {}
    # the polish's last Jacobians that the uncertainties reuse: as many steps' as points averaged
    n_polish_avg = 1 if polish_jacobians else 0
    if accepted:
        drift = {n: float(accepted[-1]["step"][n]) for n in names if n in accepted[-1]["step"]}
        first = first_averaged_point(len(accepted), st.polish_steps, st.polish_average_from)
        averaged = polish_average(accepted, names, tr, first)
        if averaged is not None:
            mean_point, drift, polish_sd, polish_se = averaged
            final = {**final, **mean_point}
            n_polish_avg = max(1, len(accepted) - first + 1)
    moving: list[str] = []
    lm_iterations, lm_spp = lm_plan(st, phase)
    lm_steps: list[dict[str, float]] = []
    lm_stages: list[LMStage] = []
    if lm_iterations > 0 and stepped:
        final, _ = lm_polish(fm, problem, final, stepped, tr, spp=lm_spp,
                             seed=st.seed * 100_003 + 40_000, delta_rel=d_ref, iterations=lm_iterations,
                             fixed_scale=fixed_scale, steps_out=lm_steps, deadline=deadline,
                             decorrelated=st.lm_decorrelated, basis=st.lm_basis,
                             excess_target=st.lm_excess_target,
                             spp_max=st.lm_spp_max_factor * st.final_spp, stages_out=lm_stages)
        lm_spp = lm_stages[-1].spp if lm_stages else lm_spp
    if lm_steps:
        # The result is the LM's optimum, not the polish's: the polish points' scatter and
        # their Jacobians describe another point (on the paper simulation's d 0.5 um case exp7
        # moved sigma_t by 2 % and b3 from 5 to 14), so the uncertainties below take fresh
        # Jacobians at the final point, and the LM's last step is the drift.
        polish_se, polish_sd, n_polish_avg = {}, {}, 0
        drift = dict(lm_steps[-1])
        polished = st.uncertainties
    cut = [{"polish": "the Gauss-Newton polish", "lm": "the Levenberg-Marquardt steps"}[h]
           for h in deadline.hit if h != "iterations"]
    if cut:
        stop = f"{stop}; the time limit cut {' and '.join(cut)}"
    stage_done("polish")
    ev = evaluate(fm, problem, final, spp=st.final_spp, seed=st.seed * 100_003 + 50_000, delta_rel=d_ref,
                  fixed_scale=fixed_scale, additive=solved)
    final = ev["parameters"]
    stage_done("evaluation")
    n_valid = int(problem.valid.sum())
    dof = max(1, n_valid - len(names) - (1 if fixed_scale is None else 0))
    red = ev["chi2"] / dof
    unc: dict[str, float] = {n: float("nan") for n in names}
    covariance: dict[str, dict[str, float]] = {}
    fisher: dict[str, float] = {}
    sandwich: dict[str, float] = {}
    spread: dict[str, float] = {}
    s_unc = float("nan")
    if st.uncertainties:
        # The sandwich's curvature from the cross products of Jacobians with independent
        # render noise (see sandwich_uncertainties): one at the final point, with the secant
        # steps of the polish's (at the default steps, the finite differences of the phase
        # coefficients are 10x noisier), and the polish's last ones, as many steps' as points
        # were averaged (near the final point, within its noise; their solved additive
        # columns, which carry no render noise, from the final point's), or a second one.
        # Since session 28 the polish's Jacobians alone when it averaged two points or more
        # (four or more Jacobians, each within the points' noise of the final point, the
        # solved additive columns exact): the central one at the final point cost ~7 s of
        # the benchmark's 2 min (`uncertainty_final_jacobian` renders it still).
        last = [j for js in polish_jacobians[-n_polish_avg:] for j in js] if n_polish_avg else []
        if len(last) >= 4 and not st.uncertainty_final_jacobian:
            jac, *more = [{**solved_cols, **j} for j in last]
        else:
            jac = gn_jacobian(fm, problem, final, names, spp=st.uncertainty_spp, seed=st.seed * 100_003 + 60_000)
            more = [{**jac, **j} for j in last]
        if not more:
            more = [gn_jacobian(fm, problem, final, names, spp=st.uncertainty_spp, seed=st.seed * 100_003 + 65_000)]
        fisher, _ = fisher_uncertainties(fm, problem, final, names, ev["scale"], ev["model_variance"],
                                         ev["profiles"], spp=st.uncertainty_spp, seed=0, inflate=red,
                                         fit_scale=fixed_scale is None,
                                         jac={n: np.mean([j[n] for j in (jac, *more)], axis=0) for n in names})
        sandwich_cov: dict[str, dict[str, float]] = {}
        step_corr: dict[str, dict[str, float]] = {}
        # The result averaged polish points whose scatter (`polish_se`) is their render noise:
        # the meat then holds the data's noise alone, or that noise would be counted twice.
        data_meat = st.uncertainty_data_meat and bool(polish_se)
        unc, s_unc, _ = sandwich_uncertainties(problem, final, names, ev["scale"], ev["profiles"],
                                               ev["model_variance"], jac, delta_rel=d_ref,
                                               fit_scale=fixed_scale is None,
                                               render_variance_factor=2.0 * st.final_spp / max(1, lm_spp if lm_steps else st.lm_spp),
                                               covariance_out=sandwich_cov, jac_more=more, data_meat=data_meat,
                                               meat_cross=st.uncertainty_meat_cross,
                                               render_correlation_out=(step_corr if st.uncertainty_polish_correlation
                                                                       else None))
        sandwich = dict(unc)
        # never below the ideal linear-chi^2 bound
        unc = {k: max(v, fisher.get(k, 0.0)) for k, v in unc.items()}
        # The stochastic optimiser's own spread: the standard deviation of the averaged
        # iterates, added in quadrature. The curvature-based intervals describe the
        # minimum of the loss; along the sigma_t / phase valley the iterates wander by more
        # than that (synthetic benchmark: sandwich 0.006 /mm, error 0.057 /mm).
        # Once a polish step was taken the result is the polish's, not the iterations', and
        # the polish points' own scatter stands in for it (`polish_se`, `drift`): the
        # iterates' spread is left out. Handed over after 10 Adam iterations (session 28),
        # the iterates still walk from the coarse start, and their scatter about their
        # trend (sigma_t 0.16-0.26 /mm on the benchmark, truth 2.0) swamped the fit's own.
        xs = window_scatter(x_history[-n_avg:], trend) if not (accepted or lm_steps) \
            else np.zeros((0, len(names)))
        it_cov = np.cov(xs, rowvar=False, ddof=2 if trend else 1).reshape(len(names), len(names)) \
            if len(xs) > 2 else np.zeros((len(names), len(names)))
        for i, n in enumerate(names):
            spread[n] = float(math.sqrt(max(it_cov[i, i], 0.0)))
        unc, moving = combined_uncertainties(unc, spread, polish_se, drift, polish_sd, polished=polished)
        if polished:
            drifting = moving
        covariance = combined_covariance(names, unc, sandwich_cov, it_cov,
                                         *((polish_se, step_corr) if st.uncertainty_polish_correlation else ()))
        stage_done("uncertainties")
    elif on_stage:
        on_stage("done")
    return FitResult(
        channel=problem.channel, model=phase, extensions=list(fm.extensions), parameters=final,
        uncertainties=unc, fixed=fixed, scale=ev["scale"], scale_uncertainty=s_unc, loss=ev["loss"],
        loss_unbiased=ev["loss_unbiased"],
        delta_rel=d_ref, chi2=ev["chi2"], dof=dof, reduced_chi2=red, iterations=it,
        time_s=time.monotonic() - t0, stop_reason=stop, spp_schedule=schedule, loss_curve=curve,
        angles_deg=[float(a) for a in problem.angles_deg], fitted=ev["profiles"],
        lm_stages=[g.to_dict() for g in lm_stages],
        model_variance=ev["model_variance"], start=dict(init), settings=st.to_dict(), scale_mode=st.scale,
        scale_calibration=cal.to_dict() if cal is not None else None, fisher_uncertainties=fisher,
        optimizer_spread=spread, sandwich_uncertainties=sandwich,
        polish_se={k: float(v) for k, v in polish_se.items() if k in names}, gn_trace=gn_trace,
        covariance=covariance, drift=drift, drifting=drifting,
        solved=list(solved), polish=polish, stage_times_s={k: round(v, 2) for k, v in stage_times.items()})


def loss_at(problem: Problem, model: str, params: Mapping[str, float], *, extensions: Sequence[str] = (),
            spp: int = 1024, seed: int = 12_345, delta_range: tuple[float, float] = DEFAULT_DELTA_RANGE,
            forward: ForwardModel | None = None, fixed_scale: float | None = None,
            engine: str | None = None) -> dict[str, Any]:
    """Loss / chi^2 of given parameters (e.g. the true ones: the noise floor), scale profiled
    unless `fixed_scale`. Rendered with `engine` (default: the fit's, `FitSettings.engine`),
    so that a fit's loss and the floor carry the same engine's render noise (up to session
    61 the floor took the camera engine's while the fits rendered with the light engine)."""
    fm = forward or forward_model(problem, model_phase(model), extensions, engine or FitSettings().engine)
    return evaluate(fm, problem, params, spp=spp, seed=seed, delta_rel=reference_delta(delta_range),
                    fixed_scale=fixed_scale)
