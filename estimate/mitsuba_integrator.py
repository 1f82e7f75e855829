"""`rig_prbvolpath`: Mitsuba's `prbvolpath` with the batch-sensor index carried in ray time.

All stage angles of a call are rendered in one launch with a `batch` sensor of identical
orthographic sub-cameras looking at the one slab (at the origin). Each camera ray gets
the index k of its sub-camera (its film column block) as its `time`, which every
interaction along the path inherits; the beam emitter (`estimate.beam`) reads it to light
the path with the k-th angle. Nothing else in the rig's scene depends on time.

(Slab copies side by side were tried first: Mitsuba's ray-spawn offsets grow with the
coordinates' magnitude, (1 + max|p|) * 8.9e-5 mm, and at 50-200 mm from the origin they
skipped enough medium below the face to dim a copy by 4-16 %.)
"""

from __future__ import annotations

from typing import Any

__all__ = ["PLUGIN_NAME", "register_plugins"]

PLUGIN_NAME = "rig_prbvolpath"
_registered: set[str] = set()


def register_plugins() -> None:
    """Register `rig_prbvolpath` for the current variant (idempotent)."""
    import drjit as dr
    import mitsuba as mi
    from mitsuba.python.ad.integrators.prbvolpath import PRBVolpathIntegrator

    variant = mi.variant()
    if variant in _registered:
        return

    class RigPRBVolpathIntegrator(PRBVolpathIntegrator):
        """prbvolpath; props `copies` (sub-cameras side by side) and `copy_width` (pixels)."""

        def __init__(self, props: Any) -> None:
            super().__init__(props)
            self.copies = int(props.get("copies", 1))
            self.copy_width = int(props.get("copy_width", 1))

        def sample_rays(self, scene: Any, sensor: Any, sampler: Any) -> Any:
            ray, weight, pos = super().sample_rays(scene, sensor, sampler)
            if self.copies > 1:
                k = dr.clip(dr.floor(pos.x / self.copy_width), 0, self.copies - 1)
                ray.time = mi.Float(k)
            else:
                ray.time = mi.Float(0.0)
            return ray, weight, pos

    mi.register_integrator(PLUGIN_NAME, lambda props: RigPRBVolpathIntegrator(props))
    _registered.add(variant)
