"""Polynomial phase function (the paper's baseline, Sharma 1998) and the isotropic one.

    p(mu) = sum_{i=0..N} a_i mu^i      (monomial basis, as in the paper)

a_0 is fixed by 2 pi int_{-1}^{1} p dmu = 1, i.e. a_0 = 1/(4 pi) - sum_{even i >= 2} a_i/(i+1),
so a degree-N function has N free coefficients a_1..a_N. Nothing keeps p positive: the
positivity check finds the exact minimum over [-1, 1] (ends and real critical points).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.polynomial import polynomial as _poly

from estimate.phase_exponential import as_coefficients

__all__ = ["IsotropicPhase", "PolynomialPhase", "normalised_design", "polynomial_a0"]

ISOTROPIC = 1.0 / (4.0 * math.pi)


def polynomial_a0(a: Sequence[float] | np.ndarray) -> float:
    """a_0 that normalises sum a_i mu^i over the sphere, given a_1..a_N."""
    c = as_coefficients(a, "a")
    s = sum(c[i - 1] / (i + 1) for i in range(2, c.size + 1, 2))
    return ISOTROPIC - s


def normalised_design(mu: np.ndarray, degree: int) -> np.ndarray:
    """Matrix D with p(mu_j) = 1/(4 pi) + (D @ a)_j for a = a_1..a_N (normalisation built in)."""
    mu = np.asarray(mu, dtype=float)
    cols = []
    for i in range(1, degree + 1):
        cols.append(mu**i - (1.0 / (i + 1) if i % 2 == 0 else 0.0))
    return np.stack(cols, axis=1) if cols else np.zeros((mu.size, 0))


class PolynomialPhase:
    """p(mu) = a_0 + sum_{i=1..N} a_i mu^i with a_0 from the normalisation.

    Args:
        coeffs: a_1..a_N (length N = degree).

    Raises:
        ModelParameterError: a NaN/inf coefficient (named).
    """

    def __init__(self, coeffs: Sequence[float] | np.ndarray) -> None:
        self._a = as_coefficients(coeffs, "a")
        self.a0 = polynomial_a0(self._a)
        self._full = np.concatenate([[self.a0], self._a])

    @property
    def degree(self) -> int:
        """N."""
        return int(self._a.size)

    @property
    def coeffs(self) -> np.ndarray:
        """a_1..a_N (a copy)."""
        return self._a.copy()

    def full_coeffs(self) -> np.ndarray:
        """a_0..a_N."""
        return self._full.copy()

    def eval(self, mu: np.ndarray | float) -> np.ndarray:
        """p(mu) [1/sr]; may be <= 0 (see :meth:`is_positive`)."""
        return _poly.polyval(np.asarray(mu, dtype=float), self._full)

    __call__ = eval

    def min_value(self) -> tuple[float, float]:
        """(min of p over [-1, 1], the mu where it is reached), exactly."""
        cand = [-1.0, 1.0]
        if self.degree >= 2:
            d = _poly.polyder(self._full)
            nz = np.flatnonzero(d)
            if nz.size and nz[-1] >= 1:
                for r in np.roots(d[: nz[-1] + 1][::-1]):
                    if abs(r.imag) < 1e-9 and -1.0 < r.real < 1.0:
                        cand.append(float(r.real))
        cand_a = np.array(cand)
        v = self.eval(cand_a)
        i = int(np.argmin(v))
        return float(v[i]), float(cand_a[i])

    def is_positive(self, mu: np.ndarray | None = None) -> bool:
        """True if p > 0 on the grid ``mu``, or on all of [-1, 1] when mu is None."""
        if mu is None:
            return self.min_value()[0] > 0.0
        return bool(np.all(self.eval(mu) > 0.0))

    @property
    def g(self) -> float:
        """Asymmetry 2 pi int mu p dmu = 2 pi sum_{odd i} 2 a_i / (i + 2)."""
        return float(2.0 * math.pi * sum(2.0 * self._full[i] / (i + 2) for i in range(1, self.degree + 1, 2)))

    def __repr__(self) -> str:
        return f"PolynomialPhase({self._a.tolist()!r})"


class IsotropicPhase:
    """p = 1/(4 pi) [1/sr]."""

    g = 0.0

    def eval(self, mu: np.ndarray | float) -> np.ndarray:
        """p(mu)."""
        return np.full_like(np.asarray(mu, dtype=float), ISOTROPIC)

    __call__ = eval

    def log_eval(self, mu: np.ndarray | float) -> np.ndarray:
        """log p(mu)."""
        return np.full_like(np.asarray(mu, dtype=float), math.log(ISOTROPIC))

    def sample_mu(self, u: np.ndarray | float) -> np.ndarray:
        """Cosines 2u - 1."""
        return 2.0 * np.asarray(u, dtype=float) - 1.0

    def sample(self, u: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Cosines 2u - 1 and their pdf (1/(4 pi))."""
        mu = 2.0 * np.asarray(u, dtype=float) - 1.0
        return mu, self.eval(mu)

    def pdf(self, mu: np.ndarray | float) -> np.ndarray:
        """Sampling density per steradian."""
        return self.eval(mu)
