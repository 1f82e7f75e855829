"""The exponential phase function of any degree (section 3 of the paper).

    p(mu) = exp(sum_{i=0..M} b_i Q_i(mu)),   mu = cos(theta) in [-1, 1],

with theta the scattering angle (mu = +1: light goes straight on). ``Q_i`` is either the
paper's monomial basis ``Q_i = mu^i`` or the Legendre basis ``Q_i = P_i`` (better
conditioned for fitting). Both have ``Q_0 = 1``, but the value of ``b_0`` differs between
the bases for the same function, because P_2, P_4, ... have constant terms.
``b_0`` is not free: the normalisation over the sphere, ``2 pi int_{-1}^{1} p dmu = 1``,
fixes it (:func:`log_norm`). ``p`` is a density per steradian [1/sr].

Degree 0 is the isotropic phase function ``1/(4 pi)``; degree 1 is the von Mises-Fisher
phase function with ``kappa = b_1``, exp(b_0) = kappa / (4 pi sinh kappa) (the paper
prints 2 pi, which would integrate to 2 under its own normalisation).

The normalisation integral of a strongly peaked function (``b_1`` in the hundreds puts
almost all of the mass within ``1/b_1`` of ``mu = 1``) is computed as a log-sum-exp over
Gauss-Legendre panels graded geometrically towards every local maximum of the exponent
(the critical points of the polynomial and the ends of ``[-1, 1]``), so the relative error
stays ~1e-12 whatever the peak width between ~1e-12 and 2.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from functools import lru_cache
from typing import Literal

import numpy as np
from numpy.polynomial import legendre as _leg
from numpy.polynomial import polynomial as _poly

from estimate.errors import ModelParameterError

__all__ = [
    "Basis",
    "ExponentialPhase",
    "check_degree",
    "legendre_to_monomial",
    "log_norm",
    "log_norm_and_grad",
    "monomial_to_legendre",
    "quadrature_nodes",
    "sample_about_axis",
]

Basis = Literal["monomial", "legendre"]
_BASES = ("monomial", "legendre")

#: Gauss-Legendre nodes per panel.
_GL_NODES = 12
#: Ratio of successive panel widths towards a maximum; 0.35 keeps each panel's exponent
#: change bounded by about its own distance from the peak.
_GRADING = 0.35
#: Smallest panel, relative to the half-segment it grades (covers peaks down to ~1e-13).
_SMALLEST = 1e-13


def _check_basis(basis: str) -> None:
    if basis not in _BASES:
        raise ModelParameterError(f"basis must be one of {_BASES}, got {basis!r}")


def as_coefficients(coeffs: Sequence[float] | np.ndarray, name: str = "b") -> np.ndarray:
    """Coefficients name_1..name_M as a float array, checked finite (the error names the bad one).
    Shared by the phase-function families."""
    try:
        c = np.asarray(coeffs, dtype=float).reshape(-1)
    except (TypeError, ValueError) as e:
        raise ModelParameterError(f"{name}_1..{name}_M must be numbers: {e}") from None
    bad = np.flatnonzero(~np.isfinite(c))
    if bad.size:
        i = int(bad[0])
        raise ModelParameterError(f"{name}_{i + 1} is {c[i]!r}; coefficients must be finite")
    return c


def monomial_to_legendre(b: Sequence[float] | np.ndarray) -> np.ndarray:
    """Coefficients c_0..c_M with sum c_i P_i(mu) == sum b_i mu^i (full vectors, index 0 included)."""
    b = np.asarray(b, dtype=float)
    if b.size == 0:
        return b.copy()
    return np.asarray(_leg.poly2leg(b), dtype=float)[: b.size]


@lru_cache(maxsize=32)
def _leg2mono_matrix(n: int) -> np.ndarray:
    """Matrix T (n x n) with monomial coefficients = T @ Legendre coefficients."""
    t = np.zeros((n, n))
    for j in range(n):
        e = np.zeros(n)
        e[j] = 1.0
        col = np.asarray(_leg.leg2poly(e), dtype=float)
        t[: col.size, j] = col
    t.setflags(write=False)
    return t


def legendre_to_monomial(c: Sequence[float] | np.ndarray) -> np.ndarray:
    """Coefficients b_0..b_M with sum b_i mu^i == sum c_i P_i(mu) (full vectors)."""
    c = np.asarray(c, dtype=float)
    if c.size == 0:
        return c.copy()
    return _leg2mono_matrix(c.size) @ c


def _full_monomial(coeffs: np.ndarray, basis: str) -> np.ndarray:
    """Monomial coefficients of sum_{i=1..M} b_i Q_i(mu) (b_0 excluded; in the Legendre
    basis the constant term is not zero, e.g. P_2 = (3 mu^2 - 1)/2)."""
    full = np.concatenate([[0.0], coeffs])
    if basis == "legendre":
        full = legendre_to_monomial(full)
    return full


@lru_cache(maxsize=4)
def _gl(n: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(n)
    return x, w


@lru_cache(maxsize=4)
def _graded_unit(n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """Nodes t in (0, 1] and weights for int_0^1 f(t) dt, panels graded towards t = 0."""
    ends = [1.0]
    while ends[-1] > _SMALLEST:
        ends.append(ends[-1] * _GRADING)
    ends.append(0.0)
    edges = np.array(ends[::-1])
    x, w = _gl(n_nodes)
    a, b = edges[:-1, None], edges[1:, None]
    t = (0.5 * (b - a) * x + 0.5 * (a + b)).ravel()
    wt = (0.5 * (b - a) * w).ravel()
    return t, wt


def _breakpoints(mono: np.ndarray) -> np.ndarray:
    """Sorted points of [-1, 1] where the exponent may peak: ends and critical points."""
    pts = [-1.0, 1.0]
    if mono.size > 2 and np.any(mono[2:] != 0.0):
        d = _poly.polyder(mono)
        # trim trailing zeros so roots() sees the true degree
        nz = np.flatnonzero(d)
        d = d[: nz[-1] + 1] if nz.size else d[:1]
        if d.size > 1:
            for r in np.roots(d[::-1]):
                if abs(r.imag) <= 1e-6 * max(1.0, abs(r)) and -1.0 < r.real < 1.0:
                    pts.append(float(r.real))
                elif abs(r.imag) < 0.05 and -1.0 < r.real < 1.0:
                    # a near-double root: the exponent has a shoulder here; grading
                    # towards it costs nothing and protects the quadrature
                    pts.append(float(r.real))
    return np.unique(np.array(pts))


def quadrature_nodes(
    coeffs: Sequence[float] | np.ndarray, basis: Basis = "monomial", n_nodes: int = _GL_NODES
) -> tuple[np.ndarray, np.ndarray]:
    """Nodes mu_j and weights w_j with sum_j w_j f(mu_j) ~ int_{-1}^{1} f(mu) dmu for
    functions peaked like exp(sum_{i>=1} b_i Q_i(mu)).

    Each interval between consecutive breakpoints (ends, critical points) is split at
    its midpoint and both halves are graded geometrically towards their outer end.
    """
    _check_basis(basis)
    return _nodes_for(_full_monomial(as_coefficients(coeffs), basis), n_nodes)


def _nodes_for(mono: np.ndarray, n_nodes: int = _GL_NODES) -> tuple[np.ndarray, np.ndarray]:
    bp = _breakpoints(mono)
    t, wt = _graded_unit(n_nodes)
    mus, ws = [], []
    for a, b in itertools.pairwise(bp):
        h = 0.5 * (b - a)
        mus.append(a + h * t)          # graded towards a
        ws.append(h * wt)
        mus.append(b - h * t)          # graded towards b
        ws.append(h * wt)
    mu = np.concatenate(mus)
    w = np.concatenate(ws)
    order = np.argsort(mu, kind="stable")
    return mu[order], w[order]


def _exponent(mono: np.ndarray, mu: np.ndarray) -> np.ndarray:
    return _poly.polyval(mu, mono)


def _logsumexp(a: np.ndarray, w: np.ndarray) -> tuple[float, np.ndarray]:
    """log(sum w exp(a)) and the normalised weights w exp(a) / sum(...)."""
    amax = float(np.max(a))
    e = w * np.exp(a - amax)
    s = float(np.sum(e))
    return amax + math.log(s), e / s


def log_norm(coeffs: Sequence[float] | np.ndarray, basis: Basis = "monomial") -> float:
    """b_0 such that 2 pi int_{-1}^{1} exp(b_0 + sum_{i=1..M} b_i Q_i(mu)) dmu = 1.

    Args:
        coeffs: b_1..b_M (may be empty: isotropic, b_0 = -log(4 pi)).
        basis: "monomial" (Q_i = mu^i, the paper's) or "legendre" (Q_i = P_i).
    """
    _check_basis(basis)
    c = as_coefficients(coeffs)
    if c.size == 0 or not np.any(c):
        return -math.log(4.0 * math.pi)
    mono = _full_monomial(c, basis)
    mu, w = _nodes_for(mono)
    lse, _ = _logsumexp(_exponent(mono, mu), w)
    return -(math.log(2.0 * math.pi) + lse)


def log_norm_and_grad(
    coeffs: Sequence[float] | np.ndarray, basis: Basis = "monomial"
) -> tuple[float, np.ndarray]:
    """b_0 (see :func:`log_norm`) and d b_0 / d b_i = -<Q_i>_p for i = 1..M."""
    _check_basis(basis)
    c = as_coefficients(coeffs)
    m = c.size
    if m == 0:
        return -math.log(4.0 * math.pi), np.zeros(0)
    mono = _full_monomial(c, basis)
    mu, w = _nodes_for(mono)
    lse, pw = _logsumexp(_exponent(mono, mu), w)
    q = _basis_matrix(mu, m, basis)[:, 1:]
    return -(math.log(2.0 * math.pi) + lse), -(pw @ q)


def _basis_matrix(mu: np.ndarray, degree: int, basis: str) -> np.ndarray:
    """Columns Q_0(mu)..Q_degree(mu)."""
    mu = np.asarray(mu, dtype=float)
    if basis == "monomial":
        return np.vander(mu, degree + 1, increasing=True)
    return _leg.legvander(mu, degree)


class ExponentialPhase:
    """p(mu) = exp(b_0 + sum_{i=1..M} b_i Q_i(mu)) with b_0 from the normalisation.

    Args:
        coeffs: b_1..b_M in ``basis`` (length M = the degree; empty = isotropic).
        basis: "monomial" (the paper's Q_i = mu^i) or "legendre".

    Raises:
        ModelParameterError: a coefficient is NaN/inf (the message names b_i), or the
            basis is unknown.
    """

    def __init__(self, coeffs: Sequence[float] | np.ndarray, basis: Basis = "monomial") -> None:
        _check_basis(basis)
        self._c = as_coefficients(coeffs)
        self.basis: Basis = basis
        self._mono = _full_monomial(self._c, basis)
        if np.max(np.abs(self._mono)) > 1e6:
            raise ModelParameterError(
                f"coefficients too large (max |b_i| = {np.max(np.abs(self._mono)):.3g} > 1e6)")
        self.b0: float = log_norm(self._c, basis)
        self._mono[0] += self.b0
        self._cdf_cache: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    # -- construction -------------------------------------------------------------------
    @classmethod
    def isotropic(cls) -> ExponentialPhase:
        """Degree 0: p = 1/(4 pi)."""
        return cls([])

    @classmethod
    def von_mises_fisher(cls, kappa: float) -> ExponentialPhase:
        """Degree 1 with b_1 = kappa."""
        return cls([kappa])

    @classmethod
    def zeros(cls, degree: int, basis: Basis = "monomial") -> ExponentialPhase:
        """Isotropic function written with ``degree`` zero coefficients.

        Raises:
            ModelParameterError: degree < 0 (names ``degree``).
        """
        return cls(np.zeros(check_degree(degree)), basis)

    # -- coefficients -------------------------------------------------------------------
    @property
    def degree(self) -> int:
        """M, the number of free coefficients."""
        return int(self._c.size)

    @property
    def coeffs(self) -> np.ndarray:
        """b_1..b_M in this object's basis (a copy)."""
        return self._c.copy()

    def full_coeffs(self, basis: Basis | None = None) -> np.ndarray:
        """b_0..b_M in ``basis`` (default: this object's)."""
        basis = basis or self.basis
        _check_basis(basis)
        if basis == "monomial":
            return self._mono.copy()
        return monomial_to_legendre(self._mono)

    def to_basis(self, basis: Basis) -> ExponentialPhase:
        """The same function with coefficients in another basis."""
        full = self.full_coeffs(basis)
        return ExponentialPhase(full[1:], basis)

    # -- evaluation ---------------------------------------------------------------------
    def log_eval(self, mu: np.ndarray | float) -> np.ndarray:
        """log p(mu) [log 1/sr]; mu outside [-1, 1] is evaluated as the polynomial says."""
        return _exponent(self._mono, np.asarray(mu, dtype=float))

    def eval(self, mu: np.ndarray | float) -> np.ndarray:
        """p(mu) [1/sr]."""
        return np.exp(self.log_eval(mu))

    __call__ = eval

    def pdf(self, mu: np.ndarray | float) -> np.ndarray:
        """Density of :meth:`sample` per steradian; equal to p (the inversion is exact)."""
        return self.eval(mu)

    def moment(self, k: int) -> float:
        """2 pi int mu^k p(mu) dmu."""
        mu, w = quadrature_nodes(self._c, self.basis)
        return float(2.0 * math.pi * np.sum(w * mu**k * self.eval(mu)))

    @property
    def g(self) -> float:
        """Asymmetry 2 pi int mu p(mu) dmu (mean scattering cosine)."""
        return self.moment(1)

    # -- sampling -----------------------------------------------------------------------
    def _cdf_table(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Panel edges e_k, CDF at the edges, and the coarse edges' index."""
        if self._cdf_cache is None:
            # a 1-node rule's nodes are the panel centres and its weights their widths
            centres, widths = quadrature_nodes(self._c, self.basis, n_nodes=1)
            edges = np.concatenate([[-1.0], centres + 0.5 * widths])
            edges[-1] = 1.0
            edges = np.maximum.accumulate(edges)
            keep = np.concatenate([[True], np.diff(edges) > 0])
            edges = edges[keep]
            x, w = _gl(_GL_NODES)
            a, b = edges[:-1, None], edges[1:, None]
            nodes = 0.5 * (b - a) * x + 0.5 * (a + b)
            mass = 2.0 * math.pi * np.sum(0.5 * (b - a) * w * self.eval(nodes), axis=1)
            cdf = np.concatenate([[0.0], np.cumsum(mass)])
            cdf /= cdf[-1]
            self._cdf_cache = (edges, cdf, mass)
        return self._cdf_cache

    def _partial_mass(self, a: np.ndarray, mu: np.ndarray) -> np.ndarray:
        """2 pi int_a^mu p dmu, vectorised, with one Gauss-Legendre panel each."""
        x, w = _gl(_GL_NODES)
        h = 0.5 * (mu - a)
        nodes = h[:, None] * x[None, :] + (0.5 * (mu + a))[:, None]
        return 2.0 * math.pi * np.sum(h[:, None] * w[None, :] * self.eval(nodes), axis=1)

    def sample_mu(self, u: np.ndarray | float) -> np.ndarray:
        """Inverse CDF: mu with P(mu' <= mu) = u for u in [0, 1].

        The panel is found in a CDF table on the graded quadrature edges; inside it a
        safeguarded Newton iteration solves the exact CDF equation, so the density of the
        samples is p itself (to ~1e-12).
        """
        u = np.atleast_1d(np.asarray(u, dtype=float))
        if np.any(~np.isfinite(u)) or np.any((u < 0) | (u > 1)):
            raise ModelParameterError("u must lie in [0, 1]")
        edges, cdf, mass = self._cdf_table()
        total = float(np.sum(mass))
        k = np.clip(np.searchsorted(cdf, u, side="right") - 1, 0, edges.size - 2)
        lo, hi = edges[k].copy(), edges[k + 1].copy()
        target = (u - cdf[k]) * total       # mass still to cover inside the panel
        a = edges[k]
        # start: linear in the panel
        frac = np.where(mass[k] > 0, target / np.where(mass[k] > 0, mass[k], 1.0), 0.5)
        x = lo + np.clip(frac, 0.0, 1.0) * (hi - lo)
        for _ in range(50):
            f = self._partial_mass(a, x) - target
            lo = np.where(f < 0, x, lo)
            hi = np.where(f >= 0, x, hi)
            d = 2.0 * math.pi * self.eval(x)
            step = np.where(d > 0, f / np.where(d > 0, d, 1.0), 0.0)
            xn = x - step
            bad = (xn <= lo) | (xn >= hi) | ~np.isfinite(xn)
            xn = np.where(bad, 0.5 * (lo + hi), xn)
            if np.all(np.abs(xn - x) <= 1e-14 * np.maximum(1.0, np.abs(x))):
                x = xn
                break
            x = xn
        return np.clip(x, -1.0, 1.0)

    def sample(self, u: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Scattering cosines for uniform numbers u, and their pdf per steradian (= p)."""
        mu = self.sample_mu(u)
        return mu, self.pdf(mu)

    def sample_directions(
        self, u1: np.ndarray, u2: np.ndarray, axis: Sequence[float] = (0.0, 0.0, 1.0)
    ) -> tuple[np.ndarray, np.ndarray]:
        """Unit directions (N, 3) scattered about ``axis`` (the forward direction) and
        their pdf per steradian."""
        mu = self.sample_mu(u1)
        return sample_about_axis(mu, np.asarray(u2, dtype=float), axis), self.pdf(mu)

    def __repr__(self) -> str:
        return f"ExponentialPhase({self._c.tolist()!r}, basis={self.basis!r})"


def sample_about_axis(mu: np.ndarray, u2: np.ndarray, axis: Sequence[float]) -> np.ndarray:
    """Directions with cosine ``mu`` to ``axis`` and azimuth 2 pi u2, shape (N, 3)."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t1 = np.cross(a, helper)
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(a, t1)
    mu = np.asarray(mu, dtype=float)
    s = np.sqrt(np.clip(1.0 - mu * mu, 0.0, 1.0))
    phi = 2.0 * math.pi * np.asarray(u2, dtype=float)
    return (mu[:, None] * a + (s * np.cos(phi))[:, None] * t1 + (s * np.sin(phi))[:, None] * t2)


def check_degree(degree: int) -> int:
    """Return ``degree`` as int; raise ModelParameterError naming ``degree`` if < 0."""
    if isinstance(degree, bool) or not isinstance(degree, (int, np.integer)):
        raise ModelParameterError(f"degree must be an integer, got {degree!r}")
    if degree < 0:
        raise ModelParameterError(f"degree must be >= 0, got {degree}")
    return int(degree)
