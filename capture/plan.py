"""The capture plan: which stage angles and filters, and the steps that measure them.

Angles (degrees, DESIGN.md convention: the source direction is
(sin phi, 0, cos phi); the camera sits on the +z side):

* front-lighting angles lie in ``front_range_deg`` (default 15..75), the
  camera's side; back-lighting angles in ``back_range_deg`` (default 105..165).
* both ranges must keep out of the camera's cone: ``phi >= cone_half_angle_deg``
  (a source near phi = 0 stands in front of the lens) and
  ``phi <= 180 - cone_half_angle_deg`` (near phi = 180 the unscattered beam
  goes straight through the slab into the lens). Default cone: 10 degrees.
  Ranges may not reach 90 degrees (grazing incidence lights no spot).
* N angles are split ``n_front = ceil(N/2)`` front and the rest back unless
  given (the paper used 5 front and 5 back), each evenly spaced over its range
  including the ends (one angle sits at the range's middle).

Steps are plain dataclasses yielded by the generator :func:`plan_steps`
(bluesky-plan style); :mod:`capture.executor` runs them. Filters are the inner
loop (moving the stage is slower than turning the wheel), in serpentine order
(r g b, then b g r, ...) so each new angle starts with the filter already in
the beam.
"""

from __future__ import annotations

import math
from collections.abc import Container, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from capture.bracket import BracketPolicy
from capture.errors import PlanError
from drivers.interfaces import AngleRange

DEFAULT_FRONT_RANGE_DEG = (15.0, 75.0)
DEFAULT_BACK_RANGE_DEG = (105.0, 165.0)
DEFAULT_CONE_HALF_ANGLE_DEG = 10.0


#: A calibrated rotation zero further than this from 180 deg (degrees) is not a beam pointed
#: into the lens: such a stage offset is refused (capture) or ignored (estimate).
MAX_STAGE_OFFSET_DEG = 20.0


@dataclass(frozen=True)
class StackKey:
    """Identifies one stack: the index of its angle in the plan and the filter name."""

    angle_index: int
    filter: str

    @property
    def id(self) -> str:
        """File-name-safe id, e.g. ``a03_g``."""
        return f"a{self.angle_index:02d}_{self.filter}"


@dataclass(frozen=True)
class AngleSpec:
    """What the operator asks for (``rig capture --angles N --filters rgb``)."""

    n_angles: int = 10
    filters: tuple[str, ...] = ("r", "g", "b")
    n_front: int | None = None
    front_range_deg: tuple[float, float] = DEFAULT_FRONT_RANGE_DEG
    back_range_deg: tuple[float, float] = DEFAULT_BACK_RANGE_DEG
    cone_half_angle_deg: float = DEFAULT_CONE_HALF_ANGLE_DEG


@dataclass(frozen=True)
class CapturePlan:
    """A checked plan: angles (degrees) in acquisition order, filters, bracket policy.

    ``angles_deg`` are world angles phi (the beam's direction in the slab's frame, what the
    estimator models). The stage is commanded to ``phi + stage_offset_deg``: the beam
    calibration finds the stage angle at which the beam points straight into the lens
    (``rotation_zero_deg``, world phi = 180), so ``stage_offset_deg = rotation_zero_deg - 180``.
    A plan made without a calibration has offset 0 (stage angle = world angle).
    """

    angles_deg: tuple[float, ...]
    filters: tuple[str, ...]
    bracket: BracketPolicy = field(default_factory=BracketPolicy)
    n_front: int = 0
    front_range_deg: tuple[float, float] = DEFAULT_FRONT_RANGE_DEG
    back_range_deg: tuple[float, float] = DEFAULT_BACK_RANGE_DEG
    cone_half_angle_deg: float = DEFAULT_CONE_HALF_ANGLE_DEG
    stage_offset_deg: float = 0.0

    def stage_angle(self, index: int) -> float:
        """Stage angle (degrees) that puts the beam at world angle ``angles_deg[index]``."""
        return float(self.angles_deg[index]) + float(self.stage_offset_deg)

    def keys(self) -> list[StackKey]:
        """Every stack of the plan in acquisition order."""
        out: list[StackKey] = []
        for i in range(len(self.angles_deg)):
            order = self.filters if i % 2 == 0 else tuple(reversed(self.filters))
            out.extend(StackKey(i, f) for f in order)
        return out

    def to_dict(self) -> dict[str, Any]:
        return {
            "angles_deg": [float(a) for a in self.angles_deg],
            "filters": list(self.filters),
            "n_front": int(self.n_front),
            "front_range_deg": [float(x) for x in self.front_range_deg],
            "back_range_deg": [float(x) for x in self.back_range_deg],
            "cone_half_angle_deg": float(self.cone_half_angle_deg),
            "stage_offset_deg": float(self.stage_offset_deg),
            "bracket": self.bracket.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CapturePlan:
        return cls(
            angles_deg=tuple(float(a) for a in d["angles_deg"]),
            filters=tuple(str(f) for f in d["filters"]),
            bracket=BracketPolicy.from_dict(d.get("bracket", {})),
            n_front=int(d.get("n_front", 0)),
            front_range_deg=tuple(d.get("front_range_deg", DEFAULT_FRONT_RANGE_DEG)),  # type: ignore[arg-type]
            back_range_deg=tuple(d.get("back_range_deg", DEFAULT_BACK_RANGE_DEG)),  # type: ignore[arg-type]
            cone_half_angle_deg=float(d.get("cone_half_angle_deg", DEFAULT_CONE_HALF_ANGLE_DEG)),
            # sessions written before the offset was recorded commanded the world angle
            stage_offset_deg=float(d.get("stage_offset_deg", 0.0)),
        )


def _spaced(lo: float, hi: float, n: int) -> list[float]:
    if n == 0:
        return []
    if n == 1:
        return [0.5 * (lo + hi)]
    return [lo + (hi - lo) * k / (n - 1) for k in range(n)]


def _check_range(name: str, rng: Sequence[float], lo_ok: float, hi_ok: float) -> tuple[float, float]:
    if len(rng) != 2 or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in rng):
        raise PlanError(f"{name} range must be two finite angles in degrees, got {rng!r}")
    lo, hi = float(rng[0]), float(rng[1])
    if lo > hi:
        raise PlanError(f"{name} range [{lo:g}, {hi:g}] deg is reversed")
    if lo < lo_ok or hi > hi_ok:
        raise PlanError(
            f"{name} range [{lo:g}, {hi:g}] deg leaves [{lo_ok:g}, {hi_ok:g}] deg "
            "(it must avoid the camera's cone and grazing incidence at 90 deg)"
        )
    return lo, hi


def make_plan(
    spec: AngleSpec,
    *,
    available_filters: Sequence[str],
    stage_range: AngleRange,
    bracket: BracketPolicy | None = None,
    exposure_range_s: tuple[float, float] | None = None,
    stage_offset_deg: float = 0.0,
) -> CapturePlan:
    """Check a request and make the plan; nothing touches hardware.

    Args:
        spec: angle count, split, ranges, camera cone, filters.
        available_filters: names the filter changer knows (``FilterChanger.names()``).
        stage_range: the stage's allowed range (``RotationStage.allowed_range``).
        bracket: exposure policy (default :class:`BracketPolicy`); its open exposure
            limits are filled in from ``exposure_range_s``.
        exposure_range_s: the camera's exposure range (``Camera.exposure_range_s``).
        stage_offset_deg: stage angle minus world angle (degrees): the beam calibration's
            ``rotation_zero_deg - 180``; 0 without a calibration.

    Raises:
        PlanError: the count or a range cannot be planned, a filter is unknown or
            repeated, an angle is outside the stage's allowed range, or the
            bracket policy is inconsistent.
    """
    bracket = (bracket or BracketPolicy()).resolved(exposure_range_s)
    if not isinstance(spec.n_angles, int) or spec.n_angles < 1:
        raise PlanError(f"the number of angles must be a positive integer, got {spec.n_angles!r}")
    cone = spec.cone_half_angle_deg
    if not (math.isfinite(cone) and 0.0 <= cone < 90.0):
        raise PlanError(f"camera cone half-angle must be in [0, 90) deg, got {cone}")
    n_front = spec.n_front if spec.n_front is not None else math.ceil(spec.n_angles / 2)
    n_back = spec.n_angles - n_front
    if not 0 <= n_front <= spec.n_angles:
        raise PlanError(f"cannot split {spec.n_angles} angles into {n_front} front-lighting angles")
    front = _check_range("front-lighting", spec.front_range_deg, cone, 90.0 - 1e-9) if n_front else tuple(spec.front_range_deg)
    back = _check_range("back-lighting", spec.back_range_deg, 90.0 + 1e-9, 180.0 - cone) if n_back else tuple(spec.back_range_deg)
    for name, n, (lo, hi) in (("front-lighting", n_front, front), ("back-lighting", n_back, back)):
        if n > 1 and lo == hi:
            raise PlanError(f"{n} {name} angles cannot fit in the zero-width range [{lo:g}, {hi:g}] deg")
    angles = _spaced(front[0], front[1], n_front) + _spaced(back[0], back[1], n_back)
    if len({round(a, 9) for a in angles}) != len(angles):
        raise PlanError("the plan repeats an angle")

    filters = tuple(spec.filters)
    if not filters:
        raise PlanError("no filters requested")
    if len(set(filters)) != len(filters):
        raise PlanError(f"filter list repeats a filter: {''.join(filters) if all(len(f) == 1 for f in filters) else filters}")
    unknown = [f for f in filters if f not in available_filters]
    if unknown:
        raise PlanError(f"unknown filter {unknown[0]!r}; the filter changer has: {', '.join(available_filters)}")
    if not math.isfinite(stage_offset_deg):
        raise PlanError(f"stage offset {stage_offset_deg!r} deg must be finite")
    outside = [a for a in angles if a + stage_offset_deg not in stage_range]
    if outside:
        a = outside[0]
        at = f" (stage angle {a + stage_offset_deg:g} deg after the calibrated zero)" if stage_offset_deg else ""
        raise PlanError(
            f"angle {a:g} deg{at} is outside the stage's allowed range "
            f"[{stage_range.lo:g}, {stage_range.hi:g}] deg; narrow --front-range / --back-range "
            "or widen stage.allowed_range_deg in rig.yaml"
        )
    return CapturePlan(
        angles_deg=tuple(angles),
        filters=filters,
        bracket=bracket,
        n_front=n_front,
        front_range_deg=(float(front[0]), float(front[1])),
        back_range_deg=(float(back[0]), float(back[1])),
        cone_half_angle_deg=float(cone),
        stage_offset_deg=float(stage_offset_deg),
    )


# --------------------------------------------------------------------------- steps


@dataclass(frozen=True)
class Home:
    """Drive the stage to its mechanical origin."""


@dataclass(frozen=True)
class Move:
    """Move the stage to ``angle_deg`` (degrees, the stage's own angle)."""

    angle_deg: float


@dataclass(frozen=True)
class SelectFilter:
    """Put filter ``name`` in the beam."""

    name: str


@dataclass(frozen=True)
class Bracket:
    """Take the automatic exposure bracket of stack ``key``."""

    key: StackKey
    policy: BracketPolicy


@dataclass(frozen=True)
class Dark:
    """Take ``n`` dark frames at every exposure time of the bracket of stack ``key``."""

    key: StackKey
    n: int


@dataclass(frozen=True)
class SaveStack:
    """Merge stack ``key`` and write it (raw frames, HDR image, manifest).

    ``angle_deg`` is the world angle of the stack, ``stage_angle_deg`` the stage angle it
    was taken at (None: the same)."""

    key: StackKey
    angle_deg: float
    stage_angle_deg: float | None = None


Step = Home | Move | SelectFilter | Bracket | Dark | SaveStack


def plan_steps(plan: CapturePlan, *, done: Container[StackKey] = frozenset(), home: bool = True) -> Iterator[Step]:
    """Yield the steps that measure every stack of ``plan`` not in ``done``.

    An angle whose stacks are all done is not visited at all.
    """
    if home:
        yield Home()
    keys = plan.keys()
    for i, angle in enumerate(plan.angles_deg):
        todo = [k for k in keys if k.angle_index == i and k not in done]
        if not todo:
            continue
        stage_angle = plan.stage_angle(i)
        yield Move(stage_angle)
        for key in todo:
            yield SelectFilter(key.filter)
            yield Bracket(key, plan.bracket)
            yield Dark(key, plan.bracket.n_darks)
            yield SaveStack(key, angle, stage_angle)
