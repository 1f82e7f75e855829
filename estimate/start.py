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
from functools import lru_cache

import numpy as np

from estimate.errors import ModelParameterError
from estimate.forward import ForwardModel
from estimate.loss import log_loss, profile_scale
from estimate.problem import Problem

__all__ = ["ALBEDO_GRID", "MIE_START_DIAMETERS_UM", "PHASE_STARTS", "RESCORED", "SIGMA_GRID", "coarse_start",
           "mie_start_shapes", "phase_candidates", "start_loss"]

#: Extinction coefficients tried (1/mm): log-spaced over what a 1 mm slab's profiles can show.
SIGMA_GRID = tuple(float(x) for x in np.geomspace(0.5, 16.0, 11))
ALBEDO_GRID = (0.5, 0.7, 0.85, 0.95, 0.99)
#: Candidates scored again at the full `spp` after the screen at a quarter of it.
RESCORED = 12


#: The exponential phases' start shapes (`FitSettings.phase_starts`): "vmf", four von
#: Mises-Fisher lobes (b_1 only); "mie", those and the exp<M> fits of `mie_start_shapes`.
PHASE_STARTS = ("vmf", "mie")
#: Mean diameters [um] of the "mie" start shapes: poly-disperse spheres (10 % spread) of oil
#: in water (n 1.46 / 1.333) at 550 nm, log-spaced from near-Rayleigh (g 0.02) to strongly
#: forward (g 0.97). Neither the index nor the wavelength is the paper simulation's (1.377,
#: 600 nm), and no diameter is one of its four, so its recordings are not started at their truth.
MIE_START_DIAMETERS_UM = tuple(float(f"{d:.3g}") for d in np.geomspace(0.05, 2.0, 8))


@lru_cache(maxsize=32)
def mie_start_shapes(degree: int) -> tuple[tuple[float, ...], ...]:
    """b_1..b_M of the exp<degree> fitted (the paper's SAD of ln p, `estimate.phase_fit`) to
    each of `MIE_START_DIAMETERS_UM`'s Mie phase functions, skipping fits that failed or
    left the forward model's coefficient range (|b_i| <= 1000).

    The von Mises-Fisher starts have one shape parameter; a Mie phase function of a forward
    medium has a narrow diffraction peak over a broad wide-angle tail, which a high-degree
    fit from a vMF start builds only slowly, through a long ill-conditioned valley (d 0.5 um,
    sigma_t 6 /mm, session 88: exp7 from the vMF start 1.7 x the loss floor with sigma_t and
    the albedo held at the truth, from the Mie table's own exp7 fit 1.2 x)."""
    from estimate.mie import MieSettings, mie_poly
    from estimate.phase_fit import fit_model

    settings = MieSettings(wavelength_nm=550.0, n_particle=1.46, n_medium=1.333)
    out = []
    for d in MIE_START_DIAMETERS_UM:
        fit = fit_model(mie_poly(d, 0.1, settings), f"exp{degree}")
        if fit.ok:
            b = tuple(float(x) for x in fit.params["b"][1:])
            if max(abs(x) for x in b) <= 1000.0:
                out.append(b)
    return tuple(out)


def phase_candidates(phase: str, starts: str = "vmf") -> list[dict[str, float]]:
    """A few phase shapes from isotropic to strongly forward for the model's family
    (`starts`: `PHASE_STARTS`, for the exponential family; "mie" adds `mie_start_shapes`
    from degree 2 on)."""
    if starts not in PHASE_STARTS:
        raise ModelParameterError(f"unknown phase starts {starts!r}; use {' or '.join(PHASE_STARTS)}")
    if phase.startswith("exp"):
        deg = int(phase[3:])
        if deg == 0:
            return [{}]
        out = []
        for b1 in (0.5, 2.0, 5.0, 12.0):
            d = {f"phase.b{i}": 0.0 for i in range(1, deg + 1)}
            d["phase.b1"] = b1
            out.append(d)
        if starts == "mie" and deg >= 2:
            out += [{f"phase.b{i + 1}": x for i, x in enumerate(b)} for b in mie_start_shapes(deg)]
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
                 scale: float | None = None, phase_starts: str = "vmf",
                 ) -> tuple[dict[str, float], list[tuple[dict[str, float], float]]]:
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
    `phase_starts`: the exponential family's shapes (`phase_candidates`).
    """
    fixed = dict(fixed or {})
    phases: list[dict[str, float]] = []
    for ph in phase_candidates(fm.phase, phase_starts):
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
