"""Henyey-Greenstein and two-term Henyey-Greenstein phase functions.

Densities per steradian over the scattering cosine mu (mu = +1: straight on), normalised
to 2 pi int_{-1}^{1} p dmu = 1:

    HG(mu; g)       = (1 - g^2) / (4 pi (1 + g^2 - 2 g mu)^(3/2)),     -1 < g < 1
    TTHG(mu)        = w HG(mu; g1) + (1 - w) HG(mu; g2),               0 <= w <= 1

For the two-term function ``g1`` is the forward lobe and ``g2`` the backward lobe
(Kattawar 1975); the constructor accepts any lobes in (-1, 1), the fit constrains
g1 >= 0 >= g2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimate.errors import ModelParameterError

__all__ = ["HenyeyGreenstein", "TwoTermHG", "hg_eval", "hg_sample_mu"]

#: |g| must stay below this: at |g| -> 1 the lobe becomes a delta and (1 - g^2) underflows.
G_MAX = 1.0 - 1e-9


def _check_g(name: str, g: float) -> float:
    try:
        g = float(g)
    except (TypeError, ValueError):
        raise ModelParameterError(f"{name} must be a number, got {g!r}") from None
    if not math.isfinite(g) or abs(g) > G_MAX:
        raise ModelParameterError(f"{name} must lie in (-1, 1), got {g!r}")
    return g


def hg_eval(mu: np.ndarray | float, g: float) -> np.ndarray:
    """HG density [1/sr] at cosines mu."""
    mu = np.asarray(mu, dtype=float)
    d = 1.0 + g * g - 2.0 * g * mu
    return (1.0 - g * g) / (4.0 * math.pi * d * np.sqrt(d))


def hg_log_eval(mu: np.ndarray | float, g: float) -> np.ndarray:
    """log of :func:`hg_eval`, without overflow for g near 1."""
    mu = np.asarray(mu, dtype=float)
    d = 1.0 + g * g - 2.0 * g * mu
    return math.log1p(-g * g) - math.log(4.0 * math.pi) - 1.5 * np.log(d)


def hg_sample_mu(u: np.ndarray | float, g: float) -> np.ndarray:
    """Inverse CDF of HG: mu for uniform u in [0, 1]."""
    u = np.asarray(u, dtype=float)
    if abs(g) < 1e-6:
        return 2.0 * u - 1.0
    s = (1.0 - g * g) / (1.0 - g + 2.0 * g * u)
    return np.clip((1.0 + g * g - s * s) / (2.0 * g), -1.0, 1.0)


@dataclass(frozen=True)
class HenyeyGreenstein:
    """HG phase function with asymmetry ``g`` in (-1, 1)."""

    g: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "g", _check_g("g", self.g))

    def eval(self, mu: np.ndarray | float) -> np.ndarray:
        """p(mu) [1/sr]."""
        return hg_eval(mu, self.g)

    __call__ = eval

    def log_eval(self, mu: np.ndarray | float) -> np.ndarray:
        """log p(mu)."""
        return hg_log_eval(mu, self.g)

    @property
    def asymmetry(self) -> float:
        """Mean scattering cosine (= g)."""
        return self.g

    def sample_mu(self, u: np.ndarray | float) -> np.ndarray:
        """Inverse CDF: cosines for uniform u in [0, 1]."""
        return hg_sample_mu(u, self.g)

    def sample(self, u: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Cosines for uniform u and their pdf per steradian (= p)."""
        mu = hg_sample_mu(u, self.g)
        return mu, self.eval(mu)

    def pdf(self, mu: np.ndarray | float) -> np.ndarray:
        """Sampling density per steradian (= p)."""
        return self.eval(mu)


@dataclass(frozen=True)
class TwoTermHG:
    """w HG(g1) + (1 - w) HG(g2): forward lobe g1, backward lobe g2, weight w in [0, 1]."""

    g1: float
    g2: float
    w: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "g1", _check_g("g1", self.g1))
        object.__setattr__(self, "g2", _check_g("g2", self.g2))
        try:
            w = float(self.w)
        except (TypeError, ValueError):
            raise ModelParameterError(f"w must be a number, got {self.w!r}") from None
        if not (0.0 <= w <= 1.0):
            raise ModelParameterError(f"w must lie in [0, 1], got {self.w!r}")
        object.__setattr__(self, "w", w)

    def eval(self, mu: np.ndarray | float) -> np.ndarray:
        """p(mu) [1/sr]."""
        return self.w * hg_eval(mu, self.g1) + (1.0 - self.w) * hg_eval(mu, self.g2)

    __call__ = eval

    def log_eval(self, mu: np.ndarray | float) -> np.ndarray:
        """log p(mu), as a log-sum-exp of the lobes."""
        with np.errstate(divide="ignore"):
            a = math.log(self.w) if self.w > 0 else -np.inf
            b = math.log1p(-self.w) if self.w < 1 else -np.inf
        return np.logaddexp(a + hg_log_eval(mu, self.g1), b + hg_log_eval(mu, self.g2))

    @property
    def asymmetry(self) -> float:
        """Mean scattering cosine w g1 + (1 - w) g2."""
        return self.w * self.g1 + (1.0 - self.w) * self.g2

    @property
    def g(self) -> float:
        """Alias of :attr:`asymmetry`."""
        return self.asymmetry

    def sample_mu(self, u: np.ndarray | float) -> np.ndarray:
        """Cosines from one uniform u each: u < w picks the forward lobe and u/w, rescaled,
        inverts it; otherwise (u - w)/(1 - w) inverts the backward lobe."""
        u = np.asarray(u, dtype=float)
        w = self.w
        fwd = u < w
        u_f = np.clip(u / w, 0.0, 1.0) if w > 0 else np.zeros_like(u)
        u_b = np.clip((u - w) / (1.0 - w), 0.0, 1.0) if w < 1 else np.zeros_like(u)
        return np.where(fwd, hg_sample_mu(u_f, self.g1), hg_sample_mu(u_b, self.g2))

    def sample(self, u1: np.ndarray | float, u2: np.ndarray | float | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
        """Cosines and their pdf (= p). With u2, u1 < w picks the lobe and u2 inverts it;
        without, see :meth:`sample_mu`."""
        if u2 is None:
            mu = self.sample_mu(u1)
        else:
            u1 = np.asarray(u1, dtype=float)
            u2 = np.asarray(u2, dtype=float)
            mu = np.where(u1 < self.w, hg_sample_mu(u2, self.g1), hg_sample_mu(u2, self.g2))
        return mu, self.eval(mu)

    def pdf(self, mu: np.ndarray | float) -> np.ndarray:
        """Sampling density per steradian (= p)."""
        return self.eval(mu)
