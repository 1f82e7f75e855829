"""Parameter uncertainties of a fit (`estimate.fit.fit_channel`, stage 7 of its docstring).

`fisher_uncertainties`: the Gauss-Newton / Fisher bound from the data and render variance.
`sandwich_uncertainties`: the sandwich covariance H^-1 M H^-1 of the log loss, its curvature
H and its robust meat M from the cross products of Jacobians with independent render noise
(bounded by `UNCERTAINTY_CROSS_FLOOR`), so neither carries one Jacobian's own noise.
`iterate_drift`, `window_estimate`, `window_scatter`: how far the iterates still moved and
scattered at the end. `combined_uncertainties` adds the parts in quadrature (the polish
drift only where it stands out of its points' scatter); `combined_covariance` builds the
covariance matrix that goes with them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np
from scipy import stats

from estimate.evaluation import jacobian_columns
from estimate.forward import ForwardModel
from estimate.gauss_newton import bounded_cross
from estimate.loss import log_hdr_variance
from estimate.problem import Problem

__all__ = ["DRIFT_T", "UNCERTAINTY_CROSS_FLOOR", "combined_covariance", "combined_uncertainties", "correlation_factor",
           "data_noise_variance", "excess_share",
           "fisher_uncertainties", "iterate_drift", "log_residuals", "sandwich_uncertainties", "window_estimate", "window_scatter"]


def fisher_uncertainties(fm: ForwardModel, problem: Problem, params: Mapping[str, float],
                         names: Sequence[str], scale: float, model_variance: np.ndarray,
                         profiles: np.ndarray, *, spp: int, seed: int, inflate: float = 1.0,
                         fit_scale: bool = True, jac: Mapping[str, np.ndarray] | None = None
                         ) -> tuple[dict[str, float], float]:
    """1-sigma uncertainties of `names` and of the scale from the Gauss-Newton Fisher matrix
    of the linear chi^2 (the bound of an ideal variance-weighted fit; the log-loss fit is
    not that fit, see `sandwich_uncertainties`). Scale uncertainty NaN when not fitted."""
    jac = jac if jac is not None else jacobian_columns(fm, problem, params, names, spp=spp, seed=seed)
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


class LogResiduals(NamedTuple):
    """The log loss's residuals and their noise variances (`log_residuals`)."""

    valid: np.ndarray
    #: measured radiance over the scale, and that clipped at -delta / 2 (the log's argument)
    measured: np.ndarray
    measured_clipped: np.ndarray
    #: the fitted profiles, clipped at 0
    profiles: np.ndarray
    #: the loss's delta in radiance units (`delta_rel` x the brightest measured pixel)
    delta: float
    #: r = log(measured + delta) - log(profile + delta), 0 where not valid
    r: np.ndarray
    #: the variance channel's noise and the evaluation render's, in r's units
    v_sensor: np.ndarray
    v_eval: np.ndarray


def log_residuals(problem: Problem, scale: float, profiles: np.ndarray, model_variance: np.ndarray,
                  delta_rel: float) -> LogResiduals:
    """The residuals r of the log loss at the fitted `profiles` (radiance units, `scale` the
    measured-to-rendered factor) and their per-pixel noise variances, propagated to log
    space: the sensor's from `problem.variance`, the evaluation render's from
    `model_variance` (the variance of the rendered mean)."""
    valid = np.asarray(problem.valid, dtype=bool)
    m = problem.measured / scale
    dl = max(delta_rel * float(np.max(np.where(valid, m, -np.inf))), 1e-30)
    mm = np.clip(m, -0.5 * dl, None)
    ip = np.clip(profiles, 0, None)
    r = np.where(valid, np.log(mm + dl) - np.log(ip + dl), 0.0)
    return LogResiduals(valid, m, mm, ip, dl, r, log_hdr_variance(problem.measured, problem.variance, scale, dl),
                        model_variance / (ip + dl) ** 2)


def sandwich_uncertainties(problem: Problem, params: Mapping[str, float], names: Sequence[str], scale: float,
                           profiles: np.ndarray, model_variance: np.ndarray, jac: Mapping[str, np.ndarray],
                           *, delta_rel: float, fit_scale: bool, render_variance_factor: float = 2.0,
                           covariance_out: dict[str, dict[str, float]] | None = None,
                           jac_more: Sequence[Mapping[str, np.ndarray]] = (),
                           cross_floor: float = UNCERTAINTY_CROSS_FLOOR,
                           data_meat: bool = False, meat_cross: bool = False,
                           render_correlation_out: dict[str, dict[str, float]] | None = None,
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

    `data_meat`: the meat holds the data's noise alone (`data_noise_variance`: the
    variance channel's and any excess, sized from the residuals, less the evaluation
    render's own noise), for a result that is the mean of polish points whose scatter
    (`polish_se`, added by `combined_uncertainties`) carries the render noise; no further
    inflation or robust choice, but multiplied by the residuals' pixel-to-pixel correlation
    (`correlation_factor`). Otherwise the render noise is counted twice: on the
    one-channel benchmark's truth the residuals are almost all the evaluation render's
    noise (r^2 / (v_sensor + v_eval) 0.5-1.9 per angle) and the intervals were 1.5-2.2x too
    wide (18 noise draws, session 30, `benchmarks/coverage_variants.py`;
    `docs/estimation-log.md`). This meat's Gram matrix is the Jacobians' mean's, not their
    cross products' (`meat_cross=True` restores those, as sessions 30-33 had it; the other
    meats keep the cross products): see the comment at its use.

    `render_correlation_out`: the correlation matrix of H^-1 (A^T V A) H^-1, V the render
    noise of one polish step's gradient (`render_variance_factor` x `model_variance`): how
    the polish points scatter about the optimum, whose size `polish_se` measures
    (`combined_covariance`).
    """
    lr = log_residuals(problem, scale, profiles, model_variance, delta_rel)
    valid, m, mm, ip, dl, r = lr.valid, lr.measured, lr.measured_clipped, lr.profiles, lr.delta, lr.r
    var_r = lr.v_sensor + render_variance_factor * lr.v_eval
    var_r = np.where(valid & np.isfinite(var_r), var_r, 0.0)

    def columns(j: Mapping[str, np.ndarray]) -> np.ndarray:
        cols = [np.where(valid, -j[n] / (ip + dl), 0.0).ravel() for n in names]
        if fit_scale:
            cols.append(np.where(valid, -m / (mm + dl), 0.0).ravel())
        return np.where(np.isfinite(a := np.stack(cols, axis=1)), a, 0.0)

    As = [columns(j) for j in (jac, *jac_more)]
    A = np.mean(As, axis=0)
    pairs = [(a, b) for i, a in enumerate(As) for b in As[i + 1:]]

    def gram(w: np.ndarray, cross_products: bool = True) -> np.ndarray:
        """A^T diag(w) A: with several Jacobians and `cross_products`, their pairs' cross
        products bounded by the mean's; else the Jacobians' mean's."""
        mean_gram = A.T @ (A * w[:, None])
        if not pairs or not cross_products:
            return mean_gram
        cross = sum(a.T @ (b * w[:, None]) + b.T @ (a * w[:, None]) for a, b in pairs) / (2 * len(pairs))
        return bounded_cross(cross, mean_gram, cross_floor)

    H = gram(np.ones(A.shape[0]))
    n = int(valid.sum())
    dof = max(1, n - A.shape[1])
    c2 = float(np.sum(np.where(var_r > 0, r * r / np.where(var_r > 0, var_r, 1.0), 0.0)))
    red = c2 / dof
    try:
        Hi = np.linalg.pinv(H, rcond=1e-12)
    except np.linalg.LinAlgError:
        return {k: float("nan") for k in names}, float("nan"), red
    if data_meat:
        v_sensor, v_eval = lr.v_sensor, lr.v_eval
        v_data, _ = data_noise_variance(r, v_sensor, v_eval, valid)
        # The meat is the variance of the gradient the polish steps with, A^T r, and those
        # steps use the Monte Carlo Jacobians: Var(A^T r) = A0^T S A0 + E[E^T S E], E their
        # noise. So the meat keeps the Jacobians' mean (its noise Gram matrix included), where
        # the curvature takes their cross products. Measured (session 34, the fits' kept
        # inputs re-evaluated): with the cross-product meat the paper simulation's
        # d 0.5 um / sigma_t 6 fit was 3.9 sigma off on sigma_t and 3.5 on the albedo, with
        # this meat 1.5 and 1.3; the one-channel benchmark's 18 noise draws, RMS z 1.18 /
        # 1.10 / 1.21 / 1.17 / 0.88 (sigma_t, albedo, b1-b3) before, 0.87 / 1.08 / 1.04 /
        # 1.03 / 0.79 with it.
        cov = correlation_factor(r, v_sensor + v_eval, valid) * (Hi @ gram(v_data.ravel(), meat_cross) @ Hi)
    else:
        modelled = Hi @ gram(var_r.ravel()) @ Hi
        cov = modelled * max(1.0, red)
    if render_correlation_out is not None:
        v_step = render_variance_factor * lr.v_eval
        c_step = Hi @ gram(np.where(valid & np.isfinite(v_step), v_step, 0.0).ravel()) @ Hi
        sd_step = np.sqrt(np.clip(np.diag(c_step), 0.0, None))
        with np.errstate(invalid="ignore", divide="ignore"):
            rho = np.where(np.outer(sd_step, sd_step) > 0, c_step / np.outer(sd_step, sd_step), 0.0)
        render_correlation_out.update({a: {b: float(np.clip(rho[i, j], -1.0, 1.0)) if i != j else 1.0
                                           for j, b in enumerate(names)} for i, a in enumerate(names)})
    if covariance_out is not None:
        covariance_out.update({a: {b: float(cov[i, j]) for j, b in enumerate(names)} for i, a in enumerate(names)})
    if not data_meat and red > 1.0:
        robust = Hi @ gram(r.ravel() ** 2) @ Hi
        # never below the noise-only sandwich, never above the uniformly inflated one
        cov = np.diag(np.clip(np.diag(robust), np.diag(modelled), np.diag(cov)))
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    s_unc = float(sd[-1]) * scale if fit_scale else float("nan")
    return {k: float(sd[i]) for i, k in enumerate(names)}, s_unc, red


#: Pixel lags along a profile over which `correlation_factor` sums the residuals' correlation.
UNCERTAINTY_CORRELATION_LAGS = 10


def _lag_correlations(r: np.ndarray, v: np.ndarray, valid: np.ndarray, lags: int) -> list[float]:
    """The correlation of the noise-normalised residuals r / sqrt(v) at lags 1..`lags` along
    the profiles ((R, W) arrays); [] where nothing is valid."""
    z = np.where(valid & (v > 0) & np.isfinite(r), r / np.sqrt(np.where(v > 0, v, 1.0)), 0.0)
    ok = z != 0.0
    if not ok.any():
        return []
    z = np.where(ok, z - z[ok].mean(), 0.0)
    norm = float(np.sum(z * z))
    if norm <= 0:
        return []
    return [float(np.sum(z[..., :-lag] * z[..., lag:])) / norm for lag in range(1, min(lags, z.shape[-1] - 1) + 1)]


def _bartlett(rho: Sequence[float], lags: int) -> float:
    return 1.0 + 2.0 * sum((1.0 - (i + 1) / (lags + 1)) * x for i, x in enumerate(rho))


def correlation_factor(r: np.ndarray, v: np.ndarray, valid: np.ndarray,
                       lags: int = UNCERTAINTY_CORRELATION_LAGS) -> float:
    """How much a smooth sum over pixels of the residuals' noise exceeds the sum of their
    variances: 1 + 2 sum_l (1 - l / (lags + 1)) rho_l, rho_l the correlation of the
    noise-normalised residuals r / sqrt(v) at lag l along the profiles (Bartlett weights, as
    in the Newey-West covariance), at least 1. A rendered profile's noise is correlated over
    a few pixels (lag 1: 0.2-0.5 on the one-channel benchmark, lag 5: 0.04-0.18), and the
    sandwich's diagonal meat treats pixels as independent. (R, W) arrays; one number."""
    return max(_bartlett(_lag_correlations(r, v, valid, lags), lags), 1.0)


def data_noise_variance(r: np.ndarray, v_sensor: np.ndarray, v_eval: np.ndarray, valid: np.ndarray
                        ) -> tuple[np.ndarray, float]:
    """The data's noise variance per pixel in the residuals' units, from the residuals r =
    data - evaluation render, and the share b of it that the variance channel does not hold.

    E r^2 = v_sensor + b v_eval + v_eval: the variance channel's noise, an excess shaped like
    the render's (a simulated truth's frozen Monte Carlo noise, or model error that follows
    the signal), and the evaluation render's own noise, which does not move the estimate.
    b is one number from thousands of pixels (`excess_share`). Per pixel, r^2 less v_eval
    was useless: where the render noise dominates (the one-channel benchmark: r^2 /
    (v_sensor + v_eval) 0.5-1.9 per angle, the excess about 1/16 of v_eval) the difference of
    two one-sample variances is mostly noise, and pooled over 15 pixels it still gave one
    benchmark draw's albedo an interval 1/50 of the others'. A weighted fit of b was no
    better: v_eval, a two-seed estimate, is near 0 in some pixels, which then dominated it
    (session 30).
    Returns (v_sensor + b v_eval, b).
    """
    ok = valid & np.isfinite(r) & np.isfinite(v_sensor) & np.isfinite(v_eval)
    b = excess_share(r, v_sensor, v_eval, valid)["b"]
    return np.where(ok, v_sensor + b * v_eval, 0.0), b


def excess_share(r: np.ndarray, v_sensor: np.ndarray, v_eval: np.ndarray, valid: np.ndarray,
                 lags: int = UNCERTAINTY_CORRELATION_LAGS) -> dict[str, float]:
    """The excess noise share b of `data_noise_variance`, with its standard error.

    The moment estimate b_raw = sum(r^2 - v_sensor - v_eval) / sum(v_eval) is a small
    difference of large sums: on the one-channel benchmark the truth's frozen render noise
    is about 1/16 of the evaluation render's, and b_raw came out below zero on 3 of 8 noise
    draws (session 36). Clipped at 0, the data's excess then left the sandwich altogether,
    and those draws' intervals were the narrow ones (the derived sigma_a 2.4 sigma off).

    Its standard error: sum r^2 over Gaussian residuals of variance s_i has variance
    2 sum s_i^2, times 1 + 2 sum_l w_l rho_l^2 for the residuals' correlation rho_l along the
    profiles (the squares of correlated Gaussians correlate by rho^2; Bartlett weights w_l,
    as in `correlation_factor`). b is a variance share, so b >= 0; given b_raw and its
    standard error se, with a flat prior on b >= 0 its posterior mean is
    b_raw + se phi(t) / Phi(t), t = b_raw / se: b_raw where it stands clear of 0, about
    0.8 se where it is 0, and positive always. The sandwich's meat is linear in b, so this
    mean is what its expected variance needs.

    Returns {"b": the posterior mean, "b_raw": the moment estimate, "se": its standard error}.
    """
    ok = valid & np.isfinite(r) & np.isfinite(v_sensor) & np.isfinite(v_eval)
    total = float(np.sum(v_eval[ok]))
    if total <= 0:
        return {"b": 0.0, "b_raw": 0.0, "se": 0.0}
    b_raw = float(np.sum(r[ok] ** 2 - v_sensor[ok] - v_eval[ok])) / total
    s = v_sensor + (1.0 + max(b_raw, 0.0)) * v_eval
    rho = _lag_correlations(r, np.where(ok, s, 0.0), ok, lags)
    kappa2 = max(1.0, _bartlett([x * x for x in rho], lags))
    se = math.sqrt(2.0 * kappa2 * float(np.sum(s[ok] ** 2))) / total
    if se <= 0:
        return {"b": max(b_raw, 0.0), "b_raw": b_raw, "se": 0.0}
    t = b_raw / se
    # phi(t) / Phi(t) in logs: exact far into the negative tail, where both vanish.
    mills = math.exp(stats.norm.logpdf(t) - stats.norm.logcdf(t))
    return {"b": max(0.0, b_raw + se * mills), "b_raw": b_raw, "se": se}


#: Drift t-statistic above which a parameter counts as still moving when the fit stopped.
#: Successive iterates are correlated (gradient momentum), so the naive standard error is
#: too small by ~2-3x; 5 keeps the flag for drifts several times their noise.
DRIFT_T = 5.0


def iterate_drift(history: Sequence[Sequence[float]], names: Sequence[str],
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


def window_estimate(rows: Sequence[Sequence[float]] | Sequence[np.ndarray], trend: bool) -> np.ndarray:
    """The result from the last iterates (rows): their mean, or with `trend` the value at the
    last row of a straight line fitted to each column (least squares), which removes the
    mean's lag behind iterates that drift steadily."""
    xs = np.asarray(rows, dtype=np.float64)
    if not trend or len(xs) < 3:
        return xs.mean(axis=0)
    t = np.arange(len(xs), dtype=np.float64)
    slope, icpt = np.polyfit(t, xs, 1)
    return icpt + slope * t[-1]


def window_scatter(rows: Sequence[Sequence[float]], trend: bool) -> np.ndarray:
    """The iterates about their summary (`window_estimate`): minus the mean, or minus their
    linear trend, so a steady drift is not counted as the optimiser's scatter."""
    xs = np.asarray(rows, dtype=np.float64)
    if not trend or len(xs) < 3:
        return xs - xs.mean(axis=0)
    t = np.arange(len(xs), dtype=np.float64)
    slope, icpt = np.polyfit(t, xs, 1)
    return xs - (icpt + np.outer(t, slope))


def combined_uncertainties(base: Mapping[str, float], spread: Mapping[str, float],
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


def combined_covariance(names: Sequence[str], unc: Mapping[str, float], sandwich: Mapping[str, Mapping[str, float]],
                        iterate_cov: np.ndarray, polish_se: Mapping[str, float] | None = None,
                        polish_correlation: Mapping[str, Mapping[str, float]] | None = None,
                        ) -> dict[str, dict[str, float]]:
    """Full covariance whose diagonal is the reported uncertainties squared.

    Its correlated part is what the correlations are known for: the sandwich covariance, the
    averaged iterates' own covariance and, with `polish_correlation`
    (`sandwich_uncertainties`' `render_correlation_out`), the polish points' standard error
    `polish_se` with the correlation of the render noise their steps carry. The rest of each
    reported variance (a drift, the Fisher bound's excess over the sandwich, the polish's
    share without that correlation) sits on the diagonal alone.

    Until session 36 the sandwich's correlations were stretched over the whole reported
    interval. Where the data meat's excess is zero (`data_noise_variance`'s b) the sandwich
    holds the sensor noise alone, 1e-4 of the interval, and the polish's standard error is
    nearly all of it; it then lent the sandwich's strong sigma_t-albedo correlation to an
    error that does not share it. On `bench_coverage.py`'s eight draws (3 such) the derived
    sigma_a came out 2.4 sigma RMS off (its interval 0.0013 /mm, the errors up to 0.007).
    With the polish's share on the diagonal sigma_a was right (1.11) but sigma_s' and g,
    whose errors the correlations narrow, 2.5-3x too wide. The polish's share with its
    render correlation was tried then and made them narrow instead (sigma_a 1.43, sigma_s'
    1.44), on the draws whose excess share b had been clipped to 0. Since session 37 b is its
    posterior mean (`excess_share`) and never 0; recomputed on 8 fresh draws' kept inputs
    (`benchmarks/coverage_variants.py`), RMS z sigma_a / sigma_s' / g: 0.69 / 0.31 / 0.33 with
    the share on the diagonal, 0.74 / 0.53 / 0.67 with its correlation (the fit's default,
    `FitSettings.uncertainty_polish_correlation`), 0.85 / 0.61 / 0.76 with the oracle's b
    (`docs/estimation-log.md`)."""
    k = len(names)
    c = np.array([[float(sandwich.get(a, {}).get(b, 0.0)) for b in names] for a in names]) if sandwich \
        else np.zeros((k, k))
    c = np.where(np.isfinite(c), c, 0.0) + iterate_cov
    if polish_se and polish_correlation:
        se = np.array([float(polish_se.get(n, 0.0)) for n in names])
        rho = np.array([[float(polish_correlation.get(a, {}).get(b, 1.0 if a == b else 0.0)) for b in names]
                        for a in names])
        c = c + np.where(np.isfinite(rho), rho, 0.0) * np.outer(se, se)
    var = np.array([float(unc[n]) for n in names]) ** 2
    d = np.clip(np.diag(c), 0.0, None)
    # a part may not exceed the variance reported (a drift that is not added, rounding)
    with np.errstate(invalid="ignore", divide="ignore"):
        f = np.where(d > var, np.sqrt(var / np.where(d > 0, d, 1.0)), 1.0)
    c = c * np.outer(f, f)
    full = c + np.diag(np.clip(var - np.diag(c), 0.0, None))
    return {a: {b: float(full[i, j]) for j, b in enumerate(names)} for i, a in enumerate(names)}
