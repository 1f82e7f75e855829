"""The exponential phase function as a Mitsuba 3 plugin, and the two-term HG baseline.

p(mu) = exp(b_0 + sum_{i=1..M} b_i mu^i)  (monomial basis, the paper's Q_i = mu^i), with
mu the cosine of the scattering angle (mu = +1: straight on) and b_0 = -log(2 pi int
exp(sum b_i mu^i) dmu) fixed by normalisation over the sphere. The normalisation is
computed in Dr.Jit from the b's each time they change, so it is part of the
differentiated computation (detaching it gives wrong, even sign-flipped, gradients).

Sampling draws mu from a piecewise-linear table of p on nodes clustered at mu = +-1
(uniform in the scattering angle, good for peaked lobes) and returns the weight
exact / table-pdf, which keeps the estimator unbiased whatever the table's error.

Mitsuba's convention: ``mi.wi`` points back towards where the light came from, so the
scattering cosine is mu = -dot(wo, wi).

Call `register_plugins()` after `mi.set_variant` (done by `estimate.mitsuba_env.init_mitsuba`).
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from estimate.errors import ModelParameterError

__all__ = [
    "PLUGIN_NAME",
    "register_plugins",
    "exp_phase_dict",
    "tthg_phase_dict",
    "exp_normalisation_nodes",
    "MAX_ABS_B",
]

PLUGIN_NAME = "exponential_phase"
#: Simpson nodes in the scattering angle for b_0 (odd); 1025 keeps b_0 to ~1e-7 for b_1 ~ 300.
_NORM_NODES = 1025
#: Nodes of the sampling table.
_TABLE_NODES = 1025
#: |b_i| above this overflows float32 in exp(); refuse rather than render NaNs.
MAX_ABS_B = 1000.0

_registered: set[str] = set()


def exp_normalisation_nodes(n: int = _NORM_NODES) -> tuple[np.ndarray, np.ndarray]:
    """Nodes mu_j and weights w_j with sum_j w_j f(mu_j) ~ int_{-1}^{1} f(mu) dmu.

    Composite Simpson in theta = arccos(mu) (uniform in angle, so nodes crowd at mu = +-1
    where exponential lobes peak), including the sin(theta) Jacobian.
    """
    theta = np.linspace(0.0, math.pi, n)
    h = theta[1] - theta[0]
    simpson = np.ones(n)
    simpson[1:-1:2] = 4.0
    simpson[2:-1:2] = 2.0
    weights = simpson * h / 3.0 * np.sin(theta)
    return np.cos(theta), weights


def _check_b(b: Sequence[float]) -> list[float]:
    out = []
    for i, v in enumerate(b, start=1):
        v = float(v)
        if not math.isfinite(v) or abs(v) > MAX_ABS_B:
            raise ModelParameterError(f"phase coefficient b{i}={v!r} must be finite and |b{i}| <= {MAX_ABS_B:g}")
        out.append(v)
    return out


def exp_phase_dict(b: Sequence[float]) -> dict[str, Any]:
    """Mitsuba dict of the exponential phase function with coefficients b_1..b_M."""
    coeffs = _check_b(b)
    d: dict[str, Any] = {"type": PLUGIN_NAME, "degree": len(coeffs)}
    for i, v in enumerate(coeffs, start=1):
        d[f"b{i}"] = v
    return d


def tthg_phase_dict(g_forward: float, g_backward: float, w_forward: float) -> dict[str, Any]:
    """Two-term HG from built-in `hg` lobes: w * HG(g_forward) + (1 - w) * HG(g_backward).

    `blendphase`'s weight is the weight of its second lobe, here the backward one.
    """
    for name, v in (("g_forward", g_forward), ("g_backward", g_backward)):
        if not math.isfinite(v) or not -1.0 < v < 1.0:
            raise ModelParameterError(f"tthg {name}={v!r} must lie in (-1, 1)")
    if not math.isfinite(w_forward) or not 0.0 <= w_forward <= 1.0:
        raise ModelParameterError(f"tthg w_forward={w_forward!r} must lie in [0, 1]")
    return {
        "type": "blendphase",
        "weight": 1.0 - float(w_forward),
        "phase1": {"type": "hg", "g": float(g_forward)},
        "phase2": {"type": "hg", "g": float(g_backward)},
    }


def _make_plugin_class(mi: Any, dr: Any) -> type:
    """Build the plugin class for the current variant (Mitsuba types are per variant)."""
    mu_np, w_np = exp_normalisation_nodes()
    table_mu_np = np.cos(np.linspace(math.pi, 0.0, _TABLE_NODES))  # increasing

    class ExponentialPhaseFunction(mi.PhaseFunction):
        """exp(b_0 + sum b_i mu^i); parameters 'b1'..'bM' differentiable."""

        def __init__(self, props: Any) -> None:
            mi.PhaseFunction.__init__(self, props)
            degree = int(props.get("degree", 0))
            if degree < 0:
                raise ModelParameterError(f"exponential phase degree={degree} must be >= 0")
            coeffs = _check_b([props.get(f"b{i}", 0.0) for i in range(1, degree + 1)])
            self.degree = degree
            self.b = [mi.Float(v) for v in coeffs]
            self.m_flags = mi.PhaseFunctionFlags.Anisotropic
            self._norm_mu = mi.Float(mu_np)
            self._norm_w = mi.Float(w_np)
            self._table_mu = mi.Float(table_mu_np)
            self._update()

        # --- parameters -------------------------------------------------------
        def traverse(self, callback: Any) -> None:
            for i, v in enumerate(self.b, start=1):
                callback.put(f"b{i}", v, mi.ParamFlags.Differentiable)

        def parameters_changed(self, keys: Any = None) -> None:
            self._update()

        def _poly(self, mu: Any) -> Any:
            """sum_{i>=1} b_i mu^i by Horner (zero for degree 0)."""
            if self.degree == 0:
                return dr.zeros(mi.Float, dr.width(mu))
            acc = mi.Float(self.b[-1])
            for bi in reversed(self.b[:-1]):
                acc = dr.fma(acc, mu, bi)
            return acc * mu

        def _update(self) -> None:
            # log-sum-exp normalisation, differentiable in b (the shift m is detached, which
            # is exact: it cancels).
            poly = self._poly(self._norm_mu)
            m = dr.max(dr.detach(poly))
            z = dr.sum(self._norm_w * dr.exp(poly - m))
            self.log_norm = m + dr.log(z) + math.log(2.0 * math.pi)
            dr.make_opaque(self.log_norm)
            # Sampling table (detached: it only shapes the importance sampling).
            with dr.suspend_grad():
                tpoly = self._poly(self._table_mu)
                tm = dr.max(tpoly)
                tpdf = dr.exp(tpoly - tm)
                dr.eval(tpdf)
                self.table = mi.IrregularContinuousDistribution(mi.Float(self._table_mu), tpdf)

        @property
        def b0(self) -> float:
            """The normalisation coefficient b_0 = -log(2 pi int exp(sum b_i mu^i) dmu)."""
            return -float(dr.detach(self.log_norm)[0])

        # --- evaluation and sampling -----------------------------------------
        def _value(self, mu: Any) -> Any:
            return dr.exp(self._poly(mu) - self.log_norm)

        def eval_pdf(self, ctx: Any, mei: Any, wo: Any, active: Any = True) -> tuple[Any, Any]:
            mu = -dr.dot(wo, mei.wi)
            mu = dr.clip(mu, -1.0, 1.0)
            value = self._value(mu)
            pdf = self.table.eval_pdf_normalized(dr.detach(mu), active) * (0.5 / math.pi)
            return mi.Spectrum(dr.select(active, value, 0.0)), dr.select(active, pdf, 0.0)

        def sample(self, ctx: Any, mei: Any, sample1: Any, sample2: Any, active: Any = True) -> tuple[Any, Any, Any]:
            mu = dr.clip(self.table.sample(sample2.x, active), -1.0, 1.0)
            pdf = self.table.eval_pdf_normalized(mu, active) * (0.5 / math.pi)
            sin_t = dr.safe_sqrt(1.0 - mu * mu)
            s, c = dr.sincos(2.0 * math.pi * sample2.y)
            local = mi.Vector3f(sin_t * c, sin_t * s, mu)
            wo = mi.Frame3f(-mei.wi).to_world(local)
            value = self._value(mu)
            ok = active & (pdf > 0.0)
            weight = dr.select(ok, value / dr.maximum(pdf, 1e-30), 0.0)
            return wo, mi.Spectrum(weight), dr.select(ok, pdf, 0.0)

        def to_string(self) -> str:
            return f"ExponentialPhaseFunction[degree={self.degree}]"

    return ExponentialPhaseFunction


def register_plugins() -> None:
    """Register `exponential_phase` for the current Mitsuba variant (idempotent)."""
    import drjit as dr
    import mitsuba as mi

    variant = mi.variant()
    if variant in _registered:
        return
    cls = _make_plugin_class(mi, dr)
    mi.register_phase(PLUGIN_NAME, lambda props: cls(props))
    _registered.add(variant)
