"""Extension `sensor_nonlinearity`: response compression near full well.

Raw frames (simulated camera): electrons x -> x * (1 - c * (x / full_well)^2), monotone
for c < 1/3; c = `compression` = relative loss at full well (`apply_raw`).

Effect on a merged HDR profile (for the model): the merge reads the brightest pixels from
the shortest exposure, where they are compressed most; dimmer pixels come from longer
exposures at levels the bracket keeps below full well. Modelled as
I -> I * (1 - c * min(I / W, 1)^2) with W = `full_well_radiance`, the HDR radiance that
fills the well in the shortest exposure (profile units). This assumes each pixel is
read from the shortest exposure, an upper bound on the compression of dim pixels.
Derivative: exact.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from estimate.errors import ModelParameterError
from estimate.extensions.base import ImageExtension, ParameterSpec

__all__ = ["SensorNonlinearity", "apply_raw"]


def apply_raw(frame_electrons: np.ndarray, compression: float, full_well_e: float) -> np.ndarray:
    """Compressed raw response of a frame in electrons (values above full well clip there)."""
    if not (0.0 <= compression < 1.0 / 3.0):
        raise ModelParameterError(f"sensor_nonlinearity.compression={compression!r} must be in [0, 1/3)")
    if not full_well_e > 0:
        raise ModelParameterError(f"sensor full_well_e={full_well_e!r} must be > 0")
    x = np.clip(np.asarray(frame_electrons, dtype=np.float64), 0.0, full_well_e)
    return x * (1.0 - compression * (x / full_well_e) ** 2)


class SensorNonlinearity(ImageExtension):
    name = "sensor_nonlinearity"
    parameters = (
        ParameterSpec("compression", 0.0, 0.0, 0.33, "", "image", 1e-3,
                      "relative response loss at full well"),
        ParameterSpec("full_well_radiance", 1.0, 0.0, float("inf"), "radiance", "image", 1e-3,
                      "HDR radiance filling the well in the shortest exposure", open_lower=True),
    )

    @classmethod
    def apply(cls, image: np.ndarray, values: Mapping[str, float], *, pixel_mm: float,
              profile_only: bool, y_shape: np.ndarray | None = None) -> np.ndarray:
        img = np.asarray(image, dtype=np.float64)
        r = np.clip(img / values["full_well_radiance"], 0.0, 1.0)
        return img * (1.0 - values["compression"] * r ** 2)

    @classmethod
    def vjp_input(cls, image: np.ndarray, cotangent: np.ndarray, values: Mapping[str, float], *,
                  pixel_mm: float, profile_only: bool, y_shape: np.ndarray | None = None) -> np.ndarray:
        img = np.asarray(image, dtype=np.float64)
        w = values["full_well_radiance"]
        r = img / w
        below = (r >= 0) & (r <= 1)
        slope = np.where(below, 1.0 - 3.0 * values["compression"] * r ** 2,
                         1.0 - values["compression"] * np.where(r > 1, 1.0, 0.0))
        return np.asarray(cotangent) * slope
