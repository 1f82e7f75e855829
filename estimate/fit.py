"""Fit sigma_t, albedo and the phase function of one channel by differentiable rendering.

`fit_channel(problem, model)`:

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
   steps (`_gn_jacobian`, re-estimated every `gn_jacobian_every` iterations at
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
   `_snr_step`), so the longer steps do not turn gradient noise into excursions along b2
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
   doubles and the step shrinks (x0.85, Adam); when it flattens at `spp_max` (256) the
   iterations stop ("converged"). Their result is the average of the last `window` iterates
   (2 x `window` for Gauss-Newton), which averages the Monte Carlo noise of the steps; when
   they still drift (`_drift`), the end of their linear trend instead, since their mean
   lags the last iterate by half the window's drift (session 16: 1.3-2.9 % of sigma_t on
   the benchmark);
5. Gauss-Newton polish (`_gn_polish`, `polish_steps` = 4): full, unshrunk Gauss-Newton steps
   at `final_spp` (two 1024-spp renders per step and a new matrix from the cross product of
   two 512-spp Jacobians, `polish_cross`), which walk down the valley several % of sigma_t
   per step where the iterations crawled (benchmark, session 16: from 2.38 to 1.98 in four
   steps; truth 2.0). It replaced the iterations' 512-spp stage in the time budget. Near
   the optimum its steps scatter by 3-5 % of sigma_t (the gradient's noise at 2 x 1024 spp
   along the valley), so the result is the mean of the points after steps 2-4
   (`polish_average_from`, `_polish_average`). Each step's chi^2 against its own render
   noise (`step_chi2`) tells a move from that scatter; while any of the last three is a
   move (above the 0.1 % quantile, `polish_continue_p`) the polish goes on, up to
   `polish_max_steps` (2 x `polish_steps`), and averages its last three points, each
   weighed by its own noise. Optionally (`polish_settled_spp` > 1, off by default; session
   19) a step after a noise-sized one keeps the matrix and renders its gradient at that
   many times the spp. An optional
   Levenberg-Marquardt polish (`lm_iterations`, off by default) on the log residuals at one
   fixed seed follows: with common random numbers the renders are not smooth in the
   parameters (free flights crossing the slab boundary flip), its finite-difference
   Jacobian is noisy, and in tests it gained < 10 % of the loss for ~45 s;
6. final evaluation at `final_spp` with two seeds: fitted profiles (their mean), the model's
   own Monte Carlo variance per pixel ((p1 - p2)^2 / 4, the variance of the mean of two),
   scale, loss at the reference delta, chi^2 with var_meas + s^2 var_model;
7. uncertainties: the sandwich covariance of the log-loss estimator
   (`sandwich_uncertainties`: Gauss-Newton curvature of the log loss, the sensor and render
   noise propagated through it, times the log-space reduced chi^2 when > 1; the curvature
   from the cross products of independent Jacobians, one at the final point and the
   polish's last ones, since one Monte Carlo Jacobian's own noise fakes curvature along the
   sigma_t / phase valley and narrowed sigma_t's interval up to 20x there), never below
   the linear Fisher bound (`fisher_uncertainties`: F = J^T W J with J the Jacobian of
   s * I_model, W = 1 / (var_meas + s^2 var_model), times the reduced chi^2 when > 1; kept
   in `FitResult.fisher_uncertainties`). The Fisher bound alone was 4-25x smaller than the
   real errors: the log loss is not the variance-weighted fit the bound describes, and the
   residuals exceed the noise. The standard deviation of the averaged iterates (the stochastic
   optimiser's own spread, `FitResult.optimizer_spread`) is added in quadrature, and so is
   the last polish step (`FitResult.drift`; without a polish, the iterates' drift): the
   fit still moved that much at its end. When the polish's points are averaged, their mean
   step is the drift and their mean's standard error is added instead; the drift is then
   added only where it stands out of the points' own scatter (`_combined_uncertainties`).
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
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.stats import chi2 as chi2_dist

from estimate.errors import ModelParameterError
from estimate.forward import ForwardModel
from estimate.loss import (
    DEFAULT_DELTA_RANGE,
    ScaleCalibration,
    calibrated_scale,
    chi2,
    decorrelated_loss,
    decorrelated_loss_se,
    log_loss,
    profile_additive,
    profile_scale,
    reference_delta,
)
from estimate.problem import Problem
from estimate.start import coarse_start
from estimate.transforms import Transform, transform_for

__all__ = ["FitResult", "FitSettings", "evaluate", "fisher_uncertainties", "fit_channel", "model_phase", "secant_steps"]


def _finite_number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


@dataclass
class FitSettings:
    """Optimiser settings (defaults: the paper's exp3 fit within ~2 min on 2 cores)."""

    max_iterations: int = 80
    spp_start: int = 128
    spp_max: int = 256               # the iterations' largest spp (the polish and final evaluation: final_spp)
    final_spp: int = 1024
    start_spp: int = 32               # coarse joint grid (estimate.start)
    window: int = 8
    lr_scale: float = 1.0
    lr_decay: float = 0.85
    delta_range: tuple[float, float] = DEFAULT_DELTA_RANGE
    seed: int = 0
    time_limit_s: float | None = None
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
    polish_cross: bool = True        # polish matrix from two half-spp Jacobians' cross product (see _gn_polish)
    polish_average_from: int = 2     # the result: mean of the points after polish steps >= this (1-based; 0: last point)
    polish_max_steps: int | None = None   # polish steps in all while its last points still walk (None: 2 x polish_steps)
    polish_continue_p: float = 0.001  # a step is still a move when its noise chi^2 exceeds this upper quantile
    polish_settled_spp: int = 1      # > 1: after a noise-sized polish step, renders at this x final_spp, last Jacobians kept
    uncertainty_spp: int = 512       # the uncertainties' Jacobian at the final point (two without a polish)
    decorrelated: bool = True
    #: solve additive parameters (stray-light offset and slope) exactly at every iteration
    #: instead of stepping them (decorrelated mode only; see fit_channel)
    profile_additive: bool = True
    lm_spp: int = 1024
    uncertainties: bool = True
    scale: str = "free"              # "free": fitted (profiled) per channel; "calibrated": from the beam power

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
                if v is not None and not (_finite_number(v) and v > 0):
                    raise bad("a positive number of seconds or null")
            elif f.name == "polish_max_steps":
                if v is not None and not (isinstance(v, int) and not isinstance(v, bool) and v >= 0):
                    raise bad("a whole number >= 0 or null")
            elif f.name == "delta_range":
                if not (isinstance(v, list | tuple) and len(v) == 2 and all(_finite_number(x) and x > 0 for x in v)
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
                if not (_finite_number(v) and 0 < v < 1):
                    raise bad("a probability between 0 and 1")
                v = float(v)
            elif f.name == "gn_smooth_px":
                if not (_finite_number(v) and v >= 0):
                    raise bad("a number of pixels >= 0 (0: no smoothing)")
                v = float(v)
            elif isinstance(default, float):
                if not (_finite_number(v) and v > 0):
                    raise bad("a positive number")
                v = float(v)
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
    lm_losses: list[float] = field(default_factory=list)   # loss after each accepted LM step
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
    #: the Gauss-Newton polish after the iterations (`_gn_polish`): per step {loss, loss_new,
    #: accepted, halvings, step, step_chi2, point (when accepted)}
    polish: list[dict[str, Any]] = field(default_factory=list)
    #: wall seconds per stage: start (coarse search), iterations, polish, evaluation,
    #: uncertainties (their sum is about `time_s`)
    stage_times_s: dict[str, float] = field(default_factory=dict)

    @property
    def free(self) -> list[str]:
        return [k for k in self.parameters if k not in self.fixed]

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

    def derived(self) -> dict[str, dict[str, float | None]]:
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


def _averaged_gradient_cov(recent: Sequence[np.ndarray], momentum: float) -> np.ndarray | None:
    """Covariance of the momentum-averaged gradient: the per-iteration covariance C from
    successive differences of the recent gradients (C = mean(d d^T) / 2, which ignores slow
    trends), times (1 - m) / (1 + m) for an exponential average with momentum m; None with
    fewer than 3 gradients."""
    if len(recent) < 3:
        return None
    d = np.diff(np.asarray(recent), axis=0)
    return 0.5 * (d.T @ d) / len(d) * (1.0 - momentum) / (1.0 + momentum)


def _predicted_decrease(h_inv: np.ndarray, g_avg: np.ndarray, recent: Sequence[np.ndarray],
                        momentum: float) -> tuple[float, float]:
    """The loss decrease the Gauss-Newton model predicts for a full step, 0.5 g^T H^-1 g with
    g the averaged gradient, and the part of it that the gradient's Monte Carlo noise alone
    would produce, 0.5 tr(H^-1 C_avg) (`_averaged_gradient_cov`).
    """
    pred = 0.5 * float(g_avg @ h_inv @ g_avg)
    cov = _averaged_gradient_cov(recent, momentum)
    return pred, float("nan") if cov is None else 0.5 * float(np.trace(h_inv @ cov))


#: Finite-difference steps, in the optimiser's variables z, for the Gauss-Newton matrix.
#: Large on purpose: with common random numbers the renders are not smooth functions of
#: the parameters (a free flight that crosses the slab boundary flips, and the rest of the
#: path decorrelates), so at the parameters' default steps the columns of one seed differed
#: from another seed's by up to 2x (sigma_t, b3) while the reverse-mode gradients agreed
#: within 10 %. Steps of 5 % in sigma_t and 0.5 in b_i bring the spread to ~15 %, enough
#: for a preconditioner: the gradient itself always comes from the reverse-mode pass.
_GN_DZ = {"log": 0.05, "logit": 0.3, "tanh": 0.1}
_GN_DB = 0.5
#: Smallest eigenvalue of the Gauss-Newton matrix, relative to its largest (see _gn_direction).
GN_EIG_FLOOR = 1e-4


def _smooth_rows(a: np.ndarray, valid: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian smoothing (sigma in pixels) of (N, W) columns along each row, over valid
    pixels only (normalised convolution); invalid pixels come back as 0."""
    if sigma_px <= 0.0:
        return np.where(valid, a, 0.0)
    w = valid.astype(float)
    num = gaussian_filter1d(np.where(valid, a, 0.0), sigma_px, axis=-1, mode="constant")
    norm = gaussian_filter1d(w, sigma_px, axis=-1, mode="constant")
    return np.where(valid & (norm > 0), num / np.where(norm > 0, norm, 1.0), 0.0)


def _snr_step(h_inv: np.ndarray, g_avg: np.ndarray, recent: Sequence[np.ndarray], momentum: float) -> np.ndarray:
    """H^-1 g_avg with each eigen-direction of H^-1 shrunk by s = m^2 / (m^2 + v): m the
    averaged gradient's component along it, v that component's Monte Carlo variance
    (`_averaged_gradient_cov`). Directions where the
    gradient is mostly noise (the sigma_t / phase valley's floor, b2 against b3) get short
    steps instead of H^-1's amplification of that noise; well-measured directions keep the
    full Gauss-Newton step. With fewer than 3 gradients there is no noise estimate: s = 1."""
    mu, V = np.linalg.eigh(0.5 * (h_inv + h_inv.T))
    proj = V.T @ g_avg
    cov = _averaged_gradient_cov(recent, momentum)
    if cov is None:
        return V @ (mu * proj)
    var = np.einsum("ik,ij,jk->k", V, cov, V)
    shrink = proj ** 2 / np.maximum(proj ** 2 + var, 1e-300)
    return V @ (mu * shrink * proj)


def secant_steps(fm: ForwardModel, params: Mapping[str, float], names: Sequence[str]) -> dict[str, float]:
    """Finite-difference steps (in each parameter's own units) for Jacobians that must
    describe the mean trend of Monte Carlo renders rather than one seed's jagged surface:
    5 % in sigma_t, 0.3 in logit albedo, 0.1 in atanh g, 0.5 in b_i, 3x the default
    otherwise, and never below the parameter's default step."""
    steps: dict[str, float] = {}
    for n in names:
        spec = fm.specs[n]
        x = float(params[n])
        default = spec.fd_step * max(1.0, abs(x))
        t = transform_for(n, spec)
        if t.kind in _GN_DZ:
            steps[n] = max(default, _GN_DZ[t.kind] * t.dx_dz(t.to_z(x)))
        elif n.startswith("phase.b"):
            steps[n] = _GN_DB
        else:
            steps[n] = 3.0 * default
    return steps


def _gn_jacobian(fm: ForwardModel, problem: Problem, p: Mapping[str, float], names: Sequence[str],
                 *, spp: int, seed: int) -> dict[str, np.ndarray]:
    """d profiles / d x at `p` for the Gauss-Newton matrix (central differences, large steps)."""
    return fm.jacobian(p, problem.angles_deg, list(names), spp=spp, seed=seed, steps=secant_steps(fm, p, names))


def _gn_direction(jac: Mapping[str, np.ndarray], names: Sequence[str], tr: Sequence[Transform], z: np.ndarray,
                  problem: Problem, mean: np.ndarray, dl: float, m: np.ndarray, profiled_scale: bool,
                  grad_z: np.ndarray, damping: float = 1e-3, eig_floor: float | None = None) -> np.ndarray:
    """Gauss-Newton step in z for the log loss mean(r^2) given its gradient `grad_z`
    (-H^-1 grad_z with H^-1 from `_gn_inverse`)."""
    return -(_gn_inverse(jac, names, tr, z, problem, mean, dl, m, profiled_scale, damping, eig_floor) @ grad_z)


def _gn_columns(jac: Mapping[str, np.ndarray], names: Sequence[str], tr: Sequence[Transform], z: np.ndarray,
                problem: Problem, mean: np.ndarray, d: float, m: np.ndarray, profiled_scale: bool,
                profiled_columns: Sequence[np.ndarray] = (), smooth_px: float = 0.0,
                exact: Collection[str] = ()) -> np.ndarray:
    """A = d r / d z (pixels x len(names)) of the log residuals r = log(m + d) - log(I + d)
    at absolute delta `d`, with the profiled directions (scale, additive columns) projected
    out; see `_gn_inverse`."""
    valid = problem.valid
    den = np.clip(mean, 0.0, None) + d
    cols = [_smooth_rows(np.where(valid, -jac[nm] / den, 0.0), valid, 0.0 if nm in exact else smooth_px).ravel()
            * t.dx_dz(float(zz)) for nm, t, zz in zip(names, tr, z)]
    A = np.stack(cols, axis=1)
    A = np.where(np.isfinite(A), A, 0.0)
    out_cols = [np.where(valid, -np.asarray(c) / den, 0.0).ravel() for c in profiled_columns]
    if profiled_scale:
        out_cols.append(np.where(valid, -m / (np.clip(m, -0.5 * d, None) + d), 0.0).ravel())
    if out_cols:
        Q, R = np.linalg.qr(np.stack(out_cols, axis=1))
        keep = np.abs(np.diag(R)) > 1e-12 * max(1e-300, float(np.max(np.abs(np.diag(R)))))
        Q = Q[:, keep]
        A = A - Q @ (Q.T @ A)
    return A


#: Smallest generalised eigenvalue of the cross-product matrix against the two Jacobians'
#: mean's (see bounded_cross).
CROSS_FLOOR = 0.5


def bounded_cross(h_cross: np.ndarray, h_mean: np.ndarray, floor: float) -> np.ndarray:
    """The cross-product Gauss-Newton matrix held between `floor` x and 1 x the matrix of the
    two Jacobians' mean, in the generalised eigenvalues of one against the other.

    Noise only adds to a Gram matrix, so the noise-free matrix lies below the mean's (the
    cross product's generalised eigenvalues above 1 are noise). Below, the cross product's
    weak directions are themselves noisy, and near zero its inverse turned noise into steps
    that threw sigma_t from 3.45 to 1.8 (truth 3.0) on the fit tests' small session with
    128-spp halves; `floor` keeps each step within 1 / `floor` x the mean matrix's step
    (at 0.5 the first steps there ended 2.56-2.91 at three seeds, at 0.25 1.97-2.61, the
    mean matrix's 3.05-3.08; on the benchmark the cross product's sigma_t step was 1.3x the
    mean's, session 17).
    """
    lam_m, V = np.linalg.eigh(0.5 * (h_mean + h_mean.T))
    if lam_m.size == 0 or not np.all(np.isfinite(lam_m)) or lam_m[-1] <= 0.0:
        return h_cross
    root = V * np.sqrt(np.clip(lam_m, 1e-12 * lam_m[-1], None))       # h_mean = root root^T
    inv_root = np.linalg.inv(root)
    lam, U = np.linalg.eigh(inv_root @ (0.5 * (h_cross + h_cross.T)) @ inv_root.T)
    lam = np.clip(lam, floor, 1.0)
    return root @ (U * lam) @ U.T @ root.T


def _gn_inverse(jac: Mapping[str, np.ndarray], names: Sequence[str], tr: Sequence[Transform], z: np.ndarray,
                problem: Problem, mean: np.ndarray, dl: float | Sequence[float], m: np.ndarray, profiled_scale: bool,
                damping: float = 1e-3, eig_floor: float | None = None,
                profiled_columns: Sequence[np.ndarray] = (), smooth_px: float = 0.0,
                exact: Collection[str] = (), jac_cross: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
    """Inverse of the Gauss-Newton matrix of the log loss mean(r^2) in the variables z.

    `profiled_columns`: d profiles / d p (N, W) of parameters solved at every iteration
    outside z (additive ones); like a profiled scale, their directions are projected out.

    The matrix is 2/n A^T A with A = dr/dz = -J / (I + delta) dx/dz at this iteration's delta
    and profiles; with a profiled scale the scale's column is projected out (the scale is
    re-optimised at every iteration, so the other parameters move in its orthogonal
    complement). The gradient is the reverse-mode one (unbiased); only the matrix comes from
    finite differences. The Monte Carlo noise of a finite-difference Jacobian adds its own
    Gram matrix to A^T A: at the one-channel benchmark's end point one 256-spp Jacobian gave
    eigenvalues 2-13x those of two independent Jacobians' cross product (A1^T A2 + A2^T A1)
    / n, whose expectation is the noise-free matrix, so the steps are that much shorter than
    Newton steps. The cross product was tried as the matrix (session 4, with a trust region
    capping the predicted decrease at the loss): its small eigenvalues are noise, and the
    fit diverged both times (sigma_t 2 -> 11 and 18). The inflated matrix is kept in the
    iterations: it makes the steps short but safe. The polish after them uses the cross
    product (`jac_cross`: the second Jacobian's columns B, matrix (A^T B + B^T A) / n), where
    the smoothing and higher spp keep its noise small; see `_gn_polish`.

    `dl` (absolute delta) may be several values: the matrix is then the mean of theirs, the
    Gauss-Newton matrix of the loss averaged over delta. The fit draws delta at random per
    iteration and averages the gradients over iterations (momentum), so its averaged gradient
    is that of the delta-averaged loss; a matrix at the iteration's own delta did not match
    it. Over the default range (0.01-0.2) the matrix's weakest eigenvalue changed by up to 25x
    from one iteration to the next, and when a large-delta matrix met gradients averaged
    over small deltas the step along the weakest direction (b2 against b3) was up to 50x
    the usual, capped per component (the benchmark at seed 3: b2 -1.7 -> -5, sigma_t 21 %
    high at the end).

    `smooth_px` > 0 smooths each column of A along the row first (`_smooth_rows`, Gaussian,
    valid pixels only), except those named in `exact` (image-space parameters such as the
    lens blur's, whose columns are exact and may be sharp). The finite-difference columns are smooth functions of x and the noise is nearly
    independent per pixel, so this removes most of the noise Gram matrix: at the benchmark's
    end point the generalised eigenvalues of one 256-spp matrix against a smoothed
    4096-spp one fell from 1.2-63 to 0.9-5.8 with 3 px (the 4096-spp matrix smoothed with
    3 px moves by 0.79-0.99 against itself smoothed with 2 px: the bias is small).
    """
    eig_floor = GN_EIG_FLOOR if eig_floor is None else eig_floor
    n = max(1, int(problem.valid.sum()))
    dls = [float(dl)] if np.isscalar(dl) else [float(x) for x in dl]  # type: ignore[arg-type]
    H = np.zeros((len(names), len(names)))
    H_mean = np.zeros((len(names), len(names)))
    for d in dls:
        A = _gn_columns(jac, names, tr, z, problem, mean, d, m, profiled_scale, profiled_columns, smooth_px, exact)
        if jac_cross is None:
            H += 2.0 * (A.T @ A) / n / len(dls)
        else:
            B = _gn_columns(jac_cross, names, tr, z, problem, mean, d, m, profiled_scale, profiled_columns,
                            smooth_px, exact)
            H += (A.T @ B + B.T @ A) / n / len(dls)
            H_mean += 0.5 * ((A + B).T @ (A + B)) / n / len(dls)
    if jac_cross is not None:
        H = bounded_cross(H, H_mean, CROSS_FLOOR)
    H = H + damping * np.diag(np.diag(H)) + 1e-12 * np.eye(len(names))
    # Eigenvalue floor: directions the data barely constrain (two-term HG with the
    # forward lobe's weight -> 1 leaves g_backward free; albedo -> 1) have eigenvalues near
    # zero, and H^-1 would turn the gradient's Monte Carlo noise there into full-size steps.
    # Flooring them at `eig_floor` x the largest turns those components into short
    # gradient steps; exp3's well-posed matrices (condition ~1e3) are left unchanged.
    lam, V = np.linalg.eigh(0.5 * (H + H.T))
    lam_max = float(lam[-1]) if lam.size else 0.0
    if not np.isfinite(lam_max) or lam_max <= 0.0:
        return np.eye(len(names))
    lam = np.maximum(lam, eig_floor * lam_max)
    return (V / lam) @ V.T


def _lm_polish(fm: ForwardModel, problem: Problem, params: dict[str, float], names: Sequence[str],
               tr: Sequence[Transform], *, spp: int, seed: int, delta_rel: float, iterations: int,
               fixed_scale: float | None = None) -> tuple[dict[str, float], list[float]]:
    """Levenberg-Marquardt on the log residuals at the reference delta, one fixed seed.

    With the seed fixed (common random numbers) the loss is a smooth deterministic function
    of the parameters, so Gauss-Newton steps converge where Adam on fresh noise each
    iteration only hovers. The Jacobian is `ForwardModel.jacobian` (central differences);
    unknowns are the transformed variables z plus log scale (unless `fixed_scale`). Returns
    the parameters and the loss after each accepted step.
    """
    valid = problem.valid
    meas = problem.measured
    angles = problem.angles_deg

    def residual(p: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray, float, float, float]:
        prof = fm.render_profiles(p, angles, spp=spp, seed=seed)
        sc = fixed_scale if fixed_scale is not None else profile_scale(meas, prof, valid, delta_rel)
        m = meas / sc
        dlt = delta_rel * float(np.max(np.where(valid, m, -np.inf)))
        mm = np.clip(m, -0.5 * dlt, None)
        r = np.where(valid, np.log(mm + dlt) - np.log(np.clip(prof, 0, None) + dlt), 0.0)
        return r, prof, sc, dlt, float(np.sum(r * r) / max(1, valid.sum()))

    p = dict(params)
    z = np.array([t.to_z(p[n]) for n, t in zip(names, tr)])
    r, prof, sc, dlt, loss = residual(p)
    losses = [loss]
    lam = 1e-3
    for _ in range(iterations):
        jac = fm.jacobian(p, angles, list(names), spp=spp, seed=seed)
        cols = [np.where(valid, -jac[n] / (np.clip(prof, 0, None) + dlt), 0.0).ravel() * t.dx_dz(float(zz))
                for n, t, zz in zip(names, tr, z)]
        m = meas / sc
        if fixed_scale is None:
            cols.append(np.where(valid, -m / (np.clip(m, -0.5 * dlt, None) + dlt), 0.0).ravel())
        n_z = len(names)
        A = np.stack(cols, axis=1)
        AtA = A.T @ A
        Atr = A.T @ r.ravel()
        accepted = False
        rel = 0.0
        # Up to 8 damping increases (x4 each): in the curved sigma_t-phase valley the
        # Gauss-Newton steps overshoot; with 4 the polish of a simulated-bench fit
        # (paper d0.5_s2, calibrated scale) accepted no step at all.
        for _try in range(8):
            H = AtA + lam * np.diag(np.diag(AtA) + 1e-12)
            try:
                step = -np.linalg.solve(H, Atr)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            z_new = np.array([t.clamp_z(float(zz + dz)) for t, zz, dz in zip(tr, z, step[:n_z])])
            p_new = dict(p)
            p_new.update({n: t.to_x(float(zz)) for n, t, zz in zip(names, tr, z_new)})
            try:
                p_new = fm.validate(p_new)
            except ModelParameterError:
                lam *= 10
                continue
            r_n, prof_n, sc_n, dlt_n, loss_n = residual(p_new)
            if loss_n < loss:
                p, z, r, prof, sc, dlt = p_new, z_new, r_n, prof_n, sc_n, dlt_n
                rel = (loss - loss_n) / loss
                loss = loss_n
                losses.append(loss)
                lam = max(lam / 3.0, 1e-6)
                accepted = True
                break
            lam *= 4.0
        if not accepted or rel < 1e-3:
            break
    return p, losses


def _polish_average(accepted: Sequence[Mapping[str, Any]], names: Sequence[str], tr: Sequence[Transform],
                    start: int) -> tuple[dict[str, float], dict[str, float], dict[str, float],
                                         dict[str, float]] | None:
    """The mean of the points after the accepted polish steps `start`, `start` + 1, ...
    (1-based; stepped parameters averaged in z, solved additive ones as they are), the mean
    step between those points (x units: the drift left at the end), the points' standard
    deviation and the mean's standard error (x units). None when fewer than two points
    qualify (or `start` <= 0).

    Why: near the optimum each full Gauss-Newton step lands at the optimum plus the
    gradient's Monte Carlo noise (about 3-5 % of sigma_t on the benchmark at 2 x 1024 spp),
    so successive points are nearly independent draws about it and their mean is closer.
    The first step, from the iterations' end, is still a move and is left out by default.

    The standard error is the larger of the points' sample one and the one their steps'
    noise model gives (each entry's `noise_sd`, when present). Three points' sample standard
    deviation is itself uncertain by about half: on the session-18 benchmark the points
    agreed by chance (2.046, 2.091, 2.074; standard error 0.013) and the reported
    uncertainty was 2.7x under the error.

    When every point has its `noise_sd`, each parameter's mean weighs the points by
    1 / noise_sd^2 (a settled step's point, from renders at several times the spp, counts
    for as much more), its model standard error is 1 / sqrt(sum of the weights) and its
    sample one the weighted scatter's; with equal noise these are the plain ones.
    """
    if start <= 0:
        return None
    kept = [e for e in accepted[start - 1:] if e.get("point")]
    pts = [dict(e["point"]) for e in kept]
    if len(pts) < 2:
        return None
    keys = [k for k in pts[0] if all(k in q for q in pts)]
    noise = [e.get("noise_sd") or {} for e in kept]
    by_name = dict(zip(names, tr))
    mean: dict[str, float] = {}
    sd: dict[str, float] = {}
    se: dict[str, float] = {}
    n = len(pts)
    for k in keys:
        xs = np.array([q[k] for q in pts], dtype=float)
        nsd = np.array([q.get(k, math.nan) for q in noise], dtype=float)
        modelled = bool(np.all(np.isfinite(nsd) & (nsd > 0)))
        w = 1.0 / nsd ** 2 if modelled else np.ones(n)
        w = w / w.sum()
        t = by_name.get(k)
        mx = float(np.sum(w * xs))
        mean[k] = t.to_x(float(np.sum(w * [t.to_z(float(x)) for x in xs]))) if t is not None else mx
        if k in names:
            sd[k] = float(np.std(xs, ddof=1))
            # weighted sample standard error (plain sd / sqrt(n) for equal weights)
            se[k] = math.sqrt(max(float(np.sum(w * (xs - mx) ** 2)) * n / (n - 1), 0.0) * float(np.sum(w ** 2)))
            if modelled:
                se[k] = max(se[k], 1.0 / math.sqrt(float(np.sum(1.0 / nsd ** 2))))
    drift = {k: float((pts[-1][k] - pts[0][k]) / (n - 1)) for k in keys if k in names}
    return mean, drift, sd, se


def _averaged_count(planned: int, average_from: int) -> int:
    """How many polish points the result averages when the polish runs its `planned` steps
    (points `average_from` .. `planned`; 1 when `average_from` is 0: the last point). A polish
    that goes on past its plan keeps this many of its last points (`_average_from`), and its
    noise test looks at this many of its last steps (`_gn_polish`'s `keep_last`)."""
    return max(1, planned - average_from + 1) if average_from > 0 else 1


def _average_from(n_accepted: int, planned: int, average_from: int) -> int:
    """The first polish point to average (1-based; 0: none): `average_from`, or, for a polish
    that went on past its `planned` steps (still walking), the first of its last
    `_averaged_count` points."""
    if average_from > 0 and n_accepted > planned:
        return n_accepted - _averaged_count(planned, average_from) + 1
    return average_from


def _gn_polish(fm: ForwardModel, problem: Problem, params: Mapping[str, float], names: Sequence[str],
               tr: Sequence[Transform], *, steps: int, spp: int, jacobian_spp: int, seed: int,
               delta_nodes: Sequence[float], reference_delta_rel: float, fixed_scale: float | None,
               solved: Sequence[str] = (), solved_columns: Mapping[str, np.ndarray] | None = None,
               smooth_px: float = 3.0, exact: Collection[str] = (), caps: np.ndarray | None = None,
               scale_guess: float | None = None, jacobian_every: int = 1, gross: float = 1.0,
               cross: bool = False, max_steps: int | None = None, chi2_continue: float = math.inf,
               keep_last: int = 3, settled_spp_factor: int = 1,
               jacobians_out: list[list[dict[str, np.ndarray]]] | None = None
               ) -> tuple[dict[str, float], list[dict[str, Any]], tuple[np.ndarray, np.ndarray] | None]:
    """Full Gauss-Newton steps on the delta-averaged log loss at high samples per pixel, from
    the end of the stochastic iterations.

    Each step: the matrix of a smoothed finite-difference Jacobian at `jacobian_spp` (as in
    `_gn_inverse`, averaged over `delta_nodes`, relative deltas; re-estimated every
    `jacobian_every` steps) and the gradient 2/n A^T r from the mean log residual of two
    renders at `spp` with new seeds; the step -H^-1 g is capped per component at `caps` (z).
    With `cross`, two independent Jacobians at `jacobian_spp` / 2 (the same cost) give the
    matrix as their cross product (A1^T A2 + A2^T A1) / n, whose expectation lacks the
    Monte Carlo noise's Gram matrix that inflates A^T A (their mean gives the gradient's
    columns). The inflation is largest along the sigma_t / phase valley, where the true
    curvature is smallest, so one Jacobian's steps fall short there: from the benchmark's
    iteration end (sigma_t 2.39, truth 2.0), four steps ended at 2.01, 2.08 (two seeds), 2.09
    and 2.10 (two more with 2048-spp gradient renders) with one Jacobian, and at 2.02, 1.97,
    2.00, 1.96 and 2.01 with the (then unbounded) cross product (session 17; its first step
    goes most of the way, 2.39 -> 1.88-2.19). In the stochastic iterations
    the cross product made the fit diverge (session 4, 256 spp, unsmoothed; `_gn_inverse`);
    here the 3-px smoothing, the 512-spp halves, the caps and the acceptance test hold it.
    A step is halved (twice at most; then the polish stops) only when the loss without
    render noise (mean r_A r_B over the deltas) of the new point's renders rises by more
    than `gross` x the polish's starting loss plus 3 standard errors of the difference
    (from the pixels' products): a finer acceptance test does not work here. With the same
    seeds on both sides (common random numbers) the comparison rejected steps that fresh renders showed
    to be good (benchmark, session 16: sigma_t stuck at 2.29 where three unchecked steps
    went 2.37 -> 2.24 -> 2.12 -> 2.06), and with new seeds the estimator scatters by about
    the loss itself near the optimum (it can be negative there).
    Additive parameters in `solved` and a free scale are solved on every pair of renders,
    as in the iterations.

    Why: the stochastic Gauss-Newton steps cross the sigma_t / phase valley slowly, because
    along it the averaged gradient is mostly Monte Carlo noise and the steps are shrunk
    accordingly; at 2 x 1024 spp with a 1024-spp Jacobian the same steps, unshrunk, walk
    down it (benchmark, session 16, from the fit's end at sigma_t 2.226: 2.157, 2.105,
    2.065 in three steps; truth 2.0).

    Each step's size is tested against its own Monte Carlo noise: `step_chi2` = dz^T C^-1 dz
    with C = H^-1 S H^-1 the covariance of the step from the gradient's render noise (S from
    each pixel's two-render difference (r_A - r_B) / 2, pixels taken as independent). At the
    optimum a step is that noise alone and its chi^2 is about the number of parameters; a
    step well above it is still a move. While the last `keep_last` accepted steps are not
    all below `chi2_continue`, the polish goes on past `steps`, up to `max_steps` in all, so
    the points that `_polish_average` keeps have stopped walking (the benchmark at seed 3,
    session 17: b2 -0.72 -> -0.56 -> -0.24 -> +0.40 in four steps, truth 1.0, and sigma_t 6 %
    high from their mean). The noise model leaves out the matrix's own noise and the pixels'
    correlations, so steps at the noise floor run somewhat above the parameter count: on the
    benchmark (5 parameters, session 18) 1.6-11 (median ~7), walks 50-1240. At the 1 %
    quantile (15.1) the off-grid session's polish read steps of 15-30 as moves, went on to 8
    steps and wandered up its flat valley (points 2.35 -> 2.58, truth 2.4, result 5.7 %
    high, where the planned four steps' mean was 0.6 % low); the fit uses the 0.1 % quantile
    (20.5). There, too, that session's steps 4-6 had chi^2 21-39 and the polish went on to 8
    steps (2.7 % high; four steps' mean 3.0 % low): on its flat valley the steps scatter more
    than this noise model says.

    Settled steps (`settled_spp_factor` > 1): after a step whose chi^2 is at most
    `chi2_continue` (the point moved by no more than its noise), the new point's renders are
    taken at `settled_spp_factor` x `spp`, and the next step keeps the last Jacobians instead
    of rendering new ones. Near the optimum a point's scatter is the gradient's render noise
    taken through H^-1 (`noise_sd`), while a matrix error only scales the remaining distance,
    which is then within the noise; yet the Jacobians were ~80 % of a step's renders (for exp3
    2 x 10 at 512 spp against two gradient renders at 1024). A settled step at 4x the spp costs
    ~30 % less than a new-matrix step, and its point scatters half as much. A step that turns
    out a move is followed by new Jacobians at `spp`. "Noise-sized" is judged on the scale of
    `spp` (chi^2 x spp / the step's spp): the first settled step is expected to exceed its
    own, 4x smaller noise, since it starts from a point that carries the coarser steps'
    scatter; read as a move, it sent the benchmark's polish back and forth between the two
    kinds of step up to its 8 steps. Whether the polish goes on past `steps` is judged on
    each step's own noise, so it goes on until the settled steps are noise-sized too.
    Off in `FitSettings` (session 19, benchmark seeds 0-2 with the factor 4: sigma_t +2.7,
    +1.0, +3.5 %; the settled points agreed within 1-2 % of each other but not with the
    truth, and one fit's error was 3.2x its smaller uncertainty; the default's seeds 0-2 in
    session 18: +1.1, +0.9, +1.0 %). No gain in accuracy or time was shown.

    Returns the parameters, per step {loss, loss_new, accepted, halvings, step (x units),
    step_chi2 (of the full step, before caps and halvings), jacobians (new Jacobians
    rendered for it), spp (of its gradient's renders), and when accepted, point: the stepped
    and solved parameters after it, and noise_sd}, and the last pair of renders (A, B; with
    the solved additive terms) at the returned parameters. `jacobians_out` receives the
    Jacobians rendered for each step that rendered any (the uncertainties reuse the last
    ones: `sandwich_uncertainties`).
    """
    valid, meas, angles = problem.valid, problem.measured, problem.angles_deg
    n_v = max(1, int(valid.sum()))
    cols_out = list((solved_columns or {}).values())

    def state(p_in: Mapping[str, float], k: int, spp_k: int
              ) -> tuple[dict[str, float], np.ndarray, np.ndarray, float, tuple[float, float]]:
        """Renders A, B at `p_in` (seeds of step k, `spp_k` each), the solved values and scale,
        and the loss without render noise with its standard error."""
        p = dict(p_in)
        pa = fm.render_profiles(p, angles, spp=spp_k, seed=seed + 2 * k)
        pb = fm.render_profiles(p, angles, spp=spp_k, seed=seed + 2 * k + 1)
        if solved:
            shift = _solve_additive(fm, problem, p, solved, 0.5 * (pa + pb), reference_delta_rel, fixed_scale,
                                    scale_guess=scale_guess, columns=solved_columns)
            pa, pb = pa + shift, pb + shift
        sc = fixed_scale if fixed_scale is not None else profile_scale(meas, 0.5 * (pa + pb), valid,
                                                                        reference_delta_rel, guess=scale_guess)
        per_delta = np.array([decorrelated_loss_se(meas, pa, pb, valid, sc, q) for q in delta_nodes])
        return p, pa, pb, sc, (float(per_delta[:, 0].mean()), float(per_delta[:, 1].mean()))

    def noise_sized(chi2: float, spp_step: int) -> bool:
        """A step no larger than its noise on the scale of `spp` (a settled step's chi^2 is
        measured against its own, spp_step / spp times smaller noise)."""
        return chi2 * spp / spp_step <= chi2_continue

    if steps <= 0:
        return dict(params), [], None
    max_steps = steps if max_steps is None else max(steps, max_steps)
    spp_now = spp
    p, pa, pb, sc, (loss, se) = state(params, 0, spp_now)
    loss_start = loss
    trace: list[dict[str, Any]] = []
    jac: dict[str, np.ndarray] = {}
    jac_b: dict[str, np.ndarray] | None = None
    for k in range(max_steps):
        if k >= steps:
            recent = [e for e in trace if e["accepted"]][-max(1, keep_last):]
            if all(e["step_chi2"] <= chi2_continue for e in recent):
                break
        z = np.array([t.to_z(p[n]) for n, t in zip(names, tr)])
        new_jacobians = 0
        settled = (settled_spp_factor > 1 and bool(jac) and bool(trace) and trace[-1]["accepted"]
                   and noise_sized(trace[-1]["step_chi2"], trace[-1]["spp"]))
        if k % jacobian_every == 0 and not settled:
            if cross:
                half = max(1, jacobian_spp // 2)
                jac_a = _gn_jacobian(fm, problem, p, names, spp=half, seed=seed + 1000 + k)
                jac_b = _gn_jacobian(fm, problem, p, names, spp=half, seed=seed + 5000 + k)
                new_jacobians = 2
                jac = {n: 0.5 * (jac_a[n] + jac_b[n]) for n in names}
            else:
                jac = _gn_jacobian(fm, problem, p, names, spp=jacobian_spp, seed=seed + 1000 + k)
                jac_a, jac_b = jac, None
                new_jacobians = 1
            if jacobians_out is not None:
                jacobians_out.append([jac_a] if jac_b is None else [jac_a, jac_b])
        m = meas / sc
        m_max = float(np.max(np.where(valid, m, -np.inf)))
        mean = 0.5 * (pa + pb)
        dls = [max(q * m_max, 1e-30) for q in delta_nodes]
        g = np.zeros(len(names))
        # Per pixel, the gradient's share of the renders' noise: one draw of it from the two
        # renders' difference (the same noise drives every delta node, so they add up first).
        u = np.zeros((meas.size, len(names)))
        for d in dls:
            A = _gn_columns(jac, names, tr, z, problem, mean, d, m, fixed_scale is None, cols_out, smooth_px, exact)
            mm = np.log(np.clip(m, -0.5 * d, None) + d)
            ra, rb = (np.where(valid, mm - np.log(np.clip(q, 0.0, None) + d), 0.0) for q in (pa, pb))
            g += 2.0 * (A.T @ (0.5 * (ra + rb)).ravel()) / n_v / len(dls)
            u += 2.0 * A * (0.5 * (ra - rb)).ravel()[:, None] / n_v / len(dls)
        h_inv = _gn_inverse(jac_a, names, tr, z, problem, mean, dls, m, fixed_scale is None,
                            profiled_columns=cols_out, smooth_px=smooth_px, exact=exact, jac_cross=jac_b)
        dz = -(h_inv @ g)
        c_dz = h_inv @ (u.T @ u) @ h_inv.T
        step_chi2 = float(dz @ np.linalg.pinv(c_dz, rcond=1e-10, hermitian=True) @ dz)
        if caps is not None:
            dz = np.clip(dz, -caps, caps)
        entry: dict[str, Any] = {"loss": loss, "loss_new": float("nan"), "accepted": False, "halvings": 0,
                                 "step": {}, "step_chi2": step_chi2, "jacobians": new_jacobians, "spp": spp_now}
        trace.append(entry)
        for halving in range(3):
            z_new = np.array([t.clamp_z(float(zz + d_)) for t, zz, d_ in zip(tr, z, dz)])
            p_try = dict(p)
            p_try.update({n: t.to_x(float(zz)) for n, t, zz in zip(names, tr, z_new)})
            dz = 0.5 * dz
            try:
                p_try = fm.validate(p_try)
            except ModelParameterError:
                continue
            # The new point's renders: at the settled spp when this step is noise-sized (the
            # next one will be a settled step), else at `spp`.
            spp_new = spp * settled_spp_factor if noise_sized(step_chi2, spp_now) else spp
            p_new, pa_n, pb_n, sc_n, (loss_n, se_n) = state(p_try, k + 1, spp_new)
            entry.update(loss_new=loss_n, halvings=halving)
            # Undone (halved, twice at most) only when the rise exceeds the polish's starting
            # loss plus 3 standard errors of the difference: the estimator scatters by about
            # the loss itself near the optimum, and can be negative there.
            if loss_n - loss <= gross * max(loss_start, 0.0) + 3.0 * math.hypot(se, se_n):
                # The point's own Monte Carlo scatter: a full Gauss-Newton step lands at the
                # optimum plus the step's noise, whose z-space covariance is c_dz (halved with
                # the step), taken to x units at the new point.
                sd_z = np.sqrt(np.clip(np.diag(c_dz), 0.0, None)) * 0.5 ** halving
                entry.update(accepted=True, step={n: float(p_new[n] - p[n]) for n in names},
                             point={n: float(v) for n, v in p_new.items() if n in names or n in solved},
                             noise_sd={n: float(sd * abs(t.dx_dz(float(zz))))
                                       for n, t, sd, zz in zip(names, tr, sd_z, z_new)})
                p, pa, pb, sc, loss, se, spp_now = p_new, pa_n, pb_n, sc_n, loss_n, se_n, spp_new
                scale_guess = sc
                break
        if not entry["accepted"]:
            break
    return p, trace, (pa, pb)


def evaluate(fm: ForwardModel, problem: Problem, params: Mapping[str, float], *, spp: int, seed: int,
             delta_rel: float, fixed_scale: float | None = None,
             additive: Sequence[str] = ()) -> dict[str, Any]:
    """Profiles (mean of two seeds), their MC variance, scale (profiled unless `fixed_scale`),
    loss (of the mean profile), the loss without its Monte Carlo variance term
    (`loss_unbiased`, `estimate.loss.decorrelated_loss` of the two seeds), chi^2, and the
    parameters ("parameters": `params`, with the `additive` ones solved on these renders at
    `delta_rel`, see `_solve_additive`)."""
    p1 = fm.render_profiles(params, problem.angles_deg, spp=spp, seed=seed)
    p2 = fm.render_profiles(params, problem.angles_deg, spp=spp, seed=seed + 7_777)
    params = dict(params)
    if additive:
        shift = _solve_additive(fm, problem, params, additive, 0.5 * (p1 + p2), delta_rel, fixed_scale)
        p1, p2 = p1 + shift, p2 + shift
    prof = 0.5 * (p1 + p2)
    mvar = 0.25 * (p1 - p2) ** 2
    # One pixel's two-sample variance estimate is itself very noisy: smooth it along x.
    k = np.ones(5) / 5.0
    mvar = np.stack([np.convolve(r, k, mode="same") for r in mvar])
    s = fixed_scale if fixed_scale is not None else profile_scale(problem.measured, prof, problem.valid, delta_rel)
    loss = log_loss(problem.measured, prof, problem.valid, s, delta_rel)[0]
    unbiased = decorrelated_loss(problem.measured, p1, p2, problem.valid, s, delta_rel)
    c2 = chi2(problem.measured, problem.variance, prof, problem.valid, s, mvar)
    return {"profiles": prof, "model_variance": mvar, "scale": s, "loss": loss, "loss_unbiased": unbiased,
            "chi2": c2, "parameters": params}


def _solve_additive(fm: ForwardModel, problem: Problem, params: dict[str, float], names: Sequence[str],
                    mean: np.ndarray, delta_rel: float, fixed_scale: float | None,
                    scale_guess: float | None = None, columns: Mapping[str, np.ndarray] | None = None
                    ) -> np.ndarray:
    """Set the additive parameters `names` in `params` (in place) to their log-loss optimum
    for the render `mean` (made with the old values; with a free scale, the scale and
    they are solved in turn, twice) and return what that adds to the render (N, W).
    `columns`: their `ForwardModel.additive_columns`, when the caller has them."""
    cols = columns if columns is not None else fm.additive_columns(params, len(problem.angles_deg), names)
    bounds = {n: (fm.specs[n].lower, fm.specs[n].upper) for n in names}
    old = {n: float(params[n]) for n in names}
    cur = dict(old)
    shift = np.zeros_like(mean)
    s = fixed_scale
    for _ in range(1 if fixed_scale is not None else 2):
        if fixed_scale is None:
            s = profile_scale(problem.measured, mean + shift, problem.valid, delta_rel, guess=scale_guess)
        assert s is not None
        cur = profile_additive(problem.measured, mean, problem.valid, s, delta_rel, cols, old, bounds)
        shift = sum(((cur[n] - old[n]) * cols[n] for n in names), np.zeros_like(mean))
    params.update(cur)
    return shift


def _jacobian_columns(fm: ForwardModel, problem: Problem, params: Mapping[str, float], names: Sequence[str],
                      *, spp: int, seed: int) -> dict[str, np.ndarray]:
    return fm.jacobian(params, problem.angles_deg, list(names), spp=spp, seed=seed)


def fisher_uncertainties(fm: ForwardModel, problem: Problem, params: Mapping[str, float],
                         names: Sequence[str], scale: float, model_variance: np.ndarray,
                         profiles: np.ndarray, *, spp: int, seed: int, inflate: float = 1.0,
                         fit_scale: bool = True, jac: Mapping[str, np.ndarray] | None = None
                         ) -> tuple[dict[str, float], float]:
    """1-sigma uncertainties of `names` and of the scale from the Gauss-Newton Fisher matrix
    of the linear chi^2 (the bound of an ideal variance-weighted fit; the log-loss fit is
    not that fit, see `sandwich_uncertainties`). Scale uncertainty NaN when not fitted."""
    jac = jac if jac is not None else _jacobian_columns(fm, problem, params, names, spp=spp, seed=seed)
    w = np.where(problem.valid, 1.0 / (problem.variance + scale ** 2 * model_variance), 0.0)
    w = np.where(np.isfinite(w), w, 0.0).ravel()
    cols = [scale * jac[n].ravel() for n in names] + ([profiles.ravel()] if fit_scale else [])
    J = np.stack(cols, axis=1)
    F = J.T @ (J * w[:, None])
    try:
        cov = np.linalg.pinv(F, rcond=1e-12) * max(1.0, inflate)
    except np.linalg.LinAlgError:
        return {n: float("nan") for n in names}, float("nan")
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return {n: float(sd[i]) for i, n in enumerate(names)}, (float(sd[-1]) * (1.0 if fit_scale else float("nan")))


#: Smallest generalised eigenvalue of the uncertainties' cross-product curvature against the
#: matrix of the Jacobians' mean (`sandwich_uncertainties`, `bounded_cross`).
UNCERTAINTY_CROSS_FLOOR = 0.1


def sandwich_uncertainties(problem: Problem, params: Mapping[str, float], names: Sequence[str], scale: float,
                           profiles: np.ndarray, model_variance: np.ndarray, jac: Mapping[str, np.ndarray],
                           *, delta_rel: float, fit_scale: bool, render_variance_factor: float = 2.0,
                           covariance_out: dict[str, dict[str, float]] | None = None,
                           jac_more: Sequence[Mapping[str, np.ndarray]] = (),
                           cross_floor: float = UNCERTAINTY_CROSS_FLOOR
                           ) -> tuple[dict[str, float], float, float]:
    """1-sigma uncertainties of the log-loss estimator (sandwich), its scale's, and the
    log-space reduced chi^2. With `covariance_out`, the full covariance of `names` (the
    uniformly inflated sandwich, before the diagonal choice below) is written into it.

    With `jac_more`, further Jacobians with independent render noise (at the same point or
    one within the fit's noise of it), the curvature is the mean of the pairs' cross
    products (A_i^T A_j + A_j^T A_i) / 2, held between `cross_floor` x and 1 x the matrix of
    the Jacobians' mean (`bounded_cross`), and so is the meat (A_i^T S A_j, S the
    residuals' noise variance). One Monte Carlo Jacobian's A^T A carries the noise's own
    Gram matrix, which dominates where the true curvature is weakest, along the sigma_t /
    phase valley. On the paper simulation's d 0.5 um / sigma_t 6 fit (session 20) a
    512-spp Jacobian's two weakest eigenvalues were 5x those of a 4096-spp one, and two
    4096-spp Jacobians' cross product put them at 0.13 and 0.19 of their mean's; the
    single 512-spp Jacobian gave sigma_t a sandwich of 0.013-0.014 /mm, the 4096-spp pair
    0.24, four 512-spp ones 0.26. The fit was 0.71 /mm off, and a fit with sigma_t held at
    the truth reached the same loss. Where a direction's cross-product eigenvalue falls
    below the floor the Jacobians' noise does not resolve its curvature, and the interval
    there is the floor's: about 1 / sqrt(floor) x what the Jacobians' mean alone would give.

    The fit minimises sum r^2 with r = log(m/s + delta) - log(I + delta), so its covariance
    is H^-1 (A^T S A) H^-1 with A = dr/d(theta, log s), H = A^T A (Gauss-Newton curvature
    of the log loss) and S the covariance of r: the sensor noise var_m / (m + s delta)^2
    plus the Monte Carlo noise of the render the polish used (`render_variance_factor` x
    the variance of the two-seed mean in `model_variance`: one render at the same spp)
    / (I + delta)^2, independent per pixel. The result is multiplied by
    max(1, chi^2_log / dof), chi^2_log = sum r^2 / S: residuals larger than the noise
    (model error, correlated Monte Carlo structure in the data) widen the intervals.

    Where the residuals exceed the noise, the robust (White / HC0) sandwich with the
    residuals themselves in the meat, H^-1 (A^T diag(r^2) A) H^-1, is used when it is
    smaller: a uniform inflation by the reduced chi^2 assumes the excess has the noise's
    pattern, but excess concentrated in the tails (frozen Monte Carlo noise of a simulated
    truth, 2900x the sensor variance there) widened sigma_t's interval to 17 % for a fit
    3 % off. With `jac_more` its meat is the cross products A_i^T diag(r^2) A_j too: the
    Jacobians' mean carries their noise's Gram matrix, weighted by the large residuals,
    on top of a curvature that the cross products have freed of that noise.
    """
    valid = problem.valid
    m = problem.measured / scale
    dl = max(delta_rel * float(np.max(np.where(valid, m, -np.inf))), 1e-30)
    mm = np.clip(m, -0.5 * dl, None)
    ip = np.clip(profiles, 0, None)
    r = np.where(valid, np.log(mm + dl) - np.log(ip + dl), 0.0)
    var_r = (problem.variance / scale ** 2) / (mm + dl) ** 2 + render_variance_factor * model_variance / (ip + dl) ** 2
    var_r = np.where(valid & np.isfinite(var_r), var_r, 0.0)

    def columns(j: Mapping[str, np.ndarray]) -> np.ndarray:
        cols = [np.where(valid, -j[n] / (ip + dl), 0.0).ravel() for n in names]
        if fit_scale:
            cols.append(np.where(valid, -m / (mm + dl), 0.0).ravel())
        return np.where(np.isfinite(a := np.stack(cols, axis=1)), a, 0.0)

    As = [columns(j) for j in (jac, *jac_more)]
    A = np.mean(As, axis=0)
    pairs = [(a, b) for i, a in enumerate(As) for b in As[i + 1:]]

    def gram(w: np.ndarray) -> np.ndarray:
        """A^T diag(w) A: with several Jacobians, their pairs' cross products bounded by the mean's."""
        mean_gram = A.T @ (A * w[:, None])
        if not pairs:
            return mean_gram
        cross = sum(a.T @ (b * w[:, None]) + b.T @ (a * w[:, None]) for a, b in pairs) / (2 * len(pairs))
        return bounded_cross(cross, mean_gram, cross_floor)

    H, meat = gram(np.ones(A.shape[0])), gram(var_r.ravel())
    n = int(valid.sum())
    dof = max(1, n - A.shape[1])
    c2 = float(np.sum(np.where(var_r > 0, r * r / np.where(var_r > 0, var_r, 1.0), 0.0)))
    red = c2 / dof
    try:
        Hi = np.linalg.pinv(H, rcond=1e-12)
    except np.linalg.LinAlgError:
        return {k: float("nan") for k in names}, float("nan"), red
    cov = Hi @ meat @ Hi * max(1.0, red)
    if covariance_out is not None:
        covariance_out.update({a: {b: float(cov[i, j]) for j, b in enumerate(names)} for i, a in enumerate(names)})
    if red > 1.0:
        robust = Hi @ gram(r.ravel() ** 2) @ Hi
        modelled = Hi @ meat @ Hi
        # never below the noise-only sandwich, never above the uniformly inflated one
        d = np.clip(np.diag(robust), np.diag(modelled), np.diag(cov))
        cov = np.diag(d)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    s_unc = float(sd[-1]) * scale if fit_scale else float("nan")
    return {k: float(sd[i]) for i, k in enumerate(names)}, s_unc, red


#: Drift t-statistic above which a parameter counts as still moving when the fit stopped.
#: Successive iterates are correlated (gradient momentum), so the naive standard error is
#: too small by ~2-3x; 5 keeps the flag for drifts several times their noise.
DRIFT_T = 5.0


def _drift(history: Sequence[Sequence[float]], names: Sequence[str],
           window: int) -> tuple[dict[str, float], list[str]]:
    """Per parameter: mean of the last `window` iterates minus the mean of the `window`
    iterates two windows earlier (parameter units), and the names whose drift exceeds
    `DRIFT_T` standard errors (from the scatter within the two windows).

    The flattening rule stops when the loss no longer falls by more than its noise, which
    happens along the sigma_t / phase valley while the iterates still move steadily: on the
    one-channel benchmark sigma_t fell 2.34 -> 2.29 between those windows (truth 2.0) with a
    scatter of ~0.01 inside each. Empty when there are fewer than 3 windows of iterates."""
    if len(history) < 3 * window or window < 2:
        return {}, []
    xs = np.array(history[-3 * window:], dtype=np.float64)
    a, b = xs[-window:], xs[:window]
    d = a.mean(axis=0) - b.mean(axis=0)
    se = np.sqrt(a.var(axis=0, ddof=1) / window + b.var(axis=0, ddof=1) / window)
    drift = {n: float(d[i]) for i, n in enumerate(names)}
    moving = [n for i, n in enumerate(names) if se[i] > 0 and abs(d[i]) > DRIFT_T * se[i]]
    return drift, moving


def _window_estimate(rows: Sequence[Sequence[float]] | Sequence[np.ndarray], trend: bool) -> np.ndarray:
    """The result from the last iterates (rows): their mean, or with `trend` the value at the
    last row of a straight line fitted to each column (least squares), which removes the
    mean's lag behind iterates that drift steadily."""
    xs = np.asarray(rows, dtype=np.float64)
    if not trend or len(xs) < 3:
        return xs.mean(axis=0)
    t = np.arange(len(xs), dtype=np.float64)
    slope, icpt = np.polyfit(t, xs, 1)
    return icpt + slope * t[-1]


def _window_scatter(rows: Sequence[Sequence[float]], trend: bool) -> np.ndarray:
    """The iterates about their summary (`_window_estimate`): minus the mean, or minus their
    linear trend, so a steady drift is not counted as the optimiser's scatter."""
    xs = np.asarray(rows, dtype=np.float64)
    if not trend or len(xs) < 3:
        return xs - xs.mean(axis=0)
    t = np.arange(len(xs), dtype=np.float64)
    slope, icpt = np.polyfit(t, xs, 1)
    return xs - (icpt + np.outer(t, slope))


def _combined_uncertainties(base: Mapping[str, float], spread: Mapping[str, float],
                            polish_se: Mapping[str, float], drift: Mapping[str, float],
                            polish_sd: Mapping[str, float], *, polished: bool) -> tuple[dict[str, float], list[str]]:
    """The reported 1-sigma uncertainties (parameter units) and the names still moving.

    `base` (the larger of the sandwich and the Fisher bound), the iterates' `spread` and the
    averaged polish points' standard error `polish_se` add in quadrature. A parameter still
    moving when the fit stopped is at least its `drift` from the optimum, so the drift is
    added too, with one exception. When the result is the mean of several polish points
    (`polish_se` has the name), those points scatter about the optimum by their render noise
    and their mean step (the drift) is, unless it stands out of that scatter (`polish_sd`),
    the same scatter again: for three independent points its standard deviation is 0.71 of
    one point's, more than the mean's standard error (0.58) that already holds it. Such a
    drift is neither added nor flagged (session 23; on four noise draws of the benchmark
    truth adding it widened sigma_t's interval by 0-23 %; the errors were 0.22-0.94 of the
    interval without it). Without averaged points (one polish step's point, or none) the
    drift is the only measure of the last move and is always added; there `polished`
    decides only whether the names are flagged here (the iterations flag their own).
    """
    unc: dict[str, float] = {}
    moving: list[str] = []
    for n, b in base.items():
        u = math.hypot(b, spread.get(n, 0.0), polish_se.get(n, 0.0))
        if n in drift:
            stands_out = abs(drift[n]) > math.hypot(u, polish_sd.get(n, 0.0))
            if polished and stands_out:
                moving.append(n)
            if stands_out or n not in polish_se:
                u = math.hypot(u, drift[n])
        unc[n] = u
    return unc, moving


def _covariance(names: Sequence[str], unc: Mapping[str, float], sandwich: Mapping[str, Mapping[str, float]],
                iterate_cov: np.ndarray) -> dict[str, dict[str, float]]:
    """Full covariance whose diagonal is the reported uncertainties squared and whose
    correlations are those of the sandwich covariance plus the averaged iterates' own
    covariance (the two sources of error the uncertainties combine)."""
    k = len(names)
    c = np.array([[float(sandwich.get(a, {}).get(b, 0.0)) for b in names] for a in names]) if sandwich \
        else np.zeros((k, k))
    c = np.where(np.isfinite(c), c, 0.0) + iterate_cov
    d = np.sqrt(np.clip(np.diag(c), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = np.where(np.outer(d, d) > 0, c / np.outer(d, d), 0.0)
    np.fill_diagonal(corr, 1.0)
    corr = np.clip(corr, -1.0, 1.0)
    sd = np.array([float(unc[n]) for n in names])
    full = corr * np.outer(sd, sd)
    return {a: {b: float(full[i, j]) for j, b in enumerate(names)} for i, a in enumerate(names)}


def fit_channel(problem: Problem, model: str = "exp3", *, extensions: Sequence[str] = (),
                start: Mapping[str, float] | None = None, fixed: Mapping[str, float] | None = None,
                settings: FitSettings | None = None, forward: ForwardModel | None = None,
                progress: Callable[[int, float, int], None] | None = None,
                scale_calibration: ScaleCalibration | None = None) -> FitResult:
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
        progress: called as progress(iteration, reference loss, spp).
        scale_calibration: the measured scale for `settings.scale == "calibrated"` (else
            `estimate.loss.calibrated_scale` of the problem's session).

    Raises:
        DataError: calibrated scale without a beam power in the session's calibration.
    """
    st = settings or FitSettings()
    t0 = time.monotonic()
    stage_times: dict[str, float] = {}
    t_stage = t0

    def stage_done(name: str) -> None:
        nonlocal t_stage
        now = time.monotonic()
        stage_times[name] = stage_times.get(name, 0.0) + now - t_stage
        t_stage = now
    phase = model_phase(model)
    fm = forward or ForwardModel(problem.geometry, problem.beam, phase=phase, extensions=extensions,
                                 profile_y_shape=problem.y_shapes())
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
    # iteration's render (`_solve_additive`, like a free scale) instead of being stepped: as
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
    # Columns the Jacobian gets exactly (image-space parameters) carry no Monte Carlo noise to smooth away.
    exact_columns = {n for n in stepped if fm.derivative_kind(n) == "image"}
    gn_nodes = [math.exp(lo + (k + 0.5) / st.gn_delta_nodes * (hi - lo)) for k in range(st.gn_delta_nodes)]
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
                shift = _solve_additive(fm, problem, p, solved, 0.5 * (pa + pb_), delta_rel, fixed_scale,
                                        scale_guess=scale, columns=solved_cols)
                pa, pb_ = pa + shift, pb_ + shift
                # (The linearizations keep the previous additive values: the last image-space
                # effect adds them, so the pull-back through the chain does not depend on them.)
                sol.update({n: p[n] for n in solved})
            mean = 0.5 * (pa + pb_)
            if fixed_scale is None:
                scale = profile_scale(problem.measured, mean, problem.valid, delta_rel, guess=scale)
            curve_loss = log_loss(problem.measured, mean, problem.valid, scale, d_ref)[0]
            m = problem.measured / scale
            dl = max(delta_rel * float(np.max(np.where(problem.valid, m, -np.inf))), 1e-30)
            mm = np.log(np.clip(m, -0.5 * dl, None) + dl)
            ra = np.where(problem.valid, mm - np.log(np.clip(pa, 0, None) + dl), 0.0)
            rb = np.where(problem.valid, mm - np.log(np.clip(pb_, 0, None) + dl), 0.0)
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
                gn_jac = _gn_jacobian(fm, problem, p, stepped, spp=st.gn_jacobian_spp,
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
            h_inv = _gn_inverse(gn_jac, stepped, tr, z, problem, mean, gn_dl, m, fixed_scale is None,
                                profiled_columns=list(solved_cols.values()), smooth_px=st.gn_smooth_px,
                                exact=exact_columns)
            gn_grads.append(g)
            recent = gn_grads[-2 * st.window:]
            gn_trace.append([it, *_predicted_decrease(h_inv, g_avg, recent, st.gn_momentum)])
            dz = -st.gn_step * (_snr_step(h_inv, g_avg, recent, st.gn_momentum) if st.gn_snr else h_inv @ g_avg)
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
        if st.time_limit_s is not None and time.monotonic() - t0 > st.time_limit_s:
            stop = "time_limit"
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
    drift, drifting = _drift(x_history, names, st.window)
    # Iterates that still drift are summarised by the end of their linear trend: their mean
    # lags the last iterate by half the window's drift (the benchmark, seed 0: mean of the
    # last 16 iterates sigma_t 2.172, last iterate 2.126, trend end 2.115; truth 2.0).
    trend = bool(drifting) and n_avg >= 4
    z_final = _window_estimate(history[-n_avg:], trend) if history else z
    if x_history:
        x_end = _window_estimate(x_history[-n_avg:], trend)
        sol.update({n: float(x_end[names.index(n)]) for n in solved})
    final = params_of(z_final)
    stage_done("iterations")
    polish: list[dict[str, Any]] = []
    polish_jacobians: list[list[dict[str, np.ndarray]]] = []
    if st.polish_steps > 0 and stepped:
        caps = 5.0 * adam.lr / st.lr_scale     # the iterations' step cap
        final, polish, _ = _gn_polish(fm, problem, final, stepped, tr, steps=st.polish_steps, spp=st.final_spp,
                                   jacobian_spp=st.final_spp, seed=st.seed * 100_003 + 30_000,
                                   delta_nodes=gn_nodes or [d_ref], reference_delta_rel=d_ref,
                                   fixed_scale=fixed_scale, solved=solved, solved_columns=solved_cols,
                                   smooth_px=st.gn_smooth_px, exact=exact_columns, caps=caps, scale_guess=scale,
                                   jacobian_every=st.polish_jacobian_every, cross=st.polish_cross,
                                   max_steps=2 * st.polish_steps if st.polish_max_steps is None
                                   else st.polish_max_steps,
                                   chi2_continue=float(chi2_dist.isf(st.polish_continue_p, len(stepped))),
                                   keep_last=_averaged_count(st.polish_steps, st.polish_average_from),
                                   settled_spp_factor=st.polish_settled_spp, jacobians_out=polish_jacobians)
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
        first = _average_from(len(accepted), st.polish_steps, st.polish_average_from)
        averaged = _polish_average(accepted, names, tr, first)
        if averaged is not None:
            mean_point, drift, polish_sd, polish_se = averaged
            final = {**final, **mean_point}
            n_polish_avg = max(1, len(accepted) - first + 1)
    moving: list[str] = []
    lm_losses: list[float] = []
    if st.lm_iterations > 0:
        final, lm_losses = _lm_polish(fm, problem, final, stepped, tr, spp=st.lm_spp,
                                      seed=st.seed * 100_003 + 40_000, delta_rel=d_ref, iterations=st.lm_iterations,
                                      fixed_scale=fixed_scale)
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
        jac = _gn_jacobian(fm, problem, final, names, spp=st.uncertainty_spp, seed=st.seed * 100_003 + 60_000)
        more = [{**jac, **j} for js in polish_jacobians[-n_polish_avg:] for j in js] if n_polish_avg else []
        if not more:
            more = [_gn_jacobian(fm, problem, final, names, spp=st.uncertainty_spp, seed=st.seed * 100_003 + 65_000)]
        fisher, _ = fisher_uncertainties(fm, problem, final, names, ev["scale"], ev["model_variance"],
                                         ev["profiles"], spp=st.uncertainty_spp, seed=0, inflate=red,
                                         fit_scale=fixed_scale is None,
                                         jac={n: np.mean([j[n] for j in (jac, *more)], axis=0) for n in names})
        sandwich_cov: dict[str, dict[str, float]] = {}
        unc, s_unc, _ = sandwich_uncertainties(problem, final, names, ev["scale"], ev["profiles"],
                                               ev["model_variance"], jac, delta_rel=d_ref,
                                               fit_scale=fixed_scale is None,
                                               render_variance_factor=2.0 * st.final_spp / max(1, st.lm_spp),
                                               covariance_out=sandwich_cov, jac_more=more)
        sandwich = dict(unc)
        # never below the ideal linear-chi^2 bound
        unc = {k: max(v, fisher.get(k, 0.0)) for k, v in unc.items()}
        # The stochastic optimiser's own spread: the standard deviation of the averaged
        # iterates, added in quadrature. The curvature-based intervals describe the
        # minimum of the loss; along the sigma_t / phase valley the iterates wander by more
        # than that (synthetic benchmark: sandwich 0.006 /mm, error 0.057 /mm).
        xs = _window_scatter(x_history[-n_avg:], trend)
        it_cov = np.cov(xs, rowvar=False, ddof=2 if trend else 1).reshape(len(names), len(names)) \
            if len(xs) > 2 else np.zeros((len(names), len(names)))
        for i, n in enumerate(names):
            spread[n] = float(math.sqrt(max(it_cov[i, i], 0.0)))
        unc, moving = _combined_uncertainties(unc, spread, polish_se, drift, polish_sd, polished=polished)
        if polished:
            drifting = moving
        covariance = _covariance(names, unc, sandwich_cov, it_cov)
        stage_done("uncertainties")
    return FitResult(
        channel=problem.channel, model=phase, extensions=list(fm.extensions), parameters=final,
        uncertainties=unc, fixed=fixed, scale=ev["scale"], scale_uncertainty=s_unc, loss=ev["loss"],
        loss_unbiased=ev["loss_unbiased"],
        delta_rel=d_ref, chi2=ev["chi2"], dof=dof, reduced_chi2=red, iterations=it,
        time_s=time.monotonic() - t0, stop_reason=stop, spp_schedule=schedule, loss_curve=curve,
        angles_deg=[float(a) for a in problem.angles_deg], fitted=ev["profiles"], lm_losses=lm_losses,
        model_variance=ev["model_variance"], start=dict(init), settings=st.to_dict(), scale_mode=st.scale,
        scale_calibration=cal.to_dict() if cal is not None else None, fisher_uncertainties=fisher,
        optimizer_spread=spread, sandwich_uncertainties=sandwich,
        polish_se={k: float(v) for k, v in polish_se.items() if k in names}, gn_trace=gn_trace,
        covariance=covariance, drift=drift, drifting=drifting,
        solved=list(solved), polish=polish, stage_times_s={k: round(v, 2) for k, v in stage_times.items()})


def loss_at(problem: Problem, model: str, params: Mapping[str, float], *, extensions: Sequence[str] = (),
            spp: int = 1024, seed: int = 12_345, delta_range: tuple[float, float] = DEFAULT_DELTA_RANGE,
            forward: ForwardModel | None = None, fixed_scale: float | None = None) -> dict[str, Any]:
    """Loss / chi^2 of given parameters (e.g. the true ones: the noise floor), scale profiled
    unless `fixed_scale`."""
    fm = forward or ForwardModel(problem.geometry, problem.beam, phase=model_phase(model), extensions=extensions,
                                 profile_y_shape=problem.y_shapes())
    return evaluate(fm, problem, params, spp=spp, seed=seed, delta_rel=reference_delta(delta_range),
                    fixed_scale=fixed_scale)
