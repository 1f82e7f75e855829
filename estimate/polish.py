"""The polish after the fit's iterations (`estimate.fit.fit_channel`, stage 5 of its docstring).

`gn_polish`: full, unshrunk Gauss-Newton steps at the final spp, each matrix the bounded
cross product of two half-spp Jacobians, each step's size tested against its own render
noise; `polish_average`: the noise-weighted mean of its last points and their standard
error; `averaged_point_count` / `first_averaged_point`: which points that mean takes.
`lm_polish`: the Levenberg-Marquardt polish on the log residuals at fixed seeds (by
default for exponential phases of degree 5 and more: `estimate.fit.lm_plan`).
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np

from estimate.deadline import Deadline
from estimate.errors import ModelParameterError
from estimate.evaluation import solve_additive
from estimate.forward import ForwardModel
from estimate.gauss_newton import gn_columns, gn_inverse, gn_jacobian, secant_steps
from estimate.loss import decorrelated_loss_se, log_hdr_variance, log_measured, log_residual, profile_scale
from estimate.phase_exponential import legendre_to_monomial
from estimate.problem import Problem
from estimate.transforms import Transform

__all__ = ["LMStage", "averaged_point_count", "first_averaged_point", "gn_polish", "lm_noise_excess", "lm_polish",
           "log_residual_columns", "polish_average"]

#: the Gauss-Newton matrix's own damping (`gn_inverse`'s default), the polish's least
GN_DAMPING = 1e-3
#: `damped` polish: the damping's factor after a step whose loss rose (its inverse after one
#: that did not), and the tries per step
DAMPING_UP = 10.0
DAMPED_TRIES = 4
#: `lm_polish` stops after a step that gains less than this share of the loss
LM_MIN_GAIN = 1e-3

#: `lm_polish`'s coordinates for an exponential phase's coefficients
LM_BASES = ("monomial", "legendre")

#: a render kept as the base of one-sided differences: (profiles, seed, spp)
Base = tuple[np.ndarray, int, int]


def _chi2(dz: np.ndarray, cov: np.ndarray) -> float:
    """dz^T cov^+ dz (pseudo-inverse: the covariance may be singular along solved directions)."""
    return float(dz @ np.linalg.pinv(cov, rcond=1e-10, hermitian=True) @ dz)


@dataclass
class LMStage:
    """One spp stage of `lm_polish`: its renders' samples per pixel (the two halves' sum when
    decorrelated), the loss at its start and after each accepted step, why it stopped, and
    the share of the recording's noise floor its optimum still owes to fitting its own
    renders' noise (`lm_noise_excess`; nan when not measurable)."""

    spp: int
    losses: list[float]
    stop: str
    noise_excess: float = math.nan

    @property
    def steps(self) -> int:
        return max(0, len(self.losses) - 1)

    def to_dict(self) -> dict[str, Any]:
        return {"spp": int(self.spp), "steps": self.steps, "losses": [float(x) for x in self.losses],
                "stop": self.stop, "noise_excess": float(self.noise_excess)}


def lm_noise_excess(A: np.ndarray, r_a: np.ndarray, r_b: np.ndarray, measured: np.ndarray, variance: np.ndarray,
                    valid: np.ndarray, scale: float, delta: float) -> float:
    """The loss a fixed-seed least-squares optimum owes to its renders' noise, as a share of the
    recording's own noise floor.

    With the seeds fixed the optimiser fits the renders' noise along with the data: its optimum
    moves off the noise-free one by about (A^T A)^-1 A^T e, and the loss without render noise
    is higher there by tr((A^T A)^-1 A^T D A) / n (D: the per-pixel variance of the residual's
    render noise, n pixels; about k v / n for k parameters and uniform variance v). `r_a`,
    `r_b`: the log residuals of the two independent half-spp renders (their difference / 2 has
    the variance of their mean's noise, which is what the decorrelated loss's gradient
    carries); `A`: the residuals' Jacobian (any parametrisation: the trace is invariant). The
    floor is the HDR variance in log units, var / (I / s + delta)^2 s^2, averaged over the
    pixels: the loss at the true parameters without model error (a real recording's model
    error only raises it, so the share is an upper bound). `measured`, `variance`, `valid`:
    the recording's (N, W) profiles, their HDR variance and mask (`Problem`); `scale`,
    `delta`: the loss's (`log_measured`). nan when the floor is unknown."""
    n = max(1, int(valid.sum()))
    d = np.where(valid, 0.25 * (r_a - r_b) ** 2, 0.0).ravel()
    var_log = np.where(valid, log_hdr_variance(measured, variance, scale, delta), 0.0)
    floor = float(np.sum(var_log) / n)
    if not (math.isfinite(floor) and floor > 0):
        return math.nan
    h = A.T @ A
    meat = A.T @ (d[:, None] * A)
    excess = float(np.trace(np.linalg.pinv(h, rcond=1e-12, hermitian=True) @ meat)) / n
    return excess / floor


def lm_polish(fm: ForwardModel, problem: Problem, params: dict[str, float], names: Sequence[str],
              tr: Sequence[Transform], *, spp: int, seed: int, delta_rel: float, iterations: int,
              fixed_scale: float | None = None,
              steps_out: list[dict[str, float]] | None = None,
              deadline: Deadline | None = None, decorrelated: bool = True,
              basis: str = "legendre", excess_target: float | None = None, spp_max: int | None = None,
              stages_out: list[LMStage] | None = None) -> tuple[dict[str, float], list[float]]:
    """Levenberg-Marquardt on the log residuals at the reference delta, fixed seeds.

    With the seeds fixed (common random numbers) the loss is a deterministic function of the
    parameters, so Gauss-Newton steps converge where Adam on fresh noise each iteration only
    hovers (it is not quite smooth: free flights that cross the slab's faces flip). The
    Jacobian is `ForwardModel.jacobian` (central differences); unknowns are the transformed
    variables z plus log scale (unless `fixed_scale`). Parameters outside `names` (e.g. the
    additive ones the polish solved) stay as given.

    `decorrelated` (the default): two renders A, B of spp / 2 each at seeds `seed` and
    `seed` + 1, and the loss minimised is mean(r_A r_B) (`estimate.loss.decorrelated_loss`),
    its gradient (J_A^T r_B + J_B^T r_A) / 2 and its Gauss-Newton matrix that of the mean
    Jacobian. The plain loss of one render, mean(r^2), holds that render's variance, which
    depends on the parameters; a deterministic optimiser walks down that term too, toward
    the parameters that render with less noise (fewer, shorter paths: lower sigma_t). On the
    paper simulation's d 0.5 um / sigma_t 6 recording (session 83; losses without render
    noise over eight seed pairs, as ratios to the truth's) the plain-loss LM's exp7 and exp10
    ended at 1.030 +- 0.007 and 1.072 +- 0.014, sigma_t -2 % and -4 %; this one's exp7 at
    0.965 +- 0.022, the lowest of every point tried there (the exp7 profile over sigma_t:
    `benchmarks/exp_sigma_t_profile.py`). False: one render at `spp`, the plain loss
    (sessions 79-82).

    `basis` "legendre" (the default; "monomial" before session 89): the exponential phase's
    coefficients b_1..b_M are stepped as the Legendre coefficients c of the same exponent
    (b = L c, `lm_basis_matrix`). The model and the undamped Gauss-Newton step are the same;
    what changes is the damping, Marquardt's diag(J^T J), which is invariant to each
    column's scale but not to mixing them. The residuals' columns for b_i follow mu^i, which
    are nearly collinear on [-1, 1] (mu^5 and mu^7 correlate at 0.99), so once the damping
    is up the damped step in b is a poor direction; P_1..P_M are orthogonal there. With
    sigma_t held at the truth on d 0.5 um / sigma_t 6, exp7's LM stopped after 4 steps at
    1.71 x the floor in b, and reached 1.21 x in c in the same time (session 89).

    Each stage stops after `iterations` steps, when no step is accepted, or when a step gains
    less than `LM_MIN_GAIN` of the loss. `excess_target` (decorrelated only; None: one stage):
    a stage that stopped on its own with `lm_noise_excess` above this share of the noise floor
    is followed by one at the spp that brings it there (the excess falls as 1 / spp; powers of
    two, at most `spp_max`), from its end point with fresh seeds. Its optimum holds the noise
    of its renders as a fitted signal: on the paper simulation's d 0.5 um / sigma_t 2
    recording exp10's LM at 4096 spp ended with its own loss below zero and 1.19 x the floor
    without render noise, at 16384 spp at 1.00 x (session 90). Returns the parameters and the
    losses of the last stage (at its start, then after each accepted step); `steps_out`
    receives each accepted step in parameter units, `stages_out` each stage. Once `deadline`
    has passed no further step is started (stage name "lm").
    """
    p = dict(params)
    stages: list[LMStage] = []
    cur = spp
    cap = spp if spp_max is None else max(spp, spp_max)
    while True:
        p, stage = _lm_stage(fm, problem, p, names, tr, spp=cur, seed=seed + 2 * len(stages), delta_rel=delta_rel,
                             iterations=iterations, fixed_scale=fixed_scale, steps_out=steps_out,
                             deadline=deadline, decorrelated=decorrelated, basis=basis)
        stages.append(stage)
        if stages_out is not None:
            stages_out.append(stage)
        ex = stage.noise_excess
        if (excess_target is None or not decorrelated or not math.isfinite(ex) or ex <= excess_target
                or stage.stop in ("step limit", "time limit")):
            break
        if cur >= cap:
            break
        cur = min(cur * 2 ** math.ceil(math.log2(ex / excess_target)), cap)
    return p, stages[-1].losses


def _lm_stage(fm: ForwardModel, problem: Problem, params: dict[str, float], names: Sequence[str],
              tr: Sequence[Transform], *, spp: int, seed: int, delta_rel: float, iterations: int,
              fixed_scale: float | None, steps_out: list[dict[str, float]] | None,
              deadline: Deadline | None, decorrelated: bool, basis: str) -> tuple[dict[str, float], LMStage]:
    """One `lm_polish` stage at one spp and seed pair: the parameters it ends at and its record."""
    valid = problem.valid
    meas = problem.measured
    angles = problem.angles_deg
    n_v = max(1, int(valid.sum()))
    seeds = (seed, seed + 1) if decorrelated else (seed,)
    each_spp = max(1, spp // 2) if decorrelated else spp

    def residual(p: Mapping[str, float]) -> tuple[list[np.ndarray], list[np.ndarray], float, float, float]:
        profs = fm.render_profiles_many([(p, s_) for s_ in seeds], angles, spp=each_spp)
        sc = fixed_scale if fixed_scale is not None else profile_scale(meas, np.mean(profs, axis=0), valid, delta_rel)
        mm, dlt = log_measured(meas, valid, sc, delta_rel)
        rs = [log_residual(mm, prof, valid, dlt) for prof in profs]
        # decorrelated: r_A r_B, whose expectation holds no render variance; else r^2
        loss = float(np.sum(rs[0] * rs[-1]) / n_v)
        return rs, profs, sc, dlt, loss

    p = dict(params)
    z = np.array([t.to_z(p[n]) for n, t in zip(names, tr)])
    rs, profs, sc, dlt, loss = residual(p)
    losses = [loss]
    lam = 1e-3
    n_z = len(names)
    # [z, log scale] = to_u @ u: the LM's own coordinates u (the identity but for the phase
    # block; the scale's column, when free, is the last and stays)
    to_u = np.eye(n_z + (0 if fixed_scale is not None else 1))
    to_u[:n_z, :n_z] = lm_basis_matrix(names, tr, basis)
    stop = "step limit"
    A: np.ndarray | None = None
    for _ in range(iterations):
        if deadline is not None and deadline.passed("lm"):
            stop = "time limit"
            break
        # the log scale's column depends on the measurement alone: the same for both renders
        m = meas / sc
        scale_col = [np.where(valid, -m / (np.clip(m, -0.5 * dlt, None) + dlt), 0.0).ravel()] \
            if fixed_scale is None else []
        mats = []
        for prof, s_ in zip(profs, seeds):
            jac = fm.jacobian(p, angles, list(names), spp=each_spp, seed=s_)
            mats.append(np.column_stack([log_residual_columns(jac, prof, valid, dlt, names, tr, z)] + scale_col))
        # The matrix of the mean Jacobian: positive semi-definite, its render noise only damps
        # the noisy directions further (the cross product A_A^T A_B would be unbiased but can
        # be indefinite).
        A = 0.5 * (mats[0] + mats[-1])
        Atr = 0.5 * (mats[0].T @ rs[-1].ravel() + mats[-1].T @ rs[0].ravel())
        A = A @ to_u
        Atr = to_u.T @ Atr
        AtA = A.T @ A
        accepted = False
        rel = 0.0
        # Up to 8 damping increases (x4 each): in the curved sigma_t-phase valley the
        # Gauss-Newton steps overshoot; with 4 the polish of a simulated-bench fit
        # (paper d0.5_s2, calibrated scale) accepted no step at all.
        for _try in range(8):
            H = AtA + lam * np.diag(np.diag(AtA) + 1e-12)
            try:
                step = to_u @ -np.linalg.solve(H, Atr)
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
            rs_n, profs_n, sc_n, dlt_n, loss_n = residual(p_new)
            if loss_n < loss:
                if steps_out is not None:
                    steps_out.append({n: float(p_new[n] - p[n]) for n in names})
                p, z, rs, profs, sc, dlt = p_new, z_new, rs_n, profs_n, sc_n, dlt_n
                rel = (loss - loss_n) / abs(loss) if loss != 0 else 1.0
                loss = loss_n
                losses.append(loss)
                lam = max(lam / 3.0, 1e-6)
                accepted = True
                break
            lam *= 4.0
        if not accepted:
            stop = "no step lowered the loss"
            break
        if rel < LM_MIN_GAIN:
            stop = f"a step gained under {LM_MIN_GAIN:.1%} of the loss"
            break
    # the Jacobian of the last step (at the end point, or one step before it)
    excess = (lm_noise_excess(A, rs[0], rs[-1], meas, problem.variance, valid, sc, dlt)
              if A is not None and decorrelated else math.nan)
    return p, LMStage(spp=each_spp * len(seeds), losses=losses, stop=stop, noise_excess=excess)


def log_residual_columns(jac: Mapping[str, np.ndarray], profiles: np.ndarray, valid: np.ndarray, delta: float,
                         names: Sequence[str], tr: Sequence[Transform], z: Sequence[float] | np.ndarray) -> np.ndarray:
    """The Jacobian of the log residuals r = log(m + delta) - log(I + delta) in the transformed
    variables z: -dI/dx / (I + delta) * dx/dz per pixel (0 where not valid), a column per name
    (`jac`: d profiles / d x, `profiles`: the render I they were taken with)."""
    return np.stack([np.where(valid, -jac[n] / (np.clip(profiles, 0, None) + delta), 0.0).ravel() * t.dx_dz(float(zz))
                     for n, t, zz in zip(names, tr, z)], axis=1)


def lm_basis_matrix(names: Sequence[str], tr: Sequence[Transform], basis: str) -> np.ndarray:
    """Matrix B with z = B @ u for `lm_polish`'s coordinates u: the identity, except that in
    the "legendre" basis the exponential phase's b_1..b_M (all present in `names`, linear
    transforms x = unit * z) are replaced by the Legendre coefficients c_1..c_M of the same
    exponent, b = L c. The constant terms that P_2, P_4, ... bring are dropped: b_0 is fixed
    by the normalisation. L is upper triangular with a non-zero diagonal, so every b has
    one c."""
    n = len(names)
    out = np.eye(n)
    if basis == "monomial":
        return out
    if basis not in LM_BASES:
        raise ModelParameterError(f"LM basis must be one of {LM_BASES}, got {basis!r}")
    idx = {nm: i for i, nm in enumerate(names)}
    deg = 0
    while f"phase.b{deg + 1}" in idx:
        deg += 1
    if deg == 0:
        return out
    rows = [idx[f"phase.b{i}"] for i in range(1, deg + 1)]
    lmat = np.stack([legendre_to_monomial(np.eye(deg + 1)[j])[1:] for j in range(1, deg + 1)], axis=1)
    units = np.array([tr[r].unit for r in rows])
    out[np.ix_(rows, rows)] = lmat / units[:, None]
    return out


def polish_average(accepted: Sequence[Mapping[str, Any]], names: Sequence[str], tr: Sequence[Transform],
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


def averaged_point_count(planned: int, average_from: int) -> int:
    """How many polish points the result averages when the polish runs its `planned` steps
    (points `average_from` .. `planned`; 1 when `average_from` is 0: the last point). A polish
    that goes on past its plan keeps this many of its last points (`first_averaged_point`), and its
    noise test looks at this many of its last steps (`gn_polish`'s `keep_last`)."""
    return max(1, planned - average_from + 1) if average_from > 0 else 1


def first_averaged_point(n_accepted: int, planned: int, average_from: int) -> int:
    """The first polish point to average (1-based; 0: none): `average_from`, or, for a polish
    that went on past its `planned` steps (still walking), the first of its last
    `averaged_point_count` points."""
    if average_from > 0 and n_accepted > planned:
        return n_accepted - averaged_point_count(planned, average_from) + 1
    return average_from


def gn_polish(fm: ForwardModel, problem: Problem, params: Mapping[str, float], names: Sequence[str],
              tr: Sequence[Transform], *, steps: int, spp: int, jacobian_spp: int, seed: int,
              delta_nodes: Sequence[float], reference_delta_rel: float, fixed_scale: float | None,
              solved: Sequence[str] = (), solved_columns: Mapping[str, np.ndarray] | None = None,
              smooth_px: float = 3.0, exact: Collection[str] = (), caps: np.ndarray | None = None,
              scale_guess: float | None = None, jacobian_every: int = 1, gross: float = 1.0,
              cross: bool = False, max_steps: int | None = None, chi2_continue: float = math.inf,
              keep_last: int = 3, settled_spp_factor: int = 1, one_sided: bool = False,
              jacobians_out: list[list[dict[str, np.ndarray]]] | None = None, damped: bool = False,
              start_point_noise: bool = True,
              deadline: Deadline | None = None) -> tuple[dict[str, float], list[dict[str, Any]], tuple[np.ndarray, np.ndarray] | None]:
    """Full Gauss-Newton steps on the delta-averaged log loss at high samples per pixel, from
    the end of the stochastic iterations.

    Each step: the matrix of a smoothed finite-difference Jacobian at `jacobian_spp` (as in
    `gn_inverse`, averaged over `delta_nodes`, relative deltas; re-estimated every
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
    the cross product made the fit diverge (session 4, 256 spp, unsmoothed; `gn_inverse`);
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
    the points that `polish_average` keeps have stopped walking (the benchmark at seed 3,
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

    Since session 27 a step after the first is tested against its own noise plus that of the
    point it starts from (`c_point`: the covariance of the step that brought the polish there,
    shrunk with it): that point is the optimum plus that step's noise, and a full step from it
    undoes that noise too, so at the noise floor a step scatters by both. With its own noise
    alone, noise-sized steps read chi^2 11-51 on the benchmark (5 parameters) and the polish
    ran to 8 steps whenever one of three in a row passed 20.5; with the start point's noise
    they read 3-23 (session 27, seeds 0-3). The trace keeps both (`step_chi2`, `step_chi2_own`);
    `start_point_noise=False` tests against the step's own noise alone, as before.
    Once `deadline` has passed no further step is started (stage name "polish").
    Still about twice the parameter count: the matrix's own noise (a valley eigenvalue off by
    its noise scales the correction of the start point's noise) stays out of the model.

    Damped steps (`damped`, the fit's default since session 27): a step whose loss without
    render noise rises by more than 2 standard errors of the difference is retried from the
    same matrix and gradient with 10x the Levenberg-Marquardt damping (`DAMPING_UP`, up to
    `DAMPED_TRIES` tries), which turns it towards a short, scaled gradient step; after a step
    that did not rise the damping falls back by 10x, to the matrix's own (`GN_DAMPING`) at
    least. Undamped, the benchmark's seed 0 (iterations ending at sigma_t 2.6, b3 3.5 for
    truth 2.0 / 0.5) bounced across the sigma_t / phase valley: losses 4.3e-4 -> 7.5e-4 ->
    1.5e-3 -> 5.2e-4 -> 9.7e-4 -> 1.1e-3 -> 1.8e-4 in its first six steps, all kept by the
    lenient test, and still walking after eight (step chi^2 146). Damped, with the fit's
    per-parameter caps widened from 5 to 15 of Adam's last learning rates (`polish_cap_lr`;
    the phase coefficients' 0.75 cap had let b3 fall by at most 0.75 a step), it reached the
    noise floor in three steps (sigma_t 2.54 -> 2.26 -> 2.08, b3 2.0 -> 1.2 -> 0.3). A retry
    costs the new point's renders only (2 of a step's 7 renders' worth).

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

    One-sided Jacobians (`one_sided`, with `cross`): each of renders A and B is the mean of
    two at half the spp, and the two Jacobians are forward and backward differences against
    the first half of A and of B respectively, when those were rendered at `jacobian_spp` / 2
    (else against a new base render). Each costs one render per parameter instead of two, so
    a step renders 7 instead of 12 renders' worth at `spp` for 5 parameters. The mean of a
    forward and a backward difference is the central one, and the cross product of the two
    keeps the central difference's O(h^2) error. A one-sided Jacobian's noise is correlated
    with its base's (with common random numbers the perturbed render repeats the base's
    paths), so the gradient pairs each with the other render's residuals. At a `jacobian_spp`
    below `spp` each render is the mean of as many at the Jacobians' half spp as it takes, the
    first its Jacobian's base (`FitSettings.polish_jacobian_spp`; off by default: at 512 the
    benchmark's seed 0 walked the valley at half the pace, 2.50 -> 2.44 -> 2.36 -> 2.20, and
    ended 6.3 % high, session 27).

    Returns the parameters, per step {loss, loss_new, accepted, halvings (retries: halvings,
    or damping increases), damping (of the step tried last), step (x units), step_chi2 (of
    the full step, before caps, halvings and damping; step_chi2_own against its own noise
    alone), jacobians (new Jacobians
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
              ) -> tuple[dict[str, float], np.ndarray, np.ndarray, float, tuple[float, float], list[Base]]:
        """Renders A, B at `p_in` (seeds of step k, `spp_k` each), the solved values and scale,
        the loss without render noise with its standard error, and (`one_sided`) the first
        half-spp render of each of A and B, which the next Jacobians difference against."""
        p = dict(p_in)
        bases: list[Base] = []
        if one_sided and spp_k >= 2:
            # Each render the mean of `n_part` at the Jacobians' spp (the same noise as one at
            # spp_k), so that its first part can be their base: two at half the spp when the
            # Jacobians' halves are at spp / 2 (the default), more when they are cheaper.
            jac_half = max(1, jacobian_spp // 2)
            n_part = spp_k // jac_half if jac_half < spp_k and spp_k % jac_half == 0 else 2
            part_k = spp_k // n_part
            seeds = [seed + 2_000 + 4 * k + i if i < 4 else seed + 200_000 + 64 * k + i for i in range(2 * n_part)]
            parts = fm.render_profiles_many([(p, s_) for s_ in seeds], angles, spp=part_k)
            pa, pb = np.mean(parts[:n_part], axis=0), np.mean(parts[n_part:], axis=0)
            bases = [(parts[0], seeds[0], part_k), (parts[n_part], seeds[n_part], part_k)]
        else:
            pa, pb = fm.render_profiles_many([(p, seed + 2 * k), (p, seed + 2 * k + 1)], angles, spp=spp_k)
        if solved:
            shift = solve_additive(fm, problem, p, solved, 0.5 * (pa + pb), reference_delta_rel, fixed_scale,
                                   scale_guess=scale_guess, columns=solved_columns)
            pa, pb = pa + shift, pb + shift
        sc = fixed_scale if fixed_scale is not None else profile_scale(meas, 0.5 * (pa + pb), valid,
                                                                        reference_delta_rel, guess=scale_guess)
        per_delta = np.array([decorrelated_loss_se(meas, pa, pb, valid, sc, q) for q in delta_nodes])
        return p, pa, pb, sc, (float(per_delta[:, 0].mean()), float(per_delta[:, 1].mean())), bases

    def one_sided_jacobian(p_at: Mapping[str, float], base: Base | None, half: int, fallback_seed: int,
                           backward: bool) -> dict[str, np.ndarray]:
        """Forward (or backward) differences at `half` spp against `base` when it was rendered
        at that spp, else against a new base render at `fallback_seed`."""
        if base is None or base[2] != half:
            base = (fm.render_profiles(p_at, angles, spp=half, seed=fallback_seed), fallback_seed, half)
        # Twice the central differences' secant steps: with common random numbers the
        # perturbed render's paths decorrelate from the base's in proportion to the step, so
        # a one-sided difference over h is ~1.4x as noisy as a central one over +-h, and one
        # over 2h about as noisy (512 spp, the benchmark's parameters: sigma_t column 1.04
        # against 1.13 relative RMS error; phase columns 0.20-0.32 against 0.18-0.19). The
        # one-sided differences' O(h) error (~15 % of the phase columns there) cancels in
        # the mean of the forward and the backward one.
        steps = {n: 2.0 * h for n, h in secant_steps(fm, p_at, names).items()}
        return fm.jacobian(p_at, angles, list(names), spp=half, seed=base[1], steps=steps,
                           base_profiles=base[0], backward=backward)

    def noise_sized(chi2: float, spp_step: int) -> bool:
        """A step no larger than its noise on the scale of `spp` (a settled step's chi^2 is
        measured against its own, spp_step / spp times smaller noise)."""
        return chi2 * spp / spp_step <= chi2_continue

    if steps <= 0:
        return dict(params), [], None
    max_steps = steps if max_steps is None else max(steps, max_steps)
    spp_now = spp
    p, pa, pb, sc, (loss, se), bases = state(params, 0, spp_now)
    loss_start = loss
    trace: list[dict[str, Any]] = []
    jac: dict[str, np.ndarray] = {}
    jac_b: dict[str, np.ndarray] | None = None
    lam = GN_DAMPING
    c_point: np.ndarray | None = None
    for k in range(max_steps):
        if deadline is not None and deadline.passed("polish"):
            break
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
                if one_sided:
                    jac_a = one_sided_jacobian(p, bases[0] if bases else None, half, seed + 1000 + k, backward=False)
                    jac_b = one_sided_jacobian(p, bases[1] if bases else None, half, seed + 5000 + k, backward=True)
                else:
                    jac_a = gn_jacobian(fm, problem, p, names, spp=half, seed=seed + 1000 + k)
                    jac_b = gn_jacobian(fm, problem, p, names, spp=half, seed=seed + 5000 + k)
                new_jacobians = 2
                jac = {n: 0.5 * (jac_a[n] + jac_b[n]) for n in names}
            else:
                jac = gn_jacobian(fm, problem, p, names, spp=jacobian_spp, seed=seed + 1000 + k)
                jac_a, jac_b = jac, None
                new_jacobians = 1
            if jacobians_out is not None:
                jacobians_out.append([jac_a] if jac_b is None else [jac_a, jac_b])
        # The one-sided Jacobians of the point whose renders A, B the gradient uses (a
        # settled step keeps older ones, whose noise is independent of them).
        paired = (jac_a, jac_b) if one_sided and cross and jac_b is not None and new_jacobians else None
        m = meas / sc
        logs = [log_measured(meas, valid, sc, q) for q in delta_nodes]
        mean = 0.5 * (pa + pb)
        dls = [d for _, d in logs]
        g = np.zeros(len(names))
        # Per pixel, the gradient's share of the renders' noise: one draw of it from the two
        # renders' difference (the same noise drives every delta node, so they add up first).
        u = np.zeros((meas.size, len(names)))
        for mm, d in logs:
            A = gn_columns(jac, names, tr, z, problem, mean, d, m, fixed_scale is None, cols_out, smooth_px, exact)
            ra, rb = (log_residual(mm, q, valid, d) for q in (pa, pb))
            if paired:
                # Each one-sided Jacobian's noise is correlated with its base render's, which
                # is half of render A's (or B's); paired with the other render's residuals its
                # noise averages out of the gradient instead of biasing it.
                a_a, a_b = (gn_columns(j, names, tr, z, problem, mean, d, m, fixed_scale is None, cols_out,
                                       smooth_px, exact) for j in paired)
                g += (a_b.T @ ra.ravel() + a_a.T @ rb.ravel()) / n_v / len(dls)
            else:
                g += 2.0 * (A.T @ (0.5 * (ra + rb)).ravel()) / n_v / len(dls)
            u += 2.0 * A * (0.5 * (ra - rb)).ravel()[:, None] / n_v / len(dls)

        # The matrix's inverse at a given damping (this step's Jacobians and point).
        inverse = partial(gn_inverse, jac_a, names, tr, z, problem, mean, dls, m, fixed_scale is None,
                          profiled_columns=cols_out, smooth_px=smooth_px, exact=exact, jac_cross=jac_b)
        h_inv = inverse(damping=GN_DAMPING)
        s_u = u.T @ u
        dz_full = -(h_inv @ g)
        c_dz = h_inv @ s_u @ h_inv.T
        # The current point is itself the optimum plus the noise of the step that brought it
        # there (`c_point`), and a full step from it undoes that noise too: at the noise floor
        # a step scatters by both.
        c_step = c_dz if c_point is None or not start_point_noise else c_dz + c_point
        step_chi2 = _chi2(dz_full, c_step)
        entry: dict[str, Any] = {"loss": loss, "loss_new": float("nan"), "accepted": False, "halvings": 0,
                                 "step": {}, "step_chi2": step_chi2, "step_chi2_own": _chi2(dz_full, c_dz),
                                 "jacobians": new_jacobians, "spp": spp_now}
        trace.append(entry)
        tries = DAMPED_TRIES if damped else 3
        lam_try = lam
        for attempt in range(tries):
            if damped:
                h_try = h_inv if lam_try <= GN_DAMPING else inverse(damping=lam_try)
                shrink = 1.0
            else:
                h_try, shrink = h_inv, 0.5 ** attempt
            dz = -(h_try @ g)
            if caps is not None:
                dz = np.clip(dz, -caps, caps)
            dz = shrink * dz
            z_new = np.array([t.clamp_z(float(zz + d_)) for t, zz, d_ in zip(tr, z, dz)])
            p_try = dict(p)
            p_try.update({n: t.to_x(float(zz)) for n, t, zz in zip(names, tr, z_new)})
            try:
                p_try = fm.validate(p_try)
            except ModelParameterError:
                lam_try *= DAMPING_UP
                continue
            # The new point's renders: at the settled spp when this step is noise-sized (the
            # next one will be a settled step), else at `spp`.
            spp_new = spp * settled_spp_factor if noise_sized(step_chi2, spp_now) else spp
            p_new, pa_n, pb_n, sc_n, (loss_n, se_n), bases_n = state(p_try, k + 1, spp_new)
            entry.update(loss_new=loss_n, halvings=attempt, damping=lam_try if damped else GN_DAMPING)
            if damped:
                # Levenberg-Marquardt: a step whose loss rises by more than 2 standard errors
                # of the difference is retried with more damping (towards a short, scaled
                # gradient step) from the same matrix and gradient.
                ok = loss_n - loss <= 2.0 * math.hypot(se, se_n)
            else:
                # Undone (halved, twice at most) only when the rise exceeds the polish's
                # starting loss plus 3 standard errors of the difference: the estimator
                # scatters by about the loss itself near the optimum, and can be negative there.
                ok = loss_n - loss <= gross * max(loss_start, 0.0) + 3.0 * math.hypot(se, se_n)
            if ok:
                # The point's own Monte Carlo scatter: a full Gauss-Newton step lands at the
                # optimum plus the step's noise, whose z-space covariance is that of the
                # step taken (shrunk with it), taken to x units at the new point.
                c_try = c_dz if h_try is h_inv else h_try @ s_u @ h_try.T
                sd_z = np.sqrt(np.clip(np.diag(c_try), 0.0, None)) * shrink
                entry.update(accepted=True, step={n: float(p_new[n] - p[n]) for n in names},
                             point={n: float(v) for n, v in p_new.items() if n in names or n in solved},
                             noise_sd={n: float(sd * abs(t.dx_dz(float(zz))))
                                       for n, t, sd, zz in zip(names, tr, sd_z, z_new)})
                p, pa, pb, sc, loss, se, spp_now, bases = p_new, pa_n, pb_n, sc_n, loss_n, se_n, spp_new, bases_n
                scale_guess = sc
                lam = max(GN_DAMPING, lam_try / DAMPING_UP)
                c_point = c_try * shrink ** 2
                break
            lam_try *= DAMPING_UP
        if not entry["accepted"]:
            break
    return p, trace, (pa, pb)
