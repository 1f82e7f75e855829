"""Extension `thickness_error`: true thickness = nominal x (1 + e).

Derivative: finite differences (a moving boundary; prbvolpath has no boundary terms).
"""

from __future__ import annotations

from estimate.extensions.base import Extension, ParameterSpec

__all__ = ["ThicknessError"]


class ThicknessError(Extension):
    name = "thickness_error"
    kind = "scene"
    neutral_is_identity = True
    parameters = (
        ParameterSpec("e", 0.0, -0.9, 2.0, "", "fd", 0.02,
                      "relative thickness error; thickness = nominal * (1 + e)"),
    )
