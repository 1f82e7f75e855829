"""estimate.fit: recovery of known parameters on a tiny synthetic session, uncertainties."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2 as chi2_dist
from synth_session import make_session

from estimate.errors import DataError, ModelParameterError
from estimate.fit import (
    CPU_FINAL_SPP,
    GPU_FINAL_SPP,
    FitSettings,
    fit_channel,
    loss_at,
    sandwich_uncertainties,
)
from estimate.loss import (
    DEFAULT_CALIBRATION_ND,
    DEFAULT_COLLECTION_SR,
    calibrated_scale,
    decorrelated_loss,
    log_loss,
    log_measured,
    log_residual,
    profile_additive,
    profile_scale,
)
from estimate.problem import Problem, load_problem

TRUTH = {"sigma_t": 3.0, "albedo": 0.85, "phase.b1": 3.0, "phase.b2": 0.0, "phase.b3": 0.0}
PHASE = {k: v for k, v in TRUTH.items() if k.startswith("phase.")}
# One polish step (default 4): the polish has its own tests below; here it keeps the suite short.
FAST = {"max_iterations": 30, "spp_start": 128, "spp_max": 256, "final_spp": 512, "start_spp": 64, "window": 4,
        "lm_spp": 512, "lm_iterations": 4, "polish_steps": 1}


def _gn_matrix(jac: dict, prof: np.ndarray, delta: float | list[float] = 1e-3, fit_scale: bool = False,
               names: list[str] | None = None, **kw) -> np.ndarray:
    """The Gauss-Newton matrix (the inverse of `gn_inverse`, undamped) of a fake row problem
    whose profiles are `prof` (N, W), every pixel valid, parameters linear in z."""
    from types import SimpleNamespace

    from estimate.gauss_newton import gn_inverse
    from estimate.transforms import Transform

    names = names or sorted(jac)
    pb = SimpleNamespace(valid=np.ones(prof.shape, bool))
    lin = [Transform("linear", 0.1, -10, 10)] * len(names)
    return np.linalg.inv(gn_inverse(jac, names, lin, np.zeros(len(names)), pb, prof, delta, prof, fit_scale,
                                    damping=0.0, eig_floor=1e-12, **kw))


@pytest.fixture(scope="module")
def problem(tmp_path_factory):
    s = make_session(tmp_path_factory.mktemp("f") / "s", {"g": TRUTH}, angles=[30, 60, 120, 150], spp=1024,
                     width=128, scale=2e5)
    return load_problem(s, "g", columns=48)


def test_scale_profiling_and_loss_gradient():
    rng = np.random.default_rng(0)
    model = rng.uniform(0.1, 1.0, (3, 20))
    valid = np.ones_like(model, bool)
    meas = 7.0 * model
    assert profile_scale(meas, model, valid, 1e-2) == pytest.approx(7.0, rel=1e-4)
    _, g = log_loss(meas, model * 1.1, valid, 7.0, 1e-2)
    eps = 1e-6
    d = np.zeros_like(model)
    d[1, 3] = eps
    fd = (log_loss(meas, model * 1.1 + d, valid, 7.0, 1e-2)[0] - log_loss(meas, model * 1.1 - d, valid, 7.0, 1e-2)[0]) / (2 * eps)
    assert g[1, 3] == pytest.approx(fd, rel=1e-5)


def test_log_residuals_of_a_scaled_row_clip_dark_pixels_and_skip_invalid_ones():
    """The one residual every loss uses: zero where the model is the measurement over the
    scale; a measurement's noise below -delta/2 and a render's below 0 stay finite; invalid
    pixels give 0; the decorrelated loss of two equal renders is their plain loss."""
    rng = np.random.default_rng(5)
    model = rng.uniform(0.1, 1.0, (2, 16))
    valid = np.ones_like(model, bool)
    valid[1, 4] = False
    meas = 3.0 * model
    meas[0, 2] = -50.0  # a dark pixel's read noise
    lm, delta = log_measured(meas, valid, 3.0, 0.01)
    assert delta == pytest.approx(0.01 * float(model[valid].max()))
    assert lm[0, 2] == pytest.approx(np.log(0.5 * delta))
    noisy = model.copy()
    noisy[0, 5] = -1.0
    r = log_residual(lm, noisy, valid, delta)
    assert np.all(np.isfinite(r)) and r[1, 4] == 0.0
    assert np.allclose(np.delete(r.ravel(), [2, 5]), 0.0, atol=1e-12)
    assert r[0, 5] == pytest.approx(np.log(model[0, 5] + delta) - np.log(delta))
    plain = log_loss(meas, noisy, valid, 3.0, 0.01)[0]
    assert decorrelated_loss(meas, noisy, noisy, valid, 3.0, 0.01) == pytest.approx(plain)
    assert plain == pytest.approx(float(np.sum(r * r)) / valid.sum())


@pytest.mark.parametrize("delta_rel", [1e-3, 0.1])
def test_additive_parameters_solved_exactly_and_within_bounds(delta_rel):
    """An offset and slope added to a render are recovered from the log loss whatever delta
    weighs the tails, starting from other values; a lower bound holds."""
    rng = np.random.default_rng(3)
    x = np.linspace(-8.0, 8.0, 64)
    model = np.exp(-x ** 2 / 4.0)[None, :] * rng.uniform(0.5, 2.0, (5, 1))   # the render at the old values
    cols = {"o": np.ones_like(model), "k": np.broadcast_to(x, model.shape).copy()}
    valid = np.ones_like(model, bool)
    old = {"o": 0.05, "k": -0.001}
    truth = {"o": 0.02, "k": 0.0015}
    meas = 40.0 * (model + (truth["o"] - old["o"]) + (truth["k"] - old["k"]) * x)
    got = profile_additive(meas, model, valid, 40.0, delta_rel, cols, old,
                           {"o": (0.0, math.inf), "k": (-math.inf, math.inf)})
    assert got["o"] == pytest.approx(truth["o"], rel=1e-6)
    assert got["k"] == pytest.approx(truth["k"], rel=1e-6)
    # The data want a negative offset: the bound stops it at 0.
    meas_neg = 40.0 * (model - old["o"] - 0.01 + (truth["k"] - old["k"]) * x)
    got = profile_additive(meas_neg, model, valid, 40.0, delta_rel, cols, old,
                           {"o": (0.0, math.inf), "k": (-math.inf, math.inf)})
    assert 0.0 <= got["o"] < 1e-5


def test_gn_matrix_with_solved_columns_is_the_schur_complement():
    """Projecting a solved (additive) parameter's column out of the Gauss-Newton matrix gives
    the curvature of the loss with that parameter re-solved at every step: the Schur
    complement of the full matrix."""
    n, w = 3, 40
    x = np.linspace(-1.0, 1.0, w)
    prof = np.tile(np.exp(-4.0 * x ** 2), (n, 1)) * np.array([[1.0], [0.7], [1.3]])
    ones = np.ones_like(prof)
    jac = {"a": prof, "b": ones + 0.3 * prof * x, "c": ones}
    full = _gn_matrix(jac, prof, 0.01)
    schur = full[:2, :2] - np.outer(full[:2, 2], full[2, :2]) / full[2, 2]
    solved = _gn_matrix(jac, prof, 0.01, names=["a", "b"], profiled_columns=[ones])
    assert solved == pytest.approx(schur, rel=1e-6)
    assert not np.allclose(schur, full[:2, :2], rtol=0.05)


def test_gn_matrix_over_several_deltas_is_the_mean_of_their_matrices():
    """The delta-averaged Gauss-Newton matrix (the fit's randomly drawn delta averaged out) is
    the mean of the single-delta matrices, with the profiled scale projected out per delta;
    small and large deltas weight the dim tails differently, so the matrices differ."""
    n, w = 2, 60
    x = np.linspace(-3.0, 3.0, w)
    prof = np.tile(np.exp(-2.0 * x ** 2) + 1e-3, (n, 1))
    jac = {"a": prof * x ** 2, "b": prof * np.abs(x)}

    def h(dl):
        return _gn_matrix(jac, prof, dl, fit_scale=True)

    small, large = h(0.002), h(0.1)
    assert not np.allclose(small, large, rtol=0.5)
    assert h([0.002, 0.1]) == pytest.approx(0.5 * (small + large), rel=1e-6)
    assert h([0.1]) == pytest.approx(large, rel=1e-12)


def test_calibrated_scale_from_beam_power_and_lens(problem, tmp_path):
    cal = calibrated_scale(problem.session_path, "g", problem.beam.power())
    assert cal.scale == pytest.approx(2e5, rel=1e-6) and cal.defaults == ()
    assert cal.scale == pytest.approx(cal.power_e_per_s / cal.calibration_nd * cal.pixel_area_mm2 * cal.collection_sr
                                      / cal.beam_power)
    # The scale decides the loss: the truth fits better with the right one than with 1.3 x it.
    right = loss_at(problem, "exp3", TRUTH, spp=256, fixed_scale=cal.scale)["loss"]
    assert right < loss_at(problem, "exp3", TRUTH, spp=256, fixed_scale=1.3 * cal.scale)["loss"]
    # A rig configuration without the keys: the documented defaults, named.
    s = make_session(tmp_path / "s", {"g": TRUTH}, angles=[30, 150], spp=4, width=32, lens_config=False)
    d = calibrated_scale(s, "g", 1.0e6)
    assert set(d.defaults) == {"camera.collection_sr", "camera.calibration_nd"}
    assert (d.collection_sr, d.calibration_nd) == (DEFAULT_COLLECTION_SR, DEFAULT_CALIBRATION_ND)
    with pytest.raises(DataError, match="no beam power for channel 'r'"):
        calibrated_scale(problem.session_path, "r", 1.0e6)


def _toy_log_fit(m: np.ndarray, x: np.ndarray, dl: float) -> np.ndarray:
    """(a, b) of the log-loss fit of a exp(-b x) to the unit-scale profile m, delta dl x its peak."""
    from scipy.optimize import least_squares

    d = dl * m.max()
    lm = np.log(np.clip(m, -0.5 * d, None) + d)
    return least_squares(lambda th: lm - np.log(th[0] * np.exp(-th[1] * x) + d), [0.9, 1.0]).x


def test_sandwich_uncertainties_match_scatter():
    """A toy log-loss fit (I = a exp(-b x), no renders) over many noise draws: the sandwich
    1-sigma matches the scatter of the estimates; the scale, when fitted, is profiled."""
    x = np.linspace(0.0, 3.0, 60)
    a, b, s_true = 1.0, 1.2, 50.0
    model = a * np.exp(-b * x)
    var = 0.005 * s_true * model * s_true + 0.2   # Poisson-like, e-/s units (HDR: a few % per pixel)
    rng = np.random.default_rng(1)
    dl = 0.03
    est, pred = [], []
    for _ in range(60):
        meas = (s_true * model + rng.normal(0.0, np.sqrt(var)))[None, :]
        th = _toy_log_fit(meas[0] / s_true, x, dl)
        prof = (th[0] * np.exp(-th[1] * x))[None, :]
        pb = Problem(np.array([0.0]), x, meas, var[None, :], None, None, "t", None)  # type: ignore[arg-type]
        jac = {"a": prof / th[0], "b": -x * prof}
        u, su, red = sandwich_uncertainties(pb, {"a": th[0], "b": th[1]}, ["a", "b"], s_true, prof,
                                            np.zeros_like(prof), jac, delta_rel=dl, fit_scale=False)
        est.append(th)
        pred.append([u["a"], u["b"]])
        assert math.isnan(su) and 0.3 < red < 3.0
    spread = np.std(np.array(est), axis=0, ddof=1)
    mean_pred = np.mean(np.array(pred), axis=0)
    assert np.all(np.abs(mean_pred / spread - 1.0) < 0.35), (mean_pred, spread)



def test_data_meat_leaves_the_evaluation_renders_noise_out():
    """Data with unreported noise (3x the variance channel: frozen render noise of a simulated
    truth), fitted exactly; the sandwich sees the residual against a noisy evaluation render
    (variance 4x the data's, as `model_variance` says). With `data_meat` the interval matches
    the estimates' scatter: the render noise is left out (the polish points' scatter carries
    it in a fit). Without, it is counted as data noise and the interval is ~2x too wide."""
    x = np.linspace(0.0, 3.0, 90)
    a, b, s_true = 1.0, 1.2, 50.0
    model = a * np.exp(-b * x)
    var = 1e-4 * s_true * model * s_true + 0.002          # 1 % at the peak, as reported
    true_var = 9.0 * var                                   # sd 3x what the variance channel says
    mv = 4.0 * true_var / s_true ** 2                      # the evaluation render's, unit-power units
    rng = np.random.default_rng(3)
    dl = 0.03
    est, with_dm, without = [], [], []
    for _ in range(60):
        meas = (s_true * model + rng.normal(0.0, np.sqrt(true_var)))[None, :]
        th = _toy_log_fit(meas[0] / s_true, x, dl)
        exact = (th[0] * np.exp(-th[1] * x))[None, :]
        rendered = exact + rng.normal(0.0, np.sqrt(mv))[None, :]
        pb = Problem(np.array([0.0]), x, meas, var[None, :], None, None, "t", None)  # type: ignore[arg-type]
        jac = {"a": exact / th[0], "b": -x * exact}
        for out, dm in ((with_dm, True), (without, False)):
            u, _, _ = sandwich_uncertainties(pb, {"a": th[0], "b": th[1]}, ["a", "b"], s_true, rendered,
                                             mv[None, :], jac, delta_rel=dl, fit_scale=False, data_meat=dm)
            out.append([u["a"], u["b"]])
        est.append(th)
    spread = np.std(np.array(est), axis=0, ddof=1)
    assert np.all(np.abs(np.mean(with_dm, axis=0) / spread - 1.0) < 0.3), (np.mean(with_dm, axis=0), spread)
    assert np.all(np.mean(without, axis=0) / spread > 1.6), (np.mean(without, axis=0), spread)


def test_render_correlation_is_that_of_estimates_scattered_by_render_noise():
    """The polish points scatter about the optimum by the render noise of the gradient they
    step with. A toy log-loss fit to profiles carrying render noise alone (variance
    `render_variance_factor` x `model_variance`): the correlation of its estimates is the
    one `render_correlation_out` reports (a, b of a exp(-b x): strongly correlated)."""
    x = np.linspace(0.0, 3.0, 90)
    a, b, s_true, dl = 1.0, 1.2, 50.0, 0.03
    model = a * np.exp(-b * x)
    mv = (0.02 * model) ** 2 + 1e-6                # the evaluation render's variance, unit-power units
    rng = np.random.default_rng(5)
    est = [_toy_log_fit(model + rng.normal(0.0, np.sqrt(2.0 * mv)), x, dl) for _ in range(300)]
    empirical = float(np.corrcoef(np.array(est).T)[0, 1])
    pb = Problem(np.array([0.0]), x, (s_true * model)[None, :], np.full((1, x.size), 1e-6), None, None, "t",
                 None)  # type: ignore[arg-type]
    corr: dict[str, dict[str, float]] = {}
    sandwich_uncertainties(pb, {"a": a, "b": b}, ["a", "b"], s_true, model[None, :], mv[None, :],
                           {"a": model[None, :] / a, "b": (-x * model)[None, :]}, delta_rel=dl, fit_scale=False,
                           data_meat=True, render_variance_factor=2.0, render_correlation_out=corr)
    assert corr["a"]["a"] == 1.0 and corr["a"]["b"] == pytest.approx(corr["b"]["a"])
    assert abs(empirical) > 0.3 and corr["a"]["b"] == pytest.approx(empirical, abs=0.1)


def test_correlation_factor_counts_noise_shared_between_neighbouring_pixels():
    """White noise: a sum over pixels has the sum of their variances (factor ~1). Noise
    averaged over 3 neighbouring pixels (a render's reconstruction filter): a smooth sum
    has ~3x that variance, which a diagonal meat would miss."""
    from scipy import ndimage

    from estimate.uncertainties import correlation_factor

    rng = np.random.default_rng(8)
    white = rng.standard_normal((10, 400))
    valid = np.ones(white.shape, bool)
    smooth = ndimage.uniform_filter1d(rng.standard_normal((10, 400)), 3, axis=-1)
    v = np.ones(white.shape)
    assert 1.0 <= correlation_factor(white, v, valid) < 1.15
    k3 = correlation_factor(smooth, v / 3.0, valid)
    assert 2.5 < k3 < 3.2, k3
    # only the correlation counts, not the level, and invalid pixels are left out
    assert correlation_factor(5.0 * smooth, 25.0 * v, valid) == pytest.approx(k3)
    holes = valid.copy()
    holes[:, ::7] = False
    assert 2.3 < correlation_factor(smooth, v, holes) < 3.2


def test_excess_share_has_a_calibrated_standard_error_and_never_collapses_to_zero():
    """The data meat's excess share b: residuals r = excess + evaluation noise + sensor noise,
    with an excess b v_eval of 1/16 of the render's own noise (the one-channel benchmark's
    frozen truth noise), white and correlated over 3 pixels. The moment estimate scatters by
    its standard error (z about unit spread) and falls below 0 on some draws; the reported b,
    its posterior mean given b >= 0, stays positive there, near 0.8 se where b_raw is 0, and
    is b_raw where that stands clear of 0."""
    from scipy import ndimage

    from estimate.uncertainties import data_noise_variance, excess_share

    rng = np.random.default_rng(21)
    shape = (10, 120)
    valid = np.ones(shape, bool)
    v_eval = np.exp(rng.uniform(-1.0, 1.0, shape))
    v_sensor = 0.2 * v_eval
    for smooth in (False, True):
        zs, lows = [], []
        for _ in range(200):
            e = rng.standard_normal((3, *shape))
            if smooth:   # unit variance after a 3-pixel box filter
                e = ndimage.uniform_filter1d(e, 3, axis=-1) * math.sqrt(3.0)
            r = np.sqrt(v_sensor) * e[0] + np.sqrt(v_eval) * e[1] + np.sqrt(v_eval / 16) * e[2]
            x = excess_share(r, v_sensor, v_eval, valid)
            zs.append((x["b_raw"] - 1 / 16) / x["se"])
            if x["b_raw"] < 0:
                lows.append(x)
            assert x["b"] > 0 and x["b"] >= x["b_raw"]
        assert 0.8 < np.std(zs) < 1.25, (smooth, np.std(zs))
        assert abs(np.mean(zs)) < 0.3
        assert lows, "b_raw below zero on some draws, as on the benchmark"
        assert all(0.3 * x["se"] < x["b"] < x["se"] for x in lows)
    # clear of zero: the moment estimate itself; the variance returned carries it
    r = np.sqrt(v_sensor + 2.0 * v_eval) * rng.standard_normal(shape)
    x = excess_share(r, v_sensor, v_eval, valid)
    assert x["b"] == pytest.approx(x["b_raw"], rel=1e-3) and x["b"] == pytest.approx(1.0, abs=0.2)
    v, b = data_noise_variance(r, v_sensor, v_eval, valid)
    assert b == x["b"] and np.allclose(v, v_sensor + b * v_eval)


def test_sandwich_curvature_from_cross_products_of_noisy_jacobians():
    """Along a weak direction one Monte Carlo Jacobian's A^T A is inflated by its noise's
    Gram matrix, so its sandwich is too narrow there; the cross products of independent
    Jacobians (`jac_more`) give the noise-free Jacobian's interval."""
    rng = np.random.default_rng(5)
    n, w = 4, 200
    x = np.linspace(-3.0, 3.0, w)
    prof = np.exp(-np.abs(x))[None, :] * np.ones((n, 1))
    s, var = 100.0, 0.01 * 100.0 * prof + 1e-3
    pb = Problem(np.zeros(n), x, s * prof + rng.normal(0.0, np.sqrt(var)), var, None, None, "t", None)  # type: ignore[arg-type]
    true = {"a": prof, "b": prof * (1.0 + 0.05 * x)}     # nearly parallel: a valley

    def noisy():
        return {k: v + 0.05 * prof * rng.standard_normal(v.shape) for k, v in true.items()}

    def sd_b(jac, more=()):
        return sandwich_uncertainties(pb, {}, ["a", "b"], s, prof, np.zeros_like(prof), jac, delta_rel=0.01,
                                      fit_scale=False, jac_more=more)[0]["b"]

    exact = sd_b(true)
    single = np.mean([sd_b(noisy()) for _ in range(20)])
    pair = np.mean([sd_b(noisy(), [noisy()]) for _ in range(20)])
    four = np.mean([sd_b(noisy(), [noisy(), noisy(), noisy()]) for _ in range(20)])
    assert single < 0.8 * exact
    assert pair == pytest.approx(exact, rel=0.1) and four == pytest.approx(exact, rel=0.1)


def test_data_meat_holds_the_noise_of_the_jacobians_the_steps_use():
    """The polish steps with the gradient of its Monte Carlo Jacobians, whose noise E adds
    E^T S E to the gradient's variance: with the Jacobians fixed, the spread of such a step
    over noise draws of the data is the data-meat sandwich's interval (the Jacobians' mean in
    the meat, their cross products in the curvature). The cross-product meat (`meat_cross`,
    sessions 30-33) leaves E^T S E out and falls short of it."""
    rng = np.random.default_rng(11)
    n, w = 4, 200
    x = np.linspace(-3.0, 3.0, w)
    prof = np.exp(-np.abs(x))[None, :] * np.ones((n, 1))
    s, var = 100.0, 0.01 * 100.0 * prof + 1e-3
    true = {"a": prof, "b": prof * (1.0 + 0.05 * x)}     # nearly parallel: a valley
    j1, j2 = ({k: v + 0.1 * prof * rng.standard_normal(v.shape) for k, v in true.items()} for _ in range(2))
    dl = 0.01 * float(prof.max())

    def cols(j):
        return np.stack([np.ravel(-j[k] / (prof + dl)) for k in ("a", "b")], axis=1)

    c1, c2 = cols(j1), cols(j2)
    h = 0.5 * (c1.T @ c2 + c2.T @ c1)
    g = 0.5 * (c1 + c2)
    steps, sds, exact, crossed = [], [], [], []
    for _ in range(300):
        meas = s * prof + rng.normal(0.0, np.sqrt(var))
        r = np.ravel(np.log(meas / s + dl) - np.log(prof + dl))
        steps.append(-np.linalg.solve(h, g.T @ r))
        pb = Problem(np.zeros(n), x, meas, var, None, None, "t", None)  # type: ignore[arg-type]
        kw: dict = {"delta_rel": 0.01, "fit_scale": False, "data_meat": True}
        sds.append(sandwich_uncertainties(pb, {}, ["a", "b"], s, prof, np.zeros_like(prof), j1, jac_more=[j2],
                                          **kw)[0]["b"])
        if len(exact) < 20:
            exact.append(sandwich_uncertainties(pb, {}, ["a", "b"], s, prof, np.zeros_like(prof), true, **kw)[0]["b"])
            crossed.append(sandwich_uncertainties(pb, {}, ["a", "b"], s, prof, np.zeros_like(prof), j1,
                                                  jac_more=[j2], meat_cross=True, **kw)[0]["b"])
    spread = float(np.std(np.array(steps)[:, 1], ddof=1))
    assert np.mean(sds) == pytest.approx(spread, rel=0.15), (np.mean(sds), spread)
    # The cross-product meat estimates the noise-free Jacobian's meat and misses E^T S E
    # (0.74-0.83 of the spread at seeds 11-14; the noise-free Jacobian's own interval is
    # 0.75-1.0 of it, depending on the draw of the Jacobians' noise).
    assert np.mean(crossed) < 0.9 * spread, (np.mean(crossed), spread)
    assert np.mean(exact) < 1.05 * spread


def test_robust_sandwich_meat_from_cross_products_of_noisy_jacobians():
    """Residuals 30x the stated noise in the tails (the frozen Monte Carlo noise of a simulated
    truth) select the robust meat A^T diag(r^2) A. Built from the Jacobians' mean, it also
    carries their noise's Gram matrix weighted by r^2, which the cross-product curvature
    does not: with two 15 %-noisy Jacobians that interval was 1.9x the noise-free one's
    (four: 1.4x). Its cross products give the noise-free Jacobian's interval."""
    rng = np.random.default_rng(5)
    n, w = 4, 200
    x = np.linspace(-3.0, 3.0, w)
    prof = np.exp(-np.abs(x))[None, :] * np.ones((n, 1))
    s, var = 100.0, 0.01 * 100.0 * prof + 1e-3
    excess = np.where(np.abs(x) > 1.5, 30.0, 1.0)
    pb = Problem(np.zeros(n), x, s * prof + excess * rng.normal(0.0, np.sqrt(var)), var,  # type: ignore[arg-type]
                 None, None, "t", None)
    true = {"a": prof, "b": prof * (1.0 + 0.05 * x)}

    def noisy():
        return {k: v + 0.15 * prof * rng.standard_normal(v.shape) for k, v in true.items()}

    def sd_b(jac, more=()):
        u, _, red = sandwich_uncertainties(pb, {}, ["a", "b"], s, prof, np.zeros_like(prof), jac, delta_rel=0.01,
                                           fit_scale=False, jac_more=more)
        assert red > 100.0     # the robust branch
        return u["b"]

    exact = sd_b(true)
    pair = np.mean([sd_b(noisy(), [noisy()]) for _ in range(20)])
    four = np.mean([sd_b(noisy(), [noisy(), noisy(), noisy()]) for _ in range(20)])
    assert pair == pytest.approx(exact, rel=0.15) and four == pytest.approx(exact, rel=0.15)


def test_recovers_sigma_t_and_albedo(problem):
    est = []
    for seed in (0,):
        r = fit_channel(problem, "exp3", fixed=PHASE, settings=FitSettings(seed=seed, scale="calibrated", **FAST))
        est.append(r)
        assert set(r.uncertainties) == {"sigma_t", "albedo"}
        assert all(math.isfinite(u) and u > 0 for u in r.uncertainties.values())
        assert r.fitted.shape == problem.measured.shape
        assert r.iterations <= FAST["max_iterations"] and r.spp_schedule[0] == [0, 128]
        assert r.scale == pytest.approx(2e5) and r.scale_mode == "calibrated"
        assert r.dof == int(problem.valid.sum()) - 2
        # the sandwich is never below the ideal linear-chi^2 bound
        assert all(r.uncertainties[k] >= r.fisher_uncertainties[k] for k in r.uncertainties)
    for r in est:
        assert r.parameters["sigma_t"] == pytest.approx(3.0, rel=0.1)
        assert abs(r.parameters["albedo"] - 0.85) < 0.03
    # The fit is no worse than a wrong parameter set by far (loss at a clearly wrong point).
    wrong = loss_at(problem, "exp3", {**TRUTH, "sigma_t": 0.7, "albedo": 0.5}, spp=256, fixed_scale=2e5)["loss"]
    assert est[0].loss < wrong
    # Final loss near the noise floor (the loss at the true parameters, same spp and delta).
    assert est[0].loss < 1.5 * loss_at(problem, "exp3", TRUTH, spp=512, fixed_scale=2e5)["loss"]


@pytest.mark.parametrize("solve", [True, False])
def test_radiance_valued_extension_parameters_are_fitted(problem, solve):
    """A stray-light offset of 2 % of the peak added to the recording is recovered, solved
    on every iteration's render (the default) or stepped by the optimiser (its z unit
    follows the render's peak, 1e7-scale radiances, so neither Adam's step nor the
    Gauss-Newton eigenvalue floor leaves it at its start)."""
    from dataclasses import replace

    from estimate.forward import ForwardModel

    fm = ForwardModel(problem.geometry, problem.beam, phase="exp3", extensions=("stray_light",))
    peak = float(fm.render_profiles(TRUTH, problem.angles_deg, spp=256, seed=1).max())
    offset = 0.02 * peak
    pb = replace(problem, measured=problem.measured + 2e5 * offset)
    r = fit_channel(pb, "exp3", extensions=("stray_light",), fixed=PHASE,
                    start={"sigma_t": 2.6, "albedo": 0.8},
                    settings=FitSettings(seed=1, scale="calibrated", uncertainties=False, profile_additive=solve,
                                         **FAST))
    assert r.solved == (["stray_light.offset", "stray_light.slope_per_mm"] if solve else [])
    assert r.parameters["stray_light.offset"] == pytest.approx(offset, rel=0.1 if solve else 0.3)
    assert r.parameters["sigma_t"] == pytest.approx(3.0, rel=0.05 if solve else 0.1)


@pytest.mark.parametrize("peak", [1.0, 1.1e7])
def test_radiance_valued_transforms_follow_the_render_scale(peak):
    """In z, a radiance-valued parameter is measured in fractions of the peak, so the
    optimiser's steps and its Gauss-Newton columns (J dx/dz) do not depend on the render's
    units; bounds hold in x."""
    from estimate.extensions.stray_light import StrayLight
    from estimate.transforms import RADIANCE_UNIT, transform_for

    spec = {p.name: p for p in StrayLight.parameters}["offset"]
    t = transform_for("stray_light.offset", spec, peak)
    assert t.dx_dz(0.0) == pytest.approx(RADIANCE_UNIT * peak)
    assert t.to_x(t.to_z(0.03 * peak)) == pytest.approx(0.03 * peak)
    assert t.to_x(-5.0) == 0.0 and t.clamp_z(-5.0) == 0.0  # offset >= 0
    assert t.lr * t.dx_dz(0.0) / peak == pytest.approx(0.3 * RADIANCE_UNIT)
    assert transform_for("albedo", spec, peak).kind == "logit"  # named parameters keep theirs
    # The slope's z unit moves the profile's ends (half-width 8.5 mm) as far as the offset's.
    slope = {p.name: p for p in StrayLight.parameters}["slope_per_mm"]
    ts = transform_for("stray_light.slope_per_mm", slope, peak, 8.5)
    assert ts.dx_dz(0.0) * 8.5 == pytest.approx(t.dx_dz(0.0))
    assert transform_for("stray_light.slope_per_mm", slope, peak).dx_dz(0.0) == pytest.approx(t.dx_dz(0.0))


def test_fixed_parameters_stay(problem):
    r = fit_channel(problem, "tthg", start={"sigma_t": 3.0, "albedo": 0.85},
                    fixed={"phase.g_backward": -0.2, "phase.w_forward": 0.95},
                    settings=FitSettings(seed=3, max_iterations=6, spp_start=16, spp_max=16, final_spp=32,
                                         window=3, uncertainties=False, lm_iterations=0, scale="free"))
    assert r.scale_mode == "free" and r.scale_calibration is None
    assert r.parameters["phase.g_backward"] == -0.2 and r.parameters["phase.w_forward"] == 0.95
    assert r.start["sigma_t"] == 3.0 and r.iterations == 6 and r.stop_reason == "max_iterations"


def test_with_a_polish_the_iterations_hand_over_after_their_count(problem, monkeypatch):
    """With a polish the stochastic iterations stop after `iterations_before_polish`, and the
    uncertainties leave their spread out (the result is the polish's) and take the polish's
    last Jacobians without rendering one at the final point; without a polish the iterations
    run on (here to max_iterations) and their spread is part of the interval."""
    import estimate.fit as fit_mod

    central: list[int] = []
    real = fit_mod.gn_jacobian
    monkeypatch.setattr(fit_mod, "gn_jacobian", lambda *a, **k: central.append(1) or real(*a, **k))
    base = {"seed": 5, "max_iterations": 7, "spp_start": 16, "spp_max": 16, "final_spp": 32, "window": 3,
            "lm_iterations": 0, "scale": "free", "uncertainty_spp": 32, "iterations_before_polish": 4}
    polish = {"polish_steps": 2, "polish_max_steps": 2, "polish_average_from": 1}
    r = fit_channel(problem, "exp3", start={"sigma_t": 3.0, "albedo": 0.85}, settings=FitSettings(**base, **polish))
    assert r.iterations == 4 and r.stop_reason == "handed to the polish after 4 iterations"
    assert sum(e["accepted"] for e in r.polish) == 2 and not central
    assert set(r.optimizer_spread) >= {"sigma_t", "albedo"} and not any(r.optimizer_spread.values())
    assert all(np.isfinite(v) and v > 0 for v in r.uncertainties.values())
    fit_channel(problem, "exp3", start={"sigma_t": 3.0, "albedo": 0.85},
                settings=FitSettings(**base, **polish, uncertainty_final_jacobian=True))
    assert len(central) == 1
    r0 = fit_channel(problem, "exp3", start={"sigma_t": 3.0, "albedo": 0.85},
                     settings=FitSettings(**base, polish_steps=0))
    assert r0.iterations == 7 and r0.stop_reason == "max_iterations" and not r0.polish
    assert r0.optimizer_spread["sigma_t"] > 0.0


def test_final_spp_default_follows_the_variant(monkeypatch):
    assert FitSettings.for_variant("cuda_ad_mono").final_spp == GPU_FINAL_SPP > CPU_FINAL_SPP
    assert FitSettings.for_variant("llvm_ad_mono", seed=3).final_spp == CPU_FINAL_SPP == FitSettings().final_spp
    assert FitSettings.for_variant("cuda_ad_mono", final_spp=64).final_spp == 64
    # None: the variant init_mitsuba would pick (RIG_MITSUBA_VARIANT first).
    monkeypatch.setenv("RIG_MITSUBA_VARIANT", "cuda_ad_mono")
    assert FitSettings.for_variant(scale="calibrated").final_spp == GPU_FINAL_SPP
    monkeypatch.setenv("RIG_MITSUBA_VARIANT", "llvm_ad_mono")
    assert FitSettings.for_variant().final_spp == CPU_FINAL_SPP


def test_iterations_before_polish_setting_is_checked():
    assert FitSettings.from_dict({"iterations_before_polish": None}).iterations_before_polish is None
    with pytest.raises(ModelParameterError, match="iterations_before_polish"):
        FitSettings.from_dict({"iterations_before_polish": 0}, where="results.yaml")


def test_engine_setting_is_checked():
    """A results.yaml whose engine was edited is refused when read, before a diagnosis runs."""
    assert FitSettings.from_dict({"engine": "camera"}).engine == "camera"
    assert FitSettings().engine == "light"
    with pytest.raises(ModelParameterError, match="settings.fit: fit setting engine = 'photons'"):
        FitSettings.from_dict({"engine": "photons"}, where="settings.fit")


def _toy_problem(x, meas):
    return Problem(np.array([0.0]), x, meas, np.ones_like(meas), np.ones_like(meas, bool), None, "t", None)  # type: ignore[arg-type]


def test_gauss_newton_step_solves_the_linearised_log_fit():
    """`gn_direction` with the exact Jacobian: one step = the linear least-squares step of the
    log residuals; repeated full steps on I = a exp(-b x) converge to the truth."""
    from estimate.gauss_newton import gn_direction
    from estimate.transforms import Transform

    x = np.linspace(0.0, 3.0, 50)
    tr = [Transform("log", 0.1), Transform("linear", 0.1, -10.0, 10.0)]
    meas = (2.0 * np.exp(-1.3 * x))[None, :]
    pb = _toy_problem(x, meas)
    dl = 1e-3 * float(meas.max())
    theta = np.array([1.2, 0.8])
    for step in range(8):
        prof = (theta[0] * np.exp(-theta[1] * x))[None, :]
        jac = {"a": prof / theta[0], "b": -x * prof}
        z = np.array([math.log(theta[0]), theta[1]])
        r = np.log(meas + dl) - np.log(prof + dl)
        A = np.stack([(-jac["a"] / (prof + dl)).ravel() * theta[0], (-jac["b"] / (prof + dl)).ravel()], axis=1)
        g = 2.0 * A.T @ r.ravel() / r.size
        dz = gn_direction(jac, ["a", "b"], tr, z, pb, prof, dl, meas, False, g, damping=0.0)
        if step == 0:
            assert np.allclose(dz, -np.linalg.lstsq(A, r.ravel(), rcond=None)[0], rtol=1e-8)
        z = z + dz
        theta = np.array([math.exp(z[0]), z[1]])
    assert theta == pytest.approx([2.0, 1.3], rel=1e-6)


def test_gauss_newton_with_profiled_scale_matches_the_joint_step():
    """With the scale profiled out, the step equals the parameters' part of the joint
    least-squares step over (parameters, log scale) at the optimal scale (a_s^T r = 0)."""
    from estimate.gauss_newton import gn_direction
    from estimate.transforms import Transform

    rng = np.random.default_rng(4)
    x = np.linspace(0.0, 3.0, 40)
    prof = np.exp(-x)[None, :]
    meas = prof * (1.0 + 0.05 * rng.normal(size=prof.shape))
    pb = _toy_problem(x, meas)
    dl = 1e-3
    jac = {"a": (x ** 2)[None, :] * prof, "b": -np.sin(2.0 * x)[None, :] * prof}
    tr = [Transform("linear", 0.1, -10, 10), Transform("linear", 0.1, -10, 10)]
    A = np.stack([(-jac[n] / (prof + dl)).ravel() for n in ("a", "b")], axis=1)
    a_s = (-meas / (meas + dl)).ravel()
    r = (np.log(meas + dl) - np.log(prof + dl)).ravel()
    r = r - a_s * (a_s @ r) / (a_s @ a_s)                      # at the profiled (optimal) scale
    joint = -np.linalg.lstsq(np.column_stack([A, a_s]), r, rcond=None)[0]
    g = 2.0 * A.T @ r / r.size
    dz = gn_direction(jac, ["a", "b"], tr, np.zeros(2), pb, prof, dl, meas, True, g, damping=0.0)
    assert dz == pytest.approx(joint[:2], rel=1e-5)


def test_unknown_optimizer_is_refused(problem):
    from estimate.errors import ModelParameterError

    with pytest.raises(ModelParameterError, match="unknown optimizer"):
        fit_channel(problem, "exp3", start={"sigma_t": 3.0, "albedo": 0.85},
                    settings=FitSettings(optimizer="lbfgs", max_iterations=1))


def test_gauss_newton_step_is_short_along_an_unconstrained_direction():
    """A parameter the data do not constrain (two-term HG's g_backward once the forward
    lobe's weight is 1: its column is zero) gets a short gradient step from the eigenvalue
    floor, not a noise-amplified Newton step; the constrained parameter's step is the
    least-squares one."""
    from estimate.gauss_newton import GN_EIG_FLOOR, gn_direction
    from estimate.transforms import Transform

    x = np.linspace(0.0, 3.0, 50)
    prof = np.exp(-x)[None, :]
    meas = prof * 1.1
    pb = _toy_problem(x, meas)
    dl = 1e-3
    jac = {"a": prof, "free": np.zeros_like(prof)}
    tr = [Transform("linear", 0.1, -10, 10), Transform("linear", 0.1, -10, 10)]
    A = (-jac["a"] / (prof + dl)).ravel()[:, None]
    r = (np.log(meas + dl) - np.log(prof + dl)).ravel()
    g = np.array([2.0 * float(A[:, 0] @ r) / r.size, 1e-3])      # noise in the free component
    dz = gn_direction(jac, ["a", "free"], tr, np.zeros(2), pb, prof, dl, meas, False, g, damping=0.0)
    assert dz[0] == pytest.approx(-np.linalg.lstsq(A, r, rcond=None)[0][0], rel=1e-6)
    lam_max = 2.0 * float(A[:, 0] @ A[:, 0]) / r.size
    assert dz[1] == pytest.approx(-1e-3 / (GN_EIG_FLOOR * lam_max), rel=1e-6)


def test_secant_steps_are_large_in_the_optimiser_variables():
    from estimate.beam import BeamProfile
    from estimate.forward import ForwardModel
    from estimate.gauss_newton import secant_steps
    from estimate.geometry import RigGeometry

    fm = ForwardModel(RigGeometry(thickness_mm=1.0, magnification=0.5, profile_columns=(236, 276)),
                      BeamProfile.disk(0.3), phase="exp3", extensions=("angle_offset",))
    p = dict(fm.default_parameters())
    p.update({"sigma_t": 4.0, "albedo": 0.9, "angle_offset.delta_deg": 0.0})
    names = ["sigma_t", "albedo", "phase.b1", "angle_offset.delta_deg"]
    s = secant_steps(fm, p, names)
    assert s["sigma_t"] == pytest.approx(0.05 * 4.0)
    assert s["albedo"] == pytest.approx(0.3 * 0.9 * 0.1)
    assert s["phase.b1"] == 0.5
    assert s["angle_offset.delta_deg"] == pytest.approx(3.0 * fm.specs["angle_offset.delta_deg"].fd_step)
    for n in names:
        assert s[n] >= fm.specs[n].fd_step * max(1.0, abs(p[n]))


def test_coarse_start_searches_phase_and_material_jointly():
    """On a toy model where a forward shape is compensated by sigma_t (the profile depends
    on sigma_t (1 - g)), a sequential search from the middle shape stops at the wrong
    (sigma_t, g); the joint grid finds the true grid point. Fixed parameters stay."""
    from estimate.start import ALBEDO_GRID, RESCORED, SIGMA_GRID, coarse_start

    x = np.linspace(0.0, 2.0, 40)

    calls: list[int] = []

    class Toy:
        phase = "hg"

        def render_profiles(self, p, angles, *, spp, seed):
            calls.append(spp)
            return (p["albedo"] * np.exp(-x * p["sigma_t"] * (1.0 - p["phase.g"])))[None, :]

        def render_profiles_many(self, requests, angles, *, spp):
            return [self.render_profiles(p, angles, spp=spp, seed=seed) for p, seed in requests]

    truth = {"sigma_t": SIGMA_GRID[7], "albedo": ALBEDO_GRID[2], "phase.g": 0.2}
    meas = Toy().render_profiles(truth, None, spp=0, seed=0)
    pb = _toy_problem(x, meas)
    calls.clear()
    best, tried = coarse_start(Toy(), pb, {"phase.g": 0.5}, scale=1.0, spp=32)   # type: ignore[arg-type]
    assert len(tried) == 4 * len(SIGMA_GRID) * len(ALBEDO_GRID)
    assert best == pytest.approx(truth)
    # every candidate screened at a quarter of the samples, the best few scored again
    assert calls.count(8) == len(tried) and calls.count(32) == RESCORED and len(calls) == len(tried) + RESCORED
    best, tried = coarse_start(Toy(), pb, {"phase.g": 0.5}, scale=1.0, fixed={"phase.g": 0.5})   # type: ignore[arg-type]
    assert best["phase.g"] == 0.5 and len(tried) == len(SIGMA_GRID) * len(ALBEDO_GRID)



def test_drift_flags_iterates_still_moving_and_not_stationary_ones():
    from estimate.uncertainties import iterate_drift

    rng = np.random.default_rng(5)
    n = 40
    z_sigma = np.log(2.4) - 0.004 * np.arange(n) + 0.004 * rng.normal(size=n)   # still falling
    z_b = 1.0 + 0.05 * rng.normal(size=n)                                          # settled
    hist = [[float(np.exp(a)), float(b)] for a, b in zip(z_sigma, z_b)]           # parameter units
    drift, moving = iterate_drift(hist, ["sigma_t", "b"], 8)
    assert moving == ["sigma_t"]
    assert drift["sigma_t"] == pytest.approx(np.exp(z_sigma[-8:]).mean() - np.exp(z_sigma[-24:-16]).mean())
    assert drift["sigma_t"] < 0 and abs(drift["b"]) < 0.1
    assert iterate_drift(hist[:20], ["sigma_t", "b"], 8) == ({}, [])


def test_window_estimate_follows_a_drift_to_its_end_and_averages_a_settled_window():
    from estimate.uncertainties import window_estimate, window_scatter

    rng = np.random.default_rng(11)
    n = 16
    t = np.arange(n)
    rows = np.stack([2.3 - 0.01 * t + 0.004 * rng.normal(size=n),    # drifting, noisy
                     0.9 + 0.002 * rng.normal(size=n)], axis=1)      # settled
    end = window_estimate(rows, trend=True)
    mean = window_estimate(rows, trend=False)
    # The mean lags the last iterate by half the window's drift; the trend's end does not.
    assert mean[0] == pytest.approx(2.3 - 0.01 * (n - 1) / 2, abs=0.004)
    assert end[0] == pytest.approx(2.3 - 0.01 * (n - 1), abs=0.006)
    assert end[1] == pytest.approx(0.9, abs=0.003)
    assert np.allclose(mean, rows.mean(axis=0))
    # The scatter about the trend is the noise, not the drift.
    assert np.std(window_scatter(rows, trend=True)[:, 0]) == pytest.approx(0.004, rel=0.5)
    assert np.std(window_scatter(rows, trend=False)[:, 0]) > 0.04
    # Too few rows for a line: the mean.
    assert np.allclose(window_estimate(rows[:2], trend=True), rows[:2].mean(axis=0))


def test_smooth_rows_keeps_smooth_columns_and_ignores_invalid_pixels():
    from estimate.gauss_newton import smooth_rows

    x = np.linspace(-1.0, 1.0, 101)
    col = np.vstack([1.0 + 0.5 * x, np.full_like(x, 2.0)])   # a Gaussian leaves both unchanged
    valid = np.ones_like(col, bool)
    valid[1, 40:45] = False
    col_bad = col.copy()
    col_bad[1, 40:45] = 1e6                        # garbage in masked pixels must not leak
    out = smooth_rows(col_bad, valid, 3.0)
    assert out[0, 12:-12] == pytest.approx(col[0, 12:-12], rel=1e-9)   # edges: exact for constants only
    assert out[1][valid[1]] == pytest.approx(col[1][valid[1]], rel=1e-9)
    assert np.all(out[~valid] == 0.0)
    assert smooth_rows(col_bad, valid, 0.0)[valid] == pytest.approx(col_bad[valid])


def test_smoothing_removes_most_of_the_noise_gram_matrix():
    """The Gauss-Newton matrix from a noisy finite-difference Jacobian is inflated by the
    noise's own Gram matrix, most along the weakly determined direction; smoothing the
    log-space columns along the row (they are smooth, the noise is per pixel) brings its
    generalised eigenvalues against the noise-free matrix back towards 1."""
    from scipy.linalg import eigh

    rng = np.random.default_rng(3)
    n, w = 4, 200
    x = np.linspace(-3.0, 3.0, w)
    prof = np.exp(-np.abs(x))[None, :] * np.linspace(0.8, 1.2, n)[:, None]
    # two nearly parallel columns: a valley
    jac = {"a": prof * (1.0 + 0.1 * x), "b": prof * (1.0 + 0.12 * x + 0.02 * x ** 2)}
    noisy = {k: v + 0.1 * prof * rng.standard_normal(v.shape) for k, v in jac.items()}

    def gram(j: dict, s: float) -> np.ndarray:
        return _gn_matrix(j, prof, smooth_px=s)

    exact = gram(jac, 0.0)
    raw = eigh(gram(noisy, 0.0), exact, eigvals_only=True)
    smooth = eigh(gram(noisy, 3.0), exact, eigvals_only=True)
    assert raw.max() > 3.0                       # the valley's eigenvalue, inflated by the noise
    assert smooth.max() < 1.0 + 0.25 * (raw.max() - 1.0)
    assert smooth.min() > 0.8


def test_snr_step_keeps_measured_directions_and_shrinks_noisy_ones():
    from estimate.gauss_newton import snr_step

    h_inv = np.diag([1.0, 100.0])                  # the second direction is weak: H^-1 amplifies it
    g = np.array([0.5, 0.01])
    rng = np.random.default_rng(0)
    steady = [g.copy() for _ in range(6)]
    assert snr_step(h_inv, g, steady, 0.7) == pytest.approx(h_inv @ g)   # no noise: the Newton step
    assert snr_step(h_inv, g, steady[:2], 0.7) == pytest.approx(h_inv @ g)   # too few to tell: unchanged
    noisy = [g + np.array([1e-3, 0.3]) * rng.standard_normal(2) for _ in range(16)]
    step = snr_step(h_inv, g, noisy, 0.7)
    assert step[0] == pytest.approx(0.5, rel=0.01)      # signal >> noise: kept
    assert 0.0 < step[1] < 0.1 * (h_inv @ g)[1]         # noise >> signal: shrunk


def test_exact_columns_are_not_smoothed():
    """Image-space parameters (the lens blur's) have exact, possibly sharp Jacobian columns:
    the Gauss-Newton matrix takes them as they are."""
    n, w = 2, 120
    x = np.linspace(-3.0, 3.0, w)
    prof = np.exp(-np.abs(x))[None, :] * np.ones((n, 1))
    sharp = prof * (np.abs(x) < 0.1)                  # a 2-pixel feature
    jac = {"a": sharp, "b": prof}

    def h(**kw):
        return _gn_matrix(jac, prof, **kw)

    raw, smooth, kept = h(), h(smooth_px=3.0), h(smooth_px=3.0, exact={"a"})
    assert kept[0, 0] == pytest.approx(raw[0, 0], rel=1e-9)
    assert smooth[0, 0] < 0.7 * raw[0, 0]             # smoothing would have spread the sharp column
    assert kept[1, 1] == pytest.approx(smooth[1, 1], rel=1e-9)


def test_cross_product_matrix_drops_the_noise_gram_matrix():
    """Two independent noisy Jacobians: one's A^T A is inflated by the noise's Gram matrix
    (most where the true curvature is weakest), the cross product of the two is not."""
    rng = np.random.default_rng(7)
    n, w = 4, 200
    x = np.linspace(-3.0, 3.0, w)
    prof = np.exp(-np.abs(x))[None, :] * np.ones((n, 1))
    # Two nearly parallel columns: a weak direction, as along the sigma_t / phase valley.
    true = {"a": prof, "b": prof * (1.0 + 0.05 * x)}

    def noisy():
        return {k: v + 0.05 * prof * rng.standard_normal(v.shape) for k, v in true.items()}

    def h(jac, **kw):
        return _gn_matrix(jac, prof, **kw)

    exact = np.linalg.eigvalsh(h(true))
    single = np.mean([np.linalg.eigvalsh(h(noisy())) for _ in range(20)], axis=0)
    cross = np.mean([np.linalg.eigvalsh(h(noisy(), jac_cross=noisy())) for _ in range(20)], axis=0)
    assert single[0] > 1.5 * exact[0]                       # the weak direction, inflated
    assert cross[0] == pytest.approx(exact[0], rel=0.15)    # unbiased
    assert cross[1] == pytest.approx(exact[1], rel=0.02)


def test_bounded_cross_keeps_the_matrix_between_floor_and_mean():
    """The cross-product matrix is held between `floor` x and 1 x the mean's matrix in
    their generalised eigenvalues; inside those bounds it is left as it is."""
    from estimate.gauss_newton import bounded_cross

    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    h_mean = q @ np.diag([4.0, 1.0, 0.01]) @ q.T
    root = q @ np.diag(np.sqrt([4.0, 1.0, 0.01]))
    for lam, want in (([0.8, 0.6, 0.7], [0.8, 0.6, 0.7]), ([1.7, -0.3, 0.05], [1.0, 0.5, 0.5])):
        h_cross = root @ np.diag(lam) @ root.T
        out = bounded_cross(h_cross, h_mean, 0.5)
        gen = np.linalg.eigvals(np.linalg.solve(h_mean, out)).real
        assert sorted(gen) == pytest.approx(sorted(want), abs=1e-9)


def test_averaged_polish_points_mean_step_within_their_scatter_is_not_added_twice():
    """Three polish points drawn about the optimum with standard deviation 1: their mean's
    standard error (0.58) already holds their scatter, and their mean step (the drift,
    standard deviation 0.71) is that scatter again unless it stands out of it. Over many
    draws, adding it anyway widened the interval by about a third; only a drift beyond the
    points' scatter is added and flagged. Without averaged points the drift is added."""
    from estimate.uncertainties import combined_uncertainties

    rng = np.random.default_rng(3)
    widths, plain, flagged = [], [], 0
    for _ in range(400):
        pts = rng.normal(0.0, 1.0, 3)
        drift = {"x": float((pts[-1] - pts[0]) / 2)}
        sd = {"x": float(np.std(pts, ddof=1))}
        se = {"x": 1.0 / math.sqrt(3)}     # the points' noise model
        unc, moving = combined_uncertainties({"x": 0.0}, {}, se, drift, sd, polished=True)
        widths.append(unc["x"])
        plain.append(math.hypot(se["x"], drift["x"]))
        flagged += bool(moving)
    assert np.mean(widths) == pytest.approx(1.0 / math.sqrt(3), rel=0.05)
    assert np.mean(plain) > 1.15 * np.mean(widths)
    assert flagged < 0.1 * 400
    # A walk: the points still move by 3 per step, far beyond their scatter.
    unc, moving = combined_uncertainties({"x": 0.1}, {"x": 0.05}, {"x": 0.5}, {"x": 3.0}, {"x": 1.0},
                                         polished=True)
    assert moving == ["x"] and unc["x"] == pytest.approx(math.hypot(0.1, 0.05, 0.5, 3.0))
    # One polish point or none: the last move is the only measure of the distance left.
    unc, moving = combined_uncertainties({"x": 0.1}, {"x": 0.05}, {}, {"x": 0.2}, {}, polished=False)
    assert moving == [] and unc["x"] == pytest.approx(math.hypot(0.1, 0.05, 0.2))


def test_covariance_correlates_only_the_parts_whose_correlation_is_modelled():
    """The reported covariance: the sandwich's, the iterates' and (with its correlation) the
    polish's correlated parts plus the rest of each variance on the diagonal. Where the sandwich is all of the interval its
    correlation is kept; where an uncorrelated part (the polish points' standard error)
    dominates, the sandwich's strong sigma_t-albedo correlation is not stretched over it:
    the derived sigma_a = sigma_t (1 - albedo) then gets the variance of independent parts
    (bench_coverage's draw 0, session 36: 0.0013 /mm before, the error 0.0068)."""
    from estimate.derived import derived_quantities
    from estimate.uncertainties import combined_covariance

    names = ["sigma_t", "albedo"]
    s_st, s_a, rho = 7e-5, 1.2e-6, 0.95
    sandwich = {"sigma_t": {"sigma_t": s_st ** 2, "albedo": rho * s_st * s_a},
                "albedo": {"sigma_t": rho * s_st * s_a, "albedo": s_a ** 2}}
    zero = np.zeros((2, 2))
    # the sandwich is the whole interval: its correlation stays
    full = combined_covariance(names, {"sigma_t": s_st, "albedo": s_a}, sandwich, zero)
    assert full["sigma_t"]["albedo"] == pytest.approx(rho * s_st * s_a)
    # the polish's standard error is nearly all of it: no correlation borrowed
    unc = {"sigma_t": 0.0342, "albedo": 0.00136}
    full = combined_covariance(names, unc, sandwich, zero)
    assert full["sigma_t"]["sigma_t"] == pytest.approx(unc["sigma_t"] ** 2)
    assert full["albedo"]["albedo"] == pytest.approx(unc["albedo"] ** 2)
    assert abs(full["sigma_t"]["albedo"]) / (unc["sigma_t"] * unc["albedo"]) < 1e-5
    params = {"sigma_t": 2.03, "albedo": 0.898, "phase.b1": 3.0, "phase.b2": 1.0, "phase.b3": 0.5}
    sa = derived_quantities("exp3", params, full)["sigma_a"]["uncertainty"]
    independent = math.hypot((1 - params["albedo"]) * unc["sigma_t"], params["sigma_t"] * unc["albedo"])
    assert sa == pytest.approx(independent, rel=1e-3)
    # the polish's share carries the render-noise correlation of its steps, where given
    se = {"sigma_t": 0.0342, "albedo": 0.00136}
    corr = {"sigma_t": {"sigma_t": 1.0, "albedo": -0.6}, "albedo": {"sigma_t": -0.6, "albedo": 1.0}}
    full = combined_covariance(names, unc, sandwich, zero, se, corr)
    assert full["sigma_t"]["albedo"] / (unc["sigma_t"] * unc["albedo"]) == pytest.approx(-0.6, abs=1e-3)
    assert full["albedo"]["albedo"] == pytest.approx(unc["albedo"] ** 2)
    # the iterates' covariance is correlated too, and a part is never above the variance reported
    it = np.array([[4e-4, 3.9e-6], [3.9e-6, 4e-8]])
    full = combined_covariance(names, {"sigma_t": 0.01, "albedo": 1e-4}, {}, it)
    assert full["sigma_t"]["sigma_t"] == pytest.approx(1e-4) and full["albedo"]["albedo"] == pytest.approx(1e-8)
    assert full["sigma_t"]["albedo"] / (0.01 * 1e-4) == pytest.approx(3.9e-6 / math.sqrt(4e-4 * 4e-8))


def test_polish_average_takes_the_later_points_in_z():
    """The polish's result is the mean of the points after steps `start`..: the stepped
    parameters averaged in their optimiser variables, solved additive ones as they are, the
    mean step as the drift and the mean's standard error."""
    from estimate.polish import polish_average
    from estimate.transforms import Transform

    names = ["sigma_t", "phase.b1"]
    tr = [Transform("log", 0.08), Transform("linear", 0.15, -200, 200)]
    pts = [{"sigma_t": 2.4, "phase.b1": 2.0, "stray.offset": 0.0},
           {"sigma_t": 1.9, "phase.b1": 3.1, "stray.offset": 1.0},
           {"sigma_t": 2.1, "phase.b1": 2.9, "stray.offset": 3.0},
           {"sigma_t": 2.0, "phase.b1": 3.0, "stray.offset": 2.0}]
    acc = [{"accepted": True, "point": p} for p in pts]
    mean, drift, sd, se = polish_average(acc, names, tr, 2)
    assert mean["sigma_t"] == pytest.approx(math.exp(np.mean(np.log([1.9, 2.1, 2.0]))))
    assert mean["phase.b1"] == pytest.approx(3.0)
    assert mean["stray.offset"] == pytest.approx(2.0)
    assert drift == pytest.approx({"sigma_t": 0.05, "phase.b1": -0.05})
    assert sd["sigma_t"] == pytest.approx(np.std([1.9, 2.1, 2.0], ddof=1))
    assert se["sigma_t"] == pytest.approx(sd["sigma_t"] / math.sqrt(3))
    assert "stray.offset" not in se and "stray.offset" not in drift
    # With the steps' noise model: the standard error is the larger of the sample one and
    # the model's (rms of the points' noise / sqrt(3)).
    noisy = [{**e, "noise_sd": {"sigma_t": 0.3, "phase.b1": 0.01}} for e in acc]
    _, _, _, se_m = polish_average(noisy, names, tr, 2)
    assert se_m["sigma_t"] == pytest.approx(0.3 / math.sqrt(3))
    assert se_m["phase.b1"] == pytest.approx(se["phase.b1"])
    # Unequal noise: each parameter weighted by 1 / noise_sd^2, the model error 1 / sqrt(sum).
    unequal = [{**e, "noise_sd": {"sigma_t": sdv, "phase.b1": 0.1}} for e, sdv in zip(acc, (0.1, 0.2, 0.1, 0.1))]
    mean_w, _, sd_w, se_w = polish_average(unequal, names, tr, 2)
    w = np.array([1 / 0.2 ** 2, 1 / 0.1 ** 2, 1 / 0.1 ** 2])
    assert mean_w["sigma_t"] == pytest.approx(math.exp(np.sum(w * np.log([1.9, 2.1, 2.0])) / w.sum()))
    assert mean_w["phase.b1"] == pytest.approx(3.0)           # equal noise: the plain mean
    assert se_w["sigma_t"] == pytest.approx(1 / math.sqrt(w.sum()))
    assert sd_w["sigma_t"] == pytest.approx(sd["sigma_t"])
    # Too few points after `start`, or averaging off: the last point stands.
    assert polish_average(acc[:2], names, tr, 2) is None
    assert polish_average(acc, names, tr, 0) is None


def _polish_setup(problem):
    from estimate.forward import ForwardModel
    from estimate.transforms import transform_for

    fm = ForwardModel(problem.geometry, problem.beam, phase="exp3", profile_y_shape=problem.y_shapes())
    names = ["sigma_t", "albedo", "phase.b1", "phase.b2", "phase.b3"]
    tr = [transform_for(n, fm.specs[n]) for n in names]
    scale = calibrated_scale(problem.session_path, "g", problem.beam.power()).scale
    return fm, names, tr, scale


@pytest.mark.parametrize(("cross", "one_sided", "damped"),
                         [(False, False, False), (True, False, False), (True, True, False), (True, True, True)])
def test_gn_polish_walks_towards_the_truth_and_reports_its_steps(problem, cross, one_sided, damped):
    """From a start 15 % high in sigma_t, the polish's full Gauss-Newton steps at a fixed,
    moderate spp bring sigma_t within a third of that and lower the loss without render
    noise, with one Jacobian's matrix, two half-spp Jacobians' cross product, or two
    one-sided ones against half of each gradient render (also with Levenberg-Marquardt damping)."""
    from estimate.polish import gn_polish

    fm, names, tr, scale = _polish_setup(problem)
    start = fm.default_parameters()
    start.update(TRUTH)
    start["sigma_t"] = 3.45
    out, trace, renders = gn_polish(fm, problem, start, names, tr, steps=3, spp=512, jacobian_spp=512, seed=5,
                                    delta_nodes=[0.02, 0.1], reference_delta_rel=0.045, fixed_scale=scale,
                                    cross=cross, one_sided=one_sided, damped=damped)
    assert renders is not None and renders[0].shape == problem.measured.shape
    assert trace and trace[0]["accepted"]
    assert abs(out["sigma_t"] - 3.0) < 0.15, out
    kept = [e for e in trace if e["accepted"]]
    assert kept[-1]["loss_new"] < trace[0]["loss"]
    # Each kept step is what the parameters moved by, and its point is where it arrived.
    assert sum(e["step"]["sigma_t"] for e in kept) == pytest.approx(out["sigma_t"] - 3.45, abs=1e-9)
    assert kept[-1]["point"]["sigma_t"] == out["sigma_t"]


def test_polish_step_chi2_separates_a_move_from_noise_and_a_walk_goes_on(problem):
    """A step's chi^2 against its own render noise: far above the parameter count when the
    polish starts 15 % off in sigma_t, about that count (the noise alone) at the truth. A
    polish still walking goes on past its planned steps; one at the noise floor does not."""
    from estimate.polish import gn_polish

    fm, names, tr, scale = _polish_setup(problem)
    kw = {"spp": 256, "jacobian_spp": 512, "delta_nodes": [0.02, 0.1], "reference_delta_rel": 0.045,
          "fixed_scale": scale, "cross": True, "chi2_continue": float(chi2_dist.isf(0.01, len(names))),
          "keep_last": 1, "max_steps": 3}
    off = {**fm.default_parameters(), **TRUTH, "sigma_t": 3.45}
    _, walk, _ = gn_polish(fm, problem, off, names, tr, steps=1, seed=5, **kw)
    assert walk[0]["step_chi2"] > 10 * len(names)
    assert len(walk) > 1                      # went on: its only planned step was a move
    at = {**fm.default_parameters(), **TRUTH}
    chi2s = []
    for seed in (11, 12, 13):
        _, tr_at, _ = gn_polish(fm, problem, at, names, tr, steps=1, seed=seed, **kw)
        chi2s.append(tr_at[0]["step_chi2"])
        assert len(tr_at) == 1                # noise alone: stopped as planned
    assert 0.2 * len(names) < np.mean(chi2s) < 4 * len(names)


def test_a_settled_polish_step_keeps_the_matrix_and_renders_more_samples(problem, monkeypatch):
    """After a noise-sized step the polish renders the new point at `settled_spp_factor` x the
    spp and its next step keeps the last Jacobians; after a move, or with the factor 1, each
    step renders two new ones at the plain spp. A settled point's noise is smaller."""
    import estimate.polish as polish_mod

    fm, names, tr, scale = _polish_setup(problem)
    calls: list[int] = []
    real = polish_mod.gn_jacobian

    def counted(*a, **kw):
        calls.append(kw["seed"])
        return real(*a, **kw)

    monkeypatch.setattr(polish_mod, "gn_jacobian", counted)
    kw = {"steps": 3, "spp": 64, "jacobian_spp": 128, "delta_nodes": [0.045], "reference_delta_rel": 0.045,
          "fixed_scale": scale, "cross": True, "seed": 7}
    at = {**fm.default_parameters(), **TRUTH}
    # Every step noise-sized (an infinite threshold): new Jacobians once, then 4x the spp.
    _, trace, _ = polish_mod.gn_polish(fm, problem, at, names, tr, chi2_continue=math.inf, settled_spp_factor=4, **kw)
    assert all(e["accepted"] for e in trace)
    assert [e["jacobians"] for e in trace] == [2, 0, 0] and len(calls) == 2
    assert [e["spp"] for e in trace] == [64, 256, 256]
    first, later = trace[0]["noise_sd"]["sigma_t"], np.mean([e["noise_sd"]["sigma_t"] for e in trace[1:]])
    assert later < 0.8 * first                                 # 4x the samples: about half the noise
    # No step settled (a zero threshold) or the factor 1: two new Jacobians at 64 spp each step.
    for chi2_continue, factor in ((0.0, 4), (math.inf, 1)):
        calls.clear()
        _, trace, _ = polish_mod.gn_polish(fm, problem, at, names, tr, chi2_continue=chi2_continue,
                                           settled_spp_factor=factor, max_steps=3, **kw)
        assert [e["jacobians"] for e in trace] == [2, 2, 2] and len(calls) == 6
        assert [e["spp"] for e in trace] == [64, 64, 64]


def test_one_sided_polish_jacobians_reuse_half_of_each_render(problem, monkeypatch):
    """With one-sided Jacobians each step renders 5 perturbed profiles per Jacobian against
    the first half-spp render of A (forward) and of B (backward), and no base of its own; at
    a Jacobian spp that differs from the renders' halves it renders one base per Jacobian."""
    fm, names, tr, scale = _polish_setup(problem)
    import estimate.polish as polish_mod

    calls: list[tuple[int, int]] = []
    real_radiance = fm._queue_radiance

    def counted(values, angles, window, spp, seed, *a, **k):
        calls.append((spp, seed))
        return real_radiance(values, angles, window, spp, seed, *a, **k)

    real_jac = fm.jacobian
    directions: list[bool] = []

    def jac_counted(*a, **kw):
        directions.append(kw.get("backward", False))
        assert kw["base_profiles"] is not None
        return real_jac(*a, **kw)

    monkeypatch.setattr(fm, "_queue_radiance", counted)      # every render goes through it
    monkeypatch.setattr(fm, "jacobian", jac_counted)
    at = {**fm.default_parameters(), **TRUTH}
    kw = {"steps": 2, "seed": 7, "delta_nodes": [0.045], "reference_delta_rel": 0.045, "fixed_scale": scale,
          "cross": True, "one_sided": True, "chi2_continue": math.inf}
    _, trace, _ = polish_mod.gn_polish(fm, problem, at, names, tr, spp=128, jacobian_spp=128, **kw)
    assert [e["jacobians"] for e in trace] == [2, 2] and directions == [False, True, False, True]
    # per point 4 half renders (64 spp); per step 2 x 5 perturbed renders at 64 spp
    assert sorted({s for s, _ in calls}) == [64]
    points = 1 + sum(e["halvings"] + 1 for e in trace)         # the start's and each tried step's
    assert len(calls) == 4 * points + 2 * 2 * len(names)
    calls.clear()
    _, trace, _ = polish_mod.gn_polish(fm, problem, at, names, tr, spp=128, jacobian_spp=256, steps=1,
                                       **{k: v for k, v in kw.items() if k != "steps"})
    points = 1 + trace[0]["halvings"] + 1
    assert len(calls) == 4 * points + 2 * (1 + len(names))   # a base of its own per Jacobian at 128 spp
    assert sum(s == 128 for s, _ in calls) == 2 * (1 + len(names))
    # Cheaper Jacobians (halves at 32 spp): each render the mean of four at 32, the first its base.
    calls.clear()
    _, trace, _ = polish_mod.gn_polish(fm, problem, at, names, tr, spp=128, jacobian_spp=64, steps=1,
                                       **{k: v for k, v in kw.items() if k != "steps"})
    points = 1 + trace[0]["halvings"] + 1
    assert sorted({s for s, _ in calls}) == [32]
    assert len(calls) == 8 * points + 2 * len(names)
    assert len({sd for _, sd in calls[:8]}) == 8                # the parts' seeds all differ


def test_an_extended_polish_averages_as_many_last_points_as_planned():
    from estimate.polish import averaged_point_count, first_averaged_point

    assert first_averaged_point(4, 4, 2) == 2          # as planned: points 2, 3, 4
    assert first_averaged_point(3, 4, 2) == 2          # stopped early (a step undone)
    assert first_averaged_point(7, 4, 2) == 5          # went on: points 5, 6, 7
    assert first_averaged_point(8, 4, 0) == 0          # the last point alone
    # the noise test watches as many last steps as the result averages
    assert averaged_point_count(4, 2) == 3 and averaged_point_count(4, 0) == 1 and averaged_point_count(4, 9) == 1
    for planned, start in ((4, 1), (4, 2), (6, 3)):
        n = planned + 3
        assert n - first_averaged_point(n, planned, start) + 1 == averaged_point_count(planned, start)


def test_gn_polish_undoes_a_step_that_makes_the_fit_grossly_worse(problem, monkeypatch):
    """A matrix that points uphill (here: forced) gives a step whose loss rises far beyond
    the noise, and so do its halves: it is undone and the polish stops at its start."""
    import estimate.polish as polish_mod

    fm, names, tr, scale = _polish_setup(problem)
    start = fm.default_parameters()
    start.update(TRUTH)
    # Uphill, every component at the cap (1 in z: sigma_t x e, ...), so that even the
    # quarter step of the last halving stays far worse.
    monkeypatch.setattr(polish_mod, "gn_inverse", lambda *a, **k: -1e4 * np.eye(len(names)))
    out, trace, _ = polish_mod.gn_polish(fm, problem, start, names, tr, steps=3, spp=128, jacobian_spp=128, seed=5,
                                         delta_nodes=[0.045], reference_delta_rel=0.045, fixed_scale=scale,
                                         caps=np.full(len(names), 4.0))
    assert len(trace) == 1 and not trace[0]["accepted"] and trace[0]["halvings"] == 2
    assert trace[0]["loss_new"] > trace[0]["loss"]
    assert all(out[n] == start[n] for n in names)


def test_a_damped_polish_retries_a_rising_step_with_more_damping(problem, monkeypatch):
    """With `damped`, a step whose loss rises beyond its noise is retried from the same
    matrix and gradient with 10x the damping (no new Jacobians) until one does not rise;
    the next step starts from a tenth of the damping that worked."""
    import estimate.polish as polish_mod

    fm, names, tr, scale = _polish_setup(problem)
    real = polish_mod.gn_inverse
    asked: list[float] = []

    def uphill_unless_damped(*a, **k):
        asked.append(k["damping"])
        # Uphill (forced) at the matrix's own damping and at 10x it; the real matrix beyond.
        return -1e4 * np.eye(len(names)) if k["damping"] < 0.05 else real(*a, **k)

    monkeypatch.setattr(polish_mod, "gn_inverse", uphill_unless_damped)
    jacobians: list[int] = []
    real_jac = fm.jacobian
    monkeypatch.setattr(fm, "jacobian", lambda *a, **k: jacobians.append(1) or real_jac(*a, **k))
    start = {**fm.default_parameters(), **TRUTH, "sigma_t": 3.45}
    out, trace, _ = polish_mod.gn_polish(fm, problem, start, names, tr, steps=1, spp=128, jacobian_spp=128, seed=5,
                                         delta_nodes=[0.045], reference_delta_rel=0.045, fixed_scale=scale,
                                         caps=np.full(len(names), 1.0), cross=True, one_sided=True, damped=True,
                                         chi2_continue=math.inf)
    assert len(trace) == 1 and trace[0]["accepted"]
    assert trace[0]["halvings"] == 2 and trace[0]["damping"] == pytest.approx(0.1)
    assert asked[:3] == pytest.approx([1e-3, 1e-2, 1e-1])
    assert len(jacobians) == 2                           # one pair, for all three tries
    assert out["sigma_t"] < 3.45


def test_a_later_polish_step_counts_the_noise_its_start_point_carries(problem):
    """The first step's chi^2 is against its own gradient noise; a later step starts from a
    point that is the optimum plus the previous step's noise, which it undoes too, so its
    chi^2 is against both (smaller than against its own noise alone)."""
    from estimate.polish import gn_polish

    fm, names, tr, scale = _polish_setup(problem)
    at = {**fm.default_parameters(), **TRUTH}
    _, trace, _ = gn_polish(fm, problem, at, names, tr, steps=3, spp=128, jacobian_spp=128, seed=9,
                            delta_nodes=[0.045], reference_delta_rel=0.045, fixed_scale=scale, cross=True,
                            one_sided=True, chi2_continue=math.inf)
    assert [e["accepted"] for e in trace] == [True] * 3
    assert trace[0]["step_chi2"] == pytest.approx(trace[0]["step_chi2_own"])
    for e in trace[1:]:
        assert 0.0 < e["step_chi2"] < e["step_chi2_own"]
    _, trace, _ = gn_polish(fm, problem, at, names, tr, steps=2, spp=128, jacobian_spp=128, seed=9,
                            delta_nodes=[0.045], reference_delta_rel=0.045, fixed_scale=scale, cross=True,
                            one_sided=True, chi2_continue=math.inf, start_point_noise=False)
    assert all(e["step_chi2"] == pytest.approx(e["step_chi2_own"]) for e in trace)



def test_lm_plan_by_phase_degree():
    """The fixed-seed LM runs on request, else for exponential phases from `lm_from_degree` on,
    at `lm_degree_spp_factor` x the final spp; never for HG families or with the degree rule off."""
    from estimate.fit import lm_plan

    st = FitSettings(final_spp=512)
    assert lm_plan(st, "exp3") == (0, 0) and lm_plan(st, "exp4") == (0, 0) and lm_plan(st, "tthg") == (0, 0)
    assert lm_plan(st, "exp5") == (st.lm_degree_iterations, 4 * 512) == lm_plan(st, "exp7")[:1] + (2048,)
    assert lm_plan(FitSettings(final_spp=512, lm_from_degree=None), "exp9") == (0, 0)
    assert lm_plan(FitSettings(final_spp=512, lm_from_degree=3), "exp3") == (60, 2048)
    # An explicit request wins, for any model, at its own spp.
    assert lm_plan(FitSettings(lm_iterations=4, lm_spp=256), "tthg") == (4, 256)
    assert lm_plan(FitSettings(lm_iterations=4, lm_spp=256), "exp7") == (4, 256)
    assert FitSettings.from_dict({"lm_from_degree": None}).lm_from_degree is None
    assert FitSettings.from_dict({}).lm_from_degree == 5
    for bad in (-1, 2.5, "five", True):
        with pytest.raises(ModelParameterError, match="lm_from_degree"):
            FitSettings.from_dict({"lm_from_degree": bad}, where="results.yaml")
    with pytest.raises(ModelParameterError, match="lm_degree_spp_factor"):
        FitSettings.from_dict({"lm_degree_spp_factor": 0})


def test_lm_polish_reports_each_accepted_step(problem):
    """`steps_out` holds every accepted step in parameter units: they add up to the way from
    the start to the result, one fewer than the losses, which fall."""
    from estimate.fit import forward_model
    from estimate.loss import reference_delta
    from estimate.polish import lm_polish
    from estimate.transforms import transform_for

    fm = forward_model(problem, "exp3")
    names = ["sigma_t", "albedo", "phase.b1"]
    start = {**fm.default_parameters(), **TRUTH, "sigma_t": 2.2, "albedo": 0.8, "phase.b1": 2.0}
    steps: list[dict[str, float]] = []
    p, losses = lm_polish(fm, problem, start, names, [transform_for(n, fm.specs[n]) for n in names], spp=256, seed=7,
                          delta_rel=reference_delta(FitSettings().delta_range), iterations=3, fixed_scale=2e5,
                          steps_out=steps)
    assert len(steps) == len(losses) - 1 >= 1
    assert all(b < a for a, b in zip(losses, losses[1:]))
    for n in names:
        assert start[n] + sum(s[n] for s in steps) == pytest.approx(p[n], rel=1e-12, abs=1e-12)
    assert abs(p["sigma_t"] - 3.0) < abs(start["sigma_t"] - 3.0)


def test_a_high_degree_fit_ends_at_the_lm_point_and_takes_its_uncertainties_there(problem, monkeypatch, tmp_path):
    """exp5 (from `lm_from_degree`) runs the LM after the polish at the degree's spp; exp3 does
    not. The result is the LM's point: the drift is its last step, the polish points' scatter
    is not carried over, and the uncertainties render fresh Jacobians at that point."""
    import estimate.fit as fit_mod

    calls: list[dict] = []

    def fake_lm(fm, pb, params, names, tr, *, spp, seed, delta_rel, iterations, fixed_scale=None, steps_out=None,
                deadline=None, decorrelated=False, basis="monomial", excess_target=None, spp_max=None,
                stages_out=None):
        from estimate.polish import LMStage

        calls.append({"spp": spp, "iterations": iterations, "names": list(names), "decorrelated": decorrelated,
                      "basis": basis, "excess_target": excess_target, "spp_max": spp_max})
        moved = {**params, "sigma_t": params["sigma_t"] * 1.01}
        steps_out.append({n: moved[n] - params[n] for n in names})
        stages_out.append(LMStage(spp=spp, losses=[1.0, 0.95], stop="no step lowered the loss", noise_excess=0.5))
        stages_out.append(LMStage(spp=4 * spp, losses=[0.96, 0.9], stop="a step gained under 0.1% of the loss",
                                  noise_excess=0.08))
        return moved, [0.96, 0.9]

    central: list[dict] = []
    real_jac = fit_mod.gn_jacobian
    monkeypatch.setattr(fit_mod, "lm_polish", fake_lm)
    monkeypatch.setattr(fit_mod, "gn_jacobian", lambda fm, pb, p, *a, **k: central.append(dict(p)) or real_jac(fm, pb, p, *a, **k))
    st = FitSettings(seed=5, max_iterations=4, spp_start=16, spp_max=16, final_spp=32, window=3, scale="calibrated",
                     uncertainty_spp=32, iterations_before_polish=3, polish_steps=2, polish_max_steps=2,
                     polish_average_from=1, lm_degree_iterations=3, lm_degree_spp_factor=2)
    start = {"sigma_t": 3.0, "albedo": 0.85, "phase.b1": 3.0}
    r3 = fit_channel(problem, "exp3", start=start, settings=st)
    assert not calls and r3.polish_se and not central
    r5 = fit_channel(problem, "exp5", start=start, settings=st)
    assert calls == [{"spp": 64, "iterations": 3, "names": list(r5.uncertainties), "decorrelated": True,
                      "basis": "legendre", "excess_target": st.lm_excess_target, "spp_max": 32 * 32}]
    # every stage is kept, the steps counted over them, the last one's spp reported
    assert [g["spp"] for g in r5.lm_stages] == [64, 256] and r5.lm_steps == 2 and r5.lm_spp == 256
    assert r5.lm_stages[0]["noise_excess"] == 0.5 and r5.lm_losses == [0.96, 0.9]
    # results.yaml keeps the stages
    import yaml

    from estimate.results import write_run

    (tmp_path / "run").mkdir()
    out = write_run(tmp_path / "run", problem.session_path, [r5], {"g": problem}, {}, plots=False)
    doc = yaml.safe_load((out if out.is_file() else out / "results.yaml").read_text())
    lm = doc["channels"]["g"]["levenberg_marquardt"]
    assert [g["spp"] for g in lm] == [64, 256] and lm[1]["stop"] == "a step gained under 0.1% of the loss"
    assert r5.drift["sigma_t"] == pytest.approx(r5.parameters["sigma_t"] / 1.01 * 0.01, rel=1e-9)
    assert r5.drift["albedo"] == 0.0 and not r5.polish_se
    assert len(central) == 2 and all(c["sigma_t"] == r5.parameters["sigma_t"] for c in central)
    assert all(math.isfinite(v) and v > 0 for v in r5.uncertainties.values())


def test_lm_noise_excess_predicts_what_a_fixed_noise_optimum_adds_to_the_loss():
    """A linear least-squares model fitted to two noisy 'renders' at fixed noise (the
    decorrelated loss's optimum) ends off the noise-free optimum; the loss without render
    noise rises there by tr((A^T A)^-1 A^T D A) / n. `lm_noise_excess`, from one fit's two
    residuals, predicts the mean rise over 400 fits, as a share of the HDR noise floor, with
    the render noise differing across the pixels."""
    from estimate.polish import lm_noise_excess

    rng = np.random.default_rng(90)
    n, k = 600, 6
    X = rng.normal(size=(n, k)) * np.linspace(0.2, 2.0, n)[:, None]
    beta = rng.normal(size=k)
    sd_half = np.linspace(0.01, 0.05, n)          # each half render's noise in log units
    floor_sd = 0.02                                # the recording's noise, log units
    delta = 1e-3
    measured = rng.uniform(0.5, 2.0, (1, n))
    variance = (floor_sd * (measured + delta)) ** 2
    valid = np.ones((1, n), bool)
    y = X @ beta                                   # the noise-free optimum fits y exactly
    rises, predicted = [], []
    for _ in range(400):
        e_a, e_b = sd_half * rng.normal(size=n), sd_half * rng.normal(size=n)
        # minimise mean((y - X b - e_a)(y - X b - e_b)): b = (X^T X)^-1 X^T (y - (e_a + e_b) / 2)
        b = np.linalg.lstsq(X, y - 0.5 * (e_a + e_b), rcond=None)[0]
        rises.append(float(np.mean((X @ (b - beta)) ** 2)) / floor_sd ** 2)
        r_a, r_b = (y - X @ b - e_a)[None, :], (y - X @ b - e_b)[None, :]
        predicted.append(lm_noise_excess(-X, r_a, r_b, measured, variance, valid, 1.0, delta))
    expected = float(np.trace(np.linalg.solve(X.T @ X, X.T @ (0.5 * sd_half[:, None] ** 2 * X)))) / n / floor_sd ** 2
    assert np.mean(rises) == pytest.approx(expected, rel=0.1)
    assert np.mean(predicted) == pytest.approx(expected, rel=0.05)
    assert np.std(predicted) < 0.15 * expected          # one fit's estimate is already close
    # no floor, no share
    assert math.isnan(lm_noise_excess(-X, r_a, r_b, measured, np.zeros_like(variance), valid, 1.0, delta))


def test_lm_polish_raises_its_spp_while_its_noise_excess_is_above_the_target(problem):
    """A stage whose optimum owes more than `excess_target` of the floor to its renders' noise
    is followed by one at enough more spp (powers of two, at most `spp_max`), from its end
    point; without a target, one stage. The stages record their spp, losses and stop."""
    from estimate.fit import forward_model
    from estimate.loss import reference_delta
    from estimate.polish import LMStage, lm_polish
    from estimate.transforms import transform_for

    fm = forward_model(problem, "exp3")
    names = ["sigma_t", "albedo"]
    start = {**fm.default_parameters(), **TRUTH, "sigma_t": 2.4}
    tr = [transform_for(n, fm.specs[n]) for n in names]
    d_ref = reference_delta(FitSettings().delta_range)

    def run(**kw):
        stages: list[LMStage] = []
        p, losses = lm_polish(fm, problem, start, names, tr, spp=32, seed=7, delta_rel=d_ref, iterations=30,
                              fixed_scale=2e5, stages_out=stages, **kw)
        return p, losses, stages

    _, losses, one = run()
    assert len(one) == 1 and one[0].spp == 32 and one[0].losses == losses
    assert one[0].noise_excess > 0 and one[0].stop != "step limit", one[0]
    # a target below any 32..128-spp stage's excess: 32 -> 128 (the cap), then stop
    p, losses, staged = run(excess_target=1e-9, spp_max=128)
    assert [g.spp for g in staged] == [32, 128] and staged[-1].losses == losses
    assert staged[0].noise_excess == one[0].noise_excess       # the same first stage
    # the excess falls about as 1 / spp
    assert staged[1].noise_excess < 0.6 * staged[0].noise_excess, [(g.spp, g.noise_excess, g.stop) for g in staged]
    # a target the first stage meets: no second one
    _, _, met = run(excess_target=10 * one[0].noise_excess, spp_max=128)
    assert len(met) == 1
    assert LMStage(spp=64, losses=[1.0, 0.5, 0.4], stop="x").to_dict()["steps"] == 2


def test_the_lm_excess_target_setting_is_checked():
    assert FitSettings.from_dict({"lm_excess_target": None}).lm_excess_target is None
    assert FitSettings.from_dict({"lm_excess_target": 0.2}).lm_excess_target == 0.2
    for bad in (0, -0.1, "small", float("nan"), True):
        with pytest.raises(ModelParameterError, match="lm_excess_target"):
            FitSettings.from_dict({"lm_excess_target": bad}, where="results.yaml")
    with pytest.raises(ModelParameterError, match="lm_spp_max_factor"):
        FitSettings.from_dict({"lm_spp_max_factor": 0})


def test_the_lm_legendre_basis_maps_legendre_coefficients_to_the_same_exponent():
    """z = B u: sigma_t, albedo and the scale's place stay; u's phase block holds the
    Legendre coefficients c_1..c_M of the exponent whose monomial coefficients are z's b_1..b_M
    (the constant each P_i adds is the normalisation's), for b's given in any order."""
    from numpy.polynomial import legendre as leg

    from estimate.polish import lm_basis_matrix
    from estimate.transforms import transform_for

    fm_specs = {n: None for n in ("sigma_t", "albedo", "phase.b1", "phase.b2", "phase.b3", "phase.b4")}
    names = ["phase.b3", "sigma_t", "phase.b1", "albedo", "phase.b4", "phase.b2"]
    tr = [transform_for(n, fm_specs[n]) for n in names]
    assert np.array_equal(lm_basis_matrix(names, tr, "monomial"), np.eye(6))
    B = lm_basis_matrix(names, tr, "legendre")
    rng = np.random.default_rng(3)
    u = rng.normal(size=6)
    z = B @ u
    c = np.zeros(5)
    c[1:] = [u[names.index(f"phase.b{i}")] for i in range(1, 5)]
    b = leg.leg2poly(c)
    mu = np.linspace(-1, 1, 9)
    exponent = sum(z[names.index(f"phase.b{i}")] * mu ** i for i in range(1, 5))
    assert np.allclose(exponent, leg.legval(mu, c) - b[0], atol=1e-12)
    assert z[1] == u[1] and z[3] == u[3]
    with pytest.raises(ModelParameterError, match="LM basis"):
        lm_basis_matrix(names, tr, "chebyshev")
    with pytest.raises(ModelParameterError, match="lm_basis"):
        FitSettings.from_dict({"lm_basis": "chebyshev"})


def test_lm_polish_in_the_legendre_basis_lowers_the_loss_and_reports_its_steps(problem):
    """The same LM with its phase steps in Legendre coordinates: each accepted step lowers
    the fixed-seed loss, and the steps (in b units) add up to the way from the start."""
    from estimate.fit import forward_model
    from estimate.loss import reference_delta
    from estimate.polish import lm_polish
    from estimate.transforms import transform_for

    fm = forward_model(problem, "exp3")
    names = ["sigma_t", "albedo", "phase.b1", "phase.b2", "phase.b3"]
    start = {**fm.default_parameters(), **TRUTH, "sigma_t": 2.4, "phase.b1": 1.0, "phase.b2": 0.5, "phase.b3": 0.0}
    steps: list[dict[str, float]] = []
    p, losses = lm_polish(fm, problem, start, names, [transform_for(n, fm.specs[n]) for n in names], spp=256, seed=7,
                          delta_rel=reference_delta(FitSettings().delta_range), iterations=3, fixed_scale=2e5,
                          steps_out=steps, basis="legendre")
    assert len(steps) == len(losses) - 1 >= 1
    assert all(b < a for a, b in zip(losses, losses[1:]))
    for n in names:
        assert start[n] + sum(s[n] for s in steps) == pytest.approx(p[n], rel=1e-12, abs=1e-12)


def test_deadline_passes_once_its_budget_is_spent_and_names_each_stage_once():
    from estimate.deadline import Deadline

    none = Deadline.after(None)
    assert not none.passed("iterations") and none.hit == []
    assert not Deadline.after(3600.0).passed("polish")
    spent = Deadline.after(0.0, start=0.0)      # monotonic time 0 is long past
    assert spent.passed("polish") and spent.passed("polish") and spent.passed("lm")
    assert spent.hit == ["polish", "lm"]


def test_lm_polish_starts_no_step_after_its_deadline(problem):
    from estimate.deadline import Deadline
    from estimate.fit import forward_model
    from estimate.loss import reference_delta
    from estimate.polish import lm_polish
    from estimate.transforms import transform_for

    fm = forward_model(problem, "exp3")
    names = ["sigma_t", "albedo"]
    start = {**fm.default_parameters(), **TRUTH, "sigma_t": 2.2}
    spent = Deadline.after(0.0, start=0.0)
    steps: list[dict[str, float]] = []
    p, losses = lm_polish(fm, problem, start, names, [transform_for(n, fm.specs[n]) for n in names], spp=64, seed=7,
                          delta_rel=reference_delta(FitSettings().delta_range), iterations=3, fixed_scale=2e5,
                          steps_out=steps, deadline=spent)
    assert p == start and len(losses) == 1 and not steps and spent.hit == ["lm"]


def test_the_time_limit_covers_the_polishes_and_the_result_is_still_evaluated(problem):
    """A spent budget stops the iterations after one and starts neither the Gauss-Newton
    polish nor the LM (session 79's exp7 LM ran 60 steps past it); the stop reason says what
    the limit cut, and the result still has its evaluation and intervals."""
    st = FitSettings(seed=5, max_iterations=6, spp_start=16, spp_max=16, final_spp=32, window=3, scale="free",
                     uncertainty_spp=32, iterations_before_polish=4, polish_steps=2, polish_max_steps=2,
                     lm_iterations=3, lm_spp=32, time_limit_s=1e-9)
    r = fit_channel(problem, "exp3", start={"sigma_t": 3.0, "albedo": 0.85}, settings=st)
    assert r.iterations == 1 and not r.polish and r.lm_steps == 0
    assert r.stop_reason == ("time_limit; the time limit cut the Gauss-Newton polish and the "
                             "Levenberg-Marquardt steps")
    assert math.isfinite(r.loss) and all(math.isfinite(v) and v > 0 for v in r.uncertainties.values())


def test_lm_polish_minimises_a_loss_without_the_renders_variance(problem):
    """The decorrelated LM's loss (two half-spp renders, mean(r_A r_B)) does not fall as the
    samples per pixel rise, where the plain loss of one render does: its variance, which
    depends on the parameters, is not in it for the steps to walk down."""
    from estimate.fit import forward_model
    from estimate.loss import reference_delta
    from estimate.polish import lm_polish
    from estimate.transforms import transform_for

    fm = forward_model(problem, "exp3")
    names = ["sigma_t", "albedo"]
    start = {**fm.default_parameters(), **TRUTH}
    tr = [transform_for(n, fm.specs[n]) for n in names]

    def loss0(spp: int, decorrelated: bool) -> float:
        return lm_polish(fm, problem, start, names, tr, spp=spp, seed=11, iterations=0, fixed_scale=2e5,
                         delta_rel=reference_delta(FitSettings().delta_range), decorrelated=decorrelated)[1][0]

    plain_drop = loss0(8, False) - loss0(256, False)
    dec_drop = loss0(16, True) - loss0(512, True)
    assert plain_drop > 0 and abs(dec_drop) < 0.2 * plain_drop, (plain_drop, dec_drop)
