"""Light paths: the slab rendered by tracing light from the beam to the camera.

The forward model's camera engine (`estimate.forward`, Mitsuba's `prbvolpath`) traces paths
from the orthographic camera and connects each vertex to the collimated beam. A vertex adds
light only where it lies inside the beam's narrow column, so a profile pixel a few
millimetres from the spot gets light from the few camera paths that wander into it. This
engine traces the other way: every path starts in the beam, and every scattering vertex is
connected to the camera. The camera is orthographic and looks along -z, so it sees a vertex
along one direction (+z) and the connection is deterministic:

    contribution = w * albedo * p(mu) * exp(-sigma_t * depth) / A_pixel

in the pixel the vertex projects to (w the path's power, mu the cosine between the path's
direction and +z, depth the vertex's distance below the front face, A_pixel the pixel's
area in the object plane, mm^2). Samples are then spent where the light is.

A profile is one sensor row, 67 um tall, while the light spreads over a millimetre or more
in y: most vertices would land in other rows. But the slab and the medium do not change
along y (the beam's v axis is world y at every stage angle), so where a path goes does not
depend on the start v within the beam. Every path therefore starts at v = 0 and each vertex,
displaced by dy, adds to a row the beam's share of start positions v that would put it
there: the integral of the map's conditional irradiance E(v | u) over [y_lo - dy, y_hi - dy].
Every vertex then adds to the profile row. The slab's walls at |y| = half width are ignored
(12.5 mm against the light's spread of a few mm). `benchmarks/exp_light_tracing.py` measured
this estimator at 30-115 times the camera engine's precision per second at the profile's
peak and shoulder, 6-50 in its tail (2 cores, `docs/forward-model.md`).

Derivatives (`render(..., scores=...)`): with every distance drawn from sigma_t exp(-sigma_t t)
and every direction from (a proposal of) the phase function, the derivative of a path's
expected contribution is the contribution times the derivative of the log of the physical
path density (the score): for k collisions, total length L and depth z below the face,

    d/dsigma_t: k / sigma_t - L - z      d/dalbedo: k / albedo      d/db: sum_j d log p(mu_j) / db

summed over the path's sampled directions and its connection to the camera. So one pass
renders the image and its Jacobian for these parameters (unbiased; the slab's faces do not
move with them, so there is no boundary term). The beam halo, the stage angle and the
thickness move the light's sources or the walls: those are differentiated by differences.

A refractive boundary (`eta` > 1, the extension `refractive_boundary`): the beam is refracted
on entry and carries the share 1 - F that enters (Fresnel); a flight that reaches a face is
reflected with probability F (totally beyond the critical angle), else the path leaves; the
connection to the camera leaves through the front face at normal incidence, transmitted by
1 - F0 with the radiance divided by n^2, directly or after reflecting off the back face, with
every round trip between the faces summed in closed form (`_connection`).

Scope: the slab, with or without that boundary; a Gaussian halo around the map's centroid as
in `estimate.beam`; phase functions exp<M>, hg and tthg as in the camera engine. Units: mm,
1/mm; the image is radiance in the map's irradiance units per steradian, as the camera
engine's.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from estimate.beam import BeamProfile
from estimate.errors import ModelParameterError
from estimate.geometry import PixelWindow, RigGeometry
from estimate.mitsuba_phase import inverse_cdf_table, tabulated_inverse_cdf, tabulated_log_p
from estimate.phase_exponential import ExponentialPhase
from estimate.phase_tabulated import TabulatedPhase

__all__ = ["CHUNK_PATHS", "LightPaths", "MAX_ROWS", "RENDER_REVISION", "SourceTables", "TABLE",
           "check_phase_table", "phase_parameter_names"]

#: Changes whenever the same seed and settings render a different image, so that images cached
#: from an earlier revision are not reused (`sim_devices.rendered_scene.RenderedScene.cache_key`).
#: 2: the pixel sums in double precision (session 91); the single-precision sums had put the
#: bright pixels 0.03-0.10 % low at 16384 spp (see `LightPaths.render`).
RENDER_REVISION = 2

#: Windows of more rows than this are refused: each vertex adds to every row of the window.
MAX_ROWS = 64

#: Paths traced in one launch at most (their state is about 0.1 kB a path).
CHUNK_PATHS = 2 ** 22

#: The camera engine's sampling table size (`estimate.mitsuba_phase`), reused here.
_TABLE_SIZE = 2048
#: Phase model name of a tabulated phase function (`estimate.phase_tabulated`): a truth
#: the simulated bench renders, with no parameters to fit.
TABLE = "table"


def check_phase_table(phase: str, table: TabulatedPhase | None) -> None:
    """`ModelParameterError` unless a tabulated phase function comes with phase "table" and
    only with it (`LightPaths`, `estimate.forward.ForwardModel`)."""
    if (phase == TABLE) != (table is not None):
        raise ModelParameterError('a tabulated phase function goes with phase "table", and only with it')


def phase_parameter_names(phase: str, degree: int | None = None) -> list[str]:
    """The model's phase parameter names for a phase model name (`exp<M>`, `hg`, `tthg`;
    `table`, a tabulated truth, has none)."""
    if phase == TABLE:
        return []
    if phase == "hg":
        return ["phase.g"]
    if phase == "tthg":
        return ["phase.g_forward", "phase.g_backward", "phase.w_forward"]
    if phase.startswith("exp") and phase[3:].isdigit():
        return [f"phase.b{i}" for i in range(1, int(phase[3:]) + 1)]
    raise ModelParameterError(f"unknown phase model {phase!r}; use 'exp<M>' (e.g. exp3), 'hg' or 'tthg'")


@dataclass(frozen=True)
class SourceTables:
    """The beam map's bilinear irradiance, tabulated for sampling the start u from its
    marginal and integrating v from its conditional (numpy, float64).

    The map is padded with one ring of zeros, as `BeamProfile.lookup` reads it: nodes
    u_i = u_lo + i * pitch (i < nu), v_j = v_lo + j * pitch (j < nv).
    """

    u_lo: float
    v_lo: float
    pitch: float
    #: padded irradiance [nv, nu]
    e: np.ndarray
    #: marginal M_i = int E(u_i, v) dv at each u node [nu]
    marginal: np.ndarray
    #: cumulative mass of the marginal's intervals [nu]; cum[0] = 0, cum[-1] = power
    cum: np.ndarray
    #: per u node, the cumulative integral of E(u_i, v) dv up to node v_j [nu, nv]
    cum_v: np.ndarray

    @classmethod
    def from_profile(cls, profile: BeamProfile) -> SourceTables:
        e = np.pad(np.clip(np.asarray(profile.irradiance, dtype=np.float64), 0.0, None), 1)
        p = float(profile.pitch_mm)
        # Between nodes the bilinear surface is linear in v: trapezoids are exact.
        seg_v = 0.5 * (e[1:, :] + e[:-1, :]) * p                     # [nv - 1, nu]
        cum_v = np.vstack([np.zeros((1, e.shape[1])), np.cumsum(seg_v, axis=0)]).T
        marginal = cum_v[:, -1].copy()
        seg_u = 0.5 * (marginal[1:] + marginal[:-1]) * p
        cum = np.concatenate([[0.0], np.cumsum(seg_u)])
        if not cum[-1] > 0.0:
            raise ModelParameterError("the beam map holds no power: nothing to trace light paths from")
        return cls(float(profile.u0_mm) - p, float(profile.v0_mm) - p, p, e, marginal, cum, cum_v)

    @property
    def power(self) -> float:
        """Integral of the bilinear map (its power; `BeamProfile.power` sums the samples)."""
        return float(self.cum[-1])


class LightPaths:
    """Light tracing of the index-matched slab for one beam map and phase model.

    Args:
        geometry: slab and camera (`RigGeometry`; the thickness is given per render).
        phase: "exp<M>", "hg" or "tthg" (the parameter names of `estimate.forward`), or
            "table" with `table`.
        mi: the Mitsuba module with its variant set (its Dr.Jit types are used, so the
            engine runs on the variant's backend, CPU or GPU).
        max_depth: most collisions a path makes.
        rr_depth: collisions after which Russian roulette may end a path (survival
            probability its weight relative to its start, at most 0.95).
        table: the tabulated phase function of phase "table".
    """

    def __init__(self, geometry: RigGeometry, phase: str, mi: Any, *, max_depth: int = 64,
                 rr_depth: int = 16, table: TabulatedPhase | None = None) -> None:
        check_phase_table(phase, table)
        self.geometry = geometry
        self.phase = phase
        self.table = table
        self.phase_names = phase_parameter_names(phase)
        self.mi = mi
        import drjit as dr

        self.dr = dr
        self.max_depth = int(max_depth)
        self.rr_depth = int(rr_depth)
        self._tables: tuple[BeamProfile, SourceTables, dict[str, Any]] | None = None

    # ------------------------------------------------------------------ the source
    def _source(self, profile: BeamProfile) -> tuple[SourceTables, dict[str, Any]]:
        if self._tables is not None and self._tables[0] is profile:
            return self._tables[1], self._tables[2]
        t = SourceTables.from_profile(profile)
        mi = self.mi
        dev = {"e": mi.Float(t.e.T.ravel()),            # [nu, nv]: column u_i's v samples together
               "marginal": mi.Float(t.marginal), "cum": mi.Float(t.cum),
               "cum_v": mi.Float(t.cum_v.ravel())}
        for name, x in (("total", t.power), ("pitch", t.pitch), ("u_lo", t.u_lo), ("v_lo", t.v_lo)):
            dev[name] = self.dr.opaque(mi.Float, x)
        self._tables = (profile, t, dev)
        return t, dev

    # ------------------------------------------------------------------ rendering
    def render(self, values: Mapping[str, float], angles_deg: Sequence[float], window: PixelWindow,
               paths_per_angle: int, seed: int, *, beam: BeamProfile, thickness_mm: float,
               sigma_t: float | None = None, eta: float = 1.0,
               scores: Sequence[str] = (), tent: bool = False) -> tuple[Any, dict[str, Any]]:
        """Radiance of `window` at each stage angle, and its derivatives for `scores`.

        Args:
            values: the model's parameters (sigma_t, albedo, phase.*, and with a halo
                beam_halo.fraction / beam_halo.sigma_mm).
            angles_deg: stage angles phi (degrees; the angle offset already added).
            window: the sensor pixels (at most `MAX_ROWS` rows).
            paths_per_angle: light paths per stage angle.
            seed: the random numbers (same seed, same paths).
            beam: the beam map lighting the slab.
            thickness_mm: the slab's thickness.
            sigma_t: the extinction to trace with (1/mm; a filter band's node), default
                values["sigma_t"].
            eta: the slab's refractive index against the air (1: index-matched, the faces
                let every path out; > 1: Fresnel reflection and refraction, see the module doc).
            scores: parameter names whose derivative images are wanted: "sigma_t" (that
                is, d/d of the extinction traced with), "albedo", the phase parameters.
            tent: each vertex split between the two nearest column centres (a 2-px triangle
                response, continuous in the vertex's x) instead of added to the column it
                falls in (the pixel's box). For differences in parameters that move every
                path (the angle offset, the thickness): with the box, vertices near a
                column's edge change column and common random numbers cancel little of it.

        Returns:
            (image, derivatives): Dr.Jit double-precision arrays (evaluated, one chunk of
            `CHUNK_PATHS` paths at a time), laid out as (rows, angles, columns), radiance per steradian in
            the map's units; each derivative image per unit of its parameter.
        """
        dr = self.dr
        mi = self.mi
        Float, UInt32, Bool = mi.Float, mi.UInt32, mi.Bool
        geo = self.geometry
        H, W = window.height, window.width
        if H > MAX_ROWS:
            raise ModelParameterError(f"the light engine renders at most {MAX_ROWS} rows a window, not {H}")
        n_ang = len(angles_deg)
        n = int(paths_per_angle)
        if n < 1 or n_ang < 1:
            raise ModelParameterError("a light-path render needs at least one angle and one path")
        for name in scores:
            if name not in ("sigma_t", "albedo", *self.phase_names):
                raise ModelParameterError(f"the light engine has no score for {name!r}")
        D = dr.opaque(Float, float(thickness_mm))
        hw = float(geo.half_width_mm)
        pitch = float(geo.pixel_mm)
        cx, cy = geo.center_px
        tables, dev = self._source(beam)
        total = n_ang * n

        def o(x: float) -> Any:
            # Opaque: new values reuse the compiled kernels instead of being baked into them.
            return dr.opaque(Float, float(x))

        n_px = H * n_ang * W
        # The sums are kept in double precision. The paths' contributions reach each pixel from
        # every thread (CPU cores, GPU warps), in an order that changes from run to run; in single precision the
        # sum then changed in its 7th digit between two calls with the same seed, enough for
        # the fixed-seed Levenberg-Marquardt to take 3, 6 or 9 steps from the same point
        # (session 90). In double precision the order shows only in the 16th digit. The
        # single-precision sums were biased too: each addition rounds to the sum's last bit
        # (1e-7 of it), and over the 1e5-1e6 additions into a bright pixel the roundings did not
        # cancel. At 16384 spp the profiles' peaks came out 0.03-0.10 % low against these sums
        # (the tails less): 0.1-0.3 of one HDR pixel's sensor noise on the paper simulation,
        # but of one sign over the bright pixels of every angle (session 92).
        Acc = mi.Float64
        image = dr.zeros(Acc, n_px)
        d_img = {name: dr.zeros(Acc, n_px) for name in scores}
        phase = _PhaseOps(self.phase, values, mi, dr, self.table)
        rows = [(-(window.row0 + r - cy) * pitch - pitch, -(window.row0 + r - cy) * pitch) for r in range(H)]
        names = list(scores)
        phase_scored = [nm for nm in names if nm in self.phase_names]
        max_depth, rr_depth = self.max_depth, self.rr_depth
        halo_f = float(values.get("beam_halo.fraction", 0.0))
        halo_s = float(values.get("beam_halo.sigma_mm", 1.0))
        w0 = o(tables.power * (1.0 + halo_f) / n)
        halo_k = o(1.0 / (halo_s * math.sqrt(2.0)))
        cu_, cv_ = beam.centroid_mm()
        cv = o(cv_)
        phis = Float([math.radians(float(a)) for a in angles_deg] + [0.0])
        dr.make_opaque(phis)
        sig_t = o(values["sigma_t"] if sigma_t is None else sigma_t)
        albedo = o(values["albedo"])
        if not (math.isfinite(eta) and eta >= 1.0):
            raise ModelParameterError(f"refractive index {eta!r}: the light engine takes n >= 1")
        refractive = eta != 1.0
        n_in = o(eta)

        def trace(start: int, size: int) -> None:
            """Paths start .. start + size (angle i's are i * n .. (i + 1) * n)."""
            idx = dr.arange(UInt32, size) + dr.opaque(UInt32, start)
            ang_i = idx // n
            phi = dr.gather(Float, phis, ang_i)
            sin_p, cos_p = dr.sincos(phi)
            # Path i draws from its own PCG32 stream whatever the chunk (the constructor would
            # add arange(size) to the state and the stream; seed() takes them as given).
            g = mi.UInt64(idx)
            rng = mi.PCG32(size=size)
            rng.seed(dr.opaque(mi.UInt64, _mix_seed(seed)) + g, g)

            # --- where each path starts: u from the map's marginal (or the halo), v = 0
            in_halo = rng.next_float32() < o(halo_f / (1.0 + halo_f))
            u_core, col_i, col_a = self._sample_u(tables, dev, rng.next_float32())
            u_halo = o(cu_) + o(halo_s * math.sqrt(2.0)) * dr.erfinv(
                dr.clip(2.0 * rng.next_float32() - 1.0, -0.9999999, 0.9999999))
            u = dr.select(in_halo, u_halo, u_core)
            # The beam line u e_u + s d meets the lit face (z = 0 when the source is on the
            # camera's side, cos phi > 0; z = -D otherwise); e_u = (-cos phi, 0, sin phi).
            front = cos_p > 0.0
            z_face = dr.select(front, 0.0, -D)
            s = (z_face - u * sin_p) / cos_p
            px = -u * cos_p + s * sin_p
            py = Float(0.0) + 0.0 * px
            pz = z_face + 0.0 * px
            weight = dr.full(Float, 1.0, size)
            if refractive:
                # Snell on entry, and the share (1 - F) that enters; the footprint on the face,
                # and so the power, is what the light paths carry.
                r_in, cos_t, _, _ = mi.fresnel(dr.abs(cos_p), n_in)
                cos_t = dr.abs(cos_t)
                wx, wy, wz = -sin_p / n_in, Float(0.0) + 0.0 * px, dr.select(front, -cos_t, cos_t)
                weight = weight * (1.0 - r_in)
            else:
                wx, wy, wz = -sin_p, Float(0.0) + 0.0 * px, -cos_p
            active = dr.full(Bool, True, size) & (dr.abs(px) <= hw)

            length = dr.zeros(Float, size)

            def alive(px: Any, py: Any, pz: Any, wx: Any, wy: Any, wz: Any, weight: Any, active: Any,
                      length: Any, k_coll: Any, depth: Any, rng: Any, *acc: Any) -> Any:
                return active & (depth < max_depth)

            def bounce(px: Any, py: Any, pz: Any, wx: Any, wy: Any, wz: Any, weight: Any, active: Any,
                       length: Any, k_coll: Any, depth: Any, rng: Any, *acc: Any) -> tuple[Any, ...]:
                score = dict(zip(phase_scored, acc))
                t = -dr.log(1.0 - rng.next_float32()) / sig_t
                xi_face = rng.next_float32()
                if refractive:
                    # A flight that reaches a face: Fresnel reflection (total beyond the critical
                    # angle) with its probability, else the path leaves. Either way no collision.
                    t_face = dr.select(wz > 0.0, -pz / wz, dr.select(wz < 0.0, (-D - pz) / wz, 1e30))
                    hit = t >= t_face
                    t = dr.minimum(t, t_face)
                    r_face = mi.fresnel(-dr.abs(wz), n_in)[0]
                    mirror = active & hit & (xi_face < r_face)
                    collided = active & ~hit
                    active = active & (collided | mirror)
                else:
                    mirror = Bool(False)
                    collided = active
                px, py, pz = px + t * wx, py + t * wy, pz + t * wz
                length = length + t
                k_coll = k_coll + dr.select(collided, 1.0, 0.0)
                active = active & (mirror | ((pz <= 0.0) & (pz >= -D))) & (dr.abs(px) <= hw)
                collided = collided & active
                # The camera's connection (direction +z, so mu = wz; see `_connection`).
                conn, dconn_sig, dlog_p = self._connection(phase, wz, pz, sig_t, D, n_in if refractive else None, names)
                base = w0 * weight * albedo * conn / (pitch * pitch)
                if tent:
                    # Split between the two nearest column centres, linearly: continuous in the
                    # vertex's x, so a small move of every path moves the image smoothly.
                    fx = px / pitch + cx - window.col0 - 0.5
                    col = dr.floor(fx)
                    share = fx - col
                    parts = [(col, 1.0 - share), (col + 1.0, share)]
                else:
                    parts = [(dr.floor(px / pitch + cx) - window.col0, Float(1.0))]
                for r, (y_lo, y_hi) in enumerate(rows):
                    mass = self._v_mass(tables, dev, col_i, col_a, in_halo, cv, halo_k, y_lo - py, y_hi - py)
                    for col, part in parts:
                        seen = collided & (col >= 0) & (col < W)
                        c = base * mass * part
                        at = UInt32(r * n_ang * W) + ang_i * W + UInt32(dr.clip(col, 0, W - 1))
                        dr.scatter_reduce(dr.ReduceOp.Add, image, Acc(c), at, seen)
                        for name in names:
                            if name == "sigma_t":
                                sc = k_coll / sig_t - length + dconn_sig
                            elif name == "albedo":
                                sc = k_coll / albedo
                            else:
                                sc = score[name] + dlog_p[name]
                            dr.scatter_reduce(dr.ReduceOp.Add, d_img[name], Acc(c * sc), at, seen)
                # The next direction (a collision's; a mirrored flight turns its z).
                mu, ratio = phase.sample(rng.next_float32(), rng.next_float32())
                if phase_scored:
                    _, dlog_s = phase.log_eval(mu, phase_scored)
                    score = {name: dr.select(collided, score[name] + dlog_s[name], score[name])
                             for name in phase_scored}
                weight = dr.select(collided, weight * albedo * ratio, weight)
                sin_t = dr.safe_sqrt(1.0 - mu * mu)
                sp, cp = dr.sincos(2.0 * math.pi * rng.next_float32())
                # An orthonormal frame around w (Duff et al. 2017, branchless).
                sign = dr.select(wz >= 0.0, 1.0, -1.0)
                a = -1.0 / (sign + wz)
                b = wx * wy * a
                lx, ly = sin_t * cp, sin_t * sp
                nx, ny, nz = (lx * (1.0 + sign * wx * wx * a) + ly * b + mu * wx,
                              lx * sign * b + ly * (sign + wy * wy * a) + mu * wy,
                              -lx * sign * wx - ly * wy + mu * wz)
                wx = dr.select(collided, nx, wx)
                wy = dr.select(collided, ny, wy)
                wz = dr.select(collided, nz, dr.select(mirror, -wz, wz))
                depth = depth + 1
                # Russian roulette once the path is long: survival probability its weight
                # (relative to its start), at most 0.95; survivors carry 1 / that.
                xi = rng.next_float32()
                q = dr.minimum(weight, 0.95)
                roulette = depth >= rr_depth
                survive = ~roulette | (xi < q)
                active = active & survive
                weight = dr.select(roulette, weight / dr.maximum(q, 1e-12), weight)
                return (px, py, pz, wx, wy, wz, weight, active, length, k_coll, depth, rng,
                        *(score[name] for name in phase_scored))

            state = (px, py, pz, wx, wy, wz, weight, active, length, dr.zeros(Float, size), dr.zeros(UInt32, size),
                     rng, *(dr.zeros(Float, size) for _ in phase_scored))
            dr.while_loop(state, alive, bounce)

        for start in range(0, total, CHUNK_PATHS):
            trace(start, min(CHUNK_PATHS, total - start))
            dr.eval(image, *d_img.values())   # one chunk's paths in memory at a time
        return image, d_img

    def _connection(self, phase: _PhaseOps, wz: Any, pz: Any, sig_t: Any, D: Any, eta: Any | None,
                    names: Sequence[str]) -> tuple[Any, Any, dict[str, Any]]:
        """A vertex's radiance towards the camera per unit of its scattered power and
        albedo: (C, d log C / d sigma_t, d log C / d phase parameter for those in `names`).

        Index-matched: C = p(mu = wz) exp(sigma_t z) (z = pz <= 0, the depth is -z).
        With a refractive index n the light leaves through the front face at normal
        incidence, transmitted by T0 = 1 - F0 with the radiance divided by n^2 (the solid
        angle widens outside), and it may first reflect off the back face: the direct term
        and the one sent down (mu = -wz) and reflected with F0, each followed by any number
        of round trips between the faces (F0^2 exp(-2 sigma_t d) each):

            C = T0 / n^2 [p(wz) e^(sigma_t z) + F0 p(-wz) e^(-sigma_t (2 d + z))] / (1 - F0^2 e^(-2 sigma_t d))
        """
        dr = self.dr
        log_p, dlog_p = phase.log_eval(wz, names)
        direct = dr.exp(log_p + sig_t * pz)
        if eta is None:
            return direct, pz, dlog_p
        f0 = self.mi.fresnel(self.mi.Float(1.0), eta)[0]
        log_q, dlog_q = phase.log_eval(-wz, names)
        back = f0 * dr.exp(log_q - sig_t * (2.0 * D + pz))
        r = f0 * f0 * dr.exp(-2.0 * sig_t * D)
        both = direct + back
        inv = 1.0 / dr.maximum(both, 1e-30)
        c = (1.0 - f0) / (eta * eta) * both / (1.0 - r)
        dsig = (direct * pz - back * (2.0 * D + pz)) * inv - 2.0 * D * r / (1.0 - r)
        dphase = {k: (direct * dlog_p[k] + back * dlog_q[k]) * inv for k in dlog_p}
        return c, dsig, dphase

    # ------------------------------------------------------------------ source helpers
    def _sample_u(self, t: SourceTables, dev: Mapping[str, Any], xi: Any) -> tuple[Any, Any, Any]:
        """u from the marginal of the bilinear map (piecewise linear between u nodes):
        (u, node index i, fraction a of the way to node i + 1)."""
        dr, mi = self.dr, self.mi
        Float, UInt32 = mi.Float, mi.UInt32
        nu = t.marginal.size
        target = xi * dev["total"]
        # First interval whose upper cumulative mass exceeds the target.
        i = dr.binary_search(0, nu - 2, lambda k: dr.gather(Float, dev["cum"], k + 1) <= target)
        i = UInt32(dr.clip(i, 0, nu - 2))
        m0 = dr.gather(Float, dev["marginal"], i)
        m1 = dr.gather(Float, dev["marginal"], i + 1)
        c = (target - dr.gather(Float, dev["cum"], i)) / dev["pitch"]      # mass into the interval / pitch
        # Solve m0 s + (m1 - m0) s^2 / 2 = c for s in [0, 1] (stable form).
        disc = dr.maximum(m0 * m0 + 2.0 * (m1 - m0) * c, 0.0)
        s = dr.clip(2.0 * c / dr.maximum(m0 + dr.sqrt(disc), 1e-30), 0.0, 1.0)
        return dev["u_lo"] + (Float(i) + s) * dev["pitch"], i, s

    def _cdf_v(self, t: SourceTables, dev: Mapping[str, Any], i: Any, v: Any) -> Any:
        """int_{-inf}^{v} E(u_i, v') dv' for u node i (piecewise linear in v)."""
        dr, mi = self.dr, self.mi
        Float, UInt32 = mi.Float, mi.UInt32
        nv = t.e.shape[0]
        f = (v - dev["v_lo"]) / dev["pitch"]
        j = UInt32(dr.clip(dr.floor(f), 0, nv - 2))
        s = dr.clip(f - Float(j), 0.0, 1.0)
        s = dr.select(f < 0.0, 0.0, s)
        k = i * nv + j
        e0 = dr.gather(Float, dev["e"], k)
        e1 = dr.gather(Float, dev["e"], k + 1)
        base = dr.gather(Float, dev["cum_v"], k)
        return base + dev["pitch"] * (e0 * s + 0.5 * (e1 - e0) * s * s)

    def _v_mass(self, t: SourceTables, dev: Mapping[str, Any], i: Any, a: Any, in_halo: Any, cv: Any,
                halo_k: Any, v_lo: Any, v_hi: Any) -> Any:
        """Share of the start positions v in [v_lo, v_hi] given the start's u (its map
        column i + a, or the halo's Gaussian)."""
        dr = self.dr
        core_num = ((1.0 - a) * (self._cdf_v(t, dev, i, v_hi) - self._cdf_v(t, dev, i, v_lo))
                    + a * (self._cdf_v(t, dev, i + 1, v_hi) - self._cdf_v(t, dev, i + 1, v_lo)))
        core_den = (1.0 - a) * dr.gather(self.mi.Float, dev["marginal"], i) + a * dr.gather(
            self.mi.Float, dev["marginal"], i + 1)
        core = dr.maximum(core_num, 0.0) / dr.maximum(core_den, 1e-30)
        halo = 0.5 * (dr.erf((v_hi - cv) * halo_k) - dr.erf((v_lo - cv) * halo_k))
        return dr.select(in_halo, halo, core)


def _mix_seed(seed: int) -> int:
    """A 64-bit PCG32 initial state from a render seed (SplitMix64's finaliser)."""
    z = (int(seed) + 0x9E3779B97F4A7C15) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    return z ^ (z >> 31)


class _PhaseOps:
    """A phase model's log density, its parameter derivatives and its sampling, on Dr.Jit
    arrays; mu is the cosine between the incoming and outgoing directions of travel
    (forward scattering at mu = 1), densities per steradian."""

    def __init__(self, phase: str, values: Mapping[str, float], mi: Any, dr: Any,
                 tabulated: TabulatedPhase | None = None) -> None:
        self.phase = phase
        self.mi = mi
        self.dr = dr
        Float = mi.Float
        if phase == TABLE and tabulated is not None:
            self.n_log_p = tabulated.nodes
            self.log_p = Float(tabulated.log_p.astype(np.float32))
            self.table = Float(tabulated_inverse_cdf(tabulated.log_p))
        elif phase.startswith("exp"):
            m = int(phase[3:])
            self.b = [float(values[f"phase.b{i}"]) for i in range(1, m + 1)]
            ep = ExponentialPhase(self.b)
            self.b_dev = [dr.opaque(Float, x) for x in self.b]
            self.b0 = dr.opaque(Float, ep.b0)
            self.moments = [dr.opaque(Float, ep.moment(i)) for i in range(1, m + 1)]
            self.table = Float(inverse_cdf_table(self.b))
        elif phase == "hg":
            self.g = [dr.opaque(Float, float(values["phase.g"]))]
        elif phase == "tthg":
            self.g = [dr.opaque(Float, float(values["phase.g_forward"])),
                      dr.opaque(Float, float(values["phase.g_backward"]))]
            self.w = dr.opaque(Float, float(values["phase.w_forward"]))
        else:
            raise ModelParameterError(f"unknown phase model {phase!r}")

    def _hg(self, g: Any, mu: Any) -> tuple[Any, Any]:
        """HG density and d log HG / dg at mu."""
        dr = self.dr
        den = 1.0 + g * g - 2.0 * g * mu
        p = (1.0 - g * g) / (4.0 * math.pi * den * dr.sqrt(den))
        dlog = -2.0 * g / (1.0 - g * g) - 3.0 * (g - mu) / den
        return p, dlog

    def log_eval(self, mu: Any, wanted: Sequence[str]) -> tuple[Any, dict[str, Any]]:
        """log p(mu) and d log p / d theta for the phase parameters among `wanted`."""
        dr = self.dr
        out: dict[str, Any] = {}
        if self.phase == TABLE:
            return tabulated_log_p(self.mi, dr, self.log_p, self.n_log_p, mu), out
        if self.phase.startswith("exp"):
            poly = self.mi.Float(0.0)
            for bi in reversed(self.b_dev):
                poly = (poly + bi) * mu
            mpow = self.mi.Float(1.0)
            for i, mom in enumerate(self.moments, start=1):
                mpow = mpow * mu
                name = f"phase.b{i}"
                if name in wanted:
                    out[name] = mpow - mom
            return self.b0 + poly, out
        if self.phase == "hg":
            p, dlog = self._hg(self.g[0], mu)
            if "phase.g" in wanted:
                out["phase.g"] = dlog
            return dr.log(p), out
        pf, df = self._hg(self.g[0], mu)
        pb, db = self._hg(self.g[1], mu)
        p = self.w * pf + (1.0 - self.w) * pb
        if "phase.w_forward" in wanted:
            out["phase.w_forward"] = (pf - pb) / p
        if "phase.g_forward" in wanted:
            out["phase.g_forward"] = self.w * pf * df / p
        if "phase.g_backward" in wanted:
            out["phase.g_backward"] = (1.0 - self.w) * pb * db / p
        return dr.log(p), out

    def _sample_hg(self, g: Any, xi: Any) -> Any:
        dr = self.dr
        sq = (1.0 - g * g) / (1.0 - g + 2.0 * g * xi)
        mu_hg = (1.0 + g * g - sq * sq) / (2.0 * g)
        return dr.select(dr.abs(g) < 1e-3, 2.0 * xi - 1.0, dr.clip(mu_hg, -1.0, 1.0))

    def sample(self, xi1: Any, xi2: Any) -> tuple[Any, Any]:
        """A scattering cosine and the weight p(mu) / proposal(mu) (1 where the sampling
        is exact)."""
        dr, mi = self.dr, self.mi
        Float, UInt32 = mi.Float, mi.UInt32
        if self.phase == TABLE or self.phase.startswith("exp"):
            # The camera engine's table (`estimate.mitsuba_phase`): mu linear in the
            # probability between its entries, so the proposal is piecewise constant.
            k = _TABLE_SIZE - 1
            x = dr.clip(xi1, 0.0, 1.0) * k
            i = UInt32(dr.clip(dr.floor(x), 0, k - 1))
            mu0 = dr.gather(Float, self.table, i)
            mu1 = dr.gather(Float, self.table, i + 1)
            mu = dr.clip(dr.lerp(mu0, mu1, x - Float(i)), -1.0, 1.0)
            pdf = 1.0 / (k * dr.maximum(mu1 - mu0, 1e-7) * 2.0 * math.pi)
            log_p, _ = self.log_eval(mu, ())
            return mu, dr.exp(log_p) / pdf
        if self.phase == "hg":
            return self._sample_hg(self.g[0], xi1), Float(1.0)
        forward = xi2 < self.w
        # xi2 picks the lobe (forward with probability w), xi1 the cosine within it.
        mu = dr.select(forward, self._sample_hg(self.g[0], xi1), self._sample_hg(self.g[1], xi1))
        return mu, Float(1.0)
