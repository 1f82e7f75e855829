"""Extension `stray_light`: additive background, constant or slowly varying across the row.

I(x) + offset + slope_per_mm * x, x in mm from the rendered window's centre (object
space), constant along y. Units: the render's radiance units. Derivative: exact.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from estimate.extensions.base import BeamFill, ImageExtension, ParameterSpec

__all__ = ["StrayLight"]


class StrayLight(ImageExtension):
    name = "stray_light"
    parameters = (
        ParameterSpec("offset", 0.0, 0.0, float("inf"), "radiance", "image", 1e-4,
                      "constant background", additive=True),
        ParameterSpec("slope_per_mm", 0.0, float("-inf"), float("inf"), "radiance/mm", "image", 1e-4,
                      "linear variation across the row", additive=True),
    )

    @staticmethod
    def _x_mm(width: int, pixel_mm: float) -> np.ndarray:
        return (np.arange(width) + 0.5 - 0.5 * width) * pixel_mm

    @classmethod
    def apply(cls, image: np.ndarray, values: Mapping[str, float], *, pixel_mm: float,
              profile_only: bool, y_shape: np.ndarray | None = None,
              merge_fill: np.ndarray | None = None,
              beam_fill: BeamFill | None = None, core_in_scene: bool = False) -> np.ndarray:
        img = np.asarray(image, dtype=np.float64)
        x = cls._x_mm(img.shape[-1], pixel_mm)
        return img + values["offset"] + values["slope_per_mm"] * x

    @classmethod
    def vjp_input(cls, image: np.ndarray, cotangent: np.ndarray, values: Mapping[str, float], *,
                  pixel_mm: float, profile_only: bool, y_shape: np.ndarray | None = None,
              merge_fill: np.ndarray | None = None,
              beam_fill: BeamFill | None = None, core_in_scene: bool = False) -> np.ndarray:
        return np.asarray(cotangent, dtype=np.float64)

    @classmethod
    def param_derivatives(cls, image: np.ndarray, values: Mapping[str, float], *, pixel_mm: float,
                          profile_only: bool, y_shape: np.ndarray | None = None,
              merge_fill: np.ndarray | None = None,
              beam_fill: BeamFill | None = None, core_in_scene: bool = False) -> dict[str, np.ndarray]:
        img = np.asarray(image, dtype=np.float64)
        x = cls._x_mm(img.shape[-1], pixel_mm)
        return {"offset": np.ones_like(img), "slope_per_mm": np.broadcast_to(x, img.shape).copy()}
