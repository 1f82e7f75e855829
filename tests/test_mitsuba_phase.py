"""The exponential phase function as a Mitsuba plugin (estimate.mitsuba_phase), and the
two-term HG baseline from built-in lobes, against the numpy phase functions."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from estimate.errors import ModelParameterError
from estimate.mitsuba_env import init_mitsuba
from estimate.mitsuba_phase import exp_phase_dict, inverse_cdf_table, tthg_phase_dict
from estimate.phase_exponential import ExponentialPhase
from estimate.phase_hg import TwoTermHG

mi = init_mitsuba("llvm_ad_mono")
import drjit as dr

CASES = [[], [2.0], [1.5, 0.5, 0.2], [0.0, 0.68], [-1.0, 2.0, -0.5, 1.0, 0.3], [300.0]]


def _mei(wi: np.ndarray):
    n = wi.shape[0]
    mei = dr.zeros(mi.MediumInteraction3f, n)
    mei.wi = mi.Vector3f(wi[:, 0], wi[:, 1], wi[:, 2])
    return mei


def _eval(phase, wi: np.ndarray, wo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ctx = mi.PhaseFunctionContext(None)
    val, pdf = phase.eval_pdf(ctx, _mei(wi), mi.Vector3f(wo[:, 0], wo[:, 1], wo[:, 2]))
    return np.array(val).ravel(), np.array(pdf).ravel()


def _mu_grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Scattering cosines crowded at +-1 and the incident/outgoing directions giving them."""
    theta = np.linspace(0.0, math.pi, n)
    mu = np.cos(theta)
    wi = np.tile([0.0, 0.0, -1.0], (n, 1))  # light travels along +z
    wo = np.stack([np.sin(theta), np.zeros(n), mu], axis=1)
    return mu, np.stack([wi, wo])


@pytest.mark.parametrize("b", CASES)
def test_eval_matches_numpy_and_is_normalised(b: list[float]) -> None:
    phase = mi.load_dict(exp_phase_dict(b))
    mu, (wi, wo) = _mu_grid(4001)
    val, _ = _eval(phase, wi, wo)
    ref = ExponentialPhase(b).eval(mu)
    assert np.allclose(val, ref, rtol=2e-4, atol=1e-30)
    # 2 pi int p dmu = 1 by Simpson in theta (independent of the plugin's own quadrature)
    theta = np.arccos(np.clip(mu, -1, 1))
    integral = 2 * math.pi * np.trapezoid(val * np.sin(theta), theta)
    assert integral == pytest.approx(1.0, abs=2e-4)
    assert phase.b0 == pytest.approx(ExponentialPhase(b).b0, abs=2e-5)


def test_scattering_cosine_convention() -> None:
    """mu = +1 is straight on: with wi pointing back to the light, wo = -wi is forward."""
    phase = mi.load_dict(exp_phase_dict([5.0]))
    wi = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    wo = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    val, _ = _eval(phase, wi, wo)
    assert val[0] > 1000 * val[1]


def _sample(phase, n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    # random incident directions
    v = rng.normal(size=(n, 3))
    wi = v / np.linalg.norm(v, axis=1, keepdims=True)
    u = rng.random((n, 3))
    ctx = mi.PhaseFunctionContext(None)
    wo, w, pdf = phase.sample(ctx, _mei(wi), mi.Float(u[:, 0]), mi.Point2f(u[:, 1], u[:, 2]))
    wo = np.stack([np.array(wo.x), np.array(wo.y), np.array(wo.z)], axis=1)
    mu = -(wo * wi).sum(axis=1)
    return mu, np.array(w).ravel(), np.array(pdf).ravel()


@pytest.mark.parametrize("b", [[1.5, 0.5, 0.2], [-1.0, 2.0, -0.5, 1.0, 0.3], [30.0]])
def test_sampled_directions_follow_reported_pdf_chi2(b: list[float]) -> None:
    phase = mi.load_dict(exp_phase_dict(b))
    n = 200_000
    mu, w, pdf = _sample(phase, n, seed=1)
    assert np.all(np.isfinite(w)) and np.all(pdf > 0)
    # weight = exact / pdf
    assert np.allclose(w * pdf, ExponentialPhase(b).eval(mu), rtol=2e-3)
    # The density of the samples in mu is the tabulated piecewise-constant one:
    # bin edges at table nodes, expected counts from the table's equal probabilities.
    table = inverse_cdf_table(b)
    k = table.size - 1
    edges = table[:: k // 64]
    counts, _ = np.histogram(mu, bins=edges)
    expected = np.full(counts.size, n / counts.size)
    chi2 = ((counts - expected) ** 2 / expected).sum()
    p_value = stats.chi2.sf(chi2, counts.size - 1)
    assert p_value > 1e-3


@pytest.mark.parametrize("b", [[1.5, 0.5, 0.2], [-2.0, 3.0], [100.0]])
def test_importance_weights_are_unbiased(b: list[float]) -> None:
    phase = mi.load_dict(exp_phase_dict(b))
    mu, w, _ = _sample(phase, 400_000, seed=2)
    ref = ExponentialPhase(b)
    # E[w] = int p = 1 and E[w mu] = g
    se = w.std() / math.sqrt(w.size)
    assert abs(w.mean() - 1.0) < 4 * se + 1e-4
    assert abs((w * mu).mean() - ref.g) < 4 * (w * mu).std() / math.sqrt(w.size) + 1e-4


def test_gradient_includes_normalisation() -> None:
    """d log p(mu)/d b_i = mu^i - <mu^i>_p: the normalisation is part of the gradient."""
    b = [1.5, 0.5, 0.2]
    phase = mi.load_dict(exp_phase_dict(b))
    params = mi.traverse(phase)
    leaves = [mi.Float(v) for v in b]
    for i, leaf in enumerate(leaves, start=1):
        dr.enable_grad(leaf)
        params[f"b{i}"] = leaf
    params.update()
    mu0 = 0.3
    wi = np.array([[0.0, 0.0, -1.0]])
    wo = np.array([[math.sqrt(1 - mu0**2), 0.0, mu0]])
    ctx = mi.PhaseFunctionContext(None)
    val, _ = phase.eval_pdf(ctx, _mei(wi), mi.Vector3f(wo[:, 0], wo[:, 1], wo[:, 2]))
    dr.backward(dr.log(val[0]))
    ref = ExponentialPhase(b)
    x, w = np.polynomial.legendre.leggauss(200)
    pw = ref.eval(x) * w * 2 * math.pi
    for i, leaf in enumerate(leaves, start=1):
        expected = mu0**i - float((pw * x**i).sum())
        assert float(dr.grad(leaf)[0]) == pytest.approx(expected, abs=2e-4)


def test_tthg_blend_matches_numpy_two_term_hg() -> None:
    phase = mi.load_dict(tthg_phase_dict(0.8, -0.3, 0.85))
    mu, (wi, wo) = _mu_grid(721)
    val, _ = _eval(phase, wi, wo)
    assert np.allclose(val, TwoTermHG(0.8, -0.3, 0.85).eval(mu), rtol=1e-4)


def test_bad_coefficients_are_refused() -> None:
    with pytest.raises(ModelParameterError, match="b2"):
        exp_phase_dict([1.0, float("nan")])
    with pytest.raises(ModelParameterError, match="w_forward"):
        tthg_phase_dict(0.5, -0.2, 1.5)
