"""Beam calibration: the rotation zero, the beam's HDR map, centre, widths and power per filter.

Procedure (device interfaces and capture only; the operator is asked to remove the slab):

1. Rotation zero. With the beam pointed into the telecentric lens, the light that passes
   the lens's aperture stop falls off as the beam tilts away from the lens axis. At one
   fixed exposure (chosen so the brightest pixel sits near `target_peak_fraction` of the
   usable range at stage 180 deg) and with matched dark frames subtracted, the total
   detected signal S(theta) is recorded on a coarse grid around 180 deg, then on a fine
   grid around the coarse maximum. A Gaussian A exp(-(theta - theta0)^2 / 2 s^2) is fitted
   to the fine points by weighted least squares (weights from the shot + read noise of
   each sum); theta0 is the rotation zero. Its uncertainty is the fit's standard error
   (scaled by sqrt(reduced chi^2) when that exceeds 1) combined with the stage resolution
   (step / sqrt(12)).
2. At the rotation zero, per filter: an automatic exposure bracket
   (`capture.bracket.acquire_bracket`), matched darks (`acquire_darks`), the noise-optimal
   merge (`capture.hdr.merge_hdr`). From the merged image: the centroid and second-moment
   widths (pixels above `moment_threshold` of the peak), the power (sum inside a circle of
   `power_radius_widths` widths) and a map window around the centre written as EXR.
3. The operator is asked to mount the slab again.

Output (CONTRACTS.md): CALDIR/calibration.yaml, beam_<f>.exr, raw/*.npz (every frame taken,
light and dark). Every file is written atomically; calibration.yaml is written last, so a
directory without it is an interrupted calibration. A non-empty CALDIR is refused.

Conventions: pixel coordinates are continuous with pixel (i, j) covering [i, i+1) x [j, j+1)
(its centre at i + 0.5); `centroid_mm` is (x, y) in the world frame (x right, y up) relative
to `center_px`; widths are 1-sigma second moments in mm (object space).
"""

from __future__ import annotations

import datetime as _dt
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
import yaml

from capture.atomic import atomic_write_text
from capture.bracket import BracketPolicy, acquire_bracket, acquire_darks
from capture.errors import CaptureError
from capture.exr_io import write_exr, write_frames
from capture.hdr import MatchedDarks, NoiseModel, merge_hdr
from drivers.interfaces import (
    ROI,
    Camera,
    FilterChanger,
    Frame,
    RotationStage,
    ShutterMode,
)

__all__ = [
    "FORMAT",
    "BeamCalibrationSettings",
    "BeamMeasurement",
    "CalibrationError",
    "Operator",
    "ScanResult",
    "beam_moments",
    "calibrate_beam",
    "check_output_dir",
    "fit_rotation_zero",
]

FORMAT = "rig-calibration/1"


class CalibrationError(CaptureError, ValueError):
    """Raised when a calibration cannot start (output directory not empty, unknown filter,
    scan outside the stage's range) or fails (no beam seen, operator declined)."""


class Operator(Protocol):
    """Someone who can act on the rig: remove or mount the slab.

    `ask(action, message)` returns True once the action is done ("remove_slab", "mount_slab").
    """

    def ask(self, action: str, message: str) -> bool: ...


@dataclass(frozen=True)
class BeamCalibrationSettings:
    """Knobs of the calibration (angles in degrees).

    Attributes:
        filters: filters to calibrate, in order; the first one is used for the scan.
        pixel_pitch_mm: object-space size of one unbinned pixel (0.020 mm / magnification).
        coarse_half_range_deg, coarse_step_deg: coarse scan around 180.
        fine_half_range_deg, fine_step_deg: fine scan around the coarse maximum.
        stage_resolution_deg: smallest stage step (enters the uncertainty).
        target_peak_fraction: brightest scan pixel at stage 180, as a fraction of the usable range.
        scan_darks: dark frames averaged for the scan's dark reference.
        bracket: exposure bracket policy of the HDR beam images.
        moment_threshold: pixels below this fraction of the peak are left out of the moments.
        power_radius_widths: the power is summed inside this many (largest) widths.
        map_halfwidth_widths: half-size of the map window in widths (at least 16 px).
    """

    filters: tuple[str, ...]
    pixel_pitch_mm: float
    coarse_half_range_deg: float = 3.0
    coarse_step_deg: float = 0.5
    fine_half_range_deg: float = 0.6
    fine_step_deg: float = 0.1
    stage_resolution_deg: float = 0.0025
    target_peak_fraction: float = 0.3
    scan_darks: int = 2
    bracket: BracketPolicy = field(default_factory=lambda: BracketPolicy(target_snr=20.0, dim_fraction=1e-3,
                                                                         n_darks=2, max_exposures=6))
    moment_threshold: float = 1e-3
    power_radius_widths: float = 6.0
    map_halfwidth_widths: float = 6.0


@dataclass
class ScanResult:
    """The rotation-zero scan: points and the fitted peak."""

    angles_deg: list[float]
    signal_e_per_s: list[float]
    sigma_e_per_s: list[float]
    exposure_s: float
    zero_deg: float
    uncertainty_deg: float
    acceptance_sigma_deg: float
    reduced_chi2: float


@dataclass
class BeamMeasurement:
    """One filter's merged beam image and its moments (pixel coordinates on the full sensor)."""

    filter: str
    radiance: np.ndarray
    variance: np.ndarray
    centroid_px: tuple[float, float]
    width_px: tuple[float, float]
    power_e_per_s: float
    exposures_s: list[float]
    bracket_reason: str


def check_output_dir(out: str | os.PathLike[str]) -> Path:
    """The calibration directory, refused if it exists and is not empty or cannot be made.

    Raises:
        CalibrationError: a file, a non-empty directory, or not creatable.
    """
    p = Path(out)
    if p.exists() and not p.is_dir():
        raise CalibrationError(f"{p} is a file; give a new or empty directory for the calibration")
    if p.is_dir() and any(p.iterdir()):
        raise CalibrationError(f"{p} is not empty; a calibration is never overwritten: give a new directory")
    try:
        p.mkdir(parents=True, exist_ok=True)
        probe = p / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise CalibrationError(f"cannot write the calibration into {p}: {e.strerror or e}; "
                               "choose a writable directory") from None
    return p


def fit_rotation_zero(angles: npt.ArrayLike, signal: npt.ArrayLike, sigma: npt.ArrayLike,
                      resolution_deg: float = 0.0) -> tuple[float, float, float, float]:
    """Fit A exp(-(a - a0)^2 / 2 s^2) to a scan.

    Returns:
        (a0, uncertainty of a0, s, reduced chi^2), degrees.

    Raises:
        CalibrationError: too few points or no peak inside the scan.
    """
    from scipy.optimize import curve_fit

    a = np.asarray(angles, dtype=np.float64)
    y = np.asarray(signal, dtype=np.float64)
    s = np.asarray(sigma, dtype=np.float64)
    if a.size < 4:
        raise CalibrationError(f"rotation-zero scan has {a.size} points; at least 4 are needed")
    k = int(np.argmax(y))
    if y[k] <= 0:
        raise CalibrationError("no signal in the rotation-zero scan; is the beam on?")

    def model(x: np.ndarray, amp: float, a0: float, w: float) -> np.ndarray:
        return amp * np.exp(-0.5 * ((x - a0) / w) ** 2)

    p0 = [y[k], a[k], max(np.ptp(a) / 4.0, 1e-3)]
    try:
        popt, pcov = curve_fit(model, a, y, p0=p0, sigma=s, absolute_sigma=True, maxfev=10000)
    except (RuntimeError, ValueError) as e:
        raise CalibrationError(f"cannot fit the rotation-zero scan ({e})") from None
    resid = (y - model(a, *popt)) / s
    dof = max(1, a.size - 3)
    chi2r = float(resid @ resid / dof)
    a0 = float(popt[1])
    if not (a.min() <= a0 <= a.max()) or not np.all(np.isfinite(pcov)):
        raise CalibrationError(f"the fitted rotation zero {a0:.3f} deg lies outside the scan "
                               f"[{a.min():.3f}, {a.max():.3f}]; widen the scan range")
    err = math.sqrt(float(pcov[1, 1]) * max(1.0, chi2r))
    unc = math.hypot(err, resolution_deg / math.sqrt(12.0))
    return a0, unc, abs(float(popt[2])), chi2r


def beam_moments(radiance: np.ndarray, threshold: float, origin_px: tuple[int, int] = (0, 0),
                 variance: np.ndarray | None = None, significance: float = 5.0
                 ) -> tuple[tuple[float, float], tuple[float, float]]:
    """Centroid (x, y) and 1-sigma widths (x, y) in pixels.

    Only pixels at or above `threshold` x peak (and, with `variance`, `significance`
    standard deviations above zero) count: background noise would otherwise dominate
    the second moments. For a Gaussian beam a 1e-3 threshold biases the widths by -0.35 %.
    Pixel (i, j) of the array counts at (origin_x + i + 0.5, origin_y + j + 0.5).
    """
    r = np.asarray(radiance, dtype=np.float64)
    peak = float(np.nanmax(r))
    if not peak > 0:
        raise CalibrationError("no beam in the image (nothing above the dark level)")
    keep = np.isfinite(r) & (r >= threshold * peak)
    if variance is not None:
        keep &= r >= significance * np.sqrt(np.asarray(variance, dtype=np.float64))
    w = np.where(keep, r, 0.0)
    ys, xs = np.indices(r.shape, dtype=np.float64)
    xs += origin_px[0] + 0.5
    ys += origin_px[1] + 0.5
    tot = w.sum()
    cx, cy = float((w * xs).sum() / tot), float((w * ys).sum() / tot)
    wx = math.sqrt(max(0.0, float((w * (xs - cx) ** 2).sum() / tot)))
    wy = math.sqrt(max(0.0, float((w * (ys - cy) ** 2).sum() / tot)))
    return (cx, cy), (wx, wy)


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


class _Calibration:
    """One run: devices, settings, the output directory, a progress callback."""

    def __init__(self, stage: RotationStage, camera: Camera, changer: FilterChanger, out: Path,
                 settings: BeamCalibrationSettings, noise: NoiseModel,
                 progress: Callable[[str], None] | None) -> None:
        self.stage, self.camera, self.changer = stage, camera, changer
        self.out, self.s, self.noise = out, settings, noise
        self.progress = progress or (lambda msg: None)
        self.raw_files: list[str] = []
        self.scan_exposure_s: float | None = None

    def _save_raw(self, name: str, frames: Sequence[Frame]) -> None:
        (self.out / "raw").mkdir(exist_ok=True)
        write_frames(self.out / "raw" / f"{name}.npz", frames)
        self.raw_files.append(f"raw/{name}.npz")

    def _choose_exposure(self) -> float:
        """An exposure that puts the brightest pixel near the target fraction of the range."""
        lo, hi = self.camera.exposure_range_s
        n = self.noise
        span = n.saturation_adu - n.bias_adu
        t = min(max(1e-3, lo), hi)
        frames = []
        for _ in range(12):
            fr = self.camera.expose(t)
            frames.append(fr)
            peak = float(fr.data.max()) - n.bias_adu - n.dark_current_e_per_s * t / n.gain_e_per_adu
            if fr.data.max() >= n.saturation_adu:
                if t <= lo * (1 + 1e-9):
                    break
                t = max(lo, t / 10.0)
                continue
            if peak < 20.0 * n.read_noise_e / n.gain_e_per_adu:
                if t >= hi * (1 - 1e-9):
                    break
                t = min(hi, t * 30.0)
                continue
            t = min(hi, max(lo, t * self.s.target_peak_fraction * span / peak))
            break
        self._save_raw("exposure_search", frames)
        return t

    def scan(self) -> ScanResult:
        s = self.s
        rng = self.stage.allowed_range
        self.changer.select(s.filters[0])
        self.stage.move_to(min(max(180.0, rng.lo), rng.hi))
        t = self._choose_exposure()
        darks = acquire_darks(self.camera, [t], s.scan_darks)
        dark = np.mean([d.data.astype(np.float64) for d in darks], axis=0)
        t = float(darks[0].exposure_s)
        self.scan_exposure_s = t
        g = self.noise.gain_e_per_adu
        frames: list[Frame] = list(darks)
        pts: dict[float, tuple[float, float]] = {}

        def measure(angles: np.ndarray, label: str) -> None:
            for a in angles:
                a = float(a)
                if a < rng.lo or a > rng.hi:
                    continue
                self.stage.move_to(a)
                a_read = round(self.stage.angle(), 6)
                fr = self.camera.expose(t)
                frames.append(fr)
                if fr.data.max() >= self.noise.saturation_adu:
                    raise CalibrationError(
                        f"beam saturates the camera at {a_read:.3f} deg even at {t:g} s; "
                        "put a stronger neutral-density filter in the beam")
                e = g * (fr.data.astype(np.float64) - dark)
                npix = e.size
                var = (np.clip(e, 0, None).sum() + npix * (self.noise.frame_variance_e2(0.0, t)
                                                           + self.noise.frame_variance_e2(0.0, t) / s.scan_darks))
                pts[a_read] = (float(e.sum()) / t, math.sqrt(var) / t)
                self.progress(f"{label} scan {a_read:.3f} deg: {pts[a_read][0]:.4g} e-/s")

        coarse = 180.0 + np.arange(-s.coarse_half_range_deg, s.coarse_half_range_deg + 1e-9, s.coarse_step_deg)
        measure(coarse, "coarse")
        if not pts:
            raise CalibrationError(f"no scan angle near 180 deg inside the stage's allowed range "
                                   f"[{rng.lo:g}, {rng.hi:g}] deg")
        best = max(pts, key=lambda k: pts[k][0])
        if pts[best][0] <= 5.0 * pts[best][1]:
            raise CalibrationError("no beam seen near 180 deg; is the slab removed and the beam on?")
        fine = best + np.arange(-s.fine_half_range_deg, s.fine_half_range_deg + 1e-9, s.fine_step_deg)
        measure(fine, "fine")
        used = sorted(k for k in pts if abs(k - best) <= s.fine_half_range_deg + 1e-9)
        self._save_raw("rotation_scan", frames)
        ang = np.array(used)
        sig = np.array([pts[k][0] for k in used])
        err = np.array([pts[k][1] for k in used])
        a0, unc, width, chi2r = fit_rotation_zero(ang, sig, err, s.stage_resolution_deg)
        order = sorted(pts)
        return ScanResult([float(k) for k in order], [pts[k][0] for k in order], [pts[k][1] for k in order],
                          t, a0, unc, width, chi2r)

    def beam_image(self, filt: str) -> BeamMeasurement:
        s = self.s
        self.changer.select(filt)
        policy = s.bracket
        if policy.first_exposure_s is None and self.scan_exposure_s is not None:
            # start where the scan's exposure put the peak at ~target_peak_fraction of the
            # range (the bracket goes shorter by itself if a filter saturates there)
            policy = replace(policy, first_exposure_s=self.scan_exposure_s)
        light, status = acquire_bracket(self.camera, policy, self.noise)
        darks = acquire_darks(self.camera, [f.exposure_s for f in light], s.bracket.n_darks)
        self._save_raw(f"beam_{filt}", list(light) + list(darks))
        res = merge_hdr(np.stack([f.data for f in light]), [f.exposure_s for f in light],
                        MatchedDarks.from_frames(darks, self.noise), self.noise)
        roi = light[0].roi
        if not res.mask.all():
            raise CalibrationError(f"filter {filt}: the beam's peak stays saturated at the shortest exposure; "
                                   "put a stronger neutral-density filter in the beam")
        rad = res.radiance.astype(np.float64)
        (cx, cy), (wx, wy) = beam_moments(rad, s.moment_threshold, (roi.x, roi.y), res.variance)
        ys, xs = np.indices(rad.shape, dtype=np.float64)
        rr = np.hypot(xs + roi.x + 0.5 - cx, ys + roi.y + 0.5 - cy)
        power = float(rad[rr <= s.power_radius_widths * max(wx, wy, 1.0)].sum())
        self.progress(f"filter {filt}: centre ({cx:.2f}, {cy:.2f}) px, widths ({wx:.2f}, {wy:.2f}) px, "
                      f"power {power:.4g} e-/s")
        return BeamMeasurement(filt, rad, res.variance.astype(np.float64), (cx, cy), (wx, wy), power,
                               [float(f.exposure_s) for f in light], status.reason)


def calibrate_beam(stage: RotationStage, camera: Camera, changer: FilterChanger, out_dir: str | os.PathLike[str],
                   settings: BeamCalibrationSettings, operator: Operator, *,
                   devices: Mapping[str, str] | None = None, software: str = "",
                   progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run the beam calibration and write CALDIR; returns the calibration.yaml content.

    Raises:
        CalibrationError: bad settings or output directory (before anything moves), the
            operator declined, or no usable beam was seen.
    """
    unknown = [f for f in settings.filters if f not in changer.names()]
    if unknown:
        raise CalibrationError(f"unknown filter {unknown[0]!r}; the filter changer has {', '.join(changer.names())}")
    if not settings.filters:
        raise CalibrationError("no filters to calibrate")
    if not (settings.pixel_pitch_mm > 0 and math.isfinite(settings.pixel_pitch_mm)):
        raise CalibrationError(f"pixel pitch {settings.pixel_pitch_mm!r} mm must be > 0")
    rng = stage.allowed_range
    if not (rng.lo <= 180.0 + settings.coarse_half_range_deg and rng.hi >= 180.0 - settings.coarse_half_range_deg):
        raise CalibrationError(f"the stage's allowed range [{rng.lo:g}, {rng.hi:g}] deg does not reach 180 deg "
                               "(beam into the lens); widen stage.allowed_range_deg")
    out = check_output_dir(out_dir)
    noise = NoiseModel.from_sensor(camera.sensor)
    if not operator.ask("remove_slab", "Remove the slab from the holder (the beam will point straight into "
                                       "the lens) and confirm."):
        raise CalibrationError("the operator did not confirm that the slab is removed; nothing was measured")
    sensor = camera.sensor
    camera.set_roi(ROI(0, 0, sensor.width, sensor.height))
    camera.set_shutter(ShutterMode.NORMAL)
    run = _Calibration(stage, camera, changer, out, settings, noise, progress)
    scan = run.scan()
    run.progress(f"rotation zero {scan.zero_deg:.4f} +- {scan.uncertainty_deg:.4f} deg")
    stage.move_to(scan.zero_deg)
    beams = [run.beam_image(f) for f in settings.filters]

    pitch = settings.pixel_pitch_mm
    total = sum(b.power_e_per_s for b in beams)
    cx = sum(b.centroid_px[0] * b.power_e_per_s for b in beams) / total
    cy = sum(b.centroid_px[1] * b.power_e_per_s for b in beams) / total
    pmax = max(b.power_e_per_s for b in beams)
    filters: dict[str, Any] = {}
    for b in beams:
        half = max(16, math.ceil(settings.map_halfwidth_widths * max(b.width_px)))
        x0 = int(min(max(0, round(cx) - half), sensor.width - 1))
        y0 = int(min(max(0, round(cy) - half), sensor.height - 1))
        x1, y1 = min(sensor.width, x0 + 2 * half), min(sensor.height, y0 + 2 * half)
        name = f"beam_{b.filter}.exr"
        write_exr(out / name, {"radiance": b.radiance[y0:y1, x0:x1], "variance": b.variance[y0:y1, x0:x1]},
                  attributes={"filter": b.filter, "origin_px_x": x0, "origin_px_y": y0,
                              "pixel_pitch_mm": float(pitch), "units": "e-/s per unbinned pixel"},
                  meta={"origin_px": [x0, y0], "stage_angle_deg": scan.zero_deg, "exposures_s": b.exposures_s})
        filters[b.filter] = {
            "map": name,
            "origin_px": [x0, y0],
            "power_e_per_s": float(b.power_e_per_s),
            "relative_power": float(b.power_e_per_s / pmax),
            "centroid_mm": [float((b.centroid_px[0] - cx) * pitch), float(-(b.centroid_px[1] - cy) * pitch)],
            "width_mm": [float(b.width_px[0] * pitch), float(b.width_px[1] * pitch)],
            "exposures_s": b.exposures_s,
            "bracket": b.bracket_reason,
            "raw": f"raw/beam_{b.filter}.npz",
        }
    doc: dict[str, Any] = {
        "format": FORMAT,
        "created": _now(),
        "software": software,
        "devices": dict(devices or {}),
        "rotation_zero_deg": float(scan.zero_deg),
        "rotation_zero_uncertainty_deg": float(scan.uncertainty_deg),
        "pixel_pitch_mm": float(pitch),
        "beam": {"center_px": [float(cx), float(cy)], "filters": filters},
        "scan": {"filter": settings.filters[0], "exposure_s": scan.exposure_s,
                 "angles_deg": scan.angles_deg, "signal_e_per_s": scan.signal_e_per_s,
                 "sigma_e_per_s": scan.sigma_e_per_s, "acceptance_sigma_deg": scan.acceptance_sigma_deg,
                 "reduced_chi2": scan.reduced_chi2, "raw": "raw/rotation_scan.npz"},
        "dark": {"method": "matched darks (capture.bracket.acquire_darks) per exposure time",
                 "n_darks": settings.bracket.n_darks, "ccd_temp_c": float(camera.temperature())},
        "settings": {k: v for k, v in asdict(settings).items() if k != "bracket"} | {"bracket": settings.bracket.to_dict()},
        "raw_files": run.raw_files,
    }
    doc["settings"]["filters"] = list(settings.filters)
    if not operator.ask("mount_slab", "Mount the slab again and confirm."):
        run.progress("the operator did not confirm that the slab is mounted again")
    atomic_write_text(out / "calibration.yaml", yaml.safe_dump(doc, sort_keys=False))
    return doc
