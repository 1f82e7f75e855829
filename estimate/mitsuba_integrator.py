"""`rig_prbvolpath`: Mitsuba's `prbvolpath` with the batch-sensor index carried in ray time.

All stage angles of a call are rendered in one launch with a `batch` sensor of identical
orthographic sub-cameras looking at the one slab (at the origin). Each camera ray gets
the index k of its sub-camera (its film column block) as its `time`, which every
interaction along the path inherits; the beam emitter (`estimate.beam`) reads it to light
the path with the k-th angle. Nothing else in the rig's scene depends on time.

`render_kept` / `backward_kept` split Mitsuba's path-replay `render_backward` into its two
halves: the primal pass (whose image is the same as `mi.render`'s at the same seed) and the
adjoint replay, run later with a cotangent that may depend on other renders. The fitter
needs the image of a render before it knows the cotangent for that render's paths (the
decorrelated loss pairs two renders), and `render_backward` repeats the primal pass, so a
separate render plus `render_backward` traced the same paths twice; keeping the primal's
per-path radiance (its `state_out`) for the replay saves that second primal pass.

(Slab copies side by side were tried first: Mitsuba's ray-spawn offsets grow with the
coordinates' magnitude, (1 + max|p|) * 8.9e-5 mm, and at 50-200 mm from the origin they
skipped enough medium below the face to dim a copy by 4-16 %.)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["PLUGIN_NAME", "KeptPrimal", "register_plugins"]

PLUGIN_NAME = "rig_prbvolpath"
_registered: set[str] = set()


@dataclass
class KeptPrimal:
    """What one primal pass leaves for its adjoint replay (Dr.Jit arrays, evaluated)."""

    sensor: Any
    sampler: Any        # the sampler as it was after the camera rays: the replay's random numbers
    ray: Any
    weight: Any
    pos: Any
    radiance: Any       # per-path primal radiance (prbvolpath's state_out)
    spp: int
    used: bool = False


def register_plugins() -> None:
    """Register `rig_prbvolpath` for the current variant (idempotent)."""
    import drjit as dr
    import mitsuba as mi
    from mitsuba.python.ad.integrators.common import ADIntegrator
    from mitsuba.python.ad.integrators.prbvolpath import PRBVolpathIntegrator

    variant = mi.variant()
    if variant is None:
        raise RuntimeError("no Mitsuba variant is set: call estimate.mitsuba_env.init_mitsuba first")
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

        def render_kept(self, scene: Any, sensor: Any, seed: int, spp: int) -> tuple[Any, KeptPrimal]:
            """`render` (same seed, same image) that also keeps the primal pass's state for
            `backward_kept`. The paths are traced (evaluated) here; the image may be lazy."""
            film = sensor.film()
            with dr.suspend_grad():
                sampler, spp = self.prepare(sensor, seed, spp, self.aov_names())  # type: ignore[arg-type]
                ray, weight, pos = self.sample_rays(scene, sensor, sampler)
                # The replay must draw the same random numbers: the primal pass uses a clone,
                # as render_backward's does, and the original is kept for the replay.
                L, valid, aovs, state = self.sample(mode=dr.ADMode.Primal, scene=scene, sampler=sampler.clone(),
                                                    ray=ray, depth=mi.UInt32(0), δL=None, δaovs=None,
                                                    state_in=None, active=mi.Bool(True))
                # One kernel traces the paths and stores what the replay needs. Left lazy, the
                # film's develop step would run the primal for the image alone and the replay
                # (or a later eval) would trace the same paths again.
                dr.eval(L, valid, state, ray, weight, pos)
                block = film.create_block()
                block.set_coalesce(block.coalesce() and spp >= 4)
                # (Mitsuba's stubs ask for Dr.Jit arrays where its own integrators pass numbers.)
                ADIntegrator._splat_to_block(block, film, pos, value=L * weight,
                                             weight=1.0,  # type: ignore[arg-type]
                                             alpha=dr.select(valid, mi.Float(1), mi.Float(0)), aovs=aovs,
                                             wavelengths=ray.wavelengths)
                film.put_block(block)
                image = film.develop()
            return image, KeptPrimal(sensor, sampler, ray, weight, pos, state, int(spp))

        def backward_kept(self, scene: Any, kept: KeptPrimal, grad_in: Any) -> None:
            """The adjoint replay of a `render_kept` pass: accumulates d(sum(grad_in * image))
            into the gradients of the scene parameters that have gradients enabled (as
            `render_backward` with the same seed would). The scene must hold the parameter
            values of the primal pass. Once per kept pass: the replay consumes its sampler."""
            if kept.used:
                raise RuntimeError("this primal pass has already been replayed")
            kept.used = True
            film = kept.sensor.film()
            with dr.suspend_grad():
                film.prepare(self.aov_names())
                # The adjoint radiance per path: the image gradient pulled back through the
                # splatting and the weight division (as render_backward computes it).
                with dr.resume_grad():
                    ones = dr.full(mi.Spectrum, 1.0, dr.width(kept.ray))
                    dr.enable_grad(ones)
                    block = film.create_block()
                    block.set_coalesce(block.coalesce() and kept.spp >= 4)
                    # (Mitsuba's stubs ask for Dr.Jit arrays where its own integrators pass numbers.)
                    ADIntegrator._splat_to_block(block, film, kept.pos, value=ones * kept.weight,
                                                 weight=1.0, alpha=1.0,  # type: ignore[arg-type]
                                                 aovs=[], wavelengths=kept.ray.wavelengths)
                    film.put_block(block)
                    image = film.develop()
                    dr.set_grad(image, grad_in)
                    dr.enqueue(dr.ADMode.Backward, image)
                    dr.traverse(dr.ADMode.Backward)
                    d_radiance = dr.grad(ones)
                film.clear()
                self.sample(mode=dr.ADMode.Backward, scene=scene, sampler=kept.sampler, ray=kept.ray,
                            depth=mi.UInt32(0), δL=d_radiance, δaovs=[], state_in=kept.radiance,
                            active=mi.Bool(True))
                dr.eval()
            kept.sampler = kept.ray = kept.weight = kept.pos = kept.radiance = None

    mi.register_integrator(PLUGIN_NAME, lambda props: RigPRBVolpathIntegrator(props))
    _registered.add(variant)
