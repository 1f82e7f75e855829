"""Mismatch diagnosis: score-test screening on synthetic profiles with a concealed effect,
a clean recording found consistent, and the CLI's bad-input errors.

Synthetic recordings: the forward model with one effect switched on, rendered at high spp
(its Monte-Carlo variance added to the data variance), plus shot-like noise; the diagnosis
sees the base model at the true material parameters (no base fit: fast) and must rank the
concealed effect first. Optionally the recording carries frozen white noise `excess` times
the variance channel that the variance channel does not report (the simulated bench's
render noise, a real sensor's fixed-pattern noise). Tiny windows and low spp keep this well
under a minute.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import ClassVar

import numpy as np
import pytest
import yaml

import estimate.refit as refit_module
from estimate.beam import BeamProfile
from estimate.diagnose import (
    FREE_PARAMETERS,
    BaseFit,
    _bic_penalty,
    _choose,
    _free_names,
    _magnitude_lr_z,
    _rank_key,
    _run_fit_settings,
    bound_side,
    diagnose_channel,
    refine_channel,
    screen_candidates,
)
from estimate.errors import ModelParameterError
from estimate.extensions.base import ParameterSpec
from estimate.fit import STAGES, FitSettings
from estimate.forward import ForwardModel
from estimate.geometry import RigGeometry
from estimate.refit import (
    DECORRELATED,
    FIXED_SEED,
    RefitResult,
    best_scale,
    cross_covariance,
    evaluate,
    independent_residuals,
    recording_variance,
    refit,
    render_stack,
    smoothed_variance,
    still_descending,
)
from estimate.residuals import (
    fit_significance,
    local_noise_variance,
    localise,
    noise_floor,
    project_out,
    smooth_structure,
)
from estimate.screening import score_test
from rig.cli import main

TRUE = {"sigma_t": 2.0, "albedo": 0.9, "phase.g": 0.5}
ANGLES = np.array([20.0, 45.0, 70.0, 110.0, 135.0, 160.0])
GEOMETRY = RigGeometry(thickness_mm=1.0, magnification=0.5, profile_columns=(240, 272))
BEAM = BeamProfile.disk(0.3)
_MODELS: dict[tuple[str, ...], ForwardModel] = {}


def make_model(exts) -> ForwardModel:
    key = tuple(exts)
    if key not in _MODELS:
        _MODELS[key] = ForwardModel(GEOMETRY, BEAM, phase="hg", extensions=key)
    return _MODELS[key]


@dataclass
class Recording:
    angles_deg: np.ndarray
    x_mm: np.ndarray
    measured: np.ndarray
    variance: np.ndarray
    geometry: RigGeometry
    beam: BeamProfile
    channel: str = "g"


@dataclass
class FittableRecording(Recording):
    valid: np.ndarray | None = None


def record(effect: dict[str, float], seed: int = 3, excess: float = 0.0) -> Recording:
    exts = sorted({k.split(".")[0] for k in effect})
    m = make_model(exts)
    renders = np.stack([m.render_profiles({**TRUE, **effect}, ANGLES, spp=4096, seed=50 + k) for k in range(4)])
    truth = renders.mean(axis=0)
    scale = 1e4
    signal = scale * truth
    var = signal / 5.0 + (1e-3 * signal.max()) ** 2 + scale ** 2 * smoothed_variance(renders) / 4
    rng = np.random.default_rng(seed)
    meas = signal + rng.normal(size=signal.shape) * np.sqrt(var)
    # Frozen pixel noise that the variance channel does not hold.
    meas = meas + rng.normal(size=signal.shape) * np.sqrt(excess * var)
    x = np.asarray(GEOMETRY.pixel_x_mm(GEOMETRY.profile_window()))
    return Recording(ANGLES, x, meas, var, GEOMETRY, BEAM)


@pytest.mark.parametrize("effect", [
    {"stray_light.offset": 0.003},
    {"angle_offset.delta_deg": 3.0},
    {"lens_blur.core_sigma_px": 2.0},
])
def test_screening_ranks_the_concealed_effect_first(effect):
    rec = record(effect)
    base = BaseFit(dict(TRUE), 1e4, "hg")
    ev, loc, scores = screen_candidates(rec, base, make_model, spp=128, repeats=3,
                                        candidates=["stray_light", "angle_offset", "lens_blur",
                                                    "thickness_error", "sensor_nonlinearity"])
    concealed = next(iter(effect)).split(".")[0]
    assert ev.residuals.significant
    assert scores[0].name == concealed, [(s.name, round(s.statistic)) for s in scores]
    assert loc["summary"]


def test_clean_recording_has_no_significant_mismatch():
    rec = record({}, seed=11)
    base = BaseFit(dict(TRUE), 1e4, "hg")
    ev, _loc, _scores = screen_candidates(rec, base, make_model, spp=128, repeats=3, candidates=["stray_light"])
    assert not ev.residuals.significant, ev.residuals.reduced_chi2
    assert ev.residuals.reduced_chi2 < 1.25


def test_clean_recording_with_frozen_excess_noise_has_no_significant_mismatch():
    rec = record({}, seed=12, excess=30.0)
    base = BaseFit(dict(TRUE), 1e4, "hg")
    ev, _loc, _scores = screen_candidates(rec, base, make_model, spp=128, repeats=3, candidates=["stray_light"])
    res = ev.residuals
    assert res.reduced_chi2 > 4.0  # the HDR variance alone calls the perfect model wrong
    assert not res.significant, (res.reduced_chi2_adjusted, res.smooth, _scores)
    # The true excess of the normalised residuals: (31 var + s^2 var_model) / (var + s^2 var_model).
    mv = ev.scale ** 2 * ev.model_variance
    truth = np.sqrt(np.mean((31.0 * rec.variance + mv) / (rec.variance + mv), axis=1))
    assert np.all(np.abs(res.noise_scale / truth - 1.0) < 0.35), (res.noise_scale, truth)
    assert res.reduced_chi2_adjusted < 1.3
    # The verdict's p-value is the test that decided (beyond the fit), and it says so: the
    # locate stage's line printed the residuals' p as fitted, which may be small.
    from estimate.diagnose import _verdict

    verdict = _verdict(ev, _loc, _scores, [], None)
    assert verdict.startswith("no significant mismatch: no smooth structure in the residuals beyond what the "
                              f"fitted parameters absorb (p = {res.p_value_smooth:.2g})"), verdict
    assert "smooth_as_fitted" in res.extra


@pytest.mark.parametrize("effect", [{"stray_light.offset": 0.003},
                                    {"lens_blur.core_sigma_px": 2.5, "lens_blur.tail_fraction": 0.05}])
def test_concealed_effect_under_frozen_excess_noise_is_significant_and_named_first(effect):
    concealed = next(iter(effect)).split(".")[0]
    rec = record(effect, seed=13, excess=30.0)
    base = BaseFit(dict(TRUE), 1e4, "hg")
    d = diagnose_channel(rec, base, make_model, candidates=["stray_light", "lens_blur", "sensor_nonlinearity"], spp=128,
                         repeats=3, iterations=4)
    assert d.significant, d.before.residuals.smooth
    assert d.candidates[0].name == concealed, [(c.name, round(c.statistic)) for c in d.candidates]
    assert d.confirmed[:1] == [concealed], d.confirmations
    assert d.after is not None and d.after.residuals.reduced_chi2_adjusted < d.before.residuals.reduced_chi2_adjusted


def test_noise_floor_recovers_the_white_excess_and_ignores_smooth_mismatch():
    rng = np.random.default_rng(5)
    f_true = np.array([1.0, 3.0, 10.0, 40.0])
    smooth = 50.0 * np.sin(np.linspace(0, np.pi, 200))  # a mismatch far above the noise
    r = rng.normal(size=(4, 200)) * f_true[:, None] + smooth
    f, m = noise_floor(r)
    assert np.all(np.abs(f / f_true - 1.0) < 0.15), f
    assert np.all(m > 100)
    res = fit_significance(r, 3)
    assert res.significant and res.reduced_chi2_adjusted > 10


@pytest.mark.parametrize("noise", ["gauss", "student5", "drifting", "fireflies", "steep"])
def test_false_positive_rate_on_white_noise_with_random_excess(noise):
    """Pure white-noise residuals, each angle with its own random excess factor 1..50 (a
    t(5) variant for heavy tails, a variant whose excess drifts by 20 % along the profile,
    render-like fireflies: each pixel the mean of 64 lognormal(0, 1.5) path contributions,
    kurtosis ~100 like a simulated-bench fit's residuals; a noise level that
    grows 20x along the profile like the tail of a spot): the smooth test must reject at
    most at its nominal level alpha = 1e-3."""
    rng = np.random.default_rng({"gauss": 21, "student5": 22, "drifting": 23, "fireflies": 24, "steep": 25}[noise])
    trials, hits, small_p = 600, 0, 0
    for _ in range(trials):
        n_ang, width = int(rng.integers(4, 12)), int(rng.choice([32, 64, 256]))
        if noise == "gauss":
            e = rng.normal(size=(n_ang, width))
        elif noise == "student5":
            e = rng.standard_t(5, size=(n_ang, width)) / np.sqrt(5 / 3)
        elif noise == "drifting":
            e = rng.normal(size=(n_ang, width)) * (1.0 + 0.2 * np.sin(np.linspace(0, np.pi, width)))
        elif noise == "fireflies":
            e = _render_noise(rng, (n_ang, width))
        else:
            e = rng.normal(size=(n_ang, width)) * np.exp(np.linspace(0.0, 3.0, width))
        res = fit_significance(e * rng.uniform(1, 50, size=n_ang)[:, None], 0)
        hits += res.significant
        small_p += res.p_value_smooth < 0.01
    assert hits <= 2, hits  # expected 0.6 at alpha = 1e-3
    assert small_p <= 0.02 * trials  # the p-value is conservative, not anti-conservative


def test_score_test_is_chi2_under_the_null_and_large_under_the_alternative():
    rng = np.random.default_rng(0)
    n = 400
    X = np.stack([np.ones(n), np.linspace(-1, 1, n)], axis=1)
    Z = np.sin(np.linspace(0, 6, n))[:, None]
    stats_null = [score_test(rng.normal(size=n), X, Z).statistic for _ in range(300)]
    assert 0.8 < np.mean(stats_null) < 1.2  # chi^2(1) has mean 1
    r = rng.normal(size=n) + 0.5 * Z[:, 0] + 3.0 * X[:, 0]  # base-direction part is projected out
    res = score_test(r, X, Z)
    assert res.statistic > 8 and res.dof == 1 and res.coefficients[0] == pytest.approx(0.5, abs=0.15)


def _render_noise(rng: np.random.Generator, shape: tuple[int, ...], samples: int = 64) -> np.ndarray:
    """Zero-mean, unit-variance Monte-Carlo-like pixel noise: the mean of `samples`
    lognormal(0, 1.5) path contributions per pixel (rare bright paths: fireflies)."""
    s = 1.5
    mean, var = math.exp(s * s / 2), (math.exp(s * s) - 1) * math.exp(s * s)
    x = rng.lognormal(0.0, s, size=(*shape, samples)).mean(axis=-1)
    return (x - mean) / math.sqrt(var / samples)


def test_candidates_beyond_doubt_are_ranked_by_what_they_could_remove():
    """The light bench's lens_blur-2: the blur's statistic was the largest, but its F law
    (render noise from a few renders) kept a finite p while chi^2 tails underflowed to 0, and
    four candidates that could remove far less ranked ahead of it."""
    from estimate.screening import CandidateScore, ranked

    def cand(name, stat, dof, log10_p):
        return CandidateScore(name, stat, dof, 10 ** log10_p, log10_p, stat / 1.2e5, [0.0] * dof)

    scores = [cand("beam_halo", 82948.0, 2, -math.inf), cand("sensor_nonlinearity", 9654.0, 1, -math.inf),
              cand("lens_blur", 87222.0, 2, -304.4), cand("stray_light", 42.0, 2, -9.0),
              cand("angle_offset", 30.0, 1, -7.4)]
    assert [c.name for c in ranked(scores)] == ["lens_blur", "beam_halo", "sensor_nonlinearity", "stray_light",
                                                "angle_offset"]
    # Above the floor the p-value decides, whatever the statistic.
    assert [c.name for c in ranked([cand("a", 40.0, 3, -6.0), cand("b", 30.0, 1, -7.0)])] == ["b", "a"]


def test_robust_score_test_holds_its_level_where_the_noise_is_heavy_tailed_and_uneven():
    """Fireflies and a noise level 4x higher where the candidate's column lives: the
    classical LM (unit variance assumed) rejects far too often, the sandwich one does not,
    and a real signal of that shape is still found."""
    rng = np.random.default_rng(3)
    n = 600
    x = np.linspace(-1, 1, n)
    X = np.stack([np.ones(n), x], axis=1)
    Z = np.exp(-((x - 0.5) / 0.1) ** 2)[:, None]
    level = 1.0 + 3.0 * Z[:, 0]
    plain, robust = [], []
    for _ in range(200):
        r = _render_noise(rng, (n,)) * level
        v = local_noise_variance(r)
        plain.append(score_test(r, X, Z).log10_p)
        robust.append(score_test(r, X, Z, noise_var=v).log10_p)
    assert np.mean(np.array(plain) < -3) > 0.2
    assert np.mean(np.array(robust) < -3) <= 0.02
    r = rng.normal(size=n) * level + 3.0 * Z[:, 0]
    assert score_test(r, X, Z, noise_var=local_noise_variance(r)).log10_p < -6


def _light_like_render_noise(rng: np.random.Generator, n_ang: int, width: int, reach: int = 6) -> np.ndarray:
    """Render noise correlated along the row like the light engine's (one path adds to the
    columns its vertices land in, a few pixels apart): white noise smoothed by a
    `reach`-pixel kernel, unit variance per pixel."""
    k = np.exp(-0.5 * (np.arange(-3 * reach, 3 * reach + 1) / reach) ** 2)
    k /= np.sqrt(np.sum(k ** 2))
    e = rng.normal(size=(n_ang, width + 6 * reach))
    return np.stack([np.convolve(row, k, mode="valid") for row in e])[:, :width]


def test_correlated_render_noise_joins_the_null_of_the_smooth_and_score_tests():
    """Residuals = sensor noise + the mean render's noise correlated along the row (2x the
    sensor's variance, the light engine's at the diagnosis' spp). Without the render
    noise's cross terms the smooth test calls most correct fits wrong and a smooth
    candidate's score test is far above chi^2(1); with the modes from independent renders
    (`render_noise_modes`) both hold their level, and a real smooth mismatch is still found."""
    from estimate.residuals import render_noise_modes

    rng = np.random.default_rng(31)
    n_ang, width, repeats = 8, 256, 6
    x = np.linspace(-1, 1, width)
    X = np.ones((n_ang * width, 1))
    Z = np.tile(np.exp(-(x / 0.3) ** 2), n_ang)[:, None]
    sigma = np.ones((n_ang, width))
    plain_sig = with_sig = 0
    plain_p, with_p = [], []
    for _ in range(60):
        # `repeats` renders, each with noise of variance 2 * repeats (their mean: 2)
        renders = np.stack([math.sqrt(2 * repeats) * _light_like_render_noise(rng, n_ang, width)
                            for _ in range(repeats)])
        r = rng.normal(size=(n_ang, width)) + renders.mean(axis=0)
        r = r / math.sqrt(3.0)
        # modes from another set of renders of the same model (as `independent_residuals`)
        other = np.stack([math.sqrt(2 * repeats) * _light_like_render_noise(rng, n_ang, width)
                          for _ in range(repeats)])
        modes = render_noise_modes(other, 1.0, sigma * math.sqrt(3.0), repeats)
        plain_sig += fit_significance(r, 1).significant
        with_sig += fit_significance(r, 1, noise_modes=modes).significant
        v = np.ones(r.size)
        plain_p.append(score_test(r.ravel(), X, Z, noise_var=v).log10_p)
        with_p.append(score_test(r.ravel(), X, Z, noise_var=v, noise_modes=modes).log10_p)
    assert plain_sig > 30 and with_sig <= 1
    # p < 0.01 in 1 % of correct fits (with the modes' own uncertainty: an F law)
    assert np.mean(np.array(plain_p) < -2) > 0.3 and np.mean(np.array(with_p) < -2) <= 0.05
    # a smooth mismatch of 1.5 sigma over the profile's middle (as strong as the correlated noise at
    # those scales) is still seen
    renders = np.stack([math.sqrt(2 * repeats) * _light_like_render_noise(rng, n_ang, width) for _ in range(repeats)])
    r = (rng.normal(size=(n_ang, width)) + renders.mean(axis=0)) / math.sqrt(3.0) + 1.5 * Z[:, 0].reshape(n_ang, width)
    other = np.stack([math.sqrt(2 * repeats) * _light_like_render_noise(rng, n_ang, width) for _ in range(repeats)])
    modes = render_noise_modes(other, 1.0, sigma * math.sqrt(3.0), repeats)
    assert fit_significance(r, 1, noise_modes=modes).significant
    assert score_test(r.ravel(), X, Z, noise_var=np.ones(r.size), noise_modes=modes).log10_p < -3


def test_the_recordings_own_render_noise_joins_the_null_when_declared():
    """A simulated recording carries frozen render noise of the same engine (the camera
    twin's): correlated along the row like the model's, and as large as one model render's
    (the demo world's share, `estimate.refit.recorded_noise_share`). The model's mean of
    4 renders alone leaves most correct fits "significant"; with `recorded` the smooth test
    holds its level, and a smooth mismatch as large as that noise at its scales is found."""
    from estimate.residuals import render_noise_modes

    rng = np.random.default_rng(70)
    n_ang, width, repeats, recorded = 10, 256, 4, 1.0
    x = np.linspace(-1, 1, width)
    total = 1.0 + 1.0 / repeats + recorded            # sensor + model mean + recording, per pixel
    sigma = np.full((n_ang, width), math.sqrt(total))

    def renders(k: int) -> np.ndarray:                # k renders of unit variance per pixel
        return np.stack([_light_like_render_noise(rng, n_ang, width) for _ in range(k)])

    def residual() -> np.ndarray:
        model = renders(repeats).mean(axis=0)
        frozen = math.sqrt(recorded) * _light_like_render_noise(rng, n_ang, width)
        return (rng.normal(size=(n_ang, width)) + model + frozen) / math.sqrt(total)

    plain_sig = with_sig = 0
    for _ in range(40):
        r, other = residual(), renders(24)
        plain_sig += fit_significance(r, 1, noise_modes=render_noise_modes(other, 1.0, sigma, repeats)).significant
        with_sig += fit_significance(r, 1, noise_modes=render_noise_modes(other, 1.0, sigma, repeats,
                                                                           recorded)).significant
    assert plain_sig > 20 and with_sig <= 1
    # the modes' covariance is one render's times 1 / repeats + recorded
    m0 = render_noise_modes(renders(24), 1.0, sigma, repeats)
    m1 = render_noise_modes(renders(24), 1.0, sigma, repeats, recorded)
    ratio = float(np.sum(m1 ** 2) / np.sum(m0 ** 2))
    assert abs(ratio - (1.0 / repeats + recorded) * repeats) < 0.5
    bump = np.exp(-(x / 0.3) ** 2)
    r = residual() + 1.5 * bump[None, :]
    assert fit_significance(r, 1, noise_modes=render_noise_modes(renders(24), 1.0, sigma, repeats,
                                                                 recorded)).significant


def test_recorded_light_paths_reads_the_declared_tier_of_the_profile_row():
    from estimate.problem import recorded_light_paths

    declared = {"engine": "light", "tiers": [{"rows": [251, 256], "spp": 1024, "paths_per_image": 524288},
                                             {"rows": [237, 251], "spp": 32, "paths_per_image": 16384}]}
    assert recorded_light_paths(declared, 254) == 524288
    assert recorded_light_paths(declared, 240) == 16384
    assert recorded_light_paths(declared, 300) is None                 # no tier holds the row
    assert recorded_light_paths(declared, 255, bin_y=2) == 524288      # binned rows 254-255
    assert recorded_light_paths(declared, 251, bin_y=2) is None        # 250-251 straddle two tiers
    assert recorded_light_paths({**declared, "engine": "camera"}, 254) is None   # white: the floor's
    assert recorded_light_paths(None, 254) is None                     # a real camera
    assert recorded_light_paths({"engine": "light", "tiers": [{"rows": "x"}]}, 254) is None


def test_local_noise_variance_follows_the_level_and_ignores_a_smooth_mismatch():
    rng = np.random.default_rng(8)
    w = 400
    level = np.linspace(1.0, 5.0, w)
    smooth = 100.0 * np.sin(np.linspace(0, np.pi, w))  # far above the noise, smooth on the pixel scale
    v = local_noise_variance(rng.normal(size=(60, w)) * level + smooth).mean(axis=0)
    ratio = (v / level ** 2).reshape(8, -1).mean(axis=1)  # 8 stretches of 50 px
    assert np.all(np.abs(ratio - 1.0) < 0.1), ratio


def test_structure_along_the_fitted_parameters_is_not_left_out_physics():
    """A fit a little off its optimum leaves a residual along its own derivative columns:
    significant as fitted, gone once projected out; structure outside them stays."""
    rng = np.random.default_rng(12)
    x = np.linspace(-1, 1, 128)
    col = np.broadcast_to(np.exp(-(x / 0.3) ** 2), (6, 128))  # d(profile)/d(parameter)
    other = np.broadcast_to(0.5 + 0.5 * x, (6, 128))  # e.g. a stray-light ramp
    noise = rng.normal(size=(6, 128))
    off = noise + 3.0 * col
    assert smooth_structure(off)[2]
    assert not smooth_structure(project_out(off, col.reshape(-1, 1)))[2]
    assert smooth_structure(project_out(off + 3.0 * other, col.reshape(-1, 1)))[2]


def _lls_chi2(y: np.ndarray, cols: np.ndarray) -> tuple[float, np.ndarray]:
    coef, *_ = np.linalg.lstsq(cols, y, rcond=None)
    return float(np.sum((y - cols @ coef) ** 2)), coef


def test_likelihood_ratio_magnitude_holds_its_level_and_survives_a_misfit():
    """Linear-Gaussian stand-in for a refit: a material column, an effect column (offset).
    Without the effect the LR magnitude is |N(0,1)|-distributed; an effect at its neutral
    value scores 0; and a real effect under a misfit 400x the noise (which inflates the
    quasi-likelihood variance) still scores far from absent."""
    rng = np.random.default_rng(5)
    n = 400
    x = np.linspace(-1, 1, n)
    material = np.exp(-(x / 0.3) ** 2)
    effect = np.ones(n)
    both = np.stack([material, effect], axis=1)
    z = []
    for _ in range(2000):
        y = 3.0 * material + rng.normal(size=n)
        c_ctrl, _ = _lls_chi2(y, material[:, None])
        c_fit, coef = _lls_chi2(y, both)
        c_neutral = float(np.sum((y - both @ np.array([coef[0], 0.0])) ** 2))
        fit = RefitResult({"stray_light.offset": coef[1]}, 1.0, {}, c_fit, 1)
        z.append(_magnitude_lr_z(fit, c_ctrl, c_neutral, n, 2, "stray_light"))
    # One magnitude parameter in the fit: P(|N(0,1)| > 1) = 0.317 (binomial sd 0.010).
    frac = float(np.mean(np.array(z) > 1.0))
    assert 0.275 < frac < 0.36, frac
    fit0 = RefitResult({"stray_light.offset": 0.0}, 1.0, {}, 420.0, 1)
    assert _magnitude_lr_z(fit0, 500.0, 420.0, n, 2, "stray_light") == 0.0
    # Misfit: an unmodelled wiggle 20x the noise; the offset is 86 % of the chi^2 drop.
    y = 3.0 * material + 60.0 * effect + 20.0 * np.sin(9 * x) * material + rng.normal(size=n)
    c_ctrl, _ = _lls_chi2(y, material[:, None])
    c_fit, coef = _lls_chi2(y, both)
    assert c_fit / n > 20  # a poor fit
    c_neutral = float(np.sum((y - both @ np.array([coef[0], 0.0])) ** 2))
    fit = RefitResult({"stray_light.offset": coef[1]}, 1.0, {}, c_fit, 1)
    assert _magnitude_lr_z(fit, c_ctrl, c_neutral, n, 2, "stray_light") > 5.0


def test_evaluation_of_a_given_render_stack_is_the_evaluation_that_renders_it():
    """The final fit's renders are made once and shared by its evaluation and the backward
    check: evaluating a stack from `render_stack` gives exactly what rendering it anew does."""
    rec = record({})
    m = make_model([])
    stack = render_stack(m, TRUE, rec, spp=32, seed=900, repeats=2, angle_idx=[1, 4])
    assert stack.shape == (2, 2, rec.measured.shape[1])
    a = evaluate(m, TRUE, rec, 3, spp=32, seed=900, repeats=2, angle_idx=[1, 4])
    b = evaluate(m, TRUE, rec, 3, spp=32, seed=900, repeats=2, angle_idx=[1, 4], renders=stack)
    assert np.array_equal(a.model, b.model) and a.residuals.chi2 == b.residuals.chi2
    c = evaluate(m, TRUE, rec, 3, spp=32, seed=901, repeats=2, angle_idx=[1, 4])
    assert not np.array_equal(a.model, c.model)


def test_final_fit_by_the_estimator_replaces_the_refit_of_a_confirmed_effect():
    """With a stray-light offset concealed, the confirmed model is fitted again by the
    estimator (log loss, Adam + Gauss-Newton) from the Levenberg-Marquardt refit carried over
    to the calibrated scale (`rig estimate`'s default); its result becomes `after` (evaluated
    in the same metric), the refit is kept alongside."""
    from estimate.loss import ScaleCalibration

    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    d = diagnose_channel(pb, BaseFit(dict(TRUE), 1e4, "hg"), make_model, candidates=["stray_light"], spp=128,
                         repeats=3, iterations=8)
    assert d.confirmed == ["stray_light"]
    lm = d.after
    # what the LM refit reports is the decorrelated step from its fixed-seed optimum
    assert d.fixed_seed_after and d.fixed_seed_after != lm.parameters
    # The recording's own scale. Under a free scale the albedo trades against it: on session
    # 57's machine (AVX2, renders about half as fast) that fit ran the albedo to its bound
    # (0.999999) and sigma_t 18 % high, where earlier sessions' machines had ended within 15 %.
    cal = ScaleCalibration(scale=1e4, power_e_per_s=1.0, beam_power=1.0, calibration_nd=1.0, collection_sr=1.0,
                           pixel_area_mm2=1.0)
    st = FitSettings(seed=2, scale="calibrated", max_iterations=14, spp_start=64, spp_max=128, final_spp=256,
                     window=3, polish_steps=1)
    stages: list[str] = []
    fr = refine_channel(pb, d, make_model, st, spp=128, repeats=3, on_stage=stages.append, scale_calibration=cal)
    assert stages == list(STAGES)              # the final fit reports its stages (rig's status line)
    assert fr is not None and d.final_fit["kept"] and d.final_fit["iterations"] == fr.iterations
    # It starts from the refit's effect, carried over to the calibrated scale (the material:
    # the better of the refit's and the coarse grid's, `_final_fit_start`).
    k = d.final_fit["start"]["radiance_factor"]
    assert k == pytest.approx(lm.scale / cal.scale)
    assert fr.extensions == ["stray_light"]
    assert fr.start["stray_light.offset"] == pytest.approx(k * lm.parameters["stray_light.offset"])
    assert d.lm_after is lm and d.after.parameters == make_model(["stray_light"]).validate(fr.parameters)
    assert fr.parameters["stray_light.offset"] == pytest.approx(0.01, rel=0.5)
    # The material within three of the final fit's own standard errors (sigma_t about 10 %).
    for name in ("sigma_t", "albedo"):
        assert abs(fr.parameters[name] - TRUE[name]) < 3.0 * fr.uncertainties[name], name
    assert abs(fr.parameters["sigma_t"] / TRUE["sigma_t"] - 1) < 0.3
    assert d.after.residuals.reduced_chi2_adjusted <= d.before.residuals.reduced_chi2_adjusted
    doc = d.as_dict()
    assert doc["material_after"]["sigma_t"] == fr.parameters["sigma_t"]
    assert doc["refit_lm"]["material"]["sigma_t"] == lm.parameters["sigma_t"]
    assert doc["material_fixed_seed_after"] == {k: d.fixed_seed_after[k] for k in d.material_names}
    assert doc["material_uncertainty_after"]["sigma_t"] == fr.uncertainties["sigma_t"]
    assert doc["confirmed_effects"]["stray_light"]["stray_light.offset"]["value"] == d.after.parameters[
        "stray_light.offset"]
    # Where the time went: every stage ran here, and the stages add up to the whole.
    from estimate.diagnose import DIAGNOSIS_STAGES

    assert list(doc["time_by_stage_s"]) == list(DIAGNOSIS_STAGES)
    assert all(v > 0 for v in doc["time_by_stage_s"].values())
    assert doc["time_by_stage_s"]["final_fit"] == d.final_fit["time_s"]
    assert sum(doc["time_by_stage_s"].values()) == pytest.approx(d.time_s, rel=1e-3, abs=0.05)
    # A named magnitude that the fit's range stopped is marked as such, in the JSON and the text.
    from estimate.diagnose import summary_text

    offset = d.after.parameters["stray_light.offset"]
    assert set(d.parameter_ranges) == set(FREE_PARAMETERS["stray_light"])
    assert "at_bound" not in doc["confirmed_effects"]["stray_light"]["stray_light.offset"]
    pinned = dataclasses.replace(d, parameter_ranges={"stray_light.offset": [(-1.0, offset)]}).as_dict()
    assert pinned["confirmed_effects"]["stray_light"]["stray_light.offset"]["at_bound"] == "upper"
    text = summary_text({"channels": {"g": pinned}, "run_id": "x", "refit_run": None})
    assert "(at the upper end of its range: stopped there, not measured)" in text
    assert f"time {d.time_s:.0f} s: evaluating the fit " in text and "the estimator's final fit" in text


def test_partial_explanation_needs_a_remaining_mismatch_and_a_small_share():
    from estimate.diagnose import MIN_SHARE, explained_share, partial_explanation

    NS = SimpleNamespace

    def ev(chi2: float, significant: bool) -> SimpleNamespace:
        return NS(residuals=NS(reduced_chi2_adjusted=chi2, significant=significant),
                  parameters={"sigma_t": 3.6, "albedo": 0.9, "lens_blur.tail_fraction": 0.1})

    before = ev(11.80, True)
    # The bench boundary session's --quick glare tail: 18 % of the excess, a mismatch left.
    p = partial_explanation(before, ev(9.90, True), ["lens_blur"], ["sigma_t", "albedo"], MIN_SHARE)
    assert p["effects"] == ["lens_blur"] and p["share_explained"] == pytest.approx(1.9 / 10.8)
    assert p["material_with"] == {"sigma_t": 3.6, "albedo": 0.9} and p["reduced_chi2_adjusted_with"] == 9.90
    # Most of the excess removed, or no significant mismatch left (a weak effect near
    # detection moves chi^2 little): named.
    assert partial_explanation(before, ev(1.20, True), ["lens_blur"], [], MIN_SHARE) == {}
    assert partial_explanation(ev(1.11, True), ev(1.09, False), ["sensor_nonlinearity"], [], MIN_SHARE) == {}
    assert partial_explanation(before, ev(9.90, True), ["lens_blur"], [], 0.0) == {}   # the full run: off
    # ... but a model that fits no better than the base fit explains none of the mismatch,
    # whatever the share asked for (the two-lobe phase session's angle offset: 11.97 -> 13.11)
    worse = partial_explanation(before, ev(13.1, True), ["angle_offset"], [], 0.0)
    assert worse["effects"] == ["angle_offset"] and worse["share_explained"] < 0
    assert partial_explanation(before, ev(11.80, True), ["angle_offset"], [], 0.0)["share_explained"] == 0.0
    assert explained_share(ev(0.98, True), ev(0.84, False)) == 1.0   # no excess to explain


def test_quick_names_no_effect_that_removes_too_little_of_the_excess(monkeypatch):
    """Where the Levenberg-Marquardt refit is the final model (`--quick`), confirmed effects
    are named only if that model removes `min_share` of the excess reduced chi^2 at the floor
    or leaves no significant mismatch; else they are reported as partial and the verdict
    names no cause."""
    import estimate.diagnose as dmod
    from estimate.diagnose import MIN_SHARE, explained_share, summary_text

    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    kw = {"candidates": ["stray_light"], "spp": 128, "repeats": 3, "iterations": 8}
    named = diagnose_channel(pb, BaseFit(dict(TRUE), 1e4, "hg"), make_model, min_share=MIN_SHARE, **kw)
    assert named.confirmed == ["stray_light"] and not named.partial
    share = explained_share(named.before, named.after)
    assert MIN_SHARE <= share <= 1.05
    # The same diagnosis with a bar above what any model can reach, and the refit taken to
    # leave a significant mismatch: confirmed, not named.
    monkeypatch.setattr(dmod, "_still_significant", lambda ev: True)
    d = diagnose_channel(pb, BaseFit(dict(TRUE), 1e4, "hg"), make_model, min_share=1.5,
                         reuse=named.first_round, **kw)
    assert [e["effect"] for e in d.confirmations if e["confirmed"]] == ["stray_light"]
    assert d.confirmed == [] and d.after is None and not d.importance and not d.fixed_seed_after
    assert d.partial["effects"] == ["stray_light"] and d.partial["share_explained"] == pytest.approx(share)
    assert "no cause is named; run the diagnosis without --quick" in d.verdict and "left-out physics" not in d.verdict
    doc = d.as_dict()
    assert doc["confirmed_effects"] == {} and doc["partial"]["min_share"] == 1.5
    text = summary_text({"channels": {"g": doc}, "run_id": "x", "refit_run": None})
    assert "not named: stray_light removed" in text and "left-out physics:" not in text


def test_with_the_final_fit_to_follow_the_last_round_leaves_the_joint_refit_to_it():
    """`rig diagnose` (not --quick): once no further round can screen at the joint refit,
    the model stage is the last candidate's refit evaluated on all angles; the estimator's
    final fit starts there and replaces it."""
    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    d = diagnose_channel(pb, BaseFit(dict(TRUE), 1e4, "hg"), make_model, candidates=["stray_light"], spp=128,
                         repeats=3, iterations=8, final_fit_follows=True)
    assert d.confirmed == ["stray_light"] and d.model_stage == "deferred"
    lm = d.after
    entry = next(e for e in d.confirmations if e["confirmed"])
    assert {k: lm.parameters[k] for k in entry["parameters"]} == entry["parameters"]
    assert lm.model.shape == rec.measured.shape           # evaluated on every angle, held-out ones too
    assert not d.fixed_seed_after                       # no decorrelated step of a joint refit
    assert d.uncertainties_after["stray_light.offset"] > 0  # the candidate refit's own
    st = FitSettings(seed=2, scale="free", max_iterations=14, spp_start=64, spp_max=128, final_spp=256, window=3,
                     polish_steps=1)
    fr = refine_channel(pb, d, make_model, st, spp=128, repeats=3)
    assert fr is not None and d.final_fit["kept"] and fr.start["sigma_t"] == lm.parameters["sigma_t"]
    assert d.lm_after is lm and fr.parameters["stray_light.offset"] == pytest.approx(0.01, rel=0.5)
    doc = d.as_dict()
    assert doc["model_stage"] == "deferred" and doc["material_fixed_seed_after"] is None
    assert sum(doc["time_by_stage_s"].values()) == pytest.approx(d.time_s, rel=1e-3, abs=0.05)
    from estimate.diagnose import summary_text

    text = summary_text({"channels": {"g": doc}, "run_id": "x", "refit_run": None})
    assert "the last candidate's Levenberg-Marquardt refit had reduced chi2" in text


def _round_fitter(pb, calls: list):
    """A `round_fit` for `diagnose_channel`, as `run_diagnosis` builds it, that keeps each fit
    it made in `calls`."""
    import estimate.diagnose as dg

    st = FitSettings(seed=2, scale="free", max_iterations=14, spp_start=64, spp_max=128, final_spp=256, window=3,
                     polish_steps=1)

    def round_fit(refitted):
        done = dg.estimator_fit(pb, make_model(refitted.extensions), refitted, st, spp=128, seed=1000, repeats=3)
        calls.append(done)
        return done
    return round_fit, st


def test_a_round_with_room_for_another_is_judged_on_the_estimators_fit_which_becomes_the_final_fit():
    """With the final fit to follow and a second effect possible, the round that confirms the
    concealed stray light fits its model by the estimator (`round_fit`) instead of the joint
    Levenberg-Marquardt refit; the check reads that fit, the rounds stop there, and
    `refine_channel` takes it as the final fit rather than fitting it again."""
    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    calls: list = []
    round_fit, st = _round_fitter(pb, calls)
    d = diagnose_channel(pb, BaseFit(dict(TRUE), 1e4, "hg"), make_model, candidates=["stray_light", "angle_offset"],
                         spp=128, repeats=3, iterations=8, final_fit_follows=True, round_fit=round_fit)
    assert d.confirmed == ["stray_light"] and len(calls) == 1 and d.round_fit is calls[0]
    assert d.round_fit.extensions == ["stray_light"]
    check = d.explained_checks[0]
    assert check["stage"] == "estimator fit" and check["explained"]
    assert check["reduced_chi2_adjusted_fit"] == d.round_fit.evaluation.residuals.reduced_chi2_adjusted
    # the better of the two fits of the model decides
    assert check["reduced_chi2_adjusted"] == min(check["reduced_chi2_adjusted_fit"], check["reduced_chi2_adjusted_refit"])
    assert all(e["round"] == 1 for e in d.confirmations)      # no second round
    # `after` is the candidate's refit on every angle, as where the joint refit is deferred
    assert d.model_stage == "deferred" and d.after.model.shape == rec.measured.shape
    assert check["reduced_chi2_adjusted_refit"] == d.after.residuals.reduced_chi2_adjusted
    assert d.stage_times_s["model"] >= d.round_fit.time_s and "final_fit" not in d.stage_times_s
    made = d.round_fit
    fr = refine_channel(pb, d, make_model, st, spp=128, repeats=3)
    assert fr is made.fit and d.after is made.evaluation and d.final_fit["made_for"] == "the rounds' check"
    assert d.final_fit["time_s"] == made.time_s and "final_fit" not in d.stage_times_s   # counted once, in "model"
    assert fr.parameters["stray_light.offset"] == pytest.approx(0.01, rel=0.5)
    doc = d.as_dict()
    assert sum(doc["time_by_stage_s"].values()) == pytest.approx(d.time_s, rel=1e-3, abs=0.05)
    from estimate.diagnose import summary_text

    text = summary_text({"channels": {"g": doc}, "run_id": "x", "refit_run": None})
    assert "with stray_light the reduced chi2 at the floor is" in text and "fitted by the estimator, " in text


def test_where_the_estimators_fit_leaves_a_mismatch_the_next_round_starts_from_it(monkeypatch):
    """A check that fails (the bar set below any fit here) sends the diagnosis into a second
    round screened at the estimator's fit; where that round confirms nothing (nothing else is
    concealed), the round-1 model stays, with its joint Levenberg-Marquardt refit made after
    all (`after`, at its decorrelated step) and its estimator's fit taken as the final fit,
    which `refine_channel` compares with that refit."""
    import estimate.diagnose as dg

    monkeypatch.setattr(dg, "EXPLAINED_REDUCED_CHI2", 0.0)
    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    calls: list = []
    round_fit, st = _round_fitter(pb, calls)
    screened_at: list[dict] = []
    real = dg._screen

    def spy(problem, current, *a, **kw):
        screened_at.append(dict(current.parameters))
        return real(problem, current, *a, **kw)

    monkeypatch.setattr(dg, "_screen", spy)
    d = diagnose_channel(pb, BaseFit(dict(TRUE), 1e4, "hg"), make_model, candidates=["stray_light", "angle_offset"],
                         spp=128, repeats=3, iterations=6, final_fit_follows=True, round_fit=round_fit)
    assert len(calls) == 1 and not d.explained_checks[0]["explained"]
    # round 1 screened at the base fit, round 2 at the estimator's fit of the stray light
    assert len(screened_at) == 2 and screened_at[1] == calls[0].evaluation.parameters
    # each round's screening and control are timed, and the second round's ranking is kept
    assert [r["round"] for r in d.rounds] == [1, 2] and d.rounds[1]["after"] == ["stray_light"]
    assert [c["name"] for c in d.rounds[1]["candidates"]] == ["angle_offset"] and "candidates" not in d.rounds[0]
    assert all(r["screening_s"] > 0 for r in d.rounds) and d.rounds[0]["control_s"] > 0
    assert json.loads(json.dumps(d.as_dict()["rounds"])) == d.as_dict()["rounds"]
    assert d.confirmed == ["stray_light"] and d.round_fit is calls[0] and d.model_stage == "refit"
    assert d.fixed_seed_after and d.after.parameters != d.fixed_seed_after   # the joint refit's decorrelated step
    assert d.after.parameters != calls[0].evaluation.parameters
    fr = refine_channel(pb, d, make_model, st, spp=128, repeats=3)
    assert len(calls) == 1 and d.final_fit["made_for"] == "the rounds' check"     # not fitted again
    assert d.final_fit["time_s"] == calls[0].time_s
    # the estimator's fit is reported unless it stopped short of the refit (`REFIT_PREFERRED_MARGIN`)
    assert (fr is calls[0].fit) == (d.final_fit.get("reported") != "refit")


def _every_refit_passes(monkeypatch, scores, rank=None):
    """Stub the screening with `scores(exts)` (the ranked CandidateScores at the model with
    extensions `exts`, after the real screening ran for its side records) and make every
    refit pass its tests, its independently rendered gain (`rank`) ranking stray light <
    angle offset < beam halo: the round's control flow is what is left to test."""
    import estimate.diagnose as dg

    real_screen, real_try = dg._screen, dg._Confirmation.try_candidate
    rank = rank or {"stray_light": 50.0, "angle_offset": 80.0, "beam_halo": 500.0}

    def screen(problem, current, exts, *a, **kw):
        real_screen(problem, current, exts, *a, **kw)
        return scores(exts)

    def try_candidate(self, name, rnd, start, *a, **kw):
        entry, fit = real_try(self, name, rnd, start, *a, **kw)
        entry.update(delta_bic=1e3, delta_bic_independent=rank[name], magnitude_sigma=50.0, no_harm=True,
                     heldout_ok=True)
        return entry, fit

    monkeypatch.setattr(dg, "_screen", screen)
    monkeypatch.setattr(dg._Confirmation, "try_candidate", try_candidate)


def test_the_first_round_compares_its_flagged_candidates_and_later_rounds_take_the_first_that_passes(monkeypatch):
    """Round 1 refits both flagged candidates though the first passes, and adds the one the
    independent renders rank higher (confusable effects screen in either order at the base
    fit); round 2 refits in screening order and stops at the first that passes every test,
    recording the flagged candidate it left (`FIRST_PASS_ROUNDS_FROM`). Every refit here
    passes, its rank set by the stub: the rule is the control flow around the tests."""
    import estimate.diagnose as dg
    from estimate.screening import CandidateScore

    monkeypatch.setattr(dg, "EXPLAINED_REDUCED_CHI2", 0.0)      # always look for a second effect
    order = {1: ["stray_light", "angle_offset"], 2: ["stray_light", "beam_halo"]}
    rounds_screened: list[int] = []

    def scores(exts):
        rounds_screened.append(len(exts) + 1)
        return [CandidateScore(n, 1e3, 1, 0.0, -200.0, 1.0) for n in order[len(exts) + 1]]

    _every_refit_passes(monkeypatch, scores)
    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    d = diagnose_channel(pb, BaseFit(dict(TRUE), 1e4, "hg"), make_model,
                         candidates=["stray_light", "angle_offset", "beam_halo"], spp=64, repeats=2, iterations=2)
    assert rounds_screened == [1, 2]
    tried = [(e["round"], e["effect"]) for e in d.confirmations]
    # round 1: both refitted, the second (ranked higher) added though the first passed too
    assert tried == [(1, "stray_light"), (1, "angle_offset"), (2, "stray_light")]
    assert d.confirmed_order == ["angle_offset", "stray_light"]
    assert "not_refitted" not in d.rounds[0] and d.rounds[1]["not_refitted"] == ["beam_halo"]
    assert json.loads(json.dumps(d.as_dict()["rounds"]))[1]["not_refitted"] == ["beam_halo"]


@pytest.mark.parametrize("first_round", [True, False])
def test_a_later_round_confirms_only_a_candidate_that_also_gains_rendered_independently(monkeypatch, first_round):
    """lens_blur-2 on the light bench (session 75): a second round's halo passed on its paired
    gain (11.4) with 2.6 rendered independently, and its refit, worse than the blur's own,
    became the model. From round 2 (`INDEPENDENT_GAIN_ROUNDS_FROM`) the independent gain must
    pass the bar too, so the next flagged candidate is refitted and added; in round 1 the same
    gain still confirms (its candidates' refits are compared with each other there)."""
    import estimate.diagnose as dg
    from estimate.screening import CandidateScore

    monkeypatch.setattr(dg, "EXPLAINED_REDUCED_CHI2", 0.0)      # always look for a second effect
    order = ({1: ["stray_light"], 2: ["angle_offset", "beam_halo"]} if first_round
             else {1: ["angle_offset"], 2: ["stray_light", "beam_halo"]})
    _every_refit_passes(monkeypatch, lambda exts: [CandidateScore(n, 1e3, 1, 0.0, -200.0, 1.0)
                                                   for n in order[len(exts) + 1]],
                        rank={"stray_light": 2.6, "angle_offset": 80.0, "beam_halo": 500.0})
    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    d = diagnose_channel(pb, BaseFit(dict(TRUE), 1e4, "hg"), make_model,
                         candidates=["stray_light", "angle_offset", "beam_halo"], spp=64, repeats=2, iterations=2)
    tried = [(e["round"], e["effect"], e["confirmed"]) for e in d.confirmations]
    if first_round:
        assert tried == [(1, "stray_light", True), (2, "angle_offset", True)]
        assert d.confirmed_order == ["stray_light", "angle_offset"]
    else:
        assert tried == [(1, "angle_offset", True), (2, "stray_light", False), (2, "beam_halo", True)]
        assert d.confirmed_order == ["angle_offset", "beam_halo"]
        assert d.confirmations[1]["independent_gain_short"]


@pytest.mark.parametrize(("third", "refitted"), [(920.0, True), (880.0, False)])
def test_the_first_round_also_refits_a_third_candidate_that_screens_in_a_near_tie(monkeypatch, third, refitted):
    """Round 1 refits its two flagged candidates and, where the next flagged one's statistic
    is within `NEAR_TIE` of the second's, that one too, which can then be the one added (the
    screening cannot order near ties); below the share it is left to later rounds."""
    from estimate.screening import CandidateScore

    stats = {"stray_light": 2e3, "angle_offset": 1e3, "beam_halo": third}
    _every_refit_passes(monkeypatch, lambda exts: [CandidateScore(n, v, 1, 0.0, -200.0, 1.0)
                                                   for n, v in stats.items()])
    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    d = diagnose_channel(pb, BaseFit(dict(TRUE), 1e4, "hg"), make_model, candidates=list(stats), spp=64,
                         repeats=2, iterations=2, max_effects=1)
    tried = [e["effect"] for e in d.confirmations if e["round"] == 1]
    if refitted:
        assert tried == ["stray_light", "angle_offset", "beam_halo"]
        assert d.rounds[0]["near_tie"] == "beam_halo" and d.confirmed_order[:1] == ["beam_halo"]
    else:
        assert tried == ["stray_light", "angle_offset"] and "near_tie" not in d.rounds[0]
        assert d.confirmed_order[:1] == ["angle_offset"]


def test_near_tie_takes_only_the_flagged_candidate_right_after_a_full_leading_prefix():
    from estimate.diagnose import near_tie
    from estimate.screening import CandidateScore

    def c(n, stat, lp=-100.0):
        return CandidateScore(n, stat, 1, 0.0, lp, 1.0)

    a, b, t, u = c("a", 10.0), c("b", 5.0), c("t", 4.6), c("u", 4.59)
    assert near_tie([a, b, t, u], [a, b], -3.0) == [t]                  # one at most
    assert near_tie([a, b, c("t", 4.4)], [a, b], -3.0) == []            # 88 % of b's
    assert near_tie([a, b, c("t", 4.8, lp=-2.0)], [a, b], -3.0) == []   # not flagged
    assert near_tie([a, b], [a, b], -3.0) == [] and near_tie([a, b, t], [], -3.0) == []
    assert near_tie([a, b, t], [a, t], -3.0) == []                      # not the ranking's prefix


def test_a_diagnosis_with_decorrelated_refits_confirms_and_models_on_that_objective(monkeypatch):
    """`refit_objective=DECORRELATED`: the control, the candidate, its neutral point and the
    joint refit all minimise or evaluate the decorrelated chi^2 (two seeds), so the paired
    BIC gain compares losses of one kind; the concealed stray light is confirmed and its
    magnitude recovered, and the report names the refit for what it was."""
    import estimate.diagnose as dg

    seen: list[str] = []
    real = dg.refit

    def spy(*a, **kw):
        seen.append(kw.get("objective", "fixed-seed"))
        return real(*a, **kw)

    monkeypatch.setattr(dg, "refit", spy)
    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    d = diagnose_channel(pb, BaseFit(dict(TRUE), 1e4, "hg"), make_model, candidates=["stray_light"], spp=128,
                         repeats=3, iterations=6, refit_objective=DECORRELATED)
    assert seen and set(seen) == {DECORRELATED}
    assert d.confirmed == ["stray_light"] and d.model_stage == "refit" and not d.fixed_seed_after
    entry = next(e for e in d.confirmations if e["confirmed"])
    assert entry["chi2_refit_after"] < min(entry["chi2_refit_control"], entry["chi2_refit_neutral"])
    assert d.after.parameters["stray_light.offset"] == pytest.approx(0.01, rel=0.5)
    assert d.uncertainties_after["stray_light.offset"] > 0
    doc = d.as_dict()
    assert doc["refit_objective"] == DECORRELATED
    from estimate.diagnose import summary_text

    text = summary_text({"channels": {"g": doc}, "run_id": "x", "refit_run": None})
    assert "decorrelated refit's" in text and "Levenberg-Marquardt" not in text
    with pytest.raises(ModelParameterError, match="objective"):
        diagnose_channel(pb, BaseFit(dict(TRUE), 1e4, "hg"), make_model, refit_objective="median")


def test_a_second_diagnosis_from_the_same_base_fit_reuses_the_first_round(monkeypatch):
    """`second_pass_channel` starts again from the base fit: given the first diagnosis's
    `first_round`, the evaluation, the screening, the control and every candidate already
    refitted are taken, not rendered again, and give the same statistics; only the decision
    follows the new call's rules. Other settings (here the LM iterations) compute afresh."""
    import estimate.diagnose as dg

    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    base = BaseFit(dict(TRUE), 1e4, "hg")
    d1 = diagnose_channel(pb, base, make_model, candidates=["stray_light", "lens_blur"], spp=64, repeats=3,
                          iterations=6, final_fit_follows=True, max_effects=1)
    first = {e["effect"]: e for e in d1.confirmations}
    assert set(first) == set(d1.first_round.refits) and d1.first_round.control is not None
    assert "first_round" not in d1.as_dict()

    calls = {"refit": 0, "evaluate": 0, "screen": 0}

    def counting(name, fn):
        def wrapped(*a, **k):
            calls[name] += 1
            return fn(*a, **k)
        return wrapped

    monkeypatch.setattr(dg, "refit", counting("refit", dg.refit))
    monkeypatch.setattr(dg, "evaluate", counting("evaluate", dg.evaluate))
    monkeypatch.setattr(dg, "_screen", counting("screen", dg._screen))
    d2 = diagnose_channel(pb, base, make_model, candidates=list(first), spp=64, repeats=3, iterations=6,
                          final_fit_follows=True, max_effects=1, max_confirm=2, refit_checks_decide=False,
                          reuse=d1.first_round)
    assert d2.before is d1.before and calls["screen"] == 0
    for e in d2.confirmations:
        same = {k: v for k, v in e.items() if k not in ("confirmed", "time_s")}
        assert same == {k: v for k, v in first[e["effect"]].items() if k not in ("confirmed", "time_s")}
        # each entry's time says where it was spent: its refit taken, not done again
        assert e["time_s"]["reused"] and e["time_s"]["refit"] == 0.0
        assert not first[e["effect"]]["time_s"]["reused"] and first[e["effect"]]["time_s"]["refit"] > 0.0
    # the only renders left: the chosen effect's uncertainties and its evaluation on all angles
    assert calls["refit"] <= 1 and calls["evaluate"] == 1
    assert d2.stage_times_s["screening"] < 0.5 * d1.stage_times_s["screening"]
    # another LM budget is another first round: computed, not taken
    d3 = diagnose_channel(pb, base, make_model, candidates=["stray_light"], spp=64, repeats=3, iterations=5,
                          final_fit_follows=True, max_effects=1, reuse=d1.first_round)
    assert d3.before is not d1.before and calls["screen"] == 1


def test_the_wald_test_of_a_candidate_is_asked_only_where_it_decides(monkeypatch):
    """A candidate's Wald test costs its refit's uncertainties (a render and one or two
    Jacobians). Where the likelihood ratio already puts the magnitude beyond MAGNITUDE_SIGMA
    it cannot change the decision and is not asked; where the BIC gain passes and the
    likelihood ratio does not, it is, and decides."""
    import estimate.diagnose as dg

    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))

    def run():
        return diagnose_channel(pb, BaseFit(dict(TRUE), 1e4, "hg"), make_model, candidates=["stray_light"],
                                spp=128, repeats=3, iterations=8, final_fit_follows=True)

    d = run()
    e = d.confirmations[0]
    assert e["confirmed"] and e["magnitude_lr_sigma"] > dg.MAGNITUDE_SIGMA
    assert e["magnitude_wald_sigma"] is None and e["magnitude_sigma"] == e["magnitude_lr_sigma"]
    assert d.uncertainties_after["stray_light.offset"] > 0   # the last model still gets its intervals
    monkeypatch.setattr(dg, "_magnitude_lr_z", lambda *a, **k: 0.0)
    d2 = run()
    e2 = d2.confirmations[0]
    assert e2["magnitude_wald_sigma"] is not None and e2["magnitude_wald_sigma"] > dg.MAGNITUDE_SIGMA
    assert e2["magnitude_sigma"] == e2["magnitude_wald_sigma"] and e2["confirmed"]
    # the same refit, its uncertainties added once
    assert e2["chi2_refit_after"] == e["chi2_refit_after"]
    assert d2.uncertainties_after == d.uncertainties_after


def test_final_fit_settings_come_from_the_fit_run():
    recorded = {"fit": {**FitSettings(seed=7, scale="calibrated", max_iterations=3).to_dict(), "future_key": 1}}
    st = _run_fit_settings(recorded)
    assert (st.seed, st.scale, st.max_iterations) == (7, "calibrated", 3)
    assert isinstance(st.delta_range, tuple)
    # a run without them (an older run, a diagnosis refit): defaults, the run's scale and seed
    st = _run_fit_settings({"scale": "calibrated", "seed": 4})
    assert (st.seed, st.scale, st.max_iterations) == (4, "calibrated", FitSettings().max_iterations)
    assert _run_fit_settings({}).scale == "free"


@pytest.mark.parametrize("key, value", [("max_iterations", "80"), ("max_iterations", 0), ("gn_step", "big"),
                                        ("gn_step", float("nan")), ("decorrelated", "yes"), ("seed", 1.5),
                                        ("delta_range", [0.1]), ("delta_range", [1e-2, -1.0]),
                                        ("time_limit_s", -5), ("optimizer", 3), ("spp_max", True),
                                        ("polish_max_steps", -1), ("polish_max_steps", 2.5),
                                        ("polish_continue_p", 1.5)])
def test_hand_edited_fit_settings_are_refused_in_one_line_naming_the_key(key, value):
    recorded = {"fit": {**FitSettings().to_dict(), key: value}}
    with pytest.raises(ModelParameterError) as e:
        _run_fit_settings(recorded, "run/results.yaml")
    msg = str(e.value)
    assert "\n" not in msg and "run/results.yaml settings.fit" in msg and key in msg
    with pytest.raises(ModelParameterError, match="not a mapping"):
        _run_fit_settings({"fit": [1, 2]}, "run/results.yaml")
    with pytest.raises(ModelParameterError, match="settings.seed"):
        _run_fit_settings({"seed": "zero"}, "run/results.yaml")


def test_recorded_fit_settings_round_trip():
    st = FitSettings(seed=3, time_limit_s=60.0, lm_iterations=2, delta_range=(1e-3, 1e-1), decorrelated=False)
    assert FitSettings.from_dict(st.to_dict()) == st
    assert FitSettings.from_dict({"gn_step": 1, "time_limit_s": None}).gn_step == 1.0
    # 0 switches the Gauss-Newton matrix's smoothing off; a negative width is refused in one line.
    assert FitSettings.from_dict({"gn_smooth_px": 0}).gn_smooth_px == 0.0
    with pytest.raises(ModelParameterError, match="gn_smooth_px = -1 is not a number of pixels >= 0"):
        FitSettings.from_dict({"gn_smooth_px": -1})


def test_significance_counts_fitted_parameters_and_localise_finds_the_tails():
    rng = np.random.default_rng(1)
    r = rng.normal(size=(6, 40))
    assert not fit_significance(r, 4).significant
    model = np.exp(-np.linspace(-3, 3, 40) ** 2)[None, :].repeat(6, axis=0)
    r[:, :5] += 4.0
    loc = localise(r, ANGLES, np.linspace(-1, 1, 40), model)
    assert fit_significance(r, 4).significant
    assert "tails" in loc["dominant"] and "left" in loc["dominant"]


# ------------------------------------------------------------------------------ CLI
def _session(tmp: Path, name: str) -> Path:
    s = tmp / name
    s.mkdir()
    (s / "session.yaml").write_text("format: rig-session/1\n")
    return s


def test_cli_without_a_fit_says_run_estimate_first(tmp_path, capsys):
    s = _session(tmp_path, "a")
    assert main(["diagnose", str(s)]) == 2
    err = capsys.readouterr().err.strip()
    assert "rig estimate" in err and "--fit" in err and "\n" not in err


def test_cli_refuses_a_fit_from_another_session(tmp_path, capsys):
    a = _session(tmp_path, "a")
    b = _session(tmp_path, "b")
    run = b / "estimates" / "20260101T000000_exp3"
    run.mkdir(parents=True)
    (run / "results.yaml").write_text(yaml.safe_dump({
        "format": "rig-estimate/1", "run_id": run.name, "session": {"path": str(b.resolve())},
        "settings": {"model": "exp3"}, "channels": {}}))
    assert main(["diagnose", str(a), "--fit", str(run)]) == 2
    err = capsys.readouterr().err.strip()
    assert "another session" in err and "\n" not in err


def test_cli_says_the_manifest_changed_when_the_fit_was_made_from_this_folder(tmp_path, capsys):
    """The same folder with a different session.yaml (edited or damaged since the fit) is named
    as that, not as a fit from another session."""
    import hashlib

    s = _session(tmp_path, "a")
    run = s / "estimates" / "20260101T000000_exp3"
    run.mkdir(parents=True)
    sha = hashlib.sha256((s / "session.yaml").read_bytes()).hexdigest()
    (run / "results.yaml").write_text(yaml.safe_dump({
        "format": "rig-estimate/1", "run_id": run.name, "session": {"path": str(s.resolve()), "manifest_sha256": sha},
        "settings": {"model": "exp3"}, "channels": {}}))
    (s / "session.yaml").write_text("format: rig-session/1\n{{ damaged")
    assert main(["diagnose", str(s)]) == 2
    err = capsys.readouterr().err.strip()
    assert "session.yaml has changed since fit" in err and "another session" not in err and "\n" not in err, err


def test_cli_refuses_a_hand_edited_fit_setting_in_one_line(tmp_path, capsys):
    s = _session(tmp_path, "a")
    run = s / "estimates" / "20260101T000000_exp3"
    run.mkdir(parents=True)
    fit = {**FitSettings().to_dict(), "max_iterations": "eighty"}
    (run / "results.yaml").write_text(yaml.safe_dump({
        "format": "rig-estimate/1", "run_id": run.name, "session": {"path": str(s.resolve())},
        "settings": {"model": "exp3", "fit": fit}, "channels": {}}))
    before = (run / "results.yaml").read_bytes()
    assert main(["diagnose", str(s)]) == 2
    err = capsys.readouterr().err.strip()
    assert "max_iterations" in err and "results.yaml" in err and "\n" not in err and "Traceback" not in err
    assert (run / "results.yaml").read_bytes() == before
    assert sorted(p.name for p in (s / "estimates").iterdir()) == [run.name]


_GOOD_CHANNEL = {"model": "exp3", "parameters": {"sigma_t": 2.0, "albedo": 0.9, "phase.b1": 1.0, "phase.b2": 0.1,
                                                  "phase.b3": 0.1},
                 "uncertainties": {"sigma_t": 0.1, "albedo": float("nan")}, "scale": 1.0}


@pytest.mark.parametrize("edit, needle", [
    (lambda d: d.update(session="elsewhere"), "session is str"),
    (lambda d: d.update(channels=["g"]), "channels is list"),
    (lambda d: d.update(channels={}), "channels holds no fitted channel"),
    (lambda d: d["channels"].update(g="oops"), "channels.g is str"),
    (lambda d: d["channels"]["g"].update(parameters=[1, 2]), "channels.g.parameters is list"),
    (lambda d: d["channels"]["g"]["parameters"].update(sigma_t="abc"), "channels.g.parameters.sigma_t = 'abc'"),
    (lambda d: d["channels"]["g"]["parameters"].pop("phase.b3"), "channels.g.parameters has no phase.b3"),
    (lambda d: d["channels"]["g"].update(scale="big"), "channels.g.scale = 'big'"),
    (lambda d: d["channels"]["g"]["uncertainties"].update(albedo="x"), "channels.g.uncertainties.albedo = 'x'"),
    (lambda d: d["settings"].update(columns="wide"), "settings.columns = 'wide'"),
    (lambda d: d["settings"].update(extensions="stray_light"), "settings.extensions = 'stray_light'"),
    # the second channel's entry is checked before the first channel's diagnosis starts
    (lambda d: d["channels"].update(r={"model": "exp3"}), "channels.r.parameters is NoneType"),
])
def test_cli_refuses_a_hand_edited_fit_entry_in_one_line_before_any_work(tmp_path, capsys, monkeypatch, edit, needle):
    import estimate.problem

    monkeypatch.setattr(estimate.problem, "load_problem", lambda *a, **k: pytest.fail("diagnosis started"))
    s = _session(tmp_path, "a")
    run = s / "estimates" / "20260101T000000_exp3"
    run.mkdir(parents=True)
    doc = {"format": "rig-estimate/1", "run_id": run.name, "session": {"path": str(s.resolve())},
           "settings": {"model": "exp3", "columns": 32, "extensions": []}, "channels": {"g": copy.deepcopy(_GOOD_CHANNEL)}}
    edit(doc)
    (run / "results.yaml").write_text(yaml.safe_dump(doc))
    before = (run / "results.yaml").read_bytes()
    assert main(["diagnose", str(s), "--quick", "--no-plots", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and "results.yaml" in err and "\n" not in err and "Traceback" not in err, err
    assert (run / "results.yaml").read_bytes() == before and not (s / "diagnoses").exists()


def test_cli_refuses_an_unwritable_session_before_any_work(tmp_path, capsys):
    s = _session(tmp_path, "a")
    (s / "diagnoses").write_text("not a folder")
    assert main(["diagnose", str(s)]) == 2
    err = capsys.readouterr().err.strip()
    assert "diagnoses is a file" in err and "\n" not in err
    assert (s / "diagnoses").read_text() == "not a folder"


def test_cli_unknown_effect_and_unknown_run(tmp_path, capsys):
    s = _session(tmp_path, "a")
    assert main(["diagnose", str(s), "--effects", "stray_light,moonlight"]) == 2
    err = capsys.readouterr().err.strip()
    assert "unknown effect 'moonlight'; choose from " in err and "stray_light" in err and "\n" not in err
    assert main(["diagnose", str(s), "--fit", "nope"]) == 2
    assert "no estimate run" in capsys.readouterr().err
    assert main(["diagnose", str(s), "--refits", "median"]) == 2
    assert "--refits" in capsys.readouterr().err
    assert main(["diagnose", str(s), "--spp", "8"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--spp 8" in err and "at least 16" in err and "\n" not in err
    # A list that names nothing is not read as "all"; a name given twice is not screened twice.
    for flag, value, said in [("--effects", ",", "names nothing"), ("--channels", " , ", "names nothing"),
                              ("--effects", "lens_blur,lens_blur", "effect 'lens_blur' is named twice"),
                              ("--channels", "gg", "channel 'g' is named twice"), ("--channels", "", "names nothing")]:
        assert main(["diagnose", str(s), flag, value]) == 2
        err = capsys.readouterr().err.strip()
        assert f"{flag} {value!r}: {said}" in err and "\n" not in err


def test_the_diagnosis_spp_follows_the_renderer(monkeypatch):
    """`rig diagnose` renders at 2048 spp on a GPU (the suite's reference on the 256-px
    window, minutes there) and 256 on the CPU; without a variant it asks the one
    `init_mitsuba` would pick. With the light engine 2048 on both (its fixed-seed refits
    fit their own correlated render noise at 256; minutes a channel on the CPU)."""
    import estimate.mitsuba_env as env
    from estimate.diagnose import (
        CPU_DIAGNOSE_SPP,
        GPU_DIAGNOSE_SPP,
        LIGHT_DIAGNOSE_SPP,
        default_diagnose_spp,
    )

    assert (CPU_DIAGNOSE_SPP, GPU_DIAGNOSE_SPP, LIGHT_DIAGNOSE_SPP) == (256, 2048, 2048)
    assert default_diagnose_spp("llvm_ad_mono", engine="light") == LIGHT_DIAGNOSE_SPP
    assert default_diagnose_spp("cuda_ad_mono", engine="light") == LIGHT_DIAGNOSE_SPP
    assert default_diagnose_spp("cuda_ad_mono") == GPU_DIAGNOSE_SPP
    assert default_diagnose_spp("llvm_ad_mono") == CPU_DIAGNOSE_SPP
    monkeypatch.setattr(env, "default_variant", lambda: "cuda_ad_mono")
    assert default_diagnose_spp() == GPU_DIAGNOSE_SPP
    monkeypatch.setattr(env, "default_variant", lambda: "llvm_ad_mono")
    assert default_diagnose_spp() == CPU_DIAGNOSE_SPP


def test_cli_end_to_end_writes_diagnosis_and_json(tmp_path, capsys):
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from synth_session import make_session

    truth = {"sigma_t": 3.0, "albedo": 0.85, "phase.b1": 3.0}
    s = make_session(tmp_path / "s", {"g": truth}, angles=[30, 60, 120, 150], spp=256, width=48, scale=2e5)
    assert main(["estimate", str(s), "--channels", "g", "--columns", "24", "--max-iterations", "3",
                 "--spp-max", "64"]) == 0
    capsys.readouterr()
    assert main(["diagnose", str(s), "--effects", "stray_light", "--spp", "32", "--no-plots", "--json"]) == 0
    doc = __import__("json").loads(capsys.readouterr().out)
    # Without --engine the diagnosis renders with the fit's own engine (rig estimate's default).
    fit_engine = yaml.safe_load((Path(doc["fit_run"]) / "results.yaml").read_text())["settings"]["fit"]["engine"]
    assert doc["settings"]["engine"] == fit_engine == "light"
    ch = doc["channels"]["g"]
    assert set(ch) >= {"significant", "localisation", "candidates", "confirmed_effects", "reduced_chi2_before",
                       "reduced_chi2_after", "material_before", "material_after"}
    assert [c["name"] for c in ch["candidates"]] in ([], ["stray_light"])
    # The synthetic session has no bracket records: the compression would take its full-well form.
    assert ch["sensor_compression_form"] == "full_well"
    # ... nor a beam calibration bracket: its own compression could not be taken out
    assert ch["sensor_calibration"] == "as read"
    written = yaml.safe_load((s / "diagnoses" / doc["run_id"] / "diagnosis.yaml").read_text())
    assert written["format"] == "rig-diagnosis/1" and written["channels"]["g"]["significant"] == ch["significant"]
    # The summary `rig diagnose` prints says where the file is from anywhere, not from the session.
    said = next(line for line in doc["summary"].splitlines() if line.startswith("diagnosis written to "))
    assert Path(said.removeprefix("diagnosis written to ")).resolve() == (s / "diagnoses" / doc["run_id"]
                                                                         / "diagnosis.yaml").resolve()
    if doc["refit_run"]:   # a confirmed effect: the refit run carries its covariance into the derived values
        refit = yaml.safe_load((Path(doc["refit_run"]) / "results.yaml").read_text())["channels"]["g"]
        assert refit["derived"]["sigma_a"]["uncertainty"] is not None
        assert set(refit["covariance"]) == set(refit["uncertainties"])


def test_beam_rms_width_and_the_halo_width_bound():
    """A Gaussian of 1/e^2 radius R has 1-sigma R/2, a disk of radius R has R/2 per axis; a
    refit may not shrink a halo below the calibrated beam's width (it would be part of the map)."""
    from estimate.refit import parameter_bounds

    assert BeamProfile.gaussian(0.4).rms_width_mm() == pytest.approx(0.2, rel=1e-3)
    assert BeamProfile.disk(0.3).rms_width_mm() == pytest.approx(0.15, rel=0.02)
    beam = BeamProfile.gaussian(0.5)
    fm = ForwardModel(RigGeometry(thickness_mm=1.0), beam, phase="hg", extensions=("beam_halo",))
    lo, hi = parameter_bounds(fm, "beam_halo.sigma_mm")
    assert lo == pytest.approx(0.25, rel=1e-3) and hi == 50.0


@pytest.mark.parametrize("concealed, earlier, expect_dropped", [
    # The blur passed round 1 by borrowing the stray light's signature and sits at absent in
    # the joint refit: dropped.
    ({"stray_light.offset": 0.003}, {"lens_blur.core_sigma_px": 0.04, "lens_blur.tail_fraction": 0.0}, True),
    # A real blur, joined later by stray light: putting the blur back to absent costs far more
    # than adding it had to gain, so it stays.
    ({"stray_light.offset": 0.003, "lens_blur.core_sigma_px": 2.5, "lens_blur.tail_fraction": 0.05},
     {"lens_blur.core_sigma_px": 2.5, "lens_blur.tail_fraction": 0.05}, False),
])
def test_backward_check_drops_an_earlier_effect_that_the_later_one_explains(concealed, earlier, expect_dropped):
    from estimate.diagnose import _free_names, _prune, refit

    rec = record(concealed, seed=17)
    exts = ["lens_blur", "stray_light"]
    m = make_model(exts)
    params = m.validate({**TRUE, "stray_light.offset": 0.003, **earlier})
    floor = np.ones(len(ANGLES))
    mv = np.full(rec.measured.shape, 1e-12)
    spp, seed = 128, 40
    # The joint refit as the forward rounds leave it, at the seed and spp _prune pairs with.
    full = refit(m, rec, params, _free_names(m, exts), spp=2 * spp, seed=seed + 303, iterations=0,
                 model_variance=mv, noise_scale=floor, uncertainties=False)
    out, rises = _prune(rec, make_model, ["lens_blur", "stray_light"], exts, full, spp=spp, seed=seed,
                        model_variance=mv, floor=floor, n_obs=rec.measured.size)
    assert [e["effect"] for e in out] == ["lens_blur"]  # the last effect was tested against the others already
    assert set(rises) == set(exts) and rises["lens_blur"] == out[0]["chi2_rise"]
    assert rises["stray_light"] > 10 * out[0]["needed"]  # the stray light is real in both cases
    e = out[0]
    assert e["with"] == ["stray_light"]
    assert e["dropped"] is expect_dropped, e
    assert "magnitude_sigma" not in e  # a refit without uncertainties: the rise alone
    if expect_dropped:
        assert abs(e["chi2_rise"]) < e["needed"]
    else:
        assert e["chi2_rise"] > 10 * e["needed"]
        # With the joint refit's intervals the magnitude must also stand clear of absent:
        # the same rise, kept with tight intervals, dropped with intervals that reach absent.
        names = _free_names(m, exts)
        for rel_sd, dropped in ((0.05, False), (20.0, True)):
            unc = {n: rel_sd * max(1.0, abs(full.parameters[n])) for n in names}
            cov = {(a, b): unc[a] ** 2 if a == b else 0.0 for a in names for b in names}
            joint = dataclasses.replace(full, uncertainties=unc, covariance=cov)
            (e2,), _ = _prune(rec, make_model, ["lens_blur", "stray_light"], exts, joint, spp=spp, seed=seed,
                              model_variance=mv, floor=floor, n_obs=rec.measured.size)
            assert e2["chi2_rise"] == e["chi2_rise"] and e2["magnitude_needed"] == 1.0
            assert e2["dropped"] is dropped and (e2["magnitude_sigma"] < 1.0) is dropped, e2
    # The same check at the estimator's final fit, in the base fit's noise metric.
    from estimate.diagnose import _prune_final, evaluate

    before = evaluate(make_model([]), TRUE, rec, 3, spp=spp, seed=seed, repeats=3)
    fin, fin_rises = _prune_final(rec, m, params, ["lens_blur", "stray_light"], before, spp=spp, seed=seed,
                                  repeats=3)
    assert [(e["effect"], e["stage"], e["dropped"]) for e in fin] == [("lens_blur", "final fit", expect_dropped)], fin
    assert fin_rises["stray_light"] > fin_rises["lens_blur"] == fin[0]["chi2_rise"]


def _fake_final_fit(monkeypatch, base: float, absent: dict[str, tuple[str, float, float]]) -> None:
    """Stands in for the renders of `_prune_final`: chi^2 `base` at the fit, and base + rise with
    effect e put back to absent (absent[e] = (its magnitude parameter, neutral value, rise))."""
    import estimate.diagnose as dg

    class Ev:
        def __init__(self, chi2: float) -> None:
            self.residuals = SimpleNamespace(chi2_adjusted=chi2, r=np.zeros(2000))

    def fake_evaluate(model, params, problem, n_params, **kw):
        for name, neutral, rise in absent.values():
            if params.get(name) == neutral:
                return Ev(base + rise)
        return Ev(base)

    monkeypatch.setattr(dg, "evaluate", fake_evaluate)
    monkeypatch.setattr(dg, "_yardstick", lambda problem, before: None)
    monkeypatch.setattr(dg, "_neutral_magnitudes", lambda model, p, e: {**p, absent[e][0]: absent[e][1]})


@pytest.mark.parametrize("rise_over_price, dropped", [(-0.5, True), (0.5, False), (1.2, False)])
def test_a_named_effect_stays_while_it_pays_its_bic_price(monkeypatch, rise_over_price, dropped):
    """Stepwise hysteresis: entering needs k ln n + BIC_STRONG, staying only k ln n. A rise
    between the two (the bench pair's blur in the final fit: 19.9 against 15.2 and 25.2) keeps
    the effect named; one below its price drops it."""
    import estimate.diagnose as dg
    from estimate.diagnose import BIC_STRONG, _bic_bar, _bic_exit_bar

    n_obs = 2000
    price = _bic_exit_bar("lens_blur", n_obs)
    assert price == pytest.approx(_bic_penalty("lens_blur", n_obs))
    assert _bic_bar("lens_blur", n_obs) == pytest.approx(price + BIC_STRONG)
    rise = price + rise_over_price * BIC_STRONG
    _fake_final_fit(monkeypatch, 2000.0, {"stray_light": ("stray_light.offset", 0.0, 5000.0),
                                          "lens_blur": ("lens_blur.core_sigma_px", 0.0, rise)})
    params = {"stray_light.offset": 0.003, "lens_blur.core_sigma_px": 1.0}
    out, rises = dg._prune_final(None, None, params, ["stray_light", "lens_blur"], None, spp=1, seed=0, repeats=1)
    assert rises == {"stray_light": pytest.approx(5000.0), "lens_blur": pytest.approx(rise)}
    assert [(e["effect"], e["dropped"]) for e in out] == [("lens_blur", dropped)]
    # the joint model fits (chi^2 2000 on 2000 pixels): no dispersion to correct for
    assert out[0]["dispersion"] == pytest.approx(1.0, abs=0.01)
    assert out[0]["needed"] == pytest.approx(price, rel=0.01)


def test_the_backward_check_names_the_model_it_was_made_in(monkeypatch):
    """`_name_after_check`, the backward check that the final fit (or, when the final fit is
    not kept after a deferred model stage, the last candidate's refit) makes: it drops what
    no longer pays, ranks the rest by the chi^2 each carries, and says in which model."""
    import estimate.diagnose as dg

    _fake_final_fit(monkeypatch, 2000.0, {"stray_light": ("stray_light.offset", 0.0, 5000.0),
                                          "lens_blur": ("lens_blur.core_sigma_px", 0.0, 8000.0),
                                          "beam_halo": ("beam_halo.fraction", 0.0, 1.0)})
    params = {"stray_light.offset": 0.003, "lens_blur.core_sigma_px": 1.0, "beam_halo.fraction": 0.01}
    d = SimpleNamespace(confirmed=["stray_light", "beam_halo", "lens_blur"], before=None, pruned=[{"stage": "x"}],
                        importance={})
    lines: list[str] = []
    dg._name_after_check(None, d, None, params, "refit", spp=1, seed=0, repeats=1, renders=None, uncertainties={},
                         covariance={}, say=lines.append)
    assert d.confirmed == ["lens_blur", "stray_light"]          # by the chi^2 each carries
    assert [(e["effect"], e["stage"], e["dropped"]) for e in d.pruned[1:]] == [
        ("stray_light", "refit", False), ("beam_halo", "refit", True)]
    assert d.importance["lens_blur"] == {"chi2_rise": pytest.approx(8000.0), "stage": "refit"}
    assert any("beam_halo in the refit: setting it to absent" in ln and "dropped" in ln for ln in lines)


def _stage_confirmation(lines: list[str]):
    """A `_Confirmation` whose renders are not wanted: `model_stage` only calls its own
    `finish`, `settle` and `evaluate_all` and the module's `_prune`, which the test replaces."""
    import estimate.diagnose as dg
    from estimate.refit import FIXED_SEED

    return dg._Confirmation(problem=None, make_model=lambda exts: None, cands=[], spp=64, seed=5, repeats=1,
                            iterations=2, refit_objective=FIXED_SEED, refit_checks_decide=False,
                            refit_below_log10_p=-3.0, max_confirm=3, grid_start=None, floor=np.ones(3),
                            yardstick=np.ones(3), train=[0, 1], held=[2], brightest=1.0, first_round=None,
                            say=lines.append)


@pytest.mark.parametrize("drop", [["beam_halo"], []])
def test_the_rounds_backward_check_refits_without_what_it_drops_and_reports_the_refit_after_it(monkeypatch, drop):
    """The model stage after two or more confirmed effects (`_Confirmation.model_stage`): the
    joint refit gets its intervals (`finish`) before the backward check (`_prune`) so the
    Wald test can act; what the check drops leaves the model and the rest is refitted
    (`settle`, from the joint refit's parameters and render variance); the effects left are
    named by the chi^2 each carries; the reported intervals are those of the last model,
    evaluated at its decorrelated step, with the fixed-seed optimum kept beside them."""
    import estimate.diagnose as dg
    from estimate.refit import RefitResult

    lines: list[str] = []
    conf = _stage_confirmation(lines)
    three = ["lens_blur", "beam_halo", "stray_light"]
    p3 = {"sigma_t": 2.1, "lens_blur.core_sigma_px": 1.5, "beam_halo.fraction": 0.001, "stray_light.offset": 0.003}
    mv = np.full((3, 8), 1e-6)
    joint = RefitResult(dict(p3), 1.0, {}, 900.0, 4)
    calls: list[tuple] = []

    def with_intervals(exts, fit):
        names = [n for n in fit.parameters if n.split(".")[0] in exts or "." not in n]
        unc = {n: 0.01 * (1 + i) for i, n in enumerate(names)}
        cov = {(a, b): unc[a] ** 2 if a == b else 0.0 for a in names for b in names}
        return dataclasses.replace(fit, uncertainties=unc, covariance=cov,
                                   decorrelated={**fit.parameters, "sigma_t": fit.parameters["sigma_t"] - 0.05})

    def finish(exts, fit, variance):
        calls.append(("finish", list(exts), variance is mv))
        return with_intervals(exts, fit)

    p2 = {k: v for k, v in p3.items() if not k.startswith("beam_halo")}
    settled = RefitResult({**p2, "sigma_t": 2.05}, 1.0, {}, 905.0, 3)

    def settle(exts, start, variance, confirmed):
        calls.append(("settle", list(exts), start == p3 and variance is mv, list(confirmed)))
        return settled, SimpleNamespace(name="settled")

    def evaluate_all(exts, parameters):
        calls.append(("evaluate_all", list(exts), dict(parameters)))
        return SimpleNamespace(name="decorrelated", residuals=SimpleNamespace(reduced_chi2=1.02))

    rises = {"lens_blur": 300.0, "beam_halo": 2.0, "stray_light": 5000.0}

    def prune(problem, make_model, confirmed, exts, full, **kw):
        calls.append(("prune", list(confirmed), bool(full.uncertainties), kw["n_obs"], kw["seed"], kw["spp"]))
        entries = [{"effect": e, "chi2_rise": rises[e], "needed": 20.0, "dropped": e in drop} for e in confirmed[:-1]]
        return entries, dict(rises)

    monkeypatch.setattr(dg, "_prune", prune)
    monkeypatch.setattr(conf, "finish", finish)
    monkeypatch.setattr(conf, "settle", settle)
    monkeypatch.setattr(conf, "evaluate_all", evaluate_all)
    current = SimpleNamespace(name="round", residuals=SimpleNamespace(r=np.r_[np.zeros(40), np.full(5, np.nan)]))
    st = conf.model_stage(list(three), list(three), current, (joint, mv), None)

    kept = [e for e in three if e not in drop]
    # intervals first (the Wald test), then the check, on every finite pixel, at the round's seed and spp
    assert calls[0] == ("finish", three, True)
    assert calls[1] == ("prune", three, True, 40, 5, 64)
    assert [e["effect"] for e in st.pruned] == ["lens_blur", "beam_halo"]
    assert st.exts == kept
    assert st.confirmed == sorted(kept, key=lambda e: -rises[e])            # stray light carries the most
    assert st.importance == {e: {"chi2_rise": rises[e], "stage": "refit"} for e in kept}
    if drop:
        # refitted without the halo, from the joint refit; that refit gets its own intervals
        assert calls[2] == ("settle", kept, True, kept)
        assert calls[3] == ("finish", kept, True)
        last = with_intervals(kept, settled)
        assert any("beam_halo with the others in the model" in ln and ln.endswith("-> dropped") for ln in lines)
    else:
        assert [c[0] for c in calls].count("finish") == 1                   # the check's intervals serve
        last = with_intervals(three, joint)
        assert all(not ln.endswith("-> dropped") for ln in lines)
    assert calls[-1] == ("evaluate_all", kept, last.decorrelated)
    assert st.current.name == "decorrelated"
    assert st.fixed_seed == last.parameters and st.uncertainties == last.uncertainties
    assert st.covariance == {a: {b: last.covariance[(a, b)] for b in last.uncertainties} for a in last.uncertainties}
    assert "beam_halo.fraction" not in st.uncertainties or not drop


def test_a_deferred_model_stage_keeps_the_candidates_intervals_and_checks_nothing(monkeypatch):
    """With the estimator's final fit to follow (`deferred`: the candidate's refit it replaces),
    the backward check waits for the final fit (`_prune_final`): no joint check here, and the
    intervals reported until then are the deferred refit's."""
    import estimate.diagnose as dg
    from estimate.refit import RefitResult

    conf = _stage_confirmation([])
    monkeypatch.setattr(dg, "_prune", lambda *a, **k: pytest.fail("no backward check before the final fit"))
    monkeypatch.setattr(conf, "finish", lambda *a: pytest.fail("no intervals for a joint refit that was not made"))
    unc = {"sigma_t": 0.02, "stray_light.offset": 1e-4}
    deferred = RefitResult({"sigma_t": 2.0, "stray_light.offset": 0.003}, 1.0, unc, 800.0, 5,
                           covariance={(a, b): unc[a] * unc[b] * (1.0 if a == b else 0.3) for a in unc for b in unc})
    current = SimpleNamespace(residuals=SimpleNamespace(r=np.zeros(10)))
    st = conf.model_stage(["lens_blur", "stray_light"], ["lens_blur", "stray_light"], current, None, deferred)
    assert st.pruned == [] and st.importance == {} and st.fixed_seed == {}
    assert st.current is current and st.confirmed == ["lens_blur", "stray_light"]
    assert st.uncertainties == unc
    assert st.covariance["sigma_t"]["stray_light.offset"] == pytest.approx(0.3 * 0.02 * 1e-4)


@pytest.mark.parametrize("tail_sd, lm_chi2, named", [(0.02, 1.0, True), (2.3, 1.0, False), (0.02, 13.1, False)])
def test_a_lone_effect_is_checked_in_the_refit_that_stands_in_for_a_final_fit_not_kept(monkeypatch, tail_sd,
                                                                                        lm_chi2, named):
    """When the estimator's final fit ends worse than the base fit, the Levenberg-Marquardt
    refit stays the model; a lone effect there must pass the same magnitude check as in a
    kept final fit (`_prune_final` at stage "refit"), by that refit's own intervals. And
    where that refit fits the whole recording worse than the base fit too (reduced chi^2 at
    the floor 11.8 -> 13.1, a significant mismatch left), its effect explains none of the
    mismatch and is not named, whatever its magnitude (session 51)."""
    import estimate.diagnose as dg
    from estimate.diagnose import ChannelDiagnosis, refine_channel

    _fake_final_fit(monkeypatch, 2000.0, {"lens_blur": ("lens_blur.tail_fraction", 0.0, 4000.0)})
    fake_evaluate = dg.evaluate

    def evaluate(model, params, problem, n_params, **kw):   # the final fit (sigma_t 9) fits worse
        ev = fake_evaluate(model, params, problem, n_params, **kw)
        ev.residuals.reduced_chi2_adjusted = 50.0 if params.get("sigma_t") == 9.0 else 1.0
        return ev

    monkeypatch.setattr(dg, "evaluate", evaluate)
    monkeypatch.setattr(dg, "render_stack", lambda *a, **k: None)
    monkeypatch.setattr(dg, "fit_channel", lambda *a, **k: SimpleNamespace(
        parameters={"sigma_t": 9.0}, iterations=3, stop_reason="cap", drifting=[], loss=1.0, reduced_chi2=50.0,
        free=["sigma_t"]))
    params = {"sigma_t": 2.0, "lens_blur.core_sigma_px": 1.0, "lens_blur.tail_fraction": 0.19}
    # the bench boundary session's tail: 19 +- 230 %, core 0 +- 59 px (here 1 +- 59)
    unc = {"sigma_t": 0.05, "lens_blur.core_sigma_px": 0.1 if tail_sd < 1 else 59.0, "lens_blur.tail_fraction": tail_sd}
    res = SimpleNamespace(noise_scale=np.array([1.0]), significant=True, extra={}, p_value_smooth=1e-9,
                          reduced_chi2_adjusted=11.8, reduced_chi2=11.8, dof=100)
    before = SimpleNamespace(residuals=res, parameters={"sigma_t": 3.0})
    lm = SimpleNamespace(extensions=["lens_blur"], parameters=params,
                         residuals=SimpleNamespace(reduced_chi2_adjusted=lm_chi2, significant=lm_chi2 > 1.2))
    d = ChannelDiagnosis("g", before, {"summary": "in the tails"}, [], [], ["lens_blur"], lm, dict(unc), "", 1.0,
                         ["sigma_t"], covariance_after={a: {b: (unc[a] ** 2 if a == b else 0.0) for b in unc}
                                                        for a in unc}, model_stage="refit")
    model = SimpleNamespace(parameter_names=list(params), phase="hg")
    assert refine_channel(None, d, lambda exts: model, FitSettings(scale="free")) is None
    assert not d.final_fit["kept"] and d.after is lm
    (check,) = d.pruned
    assert check["stage"] == "refit" and check["leading"] and check["dropped"] is (tail_sd > 1)
    assert d.confirmed == (["lens_blur"] if named else [])
    assert ("left-out physics: lens_blur" in d.verdict) is named
    assert ("no cause is named" in d.verdict) is (not named)
    worse = lm_chi2 > 11.8
    assert bool(d.partial) is worse
    assert ("fits the whole recording no better than the model without" in d.verdict) is worse


def test_a_final_fit_whose_effect_explains_too_little_names_nothing_and_asks_for_the_second_pass(monkeypatch):
    """The estimator's final fit is kept (reduced chi^2 at the floor 11.8 -> 10.5) and its
    angle offset lies far from absent, but it removes 12 % of the excess and a significant
    mismatch remains (the two-lobe phase session: 14 %): not named, and the second pass is
    asked to refit the other candidates (`stand_in_effects`)."""
    import estimate.diagnose as dg
    from estimate.diagnose import (
        MIN_SHARE,
        ChannelDiagnosis,
        refine_channel,
        stand_in_effects,
    )

    _fake_final_fit(monkeypatch, 2000.0, {"angle_offset": ("angle_offset.delta_deg", 0.0, 4000.0)})
    fake_evaluate = dg.evaluate

    def evaluate(model, params, problem, n_params, **kw):
        ev = fake_evaluate(model, params, problem, n_params, **kw)
        ev.residuals.reduced_chi2_adjusted = 10.5
        ev.residuals.reduced_chi2 = 15.0
        ev.residuals.significant = True
        ev.parameters = dict(params)
        return ev

    monkeypatch.setattr(dg, "evaluate", evaluate)
    monkeypatch.setattr(dg, "render_stack", lambda *a, **k: None)
    unc = {"sigma_t": 0.05, "angle_offset.delta_deg": 0.1}
    monkeypatch.setattr(dg, "fit_channel", lambda *a, **k: SimpleNamespace(
        parameters={"sigma_t": 3.8, "albedo": 0.8, "angle_offset.delta_deg": 1.2}, iterations=3, stop_reason="converged",
        drifting=[], loss=1.0, reduced_chi2=15.0, free=["sigma_t", "angle_offset.delta_deg"], uncertainties=unc,
        covariance={a: {b: (unc[a] ** 2 if a == b else 0.0) for b in unc} for a in unc}))
    res = SimpleNamespace(noise_scale=np.array([1.0]), significant=True, extra={}, p_value_smooth=1e-9,
                          reduced_chi2_adjusted=11.8, reduced_chi2=17.0, dof=100)
    before = SimpleNamespace(residuals=res, parameters={"sigma_t": 3.0})
    params = {"sigma_t": 3.3, "angle_offset.delta_deg": 1.1}
    lm = SimpleNamespace(extensions=["angle_offset"], parameters=params,
                         residuals=SimpleNamespace(reduced_chi2_adjusted=9.3, significant=True))
    d = ChannelDiagnosis("g", before, {"summary": "in the peak"}, [], [], ["angle_offset"], lm, dict(unc), "", 1.0,
                         ["sigma_t"], model_stage="deferred")
    model = SimpleNamespace(parameter_names=list(params), phase="hg")
    assert refine_channel(None, d, lambda exts: model, FitSettings(scale="free")) is not None
    assert d.final_fit["kept"] and not any(e["dropped"] for e in d.pruned)
    assert d.confirmed == [] and d.partial["stage"] == "final fit" and d.partial["min_share"] == MIN_SHARE
    assert d.partial["share_explained"] == pytest.approx(1.3 / 10.8)
    assert "in the estimator's final fit the reduced chi2 at the noise floor falls only 11.80 -> 10.50" in d.verdict
    assert "no cause is named" in d.verdict
    assert stand_in_effects(d) == ["angle_offset"]


@pytest.mark.parametrize("joint_chi2_per_pixel, dropped", [(1.0, False), (4.16, True)])
def test_the_bar_to_stay_scales_with_the_dispersion_the_joint_model_leaves(monkeypatch, joint_chi2_per_pixel,
                                                                             dropped):
    """A rise of 50 (the bench boundary session's glare tail in session 30's final fit) against
    a price k ln n = 15.2: where the joint model leaves chi^2 4.16 per pixel in the yardstick's
    metric (noise the yardstick does not hold), that is 50 / 4.16 = 12 < 15.2 in likelihood
    units and the effect is not named; where the joint model fits, the same rise keeps it."""
    import estimate.diagnose as dg
    from estimate.diagnose import _bic_exit_bar

    n_obs = 2000
    base = joint_chi2_per_pixel * n_obs
    _fake_final_fit(monkeypatch, base, {"refractive_boundary": ("refractive_boundary.n", 1.0, 11000.0),
                                        "lens_blur": ("lens_blur.tail_fraction", 0.0, 50.0)})
    params = {"refractive_boundary.n": 1.333, "lens_blur.tail_fraction": 0.0044}
    out, _ = dg._prune_final(None, None, params, ["lens_blur", "refractive_boundary"], None, spp=1, seed=0,
                             repeats=1)
    (e,) = out
    assert e["effect"] == "lens_blur" and e["dropped"] is dropped, e
    assert e["dispersion"] == pytest.approx(max(1.0, base / (n_obs - 3)))
    assert e["needed"] == pytest.approx(_bic_exit_bar("lens_blur", n_obs) * e["dispersion"])
    assert e["price"] == pytest.approx(_bic_exit_bar("lens_blur", n_obs))
    from estimate.diagnosis_report import _exit_bar_text

    text = _exit_bar_text(e)
    assert ("x 4.17 (the reduced chi2" in text) is dropped and f"{e['needed']:.1f}" in text


@pytest.mark.parametrize("tail, tail_sd, dropped", [(0.0063, 0.027, True), (0.02, 0.004, False)])
def test_an_effect_the_final_fit_leaves_within_its_noise_of_absent_is_not_named(monkeypatch, tail, tail_sd,
                                                                                dropped):
    """The bench's refractive-boundary session: a glare tail confirmed before the boundary
    ended at 0.63 +- 2.7 % in the estimator's final fit (core 0 +- 2.9 px), yet setting it to
    absent alone (every other parameter held) raised chi^2 by 55, above its bar of 38. Its
    magnitude, 0.2 sigma from absent by the fit's own intervals, drops it; a tail 5 sigma
    out with the same rise stays."""
    import estimate.diagnose as dg
    from estimate.diagnose import MAGNITUDE_SIGMA

    _fake_final_fit(monkeypatch, 2000.0, {"refractive_boundary": ("refractive_boundary.n", 1.0, 11000.0),
                                          "lens_blur": ("lens_blur.tail_fraction", 0.0, 55.0)})
    params = {"sigma_t": 2.0, "refractive_boundary.n": 1.332, "lens_blur.core_sigma_px": 0.0,
              "lens_blur.tail_fraction": tail}
    unc = {"sigma_t": 0.05, "refractive_boundary.n": 0.0066, "lens_blur.core_sigma_px": 2.9,
           "lens_blur.tail_fraction": tail_sd}
    cov = {a: {b: (unc[a] ** 2 if a == b else 0.0) for b in unc} for a in unc}
    cov["lens_blur.core_sigma_px"]["lens_blur.tail_fraction"] = cov["lens_blur.tail_fraction"][
        "lens_blur.core_sigma_px"] = -0.3 * 2.9 * tail_sd
    without, _ = dg._prune_final(None, None, params, ["lens_blur", "refractive_boundary"], None, spp=1, seed=0,
                                 repeats=1)
    assert not without[0]["dropped"] and "magnitude_sigma" not in without[0]  # the rise alone keeps it
    e, lead = dg._prune_final(None, None, params, ["lens_blur", "refractive_boundary"], None, spp=1, seed=0,
                              repeats=1, uncertainties=unc, covariance=cov)[0]
    assert e["effect"] == "lens_blur" and e["chi2_rise"] > e["needed"]
    assert e["dropped"] is dropped and (e["magnitude_sigma"] <= MAGNITUDE_SIGMA) is dropped, e
    # the boundary carries the most and is 50 sigma from absent (n 1.332 +- 0.0066)
    assert lead["effect"] == "refractive_boundary" and lead["leading"] and not lead["dropped"]
    assert lead["magnitude_sigma"] == pytest.approx(0.332 / 0.0066)


@pytest.mark.parametrize("tail, tail_sd, dropped", [(0.19, 2.3, True), (0.02, 0.004, False)])
def test_a_lone_effect_whose_magnitude_the_final_fit_cannot_tell_from_absent_is_not_named(monkeypatch, tail,
                                                                                         tail_sd, dropped):
    """Session 35's recapture of the bench's refractive-boundary session: with the base fit
    74 % high in sigma_t the boundary screened fifth, and a glare tail alone was confirmed by
    the refits; the estimator's fit left it at 19 +- 230 % (core 0 +- 59 px) while setting it
    to absent raised chi^2 by 4000. A lone (or leading) effect must lie more than
    MAGNITUDE_SIGMA from absent too; its rise does not decide. The summary says why nothing
    is named (`test_named_effects_are_ranked_by_the_chi2_each_carries_in_the_final_model`), and
    the verdict says so without calling it unconfirmed."""
    import estimate.diagnose as dg
    from estimate.diagnose import _verdict

    _fake_final_fit(monkeypatch, 2000.0, {"lens_blur": ("lens_blur.tail_fraction", 0.0, 4000.0)})
    params = {"sigma_t": 2.8, "lens_blur.core_sigma_px": 0.0, "lens_blur.tail_fraction": tail}
    unc = {"sigma_t": 0.05, "lens_blur.core_sigma_px": 59.0, "lens_blur.tail_fraction": tail_sd}
    cov = {a: {b: (unc[a] ** 2 if a == b else 0.0) for b in unc} for a in unc}
    (e,), _ = dg._prune_final(None, None, params, ["lens_blur"], None, spp=1, seed=0, repeats=1,
                              uncertainties=unc, covariance=cov)
    assert e["leading"] and e["with"] == [] and e["chi2_rise"] == pytest.approx(4000.0)
    assert e["dropped"] is dropped and (e["magnitude_sigma"] <= dg.MAGNITUDE_SIGMA) is dropped
    # without the fit's intervals there is nothing to ask of a lone effect
    assert dg._prune_final(None, None, params, ["lens_blur"], None, spp=1, seed=0, repeats=1)[0] == []
    before = SimpleNamespace(residuals=SimpleNamespace(
        noise_scale=np.array([1.0]), significant=True, extra={}, p_value_smooth=1e-9, reduced_chi2_adjusted=11.8,
        reduced_chi2=11.8, dof=100))
    verdict = _verdict(before, {"summary": "in the tails"}, [], [], None, ["lens_blur"])
    assert "confirmed lens_blur, but in the estimator's final fit its magnitude cannot be told from absent" in verdict
    assert verdict.endswith("no cause is named")


def _dropped_first_pass(pb, candidates):
    """A first pass whose estimator's final fit dropped its only confirmed effect, a glare tail
    (the bench's recaptured boundary session): the base fit's evaluation and screening, and
    that final fit (the tail at a magnitude no different from absent)."""
    from estimate.diagnose import ChannelDiagnosis, screen_candidates

    ev, loc, scores = screen_candidates(pb, BaseFit(dict(TRUE), 1e4, "hg"), make_model, candidates=candidates,
                                        spp=64, repeats=3)
    pruned = [{"effect": "lens_blur", "stage": "final fit", "chi2_rise": 40.0, "needed": 11.0, "price": 11.0,
               "dispersion": 1.0, "dropped": True, "with": [], "leading": True, "magnitude_sigma": 0.08,
               "magnitude_needed": 1.0}]
    d = ChannelDiagnosis("g", ev, loc, scores, [{"effect": "lens_blur", "round": 1, "delta_bic": 50.0,
                                                "confirmed": True}], [], ev, {}, "first verdict", 3.0,
                         ["sigma_t", "albedo", "phase.g"], final_fit={"kept": True, "time_s": 1.0},
                         pruned=pruned, confirmed_order=["lens_blur"], stage_times_s={"locate": 1.0, "screening": 2.0})
    final = SimpleNamespace(extensions=["lens_blur"], parameters={
        **TRUE, "lens_blur.core_sigma_px": 0.1, "lens_blur.tail_fraction": 0.001})
    return d, final


def _stray_light_second_pass(candidates):
    """A stray-light recording whose first pass's final fit dropped its glare tail
    (`_dropped_first_pass`), and quick fit settings for the second pass's final fits."""
    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    d, final = _dropped_first_pass(pb, candidates)
    st = FitSettings(seed=2, scale="free", max_iterations=14, spp_start=64, spp_max=128, final_spp=256, window=3,
                     polish_steps=1)
    return pb, d, final, st


def test_when_the_final_fit_drops_every_effect_the_other_candidates_are_refitted():
    """The estimator's final fit dropped the only confirmed effect (a glare tail standing in
    for the concealed one): every other candidate is refitted from the
    base fit, the best is fitted by the estimator and, explaining the data better than the
    fit with the stand-in, named (a stray-light offset here); the report keeps both passes."""
    from estimate.diagnose import (
        second_pass_channel,
        stand_in_effects,
        summary_text,
    )

    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    d, final = _dropped_first_pass(pb, ["lens_blur", "stray_light"])
    assert stand_in_effects(d) == ["lens_blur"]
    st = FitSettings(seed=2, scale="free", max_iterations=14, spp_start=64, spp_max=128, final_spp=256, window=3,
                     polish_steps=1)
    fr = second_pass_channel(pb, d, final, BaseFit(dict(TRUE), 1e4, "hg"), make_model, st, spp=64, repeats=3,
                             iterations=8)
    again = d.second_pass
    assert again["dropped"] == ["lens_blur"] and again["refitted"] == ["stray_light"]   # not offered again
    assert d.confirmed == ["stray_light"] and again["named"] == ["stray_light"]
    vs = again["against_first"]
    assert vs["chi2_second"] < vs["chi2_first"] and vs["gain"] > vs["needed"]
    assert fr is not None and fr.extensions == ["stray_light"] and d.final_fit["kept"]
    assert d.after.extensions == ["stray_light"] and "lens_blur.tail_fraction" not in d.after.parameters
    assert fr.parameters["stray_light.offset"] == pytest.approx(0.01, rel=0.5)
    assert again["first_final_fit"]["time_s"] == 1.0
    assert [e.get("pass") for e in d.confirmations][:1] == [None]
    assert {e["pass"] for e in d.confirmations[1:]} == {2}
    assert all("heldout_ok" in e for e in d.confirmations[1:])   # recorded, not deciding
    assert sum(d.stage_times_s.values()) == pytest.approx(d.time_s, rel=1e-3, abs=0.05)
    doc = d.as_dict()
    assert doc["second_pass"]["named"] == ["stray_light"] and "stray_light" in doc["confirmed_effects"]
    assert doc["material_before"]["sigma_t"] == TRUE["sigma_t"]     # "before" stays the fit the user made
    assert "left-out physics: stray_light" in d.verdict and "could not tell from absent" in d.verdict
    text = summary_text({"channels": {"g": doc}, "run_id": "x", "refit_run": None})
    assert "second pass: the estimator's final fit dropped lens_blur; every other candidate" in text
    assert "second pass: refit with stray_light" in text and "its final fit against the first" in text


def test_when_the_refit_kept_in_place_of_the_final_fit_explains_too_little_the_other_candidates_are_refitted():
    """The bench boundary session on an NVIDIA H200 (session 55): the first pass confirmed a
    glare tail and stray light, their estimator fit ended worse than the base fit (reduced
    chi2 at the floor 26.3 against 10.9) and was not kept, and the refit kept in its place
    removed 33 % of the excess, so nothing was named. That refit is now what the other
    candidates' final fits must beat: here a glare tail stands in for a stray light."""
    from estimate.diagnose import evaluate, second_pass_channel, stand_in_effects, summary_text

    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    d, final = _dropped_first_pass(pb, ["lens_blur", "stray_light"])
    lm = evaluate(make_model(["lens_blur"]), final.parameters, pb, 6, spp=64, repeats=3)
    b = d.before.residuals.reduced_chi2_adjusted
    a = lm.residuals.reduced_chi2_adjusted
    d.after, d.final_fit, d.pruned = lm, {"kept": False, "time_s": 1.0, "reason": "worse than the base fit"}, []
    d.partial = {"effects": ["lens_blur"], "share_explained": (b - a) / (b - 1.0), "min_share": 0.5,
                 "reduced_chi2_adjusted_before": b, "reduced_chi2_adjusted_with": a, "stage": "refit"}
    assert stand_in_effects(d) == ["lens_blur"]
    # the stage must be that of the model that stays
    assert stand_in_effects(dataclasses.replace(d, partial={**d.partial, "stage": "final fit"})) == []
    st = FitSettings(seed=2, scale="free", max_iterations=14, spp_start=64, spp_max=128, final_spp=256, window=3,
                     polish_steps=1)
    fr = second_pass_channel(pb, d, None, BaseFit(dict(TRUE), 1e4, "hg"), make_model, st, spp=64, repeats=3,
                             iterations=8)
    again = d.second_pass
    assert again["first_model"] == "refit" and again["dropped"] == ["lens_blur"]
    assert fr is not None and d.confirmed == ["stray_light"] and again["named"] == ["stray_light"]
    vs = again["against_first"]
    assert vs["chi2_second"] < vs["chi2_first"] and vs["gain"] > vs["needed"]
    assert vs["k_first"] == len(_free_names(make_model(["lens_blur"]), ["lens_blur"])) + 1
    assert "in the refit kept in place of the estimator's final fit (which fitted worse than the base fit)" in d.verdict
    assert "left-out physics: stray_light" in d.verdict
    text = summary_text({"channels": {"g": d.as_dict()}, "run_id": "x", "refit_run": None})
    assert ("second pass: the refit kept in place of the estimator's final fit (which fitted worse than the base "
            "fit) dropped lens_blur; every other candidate") in text
    assert sum(d.stage_times_s.values()) == pytest.approx(d.time_s, rel=1e-3, abs=0.05)


def test_the_second_pass_refits_a_candidate_the_screening_did_not_flag():
    """The score test is local: a base fit far from the data's optimum can leave the effect
    the recording holds unflagged (the bench's boundary session recaptured in session 46,
    p 0.05). The second pass refits it all the same, and names it where its estimator fit
    wins. Here the stray light's score is set to p 0.1, as if the base fit hid it."""
    from estimate.diagnose import SCREEN_LOG10_P, second_pass_channel, summary_text

    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    d, final = _dropped_first_pass(pb, ["lens_blur", "stray_light"])
    d.candidates = [c if c.name != "stray_light" else dataclasses.replace(c, log10_p=-1.0) for c in d.candidates]
    assert not any(c.log10_p < SCREEN_LOG10_P for c in d.candidates if c.name == "stray_light")
    st = FitSettings(seed=2, scale="free", max_iterations=14, spp_start=64, spp_max=128, final_spp=256, window=3,
                     polish_steps=1)
    fr = second_pass_channel(pb, d, final, BaseFit(dict(TRUE), 1e4, "hg"), make_model, st, spp=64, repeats=3,
                             iterations=8)
    again = d.second_pass
    assert again["refitted"] == ["stray_light"] and again["flagged"] == []
    assert [e["effect"] for e in d.confirmations if e.get("pass") == 2] == ["stray_light"]
    assert fr is not None and d.confirmed == ["stray_light"] and again["named"] == ["stray_light"]
    text = summary_text({"channels": {"g": d.as_dict()}, "run_id": "x", "refit_run": None})
    assert ("every other candidate (stray_light) refitted from the better of the base fit and the coarse grid"
            in text)


def test_a_second_pass_refit_starts_from_the_grid_where_the_base_fit_is_far_off():
    """A base fit that made up for a left-out boundary sits far from the material the
    boundary model needs (the bench's recaptured boundary session: sigma_t 57 % high, and
    the boundary refitted from there went to n 2.96). The candidate's start is then the
    coarse grid's best with the boundary switched on at its start value, judged by the
    refit's own chi^2; where the fit's material is already right (the truth here) it is
    kept, although the grid's log loss at 32 spp prefers a grid point (albedo 0.7)."""
    from estimate.diagnose import GridStart, _candidate_start

    rec = record({"refractive_boundary.n": 1.33})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    m = make_model(["refractive_boundary"])
    free = _free_names(m, ["refractive_boundary"])

    def chi2_at(p):
        return refit(m, pb, p, free, iterations=0, uncertainties=False, spp=128, seed=5).chi2

    how = GridStart(spp=32, delta_rel=0.0447, seed=7)
    far = {"sigma_t": 4.5, "albedo": 0.6, "phase.g": 0.85, "refractive_boundary.n": 1.2}
    start, info, other = _candidate_start(m, pb, far, how, chi2_at)
    assert other == far   # the start not taken
    assert info["from"] == "coarse grid" and info["chi2_grid"] < info["chi2_fit"], info
    assert start["refractive_boundary.n"] == 1.2
    assert abs(math.log(start["sigma_t"] / TRUE["sigma_t"])) < abs(math.log(far["sigma_t"] / TRUE["sigma_t"]))
    near = {**TRUE, "refractive_boundary.n": 1.33}
    start, info, other = _candidate_start(m, pb, near, how, chi2_at)
    assert other != near and other["refractive_boundary.n"] == 1.33
    assert info["from"] == "fit" and start == near, info


def test_a_second_pass_refit_that_fails_from_its_start_is_tried_from_the_other(monkeypatch):
    """The bench's glass-like boundary session (session 55): the fit's start was 1.7 % below
    the grid's by the refit's chi^2, and the boundary refitted from it gained -13 with its
    magnitude at 0 sigma; from the grid it gained 842 (11.4 sigma) and was then named. A
    second-pass refit that fails from the start chosen is tried from the other, and the
    better gain stands. Here a halo recording's chosen start is made a poor one (sigma_t
    0.3, albedo 0.3, the halo at absent); from the other the halo's refit passes and goes
    to the estimator (whose quick fit here is not kept; naming is the other tests' part)."""
    import estimate.diagnose as dg

    rec = record({"beam_halo.fraction": 0.4})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    d, final = _dropped_first_pass(pb, ["lens_blur", "beam_halo"])
    real, searched = dg._candidate_start, []

    def poor_first(model, problem, start, how, chi2_at):
        good, info, _ = real(model, problem, start, how, chi2_at)
        searched.append(info)
        poor = {**good, "sigma_t": 0.3, "albedo": 0.3, "beam_halo.fraction": 0.0}
        return poor, {**info, "from": "fit"}, good

    monkeypatch.setattr(dg, "_candidate_start", poor_first)
    st = FitSettings(seed=2, scale="free", max_iterations=14, spp_start=64, spp_max=128, final_spp=256, window=3,
                     polish_steps=1)
    dg.second_pass_channel(pb, d, final, BaseFit(dict(TRUE), 1e4, "hg"), make_model, st, spp=64, repeats=3,
                           iterations=4)
    (e,) = [e for e in d.confirmations if e.get("pass") == 2]
    other = e["start"]["other"]
    assert other["from"] == "fit" and e["start"]["from"] == "coarse grid"
    assert other["delta_bic"] < dg.BIC_STRONG < e["delta_bic"] and other["magnitude_sigma"] <= dg.MAGNITUDE_SIGMA
    assert e["magnitude_sigma"] > dg.MAGNITUDE_SIGMA and e["time_s"]["refit"] > 0 and not e["time_s"]["reused"]
    assert d.second_pass["chosen"] == ["beam_halo"]   # eligible for the estimator's fit only from the other start
    assert len(searched) == 1   # the estimator's try took both refits from the round's cache
    text = dg.summary_text({"channels": {"g": d.as_dict()}, "run_id": "x", "refit_run": None})
    assert "(started from the coarse grid; from the fit it gained -" in text


def test_when_the_first_choice_fails_its_final_fit_the_second_pass_tries_the_next(monkeypatch):
    """The bench's recaptured boundary session: stray light's refit gained the most, its
    estimator fit was not kept, and the boundary (second by its refit's gain) was never
    fitted (session 48). Now the next candidate that passed is fitted and judged against
    the first final fit, up to SECOND_PASS_FINAL_FITS of them, each try recorded. Here the
    first choice's final fit is made to fail."""
    import estimate.diagnose as dg

    pb, d, final, st = _stray_light_second_pass(["lens_blur", "stray_light", "angle_offset"])
    real, fitted = dg.refine_channel, []

    def first_not_kept(problem, dk, *a, **k):
        fitted.append(list(dk.confirmed))
        return None if len(fitted) == 1 else real(problem, dk, *a, **k)

    monkeypatch.setattr(dg, "refine_channel", first_not_kept)
    fr = dg.second_pass_channel(pb, d, final, BaseFit(dict(TRUE), 1e4, "hg"), make_model, st, spp=64, repeats=3,
                                iterations=4)
    again = d.second_pass
    first, second = again["chosen"]
    assert fitted == [[first], [second]] and {first, second} == {"stray_light", "angle_offset"}
    tries = again["tries"]
    assert [t["effect"] for t in tries] == [first, second]
    assert tries[0]["outcome"] == f"{first}'s final fit was not kept" and tries[0]["against_first"] is None
    # The next one (an angle offset on a stray-light recording) is fitted by the estimator
    # and judged: its final fit removes a few per cent of the excess, under MIN_SHARE, so it
    # is not named and never compared with the first final fit (session 51).
    assert first == "stray_light" and tries[1]["against_first"] is None
    assert tries[1]["outcome"].startswith(f"in the estimator's final fit {second} removes ")
    assert tries[1]["outcome"].endswith(f"of the excess (needs {100 * dg.MIN_SHARE:.0f} %)")
    # the second candidate's refit came from the round's cache: one pass-2 entry each
    assert sorted(e["effect"] for e in d.confirmations if e.get("pass") == 2) == ["angle_offset", "stray_light"]
    assert fr is None and again["named"] == []
    assert again["outcome"].startswith(f"{first}'s final fit was not kept; ")
    # the report says what became of each candidate the estimator fitted
    entries = {e["effect"]: e for e in d.confirmations if e.get("pass") == 2}
    assert entries[first]["confirmed"] is False
    assert entries[first]["final_fit_outcome"] == tries[0]["outcome"]
    assert entries[second]["confirmed"] == (fr is not None)
    text = dg.summary_text({"channels": {"g": d.as_dict()}, "run_id": "x", "refit_run": None})
    assert f"-> not confirmed (fitted by the estimator: {first}'s final fit was not kept)" in text
    assert sum(d.stage_times_s.values()) == pytest.approx(d.time_s, rel=1e-3, abs=0.05)


def test_a_second_pass_try_whose_final_fit_fits_worse_says_by_how_much():
    """The bench boundary session's stray light: its estimator fit ended above the base fit's
    reduced chi^2 at the floor, so it was not kept; the try says so with both numbers, where
    "was not kept" alone read as if the effect itself had been turned away."""
    from types import SimpleNamespace

    import estimate.diagnose as dg

    before = SimpleNamespace(residuals=SimpleNamespace(reduced_chi2_adjusted=12.898))
    dk = SimpleNamespace(final_fit={"kept": False, "reduced_chi2_adjusted": 37.21}, before=before,
                         confirmed=["stray_light"], partial={})
    assert dg._try_outcome("stray_light", None, dk, None, ["beam_halo"]) == (
        "stray_light's final fit was not kept: it ends at reduced chi2 37.2 at the noise floor, above the base "
        "fit's 12.9")
    # no final fit was made (nothing confirmed): nothing more to say
    dk.final_fit = {}
    assert dg._try_outcome("stray_light", None, dk, None, ["beam_halo"]) == "stray_light's final fit was not kept"


def test_the_second_pass_fits_refits_that_pass_every_test_before_those_that_fail_one():
    """The refits of the session-54 recapture of the bench boundary session (channel g): by
    the fixed-seed gain alone stray light came first and the angle offset, worse on the
    held-out angles and below the control when rendered independently, second, taking the
    last final fit from the boundary. Those passing every test go first, by their gain
    rendered independently (the boundary's is the largest), then the others by their own."""
    from estimate.diagnose import MAGNITUDE_SIGMA, second_pass_order

    def entry(effect, gain, independent, heldout=True, no_harm=True, magnitude=5.0):
        return {"effect": effect, "delta_bic": gain, "delta_bic_independent": independent, "heldout_ok": heldout,
                "no_harm": no_harm, "magnitude_sigma": magnitude}

    entries = [entry("stray_light", 800.6, 1788.0), entry("thickness_error", -9.9, -177.5, heldout=False),
               entry("refractive_boundary", 113.4, 2357.2), entry("sensor_nonlinearity", 4.1, 194.0),
               entry("angle_offset", 122.4, -72.9, heldout=False), entry("filter_bandwidth", 55.2, 1316.1)]
    assert second_pass_order(entries) == ["refractive_boundary", "stray_light", "filter_bandwidth", "angle_offset"]
    # Those that fail a test keep the order of their own gains, after every one that passes.
    failing = [entry("angle_offset", 122.4, -72.9, heldout=False), entry("lens_blur", 300.0, 5.0),
               entry("thickness_error", 20.0, 40.0)]
    assert second_pass_order(failing) == ["thickness_error", "lens_blur", "angle_offset"]
    # Each test alone sends a refit behind those that pass them all; the estimator still fits
    # it after them (a refit from a base fit far off can fail them and be the cause).
    for bad in ({"no_harm": False}, {"heldout": False}, {"independent": 5.0}):
        kw = {"independent": 2357.2, **bad}
        got = second_pass_order([entry("refractive_boundary", 900.0, **kw), entry("stray_light", 50.0, 60.0)])
        assert got == ["stray_light", "refractive_boundary"], bad
    # A refit below the bar or with a magnitude that cannot be told from absent is not fitted.
    assert second_pass_order([entry("stray_light", 9.0, 100.0),
                              entry("angle_offset", 500.0, 600.0, magnitude=0.5 * MAGNITUDE_SIGMA)]) == []


def test_a_second_pass_counts_its_refits_when_the_estimator_fits_another_candidate_first(monkeypatch):
    """The round that refits every candidate chooses by the fixed-seed gain; the estimator may
    fit another candidate first (`second_pass_order`). The round's refits are time the
    diagnosis spent all the same (session 54: left out, the bench boundary session's time
    read 620 s against 900 s of wall time)."""
    import estimate.diagnose as dg

    pb, d, final, st = _stray_light_second_pass(["lens_blur", "stray_light", "angle_offset"])
    real_order, rounds_choice = dg.second_pass_order, []

    def its_choice_last(entries):
        names = real_order(entries)
        top = max((e for e in entries if e["effect"] in names), key=lambda e: float(e["delta_bic"]))["effect"]
        rounds_choice.append(top)
        return [n for n in names if n != top] + [top]

    real_diagnose, rounds = dg.diagnose_channel, []

    def recorded(*a, **k):
        rounds.append(real_diagnose(*a, **k))
        return rounds[-1]

    monkeypatch.setattr(dg, "second_pass_order", its_choice_last)
    monkeypatch.setattr(dg, "diagnose_channel", recorded)
    monkeypatch.setattr(dg, "SECOND_PASS_FINAL_FITS", 1)  # the round's own choice is never fitted
    before = dict(d.stage_times_s)
    dg.second_pass_channel(pb, d, final, BaseFit(dict(TRUE), 1e4, "hg"), make_model, st, spp=64, repeats=3,
                           iterations=4)
    again = d.second_pass
    assert len(again["chosen"]) == 1 and again["chosen"] != rounds_choice
    refits = sum(e["time_s"]["refit"] for e in d.confirmations if e.get("pass") == 2)
    assert refits > 0
    # The round (the first diagnosis of the pass) and the try (the second) both count, whole.
    the_round, the_try = rounds
    spent = the_round.stage_times_s["confirmation"] + the_try.stage_times_s.get("confirmation", 0.0)
    assert the_round.stage_times_s["confirmation"] >= refits
    assert again["time_by_stage_s"]["confirmation"] == pytest.approx(spent)
    assert d.stage_times_s["confirmation"] - before.get("confirmation", 0.0) == pytest.approx(spent)
    assert sum(d.stage_times_s.values()) == pytest.approx(d.time_s, rel=1e-3, abs=0.05)


def test_a_second_pass_that_cannot_beat_the_first_final_fit_names_nothing(monkeypatch):
    """The second final fit must explain the data better than the one with the stand-in, by
    more than BIC_STRONG after the dispersion and the parameters' price; here the first
    final fit is given the truth itself, so nothing is gained and nothing named."""
    import estimate.diagnose as dg
    from estimate.diagnose import second_pass_channel

    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    d, _ = _dropped_first_pass(pb, ["lens_blur", "stray_light"])
    truth = SimpleNamespace(extensions=["stray_light"], parameters={**TRUE, "stray_light.offset": 0.01,
                                                                    "stray_light.slope_per_mm": 0.0})
    st = FitSettings(seed=2, scale="free", max_iterations=14, spp_start=64, spp_max=128, final_spp=256, window=3,
                     polish_steps=1)
    assert second_pass_channel(pb, d, truth, BaseFit(dict(TRUE), 1e4, "hg"), make_model, st, spp=64,
                               repeats=3) is None
    again = d.second_pass
    assert again["chosen"] == ["stray_light"] and again["named"] == [] and d.confirmed == []
    assert again["against_first"]["gain"] <= dg.BIC_STRONG
    assert "does not explain the data better than the one with lens_blur" in again["outcome"]
    assert d.verdict.startswith("first verdict; refitting every other candidate: ")


def test_a_second_pass_without_candidates_left_says_so_and_names_nothing():
    from estimate.diagnose import second_pass_channel, stand_in_effects

    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    d, final = _dropped_first_pass(pb, ["lens_blur"])
    assert second_pass_channel(pb, d, final, BaseFit(dict(TRUE), 1e4, "hg"), make_model, FitSettings(), spp=64,
                               repeats=3) is None
    assert d.confirmed == [] and d.second_pass["outcome"] == "no other candidate to refit"
    assert d.verdict == "first verdict; no other candidate to refit"
    # nothing to do where an effect is still named, or where the final fit was not kept
    assert stand_in_effects(dataclasses.replace(d, confirmed=["stray_light"])) == []
    assert stand_in_effects(dataclasses.replace(d, final_fit={"kept": False})) == []
    assert stand_in_effects(dataclasses.replace(d, final_fit={})) == []   # no final fit at all


def test_a_value_at_an_end_of_its_range_is_told_apart():
    assert bound_side(0.1, [(0.0, 0.1)]) == "upper" and bound_side(0.09995, [(0.0, 0.1)]) == "upper"
    assert bound_side(0.0, [(0.0, 0.1)]) == "lower" and bound_side(0.05, [(0.0, 0.1)]) is None
    assert bound_side(0.1, [(0.0, 0.1), (0.0, 1.0)]) == "upper"   # the refit's range, inside the parameter's
    assert bound_side(0.5, [(0.0, 0.1), (0.0, 1.0)]) is None      # past it: the final fit's range allowed that
    assert bound_side(1.0, [(0.0, 0.1), (0.0, 1.0)]) == "upper"
    assert bound_side(0.0, [(0.0, math.inf)]) == "lower" and bound_side(1e-3, [(0.0, math.inf)]) is None
    assert bound_side(5.0, [(-math.inf, math.inf)]) is None and bound_side(1.0, []) is None


def test_named_effects_are_ranked_by_the_chi2_each_carries_in_the_final_model():
    """The rounds' order follows the screening at the base fit; the names follow what each
    effect carries in the model that explains the data, and the summary says both."""
    from estimate.diagnose import _by_importance, summary_text

    ranked, imp = _by_importance(["lens_blur", "refractive_boundary"],
                                 {"lens_blur": 172.0, "refractive_boundary": 2400.0}, "final fit")
    assert ranked == ["refractive_boundary", "lens_blur"]
    assert list(imp) == ranked and imp["lens_blur"] == {"chi2_rise": 172.0, "stage": "final fit"}
    rec = record({"stray_light.offset": 0.003}, seed=5)
    d = diagnose_channel(rec, BaseFit(dict(TRUE), 1e4, "hg"), make_model, candidates=["stray_light"], spp=128,
                         repeats=3)
    doc = d.as_dict()
    assert doc["confirmed_order"] == d.confirmed and doc["importance"] == {}  # one named: nothing to rank
    doc.update(confirmed_order=["lens_blur", "refractive_boundary"], importance=imp,
               confirmed_effects={"refractive_boundary": {}, "lens_blur": {}})
    text = summary_text({"channels": {"g": doc}, "run_id": "x", "refit_run": None})
    assert ("named by the chi2 each carries in the final fit (set to absent alone): refractive_boundary 2400, "
            "lens_blur 172; the rounds added them as lens_blur, refractive_boundary") in text
    # Without the estimator's final fit the material "after" is the decorrelated step from the
    # fixed-seed LM refit, whose optimum the summary gives; with the final fit kept it does not.
    assert "the Levenberg-Marquardt refit's" in text and "decorrelated" not in text  # none made here
    doc.update(material_fixed_seed_after={"sigma_t": 1.93, "albedo": 0.851, "phase.g": 0.49})
    text = summary_text({"channels": {"g": doc}, "run_id": "x", "refit_run": None})
    assert "decorrelated chi^2 of two render seeds" in text and "sigma_t 1.93, albedo 0.851)" in text
    doc.update(pruned=[{"effect": "lens_blur", "stage": "final fit", "chi2_rise": 54.7, "needed": 38.0,
                        "price": 15.2, "dispersion": 2.49, "dropped": True, "with": ["refractive_boundary"],
                        "magnitude_sigma": 0.23, "magnitude_needed": 1.0}])
    text = summary_text({"channels": {"g": doc}, "run_id": "x", "refit_run": None})
    assert ("lens_blur set to absent in the model with refractive_boundary raises chi2 by 54.7, more than its BIC "
            "price 15.2 (k ln n) x 2.49 (the reduced chi2 the model with every named effect leaves) = 38.0; its "
            "fitted magnitude is 0.2 sigma from absent (needs more than 1) -> dropped") in text
    assert "without --quick" in text
    # the check of a lone (or leading) effect says that its magnitude decided, not its rise
    for dropped in (True, False):
        doc.update(pruned=[{"effect": "lens_blur", "stage": "final fit", "chi2_rise": 4000.0, "needed": 15.2,
                            "price": 15.2, "dispersion": 1.0, "dropped": dropped, "with": [], "leading": True,
                            "magnitude_sigma": 0.08 if dropped else 5.0, "magnitude_needed": 1.0}])
        text = summary_text({"channels": {"g": doc}, "run_id": "x", "refit_run": None})
        line = next(ln for ln in text.splitlines() if "check in the estimator's fit" in ln)
        assert "lens_blur (alone in the model; setting it to absent raises chi2 by 4000.0) lies" in line
        assert line.endswith("-> kept") is not dropped and ("cannot be told from absent" in line) is dropped
    doc.update(final_fit={"kept": True, "iterations": 3, "time_s": 1.0},
               refit_lm={"reduced_chi2_adjusted": 1.0, "material": {"sigma_t": 2.0, "albedo": 0.9}})
    text = summary_text({"channels": {"g": doc}, "run_id": "x", "refit_run": None})
    assert "final model fitted by the estimator" in text and "without --quick" not in text


def test_final_fit_under_a_calibrated_scale_starts_from_the_refit_carried_to_that_scale():
    """The LM refit fits a free scale, which trades with the albedo; the estimator's final fit
    may hold the calibrated scale. Its start takes the refit's stray light in the calibrated
    scale's units, and the better (by the log loss) of the refit's and the coarse grid's material."""
    from estimate.diagnose import _final_fit_start
    from estimate.loss import ScaleCalibration

    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    m = make_model(["stray_light"])
    # What a free-scale refit can end at: 1.5x the scale, the albedo traded down to match.
    lm = SimpleNamespace(parameters=m.validate({**TRUE, "albedo": 0.75, "stray_light.offset": 0.01 / 1.5}),
                         scale=1.5e4)
    st = FitSettings(start_spp=16)
    same, info = _final_fit_start(pb, m, lm, st, None)
    assert same == lm.parameters and info == {"from": "refit"}
    cal = ScaleCalibration(scale=1e4, power_e_per_s=1.0, beam_power=1.0, calibration_nd=1.0, collection_sr=1.0,
                           pixel_area_mm2=1.0)
    start, info = _final_fit_start(pb, m, lm, st, cal)
    assert info["radiance_factor"] == pytest.approx(1.5)
    assert start["stray_light.offset"] == pytest.approx(0.01)  # the refit's stray light, carried over
    assert info["from"] == "coarse grid" and info["loss_grid"] < info["loss_refit"]
    assert start["albedo"] in (0.85, 0.95) and start["sigma_t"] == pytest.approx(2.0, rel=0.01)


def test_refit_covariance_from_two_noisy_jacobians_is_not_narrowed_by_their_noise():
    """Along a valley one noisy Jacobian's A^T A carries its noise's Gram matrix, so the
    refit's interval there comes out too narrow; the bounded cross product of two
    independent Jacobians gives the noise-free interval. A column that is zero in both (a
    halo's width at fraction 0) has an unknown (NaN) variance."""
    rng = np.random.default_rng(11)
    x = np.linspace(-3.0, 3.0, 400)
    prof = np.exp(-np.abs(x))
    # columns: two nearly parallel parameters (a valley), a dead one, the scale
    true = np.stack([prof, prof * (1.0 + 0.05 * x), np.zeros_like(x), 0.5 * prof], axis=1)

    def noisy() -> np.ndarray:
        a = true + 0.05 * prof[:, None] * rng.standard_normal(true.shape)
        a[:, 2] = 0.0
        return a

    def sd(cov: np.ndarray) -> float:
        return float(np.sqrt(cov[1, 1]))

    exact = sd(cross_covariance(true, true))
    one = np.mean([sd(cross_covariance(a, a)) for a in (noisy() for _ in range(20))])
    two = np.mean([sd(cross_covariance(noisy(), noisy())) for _ in range(20)])
    assert one < 0.8 * exact
    assert two == pytest.approx(exact, rel=0.15)
    cov = cross_covariance(noisy(), noisy())
    assert cov.shape == (3, 3) and np.isnan(cov[2, 2]) and np.all(np.isfinite(cov[:2, :2]))


class _OneByOne:
    """A toy model's `render_profiles_many`: its renders one after the other."""

    def render_profiles_many(self, requests, angles, *, spp):
        return [self.render_profiles(th, angles, spp=spp, seed=seed) for th, seed in requests]


class _NoisyWidth(_OneByOne):
    """A profile exp(-|x| / w) (1 + c x / 4) rendered with Monte Carlo noise whose size
    grows with the width w (common random numbers per seed): a fixed-seed chi^2 then
    prefers narrower profiles, as the slab's renders prefer quieter (lower) albedos."""

    x = np.linspace(-4.0, 4.0, 200)
    jacobian_renders = 0
    specs: ClassVar[dict[str, ParameterSpec]] = {
        "toy.w": ParameterSpec("w", 1.0, 0.2, 5.0, "mm", "fd", 0.01, "width"),
        "toy.c": ParameterSpec("c", 0.0, -1.0, 1.0, "", "fd", 0.01, "tilt")}
    parameter_names: ClassVar[list[str]] = list(specs)

    def validate(self, p):
        return {k: float(p.get(k, v.neutral)) for k, v in self.specs.items()}

    def mean(self, th):
        return np.exp(-np.abs(self.x) / th["toy.w"]) * (1.0 + th["toy.c"] * self.x / 4.0)

    def render_profiles(self, th, angles, *, spp, seed):
        eps = np.random.default_rng(seed).standard_normal((len(angles), self.x.size))
        return self.mean(th) * (1.0 + 0.3 * th["toy.w"] * eps / math.sqrt(spp / 64))

    def jacobian(self, th, angles, free, *, spp, seed, steps):
        self.jacobian_renders += 2 * len(free)
        out = {}
        for n in free:
            hi, lo = dict(th), dict(th)
            hi[n] += steps[n]
            lo[n] -= steps[n]
            out[n] = (self.render_profiles(hi, angles, spp=spp, seed=seed)
                      - self.render_profiles(lo, angles, spp=spp, seed=seed)) / (2 * steps[n])
        return out


def _width_recordings(count: int, seed: int = 3) -> tuple[_NoisyWidth, dict[str, float], np.ndarray, list[Recording]]:
    """`count` recordings of `_NoisyWidth` at w = 1, c = 0.2 (three angles, noise 0.01)."""
    toy = _NoisyWidth()
    truth = {"toy.w": 1.0, "toy.c": 0.2}
    rng = np.random.default_rng(seed)
    mean = np.tile(toy.mean(truth), (3, 1))
    recs = [Recording(np.array([10.0, 20.0, 30.0]), toy.x, mean + rng.normal(0.0, 0.01, mean.shape),
                      np.full(mean.shape, 1e-4), None, None) for _ in range(count)]
    return toy, truth, mean, recs


class _DimmableWidth(_NoisyWidth):
    """`_NoisyWidth` times a brightness b: with a free scale, b changes nothing the data
    can see (s b is all that counts), so no refit should move it or gain by it."""

    specs: ClassVar[dict[str, ParameterSpec]] = {
        **_NoisyWidth.specs, "toy.b": ParameterSpec("b", 1.0, 1e-4, 10.0, "", "fd", 0.01, "brightness")}
    parameter_names: ClassVar[list[str]] = list(specs)

    def mean(self, th):
        return th["toy.b"] * super().mean(th)


def test_a_refit_cannot_buy_its_own_weights_by_dimming_its_renders():
    """The render variance in the weights is held in the data's units: a parameter that only
    dims the render (the scale makes up for it) leaves the chi^2 as it was. Up to session 46
    the variance followed the refit's scale (s^2 var_model), so dimming the render bought
    smaller residuals: the bench's boundary refit went to n 2.99 with its scale 5500 x and
    its chi^2 from 7732 to 744 (session 47). Both objectives."""
    toy = _DimmableWidth()
    _, _, mean, (rec,) = _width_recordings(1, seed=5)
    start = {"toy.w": 1.0, "toy.c": 0.2, "toy.b": 1.0}
    for objective in (FIXED_SEED, DECORRELATED):
        kw = {"spp": 64, "seed": 100, "model_variance": (0.3 * mean) ** 2, "uncertainties": False,
              "objective": objective}
        at_start = refit(toy, rec, start, ["toy.b"], iterations=0, **kw)
        r = refit(toy, rec, start, ["toy.b"], iterations=20, **kw)
        assert r.chi2 == pytest.approx(at_start.chi2, rel=1e-6), objective
        assert 0.5 < r.parameters["toy.b"] < 2.0, objective
        # dimmed 100 x by hand: the same chi^2, the scale 100 x
        dim = refit(toy, rec, {**start, "toy.b": 0.01}, ["toy.b"], iterations=0, **kw)
        assert dim.chi2 == pytest.approx(at_start.chi2, rel=1e-6) and dim.scale == pytest.approx(100 * at_start.scale)


class _SteepSecant(_NoisyWidth):
    """`_NoisyWidth` without render noise whose Jacobian is three times too steep, as a
    secant over a wide step of a strongly curved render can be: each Gauss-Newton step then
    covers a third of the way, and the refit walks towards the optimum in many short steps."""

    def render_profiles(self, th, angles, *, spp, seed):
        return np.tile(self.mean(th), (len(angles), 1))

    def jacobian(self, th, angles, free, *, spp, seed, steps):
        return {n: 3.0 * v for n, v in super().jacobian(th, angles, free, spp=spp, seed=seed, steps=steps).items()}


def test_a_refit_still_descending_fast_when_its_iterations_are_spent_goes_on_to_its_optimum(monkeypatch):
    """The LM's `iterations` are extended, up to LM_EXTENSION x, while its last two
    iterations still lowered chi^2 by more than LM_STILL_DESCENDING of it, with longer steps
    there; the first `iterations` are the plain LM's; a refit that starts at its optimum stops
    as before."""
    toy = _SteepSecant()
    _, truth, _, (rec,) = _width_recordings(1, seed=9)
    start = {"toy.w": 2.5, "toy.c": -0.3}
    kw = {"spp": 64, "seed": 1, "uncertainties": False}
    monkeypatch.setattr(refit_module, "LM_EXTENSION", 1)
    capped = refit(toy, rec, start, ["toy.w", "toy.c"], iterations=3, **kw)
    monkeypatch.setattr(refit_module, "LM_EXTENSION", 2)
    monkeypatch.setattr(refit_module, "LM_EXPANSION_MAX", 0.0)
    plain = refit(toy, rec, start, ["toy.w", "toy.c"], iterations=3, **kw)
    monkeypatch.undo()
    went_on = refit(toy, rec, start, ["toy.w", "toy.c"], iterations=3, **kw)
    assert capped.iterations == 3
    assert 3 < went_on.iterations <= refit_module.LM_EXTENSION * 3
    assert went_on.chi2 < plain.chi2 < 0.5 * capped.chi2
    assert abs(went_on.parameters["toy.w"] - truth["toy.w"]) < abs(capped.parameters["toy.w"] - truth["toy.w"])
    # The first three iterations are the capped refit's: only the fourth on takes longer steps.
    monkeypatch.setattr(refit_module, "LM_EXTENSION", 1)
    assert refit(toy, rec, start, ["toy.w", "toy.c"], iterations=3, **kw).parameters == capped.parameters
    monkeypatch.undo()
    optimum = refit(toy, rec, start, ["toy.w", "toy.c"], iterations=40, **kw)
    again = refit(toy, rec, optimum.parameters, ["toy.w", "toy.c"], iterations=3, **kw)
    assert again.iterations <= 3


class _CountedSteepSecant(_SteepSecant):
    """`_SteepSecant` counting the refit's own renders (its start and trials; the Jacobians'
    renders are counted apart, in `jacobian_renders`)."""

    renders = 0

    def render_profiles(self, th, angles, *, spp, seed):
        self.renders += 1
        return super().render_profiles(th, angles, spp=spp, seed=seed)

    def own_renders(self) -> int:
        return self.renders - self.jacobian_renders


def test_a_refit_stops_where_a_step_can_gain_no_more_than_a_negligible_chi2(monkeypatch):
    """From its optimum a refit renders its start and nothing else: the first trial step's
    predicted gain is below LM_NEGLIGIBLE_GAIN, so the trial is not rendered (without that
    bar it renders trials). On a long walk it stops once the next step is predicted to gain
    less than the bar, sooner than it would have crawled on and within about the bar of it
    (the secant here is 3 x too steep, so the prediction is short by as much)."""
    _, _, _, (rec,) = _width_recordings(1, seed=9)
    start = {"toy.w": 2.5, "toy.c": -0.3}
    kw = {"spp": 64, "seed": 1, "uncertainties": False}
    toy = _CountedSteepSecant()
    optimum = refit(toy, rec, start, ["toy.w", "toy.c"], iterations=40, **kw)
    toy.renders = toy.jacobian_renders = 0
    again = refit(toy, rec, optimum.parameters, ["toy.w", "toy.c"], iterations=8, **kw)
    assert toy.own_renders() == 1 and again.iterations == 1 and again.parameters == optimum.parameters
    monkeypatch.setattr(refit_module, "LM_NEGLIGIBLE_GAIN", 0.0)
    toy.renders = toy.jacobian_renders = 0
    refit(toy, rec, optimum.parameters, ["toy.w", "toy.c"], iterations=8, **kw)
    assert toy.own_renders() > 2                 # trials rendered
    crawled = refit(toy, rec, start, ["toy.w", "toy.c"], iterations=40, **kw)
    monkeypatch.undo()
    assert optimum.iterations < crawled.iterations
    assert optimum.chi2 - crawled.chi2 < 2 * refit_module.LM_NEGLIGIBLE_GAIN


@pytest.mark.parametrize(("history", "expect"), [
    ([100.0, 90.0, 80.0], True),           # 20 % over the last two iterations
    ([100.0, 99.0, 97.0], False),          # 3 %
    ([1000.0, 100.0, 98.0, 97.0], False),  # fast earlier, slow now
    ([100.0, 50.0], False),                # fewer than two iterations
    ([0.0, 0.0, 0.0], False),
])
def test_still_descending_reads_the_last_two_iterations(history, expect):
    assert still_descending(history) is expect


def test_decorrelated_step_removes_the_fixed_seed_refits_render_noise_bias():
    """Twelve recordings of w = 1, each refitted at its own seed: the LM's fixed-seed
    optimum sits several of its standard errors narrow; one Gauss-Newton step on the two
    seeds' decorrelated chi^2 lands within 2.5 of the truth. The scale (the noise grows
    with it too) follows."""
    toy, truth, mean, recs = _width_recordings(12)
    lm, dec, scales = [], [], []
    for k, rec in enumerate(recs):
        r = refit(toy, rec, truth, ["toy.w", "toy.c"], spp=64, seed=100 + k, iterations=20,
                  model_variance=(0.3 * mean) ** 2, decorrelate=True)
        lm.append(r.parameters["toy.w"])
        dec.append(r.decorrelated["toy.w"])
        scales.append((r.scale, r.decorrelated_scale))
    se = np.std(dec) / math.sqrt(len(dec))
    assert np.mean(lm) < 1.0 - 6 * se
    assert abs(np.mean(dec) - 1.0) < 2.5 * se
    s_lm, s_dec = np.mean(scales, axis=0)
    assert abs(s_dec - 1.0) < 0.5 * abs(s_lm - 1.0)
    # without the option the result is the LM's alone
    r = refit(toy, rec, truth, ["toy.w", "toy.c"], spp=64, seed=100, iterations=20, model_variance=(0.3 * mean) ** 2)
    assert r.decorrelated is None


def test_a_refits_uncertainties_can_be_skipped_and_added_later_from_its_optimum():
    """`uncertainties=False` returns the same optimum without the uncertainties' renders;
    `iterations=0` from that optimum adds them (and the decorrelated step) as the full
    refit would have: the diagnosis's rounds skip them and only the last model gets them."""
    toy, _, mean, (rec,) = _width_recordings(1, seed=5)
    kw = {"spp": 64, "seed": 100, "model_variance": (0.3 * mean) ** 2}
    counts = []
    fits = []
    for unc in (True, False):
        toy.jacobian_renders = 0
        fits.append(refit(toy, rec, {"toy.w": 1.4, "toy.c": 0.0}, ["toy.w", "toy.c"], iterations=20,
                          decorrelate=unc, uncertainties=unc, **kw))
        counts.append(toy.jacobian_renders)
    full, bare = fits
    assert bare.parameters == full.parameters and bare.chi2 == full.chi2 and bare.iterations == full.iterations
    assert bare.uncertainties == {} and bare.covariance == {} and bare.decorrelated is None
    assert counts[1] < counts[0]
    later = refit(toy, rec, bare.parameters, ["toy.w", "toy.c"], iterations=0, decorrelate=True, **kw)
    assert later.parameters == full.parameters and later.chi2 == pytest.approx(full.chi2, rel=1e-12)
    assert later.uncertainties == pytest.approx(full.uncertainties, rel=1e-9)
    assert later.covariance == pytest.approx(full.covariance, rel=1e-9)
    assert later.decorrelated == pytest.approx(full.decorrelated, rel=1e-12)
    assert all(v > 0 for v in later.uncertainties.values())


def test_decorrelated_refit_iterates_to_the_truth_where_the_fixed_seed_refit_leans():
    """Twelve recordings of w = 1, refitted from w 1.4 at their own seeds: the fixed-seed LM
    ends several standard errors narrow; the refit on the two seeds' decorrelated chi^2
    (`objective=DECORRELATED`) ends within 2.5 of the truth, in more than one step."""
    toy, _, mean, recs = _width_recordings(12)
    lm, dec, its = [], [], []
    for k, rec in enumerate(recs):
        kw = {"spp": 64, "seed": 100 + k, "iterations": 20, "model_variance": (0.3 * mean) ** 2,
              "uncertainties": False}
        lm.append(refit(toy, rec, {"toy.w": 1.4, "toy.c": 0.0}, ["toy.w", "toy.c"], **kw).parameters["toy.w"])
        r = refit(toy, rec, {"toy.w": 1.4, "toy.c": 0.0}, ["toy.w", "toy.c"], objective=DECORRELATED, **kw)
        assert r.objective == DECORRELATED and r.decorrelated is None
        dec.append(r.parameters["toy.w"])
        its.append(r.iterations)
    se = np.std(dec) / math.sqrt(len(dec))
    assert np.mean(lm) < 1.0 - 6 * se
    assert abs(np.mean(dec) - 1.0) < 2.5 * se
    assert max(its) > 1


def test_a_decorrelated_refits_loss_is_its_end_points_and_pairs_with_an_evaluation_there():
    """The loss a decorrelated refit returns is a function of its end point (the weights at
    that point's own scale): `iterations=0` there gives the same number, and the same
    uncertainties, so a candidate's neutral point and its control compare in one metric.
    The loss is the decorrelated chi^2 of the two seeds' renders, below the fixed-seed
    chi^2 at the same point by about the render noise's share."""
    toy, truth, mean, (rec,) = _width_recordings(1, seed=5)
    kw = {"spp": 64, "seed": 100, "model_variance": (0.3 * mean) ** 2, "objective": DECORRELATED}
    full = refit(toy, rec, {"toy.w": 1.4, "toy.c": 0.0}, ["toy.w", "toy.c"], iterations=20, **kw)
    bare = refit(toy, rec, {"toy.w": 1.4, "toy.c": 0.0}, ["toy.w", "toy.c"], iterations=20, uncertainties=False,
                 **kw)
    assert bare.parameters == full.parameters and bare.chi2 == full.chi2 and bare.uncertainties == {}
    again = refit(toy, rec, full.parameters, ["toy.w", "toy.c"], iterations=0, **kw)
    assert again.chi2 == pytest.approx(full.chi2, rel=1e-12) and again.scale == pytest.approx(full.scale, rel=1e-12)
    assert again.uncertainties == pytest.approx(full.uncertainties, rel=1e-9)
    assert all(v > 0 for v in full.uncertainties.values())
    fixed = refit(toy, rec, full.parameters, ["toy.w", "toy.c"], iterations=0, uncertainties=False,
                  spp=64, seed=100, model_variance=(0.3 * mean) ** 2)
    assert full.chi2 < fixed.chi2
    with pytest.raises(ValueError, match="objective"):
        refit(toy, rec, truth, ["toy.w"], objective="both")
    with pytest.raises(ValueError, match="noise_variance"):
        refit(toy, rec, truth, ["toy.w"], noise_variance=np.ones(mean.shape))
    # dividing by the data's noise alone (the diagnosis' yardstick) weighs the same loss
    # without the render-variance term in its weights: larger, the same point function
    nv = np.full(mean.shape, 1e-4)
    own = refit(toy, rec, full.parameters, ["toy.w", "toy.c"], iterations=0, uncertainties=False,
                noise_variance=nv, **kw)
    assert own.chi2 > full.chi2
    assert refit(toy, rec, full.parameters, ["toy.w", "toy.c"], iterations=0, uncertainties=False,
                 noise_variance=nv, **kw).chi2 == own.chi2


class _Fireflies(_OneByOne):
    """A smooth profile rendered with path-tracer-like noise: each pixel the mean of
    spp / 16 lognormal(0, 1.5) path weights (most a little low, a few far high), unbiased."""

    x = np.linspace(-4.0, 4.0, 256)
    parameter_names: ClassVar[list[str]] = ["toy.w"]
    extensions: ClassVar[list[str]] = []

    def validate(self, p):
        return {"toy.w": float(p.get("toy.w", 1.0))}

    def mean(self, th):
        return np.exp(-np.abs(self.x) / th["toy.w"]) + 0.02

    def render_profiles(self, th, angles, *, spp, seed):
        k = max(1, spp // 16)
        w = np.random.default_rng(seed).lognormal(0.0, 1.5, size=(len(angles), self.x.size, k)).mean(axis=-1)
        return self.mean(th) * w / math.exp(1.5 ** 2 / 2)


def _firefly_recording(seed: int) -> tuple[_Fireflies, Recording]:
    """A recording of `_Fireflies` at scale 1e4 whose own noise (1 % shot-like) is far below
    the renders' (~30 % a pixel), as on a real rig's tails."""
    toy = _Fireflies()
    angles = np.arange(10.0, 90.0, 10.0)
    truth = 1e4 * np.tile(toy.mean({"toy.w": 1.0}), (len(angles), 1))
    var = 0.01 * truth + 1.0
    meas = truth + np.random.default_rng(100 + seed).normal(size=truth.shape) * np.sqrt(var)
    return toy, Recording(angles, toy.x, meas, var, GEOMETRY, BEAM)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_residuals_weighed_by_independent_renders_have_no_render_noise_bias(seed):
    """At the true parameters and scale, residuals divided by their own renders' variance
    lean positive (a firefly shrinks its own residual) and the smooth test calls the
    correct model wrong; weighed by other renders they are centred and pass."""
    toy, rec = _firefly_recording(seed)
    th = {"toy.w": 1.0}
    ev = evaluate(toy, th, rec, 1, spp=256, seed=7 + 1000 * seed, repeats=6, scale=1e4)
    r_ind, sigma, modes = independent_residuals(rec, ev, toy, spp=256, repeats=6, seed=90_000 + seed)
    assert np.mean(ev.residuals.r_adjusted) > 0.1
    assert abs(float(np.mean(r_ind))) < 0.05
    assert not smooth_structure(r_ind)[2]
    assert not smooth_structure(r_ind, noise_modes=modes)[2]
    assert sigma.shape == rec.measured.shape and np.all(sigma > 0)
    # the modes of the mean of 6 renders, from 6 or (`renders`) 24 independent ones; white
    # render noise (the toy's pixels are independent) adds nothing to the null either way
    r24, _, more = independent_residuals(rec, ev, toy, spp=256, repeats=6, seed=90_000 + seed, renders=24)
    assert modes.shape == (6, *rec.measured.shape) and more.shape == (24, *rec.measured.shape)
    assert not smooth_structure(r24, noise_modes=more)[2]
    assert all(t["cross"] < 0.05 for t in smooth_structure(r24, noise_modes=more)[0])


def test_scale_weighs_the_renders_own_noise():
    """Weights 1 / var_data trust a noisy render's pixels as exact and pull the scale low
    (fireflies in the regressor); with the render's variance in the weights it is close."""
    toy, rec = _firefly_recording(0)
    renders = render_stack(toy, {"toy.w": 1.0}, rec, spp=256, seed=7, repeats=6)
    mean, mvar = renders.mean(axis=0), smoothed_variance(renders) / 6
    var = recording_variance(rec)
    assert best_scale(rec.measured, var, mean) / 1e4 < 0.95
    assert best_scale(rec.measured, var, mean, mvar) / 1e4 == pytest.approx(1.0, abs=0.04)


def test_refits_hold_the_full_well_radiance_and_price_the_compression_alone():
    """Above the brightest pixel W only rescales the compression; below it, it clips every
    pixel into a second scale. Refits free the compression alone and BIC prices one parameter."""
    m = make_model(["sensor_nonlinearity"])
    free = _free_names(m, ["sensor_nonlinearity"])
    assert "sensor_nonlinearity.compression" in free
    assert "sensor_nonlinearity.full_well_radiance" not in free
    assert _bic_penalty("sensor_nonlinearity", 1000) == pytest.approx(math.log(1000))
    assert _bic_penalty("lens_blur", 1000) == pytest.approx(2 * math.log(1000))


def test_round_choice_ranks_by_the_independently_rendered_gain():
    """Of candidates that passed every test, the one with the larger BIC gain on the
    independently rendered training chi^2 joins the model, not the one whose fixed-seed
    refit gained more (figures of the 256-px synthetic halo session at 2048 spp: the glare
    tail fitted its render's noise). Where the independent tests do not decide (the second
    pass) the refits' gain ranks; entries without the independent figure fall back to it."""
    halo = {"effect": "beam_halo", "delta_bic": 93.5, "delta_bic_independent": 70.4}
    glare = {"effect": "lens_blur", "delta_bic": 229.0, "delta_bic_independent": -1.6}
    assert _choose([glare, halo]) == "beam_halo"
    assert _choose([halo, glare]) == "beam_halo"
    assert _choose([glare, halo], independent=False) == "lens_blur"
    assert _choose([]) is None
    old = {"effect": "stray_light", "delta_bic": 120.0}
    assert _rank_key(old) == 120.0
    assert _choose([old, halo]) == "stray_light"


@pytest.mark.parametrize("log10_p, explained, refitted",
                         [(-9.6, 5.2, True), (-2.5, 1.01, True), (-1.5, 1.01, False), (-5.0, 0.3, True)])
def test_unexplained_verdict_says_whether_the_best_candidate_was_refitted(log10_p, explained, refitted):
    """When nothing is named, the verdict says what the best-screened candidate could remove
    by its score test, never "only 100 %" (as it said of the sensor compression on the 256-px
    filter_bandwidth-2 session, session 42), and whether it was refitted at all: a first
    round refits candidates down to p < RUNNER_UP_P (`runner_ups`), none above."""
    from estimate.diagnose import RUNNER_UP_LOG10_P, _verdict
    from estimate.screening import CandidateScore

    best = CandidateScore("filter_bandwidth", 8.5, 1, 10 ** log10_p, log10_p, explained)
    before = SimpleNamespace(residuals=SimpleNamespace(
        noise_scale=np.array([1.0]), significant=True, extra={}, p_value_smooth=1e-9, reduced_chi2_adjusted=1.1,
        reduced_chi2=1.1, dof=100))
    verdict = _verdict(before, {"summary": "spread over all angles"}, [best], [], None)
    assert "only 100%" not in verdict and verdict.endswith("no cause is named")
    assert ("all of the excess" in verdict) is (explained >= 1.0)
    assert ("its refit did not confirm it" in verdict) is refitted
    assert ("so none was refitted" in verdict) is (not refitted)
    assert (log10_p < RUNNER_UP_LOG10_P) is refitted


def test_runner_ups_are_the_next_candidates_down_to_their_level():
    """A first round whose leading refits are all turned away refits the next candidates
    whose score test has p < RUNNER_UP_P: the flagged ones that MAX_CONFIRM cut off first,
    then those above the screening's Bonferroni threshold (the 256-px filter_bandwidth-2
    session: the spread at p 0.003 behind a sensor compression whose refit failed)."""
    from estimate.diagnose import RUNNER_UP_P, SCREEN_LOG10_P, runner_ups
    from estimate.screening import CandidateScore

    def cs(name, log10_p):
        return CandidateScore(name, 10.0, 1, 10 ** log10_p, log10_p, 0.5)

    scores = [cs("lens_blur", -4.8), cs("beam_halo", -4.4), cs("sensor_nonlinearity", -4.1),
              cs("filter_bandwidth", -2.5), cs("stray_light", -1.2)]
    assert scores[2].log10_p < SCREEN_LOG10_P < scores[3].log10_p < math.log10(RUNNER_UP_P) < scores[4].log10_p
    got = runner_ups(scores, scores[:2], max_confirm=2)
    assert [c.name for c in got] == ["sensor_nonlinearity", "filter_bandwidth"]
    assert [c.name for c in runner_ups(scores, scores[:2], max_confirm=1)] == ["sensor_nonlinearity"]
    # nothing flagged at all: the runner-ups are the best ones down to RUNNER_UP_P
    assert [c.name for c in runner_ups(scores[3:], [], max_confirm=2)] == ["filter_bandwidth"]
    assert runner_ups(scores[4:], [], max_confirm=2) == []


def test_a_first_round_that_confirms_nothing_refits_the_runner_up(monkeypatch):
    """The screening ranks a glare tail first (forced here) on a recording with stray light;
    the tail's refit is turned away, and the stray light, screened at p 0.005 (above the
    Bonferroni threshold, below RUNNER_UP_P), is refitted as the runner-up and named."""
    import estimate.diagnose as dg

    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    real_screen = dg._screen

    def ranked(*a, **k):
        scores = {c.name: c for c in real_screen(*a, **k)}
        return [dataclasses.replace(scores["lens_blur"], p_value=1e-6, log10_p=-6.0),
                dataclasses.replace(scores["stray_light"], p_value=0.005, log10_p=math.log10(0.005))]

    monkeypatch.setattr(dg, "_screen", ranked)
    d = diagnose_channel(pb, BaseFit(dict(TRUE), 1e4, "hg"), make_model, candidates=["lens_blur", "stray_light"],
                         spp=128, repeats=3, iterations=8, final_fit_follows=True, max_confirm=1, max_effects=1)
    by = {e["effect"]: e for e in d.confirmations}
    assert not by["lens_blur"]["confirmed"] and not by["lens_blur"].get("runner_up")
    assert by["stray_light"]["runner_up"] and by["stray_light"]["confirmed"]
    assert d.confirmed == ["stray_light"]
    from estimate.diagnose import summary_text

    text = summary_text({"channels": {"g": d.as_dict()}, "run_id": "x", "refit_run": None})
    assert "runner-up (no leading candidate confirmed): refit with stray_light" in text


def test_a_first_round_that_confirms_nothing_tries_the_closest_candidate_in_a_pair(monkeypatch):
    """An angle offset (10 deg) and a thickness error (30 %) together. With the entry bar
    raised between the offset's gain alone (dBIC 143) and the pair's (194), no single refit
    is confirmed; the offset passed every other test, so the thickness error, flagged by the
    screening at its refit, is refitted with it, and the pair is named together. With one
    effect left to add (`max_effects` 1) no pair is tried and nothing is named. The
    offset's refit is a close call there; its closer look (which at 4 x the spp confirms
    the offset alone) is switched off, so that the pair round is what is tested here."""
    import estimate.diagnose as dg

    monkeypatch.setattr(dg, "BIC_STRONG", 160.0)
    monkeypatch.setattr(dg, "_close_call", lambda entry: False)
    rec = record({"angle_offset.delta_deg": 10.0, "thickness_error.e": 0.3})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    how = {"candidates": ["angle_offset", "thickness_error"], "spp": 128, "repeats": 3, "iterations": 8,
           "final_fit_follows": True, "max_confirm": 1}
    one = diagnose_channel(pb, BaseFit(dict(TRUE), 1e4, "hg"), make_model, max_effects=1, **how)
    assert not any("effects" in e for e in one.confirmations) and one.confirmed == []
    # the same first round, taken from the first diagnosis
    d = diagnose_channel(pb, BaseFit(dict(TRUE), 1e4, "hg"), make_model, reuse=one.first_round, **how)
    by = {e["effect"]: e for e in d.confirmations}
    alone = by["angle_offset"]
    assert not alone["confirmed"] and 0 < alone["delta_bic"] < 160.0
    pair = by["angle_offset+thickness_error"]
    assert pair["confirmed"] and pair["effects"] == ["angle_offset", "thickness_error"]
    assert pair["delta_bic"] > 160.0 and min(pair["magnitude_sigma_by_effect"].values()) > dg.MAGNITUDE_SIGMA
    assert pair["pair"]["lead"] == "angle_offset"
    assert d.confirmed == ["angle_offset", "thickness_error"]
    # both magnitudes in the joint model, on the side of the truth
    assert pair["parameters"]["angle_offset.delta_deg"] > 5.0 and pair["parameters"]["thickness_error.e"] > 0.1
    from estimate.diagnose import summary_text

    text = summary_text({"channels": {"g": d.as_dict()}, "run_id": "x", "refit_run": None})
    assert "pair (no candidate confirmed alone; angle_offset came closest" in text
    assert "refit with angle_offset and thickness_error together" in text


@pytest.mark.parametrize("change, leads", [
    ({}, False),                                              # confirmed alone: no pair round
    ({"delta_bic": 6.0}, True),                                # short of the BIC bar only
    ({"heldout_ok": False}, True),                             # fails the held-out angles only
    ({"delta_bic": 6.0, "heldout_ok": False}, False),          # short of the bar and fails held-out
    ({"heldout_ok": False, "no_harm": False}, False),          # does harm too
    ({"heldout_ok": False, "magnitude_sigma": 1.0}, False),    # cannot be told from absent
    ({"delta_bic": -4.0}, False),                              # no gain at all
    ({"heldout_ok": False, "effects": ["a", "b"]}, False),     # a pair leads no pair
])
def test_a_pair_is_led_by_a_refit_that_failed_one_test_a_partner_would_explain(change, leads):
    """`try_pair`'s lead: a single refit that passed everything but the BIC bar, or
    everything but the held-out angles (on the 40-px light-engine angle offset + thickness
    session the offset alone gained dBIC 33 and worsened the held-out chi^2 86.6 -> 100.9;
    the pair it led was named, 1.42 -> 0.95)."""
    import estimate.diagnose as dg

    entry = {"delta_bic": dg.BIC_STRONG + 20.0, "magnitude_sigma": dg.MAGNITUDE_SIGMA + 2.0, "no_harm": True,
             "heldout_ok": True, **change}
    assert dg._pair_lead(entry) is leads


def test_a_close_call_is_decided_again_at_more_samples_per_pixel(monkeypatch):
    """An angle offset (3 deg) diagnosed at 64 spp: its refit gains dBIC 23 on weights that
    hold the 64-spp renders' noise, its independently rendered training chi^2 gains 330.
    With the entry bar between those, the refit is a close call: the control and the
    candidate are refitted at 4 x the spp (dBIC 115), which decides. With the bar above
    the closer look's gain too, the first refit's entry stays and nothing is named."""
    import estimate.diagnose as dg

    rec = record({"angle_offset.delta_deg": 3.0})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    how = {"candidates": ["angle_offset"], "spp": 64, "repeats": 3, "iterations": 8, "final_fit_follows": True,
           "max_confirm": 1, "max_effects": 1}
    monkeypatch.setattr(dg, "BIC_STRONG", 50.0)
    d = diagnose_channel(pb, BaseFit(dict(TRUE), 1e4, "hg"), make_model, **how)
    (e,) = d.confirmations
    cc = e["close_call"]
    assert 0 < cc["delta_bic_first"] <= 50.0 and cc["spp_first"] == 64 and cc["spp"] == 64 * dg.CLOSE_CALL_SPP_FACTOR
    assert cc["passed"] and e["confirmed"] and e["delta_bic"] == cc["delta_bic"] > 50.0
    assert d.confirmed == ["angle_offset"]
    assert 1.5 < e["parameters"]["angle_offset.delta_deg"] < 4.5
    from estimate.diagnose import summary_text

    text = summary_text({"channels": {"g": d.as_dict()}, "run_id": "x", "refit_run": None})
    assert "a close call at 64 spp" in text and "which decides" in text
    # The bar above the closer look's gain as well: still short, the first refit's entry kept.
    monkeypatch.setattr(dg, "BIC_STRONG", cc["delta_bic"] + 1.0)
    d2 = diagnose_channel(pb, BaseFit(dict(TRUE), 1e4, "hg"), make_model, **how)
    (e2,) = d2.confirmations
    assert e2["delta_bic"] == pytest.approx(cc["delta_bic_first"])
    assert not e2["close_call"]["passed"] and not e2["confirmed"] and d2.confirmed == []
    assert "still short" in summary_text({"channels": {"g": d2.as_dict()}, "run_id": "x", "refit_run": None})
    # Far from the bar (or failing another test) there is no closer look.
    assert not dg._close_call({**e2, "delta_bic": -3.0}) and not dg._close_call({**e2, "no_harm": False})
    assert not dg._close_call({**e2, "delta_bic_independent": 0.5 * dg.BIC_STRONG})


def test_a_mismatch_outside_the_catalogue_names_no_cause():
    """The recording's phase function has two lobes (forward g 0.6, backward g -0.4, forward
    weight 0.8) and the fit one: a significant mismatch that no catalogue effect is. The
    candidates' refits may gain on BIC (a stray-light glow stands in for the back lobe) but
    do not predict the held-out angles, so nothing is named and the verdict says so."""
    truth = {"sigma_t": 2.0, "albedo": 0.9, "phase.g_forward": 0.6, "phase.g_backward": -0.4, "phase.w_forward": 0.8}
    world = ForwardModel(GEOMETRY, BEAM, phase="tthg")
    renders = np.stack([world.render_profiles(truth, ANGLES, spp=4096, seed=50 + k) for k in range(4)])
    signal = 1e4 * renders.mean(axis=0)
    var = signal / 5.0 + (1e-3 * signal.max()) ** 2 + 1e8 * smoothed_variance(renders) / 4
    meas = signal + np.random.default_rng(3).normal(size=signal.shape) * np.sqrt(var)
    x = np.asarray(GEOMETRY.pixel_x_mm(GEOMETRY.profile_window()))
    pb = FittableRecording(ANGLES, x, meas, var, GEOMETRY, BEAM, valid=np.ones(meas.shape, bool))
    hg = make_model([])
    fit = refit(hg, pb, dict(TRUE), _free_names(hg, []), spp=512, seed=7, iterations=30, uncertainties=False)
    d = diagnose_channel(pb, BaseFit(dict(fit.parameters), fit.scale, "hg"), make_model, spp=128, repeats=3,
                         iterations=8, final_fit_follows=True)
    assert d.before.residuals.significant
    assert d.confirmations, "the candidates were refitted"
    assert d.confirmed == [] and not any(e["confirmed"] for e in d.confirmations)
    assert "no candidate in the catalogue explains it" in d.verdict and "no cause is named" in d.verdict


@pytest.mark.parametrize("bar, rounds", [(None, 1), (0.0, 2)])
def test_no_second_effect_is_looked_for_once_the_first_explains_the_mismatch(monkeypatch, bar, rounds):
    """A strong stray light, alone: its model, at the decorrelated step from its joint refit,
    fits at the noise floor, so no second round screens at it (`EXPLAINED_REDUCED_CHI2`), and
    the record and the summary say why. With the bar at 0 the second round screens the
    remaining candidate at the new fit."""
    import estimate.diagnose as dg
    from estimate.diagnose import EXPLAINED_REDUCED_CHI2, summary_text

    if bar is not None:
        monkeypatch.setattr(dg, "EXPLAINED_REDUCED_CHI2", bar)
    screened: list[list[str]] = []
    real_screen = dg._screen

    def counting_screen(problem, ev, exts, make, cands, **kw):
        screened.append(list(cands))
        return real_screen(problem, ev, exts, make, cands, **kw)

    monkeypatch.setattr(dg, "_screen", counting_screen)
    rec = record({"stray_light.offset": 0.01})
    pb = FittableRecording(**vars(rec), valid=np.ones(rec.measured.shape, bool))
    d = diagnose_channel(pb, BaseFit(dict(TRUE), 1e4, "hg"), make_model, candidates=["stray_light", "angle_offset"],
                         spp=128, repeats=3, iterations=8, final_fit_follows=False)
    assert d.confirmed_order[0] == "stray_light"
    assert len(screened) == rounds, screened
    doc = d.as_dict()
    text = summary_text({"channels": {"g": doc}, "run_id": "x", "refit_run": None})
    if bar is None:
        (end,) = doc["explained_checks"]
        assert end["after"] == ["stray_light"] and end["bar"] == EXPLAINED_REDUCED_CHI2 and end["explained"]
        assert end["reduced_chi2_adjusted"] <= EXPLAINED_REDUCED_CHI2
        assert end["reduced_chi2_adjusted_optimum"] > 0 and end["sigma_t_optimum"] > 0 and end["sigma_t_step"] > 0
        assert f"{end['reduced_chi2_adjusted_optimum']:.3f} at the refit's own optimum" in text
        assert not any(e["round"] == 2 for e in d.confirmations)
        assert "explained, no second effect looked for" in text
    else:
        assert screened[1] == ["angle_offset"]
        (chk,) = doc["explained_checks"]
        assert not chk["explained"] and chk["bar"] == 0.0
        assert "a second effect looked for" in text and "no second effect looked for" not in text


@pytest.mark.parametrize("final_chi2, lm_chi2, reported", [
    (1.44, 1.13, "refit"), (1.17, 1.13, "refit"), (1.15, 1.13, "final fit"), (0.99, 0.95, "final fit")])
def test_a_final_fit_that_stops_short_of_the_refit_leaves_the_refit_reported_and_names_as_it_needs(
        monkeypatch, final_chi2, lm_chi2, reported):
    """The bench's 3 % halo (session 65): the estimator's final fit, started at the LM refit,
    ended at reduced chi^2 1.44 at the floor where the refit had 1.13. Both are the same
    model rendered at the same seeds, so the refit is reported (`REFIT_PREFERRED_MARGIN`, 3 %:
    1.17 against 1.13 too); the effect named is the one the final fit's own check keeps.
    Within the margin, or at the noise floor (0.99 against 0.95: no fit stopped short there),
    the final fit is reported as before."""
    import estimate.diagnose as dg
    from estimate.diagnose import ChannelDiagnosis, refine_channel, summary_text

    _fake_final_fit(monkeypatch, 2000.0, {"beam_halo": ("beam_halo.fraction", 0.0, 4000.0)})
    fake_evaluate = dg.evaluate

    def evaluate(model, params, problem, n_params, **kw):   # the final fit is the one at sigma_t 2.01
        ev = fake_evaluate(model, params, problem, n_params, **kw)
        ev.residuals.reduced_chi2_adjusted = final_chi2 if params.get("sigma_t") == 2.01 else 1.0
        ev.residuals.reduced_chi2 = ev.residuals.reduced_chi2_adjusted
        ev.residuals.significant, ev.residuals.summary = False, lambda: {}
        ev.parameters, ev.extensions, ev.scale = dict(params), ["beam_halo"], 1.0
        return ev

    final = {"sigma_t": 2.01, "albedo": 0.951, "beam_halo.fraction": 0.027, "beam_halo.sigma_mm": 0.9}
    monkeypatch.setattr(dg, "evaluate", evaluate)
    monkeypatch.setattr(dg, "render_stack", lambda *a, **k: None)
    monkeypatch.setattr(dg, "fit_channel", lambda *a, **k: SimpleNamespace(
        parameters=dict(final), iterations=10, stop_reason="cap", drifting=[], loss=1.0, reduced_chi2=final_chi2,
        free=list(final), uncertainties={k: 0.001 for k in final}, covariance={k: {k: 1e-6} for k in final}))
    params = {"sigma_t": 2.001, "albedo": 0.949, "beam_halo.fraction": 0.029, "beam_halo.sigma_mm": 1.005}
    unc = {k: 0.002 for k in params}
    res = SimpleNamespace(noise_scale=np.array([1.0]), significant=True, extra={}, p_value_smooth=1e-9,
                          reduced_chi2_adjusted=12.2, reduced_chi2=22.0, dof=100, summary=lambda: {})
    before = SimpleNamespace(residuals=res, parameters={"sigma_t": 2.06}, scale=1.0)
    lm = SimpleNamespace(extensions=["beam_halo"], parameters=params, scale=1.0,
                         residuals=SimpleNamespace(reduced_chi2_adjusted=lm_chi2, reduced_chi2=1.5, significant=False,
                                                   summary=lambda: {}))
    region = {"reduced_chi2_adjusted": 1.0}
    loc = {"summary": "at the peak", **{k: region for k in ("front", "back", "grazing", "normal", "peak", "tails")},
           "asymmetry": {"difference_sigma": 0.0}}
    d = ChannelDiagnosis("g", before, loc, [], [], ["beam_halo"], lm, dict(unc), "", 1.0,
                         ["sigma_t"], covariance_after={a: {b: (unc[a] ** 2 if a == b else 0.0) for b in unc}
                                                        for a in unc}, model_stage="deferred")
    model = SimpleNamespace(parameter_names=list(params), phase="exp3")
    d_second_pass = copy.deepcopy(d)
    fr = refine_channel(None, d, lambda exts: model, FitSettings(scale="free"))
    assert d.final_fit["kept"] and d.confirmed == ["beam_halo"]
    assert [(e["stage"], e["dropped"]) for e in d.pruned] == [("final fit", False)]
    if reported == "refit":
        assert fr is None and d.after is lm and d.lm_after is None
        assert d.final_fit["reported"] == "refit" and d.uncertainties_after == unc
        assert f"{final_chi2:.3g}" in d.final_fit["reason"] and f"{lm_chi2:.3g}" in d.final_fit["reason"]
    else:
        assert fr is not None and d.after is not lm and d.lm_after is lm and "reported" not in d.final_fit
        assert d.uncertainties_after["sigma_t"] == 0.001
    doc = d.as_dict()
    assert doc["material_after"]["sigma_t"] == (2.001 if reported == "refit" else 2.01)
    text = summary_text({"channels": {"g": doc}, "run_id": "x", "refit_run": None})
    assert ("the refit is reported" in text) is (reported == "refit")
    # The second pass weighs final fits against each other: there the final fit stands.
    fr2 = refine_channel(None, d_second_pass, lambda exts: model, FitSettings(scale="free"), prefer_refit=False)
    assert fr2 is not None and d_second_pass.after is not lm and "reported" not in d_second_pass.final_fit
