"""Model extensions: the physics a base fit may have left out, each switchable by name.

`EXTENSIONS` maps the stable names used in configs, results and reports to their classes;
`get_extension(name)` raises `estimate.errors.ModelParameterError` for an unknown name.
"""

from __future__ import annotations

from estimate.errors import ModelParameterError
from estimate.extensions.angle_offset import AngleOffset
from estimate.extensions.base import (
    Extension,
    ImageExtension,
    ParameterSpec,
    check_value,
)
from estimate.extensions.beam_halo import BeamHalo
from estimate.extensions.filter_bandwidth import FilterBandwidth
from estimate.extensions.lens_blur import LensBlur
from estimate.extensions.refractive_boundary import RefractiveBoundary
from estimate.extensions.sensor_nonlinearity import SensorNonlinearity
from estimate.extensions.stray_light import StrayLight
from estimate.extensions.thickness_error import ThicknessError

__all__ = ["EXTENSIONS", "Extension", "ImageExtension", "ParameterSpec", "check_value", "get_extension"]

EXTENSIONS: dict[str, type[Extension]] = {
    cls.name: cls
    for cls in (RefractiveBoundary, LensBlur, StrayLight, AngleOffset, ThicknessError,
                BeamHalo, SensorNonlinearity, FilterBandwidth)
}

#: Order in which image-space extensions act on the radiance: optics first, then stray
#: light reaching the sensor, then the sensor response.
IMAGE_ORDER = ("lens_blur", "stray_light", "sensor_nonlinearity")


def get_extension(name: str) -> type[Extension]:
    """The extension class for a stable name."""
    try:
        return EXTENSIONS[name]
    except KeyError:
        raise ModelParameterError(
            f"unknown model extension {name!r}; known: {', '.join(sorted(EXTENSIONS))}") from None
