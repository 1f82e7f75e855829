"""The paper's log-intensity loss with a fitted scale, and the chi^2 of a fit.

    L(theta, s; delta) = mean_valid ( log(I_meas / s + delta) - log(I_model(theta) + delta) )^2

`I_meas` is in e-/s per pixel, `I_model` in the forward model's units, `s` the fitted scale
(measured = s * rendered). The paper normalised the mean of the image set to 1 instead; a
fitted scale does not tie the result to which pixels happen to be in the window and takes the
beam-power / gain / lens-transmission factor out of the fit cleanly (profiled out in 1-D at
every evaluation, so it costs no render).

Monte Carlo noise biases a log loss (E log(I_mc + delta) < log(E I_mc + delta), Jensen),
more where the render is relatively noisier, which depends on the parameters: at 64 spp the
minimum over the albedo of a test problem sat 0.15 below the truth, at >= 256 spp on it.
Hence the range's lower end (1 % of the peak, not the 0.1 % a noise-free render could take)
and an optimisation that ends at >= 512 spp.

`delta` is given relative to the data's intensity range: delta = delta_rel * max(I_meas / s).
A small delta weighs the dim tails (log space), a large one the bright core; the fit draws
delta_rel log-uniformly from `delta_range` at every iteration (the paper's alternation) so
no intensity range dominates. Convergence and reported loss values use the fixed geometric
mid-point `reference_delta(delta_range)`.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import minimize_scalar

__all__ = ["DEFAULT_DELTA_RANGE", "chi2", "log_loss", "profile_scale", "reference_delta"]

#: Range of delta relative to the (scaled) data maximum.
DEFAULT_DELTA_RANGE = (1e-2, 2e-1)


def reference_delta(delta_range: tuple[float, float] = DEFAULT_DELTA_RANGE) -> float:
    """Fixed relative delta for reported losses: geometric mean of the range."""
    return math.sqrt(delta_range[0] * delta_range[1])


def log_loss(measured: np.ndarray, model: np.ndarray, valid: np.ndarray, scale: float,
             delta_rel: float) -> tuple[float, np.ndarray]:
    """Loss value and its gradient with respect to `model` (same shape)."""
    m = measured / scale
    delta = delta_rel * float(np.max(np.where(valid, m, -np.inf)))
    delta = max(delta, 1e-30)
    n = max(1, int(valid.sum()))
    mm = np.clip(m, -0.5 * delta, None)  # a dark pixel's noise may dip below zero
    im = np.clip(model, 0.0, None)
    r = np.where(valid, np.log(mm + delta) - np.log(im + delta), 0.0)
    value = float(np.sum(r * r) / n)
    grad = np.where(valid & (model >= 0), -2.0 * r / (im + delta) / n, 0.0)
    return value, grad


def profile_scale(measured: np.ndarray, model: np.ndarray, valid: np.ndarray, delta_rel: float,
                  guess: float | None = None) -> float:
    """The scale s minimising the log loss for a fixed model (1-D bounded search in log s)."""
    sm = float(np.sum(np.where(valid, np.clip(model, 0, None), 0.0)))
    sd = float(np.sum(np.where(valid, measured, 0.0)))
    g0 = guess if guess and guess > 0 else (sd / sm if sm > 0 and sd > 0 else 1.0)
    lg = math.log(g0)

    def f(ls: float) -> float:
        return log_loss(measured, model, valid, math.exp(ls), delta_rel)[0]

    res = minimize_scalar(f, bounds=(lg - 3.0, lg + 3.0), method="bounded", options={"xatol": 1e-5})
    return float(math.exp(res.x))


def chi2(measured: np.ndarray, variance: np.ndarray, model: np.ndarray, valid: np.ndarray, scale: float,
         model_variance: np.ndarray | None = None) -> float:
    """sum_valid (I_meas - s I_model)^2 / (var_meas + s^2 var_model)."""
    var = np.where(valid, variance, np.inf)
    if model_variance is not None:
        var = var + scale ** 2 * model_variance
    r = (measured - scale * model) ** 2 / var
    return float(np.sum(np.where(valid, r, 0.0)))
