"""The exponential phase function as a Mitsuba 3 plugin, the two-term HG baseline, and a
tabulated phase function (the simulated bench's Mie truth, `estimate.phase_tabulated`).

p(mu) = exp(b_0 + sum_{i=1..M} b_i mu^i)  (monomial basis, the paper's Q_i = mu^i), with
mu the cosine of the scattering angle (mu = +1: straight on) and b_0 = -log(2 pi int
exp(sum b_i mu^i) dmu) fixed by normalisation over the sphere. The normalisation is
computed in Dr.Jit from the b's each time they change, so it is part of the
differentiated computation (detaching it gives wrong, even sign-flipped, gradients).

Sampling inverts a tabulated CDF: the inverse CDF is tabulated at `_INV_CDF_SIZE` equally
spaced probabilities (computed in numpy, detached, each time the b's change) and
interpolated linearly, so a sample costs two gathers (no binary search) and its density
is exactly the piecewise-constant 1 / ((K - 1) (mu_{i+1} - mu_i)). The weight is
exact value / that density, which keeps the estimator unbiased whatever the table's
error. `eval_pdf` reports the exact phase value as the pdf: it only enters multiple
importance sampling weights against area emitters, and the rig's beam is a delta emitter.

Mitsuba's convention: ``mi.wi`` points back towards where the light came from, so the
scattering cosine is mu = -dot(wo, wi).

The tabulated plugin (`tabulated_phase`) evaluates ln p linearly interpolated in the
scattering angle between equally spaced entries (given as the string property ``log_p``,
comma-separated, normalised by `TabulatedPhase`) and samples the same way as the
exponential one; it has no parameters.

Call `register_plugins()` after `mi.set_variant` (done by `estimate.mitsuba_env.init_mitsuba`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from estimate.errors import ModelParameterError

__all__ = [
    "MAX_ABS_B",
    "PLUGIN_NAME",
    "TABULATED_PLUGIN_NAME",
    "exp_normalisation_nodes",
    "exp_phase_dict",
    "inverse_cdf_of",
    "inverse_cdf_table",
    "register_plugins",
    "tabulated_inverse_cdf",
    "tabulated_log_p",
    "tabulated_phase_dict",
    "tthg_phase_dict",
]

PLUGIN_NAME = "exponential_phase"
TABULATED_PLUGIN_NAME = "tabulated_phase"
#: Simpson nodes in the scattering angle for b_0 (odd); 1025 keeps b_0 to ~1e-7 for b_1 ~ 300.
_NORM_NODES = 1025
#: Entries of the tabulated inverse CDF.
_INV_CDF_SIZE = 2048
#: Nodes (in the scattering angle) of the numpy CDF that is inverted.
_CDF_NODES = 16385
#: |b_i| above this overflows float32 in exp(); refuse rather than render NaNs.
MAX_ABS_B = 1000.0

_registered: set[str | None] = set()


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


def inverse_cdf_of(log_density: Callable[[np.ndarray], np.ndarray], size: int = _INV_CDF_SIZE) -> np.ndarray:
    """mu at probabilities 0, 1/(size-1), ..., 1 of a density on mu in [-1, 1] given by its
    log (up to a constant; a function of a numpy array of mu), increasing."""
    theta = np.linspace(math.pi, 0.0, _CDF_NODES)
    mu = np.cos(theta)
    log_w = np.asarray(log_density(mu), dtype=np.float64)
    w = np.exp(log_w - log_w.max())
    # Trapezoid CDF in mu; the theta-uniform nodes resolve peaks at mu = +-1.
    seg = 0.5 * (w[1:] + w[:-1]) * np.diff(mu)
    cdf = np.concatenate(([0.0], np.cumsum(seg)))
    cdf /= cdf[-1]
    u = np.linspace(0.0, 1.0, size)
    # Invert the piecewise-linear-density CDF segment by segment (linear in mu is enough
    # at this resolution).
    table = np.interp(u, cdf, mu)
    table[0], table[-1] = -1.0, 1.0
    return table


def inverse_cdf_table(b: Sequence[float], size: int = _INV_CDF_SIZE) -> np.ndarray:
    """mu at probabilities 0, 1/(size-1), ..., 1 of exp(sum b_i mu^i) (increasing)."""
    coeffs = list(b)

    def log_w(mu: np.ndarray) -> np.ndarray:
        poly = np.zeros_like(mu)
        for bi in reversed(coeffs):
            poly = (poly + bi) * mu
        return poly

    return inverse_cdf_of(log_w, size)


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


def tabulated_phase_dict(log_p: Sequence[float] | np.ndarray) -> dict[str, Any]:
    """Mitsuba dict of a tabulated phase function: ln p [1/sr] on equally spaced scattering
    angles over [0, pi], normalised (`estimate.phase_tabulated.TabulatedPhase.log_p`)."""
    values = np.asarray(log_p, dtype=np.float64)
    if values.ndim != 1 or values.size < 2 or not np.all(np.isfinite(values)):
        raise ModelParameterError("a tabulated phase needs at least two finite ln p values")
    return {"type": TABULATED_PLUGIN_NAME, "log_p": ",".join(f"{v:.9g}" for v in values)}


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


def _sample_inverse_cdf(mi: Any, dr: Any, inv_cdf: Any, value: Callable[[Any], Any], mei: Any, sample2: Any,
                        active: Any) -> tuple[Any, Any, Any]:
    """A direction from a tabulated inverse CDF of mu (`inverse_cdf_of`), its weight
    value / proposal density and that density (piecewise constant in mu, per steradian)."""
    k = _INV_CDF_SIZE - 1
    x = dr.clip(sample2.x, 0.0, 1.0) * k
    i = mi.UInt32(dr.clip(dr.floor(x), 0, k - 1))
    f = x - mi.Float(i)
    mu0 = dr.gather(mi.Float, inv_cdf, i, active)
    mu1 = dr.gather(mi.Float, inv_cdf, i + 1, active)
    mu = dr.clip(dr.lerp(mu0, mu1, f), -1.0, 1.0)
    pdf = dr.rcp(k * dr.maximum(mu1 - mu0, 1e-7) * (2.0 * math.pi))
    sin_t = dr.safe_sqrt(1.0 - mu * mu)
    s, c = dr.sincos(2.0 * math.pi * sample2.y)
    wo = mi.Frame3f(-mei.wi).to_world(mi.Vector3f(sin_t * c, sin_t * s, mu))
    ok = active & (pdf > 0.0)
    weight = dr.select(ok, value(mu) / pdf, 0.0)
    return wo, mi.Spectrum(weight), dr.select(ok, pdf, 0.0)


def tabulated_log_p(mi: Any, dr: Any, log_p: Any, n: int, mu: Any) -> Any:
    """ln p at scattering cosines mu (Dr.Jit) from `n` entries `log_p` (a device array) on
    equally spaced angles over [0, pi], linear in the angle between them: the tabulated
    plugin's and the light engine's evaluation."""
    x = dr.acos(dr.clip(mu, -1.0, 1.0)) * ((n - 1) / math.pi)
    i = mi.UInt32(dr.clip(dr.floor(x), 0, n - 2))
    lp0 = dr.gather(mi.Float, log_p, i)
    lp1 = dr.gather(mi.Float, log_p, i + 1)
    return dr.lerp(lp0, lp1, dr.clip(x - mi.Float(i), 0.0, 1.0))


def tabulated_inverse_cdf(log_p: np.ndarray, size: int = _INV_CDF_SIZE) -> np.ndarray:
    """`inverse_cdf_of` the density whose ln p is `log_p` on equally spaced angles over
    [0, pi], linear in the angle between them."""
    values = np.asarray(log_p, dtype=np.float64)
    grid = np.linspace(0.0, math.pi, values.size)
    return inverse_cdf_of(lambda mu: np.interp(np.arccos(np.clip(mu, -1.0, 1.0)), grid, values), size)


def _make_tabulated_class(mi: Any, dr: Any) -> type:
    """The tabulated plugin class for the current variant."""

    class TabulatedPhaseFunction(mi.PhaseFunction):
        """p from ln p linear in the scattering angle; no parameters."""

        def __init__(self, props: Any) -> None:
            mi.PhaseFunction.__init__(self, props)
            try:
                log_p = np.array([float(x) for x in str(props.get("log_p", "")).split(",")], dtype=np.float64)
            except ValueError:
                raise ModelParameterError("tabulated_phase: log_p must be comma-separated numbers") from None
            if log_p.size < 2 or not np.all(np.isfinite(log_p)):
                raise ModelParameterError("tabulated_phase: log_p needs at least two finite values")
            self.m_flags = mi.PhaseFunctionFlags.Anisotropic
            self.n = int(log_p.size)
            self.log_p = mi.Float(log_p.astype(np.float32))
            dr.make_opaque(self.log_p)
            self.inv_cdf = mi.Float(tabulated_inverse_cdf(log_p).astype(np.float32))
            dr.make_opaque(self.inv_cdf)

        def _value(self, mu: Any) -> Any:
            return dr.exp(tabulated_log_p(mi, dr, self.log_p, self.n, mu))

        def eval_pdf(self, ctx: Any, mei: Any, wo: Any, active: Any = True) -> tuple[Any, Any]:
            mu = dr.clip(-dr.dot(wo, mei.wi), -1.0, 1.0)
            value = dr.select(active, self._value(mu), 0.0)
            return mi.Spectrum(value), value

        def sample(self, ctx: Any, mei: Any, sample1: Any, sample2: Any, active: Any = True) -> tuple[Any, Any, Any]:
            return _sample_inverse_cdf(mi, dr, self.inv_cdf, self._value, mei, sample2, active)

        def to_string(self) -> str:
            return f"TabulatedPhaseFunction[entries={self.n}]"

    return TabulatedPhaseFunction


def _make_plugin_class(mi: Any, dr: Any) -> type:
    """Build the plugin class for the current variant (Mitsuba types are per variant)."""
    mu_np, w_np = exp_normalisation_nodes()

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
            self._announced: list[float] | None = None
            self._update()

        # --- parameters -------------------------------------------------------
        def traverse(self, callback: Any) -> None:
            for i, v in enumerate(self.b, start=1):
                callback.put(f"b{i}", v, mi.ParamFlags.Differentiable)

        def parameters_changed(self, keys: Any = None) -> None:
            self._update()

        def announce(self, b: Sequence[float]) -> None:
            """The values b_1..b_M that the next parameter update sets, as the float32 the
            device holds (`_update` then need not read them back); used once."""
            if len(b) != self.degree:
                raise ModelParameterError(
                    f"{len(b)} coefficients announced for a phase function of degree {self.degree}")
            self._announced = [float(np.float32(v)) for v in b]

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
            # Inverse-CDF table (detached: it only shapes the importance sampling).
            # The table is built on the host from the coefficients' values. Reading them back
            # from the device makes Dr.Jit wait for every kernel queued before (the renders
            # of a batch of candidates would run one after the other with the cores idle
            # while each is traced), so a caller that knows them says so first (`announce`).
            coeffs = self._announced if self._announced is not None else [float(dr.detach(bi)[0]) for bi in self.b]
            self._announced = None
            self.inv_cdf = mi.Float(inverse_cdf_table(coeffs).astype(np.float32))
            dr.make_opaque(self.inv_cdf)

        @property
        def b0(self) -> float:
            """The normalisation coefficient b_0 = -log(2 pi int exp(sum b_i mu^i) dmu)."""
            return -float(dr.detach(self.log_norm)[0])

        # --- evaluation and sampling -----------------------------------------
        def _value(self, mu: Any) -> Any:
            return dr.exp(self._poly(mu) - self.log_norm)

        def eval_pdf(self, ctx: Any, mei: Any, wo: Any, active: Any = True) -> tuple[Any, Any]:
            mu = dr.clip(-dr.dot(wo, mei.wi), -1.0, 1.0)
            value = dr.select(active, self._value(mu), 0.0)
            return mi.Spectrum(value), dr.detach(value)

        def sample(self, ctx: Any, mei: Any, sample1: Any, sample2: Any, active: Any = True) -> tuple[Any, Any, Any]:
            return _sample_inverse_cdf(mi, dr, self.inv_cdf, self._value, mei, sample2, active)

        def to_string(self) -> str:
            return f"ExponentialPhaseFunction[degree={self.degree}]"

    return ExponentialPhaseFunction


def register_plugins() -> None:
    """Register `exponential_phase` and `tabulated_phase` for the current Mitsuba variant
    (idempotent)."""
    import drjit as dr
    import mitsuba as mi

    variant = mi.variant()
    if variant in _registered:
        return
    cls = _make_plugin_class(mi, dr)
    mi.register_phase(PLUGIN_NAME, lambda props: cls(props))
    tab = _make_tabulated_class(mi, dr)
    mi.register_phase(TABULATED_PLUGIN_NAME, lambda props: tab(props))
    _registered.add(variant)
