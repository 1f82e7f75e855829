"""One parameter point of a fit, rendered: `evaluate` renders the profiles at two seeds and
returns their mean, Monte Carlo variance, the intensity scale (profiled, or the calibrated
one), the log loss, the loss without its render-noise term and chi^2. Parameters that only
add a fixed image (stray light; `ForwardModel.additive_parameters`) are solved exactly on
those renders (`solve_additive`) rather than stepped by the optimiser.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from estimate.forward import ForwardModel
from estimate.loss import (
    chi2,
    decorrelated_loss,
    log_loss,
    profile_additive,
    profile_scale,
)
from estimate.problem import Problem

__all__ = ["evaluate", "jacobian_columns", "smoothed_along_rows", "solve_additive"]


def smoothed_along_rows(v: np.ndarray, width: int = 5) -> np.ndarray:
    """A per-pixel variance estimate (angles, pixels) averaged over `width` pixels along each
    row: one pixel's estimate from a few renders is itself very noisy."""
    k = np.ones(width) / width
    return np.stack([np.convolve(r, k, mode="same") for r in np.atleast_2d(v)])


def evaluate(fm: ForwardModel, problem: Problem, params: Mapping[str, float], *, spp: int, seed: int,
             delta_rel: float, fixed_scale: float | None = None,
             additive: Sequence[str] = ()) -> dict[str, Any]:
    """Profiles (mean of two seeds), their MC variance, scale (profiled unless `fixed_scale`),
    loss (of the mean profile), the loss without its Monte Carlo variance term
    (`loss_unbiased`, `estimate.loss.decorrelated_loss` of the two seeds), chi^2, and the
    parameters ("parameters": `params`, with the `additive` ones solved on these renders at
    `delta_rel`, see `solve_additive`)."""
    p1, p2 = fm.render_profiles_many([(params, seed), (params, seed + 7_777)], problem.angles_deg, spp=spp)
    params = dict(params)
    if additive:
        shift = solve_additive(fm, problem, params, additive, 0.5 * (p1 + p2), delta_rel, fixed_scale)
        p1, p2 = p1 + shift, p2 + shift
    prof = 0.5 * (p1 + p2)
    mvar = smoothed_along_rows(0.25 * (p1 - p2) ** 2)
    s = fixed_scale if fixed_scale is not None else profile_scale(problem.measured, prof, problem.valid, delta_rel)
    loss = log_loss(problem.measured, prof, problem.valid, s, delta_rel)[0]
    unbiased = decorrelated_loss(problem.measured, p1, p2, problem.valid, s, delta_rel)
    c2 = chi2(problem.measured, problem.variance, prof, problem.valid, s, mvar)
    return {"profiles": prof, "model_variance": mvar, "scale": s, "loss": loss, "loss_unbiased": unbiased,
            "chi2": c2, "parameters": params}


def solve_additive(fm: ForwardModel, problem: Problem, params: dict[str, float], names: Sequence[str],
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


def jacobian_columns(fm: ForwardModel, problem: Problem, params: Mapping[str, float], names: Sequence[str],
                     *, spp: int, seed: int) -> dict[str, np.ndarray]:
    return fm.jacobian(params, problem.angles_deg, list(names), spp=spp, seed=seed)
