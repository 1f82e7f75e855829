"""Unconstrained parametrisations for the optimiser (Adam works on z, the model on theta).

sigma_t = exp(z) (log); albedo = sigmoid(z) (logit); HG lobes g = 0.99 tanh(z);
lobe weight w = sigmoid(z); exponential coefficients b_i and extension parameters are used
as they are, clamped into their allowed range (`BOUND_B` for b_i: a lobe exp(b mu) with
|b| > 200 is narrower than ~0.1 rad, beyond what a 1 mm slab's profiles resolve).
Extension parameters in the render's radiance units (a stray-light offset, a full-well
radiance) are measured in z in units of `RADIANCE_UNIT` x the render's peak: a render's
radiance scale follows the beam's size and the pixel grid (peak ~1e7 on the simulated rig),
and an absolute step or an absolute eigenvalue floor would leave them where they start.
Each transform also gives the step size Adam uses for it (in z units).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from estimate.extensions.base import ParameterSpec

__all__ = ["BOUND_B", "RADIANCE_UNIT", "Transform", "transform_for"]

BOUND_B = 200.0
#: z unit of radiance-valued parameters, as a fraction of the render's peak radiance.
RADIANCE_UNIT = 0.01
_EPS = 1e-6


def _sigmoid(z: float) -> float:
    return 1.0 / (1.0 + math.exp(-z)) if z >= 0 else math.exp(z) / (1.0 + math.exp(z))


@dataclass(frozen=True)
class Transform:
    kind: str          # "log", "logit", "tanh", "linear"
    lr: float          # Adam step size in z
    lower: float = -math.inf
    upper: float = math.inf
    unit: float = 1.0  # "linear": x = unit * z

    def to_z(self, x: float) -> float:
        if self.kind == "log":
            return math.log(max(x, 1e-12))
        if self.kind == "logit":
            p = min(max(x, _EPS), 1 - _EPS)
            return math.log(p / (1 - p))
        if self.kind == "tanh":
            return math.atanh(min(max(x / 0.99, -1 + _EPS), 1 - _EPS))
        return min(max(x, self.lower), self.upper) / self.unit

    def to_x(self, z: float) -> float:
        if self.kind == "log":
            return math.exp(min(z, 50.0))
        if self.kind == "logit":
            return min(max(_sigmoid(z), _EPS), 1 - _EPS)
        if self.kind == "tanh":
            return 0.99 * math.tanh(z)
        return min(max(z * self.unit, self.lower), self.upper)

    def dx_dz(self, z: float) -> float:
        if self.kind == "log":
            return math.exp(min(z, 50.0))
        if self.kind == "logit":
            s = _sigmoid(z)
            return s * (1 - s)
        if self.kind == "tanh":
            return 0.99 * (1 - math.tanh(z) ** 2)
        return self.unit

    def clamp_z(self, z: float) -> float:
        if self.kind == "linear":
            return min(max(z * self.unit, self.lower), self.upper) / self.unit
        return min(max(z, -30.0), 30.0)


def transform_for(name: str, spec: ParameterSpec, peak_radiance: float | None = None,
                  length_mm: float | None = None) -> Transform:
    """The transform and Adam step of a ForwardModel parameter.

    `peak_radiance`: the render's peak (its own units), for parameters in radiance units
    (`spec.unit` "radiance", "radiance/mm"); None keeps them in absolute units.
    `length_mm`: for a radiance gradient ("radiance/mm", the stray light's slope), the
    distance over which one z unit of it changes the radiance by one z unit of an offset:
    the profile's half-width. Without it the slope's step was per mm, and on the simulated
    bench's 17 mm wide profile one Adam step (0.3 % of the peak per mm) was 7x the true slope
    and moved the background at the profile's ends by 8x the offset's step.
    """
    if name == "sigma_t":
        return Transform("log", 0.08)
    if name == "albedo":
        return Transform("logit", 0.15)
    if name in ("phase.g", "phase.g_forward", "phase.g_backward"):
        return Transform("tanh", 0.04)
    if name == "phase.w_forward":
        return Transform("logit", 0.08)
    if name.startswith("phase.b"):
        return Transform("linear", 0.15, -BOUND_B, BOUND_B)
    lo = spec.lower + (1e-9 if spec.open_lower else 0.0)
    if peak_radiance and peak_radiance > 0 and spec.unit.startswith("radiance"):
        # Steps of 0.3 % of the peak per Adam iteration; Gauss-Newton sees O(1) columns.
        unit = RADIANCE_UNIT * float(peak_radiance)
        if spec.unit.startswith("radiance/") and length_mm and length_mm > 0:
            unit /= float(length_mm)
        return Transform("linear", 0.3, lo, spec.upper, unit)
    return Transform("linear", 3.0 * spec.fd_step, lo, spec.upper)
