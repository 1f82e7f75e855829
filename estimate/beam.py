"""The collimated beam: calibrated 2D irradiance map, stage angle, optional refraction.

`BeamProfile` holds the calibrated irradiance map in the beam's cross-section plane (mm).
Its axes: the map is what the camera sees at phi = 180 deg (beam straight into the lens,
slab removed), so map u is world x and map v is world y at phi = 180. At stage angle phi
the beam frame is that one rotated about the world y axis by phi - 180 deg:

    direction slab -> source  d = (sin phi, 0, cos phi)
    map u axis               e_u = (-cos phi, 0, sin phi)
    map v axis               e_v = (0, 1, 0)

The beam's axis passes through the world origin (rotation axis on the front face) and
the map's coordinates are measured from that axis.

`CollimatedBeam` (Mitsuba plugin `collimated_beam`) is a delta-direction emitter: next-event
rays from a medium point p get the irradiance of the map at the beam ray through p.
With a refractive slab (index eta > 1) the beam is refracted on entry: p is traced back
along the refracted direction to its entry point q on the lit face and the map is read
at q's outside cross-section coordinate. This conserves the footprint on the face: inside,
the cross-section is R cos_t / cos_i by R and the perpendicular irradiance is
(1 - F(theta_i)) E cos_i / cos_t. With a dielectric the shadow ray stops at the face (a
`dielectric` would block it); with an index-matched (`null`) boundary (`cross_face`) it
ends 1 mm outside, so that prbvolpath differentiates its attenuation (it drops that
derivative for shadow rays that end inside a medium).
The beam's internal reflections between the faces are included as `reflections` image
beams (unfolded straight lines) with the Fresnel reflectance F(theta_t) per bounce and the
analytic attenuation of the completed passes exp(-sigma_t d / cos_t) each; each
next-event sample picks one image with probability proportional to that weight.

Several stage angles `angle_deg[k]` can be rendered in one launch: a path carries the
index k of its sub-camera in its time (`estimate.mitsuba_integrator`) and the emitter
lights it with the k-th angle.

The optional halo (extension `beam_halo`) adds a Gaussian of relative power
`halo_fraction` and standard deviation `halo_sigma_mm` around the map's centroid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from estimate.errors import ModelParameterError

__all__ = ["PLUGIN_NAME", "SUPPORT_BOX_PX", "SUPPORT_MARGIN_PX", "SUPPORT_Z", "BeamProfile", "beam_frame",
           "beam_support", "map_from_pixel_image", "register_plugins"]

PLUGIN_NAME = "collimated_beam"
#: How far beyond the lit face a shadow ray ends when it may cross the boundary (mm).
_FACE_MARGIN_MM = 1.0
_registered: set[str | None] = set()


def beam_frame(phi_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(d, e_u, e_v) of the beam at stage angle phi (degrees), see module doc."""
    p = math.radians(phi_deg)
    d = np.array([math.sin(p), 0.0, math.cos(p)])
    e_u = np.array([-math.cos(p), 0.0, math.sin(p)])
    return d, e_u, np.array([0.0, 1.0, 0.0])


#: Weight of the curvature penalty of `BeamProfile.deblurred` (relative to |OTF(0)|^2 = 1).
DEBLUR_REGULARISATION = 1e-2
#: The 5-point Laplacian (`BeamProfile.deblurred`'s penalty).
_LAPLACIAN = np.array([[0.0, 1.0, 0.0], [1.0, -4.0, 1.0], [0.0, 1.0, 0.0]])
#: Spread (samples, Gaussian sigma) over which `_nonnegative_locally` hands a negative
#: sample's deficit to its neighbours, and its passes.
_DEFICIT_SPREAD = 1.5
_DEFICIT_PASSES = 20


def _nonnegative_locally(x: np.ndarray) -> np.ndarray:
    """`x` made non-negative with its sum unchanged: each negative sample's deficit is taken
    from its neighbours (a Gaussian of `_DEFICIT_SPREAD` samples, renormalised at the edges
    so none is lost), `_DEFICIT_PASSES` times; what is still owed then (a region whose noise
    sums negative) is taken from all the positive samples in proportion.

    Where the true irradiance is zero, a deconvolved map is zero-mean noise; clipping it at
    zero keeps the positive half, a faint positive floor, whereas here the noise's two signs
    cancel where they lie. Under the beam the deficit is a small share of what is there.
    """
    from scipy import ndimage

    y = np.asarray(x, dtype=np.float64).copy()
    # Gathering through the kernel, each source's share renormalised: scatter weights that
    # sum to 1 within the map, so a deficit near an edge is not lost off it.
    reach = ndimage.gaussian_filter(np.ones_like(y), _DEFICIT_SPREAD, mode="constant")
    for _ in range(_DEFICIT_PASSES):
        deficit = np.minimum(y, 0.0)
        if not deficit.any():
            break
        y = np.maximum(y, 0.0) + ndimage.gaussian_filter(deficit / reach, _DEFICIT_SPREAD, mode="constant")
    owed = -float(np.minimum(y, 0.0).sum())
    out: np.ndarray = np.maximum(y, 0.0)
    have = float(out.sum())
    if owed > 0.0 and have > 0.0:
        out *= max(0.0, 1.0 - owed / have)
    return out


@dataclass(frozen=True)
class BeamProfile:
    """Calibrated beam irradiance in its cross-section plane.

    Attributes:
        irradiance: array [nv, nu], >= 0, in the camera's linear units per mm^2 (any
            consistent scale; the render scales with it). Row j is v = v0_mm + j * pitch_mm,
            column i is u = u0_mm + i * pitch_mm (row index increases with +v = +y).
        pitch_mm: sample spacing in mm.
        u0_mm, v0_mm: coordinates of sample [0, 0] relative to the beam axis (mm).
        through_lens: the map was imaged through the camera's lens (a calibration frame,
            `from_camera_image`), so it carries the lens's blur: a model with `lens_blur`
            lights the slab with `deblurred(psf)`. False for analytic maps.
    Lookup is bilinear between sample centres and zero outside the map.
    """

    irradiance: np.ndarray
    pitch_mm: float
    u0_mm: float
    v0_mm: float
    through_lens: bool = False
    _cache: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        e = np.asarray(self.irradiance, dtype=np.float64)
        if e.ndim != 2 or min(e.shape) < 2:
            raise ModelParameterError("beam irradiance map must be a 2D array of at least 2x2 samples")
        if not np.all(np.isfinite(e)) or np.any(e < 0):
            raise ModelParameterError("beam irradiance map must be finite and >= 0")
        if not (math.isfinite(self.pitch_mm) and self.pitch_mm > 0):
            raise ModelParameterError(f"beam pitch_mm={self.pitch_mm!r} must be > 0")
        object.__setattr__(self, "irradiance", e)

    # --- constructors -----------------------------------------------------------------
    @classmethod
    def centered(cls, irradiance: np.ndarray, pitch_mm: float,
                 center_uv_mm: tuple[float, float] = (0.0, 0.0)) -> BeamProfile:
        """Map whose middle sample lies at `center_uv_mm` from the beam axis."""
        e = np.asarray(irradiance, dtype=np.float64)
        nv, nu = e.shape
        return cls(e, float(pitch_mm), center_uv_mm[0] - 0.5 * (nu - 1) * pitch_mm,
                   center_uv_mm[1] - 0.5 * (nv - 1) * pitch_mm)

    @classmethod
    def from_camera_image(cls, image: np.ndarray, pitch_mm: float,
                          axis_px: tuple[float, float]) -> BeamProfile:
        """From a calibration frame at phi = 180 deg (image rows top-down, y up).

        `axis_px` = (column, row) where the beam axis (rotation axis) is imaged.
        """
        e = np.asarray(image, dtype=np.float64)[::-1, :]  # row index now increases with +y
        nv = e.shape[0]
        col, row = axis_px
        return cls(e, float(pitch_mm), -col * pitch_mm, -((nv - 1) - row) * pitch_mm, through_lens=True)

    @classmethod
    def disk(cls, radius_mm: float, irradiance: float = 1.0, pitch_mm: float | None = None,
             center_uv_mm: tuple[float, float] = (0.0, 0.0)) -> BeamProfile:
        """A uniform disk map (area-sampled edge), e.g. for tests and the simulated bench."""
        if not (math.isfinite(radius_mm) and radius_mm > 0):
            raise ModelParameterError(f"beam radius_mm={radius_mm!r} must be > 0")
        pitch = pitch_mm or radius_mm / 16.0
        n = math.ceil(radius_mm / pitch) + 2
        c = (np.arange(-n, n + 1)) * pitch
        sub = (np.arange(4) + 0.5) / 4 - 0.5
        uu = c[None, :, None, None] + sub[None, None, None, :] * pitch
        vv = c[:, None, None, None] + sub[None, None, :, None] * pitch
        inside = (uu ** 2 + vv ** 2 <= radius_mm ** 2).mean(axis=(2, 3))
        return cls.centered(inside * irradiance, pitch, center_uv_mm)

    @classmethod
    def gaussian(cls, radius_mm: float, power: float = 1.0, pitch_mm: float | None = None,
                 center_uv_mm: tuple[float, float] = (0.0, 0.0)) -> BeamProfile:
        """Gaussian beam of 1/e^2 radius `radius_mm` and total `power`:
        E = 2 P / (pi R^2) exp(-2 r^2 / R^2), sampled to 3 R."""
        if not (math.isfinite(radius_mm) and radius_mm > 0):
            raise ModelParameterError(f"beam radius_mm={radius_mm!r} must be > 0")
        pitch = pitch_mm or radius_mm / 16.0
        n = math.ceil(3.0 * radius_mm / pitch)
        c = np.arange(-n, n + 1) * pitch
        r2 = c[None, :] ** 2 + c[:, None] ** 2
        e = 2.0 * power / (math.pi * radius_mm ** 2) * np.exp(-2.0 * r2 / radius_mm ** 2)
        return cls.centered(e, pitch, center_uv_mm)

    # --- numpy evaluation ----------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        return self.irradiance.shape  # type: ignore[return-value]

    def power(self) -> float:
        """Total beam power (irradiance integrated over the cross-section)."""
        return float(self.irradiance.sum() * self.pitch_mm ** 2)

    def centroid_mm(self) -> tuple[float, float]:
        e = self.irradiance
        nv, nu = e.shape
        u = self.u0_mm + np.arange(nu) * self.pitch_mm
        v = self.v0_mm + np.arange(nv) * self.pitch_mm
        s = e.sum()
        if s <= 0:
            return (0.0, 0.0)
        return float((e.sum(axis=0) * u).sum() / s), float((e.sum(axis=1) * v).sum() / s)

    def rms_width_mm(self) -> float:
        """1-sigma width of the map [mm]: the root of the mean of its two second central
        moments (a Gaussian beam of standard deviation w gives w)."""
        e = np.clip(self.irradiance, 0.0, None)
        s = float(e.sum())
        if s <= 0:
            return 0.0
        nv, nu = e.shape
        u = self.u0_mm + np.arange(nu) * self.pitch_mm
        v = self.v0_mm + np.arange(nv) * self.pitch_mm
        cu, cv = self.centroid_mm()
        var_u = float((e.sum(axis=0) * (u - cu) ** 2).sum() / s)
        var_v = float((e.sum(axis=1) * (v - cv) ** 2).sum() / s)
        return float(np.sqrt(0.5 * (var_u + var_v)))

    def blurred_along_v(self, kernel: np.ndarray) -> BeamProfile:
        """The map convolved along v (world y) with a 1D kernel in map samples (odd length,
        centred), widened by the kernel's reach so that no power is lost.

        The slab and the medium do not change along y, so an image row of the slab lit by
        this map is the image lit by the map itself, blurred along y by the kernel at the
        map's pitch: how the light engine renders the profile row with the lens blur's core
        (separable, so its y part) already applied (`estimate.forward.ForwardModel.beam_for`).
        """
        k = np.asarray(kernel, dtype=np.float64)
        if k.ndim != 1 or k.size % 2 != 1:
            raise ModelParameterError(f"beam blurring kernel has shape {k.shape}; expected an odd length")
        r = k.size // 2
        # Trim the kernel's negligible ends (a 2.5 px core in a 129-sample kernel).
        keep = np.nonzero(k > 1e-12 * float(k.max()))[0]
        reach = int(max(r - keep[0], keep[-1] - r)) if keep.size else 0
        k = k[r - reach:r + reach + 1]
        from scipy import ndimage

        e = np.pad(self.irradiance, ((reach, reach), (0, 0)))
        out = ndimage.convolve1d(e, k, axis=0, mode="constant")
        return BeamProfile(np.clip(out, 0.0, None), self.pitch_mm, self.u0_mm, self.v0_mm - reach * self.pitch_mm,
                           through_lens=self.through_lens)

    def deblurred(self, psf: np.ndarray, regularisation: float = DEBLUR_REGULARISATION, *,
                  start: np.ndarray | None = None) -> BeamProfile:
        """The map with a point-spread function taken out (regularised least squares).

        A calibration frame images the beam through the camera's lens, so when the model
        blurs the slab's image by the lens's PSF (`lens_blur`), the map it lights the slab
        with must be the beam before that blur, or the blur acts twice: once in the map,
        once on the image. On the simulated bench (beam sigma 0.25 mm, core blur 1.5 px,
        2 % glare tail) the map read 12 % wider (rms) and held 2.7 % of its power beyond
        0.75 mm against 1.1 %.

        The map is a crop of the calibration frame, and the PSF's glare reaches past it (a
        20 px tail on a 50 px crop: most of the glare falls outside). So the light outside
        the crop is unknown, not zero: the beam b (on the crop's samples) is the solution of

            min_b |crop(P * b) - m|^2 + lambda |L b|^2

        (P * b the full, unpadded convolution, compared with the map m on the crop only; L
        the 5-point Laplacian, zero outside the crop), by conjugate gradients on the normal
        equations with FFT convolutions. The penalty is on curvature, not on b itself: it
        leaves the power and the width alone (a smooth beam has little curvature) and holds
        down the map's pixel noise where the PSF's transfer is small, which the
        deconvolution would otherwise amplify (up to 16x with |b|^2 at lambda 1e-3) and
        the clipping of negative samples would then turn into a faint halo. Measured on a
        synthetic 0.25 mm beam, 1.5 px core, 2 % glare tail, 50 px crop, map noise 5e-5 of
        its peak: the share of the beam beyond 1 mm is 0.068 % (truth 0.038 %); Wiener
        with zero padding (up to session 62) left 0.23 % noise-free and more with noise.
        On the light-engine bench's lens_blur-1 session the true model's reduced chi^2 at
        the noise floor went from 6.91 (Wiener) to 5.22 (crop-aware, |b|^2 penalty) to 3.82
        with this one: the bench's own beam map gives 3.78.

        Args:
            psf: 2D kernel in map samples (odd square, sums to 1; `lens_blur.psf_2d`: one
                map sample is one sensor pixel of the calibration frame).
            regularisation: lambda, relative to |OTF(0)|^2 = 1 (the Laplacian's transfer
                reaches 64 at the Nyquist frequency).

            start: where the conjugate gradients start, an irradiance of this map's shape
                (the solution at a nearby kernel: a fit deblurs at every blur it visits, 195
                times in one lens blur diagnosis); None starts from the blurred map's
                back-projection. The solution is the same to the solver's tolerance.

        The solution's negative samples (the map's noise, amplified) are not clipped but
        handed to their neighbours (`_nonnegative_locally`): clipping keeps the positive
        half of zero-mean noise and turns it into a halo. On the light bench's lens_blur-2
        session (2.5 px core, 5 % tail, calibration map noise about 1.5e-4 of its peak) the
        clipped map held 0.135 % of its power beyond 1 mm where the unclipped solution holds
        0.044 % and the beam 0.036 %; that halo lit the slab's wings, the fit answered with
        the albedo 0.0025 low (4 sigma) and a larger tail, and the true model's reduced
        chi^2 at the noise floor was 1.32 against 1.16 with the halo gone (session 72). The
        power is the solution's: the glare that fell outside the crop is restored to the
        beam it came from (+1.1 % on that session). A delta kernel gives the map itself.
        """
        from scipy import ndimage
        from scipy.sparse.linalg import LinearOperator, cg

        k = np.asarray(psf, dtype=np.float64)
        if k.ndim != 2 or k.shape[0] != k.shape[1] or k.shape[0] % 2 != 1:
            raise ModelParameterError(f"beam deblurring kernel has shape {k.shape}; expected an odd square")
        r = k.shape[0] // 2
        e = self.irradiance
        if k[r, r] >= 1.0 - 1e-12:
            return BeamProfile(e.copy(), self.pitch_mm, self.u0_mm, self.v0_mm, through_lens=False)
        nv, nu = e.shape
        # b sits at [r, r + n) of a frame 2 r larger: its full convolution with the kernel
        # (radius r) fits the frame, so the FFT's circular convolution does not wrap.
        shape = (nv + 2 * r, nu + 2 * r)
        kk = np.zeros(shape)
        kk[:k.shape[0], :k.shape[1]] = k
        otf = np.fft.rfft2(np.roll(kk, (-r, -r), axis=(0, 1)))
        inner = (slice(r, r + nv), slice(r, r + nu))

        def through(x: np.ndarray, transfer: np.ndarray) -> np.ndarray:
            f = np.zeros(shape)
            f[inner] = x.reshape(nv, nu)
            return np.fft.irfft2(np.fft.rfft2(f) * transfer, s=shape)[inner].ravel()

        def curvature(x: np.ndarray) -> np.ndarray:
            return ndimage.convolve(x.reshape(nv, nu), _LAPLACIAN, mode="constant").ravel()

        otf_c = np.conj(otf)
        normal = LinearOperator((nv * nu, nv * nu), dtype=np.float64,
                                matvec=lambda x: (through(through(x, otf), otf_c)
                                                  + regularisation * curvature(curvature(x))))
        scale = float(np.abs(e).max()) or 1.0
        rhs = through(e / scale, otf_c)
        x0 = rhs.copy()
        if start is not None and np.shape(start) == e.shape:
            x0 = np.asarray(start, dtype=np.float64).ravel() / scale
        x, _ = cg(normal, rhs, x0=x0, rtol=1e-7, maxiter=2000)
        b = _nonnegative_locally(x.reshape(nv, nu)) * scale
        return BeamProfile(b, self.pitch_mm, self.u0_mm, self.v0_mm, through_lens=False)

    def lookup(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Bilinear irradiance at (u, v) mm, zero outside (numpy; same rule as the plugin)."""
        e = np.pad(self.irradiance, 1)
        fu = (np.asarray(u) - self.u0_mm) / self.pitch_mm + 1.0
        fv = (np.asarray(v) - self.v0_mm) / self.pitch_mm + 1.0
        nv, nu = e.shape
        fu = np.clip(fu, 0.0, nu - 1.000001)
        fv = np.clip(fv, 0.0, nv - 1.000001)
        i = np.floor(fu).astype(int)
        j = np.floor(fv).astype(int)
        a = fu - i
        b = fv - j
        return ((1 - a) * (1 - b) * e[j, i] + a * (1 - b) * e[j, i + 1]
                + (1 - a) * b * e[j + 1, i] + a * b * e[j + 1, i + 1])


#: Per axis, a camera pixel value of the bilinear map with samples B at the pixel centres is
#: sum_j B_j K(i - j): the bilinear (triangle) kernel integrated over the pixel's width.
_PIXEL_OF_BILINEAR = (1.0 / 8.0, 3.0 / 4.0, 1.0 / 8.0)


#: Side (pixels) of the box over which `beam_support` sums the frame before testing it.
SUPPORT_BOX_PX = 5
#: A box sum this many standard deviations above zero is the beam's light (`beam_support`).
SUPPORT_Z = 4.0
#: Pixels around the boxes above the threshold that the support keeps (the beam's faint edge).
SUPPORT_MARGIN_PX = 2


def beam_support(image: np.ndarray, variance: np.ndarray | None = None) -> np.ndarray:
    """Where a dark-subtracted calibration frame holds the beam's light, not only its noise.

    Off the beam a dark-subtracted pixel is noise of zero mean, and the irradiance cannot be
    negative, so the map clips it at zero; the clipped noise keeps its positive half, a
    pedestal of about 0.4 noise standard deviations in every dark pixel. Spread over the
    crop it is a faint, very wide halo lighting the whole slab: on the simulated rig's
    clean sessions (a 0.25 mm beam in a 46 x 46 px crop, the b filter's frame the noisiest)
    0.02 % of the map's power beyond 1.5 mm, where the beam has none, enough that the
    true model's chi^2 at the noise floor was 50-135 (of 2560 pixels) above a model lit by
    the world's own beam, and that the halo led the clean channels' candidates
    (docs/diagnosis-log.md, session 70).

    The support: the pixels whose box of `SUPPORT_BOX_PX`^2 pixels around them sums to
    more than `SUPPORT_Z` standard deviations above zero, widened by `SUPPORT_MARGIN_PX`.
    The standard deviation of each pixel is the merge's (`variance`) times the excess the
    frame's negative pixels show over it (frozen noise the merge does not hold), or without
    a variance the negative pixels' root mean square. A real beam's faint halo, a few 1e-4
    of the peak over millimetres, lifts many boxes above the threshold and stays; the dark
    noise (about one box in 30000 above 4 sigma) goes.

    Returns a bool mask of the frame's shape; everything when the frame has no negative
    pixel to measure the noise by (a noise-free map).
    """
    from scipy import ndimage

    x = np.asarray(image, dtype=np.float64)
    neg = x < 0
    if not neg.any():
        return np.ones(x.shape, dtype=bool)
    v = None if variance is None else np.asarray(variance, dtype=np.float64)
    if v is not None and np.all(np.isfinite(v)) and np.all(v > 0):
        sd = np.sqrt(v)
        excess = math.sqrt(max(1.0, float(np.mean((x[neg] / sd[neg]) ** 2))))
        var = (sd * excess) ** 2
    else:
        var = np.full(x.shape, float(np.mean(x[neg] ** 2)))
    b = SUPPORT_BOX_PX
    # Box sums (mode "constant": the frame's edge adds nothing) and their standard deviations.
    total = ndimage.uniform_filter(x, b, mode="constant") * b * b
    spread = np.sqrt(ndimage.uniform_filter(var, b, mode="constant") * b * b)
    lit = total > SUPPORT_Z * spread
    if not lit.any():
        return np.ones(x.shape, dtype=bool)
    # The boxes' centres above the threshold, and the margin around them. (Marking each
    # lit box's whole footprint kept dark rings two pixels wider, where clipped noise
    # then remained: on the clean sessions above, about half of the pedestal's chi^2.)
    return ndimage.binary_dilation(lit, iterations=SUPPORT_MARGIN_PX)


def map_from_pixel_image(image: np.ndarray) -> np.ndarray:
    """Map samples whose bilinear irradiance, imaged by the same pixels, gives `image` back.

    A calibration frame holds the beam integrated over each pixel (a 1-pixel box), and the
    map is read back with bilinear interpolation (a 1-pixel triangle). Used as is, both
    would widen the beam: its variance by pitch^2 / 12 + pitch^2 / 6 = pitch^2 / 4 per axis,
    0.9 % in the width of the simulated rig's 0.25 mm beam at 0.067 mm pixels (on a clean
    simulated-bench session at the true parameters, the diagnosis's score test of sensor
    compression, which reshapes the peak, fell from 9-10 to 1-3 with this correction).
    Solving K B = image along both axes (K = 1/8, 3/4, 1/8,
    zero beyond the frame; diagonally dominant, so at most 2x noise at the Nyquist frequency)
    removes it. The beam's power (the sum) is kept; the few negative samples the inversion
    leaves at a sharp edge or in the dark noise are clipped to zero, and the power restored.
    """
    from scipy.linalg import solve_banded

    e = np.asarray(image, dtype=np.float64)
    total = float(e.sum())
    a, b, c = _PIXEL_OF_BILINEAR
    for axis in (0, 1):
        n = e.shape[axis]
        if n < 3:
            continue
        ab = np.zeros((3, n))
        ab[0, 1:] = c
        ab[1, :] = b
        ab[2, :-1] = a
        e = np.moveaxis(solve_banded((1, 1), ab, np.moveaxis(e, axis, 0)), 0, axis)
    e = np.clip(e, 0.0, None)
    s = float(e.sum())
    if s > 0 and total > 0:
        e *= total / s
    return e


def _make_plugin_class(mi: Any, dr: Any) -> type:
    class CollimatedBeam(mi.Emitter):
        """Delta-direction beam with a calibrated map; see the module doc."""

        def __init__(self, props: Any) -> None:
            mi.Emitter.__init__(self, props)
            self.m_flags = mi.EmitterFlags.DeltaDirection
            self.reflections = int(props.get("reflections", 0))
            # True for a null (index-matched) boundary, which shadow rays may cross.
            self.cross_face = bool(props.get("cross_face", True))
            # Stage angles of a batched render, indexed by the path's time.
            self.copies = int(props.get("copies", 1))
            self.angle_deg = mi.Float([float(props.get("angle_deg", 45.0))] * self.copies)
            self.eta = mi.Float(props.get("eta", 1.0))
            self.thickness = mi.Float(props.get("thickness", 1.0))
            self.sigma_t = mi.Float(props.get("sigma_t", 0.0))
            self.halo_fraction = mi.Float(props.get("halo_fraction", 0.0))
            self.halo_sigma = mi.Float(props.get("halo_sigma_mm", 1.0))
            self.scale = mi.Float(props.get("scale", 1.0))
            self.set_profile(BeamProfile.disk(float(props.get("radius_mm", 0.5))))

        def set_profile(self, profile: BeamProfile) -> None:
            """Install a calibrated map (fixed data, not differentiated)."""
            e = np.pad(profile.irradiance, 1)
            self.nv, self.nu = e.shape
            self.map = mi.Float(e.ravel().astype(np.float32))
            self.map_u0 = mi.Float(profile.u0_mm - profile.pitch_mm)
            self.map_v0 = mi.Float(profile.v0_mm - profile.pitch_mm)
            self.map_inv_pitch = mi.Float(1.0 / profile.pitch_mm)
            cu, cv = profile.centroid_mm()
            self.map_power = mi.Float(profile.power())
            self.map_cu = mi.Float(cu)
            self.map_cv = mi.Float(cv)
            self.parameters_changed()

        def traverse(self, callback: Any) -> None:
            for name in ("angle_deg", "eta", "thickness", "sigma_t", "halo_fraction",
                         "scale"):
                callback.put(name, getattr(self, name), mi.ParamFlags.Differentiable)
            callback.put("halo_sigma_mm", self.halo_sigma, mi.ParamFlags.Differentiable)

        def parameters_changed(self, keys: Any = None) -> None:
            # Opaque: new angles / values reuse the compiled kernels instead of being baked in.
            dr.make_opaque(self.angle_deg, self.eta, self.thickness, self.sigma_t,
                           self.halo_fraction, self.halo_sigma, self.scale, self.map_u0,
                           self.map_v0, self.map_inv_pitch, self.map_power, self.map_cu,
                           self.map_cv)

        def _lookup(self, u: Any, v: Any, active: Any) -> Any:
            fu = (u - self.map_u0) * self.map_inv_pitch
            fv = (v - self.map_v0) * self.map_inv_pitch
            inside = active & (fu >= 0) & (fv >= 0) & (fu < self.nu - 1) & (fv < self.nv - 1)
            i = mi.UInt32(dr.clip(dr.floor(fu), 0, self.nu - 2))
            j = mi.UInt32(dr.clip(dr.floor(fv), 0, self.nv - 2))
            a = fu - mi.Float(i)
            b = fv - mi.Float(j)
            k = j * self.nu + i
            e00 = dr.gather(mi.Float, self.map, k, inside)
            e10 = dr.gather(mi.Float, self.map, k + 1, inside)
            e01 = dr.gather(mi.Float, self.map, k + self.nu, inside)
            e11 = dr.gather(mi.Float, self.map, k + self.nu + 1, inside)
            val = dr.lerp(dr.lerp(e00, e10, a), dr.lerp(e01, e11, a), b)
            return dr.select(inside, val, 0.0)

        def sample_direction(self, it: Any, sample: Any, active: Any = True) -> tuple[Any, Any]:
            p = it.p
            if self.copies > 1:
                # The path's sub-camera index, carried in time (estimate.mitsuba_integrator).
                copy = mi.UInt32(dr.clip(dr.round(it.time), 0, self.copies - 1))
            else:
                copy = mi.UInt32(0)
            phi = dr.gather(mi.Float, self.angle_deg, copy, active) * (math.pi / 180.0)
            sin_p, cos_p = dr.sincos(phi)
            front = cos_p > 0.0
            sgn_x = dr.select(sin_p >= 0.0, 1.0, -1.0)
            cos_i = dr.abs(cos_p)
            r_i, cos_t, _, _ = mi.fresnel(cos_i, self.eta)
            cos_t = dr.abs(cos_t)
            sin_t = dr.safe_sqrt(1.0 - cos_t * cos_t)
            tan_t = sin_t / dr.maximum(cos_t, 1e-6)
            d = self.thickness
            n_img = self.reflections + 1
            if n_img > 1:
                # Image k carries (R(theta_t) exp(-sigma_t d / cos_t))^k of the entering
                # beam: pick it with that probability (normalised), so the estimate's
                # weight is the constant sum of the image weights.
                att = r_i * dr.exp(-self.sigma_t * d / dr.maximum(cos_t, 1e-6))
                w_img = [mi.Float(1.0)]
                for _ in range(n_img - 1):
                    w_img.append(w_img[-1] * att)
                total = w_img[0]
                for w_i in w_img[1:]:
                    total = total + w_i
                u = sample.x * dr.detach(total)
                k = mi.UInt32(0)
                acc = mi.Float(0.0)
                for i in range(n_img - 1):
                    acc = acc + dr.detach(w_img[i])
                    k = dr.select(u >= acc, mi.UInt32(i + 1), k)
            else:
                k = mi.UInt32(0)
            odd = (k & 1) == 1
            # Depth travelled in the current pass, measured from the face it started at.
            depth_front = -p.z         # from z = 0
            depth_back = p.z + d       # from z = -d
            from_front = front ^ odd   # current pass started at the front face
            partial = dr.select(from_front, depth_front, depth_back)
            unfolded = mi.Float(k) * d + partial
            # Entry point on the lit face, unfolded; outside map coordinates there.
            xq = p.x + unfolded * tan_t * sgn_x
            zq = dr.select(front, 0.0, -d)
            u = -cos_p * xq + sin_p * zq
            v = p.y
            e = self._lookup(u, v, active)
            du = u - self.map_cu
            dv = v - self.map_cv
            s2 = self.halo_sigma * self.halo_sigma
            halo = self.halo_fraction * self.map_power * dr.exp(-(du * du + dv * dv) / (2.0 * s2)) / (2.0 * math.pi * s2)
            e = e + halo
            # Irradiance inside, perpendicular to the refracted beam.
            e = e * (1.0 - r_i) * cos_i / dr.maximum(cos_t, 1e-6)
            if n_img > 1:
                # weight w_k / P(k) = total (w_k / detach(w_k) keeps the derivative)
                w_k = w_img[0]
                for i in range(1, n_img):
                    w_k = dr.select(k == i, w_img[i], w_k)
                e = e * w_k / dr.detach(w_k) * total
            # Direction towards where the light of this pass came from.
            dz_sign = dr.select(from_front, 1.0, -1.0)
            dvec = mi.Vector3f(sgn_x * sin_t, 0.0, dz_sign * cos_t)
            dist = dr.maximum(partial, 0.0) / dr.maximum(cos_t, 1e-6)
            if self.cross_face:
                # Index-matched (null) boundary: end the shadow ray well outside the face.
                # prbvolpath back-propagates the shadow ray's medium transmittance only
                # when the ray meets a surface; a ray ending inside the medium loses the
                # sigma_t derivative of that attenuation. Mitsuba shortens shadow rays by
                # a relative 8.9e-4, so a margin of 1 um still ended grazing rays short
                # of the face (sigma_t gradient 25 % low); 1 mm of vacuum is safe.
                dist = dist + _FACE_MARGIN_MM
            valid = active & (partial >= 0.0) & (partial <= d)
            ds = dr.zeros(mi.DirectionSample3f)
            ds.p = it.p + dvec * dist
            ds.n = -dvec
            ds.d = dvec
            ds.dist = dist
            ds.pdf = dr.select(valid, 1.0, 0.0)
            ds.delta = mi.Bool(True)
            ds.time = it.time
            ds.emitter = mi.EmitterPtr(self)
            return ds, mi.Spectrum(dr.select(valid, e * self.scale, 0.0))

        def pdf_direction(self, it: Any, ds: Any, active: Any = True) -> Any:
            return mi.Float(0.0)

        def eval_direction(self, it: Any, ds: Any, active: Any = True) -> Any:
            return mi.Spectrum(0.0)

        def eval(self, si: Any, active: Any = True) -> Any:
            return mi.Spectrum(0.0)

        def sample_ray(self, time: Any, sample1: Any, sample2: Any, sample3: Any, active: Any = True) -> tuple[Any, Any]:
            return dr.zeros(mi.Ray3f), mi.Spectrum(0.0)

        def sample_wavelengths(self, si: Any, sample: Any, active: Any = True) -> tuple[Any, Any]:
            return dr.zeros(mi.Wavelength), mi.Spectrum(1.0)

        def bbox(self) -> Any:
            return mi.ScalarBoundingBox3f()

        def to_string(self) -> str:
            return f"CollimatedBeam[reflections={self.reflections}]"

    return CollimatedBeam


def register_plugins() -> None:
    """Register `collimated_beam` for the current Mitsuba variant (idempotent)."""
    import drjit as dr
    import mitsuba as mi

    variant = mi.variant()
    if variant in _registered:
        return
    cls = _make_plugin_class(mi, dr)
    mi.register_emitter(PLUGIN_NAME, lambda props: cls(props))
    _registered.add(variant)
