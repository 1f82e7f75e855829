"""A starting point for the fit: coarse search over a few phase shapes x sigma_t x albedo
at low samples per pixel, each candidate scored by the log loss at the reference delta with
its scale profiled out (or the calibrated scale). Two stages: every candidate (220) is
screened at a quarter of `spp`, and the best `RESCORED` (12) are scored again at `spp`
(32). A render's cost is nearly proportional to its samples (10 angles on the session-17
machine: 0.034 s at 8 spp, 0.097 s at 32), so this costs ~9-15 s there against ~25-33 s for
the whole grid at 32 spp. On seven sessions x two models (the benchmark's, an off-grid one,
the demo's three channels, and the paper's two d 0.01 um cases, where a whole grid at 16 spp
had picked another node in session 13) it picked the whole 32-spp grid's node every time.

The renders are queued together (`ForwardModel.render_profiles_many`): at 8 spp a render is
mostly its tracing in Python, during which the previous ones' kernels run (session 59, 2 cores,
a 64-pixel window: 6.2-6.8 s against 8.0-9.1 s one by one, the same losses bit for bit).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from estimate.forward import ForwardModel
from estimate.loss import log_loss, profile_scale
from estimate.problem import Problem

__all__ = ["ALBEDO_GRID", "RESCORED", "SIGMA_GRID", "coarse_start", "phase_candidates", "start_loss"]

#: Extinction coefficients tried (1/mm): log-spaced over what a 1 mm slab's profiles can show.
SIGMA_GRID = tuple(float(x) for x in np.geomspace(0.5, 16.0, 11))
ALBEDO_GRID = (0.5, 0.7, 0.85, 0.95, 0.99)
#: Candidates scored again at the full `spp` after the screen at a quarter of it.
RESCORED = 12


def phase_candidates(phase: str) -> list[dict[str, float]]:
    """A few phase shapes from isotropic to strongly forward for the model's family."""
    if phase.startswith("exp"):
        deg = int(phase[3:])
        if deg == 0:
            return [{}]
        out = []
        for b1 in (0.5, 2.0, 5.0, 12.0):
            d = {f"phase.b{i}": 0.0 for i in range(1, deg + 1)}
            d["phase.b1"] = b1
            out.append(d)
        return out
    if phase == "tthg":
        return [{"phase.g_forward": g, "phase.g_backward": -0.3, "phase.w_forward": 0.9}
                for g in (0.2, 0.5, 0.75, 0.9)]
    if phase == "hg":
        return [{"phase.g": g} for g in (0.2, 0.5, 0.75, 0.9)]
    return [{}]


def start_loss(fm: ForwardModel, problem: Problem, params: Mapping[str, float], spp: int, seed: int,
               delta_rel: float, scale: float | None = None) -> float:
    """Log loss of one candidate start at `delta_rel` (scale profiled unless given)."""
    return _start_losses(fm, problem, [params], spp, seed, delta_rel, scale)[0]


def _start_losses(fm: ForwardModel, problem: Problem, candidates: Sequence[Mapping[str, float]], spp: int,
                  seed: int, delta_rel: float, scale: float | None) -> list[float]:
    """`start_loss` of each candidate, their renders queued one behind the other
    (`ForwardModel.render_profiles_many`: the same numbers as one by one)."""
    meas, valid = problem.measured, problem.valid
    losses = []
    for prof in fm.render_profiles_many([(p, seed) for p in candidates], problem.angles_deg, spp=spp):
        s = scale if scale is not None else profile_scale(meas, prof, valid, delta_rel)
        losses.append(log_loss(meas, prof, valid, s, delta_rel)[0])
    return losses


def coarse_start(fm: ForwardModel, problem: Problem, base: Mapping[str, float], *, spp: int = 32,
                 seed: int = 0, delta_rel: float = 1e-2, fixed: Mapping[str, float] | None = None,
                 scale: float | None = None) -> tuple[dict[str, float], list[tuple[dict[str, float], float]]]:
    """Best grid point (parameters) and every (candidate, loss) tried.

    A joint grid: every phase candidate x sigma_t x albedo. A sequential search (sigma_t x
    albedo with one middle phase, then the phases) was cheaper but trapped: the middle,
    forward shape compensates a wrong shape with sigma_t, and on a near-isotropic medium at
    sigma_t 6 /mm (Mie 0.01 um) it started at sigma_t 11.3; the fit stayed in that valley
    (loss 3.3x the truth's, sigma_t 60 % high). The joint grid's best there is (5.7, 0.85,
    the flattest shape). Parameters in `fixed` are never changed. `scale`: the measured
    scale (calibrated mode), else profiled per candidate.

    Every candidate is screened at `spp // 4` samples and the best `RESCORED` are scored
    again at `spp`, all with the same `seed` (common random numbers). In `tried` the
    rescored candidates carry their loss at `spp` (equal to `start_loss(..., spp, seed)`,
    and the best's is the smallest of those), the others their screening loss.
    """
    fixed = dict(fixed or {})
    phases: list[dict[str, float]] = []
    for ph in phase_candidates(fm.phase):
        free = {k: v for k, v in ph.items() if k not in fixed}
        if free not in phases:
            phases.append(free)
    sig = [fixed["sigma_t"]] if "sigma_t" in fixed else SIGMA_GRID
    alb = [fixed["albedo"]] if "albedo" in fixed else ALBEDO_GRID
    candidates: list[dict[str, float]] = []
    for ph in phases:
        for st in sig:
            for a in alb:
                p = dict(base)
                p.update(ph)
                p.update({"sigma_t": st, "albedo": a})
                p.update(fixed)
                candidates.append(p)
    screen_spp = max(1, int(spp) // 4)
    losses = _start_losses(fm, problem, candidates, screen_spp, seed, delta_rel, scale)

    def rank(i: int) -> tuple[bool, float]:
        # A NaN loss (nothing valid) sorts last, behind every finite one.
        return (not np.isfinite(losses[i]), losses[i])

    pool = list(range(len(candidates)))
    if screen_spp < spp:
        pool = sorted(pool, key=rank)[:RESCORED]
        for i, loss in zip(pool, _start_losses(fm, problem, [candidates[i] for i in pool], spp, seed, delta_rel,
                                               scale)):
            losses[i] = loss
    best = min(pool, key=rank)
    return dict(candidates[best]), list(zip(candidates, losses))
