"""Extension `lens_blur`: point-spread function of lens and sensor, in image space.

PSF = (1 - tail_fraction) * core + tail_fraction * tail, both normalised:
- core: Gaussian of standard deviation `core_sigma_px` (0 = a delta: no core blur);
- tail (veiling glare): 2D kernel (1 + r^2 / s^2)^(-3/2), s = `tail_scale_px`, whose line
  spread function is the Lorentzian 1 / (1 + x^2 / s^2).
Both are truncated at `TRUNCATION_PX` and renormalised. Full frames are blurred in 2D;
a single rendered profile row is blurred with the line-spread function (this treats the
image as constant along y over the PSF: exact for the tail of a spot much taller than
the PSF, an approximation near a narrow spot's peak; render a band and blur in 2D when
that matters). Zero padding outside the rendered window. The PSF is symmetric, so the
operator is self-adjoint. Derivative: exact through this image function.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from scipy import ndimage, signal

from estimate.extensions.base import ImageExtension, ParameterSpec

__all__ = ["TRUNCATION_PX", "LensBlur", "line_spread", "psf_2d"]

TRUNCATION_PX = 64


def _gauss(x: np.ndarray, s: float) -> np.ndarray:
    if s <= 0:
        return (x == 0).astype(float)
    return np.exp(-0.5 * (x / s) ** 2)


def line_spread(values: Mapping[str, float], radius: int = TRUNCATION_PX) -> np.ndarray:
    """1D kernel (odd length 2*radius+1), sums to 1."""
    x = np.arange(-radius, radius + 1, dtype=float)
    core = _gauss(x, values["core_sigma_px"])
    core /= core.sum()
    tail = 1.0 / (1.0 + (x / values["tail_scale_px"]) ** 2)
    tail /= tail.sum()
    f = values["tail_fraction"]
    return (1.0 - f) * core + f * tail


def psf_2d(values: Mapping[str, float], radius: int = TRUNCATION_PX) -> np.ndarray:
    """2D kernel (2*radius+1 square), sums to 1."""
    x = np.arange(-radius, radius + 1, dtype=float)
    xx, yy = np.meshgrid(x, x)
    core = _gauss(xx, values["core_sigma_px"]) * _gauss(yy, values["core_sigma_px"])
    core /= core.sum()
    tail = (1.0 + (xx ** 2 + yy ** 2) / values["tail_scale_px"] ** 2) ** -1.5
    tail /= tail.sum()
    f = values["tail_fraction"]
    return (1.0 - f) * core + f * tail


class LensBlur(ImageExtension):
    name = "lens_blur"
    parameters = (
        ParameterSpec("core_sigma_px", 0.0, 0.0, 20.0, "px", "image", 0.05,
                      "standard deviation of the sharp core"),
        ParameterSpec("tail_fraction", 0.0, 0.0, 0.5, "", "image", 0.002,
                      "fraction of the light in the long tail"),
        ParameterSpec("tail_scale_px", 20.0, 0.0, 200.0, "px", "image", 0.5,
                      "scale of the tail", open_lower=True),
    )

    @classmethod
    def apply(cls, image: np.ndarray, values: Mapping[str, float], *, pixel_mm: float,
              profile_only: bool) -> np.ndarray:
        img = np.asarray(image, dtype=np.float64)
        if values["core_sigma_px"] == 0 and values["tail_fraction"] == 0:
            return img.copy()
        if profile_only or img.shape[-2] == 1:
            return ndimage.convolve1d(img, line_spread(values), axis=-1, mode="constant")
        k = psf_2d(values)
        k = k.reshape((1,) * (img.ndim - 2) + k.shape)
        return signal.fftconvolve(img, k, mode="same", axes=(-2, -1))

    @classmethod
    def vjp_input(cls, image: np.ndarray, cotangent: np.ndarray, values: Mapping[str, float], *,
                  pixel_mm: float, profile_only: bool) -> np.ndarray:
        return cls.apply(cotangent, values, pixel_mm=pixel_mm, profile_only=profile_only)
