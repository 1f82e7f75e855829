"""Extension `lens_blur`: point-spread function of lens and sensor, in image space.

PSF = (1 - tail_fraction) * core + tail_fraction * tail, both normalised:
- core: Gaussian of standard deviation `core_sigma_px` (0 = a delta: no core blur);
- tail (veiling glare): 2D kernel (1 + r^2 / s^2)^(-3/2), s = `tail_scale_px`, whose line
  spread function would be the Lorentzian 1 / (1 + x^2 / s^2) were it not truncated.
Both are truncated to the square |x|, |y| <= `TRUNCATION_PX` and renormalised; a profile's
line spread is the marginal of that truncated kernel, so a y-constant image's 2D blur and
its profile blur agree exactly. Full frames are blurred in 2D.

A single rendered profile row cannot be blurred in 2D: the rows above and below it are not
rendered. The line-spread function (LSF, the PSF summed over y) is exact only for an image
that is constant along y over the PSF. The rig's spot is not: the beam is a few pixels wide,
and light seen at pixel distance dy from the profile row is weaker by the image's shape
h(x, dy) = I(x, y0 + dy) / I(x, y0). On the simulated bench (beam sigma 3.75 px, core blur
1.5 px, 2 % tail) the LSF put 4-21 % too much light in 16-pixel bins near the spot, against
the bench's 2D blur of the same radiance (`benchmarks/bench_profile_blur.py`). With `y_shape` (h per image row, from the
recording's rows around the profile row: `estimate.problem.Problem.y_shape`) each LSF
weight is multiplied by the mean of h under the PSF's spread in y at that x offset:

    out(x) = sum_dx I(x - dx) [ (1 - f) G(dx) E_G[h(x - dx, .)] + f L(dx) E_T|dx[h(x - dx, .)] ]

with G, L the core's and the tail's LSF (as `line_spread`), E_G the mean over dy under the
core's normalised Gaussian and E_T|dx the mean under the tail kernel's conditional
distribution of dy at offset dx. The image is taken as I(x', y0) h(x', dy) near the
profile row, i.e. its y-shape is the recording's. h = 1 everywhere gives the LSF exactly.
On the bench this leaves 1.4-5.3 % (0.4-1.7 % with the unblurred rows' own shape).

The recorded shape is that of the blurred image, stray light included: a spot sigma_y wide
reads as sqrt(sigma_y^2 + sigma_core^2) wide, and its E_G[h] overstates the light the blur
keeps in the profile row (a 3.75 px beam under a 2.5 px core: 0.88 instead of 0.83). So the
recorded shape is first deblurred along y by the PSF being applied (`unblurred_y_shape`):
per column, the regularised least-squares u of K u = h_rec, K the PSF's line spread along y,
u free beyond the recorded +-radius rows (the light from there is unknown, not zero) and a
curvature penalty `Y_DEBLUR_REGULARISATION` against the amplified noise; then u / u(0).
For an image a(x) b(y) under the separable core this recovers b up to the regularisation's
smoothing; the tail, not separable, to first order. A column
whose deblurred centre is not clearly positive keeps its recorded shape. The deblurring is
a fixed linear map for given blur values (cached), so derivatives by the parameters stay
those of a deterministic image function. Zero padding outside the rendered window.

The core's part needs no y-shape where the scene can carry it (`core_in_scene`): the slab
does not change along y, so the row of the slab lit by the beam map blurred along v by the
core's line spread is sum_dy G(dy) I(x, y0 + dy), the image blurred along y by the (separable)
core. The light engine renders the profile row that way when it re-lights the slab at every
blur anyway (`estimate.forward.ForwardModel.core_blur_in_scene`); the weights then keep the
core's line spread alone, and the tail's term, which acts on I(x', y0), is divided by the
core's mean of h, E_G[h(x', .)], since the row holds I(x', y0) E_G[h(x', .)]. The PSF is
symmetric, so the full-frame and LSF operators are self-adjoint; the weighted profile
operator is not (`vjp_input` applies its transpose). Derivative: exact through this image
function.
"""

from __future__ import annotations

import functools
import weakref
from collections import OrderedDict
from collections.abc import Mapping

import numpy as np
from scipy import ndimage, signal

from estimate.extensions.base import BeamFill, ImageExtension, ParameterSpec

__all__ = ["TRUNCATION_PX", "Y_DEBLUR_REGULARISATION", "LensBlur", "core_line_spread", "line_spread",
           "profile_weights", "psf_2d", "unblurred_y_shape"]

TRUNCATION_PX = 64
#: Weight of the curvature penalty in the y-shape's deblurring (`unblurred_y_shape`), in
#: units of h^2 per px^4 (h ~ 1): it passes the beam's spatial frequencies (below ~0.1 per
#: pixel for a 3.75 px sigma) and damps those a 2.5 px core has all but erased, where
#: deblurring would only amplify the recording's noise. Chosen on the light bench's
#: lens_blur-2 (2.5 px + 5 %, profile rows at 8192 spp, the band at 32): the true model's
#: reduced chi^2 at the noise floor is 5.03 with the recorded shape as it is, 4.53 / 4.00 /
#: 3.57 / 3.64 deblurred with 1e-3 / 1e-2 / 0.1 / 1 (`benchmarks/bench_lens_blur_floor.py`),
#: the recorded 32-row band's outermost row repeated beyond it; with its decay continued
#: instead (`estimate.problem.y_shape_from_rows`, session 64) 2.54 / 2.40 / 2.69 at 1e-2 / 0.1 / 1.
Y_DEBLUR_REGULARISATION = 0.1
#: A column whose deblurred centre u(0) falls below this (h_rec(0) = 1) keeps its recorded
#: shape: its profile row is not a maximum the blur has lowered, and u / u(0) would blow up.
_Y_DEBLUR_MIN_CENTRE = 0.5


def _gauss(x: np.ndarray, s: float) -> np.ndarray:
    if s <= 0:
        return (x == 0).astype(float)
    return np.exp(-0.5 * (x / s) ** 2)


def _line_spread_parts(values: Mapping[str, float], radius: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Offsets x (px) and the core's and the tail's line spread at them, each summing to 1."""
    x = np.arange(-radius, radius + 1, dtype=float)
    core = _gauss(x, values["core_sigma_px"])
    core /= core.sum()
    # The tail's line spread is the marginal over y of the very 2D kernel `psf_2d` applies,
    # truncated to the same square: the untruncated marginal (the Lorentzian
    # 1 / (1 + x^2 / s^2)) holds 95 % of the kernel at x = 0 but 82 % at x = 2 s (s = 20 px),
    # and that difference, on a 2 % tail, put 1-7 % too much light in the profile's shoulders.
    tail = _tail_2d(x, values["tail_scale_px"]).sum(axis=1)
    tail /= tail.sum()
    return x, core, tail


def _tail_2d(x: np.ndarray, s: float) -> np.ndarray:
    """The tail kernel (1 + r^2 / s^2)^(-3/2) on the square x by x, [dx, dy], unnormalised."""
    return (1.0 + (x[:, None] ** 2 + x[None, :] ** 2) / s ** 2) ** -1.5


def line_spread(values: Mapping[str, float], radius: int = TRUNCATION_PX) -> np.ndarray:
    """1D kernel (odd length 2*radius+1), sums to 1."""
    _, core, tail = _line_spread_parts(values, radius)
    f = values["tail_fraction"]
    return (1.0 - f) * core + f * tail


@functools.lru_cache(maxsize=64)
def _y_deblur_matrix(core_sigma_px: float, tail_fraction: float, tail_scale_px: float, radius: int) -> np.ndarray:
    """M (2 radius + 1 square): u = M h_rec on dy = -radius..radius (module docstring)."""
    k = line_spread({"core_sigma_px": core_sigma_px, "tail_fraction": tail_fraction,
                     "tail_scale_px": tail_scale_px}, radius)
    n_obs, n_u = 2 * radius + 1, 4 * radius + 1
    # Observation dy_i = i - radius sees unknown dy_j = j - 2 radius with weight k[dy_i - dy_j + radius].
    off = (np.arange(n_obs)[:, None] - radius) - (np.arange(n_u)[None, :] - 2 * radius)
    a = np.where(np.abs(off) <= radius, k[np.clip(off + radius, 0, 2 * radius)], 0.0)
    d2 = np.zeros((n_u - 2, n_u))
    idx = np.arange(n_u - 2)
    d2[idx, idx], d2[idx, idx + 1], d2[idx, idx + 2] = 1.0, -2.0, 1.0
    m = np.linalg.solve(a.T @ a + Y_DEBLUR_REGULARISATION * d2.T @ d2, a.T)
    out: np.ndarray = m[radius:radius + n_obs]
    out.setflags(write=False)
    return out


def unblurred_y_shape(values: Mapping[str, float], y_shape: np.ndarray, radius: int = TRUNCATION_PX) -> np.ndarray:
    """The recorded y-shape h_rec (N, 2 radius + 1, W) deblurred along y by the PSF of
    `values`: the shape of the unblurred image the profile blur needs (module docstring)."""
    h = np.asarray(y_shape, dtype=np.float64)
    if values["core_sigma_px"] == 0 and values["tail_fraction"] == 0:
        return h
    m = _y_deblur_matrix(float(values["core_sigma_px"]), float(values["tail_fraction"]),
                         float(values["tail_scale_px"]), radius)
    u = np.einsum("ij,njw->niw", m, h)
    centre = u[:, radius:radius + 1, :]
    ok = centre > _Y_DEBLUR_MIN_CENTRE
    out = np.where(ok, u / np.where(ok, centre, 1.0), h)
    # The deblurred shape may ring slightly negative beside a sharp edge; light is not negative.
    return np.clip(out, 0.0, None)


def profile_weights(values: Mapping[str, float], y_shape: np.ndarray, radius: int = TRUNCATION_PX, *,
                    recorded: bool = True, core_in_scene: bool = False) -> np.ndarray:
    """Weights w[n, k, x'] of the profile blur: the light of source pixel x' of row n that
    lands at x' + (k - radius) (module docstring). `y_shape`: (N, 2 radius + 1, W), h at
    dy = -radius..radius (row `radius` is dy = 0); `recorded`: it is the blurred recording's
    shape (deblurred first by `unblurred_y_shape`), else the unblurred image's.
    `core_in_scene`: the row to blur was rendered lit by the beam map blurred along y by the
    core (`estimate.beam.BeamProfile.blurred_along_v`), so it holds sum_dy G(dy) I(x', y0 +
    dy) = I(x', y0) E_G[h(x', .)] already: the core's weight is then its line spread alone,
    exact whatever the image's y-shape, and the tail's term, which acts on I(x', y0), is
    divided by that E_G[h]. Returns (N, 2 radius + 1, W).
    """
    h = np.asarray(y_shape, dtype=np.float64)
    if h.ndim != 3 or h.shape[1] != 2 * radius + 1:
        raise ValueError(f"y_shape has shape {h.shape}; expected (N, {2 * radius + 1}, W)")
    if recorded:
        h = unblurred_y_shape(values, h, radius)
    x, core, tail = _line_spread_parts(values, radius)
    s = values["tail_scale_px"]
    f = values["tail_fraction"]
    # Core: separable, so the mean of h over y is one number per source pixel.
    e_core = np.einsum("d,ndw->nw", core, h)
    if core_in_scene:
        w = np.broadcast_to((1.0 - f) * core[None, :, None], (h.shape[0], core.size, h.shape[2])).copy()
    else:
        w = (1.0 - f) * core[None, :, None] * e_core[:, None, :]
    if f > 0:
        # Tail: the 2D kernel (1 + r^2 / s^2)^-3/2 at offset dx, normalised over dy.
        t2 = _tail_2d(x, s)   # [dx, dy]
        cond = t2 / t2.sum(axis=1, keepdims=True)
        e_tail = np.einsum("kd,ndw->nkw", cond, h)
        if core_in_scene:
            # A column whose deblurred shape has no centre left keeps the tail's own weight.
            e_tail = e_tail / np.where(e_core > 1e-6, e_core, 1.0)[:, None, :]
        w = w + f * tail[None, :, None] * e_tail
    return w


def core_line_spread(values: Mapping[str, float], radius: int = TRUNCATION_PX) -> np.ndarray:
    """The core's line spread (odd length 2 radius + 1, sums to 1): its kernel along x, and,
    the core being separable, along y (`ForwardModel.beam_for` blurs the beam map with it)."""
    return _line_spread_parts(values, radius)[1]


#: Recent `profile_weights` of the recorded y-shape, by the y-shape array's identity and the
#: blur's values: a fit's finite differences and Jacobians blur renders of the same angles at
#: the same blur many times over (a lens blur's diagnosis called it 1049 times, 18 s of its
#: 84 s on 2 cores at 256 spp; on a GPU the largest cost of that diagnosis). The entry holds
#: a weak reference to the array, so a hit is the same object, never a new one at a reused
#: id, and the cache keeps no y-shape alive (each entry's weights: about 2 MB on rig
#: estimate's 8 x 256-px window); `estimate.forward.ForwardModel.y_shape_for` hands out one
#: array per set of angles.
_WEIGHTS_CACHE: OrderedDict[tuple[int, bool, tuple[tuple[str, float], ...]],
                            tuple[weakref.ref[np.ndarray], np.ndarray]] = OrderedDict()
_WEIGHTS_CACHE_SIZE = 16


def _recorded_profile_weights(values: Mapping[str, float], y_shape: np.ndarray,
                              core_in_scene: bool = False) -> np.ndarray:
    """`profile_weights(values, y_shape, core_in_scene=...)` of a recorded y-shape, from
    `_WEIGHTS_CACHE` when the same array was blurred at the same values lately (read-only
    arrays only: a writable one could change under its id)."""
    h = np.asarray(y_shape)
    if h.flags.writeable:
        return profile_weights(values, h, core_in_scene=core_in_scene)
    key = (id(h), core_in_scene, tuple(sorted((k, float(v)) for k, v in values.items())))
    hit = _WEIGHTS_CACHE.get(key)
    if hit is not None and hit[0]() is h:
        _WEIGHTS_CACHE.move_to_end(key)
        return hit[1]
    w = profile_weights(values, h, core_in_scene=core_in_scene)
    w.setflags(write=False)
    _WEIGHTS_CACHE[key] = (weakref.ref(h), w)
    while len(_WEIGHTS_CACHE) > _WEIGHTS_CACHE_SIZE:
        _WEIGHTS_CACHE.popitem(last=False)
    return w


def _weighted_profile(img: np.ndarray, w: np.ndarray, transpose: bool) -> np.ndarray:
    """out[n, x] = sum_k img[n, x - dx_k] w[n, k, x - dx_k] (or its transpose:
    out[n, x'] = sum_k img[n, x' + dx_k] w[n, k, x']), img (N, W), zero padding."""
    n_k = w.shape[1]
    radius = n_k // 2
    width = img.shape[-1]
    out = np.zeros_like(img)
    for k in range(n_k):
        dx = k - radius
        if abs(dx) >= width:
            continue
        if transpose:
            # source x' gathers the cotangent at x' + dx
            if dx >= 0:
                out[:, :width - dx] += img[:, dx:] * w[:, k, :width - dx]
            else:
                out[:, -dx:] += img[:, :width + dx] * w[:, k, -dx:]
        else:
            src = img * w[:, k, :]
            if dx >= 0:
                out[:, dx:] += src[:, :width - dx]
            else:
                out[:, :width + dx] += src[:, -dx:]
    return out


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
    neutral_is_identity = True
    parameters = (
        ParameterSpec("core_sigma_px", 0.0, 0.0, 20.0, "px", "image", 0.05,
                      "standard deviation of the sharp core"),
        ParameterSpec("tail_fraction", 0.0, 0.0, 0.5, "", "image", 0.002,
                      "fraction of the light in the long tail"),
        ParameterSpec("tail_scale_px", 20.0, 0.0, 200.0, "px", "image", 0.5,
                      "scale of the tail", open_lower=True),
    )

    @classmethod
    def _profile_rows(cls, img: np.ndarray, y_shape: np.ndarray) -> tuple[np.ndarray, tuple[int, ...]]:
        """img (..., 1, W) or (N, W) -> (N, W) for the weighted profile blur."""
        n = np.asarray(y_shape).shape[0]
        flat = img.reshape(-1, img.shape[-1])
        if flat.shape[0] != n:
            raise ValueError(f"y_shape has {n} rows for an image of {flat.shape[0]} profile rows")
        return flat, img.shape

    @classmethod
    def apply(cls, image: np.ndarray, values: Mapping[str, float], *, pixel_mm: float,
              profile_only: bool, y_shape: np.ndarray | None = None,
              merge_fill: np.ndarray | None = None,
              beam_fill: BeamFill | None = None, core_in_scene: bool = False) -> np.ndarray:
        img = np.asarray(image, dtype=np.float64)
        if values["core_sigma_px"] == 0 and values["tail_fraction"] == 0:
            return img.copy()
        if profile_only or img.shape[-2] == 1:
            if y_shape is not None:
                flat, shape = cls._profile_rows(img, y_shape)
                return _weighted_profile(flat, _recorded_profile_weights(values, y_shape, core_in_scene),
                                         False).reshape(shape)
            # Without a y-shape, the line spread: with the core in the scene its core part is
            # exact; otherwise, and for the tail, the image is taken as constant along y.
            return ndimage.convolve1d(img, line_spread(values), axis=-1, mode="constant")
        k = psf_2d(values)
        k = k.reshape((1,) * (img.ndim - 2) + k.shape)
        return signal.fftconvolve(img, k, mode="same", axes=(-2, -1))

    @classmethod
    def vjp_input(cls, image: np.ndarray, cotangent: np.ndarray, values: Mapping[str, float], *,
                  pixel_mm: float, profile_only: bool, y_shape: np.ndarray | None = None,
              merge_fill: np.ndarray | None = None,
              beam_fill: BeamFill | None = None, core_in_scene: bool = False) -> np.ndarray:
        cot = np.asarray(cotangent, dtype=np.float64)
        if (y_shape is not None and (profile_only or cot.shape[-2] == 1)
                and not (values["core_sigma_px"] == 0 and values["tail_fraction"] == 0)):
            flat, shape = cls._profile_rows(cot, y_shape)
            return _weighted_profile(flat, _recorded_profile_weights(values, y_shape, core_in_scene),
                                     True).reshape(shape)
        return cls.apply(cot, values, pixel_mm=pixel_mm, profile_only=profile_only)
