"""Common form of a model extension: named parameters whose neutral value means "absent".

Each extension is a small module defining one `Extension` subclass. Three kinds:

- ``scene``: changes the Mitsuba scene (refractive_boundary, beam_halo, filter_bandwidth,
  angle_offset, thickness_error); the forward model reads its values when rendering.
- ``image``: acts on the rendered radiance in image space (lens_blur, stray_light,
  sensor_nonlinearity); it provides `apply` and the pull-back of a cotangent (`vjp_input`)
  so that gradients of scene parameters pass through it.

`derivative` of each parameter says how the forward model differentiates it:
``ad`` (Dr.Jit reverse mode through the render), ``image`` (exact, through the image-space
function), ``fd`` (central finite difference with common random numbers: geometric
parameters whose Mitsuba derivative is missing or biased, e.g. directions detached in
next-event estimation, the boundary position, the dielectric index).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, TypedDict

import numpy as np

from estimate.errors import ModelParameterError

__all__ = ["BeamFill", "Extension", "ImageExtension", "ParameterSpec", "RowData", "check_value", "no_row_data"]


@dataclass(frozen=True)
class ParameterSpec:
    """One extension parameter.

    Attributes:
        name: short name; the full name is "<extension>.<name>".
        neutral: value at which the effect is absent (or a harmless shape default).
        lower, upper: allowed range (inclusive unless `open_lower`).
        unit: unit string for reports.
        derivative: "ad", "image" or "fd" (see module doc).
        fd_step: absolute finite-difference step for "fd" / default step.
        doc: one line.
        additive: the effect adds `value x a fixed image` to the render (linear in this
            parameter, the same image whatever the scene): a fit can solve for it exactly at
            every iteration instead of stepping it (`ForwardModel.additive_parameters`).
    """

    name: str
    neutral: float
    lower: float
    upper: float
    unit: str
    derivative: str
    fd_step: float
    doc: str
    open_lower: bool = False
    additive: bool = False


def check_value(full_name: str, value: float, spec: ParameterSpec) -> float:
    """Validate one value; raises ModelParameterError naming the parameter."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ModelParameterError(f"{full_name}={value!r} is not a number") from None
    if math.isnan(v):
        raise ModelParameterError(f"{full_name} is NaN")
    if v < spec.lower or (spec.open_lower and v == spec.lower) or v > spec.upper:
        lo = "(" if spec.open_lower else "["
        raise ModelParameterError(
            f"{full_name}={v:g} outside its allowed range {lo}{spec.lower:g}, {spec.upper:g}] {spec.unit}")
    return v


class Extension:
    """A left-out effect; subclasses set `name`, `kind`, `parameters`."""

    name: ClassVar[str]
    kind: ClassVar[str]  # "scene" or "image"
    parameters: ClassVar[tuple[ParameterSpec, ...]]
    #: At its neutral values the extension leaves a render bit for bit as the model without
    #: it renders it at the same seed and spp: it draws no random numbers of its own and
    #: changes no path (an angle offset of 0, a thickness error of 0, a halo of no power, a
    #: lens blur of zero width whose beam map is then the calibrated one, a filter band of
    #: no spread, rendered as one wavelength). The screening then shares one render as the
    #: base of these candidates' secants (`estimate.diagnose._screen`);
    #: tests/test_extensions.py holds each to it. False where the neutral scene differs in
    #: its sampling (an index-matched dielectric boundary draws a reflection decision).
    neutral_is_identity: ClassVar[bool] = False

    @classmethod
    def full_names(cls) -> list[str]:
        return [f"{cls.name}.{p.name}" for p in cls.parameters]

    @classmethod
    def neutral_values(cls) -> dict[str, float]:
        return {f"{cls.name}.{p.name}": p.neutral for p in cls.parameters}

    @classmethod
    def spec(cls, short: str) -> ParameterSpec:
        for p in cls.parameters:
            if p.name == short:
                return p
        raise ModelParameterError(f"extension {cls.name} has no parameter {short!r}")

    @classmethod
    def values(cls, params: Mapping[str, float]) -> dict[str, float]:
        """This extension's values (short names) from a full parameter mapping, validated."""
        out = {}
        for p in cls.parameters:
            full = f"{cls.name}.{p.name}"
            out[p.name] = check_value(full, params.get(full, p.neutral), p)
        return out


@dataclass(frozen=True)
class BeamFill:
    """The beam calibration frame as the sensor read it, for effects of the sensor that also
    act on the calibration (`estimate.extensions.sensor_nonlinearity.calibration_gain`).

    Attributes:
        weights: each beam-map pixel's share of the measured beam power, shape (P,), sum 1.
        fill: the calibration merge's mean squared fill of the well at those pixels, shape
            (P,) (`estimate.problem.merge_fill_from_rows` over the map's rows).
        pixels: the map as read, the calibration frame's pixels (e-/s, >= 0), shape (H, W);
            None when only the power is to be corrected.
        fill_map: the merge's fill at every pixel of `pixels`, shape (H, W).
        to_profile: how `estimate.problem` turns such a pixel image into the beam profile
            the renderer takes (`estimate.beam.BeamProfile.from_camera_image` of the map
            with the pixel integration undone), for a map decompressed at a compression.
        source: where the fills come from: "kept frames" (the exposures the calibration's
            merge kept, recounted from its light frames) or "replayed" (from the map and
            its bracket alone).
    """

    weights: np.ndarray
    fill: np.ndarray
    pixels: np.ndarray | None = None
    fill_map: np.ndarray | None = None
    to_profile: Callable[[np.ndarray], Any] | None = None
    source: str = "replayed"


class RowData(TypedDict):
    """What image-space extensions take from the recording about the profile rows (the
    keyword arguments `y_shape` and `merge_fill` of `ImageExtension` methods), and about the
    beam calibration (`beam_fill`, every window)."""

    y_shape: np.ndarray | None
    merge_fill: np.ndarray | None
    beam_fill: BeamFill | None
    core_in_scene: bool


def no_row_data() -> RowData:
    """Nothing from the recording (full frames, other windows, a model without a problem)."""
    return {"y_shape": None, "merge_fill": None, "beam_fill": None, "core_in_scene": False}


class ImageExtension(Extension):
    """An image-space effect on radiance arrays shaped (..., H, W).

    `y_shape` (profile renders only, else None): the recorded image's shape across the rows
    around the profile row, per image row, shaped (N, 2 TRUNCATION_PX + 1, W) with N the
    leading size of `image` (`estimate.problem.Problem.y_shape`). Only effects that mix
    rows (the lens blur) use it; the others ignore it.

    `merge_fill` (profile renders only, else None): per profile pixel, the HDR merge's mean
    (fill of the well)^2 over the exposures it read, shaped (N, W)
    (`estimate.problem.merge_fill_from_rows`). Only the sensor's compression uses it.

    `beam_fill` (any window; None when unknown): the beam calibration frame's power shares
    and merge fills (`BeamFill`). Only the sensor's compression uses it: the calibration
    frame went through the same sensor.

    `core_in_scene` (single-row renders only): the render was lit by the beam map blurred
    along y by the lens blur's core (`ForwardModel.core_blur_in_scene`), so the core's y
    part is in the image already. Only the lens blur uses it.
    """

    kind = "image"

    @classmethod
    def apply(cls, image: np.ndarray, values: Mapping[str, float], *, pixel_mm: float,
              profile_only: bool, y_shape: np.ndarray | None = None,
              merge_fill: np.ndarray | None = None,
              beam_fill: BeamFill | None = None, core_in_scene: bool = False) -> np.ndarray:
        raise NotImplementedError

    @classmethod
    def vjp_input(cls, image: np.ndarray, cotangent: np.ndarray, values: Mapping[str, float], *,
                  pixel_mm: float, profile_only: bool, y_shape: np.ndarray | None = None,
              merge_fill: np.ndarray | None = None,
              beam_fill: BeamFill | None = None, core_in_scene: bool = False) -> np.ndarray:
        """Cotangent w.r.t. the input image given one w.r.t. the output."""
        raise NotImplementedError

    @classmethod
    def param_derivatives(cls, image: np.ndarray, values: Mapping[str, float], *, pixel_mm: float,
                          profile_only: bool, y_shape: np.ndarray | None = None,
              merge_fill: np.ndarray | None = None,
              beam_fill: BeamFill | None = None, core_in_scene: bool = False) -> dict[str, np.ndarray]:
        """d output / d parameter for each parameter (central differences of this exact,
        deterministic image function with a small relative step; no rendering noise)."""
        out = {}
        for p in cls.parameters:
            h = 1e-4 * max(1.0, abs(values[p.name]))
            lo = dict(values)
            hi = dict(values)
            base = values[p.name]
            a = max(p.lower, base - h) if not p.open_lower else max(p.lower + 1e-12, base - h)
            b = min(p.upper, base + h)
            lo[p.name] = a
            hi[p.name] = b
            out[p.name] = (cls.apply(image, hi, pixel_mm=pixel_mm, profile_only=profile_only, y_shape=y_shape,
                                     merge_fill=merge_fill, beam_fill=beam_fill, core_in_scene=core_in_scene)
                           - cls.apply(image, lo, pixel_mm=pixel_mm, profile_only=profile_only, y_shape=y_shape,
                                       merge_fill=merge_fill, beam_fill=beam_fill, core_in_scene=core_in_scene)
                           ) / (b - a)
        return out
