"""A model against a recording: the diagnosis' evaluations and refits (`estimate.diagnose`).

`evaluate` renders a model at several seeds and returns its normalised residuals, with the
model's own Monte-Carlo variance (pooled over `VARIANCE_POOL_PX` neighbours) in the noise;
`render_stack` the renders themselves. `refit` is a Levenberg-Marquardt loop on the forward
model's `jacobian` (finite differences with common random numbers and the large secant
steps of `estimate.gauss_newton.secant_steps`, exact for image-space parameters), with the
scale (measured = scale * rendered) as a free linear parameter; its covariance takes its
curvature from the bounded cross product of two Jacobians with independent render noise
(`cross_covariance`), and with `decorrelate` it ends with one Gauss-Newton step on the
decorrelated chi^2 of two render seeds (`decorrelated_step`), which removes the fixed-seed
optimum's render-noise bias. With `objective="decorrelated"` it iterates those steps from
the start instead (`DECORRELATED`): half the samples of a fixed-seed refit an iteration
buy the same freedom from that bias.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from estimate.errors import ModelParameterError
from estimate.gauss_newton import bounded_cross, secant_steps
from estimate.model_protocols import ProfileModel, ProfileRecording
from estimate.residuals import (
    FitResiduals,
    fit_significance,
    noise_floor,
    normalised_residuals,
    render_noise_modes,
)
from estimate.uncertainties import UNCERTAINTY_CROSS_FLOOR

__all__ = ["DECORRELATED", "DEFAULT_REPEATS", "DEFAULT_SEED", "FIXED_SEED", "MAX_GLARE_FRACTION", "OBJECTIVES",
           "Evaluation", "RefitResult", "best_scale",
           "cross_covariance", "decorrelated_step", "evaluate", "independent_residuals", "parameter_bounds",
           "recorded_noise_share", "recording_variance", "refit", "render_stack", "smoothed_variance"]


_log = logging.getLogger(__name__)


#: The refit's second Jacobian, for its uncertainties' cross-product curvature, is rendered
#: at the refit's seed plus this (render noise independent of the refit's own).
UNCERTAINTY_SEED_OFFSET = 7919


#: A refit's objectives (`refit(objective=...)`). FIXED_SEED: Levenberg-Marquardt on the
#: chi^2 of one render seed, whose minimum leans towards quieter renders by a bias that goes
#: as 1 / spp (on the 256-px window it wants 2048 spp; session 41). DECORRELATED:
#: Gauss-Newton steps on sum r_A r_B of two seeds (`decorrelated_chi2`), which has no such
#: term, so 512 spp serve there (session 44's experiment, `benchmarks/exp_decorrelated_refit.py`).
FIXED_SEED = "fixed-seed"
DECORRELATED = "decorrelated"
OBJECTIVES = (FIXED_SEED, DECORRELATED)


#: A fixed-seed refit (Levenberg-Marquardt) that is still descending when its `iterations`
#: are spent goes on, up to LM_EXTENSION x `iterations` in all, while its last two
#: iterations lowered the chi^2 by more than LM_STILL_DESCENDING of it. Refits from a base fit
#: that made up for a left-out effect walk a long valley: on the light bench's glass-like
#: boundary session (base sigma_t 4.0, b1 14; truth 2.0, 1.8) the boundary's refit was still
#: gaining 10-20 % an iteration at its eighth (n 1.26 -> 1.40, sigma_t 3.4 -> 2.9), and the
#: joint refit after it 13 %, so the round judged the model where the refit had stopped, not
#: at its optimum (docs/diagnosis-log.md, session 69). Near an optimum the gains are well
#: under 1 % an iteration and nothing changes.
LM_EXTENSION = 2
LM_STILL_DESCENDING = 0.05

#: In those further iterations, a step that lowered the chi^2 by more than
#: LM_STILL_DESCENDING is tried again at 2x, then 4x, its length (at most LM_EXPANSION_MAX x),
#: and the longest that still lowers it is kept: one render a try, where an iteration's
#: Jacobian is two a free parameter. On that boundary session every step was accepted at the
#: first try with the damping at its floor and gained 10-20 %: full Gauss-Newton steps that
#: fall short, as when the secant Jacobian over its wide steps is steeper than the render's
#: mean trend along a curved valley. Not in the first `iterations`: there a longer first step
#: sent a control and its candidate's refit into different basins on a test recording whose
#: stray light the material can partly take up (sigma_t 2.0 -> 0.67 and 1.77), and the paired
#: gain between them compared two valleys.
LM_EXPANSION_MAX = 4.0

#: A fixed-seed refit is done when its next trial step's predicted decrease of the chi^2 (the
#: linearised model's at this damping, -(2 g.d + d.H.d)) is below this: that trial is not
#: rendered, nor the more damped ones after it, whose predicted gains are smaller still. The
#: chi^2 is in units of the noise (each pixel divided by f^2 (var + render var)), and what the
#: diagnosis decides from refits is a difference of chi^2 against bars of 1 or more (the BIC
#: bar 10, a magnitude 1 sigma from absent by its likelihood ratio). Before, a refit went on
#: while a step gained 1e-4 of its chi^2 and tried eight ever more damped steps before giving
#: up: on the light bench's boundary + halo pair the second round's control crawled
#: 792.7 -> 792.1 over four more iterations (lambda 13 -> 6e3, each a Jacobian and rejected
#: trials) and the halo's refit ended on an iteration of eight rejected trials, about 40 s of
#: a 349-s screening and confirmation (session 73). Not the gain of the step just taken: with
#: a secant Jacobian one iteration can gain little after rejected trials and the next, on a
#: new Jacobian, much (a halo refitted at 64 spp in the tests: 0.4, then 20).
LM_NEGLIGIBLE_GAIN = 0.5

#: A decorrelated refit stops when a step lowers its loss by less than this fraction of it.
#: On the synthetic suite's 256-px window (loss about 1270 on 1900 pixels) that is about 1.3:
#: the experiment's refits, whose weights moved with the scale each iteration, bounced within
#: +-10 for their last 3-4 iterations.
DECORRELATED_RTOL = 1e-3


#: A decorrelated refit refuses points whose renders are more than this many times as noisy
#: (`render_noise_ratio`, relative to the data's noise) as at its start. The decorrelated
#: chi^2 has no render-variance term in its expectation, but its spread grows with the render
#: noise, and a minimiser over parameters is drawn to where that spread lets the loss reach
#: lowest (the winner's curse). With the scale profiled the loss is not even bounded below:
#: where the two seeds' renders are sparse and hardly overlap, sum f_A f_B -> 0 and the
#: scale and -loss grow without end. A test recording with a concealed stray light 0.01,
#: its base model refitted at 128 spp on a 32-px window, went in four steps to sigma_t 0.01
#: (an almost transparent slab, a few paths a pixel), scale x 100 and loss -85 (from 1634),
#: where the fixed-seed refit stopped at sigma_t 0.88 with chi^2 928. Four times the
#: variance is twice the standard deviation.
DECORRELATED_MAX_NOISE_GROWTH = 4.0


#: Evaluation seeds and repeats of a diagnosis (`rig diagnose`): every model, the final fit
#: included, is rendered at seeds DEFAULT_SEED + 7 k, k < DEFAULT_REPEATS.
DEFAULT_SEED = 1000


DEFAULT_REPEATS = 6


#: Pixels pooled in the estimate of the model's Monte-Carlo variance.
VARIANCE_POOL_PX = 15


@dataclass
class Evaluation:
    """A model evaluated against the data: mean render of `repeats` seeds and its residuals."""

    parameters: dict[str, float]
    extensions: list[str]
    scale: float
    model: np.ndarray
    model_variance: np.ndarray
    residuals: FitResiduals
    n_params: int


def recording_variance(problem: ProfileRecording) -> np.ndarray:
    var = np.asarray(problem.variance, dtype=np.float64).copy()
    valid = getattr(problem, "valid", None)
    if valid is not None:
        var = np.where(np.asarray(valid, bool), var, np.inf)
    return np.where(np.isfinite(var) & (var > 0), var, np.inf)


def best_scale(measured: np.ndarray, var: np.ndarray, f: np.ndarray,
               model_variance: np.ndarray | None = None, *, passes: int = 3) -> float:
    """Weighted least-squares scale s of measured ~ s f, weights 1 / var.

    With `model_variance` (the render f's own Monte-Carlo variance, unit-power units) the
    weights are 1 / (var + s^2 model_variance), re-weighted `passes` times from the
    var-only scale. Where the render noise dominates, the var-only weights trust the
    render's pixels as if exact: on the clean demo session (model 6 x 256 spp, the data's
    HDR variance only read noise in the tails) they put the scale 7-8 % below the
    calibrated one, and the peak then stood 5 % above the scaled model at every angle.
    """
    def solve(v: np.ndarray) -> float:
        w = 1.0 / v
        den = float(np.sum(w * f * f))
        return float(np.sum(w * measured * f) / den) if den > 0 else 1.0

    s = solve(var)
    if model_variance is not None:
        for _ in range(passes):
            s = solve(var + s * s * model_variance)
    return s


def smoothed_variance(renders: np.ndarray) -> np.ndarray:
    """Per-pixel Monte-Carlo variance of one render from a few seeds, pooled over neighbours.

    A variance from a handful of seeds is itself so noisy that dividing by it turns the
    normalised residuals into Student-t variables (variance 3 for 4 seeds). The path
    tracer's variance per unit of signal changes slowly along the profile (it follows
    the signal through the sharp spot), so the ratio variance / mean is pooled over
    `VARIANCE_POOL_PX` pixels and multiplied back by the mean.
    """
    v = renders.var(axis=0, ddof=1)
    m = np.abs(renders.mean(axis=0))
    floor = 1e-6 * max(float(m.max()), 1e-300)
    ratio = v / np.maximum(m, floor)
    pooled = ndimage.uniform_filter1d(ratio, VARIANCE_POOL_PX, axis=-1, mode="nearest")
    return pooled * np.maximum(m, floor)


def evaluate(model: ProfileModel, params: Mapping[str, float], problem: ProfileRecording, n_params: int, *,
             spp: int = 256, seed: int = DEFAULT_SEED, repeats: int = 4, angle_idx: Sequence[int] | None = None,
             scale: float | None = None, noise_variance: np.ndarray | None = None,
             renders: np.ndarray | None = None) -> Evaluation:
    """Render `repeats` seeds, average, and test the fit (scale refitted unless given).

    `noise_variance` (per pixel of the whole problem, e-^2/s^2): the data's noise variance
    including its noise floor, which replaces var_HDR and the estimated floor, so that
    models are compared in one noise metric; the model's own Monte-Carlo variance (which
    differs between models: a blur averages it over neighbouring pixels) is added to it.
    None: the usual residuals, the noise floor estimated from them.
    `renders`: the (repeats, N, W) stack these arguments would render (`render_stack`),
    when the caller already has it.
    """
    idx = list(range(len(problem.angles_deg))) if angle_idx is None else list(angle_idx)
    if renders is None:
        renders = render_stack(model, params, problem, spp=spp, seed=seed, repeats=repeats, angle_idx=idx)
    mean = renders.mean(axis=0)
    mvar = smoothed_variance(renders) / repeats if repeats > 1 else np.zeros_like(mean)
    meas = np.asarray(problem.measured, dtype=np.float64)[idx]
    var = recording_variance(problem)[idx]
    # The data's noise: the HDR variance with the floor estimated from the residuals, or the
    # given one (the floor included, held at 1).
    nv = var if noise_variance is None else np.asarray(noise_variance, dtype=np.float64)[idx]
    s = best_scale(meas, nv, mean, mvar) if scale is None else float(scale)
    r = normalised_residuals(meas, nv, mean, s, mvar)
    r = np.where(np.isfinite(nv), r, np.nan)
    # The smooth test's null holds the mean render's correlated noise (the light engine's:
    # one path adds to several columns), estimated from the same renders.
    modes = render_noise_modes(renders, s, np.sqrt(nv + s ** 2 * mvar), repeats,
                               recorded_noise_share(model, problem, spp))
    res = fit_significance(r, n_params, noise_modes=modes,
                           noise_scale=None if noise_variance is None else np.ones(len(idx)))
    return Evaluation(dict(model.validate(params)), list(model.extensions), s, mean, mvar, res, n_params)


def independent_residuals(problem: ProfileRecording, ev: Evaluation, model: ProfileModel, *, spp: int, repeats: int,
                          seed: int, renders: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The residuals of `ev` weighed by a Monte-Carlo variance independent of its mean render.

    `evaluate` divides each pixel by the variance of the very renders whose mean it
    subtracts. Path-tracer noise is skewed (most pixels a little low, a few fireflies far
    high), and a firefly in the mean both pulls its residual negative and inflates its own
    variance, so that residual is shrunk; a pixel where the mean is a little low keeps a
    small variance and its positive residual at full weight. The normalised residuals of a
    correct model then lean positive wherever the render noise dominates (the tails), a
    smooth mismatch to the smooth-structure test, and one along the lens blur's and the
    halo's signatures to the score tests. On the clean demo session (channel g, 1024 spp
    frozen into the recording, 6 x 256 spp in the model) the screening so weighed found
    the lens blur's score 43 on 2 dof and the smooth test beyond the fit p = 6e-4; weighed
    by 6 other renders, the largest score is 3.5 on 1 dof and p = 0.74.

    `model` and `ev` must be the same model at the same parameters, `ev` the mean of
    `repeats` renders at `spp` (as `evaluate` makes it). Renders `repeats` more at seeds
    seed + 7 k (`renders` more where given and larger: a better estimate of the variance
    and of the modes, whose count sets the score tests' degrees of freedom). Returns (r / f, sigma f, modes): the residuals in units of their own noise
    floor f (`estimate.residuals.noise_floor`, per angle), the per-pixel noise standard
    deviation they were divided by (measured units), both (angles, pixels), and the modes
    of the correlated noise that `ev`'s mean render puts into r / f
    (`estimate.residuals.render_noise_modes`, from the independent renders: the same
    model, spp and count).
    """
    stack = render_stack(model, ev.parameters, problem, spp=spp, seed=seed, repeats=max(repeats, 2, renders or 0))
    mvar = smoothed_variance(stack) / repeats
    var = recording_variance(problem)
    r = normalised_residuals(np.asarray(problem.measured, dtype=np.float64), var, ev.model, ev.scale, mvar)
    r = np.where(np.isfinite(var), r, np.nan)
    f, _ = noise_floor(r)
    sigma = np.sqrt(var + ev.scale ** 2 * mvar) * f[:, None]
    return r / f[:, None], sigma, render_noise_modes(stack, ev.scale, sigma, repeats,
                                                     recorded_noise_share(model, problem, spp))


def recorded_noise_share(model: ProfileModel, problem: ProfileRecording, spp: int) -> float:
    """The recording's frozen render noise as a variance in units of one model render's
    at `spp` (`estimate.residuals.render_noise_modes`' `recorded`): the model's paths per
    image over the recording's, when the simulated camera declared a light-engine render
    (`estimate.problem.Problem.recording_paths`) and the model is the light engine too
    (its renders then carry that noise's correlation along the row); else 0.

    On the demo world (1024 spp on a 512-column frame, the model 2048 spp on 256 columns)
    the share is 1: the recording's noise is as large as one model render's and 4 times
    that of the 4-render mean the smooth test held alone, and clean sessions tested
    significant on it (docs/diagnosis-log.md, session 70).
    """
    paths = getattr(problem, "recording_paths", None)
    if not paths or getattr(model, "engine", "camera") != "light":
        return 0.0
    width = int(np.shape(problem.measured)[1])
    return float(spp) * width / float(paths)


def render_stack(model: ProfileModel, params: Mapping[str, float], problem: ProfileRecording, *, spp: int = 256,
                 seed: int = DEFAULT_SEED, repeats: int = 4, angle_idx: Sequence[int] | None = None) -> np.ndarray:
    """The (repeats, N, W) renders `evaluate` averages: seeds seed + 7 k, queued together
    (`ForwardModel.render_profiles_many`)."""
    idx = list(range(len(problem.angles_deg))) if angle_idx is None else list(angle_idx)
    angles = [float(problem.angles_deg[i]) for i in idx]
    return np.stack(model.render_profiles_many([(params, seed + 7 * k) for k in range(repeats)], angles, spp=spp))


#: Largest fraction of the light a refit may put in the lens blur's wide tail (veiling
#: glare). Camera lenses scatter about 1-5 % of the light that way (ISO 9358 glare
#: indices), so 10 % is generous. Without this bound, the bench's refractive-boundary session
#: (no blur at all) got a joint refit with a 24 % tail beside n = 1.14. The tail stood in for
#: the boundary, and the estimator's final fit, started with the effects held there, ended
#: 19 % high in sigma_t.
MAX_GLARE_FRACTION = 0.1


def parameter_bounds(model: ProfileModel, name: str) -> tuple[float, float]:
    spec = model.specs[name]
    lo = spec.lower
    hi = spec.upper
    if spec.open_lower or name in ("sigma_t",):
        lo = lo + max(1e-6, 1e-6 * abs(hi if math.isfinite(hi) else 1.0))
    if name == "thickness_error.e":
        lo = max(lo, -0.5)
    if name == "sensor_nonlinearity.compression":
        hi = min(hi, 0.32)
    if name == "lens_blur.tail_fraction":
        hi = min(hi, MAX_GLARE_FRACTION)
    if name == "beam_halo.sigma_mm":
        # A halo no wider than the calibrated beam would be part of the calibration's map.
        # Without this bound a refit (synthetic suite, 30 % halo at 1 mm) collapsed the halo
        # to sigma 5e-5 mm, extra power in the core, which fitted its own render's noise.
        beam = getattr(model, "beam_profile", None)
        if beam is not None:
            lo = max(lo, beam.rms_width_mm())
    return lo, hi


@dataclass
class RefitResult:
    """Result of `refit`: parameters, scale, 1-sigma uncertainties, chi^2 of the fixed-seed fit."""

    parameters: dict[str, float]
    scale: float
    uncertainties: dict[str, float]
    chi2: float
    iterations: int
    covariance: dict[tuple[str, str], float] = field(default_factory=dict)
    #: with `refit(decorrelate=True)`: the parameters and scale after the decorrelated
    #: Gauss-Newton step (`decorrelated_step`; the LM point when the step gained nothing),
    #: free of the fixed-seed chi^2's render-noise bias; `parameters` and `chi2` stay the LM's
    decorrelated: dict[str, float] | None = None
    decorrelated_scale: float | None = None
    #: the objective `chi2` is the minimum of (`OBJECTIVES`): with DECORRELATED, `chi2` is the
    #: decorrelated chi^2 of seeds seed and seed + UNCERTAINTY_SEED_OFFSET at `parameters`
    objective: str = FIXED_SEED


def refit_columns(jac: Mapping[str, np.ndarray], f: np.ndarray, s: float, sig: np.ndarray) -> np.ndarray:
    """d residual / d (free parameters, scale) of the refit's chi^2, one column each."""
    cols = [np.ravel(-s * jac[n] / sig) for n in jac] + [np.ravel(-f / sig)]
    return np.nan_to_num(np.stack(cols, axis=1), nan=0.0, posinf=0.0, neginf=0.0)


def cross_inverse(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Inverse Gauss-Newton curvature from two Jacobians with independent render noise,
    every column (the scale's last) included; NaN rows and columns where both are zero.

    The curvature is their cross product (A^T B + B^T A) / 2, held between
    `UNCERTAINTY_CROSS_FLOOR` x and 1 x the matrix of their mean (`bounded_cross`), with the
    columns normalised first: parameters in their own units span many decades (a
    stray-light offset in e-/s against an albedo). A column that is zero in both (a halo's
    width while its fraction is 0) constrains nothing: its variance is NaN (unknown), not 0.
    """
    mean = 0.5 * (a + b)
    cn = np.linalg.norm(mean, axis=0)
    live = cn > 1e-300 * max(1.0, float(np.max(cn, initial=0.0)))
    an, bn, mn = (x[:, live] / cn[live] for x in (a, b, mean))
    h = bounded_cross(0.5 * (an.T @ bn + bn.T @ an), mn.T @ mn, UNCERTAINTY_CROSS_FLOOR)
    inv = np.full((a.shape[1], a.shape[1]), np.nan)
    inv[np.ix_(live, live)] = np.linalg.pinv(h) / np.outer(cn[live], cn[live])
    return inv


def cross_covariance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Gauss-Newton covariance (unit noise) of the free parameters from two Jacobians with
    independent render noise (`cross_inverse` without the scale's row and column)."""
    return cross_inverse(a, b)[:-1, :-1]


def decorrelated_chi2(meas: np.ndarray, sig: np.ndarray, f_a: np.ndarray, f_b: np.ndarray) -> tuple[float, float]:
    """sum r_A r_B / sig^2 over pixels, r = measured - scale x render, for two renders with
    independent noise, at the scale that minimises it; returns (loss, scale)."""
    w = np.where(np.isfinite(sig), 1.0 / np.where(np.isfinite(sig), sig, 1.0) ** 2, 0.0)
    den = float(np.sum(w * f_a * f_b))
    s = float(np.sum(w * meas * 0.5 * (f_a + f_b)) / den) if den > 0 else 1.0
    return float(np.sum(w * (meas - s * f_a) * (meas - s * f_b))), s


def render_noise_ratio(sig: np.ndarray, f_a: np.ndarray, f_b: np.ndarray, s: float) -> float:
    """Mean over pixels of one render's Monte-Carlo variance over the noise, s^2 (f_A - f_B)^2
    / (2 sig^2), from two renders with independent noise (pixels where sig is not finite left out)."""
    keep = np.isfinite(sig)
    if not np.any(keep):
        return 0.0
    d = np.where(keep, s * (f_a - f_b) / np.where(keep, sig, 1.0), 0.0)
    return float(0.5 * np.sum(d * d) / np.count_nonzero(keep))


def decorrelated_step(render: Callable[[dict[str, float]], tuple[np.ndarray, np.ndarray]], meas: np.ndarray,
                      sig: np.ndarray, theta: Mapping[str, float], s: float, f_a: np.ndarray, f_b: np.ndarray,
                      a: np.ndarray, b: np.ndarray, free: Sequence[str],
                      bounds: Sequence[tuple[float, float]], halvings: int = 2,
                      max_noise: float | None = None) -> tuple[dict[str, float], float]:
    """One Gauss-Newton step on the decorrelated chi^2 from a fixed-seed optimum.

    A fixed-seed chi^2 sum (m - s f_A)^2 / sig^2 has the expectation sum ((m - s E f)^2 +
    s^2 Var f_A) / sig^2: its minimum leans towards parameters whose renders are less
    noisy (the synthetic suite's clean recording, refitted from the truth at 512 spp:
    albedo 0.81-0.84 for 0.90, at 4096 spp 0.89; the bias goes as 1 / spp). The product of
    two renders with independent noise, sum r_A r_B, has no such term. From the LM optimum
    (theta, s) of seed A, with `a`, `b` the residuals' Jacobians there (free parameters and
    scale; seeds A and B) and `f_a`, `f_b` the renders, the step is -H^-1 g with g =
    (A^T r_B + B^T r_A) / 2 and H the bounded cross product (`cross_inverse`); halved up
    to `halvings` times while it does not lower the loss (scale profiled, `render(theta)`
    gives both seeds' renders). With `max_noise`, a trial whose renders' noise ratio
    (`render_noise_ratio`) exceeds it is refused as well. Returns the parameters and scale
    of the best point (theta and its decorrelated scale when no step gains).
    """
    keep = np.isfinite(sig)
    r_a = np.where(keep, (meas - s * f_a) / np.where(keep, sig, 1.0), 0.0).ravel()
    r_b = np.where(keep, (meas - s * f_b) / np.where(keep, sig, 1.0), 0.0).ravel()
    inv = np.nan_to_num(cross_inverse(a, b), nan=0.0)
    step = -inv @ (0.5 * (a.T @ r_b + b.T @ r_a))
    loss0, s0 = decorrelated_chi2(meas, sig, f_a, f_b)
    for k in range(halvings + 1):
        frac = 0.5 ** k
        trial = stepped(theta, free, bounds, frac * step)
        try:
            fa_t, fb_t = render(trial)
        except ModelParameterError:
            continue
        loss, s_t = decorrelated_chi2(meas, sig, fa_t, fb_t)
        if loss < loss0 and (max_noise is None or render_noise_ratio(sig, fa_t, fb_t, s_t) <= max_noise):
            return trial, s_t
    return dict(theta), s0


def refit(model: ProfileModel, problem: ProfileRecording, start: Mapping[str, float], free: Sequence[str], *,
          angle_idx: Sequence[int] | None = None, spp: int = 256, seed: int = 2000, iterations: int = 12,
          model_variance: np.ndarray | None = None, noise_scale: np.ndarray | None = None,
          decorrelate: bool = False, uncertainties: bool = True, objective: str = FIXED_SEED,
          noise_variance: np.ndarray | None = None) -> RefitResult:
    """Levenberg-Marquardt fit of `free` parameters (and the scale) with a fixed render seed.

    `iterations` LM iterations at most, or up to LM_EXTENSION times as many while the fit is
    still descending fast at the end of them (`still_descending`); fewer where a step gains
    less than 1e-4 of the chi^2, where the next step's predicted gain is below
    LM_NEGLIGIBLE_GAIN (that step not rendered), or where none is found.

    `model_variance` (per pixel of the whole problem, in the data's units, e-^2/s^2: a
    render's Monte-Carlo variance times the squared scale of the evaluation that measured
    it) is added to the data's variance, and `noise_scale` (f per angle of the whole
    problem, `estimate.residuals.noise_floor`) scales that sum by f^2: the weights
    1 / (f^2 (var + model_variance)) are the same at every point the refit visits.
    (Up to session 46 the render variance was in the render's units and followed the
    refit's own scale, s^2 var_model. A model that dims its renders then buys its own
    weights: on the bench's recaptured boundary session a refractive boundary refitted
    from a base fit 57 % off went to n 2.99, its scale to 5500 x the others' and its
    chi^2 from 7732 to 744, while its training angles rendered at other seeds fitted
    worse, 15259 -> 16743 (session 47). Fixed weights also make the paired comparisons
    between a round's refits, and the Jacobian columns, which hold the weights constant,
    exact.) Uncertainties: Gauss-Newton covariance at the
    optimum, its curvature from two Jacobians with independent render noise
    (`cross_covariance`: this seed's and seed + `UNCERTAINTY_SEED_OFFSET`'s, one render and
    one Jacobian more), inflated by the (adjusted) reduced chi^2 when it exceeds 1.
    With `decorrelate`, one Gauss-Newton step on the two seeds' decorrelated chi^2 from the
    LM optimum (`decorrelated_step`, two renders a try) gives `RefitResult.decorrelated`:
    the LM's fixed-seed chi^2 leans towards parameters with quieter renders.

    `uncertainties=False` skips the uncertainties' render and Jacobians (and returns no
    covariance) where only the optimum and its chi^2 are wanted; `decorrelate` needs them
    and overrides it. With `iterations=0` the refit evaluates `start`: its chi^2 and scale,
    and its uncertainties (and decorrelated step) unless `uncertainties=False`; so a
    refit's uncertainties can be added later, from its optimum, at the same cost.

    `objective=DECORRELATED` minimises the decorrelated chi^2 of two seeds instead
    (`_refit_decorrelated`); `decorrelate` is then moot and `chi2` is that loss. Its
    `noise_variance` (per pixel of the whole problem, e-^2/s^2; the diagnosis' yardstick):
    the data's noise the loss divides by, in place of f^2 (var + s^2 var_model). That loss
    has no render-variance term, and dividing it by one only shrinks it and every gain
    measured in it (on the synthetic suite's 256-px window at 512 spp, to 0.63 of the
    data's own metric).
    """
    if objective not in OBJECTIVES:
        raise ValueError(f"refit objective {objective!r}: expected one of {', '.join(OBJECTIVES)}")
    if noise_variance is not None and objective != DECORRELATED:
        raise ValueError("refit: noise_variance is for the decorrelated objective (the fixed-seed chi^2 holds "
                         "its render's variance)")
    idx = list(range(len(problem.angles_deg))) if angle_idx is None else list(angle_idx)
    angles = [float(problem.angles_deg[i]) for i in idx]
    meas = np.asarray(problem.measured, dtype=np.float64)[idx]
    var = recording_variance(problem)[idx]
    mv = None if model_variance is None else np.asarray(model_variance)[idx]
    floor2 = (np.ones(len(idx)) if noise_scale is None else np.asarray(noise_scale, dtype=np.float64)[idx] ** 2)[:, None]
    theta = dict(model.validate(start))
    free = list(free)
    bounds = [parameter_bounds(model, n) for n in free]
    for n, (lo, hi) in zip(free, bounds):
        theta[n] = float(np.clip(theta[n], lo, hi))
    # The weights: fixed for the whole refit, whichever the objective.
    if noise_variance is None:
        weight_var = (var if mv is None else var + mv) * floor2
    else:
        nv = np.asarray(noise_variance, dtype=np.float64)[idx]
        weight_var = np.where(np.isfinite(var) & (nv > 0), nv, np.inf)
    sig = np.sqrt(weight_var)
    if objective == DECORRELATED:
        return _refit_decorrelated(model, angles, meas, sig, theta, free, bounds, spp=spp, seed=seed,
                                   iterations=iterations, uncertainties=uncertainties)

    def residual(th: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray, float]:
        f = model.render_profiles(th, angles, spp=spp, seed=seed)
        s = best_scale(meas, weight_var, f)
        r = (meas - s * f) / sig
        r = np.where(np.isfinite(sig), r, 0.0)
        return r, f, s

    def expanded(step: np.ndarray, best: tuple[dict[str, float], np.ndarray, np.ndarray, float, float]
                 ) -> tuple[dict[str, float], np.ndarray, np.ndarray, float, float]:
        # The accepted step from theta, longer while that lowers the chi^2 (LM_EXPANSION_MAX).
        k = 2.0
        while k <= LM_EXPANSION_MAX:
            longer = stepped(theta, free, bounds, k * step)
            if longer == best[0]:      # held at its bounds: no longer step
                break
            try:
                r3, f3, s3 = residual(longer)
            except ModelParameterError:
                break
            c3 = float(np.sum(r3 * r3))
            if not c3 < best[4]:
                break
            best = (longer, r3, f3, s3, c3)
            k *= 2.0
        return best

    r, f, s = residual(theta)
    chi2 = float(np.sum(r * r))
    lam = 1e-3
    it = 0
    A = None
    a_at: dict[str, float] = {}  # the point of the loop's last Jacobian
    history = [chi2]
    for it in range(1, LM_EXTENSION * iterations + 1):
        # Secant steps (estimate.fit.secant_steps), not the parameters' small default steps:
        # with common random numbers a render is not a smooth function of sigma_t or the
        # phase (a free flight crossing the slab boundary flips), and small-step columns
        # differed between seeds by up to 2x, so LM saw no descent towards the optimum.
        # Central: forward differences against the render at theta (half the renders) were
        # tried in session 32 and stalled after one step on the simulated bench's pair session
        # (docs/diagnosis-log.md).
        A = refit_columns(model.jacobian(theta, angles, free, spp=spp, seed=seed,
                                          steps=secant_steps(model, theta, free)), f, s, sig)
        a_at = dict(theta)
        g = A.T @ r.ravel()
        H = A.T @ A
        d = np.maximum(np.diag(H), 1e-300)
        improved = False
        settled = False
        for _ in range(8):
            try:
                step = -np.linalg.solve(H + lam * np.diag(d), g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            if -(2.0 * float(g @ step) + float(step @ H @ step)) < LM_NEGLIGIBLE_GAIN:
                settled = True       # no step at this damping or more can gain what counts
                break
            trial = stepped(theta, free, bounds, step)
            try:
                r2, f2, s2 = residual(trial)
            except ModelParameterError:
                lam *= 10.0
                continue
            c2 = float(np.sum(r2 * r2))
            if c2 < chi2:
                if it > iterations and (chi2 - c2) > LM_STILL_DESCENDING * chi2:
                    trial, r2, f2, s2, c2 = expanded(step, (trial, r2, f2, s2, c2))
                rel = (chi2 - c2) / max(chi2, 1e-300)
                theta, r, f, s, chi2 = trial, r2, f2, s2, c2
                lam = max(lam / 3.0, 1e-7)
                improved = True
                break
            lam *= 4.0
        if _log.isEnabledFor(logging.DEBUG):
            _log.debug("LM iteration %d: chi2 %.3f (%s), lambda %.1e, at %s", it, chi2,
                       "step" if improved else "settled" if settled else "no step", lam,
                       ", ".join(f"{n} {theta[n]:.5g}" for n in free))
        history.append(chi2)
        # A settled iteration accepted no step, so `not improved` ends the refit there too.
        if not improved or rel < 1e-4:
            break
        if it >= iterations and not still_descending(history):
            break
    if not (uncertainties or decorrelate):
        return RefitResult(theta, s, {}, chi2, it)
    # The curvature from two Jacobians with independent render noise (this seed's and
    # another's): one Monte Carlo Jacobian's A^T A carries the noise's own Gram matrix,
    # which dominates the weakly constrained directions and narrows their intervals
    # (estimate.fit.sandwich_uncertainties). The refit itself stays at one seed.
    steps = secant_steps(model, theta, free)
    seed_b = seed + UNCERTAINTY_SEED_OFFSET
    f_b = model.render_profiles(theta, angles, spp=spp, seed=seed_b)
    # The loop's last Jacobian is this seed's at the final point unless a step moved it since.
    a_own = A if A is not None and a_at == theta else refit_columns(
        model.jacobian(theta, angles, free, spp=spp, seed=seed, steps=steps), f, s, sig)
    As = [a_own, refit_columns(model.jacobian(theta, angles, free, spp=spp, seed=seed_b, steps=steps),
                               f_b, s, sig)]
    unc, covd = _uncertainties(As[0], As[1], free, chi2, sig)
    dec: dict[str, float] | None = None
    dec_s: float | None = None
    if decorrelate:
        def both(th: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
            return (model.render_profiles(th, angles, spp=spp, seed=seed),
                    model.render_profiles(th, angles, spp=spp, seed=seed_b))

        dec, dec_s = decorrelated_step(both, meas, sig, theta, s, f, f_b, As[0], As[1], free, bounds)
    return RefitResult(theta, s, unc, chi2, it, covd, dec, dec_s)


def stepped(theta: Mapping[str, float], free: Sequence[str], bounds: Sequence[tuple[float, float]],
            step: np.ndarray) -> dict[str, float]:
    """`theta` moved by `step` along the `free` parameters, each held within its bounds."""
    out = dict(theta)
    for j, (n, (lo, hi)) in enumerate(zip(free, bounds)):
        out[n] = float(np.clip(theta[n] + step[j], lo, hi))
    return out


def still_descending(history: Sequence[float]) -> bool:
    """Whether a refit whose chi^2 went through `history` (its start, then each iteration's
    end) is still descending: its last two iterations lowered the chi^2 by more than
    LM_STILL_DESCENDING of where they started."""
    if len(history) < 3 or not history[-3] > 0:
        return False
    return (history[-3] - history[-1]) / history[-3] > LM_STILL_DESCENDING


def _uncertainties(a: np.ndarray, b: np.ndarray, free: Sequence[str], chi2: float,
                   sig: np.ndarray) -> tuple[dict[str, float], dict[tuple[str, str], float]]:
    """A refit's 1-sigma uncertainties and covariance of `free` from two Jacobians with
    independent render noise (`cross_covariance`), inflated by the reduced chi^2 where it
    exceeds 1 (NaN where a parameter constrains nothing)."""
    n_obs = int(np.sum(np.isfinite(sig)))
    cov = cross_covariance(a, b) * max(1.0, chi2 / max(1, n_obs - len(free) - 1))
    unc = {n: float(math.sqrt(max(cov[j, j], 0.0))) if np.isfinite(cov[j, j]) else float("nan")
           for j, n in enumerate(free)}
    covd = {(p, q): float(cov[i, j]) for i, p in enumerate(free) for j, q in enumerate(free)}
    return unc, covd


def _refit_decorrelated(model: ProfileModel, angles: Sequence[float], meas: np.ndarray, sig: np.ndarray,
                        theta: dict[str, float], free: list[str], bounds: Sequence[tuple[float, float]], *,
                        spp: int, seed: int, iterations: int, uncertainties: bool) -> RefitResult:
    """`refit` on the decorrelated chi^2 of seeds `seed` and `seed + UNCERTAINTY_SEED_OFFSET`.

    Each iteration renders both seeds' Jacobians at theta (the fixed-seed refit's secant
    steps, central differences; split one-sided ones, seed A's forward and seed B's
    backward, were tried in session 47 and weakened a halo's gain 110 -> 19) and takes
    `decorrelated_step`, halved up to three times and never to renders more
    than `DECORRELATED_MAX_NOISE_GROWTH` times as noisy as the start's, until a step gains less
    than `DECORRELATED_RTOL` of the loss, none gains, or `iterations` are done. The weights
    are `refit`'s fixed `sig` (1 / (f^2 (var + model_variance)), or 1 / `noise_variance`
    where given), so the loss only falls and is a function of the point
    alone: `iterations=0` from a refit's optimum gives the same number, and two refits from
    the same data with the same weights and seeds are paired (their losses differ by what
    their models explain; the two seeds' render noise is common to both by common random
    numbers). Its expectation has no render variance term: under the right model it is
    the data's share of the noise, var / (var + model_variance) a pixel, below the
    fixed-seed chi^2's 1; with `noise_variance` the data's noise, about 1 a pixel.
    """
    seed_b = seed + UNCERTAINTY_SEED_OFFSET
    last: dict[tuple[tuple[str, float], ...], tuple[np.ndarray, np.ndarray]] = {}

    def both(th: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray]:
        # The accepted trial of `decorrelated_step` is the next iteration's point: its two
        # renders are kept (the last pair only) rather than rendered again.
        key = tuple(sorted(th.items()))
        if key not in last:
            last.clear()
            last[key] = (model.render_profiles(th, angles, spp=spp, seed=seed),
                         model.render_profiles(th, angles, spp=spp, seed=seed_b))
        return last[key]

    f_a, f_b = both(theta)
    loss, s = decorrelated_chi2(meas, sig, f_a, f_b)
    max_noise = DECORRELATED_MAX_NOISE_GROWTH * render_noise_ratio(sig, f_a, f_b, s)
    jac_at: dict[str, float] | None = None
    a = b = np.zeros((0, 0))
    it = 0

    def jacobians(th: dict[str, float], scale: float) -> tuple[np.ndarray, np.ndarray]:
        fa, fb = both(th)
        steps = secant_steps(model, th, free)
        return (refit_columns(model.jacobian(th, angles, free, spp=spp, seed=seed, steps=steps), fa, scale, sig),
                refit_columns(model.jacobian(th, angles, free, spp=spp, seed=seed_b, steps=steps), fb, scale, sig))

    for it in range(1, iterations + 1):
        a, b = jacobians(theta, s)
        jac_at = dict(theta)
        new, _ = decorrelated_step(both, meas, sig, theta, s, f_a, f_b, a, b, free, bounds, halvings=3,
                                   max_noise=max_noise)
        if new == theta:
            _log.debug("decorrelated iteration %d: loss %.3f, no step", it, loss)
            break
        f_a, f_b = both(new)
        new_loss, s_new = decorrelated_chi2(meas, sig, f_a, f_b)
        gain = loss - new_loss
        theta, loss, s = new, new_loss, s_new
        _log.debug("decorrelated iteration %d: loss %.3f (gain %.3f)", it, loss, gain)
        if gain < DECORRELATED_RTOL * max(abs(loss), 1.0):
            break
    if not uncertainties:
        return RefitResult(theta, s, {}, loss, it, objective=DECORRELATED)
    if jac_at != theta:
        a, b = jacobians(theta, s)
    unc, covd = _uncertainties(a, b, free, loss, sig)
    return RefitResult(theta, s, unc, loss, it, covd, objective=DECORRELATED)
