"""The paper's log-intensity loss with a fitted scale, and the chi^2 of a fit.

    L(theta, s; delta) = mean_valid ( log(I_meas / s + delta) - log(I_model(theta) + delta) )^2

`I_meas` is in e-/s per pixel, `I_model` in the forward model's units, `s` the fitted scale
(measured = s * rendered). The paper normalised the mean of the image set to 1 instead; a
fitted scale does not tie the result to which pixels happen to be in the window and takes the
beam-power / gain / lens-transmission factor out of the fit cleanly (profiled out in 1-D at
every evaluation, so it costs no render).

Monte Carlo noise biases a log loss (E log(I_mc + delta) < log(E I_mc + delta), Jensen),
more where the render is relatively noisier, which depends on the parameters: at 64 spp the
minimum over the albedo of a test problem sat 0.15 below the truth, at >= 256 spp on it.
Hence the range's lower end (1 % of the peak, not the 0.1 % a noise-free render could take)
and an optimisation that ends at >= 512 spp.

`delta` is given relative to the data's intensity range: delta = delta_rel * max(I_meas / s).
A small delta weighs the dim tails (log space), a large one the bright core; the fit draws
delta_rel log-uniformly from `delta_range` at every iteration (the paper's alternation) so
no intensity range dominates. Convergence and reported loss values use the fixed geometric
mid-point `reference_delta(delta_range)`.

The scale need not be fitted: the rig measures it. `rig calibrate-beam` records the beam's
detected rate per filter with the slab removed and the beam straight into the lens through a
neutral-density filter of transmission T_nd (`power_e_per_s` = P_f T_nd), so the e-/s per
pixel of the light the slab scatters is

    I_meas = L_unit * P_f * A_px * Omega,   P_f = power_e_per_s / T_nd

with L_unit the radiance for a unit-power beam [1/(mm^2 sr)], A_px the object-space area of
one (binned) pixel [mm^2] and Omega the solid angle the telecentric lens collects from each
object point [sr]. The forward model renders with the calibration's beam map as it was
measured (e-/s per pixel through the ND, `load_problem`), i.e. I_model = L_unit * B with B
the map's total (`BeamProfile.power()`, ~ power_e_per_s up to the map window), so

    scale = I_meas / I_model = power_e_per_s / T_nd * A_px * Omega / B.
 Omega and T_nd are constants of the lens and of
the calibration ND filter (the same for every filter), read from the session's rig
configuration snapshot (`camera.collection_sr`, `camera.calibration_nd`; see
`calibrated_scale`). A free scale is nearly degenerate with the albedo (a brighter,
more scattering slab and a dimmer beam give similar shapes): fixing it removes that valley.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares, minimize_scalar

from estimate.errors import DataError

__all__ = ["DEFAULT_CALIBRATION_ND", "DEFAULT_COLLECTION_SR", "DEFAULT_DELTA_RANGE", "ScaleCalibration",
           "calibrated_scale", "chi2", "log_hdr_variance", "log_loss", "profile_additive", "profile_scale",
           "reference_delta"]

#: Collection solid angle of the lens [sr] when the rig configuration gives none
#: (`camera.collection_sr`); equal to the default simulated world's `optics.collection_sr`.
DEFAULT_COLLECTION_SR = 0.01
#: Transmission of the ND filter in the beam during `rig calibrate-beam` when the rig
#: configuration gives none (`camera.calibration_nd`); the default world's `optics.calibration_nd`.
DEFAULT_CALIBRATION_ND = 1.0e-3

#: Range of delta relative to the (scaled) data maximum.
DEFAULT_DELTA_RANGE = (1e-2, 2e-1)


def reference_delta(delta_range: tuple[float, float] = DEFAULT_DELTA_RANGE) -> float:
    """Fixed relative delta for reported losses: geometric mean of the range."""
    return math.sqrt(delta_range[0] * delta_range[1])


def log_measured(measured: np.ndarray, valid: np.ndarray, scale: float, delta_rel: float
                 ) -> tuple[np.ndarray, float]:
    """log(I_meas / s + delta) per pixel, and delta = delta_rel * max over the valid pixels
    of I_meas / s (in the model's units; at least 1e-30).

    A dark pixel's sensor noise may dip below zero; it is clipped at -delta / 2 so the
    logarithm stays finite.
    """
    m = measured / scale
    delta = max(delta_rel * float(np.max(np.where(valid, m, -np.inf))), 1e-30)
    return np.log(np.clip(m, -0.5 * delta, None) + delta), delta


def log_hdr_variance(measured: np.ndarray, variance: np.ndarray, scale: float, delta: float) -> np.ndarray:
    """The HDR variance of log(I_meas / s + delta) per pixel, to first order:
    var / s^2 / (I_meas / s + delta)^2, with I_meas / s clipped at -delta / 2 as in
    `log_measured` (`variance` in the measured units squared, `delta` in the model's)."""
    m = np.clip(measured / scale, -0.5 * delta, None)
    return variance / scale ** 2 / (m + delta) ** 2


def log_residual(log_meas: np.ndarray, model: np.ndarray, valid: np.ndarray, delta: float) -> np.ndarray:
    """r = log(I_meas / s + delta) - log(I_model + delta) on the valid pixels, 0 elsewhere
    (`log_meas`, `delta` from `log_measured`; a render's negative values count as 0)."""
    return np.where(valid, log_meas - np.log(np.clip(model, 0.0, None) + delta), 0.0)


def log_loss(measured: np.ndarray, model: np.ndarray, valid: np.ndarray, scale: float,
             delta_rel: float) -> tuple[float, np.ndarray]:
    """Loss value and its gradient with respect to `model` (same shape)."""
    lm, delta = log_measured(measured, valid, scale, delta_rel)
    n = max(1, int(valid.sum()))
    im = np.clip(model, 0.0, None)
    r = log_residual(lm, model, valid, delta)
    value = float(np.sum(r * r) / n)
    grad = np.where(valid & (model >= 0), -2.0 * r / (im + delta) / n, 0.0)
    return value, grad


def decorrelated_loss(measured: np.ndarray, model_a: np.ndarray, model_b: np.ndarray, valid: np.ndarray,
                      scale: float, delta_rel: float) -> float:
    """mean(r_A r_B) over valid pixels for two independent renders A, B of the same
    parameters, r = log(m + delta) - log(I + delta) as in `log_loss`.

    Unlike `log_loss` of one render (or of their mean), its expectation has no Monte Carlo
    variance term, so it compares parameter sets fairly: a render's variance grows with
    sigma_t and the albedo, and on the one-channel benchmark the plain loss at 1024 spp put
    a fit 19 % above the truth where this one put them level.
    """
    return decorrelated_loss_se(measured, model_a, model_b, valid, scale, delta_rel)[0]


def decorrelated_loss_se(measured: np.ndarray, model_a: np.ndarray, model_b: np.ndarray, valid: np.ndarray,
                         scale: float, delta_rel: float) -> tuple[float, float]:
    """`decorrelated_loss` and its standard error, std(r_A r_B) / sqrt(n) over the valid
    pixels (taken as independent)."""
    lm, delta = log_measured(measured, valid, scale, delta_rel)
    n = max(1, int(valid.sum()))
    ra, rb = (log_residual(lm, q, valid, delta) for q in (model_a, model_b))
    prod = (ra * rb)[valid]
    se = float(np.std(prod) / math.sqrt(n)) if prod.size else 0.0
    return float(np.sum(ra * rb) / n), se


def profile_scale(measured: np.ndarray, model: np.ndarray, valid: np.ndarray, delta_rel: float,
                  guess: float | None = None) -> float:
    """The scale s minimising the log loss for a fixed model (1-D bounded search in log s)."""
    sm = float(np.sum(np.where(valid, np.clip(model, 0, None), 0.0)))
    sd = float(np.sum(np.where(valid, measured, 0.0)))
    g0 = guess if guess and guess > 0 else (sd / sm if sm > 0 and sd > 0 else 1.0)
    lg = math.log(g0)

    def f(ls: float) -> float:
        return log_loss(measured, model, valid, math.exp(ls), delta_rel)[0]

    res = minimize_scalar(f, bounds=(lg - 3.0, lg + 3.0), method="bounded", options={"xatol": 1e-5})
    return float(math.exp(res.x))


def profile_additive(measured: np.ndarray, model: np.ndarray, valid: np.ndarray, scale: float,
                     delta_rel: float, columns: Mapping[str, np.ndarray], values: Mapping[str, float],
                     bounds: Mapping[str, tuple[float, float]]) -> dict[str, float]:
    """The values of additive parameters minimising the log loss for a fixed render.

    `model` was rendered with `values`; parameter k adds `(v_k - values_k) * columns[k]` to
    it (an additive effect, e.g. a stray-light offset and slope: `ForwardModel.
    additive_columns`). Solved by bounded least squares on the log residuals at `delta_rel`
    (no render, milliseconds). Returns the new values, inside `bounds`.
    """
    names = list(columns)
    if not names:
        return {}
    lm_all, delta = log_measured(measured, valid, scale, delta_rel)
    lm = lm_all[valid]
    base = np.asarray(model, dtype=np.float64)[valid]
    cols = np.stack([np.asarray(columns[n], dtype=np.float64)[valid] for n in names], axis=1)
    x0 = np.array([float(values[n]) for n in names])
    # Each parameter in units of a typical size of its effect: the columns (ones, x in mm)
    # and the values (radiance ~1e5) differ by orders of magnitude.
    unit = np.array([delta / max(float(np.sqrt(np.mean(c ** 2))), 1e-300) for c in cols.T])
    lo = np.array([bounds[n][0] for n in names])
    hi = np.array([bounds[n][1] for n in names])
    floor = 1e-3 * delta  # keeps log finite where a trial value would push the model below 0

    def resid(u: np.ndarray) -> np.ndarray:
        return lm - np.log(np.clip(base + cols @ (u * unit - x0), floor, None) + delta)

    def jac(u: np.ndarray) -> np.ndarray:
        I = base + cols @ (u * unit - x0)
        return np.where((I > floor)[:, None], -cols * unit / (np.clip(I, floor, None) + delta)[:, None], 0.0)

    u0 = np.clip(x0, lo, hi) / unit
    res = least_squares(resid, u0, jac=jac, bounds=(lo / unit, hi / unit), method="trf",
                        x_scale=1.0, xtol=1e-10, ftol=1e-10, gtol=1e-12, max_nfev=50)
    return {n: float(v) for n, v in zip(names, np.clip(res.x * unit, lo, hi))}


def chi2(measured: np.ndarray, variance: np.ndarray, model: np.ndarray, valid: np.ndarray, scale: float,
         model_variance: np.ndarray | None = None) -> float:
    """sum_valid (I_meas - s I_model)^2 / (var_meas + s^2 var_model)."""
    var = np.where(valid, variance, np.inf)
    if model_variance is not None:
        var = var + scale ** 2 * model_variance
    r = (measured - scale * model) ** 2 / var
    return float(np.sum(np.where(valid, r, 0.0)))


@dataclass(frozen=True)
class ScaleCalibration:
    """The measured scale of one channel: measured [e-/s per pixel] = scale * rendered.

    Attributes:
        scale: power_e_per_s / calibration_nd * pixel_area_mm2 * collection_sr / beam_power.
        power_e_per_s: detected beam rate through the ND filter (calibration.yaml).
        beam_power: total of the beam map the forward model renders with [e-/s].
        calibration_nd: ND transmission during the calibration.
        collection_sr: collection solid angle of the lens [sr].
        pixel_area_mm2: object-space area of one (binned) stack pixel [mm^2].
        defaults: configuration keys that were absent (their defaults were used).
    """

    scale: float
    power_e_per_s: float
    beam_power: float
    calibration_nd: float
    collection_sr: float
    pixel_area_mm2: float
    defaults: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, object]:
        return {"scale": self.scale, "power_e_per_s": self.power_e_per_s, "beam_power": self.beam_power,
                "calibration_nd": self.calibration_nd,
                "collection_sr": self.collection_sr, "pixel_area_mm2": self.pixel_area_mm2,
                "defaults": list(self.defaults)}


def _positive(value: object, what: str) -> float:
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise DataError(f"{what} must be a number, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise DataError(f"{what} must be > 0, got {value!r}")
    return v


def calibrated_scale(session_dir: str | os.PathLike[str], channel: str, beam_power: float, *,
                     collection_sr: float | None = None, calibration_nd: float | None = None) -> ScaleCalibration:
    """The scale of `channel` from the session's beam calibration and rig configuration.

    `beam_power`: total of the beam map the forward model renders with (the problem's
    `beam.power()`, e-/s through the ND as the calibration measured it).

    Omega = `collection_sr` if given, else the snapshot's `camera.collection_sr`, else
    DEFAULT_COLLECTION_SR; T_nd likewise from `camera.calibration_nd` (DEFAULT_CALIBRATION_ND).
    The pixel area is the session geometry's `pixel_pitch_mm` (else the calibration's)
    squared times the ROI binning (bin_x * bin_y), matching `load_problem`'s pixel grid.

    Raises:
        DataError: no calibration, or it lacks this channel's `power_e_per_s`.
    """
    from capture.errors import SessionError
    from capture.session import Session

    try:
        s = Session.open(session_dir)
        cal = s.load_calibration() if s.calibration_dir is not None else None
    except SessionError as e:
        raise DataError(str(e)) from None
    if cal is None:
        raise DataError(f"{session_dir} has no beam calibration: the calibrated scale needs the beam power; "
                        "use --scale free")
    entry = ((cal.get("beam") or {}).get("filters") or {}).get(channel) or {}
    if "power_e_per_s" not in entry:
        raise DataError(f"the calibration of {session_dir} has no beam power for channel {channel!r}; "
                        "use --scale free")
    power = _positive(entry["power_e_per_s"], f"calibration beam.filters.{channel}.power_e_per_s")
    cam = (s.rig_config.get("camera") or {}) if isinstance(s.rig_config.get("camera"), dict) else {}
    defaults = []
    if collection_sr is None:
        if cam.get("collection_sr") is None:
            defaults.append("camera.collection_sr")
        collection_sr = cam.get("collection_sr", DEFAULT_COLLECTION_SR)
    if calibration_nd is None:
        if cam.get("calibration_nd") is None:
            defaults.append("camera.calibration_nd")
        calibration_nd = cam.get("calibration_nd", DEFAULT_CALIBRATION_ND)
    omega = _positive(collection_sr, "camera.collection_sr")
    nd = _positive(calibration_nd, "camera.calibration_nd")
    if nd > 1.0:
        raise DataError(f"camera.calibration_nd is a transmission (0, 1], got {nd}")
    geo = s.geometry()
    pitch = _positive(geo.get("pixel_pitch_mm", cal.get("pixel_pitch_mm")), "pixel_pitch_mm")
    roi = dict(geo.get("roi") or geo.get("camera_roi") or {})
    for r in s.stacks():
        if r.key.filter == channel and r.done and r.info.get("roi"):
            roi = dict(r.info["roi"])
            break
    area = pitch * pitch * int(roi.get("bin_x", 1)) * int(roi.get("bin_y", 1))
    b = _positive(beam_power, "beam map power")
    return ScaleCalibration(scale=power / nd * area * omega / b, power_e_per_s=power, beam_power=b, calibration_nd=nd,
                            collection_sr=omega, pixel_area_mm2=area, defaults=tuple(defaults))
