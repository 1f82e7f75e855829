"""Extension `angle_offset`: every stage angle off by the same delta (rotation zero error).

The beam is rendered at phi + delta_deg. Derivative: finite differences (the beam direction
enters next-event estimation detached, so Mitsuba's gradient would miss most of it).
"""

from __future__ import annotations

from estimate.extensions.base import Extension, ParameterSpec

__all__ = ["AngleOffset"]


class AngleOffset(Extension):
    name = "angle_offset"
    kind = "scene"
    neutral_is_identity = True
    parameters = (
        ParameterSpec("delta_deg", 0.0, -20.0, 20.0, "deg", "fd", 0.25,
                      "added to every stage angle"),
    )
