"""Small synthetic sessions for the estimation tests and benchmarks.

A session (capture.session format) whose HDR stacks hold profiles rendered by the forward
model at known parameters, times a known scale, plus Poisson-like sensor noise, and a
calibration directory with a Gaussian beam map. Test data, not the simulated bench.

The rig configuration snapshot carries `camera.collection_sr` and `camera.calibration_nd`
chosen so that the calibrated scale (`estimate.loss.calibrated_scale`:
power_e_per_s / calibration_nd * pixel_area * collection_sr / beam map power) equals the `scale` the profiles
were multiplied by, unless `collection_sr_error` makes it deliberately wrong.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import yaml

from capture.exr_io import write_exr
from capture.hdr import HdrResult, NoiseModel
from capture.plan import CapturePlan, StackKey
from capture.session import Session
from drivers.interfaces import ROI, Frame, SensorInfo

SENSOR = SensorInfo("synthetic", 512, 512, 20.0, 1.5, 100.0, 10.0, 100000.0, 65535, 0.1)
PITCH_MM = 0.020 / 0.3
CENTER_PX = (256.3, 255.6)
PROFILE_ROW = 256
ROI_ROWS = (252, 8)
BEAM_POWER = 1.0e6          # e-/s through the calibration ND (calibration.yaml power_e_per_s)
CALIBRATION_ND = 1.0e-3


def beam_samples(beam_sigma_mm: float = 0.25, power: float = BEAM_POWER) -> tuple[np.ndarray, np.ndarray]:
    """(samples, frame) of the synthetic Gaussian beam on the 24 x 24 pixels around the axis.

    The true beam is the bilinear surface through `samples` (a Gaussian of `beam_sigma_mm`
    sampled at the pixel centres, e-/s x pixel area each); `frame` is what a camera records of
    it, its integral over each pixel (the kernel (1/8, 3/4, 1/8) per axis,
    `estimate.beam.map_from_pixel_image` undoes it). Both sum to `power`. Sessions render their
    truth with the samples and the estimator reads the frame, as on the rig."""
    n = 24
    x0 = round(CENTER_PX[0]) - n // 2
    y0 = round(CENTER_PX[1]) - n // 2
    jj, ii = np.mgrid[0:n, 0:n]
    xm = (x0 + ii + 0.5 - CENTER_PX[0]) * PITCH_MM
    ym = -(y0 + jj + 0.5 - CENTER_PX[1]) * PITCH_MM
    samples = np.exp(-(xm ** 2 + ym ** 2) / (2 * beam_sigma_mm ** 2))
    samples *= power / samples.sum()
    from estimate.beam import _PIXEL_OF_BILINEAR  # the kernel map_from_pixel_image takes out

    k = np.array(_PIXEL_OF_BILINEAR)
    frame = np.apply_along_axis(lambda r: np.convolve(r, k, mode="same"), 1, samples)
    frame = np.apply_along_axis(lambda c: np.convolve(c, k, mode="same"), 0, frame)
    return samples, frame * (power / frame.sum())


def write_calibration(caldir: Path, filters: Sequence[str], beam_sigma_mm: float = 0.25,
                      power: float = BEAM_POWER, rotation_zero_deg: float = 180.0) -> Path:
    """A calibration directory with a Gaussian beam frame per filter (e-/s per pixel, `beam_samples`)."""
    caldir.mkdir(parents=True, exist_ok=True)
    n = 24
    x0 = round(CENTER_PX[0]) - n // 2
    y0 = round(CENTER_PX[1]) - n // 2
    _, img = beam_samples(beam_sigma_mm, power)
    entries = {}
    for f in filters:
        write_exr(caldir / f"beam_{f}.exr", {"radiance": img, "variance": img * 0.01},
                  meta={"origin_px": [x0, y0]})
        entries[f] = {"map": f"beam_{f}.exr", "power_e_per_s": float(power), "relative_power": 1.0,
                      "centroid_mm": [0.0, 0.0], "width_mm": [beam_sigma_mm, beam_sigma_mm]}
    cal = {"format": "rig-calibration/1", "rotation_zero_deg": rotation_zero_deg, "rotation_zero_uncertainty_deg": 0.01,
           "pixel_pitch_mm": PITCH_MM, "beam": {"center_px": list(CENTER_PX), "filters": entries}}
    (caldir / "calibration.yaml").write_text(yaml.safe_dump(cal), encoding="utf-8")
    return caldir


def make_session(path: Path, truth: Mapping[str, Mapping[str, float]], *, angles: Sequence[float],
                 phase: str = "exp3", scale: float = 5.0e3, spp: int = 2048, seed: int = 0,
                 noise: bool = True, width: int = 512, skip: Sequence[str] = (),
                 calibration: bool = True, collection_sr_error: float = 1.0, lens_config: bool = True,
                 engine: str = "camera") -> Path:
    """Write a session whose channel f holds profiles of `truth[f]` (ForwardModel parameters),
    rendered by the forward model's `engine` (camera by default: not the estimator's).

    `skip` lists stack ids left pending; the configuration's collection_sr is the true one
    times `collection_sr_error` (`lens_config` False: no camera keys at all). Returns the
    session path.
    """
    from estimate.beam import BeamProfile
    from estimate.forward import ForwardModel
    from estimate.geometry import RigGeometry

    filters = tuple(truth)
    caldir = write_calibration(path.parent / (path.name + "_cal"), filters)
    plan = CapturePlan(angles_deg=tuple(float(a) for a in angles), filters=filters,
                       n_front=sum(1 for a in angles if a < 90))
    x0 = round(CENTER_PX[0]) - width // 2
    roi = {"x": x0, "y": ROI_ROWS[0], "width": width, "height": ROI_ROWS[1], "bin_x": 1, "bin_y": 1}
    geometry = {"thickness_mm": 1.0, "pixel_pitch_mm": PITCH_MM, "magnification": 0.3,
                "center_px": list(CENTER_PX), "profile_row": PROFILE_ROW, "roi": roi}
    rig_config: dict = {"filter": {"wavelengths_nm": {"r": 630.0, "g": 530.0, "b": 465.0}}}
    if lens_config:
        # The profiles are rendered with the calibration's beam map (total BEAM_POWER), so
        # scale = BEAM_POWER / nd * area * Omega / BEAM_POWER: Omega = scale nd / area (a
        # synthetic lens: with scale 2e5 this is no physical solid angle, only consistent).
        rig_config["camera"] = {"collection_sr": collection_sr_error * scale * CALIBRATION_ND / PITCH_MM ** 2,
                                "calibration_nd": CALIBRATION_ND}
    s = Session.create(path, plan=plan, frame_shape=(ROI_ROWS[1], width),
                       rig_config=rig_config,
                       devices={"stage": "synthetic", "camera": "synthetic", "filter": "synthetic"},
                       sensor=SENSOR, noise=NoiseModel.from_sensor(SENSOR), geometry=geometry,
                       calibration=caldir if calibration else None)
    rng = np.random.default_rng(seed)
    with s:
        for f in filters:
            # The truth's beam is the one the calibration frame recorded (`beam_samples`).
            img, _ = beam_samples()
            beam = BeamProfile.from_camera_image(
                img / PITCH_MM ** 2, PITCH_MM,
                (CENTER_PX[0] - 0.5 - (round(CENTER_PX[0]) - 12),
                 CENTER_PX[1] - 0.5 - (round(CENTER_PX[1]) - 12)))
            geo = RigGeometry(thickness_mm=1.0, magnification=0.3, image_center_px=CENTER_PX,
                              profile_row=PROFILE_ROW, profile_columns=(x0, x0 + width))
            fm = ForwardModel(geo, beam, phase=phase, engine=engine)
            prof = fm.render_profiles(dict(truth[f]), list(angles), spp=spp, seed=seed + 1000) * scale
            t_exp = 1.0  # s: the variance of an e-/s estimate from one exposure of t seconds
            for k, a in enumerate(angles):
                key = StackKey(k, f)
                if key.id in skip:
                    continue
                lam = np.clip(prof[k], 0, None)
                var = (lam * t_exp + SENSOR.read_noise_e ** 2) / t_exp ** 2
                row = lam + (rng.normal(0.0, np.sqrt(var)) if noise else 0.0)
                band = np.repeat(row[None, :], ROI_ROWS[1], axis=0).astype(np.float32)
                vband = np.repeat(var[None, :], ROI_ROWS[1], axis=0).astype(np.float32)
                frames = [Frame(np.zeros((ROI_ROWS[1], width), np.uint16), t_exp, False, -20.0, 0.0, t_exp,
                                ROI(x0, ROI_ROWS[0], width, ROI_ROWS[1]))]
                hdr = HdrResult(band, vband, np.ones(band.shape, bool), np.ones(band.shape, np.uint8))
                s.write_stack(key, frames=frames, hdr=hdr, info={"roi": roi})
    return path
