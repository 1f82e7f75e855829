"""Phase functions: exponential (any degree, both bases), HG, two-term HG, polynomial."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy import integrate, stats

from estimate.errors import ModelParameterError
from estimate.phase_exponential import (
    ExponentialPhase,
    check_degree,
    legendre_to_monomial,
    log_norm,
    log_norm_and_grad,
    monomial_to_legendre,
)
from estimate.phase_hg import HenyeyGreenstein, TwoTermHG
from estimate.phase_polynomial import IsotropicPhase, PolynomialPhase


def _reference_integral(b: np.ndarray, b0: float) -> float:
    """2 pi int exp(b0 + sum b_i mu^i) dmu by adaptive quadrature on many sub-intervals."""
    full = np.concatenate([[b0], b])
    f = lambda m: math.exp(np.polynomial.polynomial.polyval(m, full))
    edges = np.linspace(-1, 1, 801)
    total = sum(integrate.quad(f, a, c, epsabs=0, epsrel=1e-12, limit=200)[0] for a, c in itertools.pairwise(edges))
    return 2 * math.pi * total


def _vmf_log_norm(kappa: float) -> float:
    # p = kappa / (4 pi sinh kappa) exp(kappa mu) under 2 pi int p dmu = 1 (the paper's
    # kappa/(2 pi sinh kappa) integrates to 2 under its own normalisation)
    log_sinh = kappa + math.log1p(-math.exp(-2 * kappa)) - math.log(2)
    return math.log(kappa) - math.log(4 * math.pi) - log_sinh


@pytest.mark.parametrize("kappa", [1e-3, 0.7, 5.0, 50.0, 150.0, 300.0, 800.0])
def test_degree_one_is_von_mises_fisher(kappa: float) -> None:
    e = ExponentialPhase.von_mises_fisher(kappa)
    assert e.b0 == pytest.approx(_vmf_log_norm(kappa), abs=1e-9)
    mu = np.linspace(-1, 1, 11)
    np.testing.assert_allclose(e.log_eval(mu), _vmf_log_norm(kappa) + kappa * mu, atol=1e-9)
    # vMF mean cosine coth(kappa) - 1/kappa
    assert e.g == pytest.approx(1 / math.tanh(kappa) - 1 / kappa, abs=1e-9)


def test_degree_zero_is_isotropic() -> None:
    for e in (ExponentialPhase.isotropic(), ExponentialPhase.zeros(4), ExponentialPhase([0.0, 0.0], "legendre")):
        np.testing.assert_allclose(e.eval(np.linspace(-1, 1, 7)), 1 / (4 * math.pi), rtol=1e-12)
        assert e.g == pytest.approx(0.0, abs=1e-12)
    assert IsotropicPhase().eval(0.3) == pytest.approx(1 / (4 * math.pi))


@pytest.mark.parametrize("seed", range(6))
def test_normalisation_peaked_high_degree(seed: int) -> None:
    rng = np.random.default_rng(seed)
    b = rng.normal(0, 1, 7) * np.array([300, 60, 40, 30, 20, 10, 5])
    b[0] = abs(b[0]) + 100           # b_1 in the hundreds: a sharp forward lobe
    b0 = log_norm(b)
    assert _reference_integral(b, b0) == pytest.approx(1.0, rel=1e-6)


def test_normalisation_interior_peak_and_backward() -> None:
    for b in ([-400.0], [0.0, 250.0], [20.0, -300.0], [5.0, 0.0, -200.0, 0.0, 150.0]):
        b = np.array(b)
        assert _reference_integral(b, log_norm(b)) == pytest.approx(1.0, rel=1e-6)


def test_gradient_of_log_norm_matches_finite_differences() -> None:
    c = np.array([120.0, -15.0, 4.0])
    for basis in ("monomial", "legendre"):
        _, grad = log_norm_and_grad(c, basis)
        h = 1e-5
        fd = [(log_norm(c + h * np.eye(3)[i], basis) - log_norm(c - h * np.eye(3)[i], basis)) / (2 * h)
              for i in range(3)]
        np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-8)


def test_legendre_monomial_round_trip() -> None:
    rng = np.random.default_rng(3)
    for m in range(9):
        b = rng.normal(size=m + 1)
        np.testing.assert_allclose(legendre_to_monomial(monomial_to_legendre(b)), b, atol=1e-12)
        mu = np.linspace(-1, 1, 9)
        np.testing.assert_allclose(np.polynomial.legendre.legval(mu, monomial_to_legendre(b)),
                                   np.polynomial.polynomial.polyval(mu, b), atol=1e-12)
    e = ExponentialPhase([30.0, -4.0, 2.0, 1.0], "monomial")
    el = e.to_basis("legendre")
    mu = np.linspace(-1, 1, 21)
    np.testing.assert_allclose(el.log_eval(mu), e.log_eval(mu), atol=1e-10)
    assert el.b0 == pytest.approx(el.full_coeffs("legendre")[0])
    np.testing.assert_allclose(el.to_basis("monomial").full_coeffs(), e.full_coeffs(), atol=1e-9)


def _chi2_pvalue(mu: np.ndarray, cdf, bins: int = 40) -> float:
    edges = np.linspace(-1, 1, bins + 1)
    counts, _ = np.histogram(mu, edges)
    expected = mu.size * np.diff(cdf(edges))
    keep = expected > 5
    return float(stats.chisquare(counts[keep], expected[keep] * counts[keep].sum() / expected[keep].sum()).pvalue)


def test_exponential_sampling_chi_square() -> None:
    rng = np.random.default_rng(11)
    e = ExponentialPhase([2.0, 1.5, -1.0])
    mu, pdf = e.sample(rng.random(40000))
    np.testing.assert_allclose(pdf, e.eval(mu))

    def cdf(x: np.ndarray) -> np.ndarray:
        return np.array([2 * math.pi * integrate.quad(lambda m: float(e.eval(m)), -1, xi, epsabs=1e-13)[0]
                         for xi in x])

    assert _chi2_pvalue(mu, cdf) > 1e-3


def test_exponential_sampling_peaked_and_directions() -> None:
    rng = np.random.default_rng(5)
    e = ExponentialPhase([300.0])
    u = rng.random(20000)
    mu = e.sample_mu(u)
    # vMF inverse CDF in closed form: mu = 1 + log(u + (1-u) exp(-2 kappa)) / kappa
    np.testing.assert_allclose(mu, 1 + np.log(u + (1 - u) * math.exp(-600)) / 300, atol=1e-10)
    d, _ = e.sample_directions(rng.random(100), rng.random(100), axis=(1.0, 0.0, 0.0))
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert np.all(d[:, 0] > 0.9)
    with pytest.raises(ModelParameterError):
        e.sample_mu([1.5])


def test_exponential_parameter_checks() -> None:
    with pytest.raises(ModelParameterError, match="b_2"):
        ExponentialPhase([1.0, float("nan")])
    with pytest.raises(ModelParameterError, match="b_1"):
        log_norm([float("inf")])
    with pytest.raises(ModelParameterError, match="degree"):
        ExponentialPhase.zeros(-1)
    with pytest.raises(ModelParameterError, match="degree"):
        check_degree(-3)
    with pytest.raises(ModelParameterError, match="basis"):
        ExponentialPhase([1.0], "chebyshev")  # type: ignore[arg-type]


def test_hg_normalised_g_and_sampling() -> None:
    rng = np.random.default_rng(2)
    for g in (-0.7, 0.0, 0.5, 0.95):
        h = HenyeyGreenstein(g)
        norm = 2 * math.pi * integrate.quad(lambda m, h=h: float(h.eval(m)), -1, 1, points=[1.0], limit=200)[0]
        assert norm == pytest.approx(1.0, rel=1e-8)
        mean = 2 * math.pi * integrate.quad(lambda m, h=h: m * float(h.eval(m)), -1, 1, limit=200)[0]
        assert mean == pytest.approx(g, abs=1e-8)
        mu, pdf = h.sample(rng.random(30000))
        np.testing.assert_allclose(pdf, h.eval(mu))

        def cdf(x: np.ndarray, g: float = g) -> np.ndarray:
            if g == 0:
                return (x + 1) / 2
            return (1 - g * g) / (2 * g) * (1 / np.sqrt(1 + g * g - 2 * g * x) - 1 / (1 + g))

        assert _chi2_pvalue(mu, cdf) > 1e-3
    with pytest.raises(ModelParameterError, match="g"):
        HenyeyGreenstein(1.0)


def test_two_term_hg() -> None:
    t = TwoTermHG(0.9, -0.4, 0.8)
    assert t.asymmetry == pytest.approx(0.8 * 0.9 + 0.2 * -0.4)
    norm = 2 * math.pi * integrate.quad(lambda m: float(t.eval(m)), -1, 1, limit=200)[0]
    assert norm == pytest.approx(1.0, rel=1e-8)
    mu = np.linspace(-1, 1, 9)
    np.testing.assert_allclose(np.exp(t.log_eval(mu)), t.eval(mu), rtol=1e-12)
    rng = np.random.default_rng(4)
    s, pdf = t.sample(rng.random(40000), rng.random(40000))
    assert s.mean() == pytest.approx(t.asymmetry, abs=0.01)
    np.testing.assert_allclose(pdf, t.eval(s))

    def cdf(x: np.ndarray) -> np.ndarray:
        return np.array([2 * math.pi * integrate.quad(lambda m: float(t.eval(m)), -1, xi, limit=200)[0] for xi in x])

    assert _chi2_pvalue(t.sample_mu(rng.random(40000)), cdf) > 1e-3
    assert _chi2_pvalue(s, cdf) > 1e-3
    # w = 1 is plain HG
    np.testing.assert_allclose(TwoTermHG(0.6, -0.3, 1.0).eval(mu), HenyeyGreenstein(0.6).eval(mu))
    for bad in ({"w": 1.2}, {"w": float("nan")}, {"g2": -1.0}):
        kw = {"g1": 0.5, "g2": -0.2, "w": 0.5, **bad}
        with pytest.raises(ModelParameterError, match=next(iter(bad))):
            TwoTermHG(**kw)


def test_polynomial_normalisation_positivity_and_g() -> None:
    p = PolynomialPhase([0.02, 0.03, 0.0])
    assert 2 * math.pi * integrate.quad(lambda m: float(p.eval(m)), -1, 1)[0] == pytest.approx(1.0, rel=1e-12)
    g = 2 * math.pi * integrate.quad(lambda m: m * float(p.eval(m)), -1, 1)[0]
    assert p.g == pytest.approx(g, rel=1e-12)
    assert p.is_positive()
    grid = np.linspace(-1, 1, 2001)
    # positive at both ends, negative in a dip around mu^2 = 0.58: the exact minimum
    # finds it, an end-point check would not
    dip = PolynomialPhase([0.0, -0.7, 0.0, 0.6])
    assert dip.eval(np.array([-1.0, 1.0])).min() > 0
    m, at = dip.min_value()
    assert m < 0 and 0.7 < abs(at) < 0.8
    assert m == pytest.approx(dip.eval(grid).min(), abs=1e-6)
    assert not dip.is_positive() and not dip.is_positive(grid)
    assert dip.is_positive(np.array([-1.0, 0.0, 1.0]))
    with pytest.raises(ModelParameterError, match="a_2"):
        PolynomialPhase([0.1, float("nan")])
