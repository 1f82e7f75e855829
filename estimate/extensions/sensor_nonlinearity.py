"""Extension `sensor_nonlinearity`: response compression near full well.

Raw frames (simulated camera): electrons x -> x * (1 - c * (x / full_well)^2), monotone
for c < 1/3; c = `compression` = relative loss at full well (`apply_raw`).

Effect on a merged HDR profile. Each exposure of a bracket reads the pixel's charge
L t_i, compressed by c (L t_i / FW)^2, and the merge (`capture.hdr.merge_hdr`) averages the
exposures it keeps (unsaturated, not in a bloom's reach) with inverse-variance weights
w_i. So the merged radiance is L (1 - c g) with

    g = sum_i w_i (L t_i / FW)^2 / sum_i w_i

the mean squared fill of the well over the exposures read: the longest one kept dominates,
filled to between a quarter and nearly all of the well by a bracket of factor-4 steps,
so g is a sawtooth along the profile, not a function of L alone. With the recording's
brackets (`merge_fill`, from `estimate.problem.merge_fill_from_rows`) the model is exactly
that: I -> I (1 - c g), one parameter. The recording gives g_m, the fill of the merged
radiance L_m = L (1 - c g) rather than of L: g_m = g (1 - c g)^2 (g is quadratic in the
radiance), which `true_fill` solves for g at the compression being tried (29 % more fill than
g_m at a full well compressed by 12 %: 1 / 0.88^2; at c = 0 the two agree, so the screening's column is
-I g_m). Without them (a session without its
bracket records, or synthetic sessions made by this model) the older form
I -> I (1 - c min(I / W, 1)^2), W = `full_well_radiance` the HDR radiance that fills the
well in the shortest exposure (profile units): each pixel read from the shortest exposure,
an upper bound on the compression of dim pixels. Up to session 62 that was the only form;
on the light bench's 6 % session the merged form's fit reaches the true model's own reduced
chi^2 at the noise floor (1.25 against 1.26). A compression above 1 - saturation / full well
reads a full well below the noise model's saturation level; the merge finds those clipped
wells by their plateau (`capture.hdr.plateau_saturation_adu`, since session 64; before, it
kept them as measurements) and records how many exposures it kept per pixel, which
`merge_fill_from_rows` reads. Derivative: exact in the image (linear in it); by c through
`true_fill`'s root (finite differences of a deterministic function).

The beam calibration went through the same sensor (session 67). Its frame read the beam's
peak and the well-filled pixels of its bracket low by the same c g, so the calibrated beam
power is low, by 0.73 % at c = 0.06 on the light bench (3.178e7 against the clean sessions'
3.201e7 e-/s), and the model, which renders the beam map scaled to that power, is dim by
as much wherever the scale is the calibrated one (`rig estimate`'s default). Unmodelled, a
fit with the compression on made up for it with the albedo: 0.9523 against 0.95 on three
independent recordings at c = 0.06, the compression 0.053-0.058. With the calibration
frame's fills (`BeamFill`: the map's rows through `merge_fill_from_rows`, with the exposures
the calibration's merge kept, recounted from its frames) the model multiplies by
`calibration_gain`, which restores the bench's
power to 0.005 % at c = 0.06 and 0.01 % at 0.12 (from the calibration merge's kept exposures
per pixel; replayed from the map alone, 0.03 %). With a free scale the factor is absorbed by
the scale. The map's shape was read wrong too: its wings, read from longer exposures at fills
up to 0.6, are low by up to c g (3.6 % at c = 0.06) against its peak, which lifted even the
truth's own reduced chi^2 at the floor (1.208 at 12 % against the clean sessions' 1.12-1.15)
and left the albedo 0.0009 high at 12 %. With the calibration frame's pixels the slab is lit
by `decompressed_map` at the values' c (`estimate.forward.ForwardModel.decompresses_beam`):
the albedo then within 0.0002 of the truth and the fits at the truth's own chi^2.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from estimate.errors import ModelParameterError
from estimate.extensions.base import BeamFill, ImageExtension, ParameterSpec

__all__ = ["SensorNonlinearity", "apply_raw", "calibration_gain", "decompressed_map", "true_fill"]

#: Bisection steps of `true_fill` on [g_m, 1]: 2^-48 < 1e-14.
_FILL_ITERATIONS = 48


def apply_raw(frame_electrons: np.ndarray, compression: float, full_well_e: float) -> np.ndarray:
    """Compressed raw response of a frame in electrons (values above full well clip there)."""
    if not (0.0 <= compression < 1.0 / 3.0):
        raise ModelParameterError(f"sensor_nonlinearity.compression={compression!r} must be in [0, 1/3)")
    if not full_well_e > 0:
        raise ModelParameterError(f"sensor full_well_e={full_well_e!r} must be > 0")
    x = np.clip(np.asarray(frame_electrons, dtype=np.float64), 0.0, full_well_e)
    return x * (1.0 - compression * (x / full_well_e) ** 2)


def true_fill(compression: float, merged_fill: np.ndarray) -> np.ndarray:
    """The well's mean squared fill g of the true radiance, from g_m of the merged radiance:
    the solution of g (1 - c g)^2 = g_m (module docstring), g_m >= 0, capped at 1 (the merge
    keeps no sample beyond a full well; a g_m that no g <= 1 explains at this c means the c
    is too large for the recording, and the cap keeps the model finite there)."""
    gm = np.clip(np.asarray(merged_fill, dtype=np.float64), 0.0, None)
    c = float(compression)
    if c == 0.0:
        return gm
    # g (1 - c g)^2 rises monotonically on [0, 1] for c < 1/3, from <= g_m at g = g_m:
    # bisection on [g_m, 1] (where even g = 1 falls short, the cap).
    lo, hi = np.minimum(gm, 1.0), np.ones_like(gm)
    for _ in range(_FILL_ITERATIONS):
        mid = 0.5 * (lo + hi)
        below = mid * (1.0 - c * mid) ** 2 < gm
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return 0.5 * (lo + hi)


def calibration_gain(compression: float, beam_fill: BeamFill) -> float:
    """How much more power the beam carries than its calibration frame read: sum_p w_p /
    (1 - c g_p) over the beam map's pixels (`BeamFill`: w_p each pixel's share of the read
    power, g_p the calibration merge's fill there, converted by `true_fill`). The model
    renders the beam map scaled to the read power, so its radiance is low by this factor
    wherever the compression is on; 1 at c = 0, d/dc = sum_p w_p g_p there."""
    c = float(compression)
    if c == 0.0:
        return 1.0
    w = np.asarray(beam_fill.weights, dtype=np.float64)
    return float(np.sum(w / (1.0 - c * true_fill(c, beam_fill.fill))))


def decompressed_map(compression: float, beam_fill: BeamFill) -> np.ndarray:
    """The calibration frame's pixels with the compression taken out, p / (1 - c g_p), scaled
    back to the read power (the shape the beam had; its power is `calibration_gain`'s)."""
    if beam_fill.pixels is None or beam_fill.fill_map is None:
        raise ValueError("this BeamFill carries no pixel map")
    pix = np.asarray(beam_fill.pixels, dtype=np.float64)
    c = float(compression)
    if c == 0.0:
        return pix
    out = pix / (1.0 - c * true_fill(c, beam_fill.fill_map))
    total = float(out.sum())
    return out * (float(pix.sum()) / total) if total > 0 else out


class SensorNonlinearity(ImageExtension):
    name = "sensor_nonlinearity"
    parameters = (
        ParameterSpec("compression", 0.0, 0.0, 0.33, "", "image", 1e-3,
                      "relative response loss at full well"),
        ParameterSpec("full_well_radiance", 1.0, 0.0, float("inf"), "radiance", "image", 1e-3,
                      "HDR radiance filling the well in the shortest exposure", open_lower=True),
    )

    @classmethod
    def apply(cls, image: np.ndarray, values: Mapping[str, float], *, pixel_mm: float,
              profile_only: bool, y_shape: np.ndarray | None = None,
              merge_fill: np.ndarray | None = None,
              beam_fill: BeamFill | None = None, core_in_scene: bool = False) -> np.ndarray:
        img = np.asarray(image, dtype=np.float64)
        gain = 1.0 if beam_fill is None else calibration_gain(values["compression"], beam_fill)
        if merge_fill is not None:
            c = values["compression"]
            return gain * img * (1.0 - c * true_fill(c, cls._fill(img, merge_fill)))
        r = np.clip(img / values["full_well_radiance"], 0.0, 1.0)
        return gain * img * (1.0 - values["compression"] * r ** 2)

    @staticmethod
    def _fill(img: np.ndarray, merge_fill: np.ndarray) -> np.ndarray:
        """The merge's fill g, (N, W), shaped to broadcast against `img` (N, W) or (N, 1, W)."""
        g = np.asarray(merge_fill, dtype=np.float64)
        if g.size != img.size:
            raise ValueError(f"merge_fill has {g.size} values for an image of {img.size} pixels")
        return g.reshape(img.shape)

    @classmethod
    def vjp_input(cls, image: np.ndarray, cotangent: np.ndarray, values: Mapping[str, float], *,
                  pixel_mm: float, profile_only: bool, y_shape: np.ndarray | None = None,
              merge_fill: np.ndarray | None = None,
              beam_fill: BeamFill | None = None, core_in_scene: bool = False) -> np.ndarray:
        img = np.asarray(image, dtype=np.float64)
        gain = 1.0 if beam_fill is None else calibration_gain(values["compression"], beam_fill)
        if merge_fill is not None:
            c = values["compression"]
            return gain * np.asarray(cotangent) * (1.0 - c * true_fill(c, cls._fill(img, merge_fill)))
        w = values["full_well_radiance"]
        r = img / w
        below = (r >= 0) & (r <= 1)
        slope = np.where(below, 1.0 - 3.0 * values["compression"] * r ** 2,
                         1.0 - values["compression"] * np.where(r > 1, 1.0, 0.0))
        return gain * np.asarray(cotangent) * slope
