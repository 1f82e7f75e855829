"""The forward model: the rig as a differentiable Mitsuba 3 scene.

A homogeneous slab (sigma_t [1/mm], albedo, phase function `exp<M>` or `tthg`) lit by the
calibrated collimated beam (`estimate.beam`) at stage angles phi, seen by a telecentric
camera (orthographic sensor) that renders only the pixel window asked for (one row for
estimation, a band or the full frame for the simulated camera). One channel per render
(`*_ad_mono` variant). Extensions (`estimate.extensions`) add the physics a base fit may
leave out; each is switched on by name at construction and has neutral values.

Parameters are a flat mapping name -> float:
    "sigma_t", "albedo",
    "phase.b1" .. "phase.bM"                        (phase "exp<M>"),
    "phase.g_forward", "phase.g_backward", "phase.w_forward"   (phase "tthg"),
    "phase.g"                                       (phase "hg"),
    "<extension>.<parameter>"                       (see `ForwardModel.parameter_names`).

All angles of a call are rendered with the same compiled kernels: angles and parameters
are opaque Dr.Jit values. Seeds are explicit: angle k of a call with seed s uses the
Mitsuba seed `render_seed(s, k)` (every band node of `filter_bandwidth` alike), so a call is
reproducible and finite differences can use common random numbers.

See docs/forward-model.md for the API and its conventions.
"""

from __future__ import annotations

import math
import re
import threading
import weakref
from collections import OrderedDict
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
import numpy.typing as npt

from estimate.beam import BeamProfile
from estimate.errors import ModelParameterError
from estimate.extensions import EXTENSIONS, IMAGE_ORDER, check_value, get_extension
from estimate.extensions.base import BeamFill, ImageExtension, ParameterSpec, RowData, no_row_data
from estimate.extensions.filter_bandwidth import band_nodes
from estimate.extensions.lens_blur import TRUNCATION_PX as LENS_BLUR_RADIUS
from estimate.extensions.lens_blur import core_line_spread, psf_2d
from estimate.extensions.refractive_boundary import INTERNAL_REFLECTIONS
from estimate.extensions.sensor_nonlinearity import decompressed_map
from estimate.geometry import PixelWindow, RigGeometry
from estimate.light_paths import TABLE, LightPaths, check_phase_table
from estimate.mitsuba_env import init_mitsuba
from estimate.mitsuba_phase import exp_phase_dict, tabulated_phase_dict, tthg_phase_dict
from estimate.phase_tabulated import TabulatedPhase

__all__ = ["BASE_SPECS", "CAMERA", "ENGINES", "LIGHT", "ForwardModel", "Linearization", "check_engine",
           "phase_specs", "render_seed"]

#: Render engines (`ForwardModel(engine=...)`): paths from the camera (Mitsuba's prbvolpath)
#: or from the beam (`estimate.light_paths`).
CAMERA = "camera"
LIGHT = "light"
ENGINES = (CAMERA, LIGHT)


def check_engine(engine: str) -> str:
    """`engine` if it names a render engine, else `ModelParameterError` (one line)."""
    if engine not in ENGINES:
        raise ModelParameterError(f"unknown render engine {engine!r}; use one of {', '.join(ENGINES)}")
    return engine

_INF = float("inf")
#: Largest number of paths (pixels x spp) traced in one launch; bounds memory (~0.2 kB each).
_MAX_LANES = 2 ** 22
#: Renders queued before the first is read back (`ForwardModel._radiances`), and the most
#: paths they may hold between them: at a few samples per pixel a render is mostly its tracing
#: in Python, and 32 queued took the coarse start from 8-9 s to 6 s on 2 cores (16: 6-7 s,
#: 256: 5.4-6 s); at the spp of the fits a render is its kernels, and queueing gains nothing.
_QUEUED_RENDERS = 32
_QUEUED_LANES = 2 ** 24


#: Scenes (`_SceneBundle`s: a slab per angle, its medium, phase function, beam and sensors)
#: kept alive across every ForwardModel of the process; the least recently used beyond
#: this are dropped and rebuilt when next asked for (identical renders: same scene, same
#: seeds, the compiled kernels reused). Dr.Jit traces a virtual call (a shape's
#: intersection, a medium's or phase function's sampling) once for every live instance of
#: its class, not only this scene's, so each live scene adds to every launch's tracing: on
#: the simulated bench's 8 angles a 256-spp render took 416 ms alone, 483 ms beside 10
#: other models' scenes and 1046 ms beside 40, an 8-spp render 22, 92 and 671 ms (session
#: 50). A diagnosis builds a model for every candidate and combination, and had kept all
#: their scenes.
MAX_LIVE_BUNDLES = 6

_live_bundles: OrderedDict[tuple[int, int], weakref.ReferenceType[ForwardModel]] = OrderedDict()
_live_lock = threading.Lock()


def _keep_live(model: ForwardModel, copies: int) -> None:
    """Mark `model`'s bundle of `copies` as just used; drop the least recently used
    bundles (of any model) beyond `MAX_LIVE_BUNDLES`. A renderer still holding a dropped
    bundle (a `Linearization` between its primal and adjoint passes) keeps it alive and
    usable; only the cache lets go of it."""
    key = (id(model), copies)
    with _live_lock:
        # Entries of models already collected hold no scene; they must not take a place.
        for dead in [k for k, ref in _live_bundles.items() if ref() is None]:
            del _live_bundles[dead]
        _live_bundles[key] = weakref.ref(model)
        _live_bundles.move_to_end(key)
        while len(_live_bundles) > MAX_LIVE_BUNDLES:
            (_, c), ref = _live_bundles.popitem(last=False)
            owner = ref()
            if owner is not None:
                owner._bundles.pop(c, None)


def live_bundles() -> int:
    """How many scene bundles the cache keeps alive now (at most `MAX_LIVE_BUNDLES`)."""
    with _live_lock:
        return sum(1 for ref in _live_bundles.values() if ref() is not None)


#: Base parameters of every model.
BASE_SPECS: dict[str, ParameterSpec] = {
    # sigma_t: reverse mode, finite differences with refractive_boundary (ForwardModel.__init__).
    "sigma_t": ParameterSpec("sigma_t", 1.0, 0.0, 1e4, "1/mm", "ad", 0.01,
                             "extinction coefficient", open_lower=True),
    "albedo": ParameterSpec("albedo", 0.9, 0.0, 1.0, "", "ad", 0.01, "single-scattering albedo"),
}


def phase_specs(phase: str) -> dict[str, ParameterSpec]:
    """Parameter specs of a phase model name: "exp<M>" (M >= 0), "hg" or "tthg" ("table", a
    tabulated truth, has none)."""
    if phase == TABLE:
        return {}
    m = re.fullmatch(r"exp(\d+)", phase)
    if m:
        return {f"phase.b{i}": ParameterSpec(f"b{i}", 0.0, -1000.0, 1000.0, "", "ad", 0.05,
                                             f"exponential phase coefficient of mu^{i}")
                for i in range(1, int(m.group(1)) + 1)}
    if phase == "hg":
        return {"phase.g": ParameterSpec("g", 0.5, -0.999, 0.999, "", "ad", 0.01, "Henyey-Greenstein g")}
    if phase == "tthg":
        return {
            "phase.g_forward": ParameterSpec("g_forward", 0.5, -0.999, 0.999, "", "ad", 0.01, "forward lobe g"),
            "phase.g_backward": ParameterSpec("g_backward", -0.3, -0.999, 0.999, "", "ad", 0.01, "backward lobe g"),
            "phase.w_forward": ParameterSpec("w_forward", 0.9, 0.0, 1.0, "", "ad", 0.01, "forward lobe weight"),
        }
    raise ModelParameterError(f"unknown phase model {phase!r}; use 'exp<M>' (e.g. exp3), 'hg' or 'tthg'")


def _angle_key(angle_deg: float) -> float:
    return round(float(angle_deg), 6)


def render_seed(seed: int, angle_index: int) -> int:
    """Mitsuba seed of one render of a call (uint32)."""
    return (int(seed) * 1_000_003 + angle_index * 7919) % (2 ** 32)


class ForwardModel:
    """The rig's forward model for one colour channel.

    Args:
        geometry: slab and camera geometry.
        beam: calibrated beam map for this channel.
        phase: "exp<M>" (exponential plugin, monomial basis, degree M), "hg" (built-in
            Henyey-Greenstein) or "tthg" (two built-in `hg` lobes in `blendphase`); or
            "table" with `phase_table` (no phase parameters: the simulated bench's Mie truth).
        extensions: names of the extensions to include (see `estimate.extensions`).
        variant: Mitsuba variant; None = automatic (`estimate.mitsuba_env`).
        max_depth: path length limit of `prbvolpath`.
        rr_depth: depth at which Russian roulette starts.
        profile_y_shape: the recording's shape across the rows around the profile row, per
            stage angle (degrees -> array (2 TRUNCATION_PX + 1, W) over the profile columns,
            `estimate.problem.Problem.y_shapes`), for the lens blur of profile renders
            (`estimate.extensions.lens_blur`); angles without one, other columns and None
            use the line-spread function.
        profile_merge_fill: the HDR merge's mean squared fill of the well per profile pixel,
            per stage angle (degrees -> array (W,), `estimate.problem.Problem.merge_fills`),
            for the sensor compression of profile renders
            (`estimate.extensions.sensor_nonlinearity`); without one for every angle the
            compression takes its full-well form.
        beam_fill: the beam calibration frame's power shares, merge fills and pixels
            (`estimate.problem.Problem.beam_fill`), for the sensor compression of the
            calibration itself: its power (`estimate.extensions.sensor_nonlinearity.
            calibration_gain`) and, with the pixels, its map's shape (`decompresses_beam`);
            None leaves the calibration as read.
        engine: how the slab is rendered (`ENGINES`): "camera", Mitsuba's `prbvolpath`
            from the camera with next-event connections to the beam (derivatives by path
            replay); or "light", paths from the beam connected to the camera
            (`estimate.light_paths`: tens of times less Monte Carlo noise a second on the
            profile row, derivatives by score functions in the same pass). With "light",
            `spp` means spp x the window's width light paths per stage angle.
        phase_table: the tabulated phase function of phase "table" (`estimate.phase_tabulated`).
    """

    def __init__(self, geometry: RigGeometry, beam: BeamProfile, *, phase: str = "exp3",
                 extensions: Iterable[str] = (), variant: str | None = None,
                 max_depth: int = 64, rr_depth: int = 16,
                 profile_y_shape: Mapping[float, np.ndarray] | None = None, engine: str = CAMERA,
                 profile_merge_fill: Mapping[float, np.ndarray] | None = None,
                 beam_fill: BeamFill | None = None, phase_table: TabulatedPhase | None = None) -> None:
        self.engine = check_engine(engine)
        check_phase_table(phase, phase_table)
        self.phase_table = phase_table
        self.beam_fill = beam_fill
        self.geometry = geometry
        self.profile_y_shape: dict[float, np.ndarray] = {
            _angle_key(a): np.asarray(h, dtype=np.float64) for a, h in (profile_y_shape or {}).items()}
        self.profile_merge_fill: dict[float, np.ndarray] = {
            _angle_key(a): np.asarray(g, dtype=np.float64) for a, g in (profile_merge_fill or {}).items()}
        self.beam_profile = beam
        self.phase = phase
        self.extensions: tuple[str, ...] = tuple(dict.fromkeys(extensions))
        for name in self.extensions:
            get_extension(name)
        self.specs: dict[str, ParameterSpec] = dict(BASE_SPECS)
        self.specs.update(phase_specs(phase))
        for name in self.extensions:
            for p in EXTENSIONS[name].parameters:
                self.specs[f"{name}.{p.name}"] = p
        if engine == LIGHT and "beam_halo" in self.extensions:
            # The halo moves where light paths start: its derivatives by differences.
            for p in EXTENSIONS["beam_halo"].parameters:
                name = f"beam_halo.{p.name}"
                self.specs[name] = replace(self.specs[name], derivative="fd")
        if "refractive_boundary" in self.extensions and engine == CAMERA:
            # Next-event rays to the refracted beam must stop inside the medium (a
            # dielectric would block them) and prbvolpath drops the attenuation derivative
            # of such rays: sigma_t (and the band spread acting through it) by differences.
            for name in ("sigma_t", "filter_bandwidth.spread"):
                if name in self.specs:
                    self.specs[name] = replace(self.specs[name], derivative="fd")
        #: The beam map was imaged through the lens (a calibration frame) and the model blurs
        #: the image by the lens's PSF: the slab is lit by the map with that PSF taken out
        #: (`beam_for`), so the blur acts once. The blur's parameters then also change the
        #: scene, and are differentiated by finite differences of whole renders (common
        #: random numbers; the render is linear in the map, so those differences carry
        #: little Monte Carlo noise).
        self.deblurs_beam = "lens_blur" in self.extensions and bool(getattr(beam, "through_lens", False))
        if self.deblurs_beam:
            for p in EXTENSIONS["lens_blur"].parameters:
                name = f"lens_blur.{p.name}"
                self.specs[name] = replace(self.specs[name], derivative="fd")
        #: With the light engine, a single-row render (the profile) of such a model is lit by
        #: that map blurred along v by the blur's core (`beam_for(single_row=True)`): the slab
        #: does not change along y, so that row is the image blurred along y by the core, and
        #: the blur then only applies the core along x (`LensBlur.apply(core_in_scene=True)`).
        #: The core is separable, so its part of the blur is exact, where the profile-row blur
        #: otherwise reads the image's y-shape from the recording's rows, deblurred: on the
        #: light bench's lens blurs that reading left the true model's reduced chi^2 at the
        #: noise floor at 1.44 and 2.40, against 1.30 and 1.56 for an exact 2D blur of the
        #: model's own rows (docs/diagnosis-log.md, session 68). The tail, not separable,
        #: still reads the y-shape.
        self.core_blur_in_scene = self.deblurs_beam and engine == LIGHT
        #: The beam map is a calibration frame read through the sensor whose compression the
        #: model includes (`beam_fill` with the frame's pixels): its wings, read from longer
        #: exposures at fills up to 0.6, are low against its peak by up to c g (3.6 % at a 6 %
        #: compression on the bench). The slab is lit by the map with the compression taken
        #: out at the values' c (`beam_for`; its power stays the read one, which
        #: `calibration_gain` corrects in the image), so the compression also changes the scene
        #: and is differentiated by finite differences of whole renders, as the blur is.
        self.decompresses_beam = ("sensor_nonlinearity" in self.extensions and beam_fill is not None
                                  and beam_fill.pixels is not None and beam_fill.to_profile is not None)
        if self.decompresses_beam:
            self.specs["sensor_nonlinearity.compression"] = replace(
                self.specs["sensor_nonlinearity.compression"], derivative="fd")
        self._beams: dict[tuple[float, ...], BeamProfile] = {}
        self._core_beams: dict[tuple[float, ...], BeamProfile] = {}
        self._decompressed: dict[float, BeamProfile] = {}
        self._y_shapes: dict[tuple[float, ...], np.ndarray] = {}
        self._last_deblurred: tuple[float, BeamProfile] | None = None
        self.mi = init_mitsuba(variant)
        import drjit as dr

        self.dr = dr
        self.max_depth = int(max_depth)
        self.rr_depth = int(rr_depth)
        self._lock = threading.Lock()
        self._bundles: dict[int, _SceneBundle] = {}
        self._refractive = "refractive_boundary" in self.extensions
        self._light: LightPaths | None = None
        if engine == LIGHT:
            self._light = LightPaths(geometry, phase, self.mi, max_depth=self.max_depth, rr_depth=self.rr_depth,
                                     table=phase_table)
        else:
            self._bundle(1)

    # ------------------------------------------------------------------ parameters
    @property
    def parameter_names(self) -> list[str]:
        """All parameter names of this model, base first, then phase, then extensions."""
        return list(self.specs)

    def default_parameters(self) -> dict[str, float]:
        """Neutral / default values of every parameter."""
        return {k: s.neutral for k, s in self.specs.items()}

    def derivative_kind(self, name: str) -> str:
        """"ad", "image" or "fd": how `vjp` / `jacobian` differentiate this parameter."""
        return self._spec(name).derivative

    def acts_in_image(self, name: str) -> bool:
        """Whether the parameter belongs to an image-space extension (a blur, stray light,
        sensor compression): its derivative columns have pixel-scale structure that must not
        be smoothed, whether they are exact ("image") or, with `deblurs_beam`, rendered."""
        ext = name.split(".", 1)[0]
        return ext in self.extensions and EXTENSIONS[ext].kind == "image"

    def beam_for(self, values: Mapping[str, float], single_row: bool = False) -> BeamProfile:
        """The beam map that lights the slab at these parameter values: the calibrated one,
        or with `deblurs_beam` the calibrated one with the lens's PSF at the values' blur
        taken out (`estimate.beam.BeamProfile.deblurred`; the map itself at no blur), and
        with `decompresses_beam` the sensor's compression taken out first. `single_row`
        (a one-row window) with `core_blur_in_scene`: that map blurred along v by the blur's
        core (`estimate.beam.BeamProfile.blurred_along_v`)."""
        c = float(values.get("sensor_nonlinearity.compression", 0.0)) if self.decompresses_beam else 0.0
        base = self.beam_profile if c == 0.0 else self._decompressed_beam(c)
        if not self.deblurs_beam:
            return base
        v = {p.name: float(values.get(f"lens_blur.{p.name}", p.neutral)) for p in EXTENSIONS["lens_blur"].parameters}
        if v["core_sigma_px"] == 0 and v["tail_fraction"] == 0:
            return base
        key = (c, *(v[k] for k in sorted(v)))
        deblurred = self._deblurred_beam(base, key, v)
        if not (single_row and self.core_blur_in_scene and v["core_sigma_px"] > 0):
            return deblurred
        hit = self._core_beams.get(key)
        if hit is None:
            hit = deblurred.blurred_along_v(core_line_spread(v))
            if len(self._core_beams) >= 16:
                self._core_beams.pop(next(iter(self._core_beams)))
            self._core_beams[key] = hit
        return hit

    def _deblurred_beam(self, base: BeamProfile, key: tuple[float, ...], v: Mapping[str, float]) -> BeamProfile:
        """`base` (the map decompressed at c = key[0]) with the lens's PSF at the blur values
        `v` taken out, cached under `key`."""
        c = key[0]
        hit = self._beams.get(key)
        if hit is None:
            # One sample of the map is one sensor pixel of the calibration frame; the PSF is in
            # sensor pixels.
            if not math.isclose(self.beam_profile.pitch_mm, self.geometry.pixel_mm, rel_tol=1e-6):
                raise ModelParameterError(
                    f"the beam map's pitch {self.beam_profile.pitch_mm:.6g} mm is not the sensor's pixel "
                    f"{self.geometry.pixel_mm:.6g} mm; the lens blur cannot be taken out of it")
            # Started from the last map deblurred from the same base: a fit moves the blur a
            # little at a time (a lens blur diagnosis deblurs at about 200 distinct blurs).
            last = self._last_deblurred
            hit = base.deblurred(psf_2d(v), start=last[1].irradiance if last is not None and last[0] == c else None)
            self._last_deblurred = (c, hit)
            if len(self._beams) >= 16:  # a fit visits many points; keep the recent ones
                self._beams.pop(next(iter(self._beams)))
            self._beams[key] = hit
        return hit

    def _decompressed_beam(self, compression: float) -> BeamProfile:
        """The calibrated map with the sensor's compression at `compression` taken out
        (`decompresses_beam`; `sensor_nonlinearity.decompressed_map`), recent ones cached."""
        hit = self._decompressed.get(compression)
        if hit is None:
            bf = self.beam_fill
            assert bf is not None and bf.to_profile is not None
            hit = bf.to_profile(decompressed_map(compression, bf))
            if len(self._decompressed) >= 16:
                self._decompressed.pop(next(iter(self._decompressed)))
            self._decompressed[compression] = hit
        return hit

    def _spec(self, name: str) -> ParameterSpec:
        try:
            return self.specs[name]
        except KeyError:
            ext = name.split(".", 1)[0]
            if ext in EXTENSIONS and ext not in self.extensions:
                raise ModelParameterError(
                    f"parameter {name!r} belongs to extension {ext!r}, which this model does not include") from None
            if ext not in EXTENSIONS and "." in name and ext != "phase":
                get_extension(ext)
            raise ModelParameterError(f"unknown model parameter {name!r}") from None

    def validate(self, params: Mapping[str, float]) -> dict[str, float]:
        """Full, checked parameter dict (missing names take their defaults).

        Raises:
            ModelParameterError: unknown name, NaN, or a value outside its range (the
                message names the parameter).
        """
        out = self.default_parameters()
        for k, v in params.items():
            self._spec(k)
            out[k] = v
        for k, s in self.specs.items():
            out[k] = check_value(k, out[k], s)
        thickness = self.geometry.thickness_mm * (1.0 + out.get("thickness_error.e", 0.0))
        if thickness <= 0:
            raise ModelParameterError(f"thickness_error.e={out['thickness_error.e']:g} makes the thickness <= 0")
        return out

    # ------------------------------------------------------------------ scene
    def _bundle(self, copies: int) -> _SceneBundle:
        """The scene with `copies` slab copies (one per angle of a batched render)."""
        bundle = self._bundles.get(copies)
        if bundle is None:
            bundle = _SceneBundle(self, copies)
            self._bundles[copies] = bundle
        _keep_live(self, copies)
        return bundle

    def _bands(self, values: Mapping[str, float]) -> list[tuple[float, float]]:
        """(node x, quadrature weight) of each band node; one node at spread 0.

        Every node is rendered with the same random numbers (seed) and the full spp, so
        near spread 0 the nodes' noise is nearly the same: a band model keeps common random
        numbers with the model without it, as every other candidate of a diagnosis does,
        and about its Monte Carlo variance (at spread 0 it is that model, bit for bit). A
        seed a node gave a band render 0.35 of that variance, which a fixed-seed refit took
        for a gain (docs/diagnosis-log.md, session 53).
        """
        if "filter_bandwidth" in self.extensions and values.get("filter_bandwidth.spread", 0.0) != 0.0:
            # At spread 0 every node renders the same image (and d/dspread = sum_k w_k x_k dI/dsigma_t
            # vanishes with the symmetric nodes), so one render does.
            x, w = band_nodes()
            return list(zip(x.tolist(), w.tolist()))
        return [(0.0, 1.0)]

    # ------------------------------------------------------------------ rendering
    def _groups(self, n_angles: int, window: PixelWindow, spp: int) -> tuple[list[range], int]:
        """Angle groups rendered in one launch each, and the number of sample passes."""
        lanes_per_angle = window.width * window.height * int(spp)
        per_group = max(1, min(n_angles, _MAX_LANES // max(1, lanes_per_angle)))
        passes = max(1, math.ceil(lanes_per_angle / _MAX_LANES))
        groups = [range(i, min(n_angles, i + per_group)) for i in range(0, n_angles, per_group)]
        return groups, passes

    def _launch(self, bundle: _SceneBundle, window: PixelWindow, spp: int, seed: int, first: int,
                pass_index: int, ad: bool) -> Any:
        """One mi.render of a group; returns the (H, copies * W) image (Dr.Jit, unevaluated)."""
        kwargs = {"params": bundle.params} if ad else {}
        bundle.scene.integrator().copy_width = window.width
        return self.mi.render(bundle.scene, sensor=bundle.sensor(window), spp=int(spp),
                              seed=render_seed(seed, first + 1000 * pass_index), **kwargs)

    def _render_radiance(self, values: Mapping[str, float], angles: Sequence[float],
                         window: PixelWindow, spp: int, seed: int, first_index: int = 0) -> np.ndarray:
        """Scene radiance (before image-space extensions), shape (N, H, W)."""
        return _gather_radiance(self._queue_radiance(values, angles, window, spp, seed, first_index),
                                len(angles), window)

    def _queue_radiance(self, values: Mapping[str, float], angles: Sequence[float], window: PixelWindow,
                        spp: int, seed: int, first_index: int = 0, tent: bool = False) -> list[tuple[range, float, Any]]:
        """The launches of `_render_radiance`, queued and not yet read back (`_gather_radiance`).
        `tent`: the light engine's continuous column response (`LightPaths.render`; ignored by the
        camera engine)."""
        if self._light is not None:
            return [(range(0, len(angles)), w, img)
                    for _, w, img, _ in self._light_renders(values, angles, window, spp, seed, first_index, tent=tent)]
        groups, passes = self._groups(len(angles), window, spp)
        spp_pass = max(1, math.ceil(int(spp) / passes))
        pending = []
        with self.dr.suspend_grad():
            for grp in groups:
                bundle = self._bundle(len(grp))
                for x, w in self._bands(values):
                    bundle.assign(values, {}, [angles[i] for i in grp], x)
                    for q in range(passes):
                        img = self._launch(bundle, window, spp_pass, seed, first_index + grp.start, q, False)
                        # No sync here: Dr.Jit runs this launch while Python traces the next.
                        pending.append((grp, w / passes, img))
        return pending

    def _light_renders(self, values: Mapping[str, float], angles: Sequence[float], window: PixelWindow, spp: int,
                       seed: int, first_index: int = 0, scores: Sequence[str] = (),
                       tent: bool = False) -> list[tuple[float, float, Any, dict[str, Any]]]:
        """The light engine's renders of one call: per band node (x, quadrature weight,
        image, score images), images laid out (rows, angles, columns), not yet read back.
        Every node uses the same random numbers, as the camera engine's do (`_bands`)."""
        assert self._light is not None
        delta = values.get("angle_offset.delta_deg", 0.0)
        d = self.geometry.thickness_mm * (1.0 + values.get("thickness_error.e", 0.0))
        spread = values.get("filter_bandwidth.spread", 0.0)
        beam = self.beam_for(values, single_row=window.height == 1)
        out = []
        for x, w in self._bands(values):
            img, d_img = self._light.render(values, [float(a) + delta for a in angles], window,
                                            int(spp) * window.width, render_seed(seed, first_index), beam=beam,
                                            thickness_mm=d, sigma_t=values["sigma_t"] * (1.0 + spread * x),
                                            eta=values.get("refractive_boundary.n", 1.0), scores=scores,
                                            tent=tent)
            out.append((x, w, img, d_img))
        return out

    def _light_scores(self, values: Mapping[str, float], angles: Sequence[float], window: PixelWindow, spp: int,
                      seed: int, names: Sequence[str]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The light engine's radiance (N, H, W) and its derivatives for `names` (each an
        "ad" parameter: sigma_t, albedo, phase.*, filter_bandwidth.spread), from one pass
        per band node: d/dsigma_t of a node at sigma_t (1 + spread x) is (1 + spread x)
        times its score image, d/dspread is sigma_t x times it."""
        assert self._light is not None
        spread = values.get("filter_bandwidth.spread", 0.0)
        wanted = [n for n in names if n == "albedo" or n.startswith("phase.")]
        if "sigma_t" in names or "filter_bandwidth.spread" in names:
            wanted.insert(0, "sigma_t")
        renders = self._light_renders(values, angles, window, spp, seed, scores=wanted)
        self.dr.eval(*[img for _, _, img, _ in renders], *[v for *_, d in renders for v in d.values()])
        n, h, w_ = len(angles), window.height, window.width

        def host(a: Any) -> np.ndarray:
            return np.array(a, dtype=np.float64).reshape(h, n, w_).transpose(1, 0, 2)

        rad = np.zeros((n, h, w_))
        jac = {name: np.zeros((n, h, w_)) for name in names}
        for x, w, img, d_img in renders:
            rad += w * host(img)
            d = {k: host(v) for k, v in d_img.items()}
            for name in names:
                if name == "sigma_t":
                    jac[name] += w * (1.0 + spread * x) * d["sigma_t"]
                elif name == "filter_bandwidth.spread":
                    jac[name] += w * values["sigma_t"] * x * d["sigma_t"]
                else:
                    jac[name] += w * d[name]
        return rad, jac

    def _push_forward(self, radiance: np.ndarray, d_radiance: np.ndarray, values: Mapping[str, float],
                      window: PixelWindow, row_data: RowData) -> np.ndarray:
        """A radiance derivative (N, H, W) through the image-space extensions (exact for
        the linear ones, a blur or stray light; linearised for a sensor compression)."""
        if not self._image_exts():
            return d_radiance
        profile_only = window.height == 1
        top = float(np.max(np.abs(d_radiance)))
        if top == 0.0:
            return np.zeros_like(d_radiance)
        eps = 1e-4 * max(float(np.max(np.abs(radiance))), 1e-30) / top
        plus = self._post(radiance + eps * d_radiance, values, profile_only, row_data)
        minus = self._post(radiance - eps * d_radiance, values, profile_only, row_data)
        return (plus - minus) / (2.0 * eps)

    def _radiances(self, jobs: Sequence[tuple[Mapping[str, float], int]], angles: Sequence[float],
                   window: PixelWindow, spp: int, tent: bool = False) -> list[np.ndarray]:
        """`_render_radiance(values, angles, window, spp, seed)` of each (values, seed) of `jobs`,
        the same numbers, up to `_QUEUED_RENDERS` of them queued before the first is read back.

        Dr.Jit runs a thread's kernels in order, asynchronously, and reading any result waits
        for every kernel queued before: renders read one by one leave the cores idle while
        the next is traced in Python (most of a render at a few samples per pixel,
        `docs/forward-model.md`); queued together, each render's kernels run while the next
        is traced. The caller holds the lock."""
        lanes = len(angles) * window.width * window.height * int(spp)
        per_queue = max(1, min(_QUEUED_RENDERS, _QUEUED_LANES // max(1, lanes)))
        out: list[np.ndarray] = []
        for i in range(0, len(jobs), per_queue):
            queued = [self._queue_radiance(values, angles, window, spp, seed, tent=tent)
                      for values, seed in jobs[i:i + per_queue]]
            out.extend(_gather_radiance(q, len(angles), window) for q in queued)
        return out

    def _image_exts(self) -> list[type[ImageExtension]]:
        return [EXTENSIONS[n] for n in IMAGE_ORDER if n in self.extensions]  # type: ignore[misc]

    def _row_data(self, angles: Sequence[float], window: PixelWindow) -> RowData:
        """What the image-space extensions take from the recording for these angles'
        profile rows (`ImageExtension`): the y-shape when the lens blur acts on them
        (`y_shape_for`), the merge's fill when the sensor compression does
        (`merge_fill_for`); nothing for other windows. The beam calibration's fills
        (`beam_fill`) go to the sensor compression in every window."""
        out = no_row_data()
        if "sensor_nonlinearity" in self.extensions:
            out["beam_fill"] = self.beam_fill
        # A one-row window is lit by the core-blurred map (`beam_for`).
        out["core_in_scene"] = self.core_blur_in_scene and window.height == 1
        if window != self.geometry.profile_window():
            return out
        if "lens_blur" in self.extensions:
            out["y_shape"] = self.y_shape_for(angles)
        if "sensor_nonlinearity" in self.extensions:
            out["merge_fill"] = self.merge_fill_for(angles)
        return out

    def merge_fill_for(self, angles: Sequence[float]) -> np.ndarray | None:
        """The merge's fill for these angles' profile rows (N, W); None unless every angle
        has one over the profile's columns (the compression then takes its full-well form)."""
        width = self.geometry.profile_window().width
        fills = [self.profile_merge_fill.get(_angle_key(a)) for a in angles]
        if not fills or any(g is None or g.shape != (width,) for g in fills):
            return None
        return np.stack(fills)  # type: ignore[arg-type]

    def y_shape_for(self, angles: Sequence[float]) -> np.ndarray | None:
        """The recording's y-shape for these angles' profile rows (N, 2T + 1, W), h = 1 for
        angles without one; None when the model has none (the lens blur uses its LSF)."""
        if not self.profile_y_shape:
            return None
        key = tuple(_angle_key(a) for a in angles)
        hit = self._y_shapes.get(key)
        if hit is not None:
            return hit
        window = self.geometry.profile_window()
        rows = []
        for a in angles:
            h = self.profile_y_shape.get(_angle_key(a))
            if h is None or h.shape[-1] != window.width:
                h = np.ones((2 * LENS_BLUR_RADIUS + 1, window.width))
            rows.append(h)
        # One read-only array per set of angles: the lens blur caches its weights by it.
        out = np.stack(rows)
        out.setflags(write=False)
        if len(self._y_shapes) >= 16:
            self._y_shapes.pop(next(iter(self._y_shapes)))
        self._y_shapes[key] = out
        return out

    def _post(self, radiance: np.ndarray, values: Mapping[str, float], profile_only: bool,
              row_data: RowData | None = None) -> np.ndarray:
        img = radiance
        for ext in self._image_exts():
            img = ext.apply(img, ext.values(values), pixel_mm=self.geometry.pixel_mm, profile_only=profile_only,
                            **(row_data or no_row_data()))
        return img

    def _check_call(self, angles: npt.ArrayLike, spp: int, seed: int) -> list[float]:
        a = [float(x) for x in np.atleast_1d(np.asarray(angles, dtype=np.float64))]
        for x in a:
            if not math.isfinite(x) or not -360.0 <= x <= 360.0:
                raise ModelParameterError(f"stage angle {x!r} must be a finite number of degrees")
        if int(spp) < 1:
            raise ModelParameterError(f"spp={spp!r} must be >= 1")
        if int(seed) < 0:
            raise ModelParameterError(f"seed={seed!r} must be >= 0")
        return a

    def render_profiles(self, params: Mapping[str, float], angles_deg: npt.ArrayLike, *,
                        spp: int = 128, seed: int = 0) -> np.ndarray:
        """Profile rows for every angle, shape (N, W), image-space extensions applied.

        Args:
            params: parameter values (missing ones take their defaults).
            angles_deg: stage angles phi (degrees).
            spp: samples per pixel.
            seed: base seed (same seed -> same result).
        """
        return self.render(params, angles_deg, spp=spp, seed=seed)[:, 0, :]

    def render_profiles_many(self, requests: Sequence[tuple[Mapping[str, float], int]], angles_deg: npt.ArrayLike,
                             *, spp: int = 128) -> list[np.ndarray]:
        """`render_profiles(params, angles_deg, spp=spp, seed=seed)` for each (params, seed) of
        `requests`, the same numbers, the renders queued together (`_radiances`: on 2 cores
        the coarse start's 220 renders at 8 spp took 25 % less time)."""
        checked = [(self.validate(p), int(seed)) for p, seed in requests]
        # The smallest seed is the one to refuse, if any is.
        angles = self._check_call(angles_deg, spp, min((seed for _, seed in checked), default=0))
        window = self.geometry.window(None, None)
        row_data = self._row_data(angles, window)
        with self._lock:
            rads = self._radiances(checked, angles, window, spp)
        return [self._post(rad, values, profile_only=True, row_data=row_data)[:, 0, :]
                for rad, (values, _) in zip(rads, checked)]

    def render(self, params: Mapping[str, float], angles_deg: npt.ArrayLike, *,
               columns: tuple[int, int] | None = None, rows: tuple[int, int] | None = None,
               spp: int = 128, seed: int = 0) -> np.ndarray:
        """Images of a pixel window for every angle, shape (N, H, W), numpy float64.

        `columns` / `rows` are sensor pixel ranges [start, stop); None = the profile's
        columns / the profile row. A full frame: rows=(0, rows), columns=(0, columns).
        Image-space extensions act on the window (lens blur in 2D when H > 1).
        """
        values = self.validate(params)
        angles = self._check_call(angles_deg, spp, seed)
        window = self.geometry.window(columns, rows)
        with self._lock:
            rad = self._render_radiance(values, angles, window, spp, seed)
        return self._post(rad, values, profile_only=window.height == 1, row_data=self._row_data(angles, window))

    # ------------------------------------------------------------------ derivatives
    def linearize(self, params: Mapping[str, float], angles_deg: npt.ArrayLike, *, spp: int = 128,
                  seed: int = 0, columns: tuple[int, int] | None = None) -> Linearization:
        """Render the profiles and keep what their vector-Jacobian product needs.

        Returns a `Linearization` whose `profiles` equal `render_profiles(..., seed=seed)`
        (same paths) and whose `vjp(cotangent)` equals `vjp(params, ..., cotangent, seed=seed)`,
        for a cotangent that may be computed from the profiles themselves or from other
        renders. Path replay needs the primal pass's per-path radiance; keeping it avoids
        tracing the primal paths a second time (a separate render plus `vjp` traced them twice).
        The kept state (~0.1 kB a path) is freed by `vjp`, which can be called once.
        """
        values = self.validate(params)
        angles = self._check_call(angles_deg, spp, seed)
        window = self.geometry.window(columns, None)
        dr = self.dr
        mi = self.mi
        ad_names = [n for n, s in self.specs.items() if s.derivative == "ad"]
        if self._light is not None:
            with self._lock:
                rad, jac = self._light_scores(values, angles, window, spp, seed, ad_names)
            profiles = self._post(rad, values, profile_only=window.height == 1,
                                  row_data=self._row_data(angles, window))[:, 0, :]
            return Linearization(self, values, angles, window, int(spp), int(seed), columns, rad, profiles, [],
                                 light_jacobian=jac)
        groups, passes = self._groups(len(angles), window, spp)
        spp_pass = max(1, math.ceil(int(spp) / passes))
        kept: list[_KeptGroup] = []
        pending = []
        with self._lock:
            for grp in groups:
                ang = [angles[i] for i in grp]
                bundle = self._bundle(len(grp))
                leaves = {n: dr.opaque(mi.Float, values[n]) for n in ad_names}
                for leaf in leaves.values():
                    dr.enable_grad(leaf)
                integrator = bundle.scene.integrator()
                integrator.copy_width = window.width
                sensor = bundle.sensor(window)
                group = _KeptGroup(grp, bundle, leaves)
                for x, w in self._bands(values):
                    # The leaves go into the scene now (the primal pass ignores their
                    # gradients) and again before the replay, which other renders may precede.
                    bundle.assign(values, leaves, ang, x)
                    for q in range(passes):
                        img, state = integrator.render_kept(bundle.scene, sensor,
                                                            render_seed(seed, grp.start + 1000 * q), spp_pass)
                        pending.append((grp, w / passes, img))
                        group.passes.append((x, w / passes, state))
                kept.append(group)
            dr.eval()
            rad = _gather_radiance(pending, len(angles), window)
        row_data = self._row_data(angles, window)
        profiles = self._post(rad, values, profile_only=window.height == 1, row_data=row_data)[:, 0, :]
        return Linearization(self, values, angles, window, int(spp), int(seed), columns, rad, profiles, kept)

    def vjp(self, params: Mapping[str, float], angles_deg: npt.ArrayLike, cotangent: np.ndarray, *,
            spp: int = 128, seed: int = 0, columns: tuple[int, int] | None = None,
            fd_parameters: bool = True, base_profiles: np.ndarray | None = None) -> dict[str, float]:
        """Vector-Jacobian product: d/dtheta sum(cotangent * profiles(theta)) for every parameter.

        `cotangent` has the shape of `render_profiles` (N, W), e.g. dLoss/dprofile. "ad"
        parameters come from Dr.Jit reverse mode (path replay of one primal render), "image"
        ones exactly through the image-space functions, "fd" ones (only if `fd_parameters`)
        from central differences with common random numbers (2 extra forward renders each).
        Uses the same seeds as `render_profiles(..., seed=seed)`; pass that call's result
        as `base_profiles` to make the finite differences one-sided (one extra render per
        "fd" parameter instead of two). "sigma_t" is "ad" index-matched and "fd" with
        `refractive_boundary` (next-event rays must end inside the medium there, and
        prbvolpath drops the attenuation derivative of such rays); it is always computed,
        `fd_parameters=False` skips only the other "fd" (extension) parameters (reported 0).
        When the profiles are needed too, `linearize` gives both for the price of this call.
        """
        angles = self._check_call(angles_deg, spp, seed)
        _check_cotangent(cotangent, len(angles), self.geometry.window(columns, None).width)
        lin = self.linearize(params, angles, spp=spp, seed=seed, columns=columns)
        return lin.vjp(cotangent, fd_parameters=fd_parameters, base_profiles=base_profiles)

    def _pullback(self, radiance: np.ndarray, cot_out: np.ndarray, values: Mapping[str, float],
                  window: PixelWindow, row_data: RowData | None = None) -> tuple[np.ndarray, dict[str, float]]:
        """Cotangent on the scene radiance, and image-parameter gradients."""
        rd: RowData = row_data or no_row_data()
        exts = self._image_exts()
        pm = self.geometry.pixel_mm
        profile_only = window.height == 1
        inputs = []
        img = radiance
        for ext in exts:
            inputs.append(img)
            img = ext.apply(img, ext.values(values), pixel_mm=pm, profile_only=profile_only, **rd)
        grads: dict[str, float] = {}
        cot = cot_out
        for ext, inp in zip(reversed(exts), reversed(inputs)):
            v = ext.values(values)
            for short, dimg in ext.param_derivatives(inp, v, pixel_mm=pm, profile_only=profile_only,
                                                     **rd).items():
                grads[f"{ext.name}.{short}"] = float(np.sum(dimg * cot))
            cot = ext.vjp_input(inp, cot, v, pixel_mm=pm, profile_only=profile_only, **rd)
        return cot, grads

    def value_and_grad(self, params: Mapping[str, float], angles_deg: npt.ArrayLike,
                       loss: Callable[[np.ndarray], tuple[float, np.ndarray]], *, spp: int = 128,
                       seed: int = 0, fd_parameters: bool = True) -> tuple[float, np.ndarray, dict[str, float]]:
        """Loss, profiles and the loss gradient for every parameter.

        `loss(profiles) -> (value, dvalue/dprofiles)` works on numpy arrays (N, W); the
        gradient is `vjp` of that cotangent with the same seed (so the adjoint replays the
        forward render's paths).
        """
        lin = self.linearize(params, angles_deg, spp=spp, seed=seed)
        value, cot = loss(lin.profiles)
        grads = lin.vjp(cot, fd_parameters=fd_parameters, base_profiles=lin.profiles)
        return float(value), lin.profiles, grads

    def jacobian(self, params: Mapping[str, float], angles_deg: npt.ArrayLike, names: Sequence[str], *,
                 spp: int = 128, seed: int = 0, steps: Mapping[str, float] | None = None,
                 columns: tuple[int, int] | None = None,
                 base_profiles: np.ndarray | None = None, backward: bool = False) -> dict[str, np.ndarray]:
        """d profiles / d parameter for each name, arrays (N, W).

        "image" parameters: exact through the image-space function (one render in all).
        Others: central differences with common random numbers (same seeds), step
        `steps[name]` or the parameter's default `fd_step * max(1, |value|)`, shrunk to stay
        inside its range; one-sided (forward) differences against `base_profiles` when
        given (the `render_profiles` result with the same parameters and seed), or backward
        ones with `backward` (each falls back to the other side at a bound of the range).
        prbvolpath has no forward mode, so this is the efficient way to get a few columns
        of the Jacobian.
        """
        values = self.validate(params)
        angles = self._check_call(angles_deg, spp, seed)
        window = self.geometry.window(columns, None)
        out: dict[str, np.ndarray] = {}
        row_data = self._row_data(angles, window)
        profile_only = window.height == 1
        #: exact through the image-space function, from one render at `values`
        image_names = [name for name in names if self._spec(name).derivative == "image"]
        #: the light engine's score columns, from that same render
        score_names = ([name for name in names if self._spec(name).derivative == "ad"]
                       if self._light is not None else [])
        base_rad: np.ndarray | None = None
        if score_names:
            with self._lock:
                base_rad, jac_rad = self._light_scores(values, angles, window, spp, seed, score_names)
            for name in score_names:
                out[name] = self._push_forward(base_rad, jac_rad[name], values, window, row_data)[:, 0, :]
        #: per difference: name, the two ends' values (None: the base profiles), the step
        diffs: list[tuple[str, dict[str, float] | None, dict[str, float] | None, float]] = []
        for name in names:
            spec = self._spec(name)
            if spec.derivative == "image" or name in score_names:
                continue
            x = values[name]
            h = float((steps or {}).get(name, spec.fd_step * max(1.0, abs(x))))
            lo = x - h
            hi = x + h
            lower = spec.lower + (1e-9 if spec.open_lower else 0.0)
            if name == "thickness_error.e":
                lower = max(lower, -0.9)
            lo = max(lo, lower)
            hi = min(hi, spec.upper)
            one_sided = base_profiles is not None
            if one_sided and backward:
                hi = x
                if lo == x:  # at the lower bound: step up instead
                    lo, hi = x, min(x + h, spec.upper)
            elif one_sided:
                lo = x
                if hi == x:  # at the upper bound: step down instead
                    hi, lo = x, max(x - h, lower)
            diffs.append((name, None if one_sided and lo == x else {**values, name: lo},
                          None if one_sided and hi == x else {**values, name: hi}, hi - lo))
        if self._light is not None:
            # The light engine's differences render both ends with the continuous (tent) column
            # response (`LightPaths.render(tent=...)`), the base too: the given base profiles
            # have the pixels' box response.
            diffs = [(n, dict(values) if lo is None else lo, dict(values) if hi is None else hi, st)
                     for n, lo, hi, st in diffs]
        # Every render (the image parameters' base first, then each difference's ends) queued
        # before any is read (`_radiances`).
        jobs = [(values, seed)] if image_names and base_rad is None else []
        fd_jobs = [(v, seed) for _, v_lo, v_hi, _ in diffs for v in (v_lo, v_hi) if v is not None]
        with self._lock:
            rads = iter(self._radiances(jobs, angles, window, spp)
                        + self._radiances(fd_jobs, angles, window, spp, tent=self._light is not None))
        if image_names:
            if base_rad is None:
                base_rad = next(rads)
            for name in image_names:
                out[name] = self._image_param_derivative(base_rad, values, name, window, row_data)

        def end(v: dict[str, float] | None) -> np.ndarray:
            if v is None:  # only one-sided differences leave an end unrendered
                return np.asarray(base_profiles, dtype=np.float64)[:, None, :]
            return self._post(next(rads), v, profile_only, row_data)

        for name, v_lo, v_hi, step in diffs:
            r_lo = end(v_lo)
            out[name] = ((end(v_hi) - r_lo) / step)[:, 0, :]
        return {name: out[name] for name in names}

    def additive_parameters(self) -> list[str]:
        """Parameters that add `value x a fixed image` to the profiles (`ParameterSpec.additive`).

        Only those whose extension is the last image-space effect applied: an effect after it
        (sensor compression) would make the sum depend on the scene. Their columns
        (`additive_columns`) need no render, and a fit can solve for them exactly at every
        iteration.
        """
        exts = self._image_exts()
        last = exts[-1].name if exts else None
        return [n for n, s in self.specs.items() if s.additive and n.split(".", 1)[0] == last]

    def additive_columns(self, params: Mapping[str, float], n_angles: int,
                         names: Sequence[str] | None = None) -> dict[str, np.ndarray]:
        """d profiles / d parameter, arrays (n_angles, W), for additive parameters (all of
        `additive_parameters()` by default); exact, and without a render."""
        names = self.additive_parameters() if names is None else list(names)
        allowed = set(self.additive_parameters())
        for n in names:
            if n not in allowed:
                raise ModelParameterError(f"{n!r} is not an additive parameter of this model")
        values = self.validate(params)
        window = self.geometry.window(None, None)
        zero = np.zeros((int(n_angles), window.height, window.width))
        return {n: self._image_param_derivative(zero, values, n, window) for n in names}

    def _image_param_derivative(self, radiance: np.ndarray, values: Mapping[str, float], name: str,
                                window: PixelWindow, row_data: RowData | None = None) -> np.ndarray:
        """Exact derivative of the image chain output w.r.t. one image parameter."""
        rd: RowData = row_data or no_row_data()
        ext_name, short = name.split(".", 1)
        pm = self.geometry.pixel_mm
        profile_only = window.height == 1
        exts = self._image_exts()
        img = radiance
        for i, ext in enumerate(exts):
            v = ext.values(values)
            if ext.name == ext_name:
                d = ext.param_derivatives(img, v, pixel_mm=pm, profile_only=profile_only, **rd)[short]
                out = ext.apply(img, v, pixel_mm=pm, profile_only=profile_only, **rd)
                # Push the derivative through the rest of the chain (linearised).
                for later in exts[i + 1:]:
                    lv = later.values(values)
                    eps = 1e-4 * max(1e-30, float(np.max(np.abs(d))) or 1.0)
                    plus = later.apply(out + eps * d, lv, pixel_mm=pm, profile_only=profile_only, **rd)
                    minus = later.apply(out - eps * d, lv, pixel_mm=pm, profile_only=profile_only, **rd)
                    out = later.apply(out, lv, pixel_mm=pm, profile_only=profile_only, **rd)
                    d = (plus - minus) / (2 * eps)
                return d[:, 0, :]
            img = ext.apply(img, v, pixel_mm=pm, profile_only=profile_only, **rd)
        raise ModelParameterError(f"{name!r} is not an image-space parameter of this model")


def _gather_radiance(pending: Sequence[tuple[range, float, Any]], n_angles: int, window: PixelWindow) -> np.ndarray:
    """(N, H, W) radiance from launches' images (H, len(group) * W), each weighted (band node
    weight / sample passes) into its angle group."""
    out = np.zeros((n_angles, window.height, window.width))
    for grp, w, img in pending:
        a = np.array(img, dtype=np.float64).reshape(window.height, len(grp), window.width)
        out[grp.start:grp.stop] += w * a.transpose(1, 0, 2)
    return out


def _check_cotangent(cotangent: np.ndarray, n_angles: int, width: int) -> np.ndarray:
    cot = np.asarray(cotangent, dtype=np.float64)
    if cot.shape != (n_angles, width):
        raise ModelParameterError(f"cotangent shape {cot.shape} != (angles, width) = {(n_angles, width)}")
    if not np.all(np.isfinite(cot)):
        raise ModelParameterError("cotangent contains NaN or infinite values")
    return cot


class _KeptGroup:
    """One launch group of a `Linearization`: its scene, gradient leaves and kept passes."""

    def __init__(self, grp: range, bundle: _SceneBundle, leaves: dict[str, Any]) -> None:
        self.grp = grp
        self.bundle = bundle
        self.leaves = leaves
        self.passes: list[tuple[float, float, Any]] = []   # (band node, weight, KeptPrimal)


class Linearization:
    """Profiles rendered at one parameter point, with the state of their paths kept for one
    vector-Jacobian product (`ForwardModel.linearize`)."""

    def __init__(self, model: ForwardModel, values: dict[str, float], angles: list[float], window: PixelWindow,
                 spp: int, seed: int, columns: tuple[int, int] | None, radiance: np.ndarray,
                 profiles: np.ndarray, groups: list[_KeptGroup],
                 light_jacobian: dict[str, np.ndarray] | None = None) -> None:
        self.model = model
        self.values = values
        self.angles = angles
        self.window = window
        self.spp = spp
        self.seed = seed
        self.columns = columns
        self.radiance = radiance
        #: the rendered profiles (N, W), image-space extensions applied
        self.profiles = profiles
        self._groups: list[_KeptGroup] | None = groups
        #: the light engine's d radiance / d parameter (N, H, W) for the "ad" parameters
        self._light_jacobian = light_jacobian

    def vjp(self, cotangent: np.ndarray, *, fd_parameters: bool = True,
            base_profiles: np.ndarray | None = None) -> dict[str, float]:
        """d/dtheta sum(cotangent * profiles(theta)) for every parameter, as
        `ForwardModel.vjp` with this render's parameters, seed and spp. Once per linearization.

        Raises:
            ModelParameterError: cotangent of the wrong shape or not finite.
            RuntimeError: called a second time (the replay consumed the kept paths).
        """
        m = self.model
        cot = _check_cotangent(cotangent, len(self.angles), self.window.width)[:, None, :]
        if self._groups is None:
            raise RuntimeError("Linearization.vjp was already called; linearize again")
        groups, self._groups = self._groups, None
        dr = m.dr
        mi = m.mi
        window = self.window
        grads = {n: 0.0 for n in m.specs}
        image_exts = m._image_exts()
        if self._light_jacobian is not None:
            # The light engine's score images: the product needs no second pass.
            if image_exts:
                cot_rad, ext_grads = m._pullback(self.radiance, cot, self.values, window,
                                                 m._row_data(self.angles, window))
                grads.update(ext_grads)
            else:
                cot_rad = cot
            for name, d_rad in self._light_jacobian.items():
                grads[name] = float(np.sum(d_rad * cot_rad))
        with m._lock:
            for group in groups:
                grp = group.grp
                ang = [self.angles[i] for i in grp]
                cot_g = cot[grp.start:grp.stop]
                if image_exts:
                    cot_rad, ext_grads = m._pullback(self.radiance[grp.start:grp.stop], cot_g, self.values, window,
                                                     m._row_data(ang, window))
                    for name, gv in ext_grads.items():
                        grads[name] += gv
                else:
                    cot_rad = cot_g
                c_img = cot_rad.transpose(1, 0, 2).reshape(window.height, len(grp) * window.width)
                integrator = group.bundle.scene.integrator()
                band = None
                for x, w, state in group.passes:
                    if x != band:
                        group.bundle.assign(self.values, group.leaves, ang, x)
                        band = x
                    c = mi.TensorXf(np.ascontiguousarray(w * c_img, dtype=np.float32)
                                    .reshape(window.height, len(grp) * window.width, 1))
                    integrator.backward_kept(group.bundle.scene, state, c)
                for n, leaf in group.leaves.items():
                    g = dr.grad(leaf)
                    grads[n] += float(g[0]) if dr.width(g) else 0.0
        fd_names = [n for n, s in m.specs.items() if s.derivative == "fd" and (fd_parameters or n == "sigma_t")]
        if fd_names:
            jac = m.jacobian(self.values, self.angles, fd_names, spp=self.spp, seed=self.seed, columns=self.columns,
                             base_profiles=base_profiles)
            for n in fd_names:
                grads[n] = float(np.sum(jac[n] * cot[:, 0, :]))
        return grads


class _SceneBundle:
    """One Mitsuba scene of the model rendering `copies` stage angles in one launch (the
    path's sub-camera index, carried in its time, selects the angle), its parameters and
    its batch sensors (`copies` identical orthographic sub-cameras)."""

    def __init__(self, model: ForwardModel, copies: int) -> None:
        self.model = model
        self.copies = copies
        mi = model.mi
        T = mi.ScalarTransform4f
        g = model.geometry
        d = g.thickness_mm
        hw = g.half_width_mm
        if model.phase == "tthg":
            ps = model.specs
            phase = tthg_phase_dict(ps["phase.g_forward"].neutral, ps["phase.g_backward"].neutral,
                                    ps["phase.w_forward"].neutral)
        elif model.phase == "hg":
            phase = {"type": "hg", "g": model.specs["phase.g"].neutral}
        elif model.phase_table is not None:
            phase = tabulated_phase_dict(model.phase_table.log_p)
        else:
            phase = exp_phase_dict([0.0] * sum(1 for k in model.specs if k.startswith("phase.b")))
        refractive = model._refractive
        scene_dict: dict[str, Any] = {
            "type": "scene",
            "integrator": {"type": "rig_prbvolpath", "max_depth": model.max_depth, "rr_depth": model.rr_depth,
                           "copies": copies, "copy_width": 1},
            "medium": {"type": "homogeneous", "sigma_t": 1.0, "albedo": 0.5, "phase": phase},
            "boundary": ({"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0} if refractive
                         else {"type": "null"}),
            "beam": {"type": "collimated_beam", "thickness": d, "copies": copies,
                     "cross_face": not refractive,
                     "reflections": INTERNAL_REFLECTIONS if refractive else 0},
            "slab": {
                "type": "cube",
                "to_world": T().translate([0.0, 0.0, -0.5 * d]).scale([hw, hw, 0.5 * d]),
                "bsdf": {"type": "ref", "id": "boundary"},
                "interior": {"type": "ref", "id": "medium"},
            },
        }
        self.scene = mi.load_dict(scene_dict)
        beam = next(iter(self.scene.emitters()))
        beam.set_profile(model.beam_profile)
        self.beam_emitter = beam
        self.beam_installed = model.beam_profile
        self.params = mi.traverse(self.scene)
        keys = list(self.params.keys())

        def key(suffix: str) -> str:
            hits = [k for k in keys if k.endswith(suffix)]
            if not hits:
                raise RuntimeError(f"scene parameter *{suffix} not found among {keys}")
            return hits[0]

        self.k_sigma_t = key("sigma_t.value.value")
        self.k_albedo = key("albedo.value.value")
        # Mitsuba may merge the copies into one mesh: scale whatever meshes there are.
        self.k_vertices = [k for k in keys if k.endswith("vertex_positions")]
        self.base_vertices = [np.array(self.params[k], dtype=np.float64) for k in self.k_vertices]
        self.thickness = d
        if model.phase == "tthg":
            self.k_phase = {
                "weight": key("phase_function.weight.value.value"),
                "g0": key("phase_function.phase_0.g"),
                "g1": key("phase_function.phase_1.g"),
            }
        elif model.phase == "hg":
            self.k_phase = {"g": key("phase_function.g")}
        else:
            self.k_phase = {n: key(f"phase_function.{n.split('.')[1]}") for n in model.specs
                            if n.startswith("phase.b")}
        #: the exponential phase plugin, told its coefficients before each update (`announce`)
        self.exp_phase = None
        if self.k_phase and model.phase.startswith("exp"):
            medium = next(m for m in (sh.interior_medium() for sh in self.scene.shapes()) if m is not None)
            self.exp_phase = medium.phase_function()
        self.k_beam = {n: key(f"beam.{n}") for n in ("angle_deg", "eta", "thickness", "sigma_t",
                                                     "halo_fraction", "halo_sigma_mm")}
        self.eta = 1.5
        self.k_eta = key("eta") if refractive else None
        self.sensors: dict[PixelWindow, Any] = {}

    def sensor(self, window: PixelWindow) -> Any:
        """Batch sensor: copy k's orthographic camera sees the window on slab copy k."""
        s = self.sensors.get(window)
        if s is None:
            mi = self.model.mi
            T = mi.ScalarTransform4f
            g = self.model.geometry
            p = g.pixel_mm
            x, y = g.window_center_mm(window)
            z = 10.0 + 2.0 * g.thickness_mm
            half = 0.5 * window.width * p  # the film spans [-1, 1] in x, [-1/aspect, 1/aspect] in y
            film = {"type": "hdrfilm", "width": window.width, "height": window.height,
                    "rfilter": {"type": "box"}, "pixel_format": "luminance", "sample_border": False}
            subs = {}
            for k in range(self.copies):
                subs[f"cam{k:03d}"] = {
                    "type": "orthographic", "near_clip": 1e-3, "far_clip": 1e4,
                    "to_world": T().look_at([x, y, z], [x, y, 0.0], [0.0, 1.0, 0.0]).scale([half, half, 1.0]),
                    "film": dict(film),
                }
            batch_film = dict(film)
            batch_film["width"] = window.width * self.copies
            s = mi.load_dict({"type": "batch", "film": batch_film,
                              "sampler": {"type": "independent", "sample_count": 1}, **subs})
            self.sensors[window] = s
        return s

    def _set_thickness(self, d: float) -> None:
        if d == self.thickness:
            return
        scale = d / self.model.geometry.thickness_mm
        for k, base in zip(self.k_vertices, self.base_vertices):
            v = base.reshape(-1, 3).copy()
            v[:, 2] *= scale  # the front face z = 0 stays, the back face moves to -d
            self.params[k] = self.model.mi.Float(v.ravel().astype(np.float32))
        self.thickness = d

    def assign(self, values: Mapping[str, float], leaves: Mapping[str, Any],
               angles: Sequence[float], band_x: float) -> None:
        """Write one render's parameters (fresh AD expressions each time, so the graph
        from the leaves survives earlier adjoint passes)."""
        model = self.model
        dr = model.dr
        mi = model.mi
        if model.deblurs_beam or model.decompresses_beam:
            prof = model.beam_for(values)
            if prof is not self.beam_installed:
                self.beam_emitter.set_profile(prof)
                self.beam_installed = prof

        def val(name: str) -> Any:
            if name in leaves:
                return leaves[name]
            return dr.opaque(mi.Float, values[name])

        sigma_t = val("sigma_t")
        if "filter_bandwidth" in model.extensions:
            sigma_t = sigma_t * (1.0 + val("filter_bandwidth.spread") * band_x)
        else:
            sigma_t = sigma_t * 1.0
        p = self.params
        p[self.k_sigma_t] = sigma_t
        p[self.k_albedo] = val("albedo") * 1.0
        if model.phase == "tthg":
            p[self.k_phase["weight"]] = 1.0 - val("phase.w_forward")
            p[self.k_phase["g0"]] = val("phase.g_forward") * 1.0
            p[self.k_phase["g1"]] = val("phase.g_backward") * 1.0
        elif model.phase == "hg":
            p[self.k_phase["g"]] = val("phase.g") * 1.0
        else:
            for name, k in self.k_phase.items():
                p[k] = val(name) * 1.0
                p.set_dirty(k)  # recompute the normalisation from the new b's
            if self.exp_phase is not None:
                self.exp_phase.announce([values[name] for name in self.k_phase])
        delta = values.get("angle_offset.delta_deg", 0.0)
        e = values.get("thickness_error.e", 0.0)
        n = values.get("refractive_boundary.n", 1.0)
        d = model.geometry.thickness_mm * (1.0 + e)
        if self.k_eta is not None and n != self.eta:
            p[self.k_eta] = float(n)
            self.eta = n
        self._set_thickness(d)
        kb = self.k_beam
        a = [float(x) + delta for x in angles]
        a += [a[-1]] * (self.copies - len(a))
        angle_arr = mi.Float(a)
        dr.make_opaque(angle_arr)
        p[kb["angle_deg"]] = angle_arr
        p[kb["eta"]] = dr.opaque(mi.Float, n)
        p[kb["thickness"]] = dr.opaque(mi.Float, d)
        p[kb["sigma_t"]] = sigma_t
        if "beam_halo" in model.extensions:
            p[kb["halo_fraction"]] = val("beam_halo.fraction") * 1.0
            p[kb["halo_sigma_mm"]] = val("beam_halo.sigma_mm") * 1.0
        p.update()
