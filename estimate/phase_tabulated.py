"""A phase function rendered from its table: ln p linear in the scattering angle.

The simulated bench's truth for a Mie medium is the Mie table itself (`render.mie_phase:
table` in a world file), not a fitted exponential function: for the paper's 0.5 um
particles the exp8 fit is 9 % rms (34 % at worst) off the table in ln p, so a fit against
a recording rendered from it would be tested against a smoothed Mie phase.

The table is resampled onto `NODES` angles equally spaced in theta over [0, pi], ln p
interpolated linearly in theta between them (the Mie tables' own grid is 0.1 deg, so
nothing is lost), and normalised to 1 over the sphere for exactly that interpolant (by a
fine quadrature of each interval), so that what the engines evaluate integrates to 1.
Sampling inverts the same tabulated CDF as the exponential function's
(`estimate.mitsuba_phase.inverse_cdf_of`), weights exact value / proposal density.

The table has no parameters: it is a truth to render, not a model to fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimate.errors import ModelParameterError
from estimate.phase_table import PhaseTable

__all__ = ["NODES", "TabulatedPhase"]

#: Angles of the resampled table over [0, pi] (0.05 deg apart).
NODES = 3601
#: Sub-intervals of each table interval in the normalisation's quadrature (at least), and of
#: the whole angle range (at least: a coarse table's intervals are split further).
_SUBDIVISIONS = 8
_QUADRATURE_MIN = 8192


@dataclass(frozen=True, eq=False)
class TabulatedPhase:
    """p(theta) [1/sr] as ln p on `NODES` equally spaced scattering angles.

    Attributes:
        log_p: ln p at theta_j = j pi / (NODES - 1), normalised over the sphere for linear
            interpolation in theta.
        g: mean cosine of the interpolant.
        label: provenance for logs and reports (e.g. "Mie poly d=0.5um").
    """

    log_p: np.ndarray
    g: float
    label: str = ""

    @classmethod
    def from_table(cls, table: PhaseTable, nodes: int = NODES) -> TabulatedPhase:
        """Resample and normalise a `PhaseTable` whose angles span [0, 180] deg.

        Raises:
            ModelParameterError: the table does not cover 0 to 180 deg, or has a p <= 0 or
                non-finite value.
        """
        th = np.asarray(table.theta_deg, dtype=np.float64)
        p = np.asarray(table.p, dtype=np.float64)
        name = f"phase table {table.label}" if table.label else "the phase table"
        if th.size < 2 or abs(th[0]) > 1e-9 or abs(th[-1] - 180.0) > 1e-9:
            raise ModelParameterError(f"{name} must span 0 to 180 deg to be rendered, got {th[0]:g} to {th[-1]:g} deg")
        if not np.all(np.isfinite(p)) or np.any(p <= 0.0):
            raise ModelParameterError(f"{name} has a value that is not a positive number")
        grid = np.linspace(0.0, 180.0, int(nodes))
        log_p = np.interp(grid, th, np.log(p))
        return cls.normalised(log_p, label=table.label)

    @classmethod
    def normalised(cls, log_p: np.ndarray, label: str = "") -> TabulatedPhase:
        """From ln p (up to a constant) on equally spaced angles over [0, pi]."""
        log_p = np.asarray(log_p, dtype=np.float64)
        if log_p.ndim != 1 or log_p.size < 2 or not np.all(np.isfinite(log_p)):
            raise ModelParameterError("a tabulated phase needs at least two finite ln p values")
        n = log_p.size
        # Every interval split into equal pieces, Simpson on each piece's ends and midpoint:
        # ln p is linear there, sin(theta) smooth, so the error is ~1e-9.
        per = max(_SUBDIVISIONS, -(-_QUADRATURE_MIN // (n - 1)))
        k = 2 * per * (n - 1) + 1
        theta = np.linspace(0.0, math.pi, k)
        lp = np.interp(theta, np.linspace(0.0, math.pi, n), log_p)
        w = np.ones(k)
        w[1:-1:2] = 4.0
        w[2:-1:2] = 2.0
        w *= (theta[1] - theta[0]) / 3.0 * np.sin(theta)
        m = float(lp.max())
        f = w * np.exp(lp - m)
        z = 2.0 * math.pi * float(f.sum())
        g = float(np.sum(f * np.cos(theta)) / f.sum())
        return cls(log_p=log_p - m - math.log(z), g=g, label=label)

    @property
    def nodes(self) -> int:
        """Number of angles of the table."""
        return int(self.log_p.size)

    @property
    def step_rad(self) -> float:
        """Angle between table entries [rad]."""
        return math.pi / (self.nodes - 1)

    def log_eval(self, mu: np.ndarray | float) -> np.ndarray:
        """ln p [1/sr] at scattering cosines mu (mu = 1: straight on)."""
        theta = np.arccos(np.clip(np.asarray(mu, dtype=np.float64), -1.0, 1.0))
        return np.interp(theta, np.linspace(0.0, math.pi, self.nodes), self.log_p)

    def eval(self, mu: np.ndarray | float) -> np.ndarray:
        """p [1/sr] at scattering cosines mu."""
        return np.exp(self.log_eval(mu))

    def key(self) -> str:
        """A short fingerprint of the table (for cache names and logs)."""
        import hashlib

        return hashlib.sha1(np.ascontiguousarray(self.log_p).tobytes()).hexdigest()[:12]
