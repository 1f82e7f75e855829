"""What the simulated camera sees: the world rendered by the forward model.

`RenderedScene` is a :class:`~sim_devices.bench.SceneFunction`. With the slab mounted it
renders the slab lit at the *physical* stage angle (twin angle + the world's hidden zero
error, + the `angle_offset` tilt of the slab) through the current filter, using
`estimate.forward.ForwardModel` with the world's true material, thickness and scene
effects. With the slab removed (calibration) it shows the beam straight into the lens:
the beam map on the pixel grid, attenuated by the calibration ND filter and the lens's
telecentric acceptance exp(-delta^2 / 2 sigma^2) for a tilt delta = phi - 180 deg
(nothing beyond 10 deg of phi = 180: the beam misses the lens).

Scale. The forward model renders radiance L for a beam map of unit power [1/mm^2]:
    e-/s per unbinned pixel = L * P_f * pixel_area_mm2 * collection_sr
with P_f the world's beam power through filter f and collection_sr the lens's
collection solid angle. The straight beam: E(u, v) * P_f * nd * pixel_area_mm2 * A(delta).

Monte Carlo noise. One radiance image per (angle, filter) is rendered and reused for
every exposure, so its Monte Carlo noise is frozen into every frame of a stack (a fixed
pattern, not averaged away by more exposures). It is kept small where it matters: the
profile rows (axis row +- `profile_halfwidth_rows`, widened to 3 core sigmas + 1 row of a
world's lens blur, which mixes those rows into the profile) at `spp_profile`, the band around
them (+- `band_halfwidth_rows`) at `spp_band`, the rest of the frame at `spp_outside`
(it only feeds blooming and full-frame views). benchmarks/sim_render.py measures the
residual noise against the sensor noise of a merged bracket. `RenderedScene.render_noise`
declares it to the session (`rig capture` writes it as `extra.render_noise`).

Caching. Radiance images are cached in memory and on disk under
`<cache_dir>/<sha256(world truth, render settings, geometry, filter, angle)>.npz`, so a
later run with the same world reuses them. Image-space effects (`lens_blur`,
`stray_light`) are applied to the full frame after the cache; `sensor_nonlinearity` acts
per raw frame in the camera twin (:func:`raw_nonlinearity`).
"""

from __future__ import annotations

import hashlib
import math
import os
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from sim_devices.world import World, WorldError, beam_map

__all__ = ["MAX_DIRECT_TILT_DEG", "RenderedScene", "raw_nonlinearity"]

#: Beyond this tilt from phi = 180 the straight beam misses the lens entirely.
MAX_DIRECT_TILT_DEG = 10.0
#: Angles closer than this share one render (stage resolution is 0.0025 deg).
ANGLE_KEY_DECIMALS = 6
# 2: every (angle, filter, row tier) renders with its own seed (1 used one seed for all)
_CACHE_VERSION = "rendered-scene/2"


def raw_nonlinearity(world: World, full_well_e: float) -> Callable[[np.ndarray], np.ndarray] | None:
    """Electrons -> electrons compression of raw frames, or None when the world has none."""
    eff = world.effects.get("sensor_nonlinearity")
    if not eff or eff["compression"] == 0:
        return None
    from estimate.extensions.sensor_nonlinearity import apply_raw

    c = float(eff["compression"])
    return lambda q: apply_raw(q, c, full_well_e)


class RenderedScene:
    """Scene function of a world.

    Args:
        world: the parsed world.
        magnification: lens magnification (the world's, else the rig configuration's).
        sensor_px: (columns, rows) of the sensor.
        pixel_um: physical pixel size [um].

    Attributes:
        slab_present: False while the operator has the slab removed (calibration).
        renders: number of radiance images rendered (not read from a cache).
        disk_hits: number of radiance images read from the disk cache.
    """

    def __init__(self, world: World, *, magnification: float, sensor_px: tuple[int, int] = (512, 512),
                 pixel_um: float = 20.0) -> None:
        self.world = world
        self.magnification = float(world.optics.magnification or magnification)
        self.sensor_px = (int(sensor_px[0]), int(sensor_px[1]))
        self.pixel_um = float(pixel_um)
        self.pixel_mm = self.pixel_um * 1e-3 / self.magnification
        cols, rows = self.sensor_px
        self.axis_px = world.optics.axis_px or (cols / 2.0, rows / 2.0)
        _check_stray_light(world, cols, self.pixel_mm)
        self.slab_present = True
        self.renders = 0
        self.disk_hits = 0
        self._lock = threading.RLock()
        self._memory: dict[tuple, np.ndarray] = {}
        self._models: dict[str, Any] = {}
        self._beam_map, self._beam_pitch = beam_map(world)

    # ------------------------------------------------------------------ bench interface
    def __call__(self, angle_deg: float, filter_name: str | None, rows: slice, cols: slice) -> np.ndarray:
        """Photo-electron rate [e-/s per unbinned pixel] of the rows/cols asked."""
        cols_n, rows_n = self.sensor_px
        if filter_name is None or filter_name not in self.world.materials:
            # the wheel is between positions (or an unknown filter): the beam is blocked
            return np.zeros((rows_n, cols_n))[rows, cols]
        phys = float(angle_deg) + self.world.stage_zero_error_deg
        if self.slab_present:
            img = self.slab_image(phys, filter_name)
        else:
            img = self.direct_image(phys, filter_name)
        return img[rows, cols]

    # ------------------------------------------------------------------ the straight beam
    def direct_image(self, phys_deg: float, filter_name: str) -> np.ndarray:
        """e-/s per pixel of the beam pointed into the lens (slab removed), full frame."""
        key = ("direct", round(phys_deg, ANGLE_KEY_DECIMALS), filter_name)
        with self._lock:
            hit = self._memory.get(key)
            if hit is not None:
                return hit
        delta = (phys_deg - 180.0 + 180.0) % 360.0 - 180.0
        cols_n, rows_n = self.sensor_px
        if abs(delta) > MAX_DIRECT_TILT_DEG:
            img = np.zeros((rows_n, cols_n))
        else:
            o = self.world.optics
            accept = math.exp(-0.5 * (delta / o.acceptance_sigma_deg) ** 2)
            scale = self.world.beam.power_e_per_s[filter_name] * o.calibration_nd * accept * self.pixel_mm ** 2
            img = scale * self._beam_on_pixels(math.radians(delta))
            img = self.image_effects(img, direct=True)
        with self._lock:
            self._memory[key] = img
        return img

    def _beam_on_pixels(self, tilt_rad: float) -> np.ndarray:
        """Unit-power beam irradiance [1/mm^2] averaged over each pixel (3x3 sub-samples).

        At phi = 180 + delta the beam crosses the front-face plane with its u axis
        stretched by 1 / cos(delta) (irradiance on the plane divided by the same)."""
        from estimate.beam import BeamProfile

        cols_n, rows_n = self.sensor_px
        cx, cy = self.axis_px
        ou, ov = self.world.beam.offset_mm
        prof = BeamProfile.centered(self._beam_map, self._beam_pitch, (ou, ov))
        sub = (np.arange(3) + 0.5) / 3.0
        c = math.cos(tilt_rad)
        out = np.zeros((rows_n, cols_n))
        # only the pixels the map can reach
        nv, nu = self._beam_map.shape
        half_u = (0.5 * nu * self._beam_pitch + abs(ou)) / self.pixel_mm / max(c, 1e-3) + 3
        half_v = (0.5 * nv * self._beam_pitch + abs(ov)) / self.pixel_mm + 3
        c0, c1 = max(0, int(cx - half_u)), min(cols_n, int(cx + half_u) + 1)
        r0, r1 = max(0, int(cy - half_v)), min(rows_n, int(cy + half_v) + 1)
        if c0 >= c1 or r0 >= r1:
            return out
        for sy in sub:
            for sx in sub:
                x = (np.arange(c0, c1) + sx - cx) * self.pixel_mm
                y = -(np.arange(r0, r1) + sy - cy) * self.pixel_mm
                xx, yy = np.meshgrid(x * c, y)
                out[r0:r1, c0:c1] += prof.lookup(xx, yy) * c
        return out / 9.0

    # ------------------------------------------------------------------ the slab
    def beam_profile(self) -> Any:
        """The bench's own beam (an `estimate.beam.BeamProfile`, unit power), before any lens."""
        from estimate.beam import BeamProfile

        return BeamProfile.centered(self._beam_map, self._beam_pitch, self.world.beam.offset_mm)

    def slab_model(self, filter_name: str) -> tuple[Any, dict[str, float]]:
        """The forward model the bench renders the slab with, and its true parameters (the
        image-space effects left out: `image_effects` applies them to whole frames)."""
        return self._model(filter_name), self._params(filter_name)

    def _model(self, filter_name: str) -> Any:
        m = self._models.get(filter_name)
        if m is None:
            from estimate.forward import ForwardModel
            from estimate.geometry import RigGeometry

            w = self.world
            geom = RigGeometry(thickness_mm=w.thickness_mm, half_width_mm=w.half_width_mm,
                               sensor_px=self.sensor_px, pixel_um=self.pixel_um,
                               magnification=self.magnification, image_center_px=self.axis_px)
            beam = self.beam_profile()
            exts = [e for e in w.effects if e not in ("lens_blur", "stray_light", "sensor_nonlinearity")]
            mat = w.materials[filter_name]
            m = ForwardModel(geom, beam, phase=mat.model, extensions=exts, max_depth=w.render.max_depth,
                             engine=w.render.engine, phase_table=mat.phase_table)
            self._models[filter_name] = m
        return m

    def _params(self, filter_name: str) -> dict[str, float]:
        p = self.world.materials[filter_name].parameters()
        for k, v in self.world.effect_values().items():
            if k.split(".", 1)[0] not in ("lens_blur", "stray_light", "sensor_nonlinearity"):
                p[k] = v
        return p

    def row_tiers(self) -> list[tuple[int, int, int]]:
        """(row0, row1, spp) of the rendered tiers, every sensor row exactly once."""
        rs = self.world.render
        rows_n = self.sensor_px[1]
        centre = min(rows_n - 1, math.floor(self.axis_px[1]))
        half = rs.profile_halfwidth_rows
        blur = self.world.effects.get("lens_blur")
        if blur:
            # The lens blur mixes the rows around the profile row into it: 3 core sigmas of
            # them (and one more row, as the estimator's profile row may sit one off the axis
            # row) must carry profile-quality noise. With the default 2 rows, a 1.5 px blur
            # mixed 32-spp band rows into the profile, and their frozen noise with them
            # (bench_profile_blur.py: with the rows' own shape, 0.7-4.2 % before, 0.4-1.7 % after).
            half = max(half, math.ceil(3.0 * float(blur.get("core_sigma_px", 0.0))) + 1)
        p0, p1 = max(0, centre - half), min(rows_n, centre + half + 1)
        b0, b1 = max(0, centre - rs.band_halfwidth_rows), min(rows_n, centre + rs.band_halfwidth_rows + 1)
        b0, b1 = min(b0, p0), max(b1, p1)
        tiers = [(p0, p1, rs.spp_profile)]
        for lo, hi in ((b0, p0), (p1, b1)):
            if hi > lo:
                tiers.append((lo, hi, rs.spp_band))
        if rs.spp_outside > 0:
            for lo, hi in ((0, b0), (b1, rows_n)):
                if hi > lo:
                    tiers.append((lo, hi, rs.spp_outside))
        return tiers

    def cache_key(self, phys_deg: float, filter_name: str) -> str:
        """Disk-cache key of one radiance image."""
        parts = [_CACHE_VERSION]
        if self.world.render.engine == "light":
            # the light engine's own revision: its images of earlier revisions are not reused
            # (the camera engine's keys, and so its caches, stay as they were)
            from estimate.light_paths import RENDER_REVISION

            parts.append(f"light/{RENDER_REVISION}")
        text = "|".join([*parts, self.world.truth_hash(), repr(self.sensor_px), repr(self.pixel_um),
                         repr(self.magnification), repr(tuple(self.axis_px)), repr(self.row_tiers()),
                         filter_name, f"{round(phys_deg, ANGLE_KEY_DECIMALS):.6f}"])
        return hashlib.sha256(text.encode()).hexdigest()

    def radiance(self, phys_deg: float, filter_name: str) -> np.ndarray:
        """Scene radiance of the slab for a unit-power beam, full frame, before image
        effects (cached in memory and on disk)."""
        mkey = ("slab", round(phys_deg, ANGLE_KEY_DECIMALS), filter_name)
        with self._lock:
            hit = self._memory.get(mkey)
            if hit is not None:
                return hit
            key = self.cache_key(phys_deg, filter_name)
            path = self.world.render.cache_path() / f"{key}.npz"
            img = _read_cache(path, (self.sensor_px[1], self.sensor_px[0]))
            if img is not None:
                self.disk_hits += 1
            else:
                # float32 like the disk copy, so a cached run sees the very same numbers
                img = self._render(phys_deg, filter_name).astype(np.float32).astype(np.float64)
                self.renders += 1
                _write_cache(path, img)
            self._memory[mkey] = img
            return img

    def _render(self, phys_deg: float, filter_name: str) -> np.ndarray:
        model = self._model(filter_name)
        params = self._params(filter_name)
        cols_n, rows_n = self.sensor_px
        img = np.zeros((rows_n, cols_n))
        angle = ((phys_deg + 180.0) % 360.0) - 180.0
        # The light engine adds every vertex to every row of a window, at most MAX_ROWS of
        # them: its tiers in blocks, each with its own paths (seed); the camera engine's whole.
        from estimate.light_paths import MAX_ROWS

        light = self.world.render.engine == "light"
        for i, (r0, r1, spp) in enumerate(self.row_tiers()):
            for j, b0 in enumerate(range(r0, r1, MAX_ROWS if light else r1 - r0)):
                b1 = min(r1, b0 + MAX_ROWS) if light else r1
                img[b0:b1] = model.render(params, [angle], columns=(0, cols_n), rows=(b0, b1), spp=spp,
                                          seed=self.image_seed(phys_deg, filter_name, i) + 7919 * j)[0]
        return img

    def image_seed(self, phys_deg: float, filter_name: str, tier: int) -> int:
        """Render seed of one image's row tier, distinct per (angle, filter, tier).

        Each image is rendered on its own, as angle 0 of its call, so one world seed for
        all of them would replay the same random numbers in every pixel of every image:
        the recording's frozen Monte Carlo noise would then be correlated across angles
        and filters, where a real camera's frames are independent.
        """
        text = f"{self.world.render.seed}|{filter_name}|{round(phys_deg, ANGLE_KEY_DECIMALS):.6f}|{tier}"
        return int.from_bytes(hashlib.blake2s(text.encode(), digest_size=4).digest(), "little") % (2 ** 31)

    def slab_image(self, phys_deg: float, filter_name: str) -> np.ndarray:
        """e-/s per pixel of the lit slab, full frame (image effects applied)."""
        key = ("slab-e", round(phys_deg, ANGLE_KEY_DECIMALS), filter_name)
        with self._lock:
            hit = self._memory.get(key)
            if hit is not None:
                return hit
        rad = self.image_effects(self.radiance(phys_deg, filter_name), direct=False)
        scale = self.world.beam.power_e_per_s[filter_name] * self.pixel_mm ** 2 * self.world.optics.collection_sr
        img = np.clip(rad, 0.0, None) * scale
        with self._lock:
            self._memory[key] = img
        return img

    def image_effects(self, img: np.ndarray, *, direct: bool) -> np.ndarray:
        """Lens blur (everything the lens sees) and stray light (slab only), full frame."""
        eff = self.world.effects
        out = img
        if not direct and "stray_light" in eff:
            from estimate.extensions.stray_light import StrayLight

            out = StrayLight.apply(out, eff["stray_light"], pixel_mm=self.pixel_mm, profile_only=False)
        if "lens_blur" in eff:
            from estimate.extensions.lens_blur import LensBlur

            out = LensBlur.apply(out, eff["lens_blur"], pixel_mm=self.pixel_mm, profile_only=False)
        return out

    def profile_rows(self) -> tuple[int, int]:
        """[row0, row1) rendered at `spp_profile`."""
        r0, r1, _ = self.row_tiers()[0]
        return r0, r1

    def render_noise(self) -> dict[str, Any]:
        """What this camera's frames hold besides the sensor's noise: the frozen Monte Carlo
        noise of its renders, declared the way a real camera's data sheet declares its read
        noise, so that the estimator can put it in its null (`estimate.problem.Problem`).

        The light engine's noise is correlated along a row, unlike a real sensor's fixed
        pattern: one path adds to every column its vertices land in, a mean free path apart
        (several pixels), and every vertex adds to every row of its tier. Its size on a
        row depends only on the paths of the image: `paths_per_image` = spp x the frame's
        columns (`estimate.forward` traces spp x window width paths an angle). The camera
        engine's pixels have paths of their own: white, which the diagnosis' noise floor
        already measures.

        Returns: {"engine", "tiers": [{"rows": [row0, row1), "spp", "paths_per_image"}]}
        in unbinned sensor rows. Nothing of the world's effects is declared (a session of a
        proof case must not say what is concealed in it).
        """
        cols_n = self.sensor_px[0]
        light = self.world.render.engine == "light"
        tiers = [{"rows": [int(r0), int(r1)], "spp": int(spp),
                  "paths_per_image": int(spp) * cols_n if light else None}
                 for r0, r1, spp in self.row_tiers()]
        return {"engine": self.world.render.engine, "tiers": tiers}


def _check_stray_light(world: World, cols: int, pixel_mm: float) -> None:
    """Refuse a stray light that goes negative on the frame.

    Stray light is light: `offset + slope_per_mm * x` (x from the sensor centre) must be >= 0
    across the whole frame. A world that asks for less than nothing would not add the
    catalogue's linear background: the scene is clipped at zero after the effects, so the
    recording would carry a hinge that no catalogue effect has (a session-7..10 bench case,
    offset 0.003 with slope 0.0005 /mm on a 34 mm field, was zero over the left sixth of
    the frame, and its diagnosis could not get below reduced chi^2 ~400).

    Raises:
        WorldError: one line with the world file, the key and the largest slope allowed.
    """
    from estimate.extensions.stray_light import StrayLight

    sl = world.effects.get("stray_light")
    if not sl:
        return
    # the background the bench adds (`image_effects`), along one row of the frame
    low = float(StrayLight.apply(np.zeros(cols), sl, pixel_mm=pixel_mm, profile_only=True).min())
    half = 0.5 * (cols - 1) * pixel_mm  # the outermost pixel centres
    offset, slope = float(sl["offset"]), float(sl["slope_per_mm"])
    if low < 0.0:
        side = "left" if slope > 0 else "right"
        raise WorldError(
            f"{world.source}: effects.stray_light: offset + slope_per_mm * x = {low:.3g} at the frame's {side} "
            f"edge (x = {'-' if slope > 0 else '+'}{half:.1f} mm), but stray light cannot be negative; "
            f"use |slope_per_mm| <= {offset / half:.3g} or offset >= {abs(slope) * half:.3g}")


def _read_cache(path: Path, shape: tuple[int, int]) -> np.ndarray | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            img = np.array(z["radiance"], dtype=np.float64)
    except (OSError, ValueError, KeyError):
        return None
    return img if img.shape == shape else None


def _write_cache(path: Path, img: np.ndarray) -> None:
    """Atomic write (temp + rename); a cache that cannot be written is only slower."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
        with open(tmp, "wb") as f:
            np.savez_compressed(f, radiance=img.astype(np.float32))
        os.replace(tmp, path)
    except OSError:
        pass
