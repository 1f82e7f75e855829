"""The estimation problem of one colour channel, read from a session.

`load_problem(session_dir, channel)` extracts, for every captured stack of the channel, the
line of pixels through the scattering spot (the beam's row, `geometry.profile_row` of the
session manifest, else the calibrated beam centre), a window of `columns` pixels centred on
the beam's column, with the HDR radiance (e-/s per pixel) and its variance ((e-/s)^2), and
builds the `RigGeometry` and `BeamProfile` the forward model needs:

* pixel pitch in object space: `geometry.pixel_pitch_mm` (else the calibration's), times the
  ROI binning;
* image centre: the calibrated beam centre `center_px` (full unbinned sensor pixels, the
  rotation axis on the front face is imaged there at phi = 180 deg);
* beam: the calibration's beam map of this channel (`beam_<f>.exr`, radiance e-/s per
  unbinned pixel, window origin `origin_px`), converted to irradiance per mm^2.

World angles phi (the plan's angles) are what the forward model calls angles.
Shared by `rig estimate` and `rig diagnose`.
"""

from __future__ import annotations

import dataclasses
import math
import os
import zipfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from estimate.beam import BeamProfile, beam_support, map_from_pixel_image
from estimate.errors import DataError
from estimate.extensions.base import BeamFill
from estimate.extensions.lens_blur import TRUNCATION_PX as LENS_BLUR_RADIUS
from estimate.geometry import RigGeometry

__all__ = ["DEFAULT_COLUMNS", "Y_SHAPE_MAX", "Y_SHAPE_SMOOTH_PX", "Problem", "load_problem", "merge_fill_from_rows",
           "recorded_light_paths",
           "session_channels", "y_shape_from_rows"]

#: Default width of the profile window (pixels of the ROI, i.e. binned pixels).
DEFAULT_COLUMNS = 256
#: Box width (pixels along x) over which the rows are averaged before their ratio is taken
#: (`y_shape_from_rows`): the y-shape changes slowly along x, pixel noise does not.
Y_SHAPE_SMOOTH_PX = 9
#: Largest y-shape value kept: a row far brighter than the profile row is a defect (a hot
#: column, a reflection) or noise over a dark profile pixel, not the spot's shape.
Y_SHAPE_MAX = 4.0


def y_shape_from_rows(rows: np.ndarray, usable: np.ndarray, j: int, columns: tuple[int, int],
                      radius: int = LENS_BLUR_RADIUS) -> np.ndarray:
    """h(x, dy) = I(x, j + dy) / I(x, j) of one stack, dy = -radius..radius.

    Args:
        rows: the stack's radiance (rows, columns of the ROI), e-/s.
        usable: bool, same shape: measured pixels (finite variance, mask set).
        j: the profile row's index in `rows`.
        columns: [c0, c1) of the profile window in `rows`.
        radius: largest |dy| (the lens blur's truncation).

    Each row and the profile row are averaged over `Y_SHAPE_SMOOTH_PX` usable pixels along x
    (negative noise clipped at 0) before the ratio; where the profile row's average is not
    positive, h = 1 (nothing known: the line-spread function's assumption). Rows beyond the
    recorded band continue the decay of the band's outermost rows on that side (never
    growing; a side of fewer than 7 rows repeats its outermost row, so a single-row
    recording gives h = 1, the LSF). Repeating the outermost row, as before session 64,
    made the spot's halo as wide as the whole +-64 rows beyond a 32-row band: on the light
    bench's lens_blur-2 (2.5 px + 5 %) the true model's reduced chi^2 at the noise floor was
    3.57 with it, 2.40 with the decay continued. Values are clipped to [0, `Y_SHAPE_MAX`];
    h(x, 0) = 1.
    """
    c0, c1 = columns
    n_rows = rows.shape[0]
    k = np.ones(Y_SHAPE_SMOOTH_PX)

    def smooth(r: int) -> np.ndarray:
        ok = usable[r, c0:c1] & np.isfinite(rows[r, c0:c1])
        val = np.where(ok, np.clip(rows[r, c0:c1], 0.0, None), 0.0)
        num = np.convolve(val, k, mode="same")
        den = np.convolve(ok.astype(np.float64), k, mode="same")
        return np.where(den > 0, num / np.maximum(den, 1.0), np.nan)

    base = smooth(j)
    out = np.ones((2 * radius + 1, c1 - c0))
    lo, hi = max(0, j - radius), min(n_rows - 1, j + radius)
    for r in range(lo, hi + 1):
        if r == j:
            continue
        with np.errstate(invalid="ignore", divide="ignore"):
            h = smooth(r) / base
        out[r - j + radius] = np.clip(np.where(np.isfinite(h) & (base > 0), h, 1.0), 0.0, Y_SHAPE_MAX)
    for edge, inward, beyond in ((lo - j + radius, 1, range(lo - j + radius - 1, -1, -1)),
                                 (hi - j + radius, -1, range(hi - j + radius + 1, 2 * radius + 1))):
        out[list(beyond)] = _beyond_the_band(out, edge, inward, len(beyond))
    return out


#: Rows averaged at the band's edge, and how far inside the second average lies, for the
#: decay `_beyond_the_band` continues.
_EDGE_ROWS, _EDGE_SPAN = 3, 4


def _beyond_the_band(h: np.ndarray, edge: int, inward: int, n: int) -> np.ndarray:
    """h over the n rows beyond the recorded band, outward from row `edge`: the geometric
    decay of the band's outermost rows continued, never growing (per column, the mean of
    the `_EDGE_ROWS` outermost rows against the same `_EDGE_SPAN` rows further in). A side
    too short for that (a band of a few rows) repeats its outermost row."""
    if n == 0:
        return np.empty((0, h.shape[1]))
    if abs(edge - (h.shape[0] - 1) // 2) < _EDGE_SPAN + _EDGE_ROWS:
        return np.repeat(h[edge][None], n, axis=0)
    outer = h[[edge + inward * k for k in range(_EDGE_ROWS)]].mean(axis=0)
    inner = h[[edge + inward * (k + _EDGE_SPAN) for k in range(_EDGE_ROWS)]].mean(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.clip(np.where(inner > 0, outer / inner, 0.0), 0.0, 1.0) ** (1.0 / _EDGE_SPAN)
    return h[edge][None] * ratio[None] ** np.arange(1, n + 1)[:, None]


def merge_fill_from_rows(rows: np.ndarray, j: int, columns: tuple[int, int], exposures_s: Sequence[float],
                         noise: Any, full_well_e: float, *, bin_px: int = 1, bloom_rows: int = 2,
                         bloom_cols: int = 0, n_valid: np.ndarray | None = None) -> np.ndarray:
    """g(x): the HDR merge's mean squared fill of the well at each profile pixel of one stack.

    The merge (`capture.hdr.merge_hdr`) keeps the exposures whose raw value stays below the
    saturation level and outside a bloom's reach, and averages them with inverse-variance
    weights w_i = t_i^2 / var_i. A response that compresses the charge x by c (x / FW)^2
    then leaves the merged radiance at L (1 - c g), g = sum_i w_i (L t_i / FW)^2 / sum_i w_i
    (`estimate.extensions.sensor_nonlinearity`). The merge's choices are replayed here from
    the merged radiance itself, which stands in for the true one (off by the compression and
    the noise; the fill it gives is the merged radiance's, which the extension converts:
    `estimate.extensions.sensor_nonlinearity.true_fill`), unless the stack records how many
    exposures the merge kept (`n_valid`): those are its shortest, validity falling with the
    exposure time, and that record is exact where the replay is not (a strongly compressed
    well reads below the level its uncompressed prediction crosses).

    Args:
        rows: the stack's radiance (rows, columns of the ROI), e-/s per (binned) pixel.
        j: the profile row's index in `rows`.
        columns: [c0, c1) of the profile window in `rows`.
        exposures_s: the bracket's exposure times (s).
        noise: the session's `capture.hdr.NoiseModel` (gain, bias, read noise, dark
            current, saturation level).
        full_well_e: the sensor's full well (electrons per unbinned pixel).
        bin_px: unbinned pixels per binned pixel (the charge is taken as even over them).
        bloom_rows, bloom_cols: the merge's bloom reach (`capture.hdr.MergeOptions`).
        n_valid: the stack's `n_valid` channel (same shape as `rows`), or None to replay.

    Returns g over the profile columns, shape (c1 - c0,); 0 where no exposure was kept.
    """
    from capture.hdr import saturation_mask

    c0, c1 = columns
    lum = np.clip(np.nan_to_num(np.asarray(rows, dtype=np.float64), nan=0.0, posinf=0.0), 0.0, None)
    t = np.asarray(exposures_s, dtype=np.float64)
    gain = float(noise.gain_e_per_adu)
    dark = float(noise.dark_current_e_per_s) * bin_px
    if n_valid is not None:
        rank = np.argsort(np.argsort(t, kind="stable"), kind="stable")   # 0 = the shortest exposure
        kept = rank[:, None] < np.rint(np.asarray(n_valid, dtype=np.float64)[j, c0:c1])[None, :]
    else:
        # The raw level each exposure would read (uncompressed: the compression is a few percent).
        raw = (lum[None] * t[:, None, None] + dark * t[:, None, None]) / gain + float(noise.bias_adu)
        kept = ~saturation_mask(raw, float(noise.saturation_adu), bloom_rows=bloom_rows, bloom_cols=bloom_cols)
        kept = kept[:, j, c0:c1]
    lj = lum[j, c0:c1]
    var = noise.frame_variance_e2(lj[None] * t[:, None], t[:, None])   # the merge's own variance model
    w = np.where(kept, t[:, None] ** 2 / var, 0.0)
    fill = (lj[None] * t[:, None] / (bin_px * float(full_well_e))) ** 2
    den = w.sum(axis=0)
    return np.where(den > 0, (w * fill).sum(axis=0) / np.where(den > 0, den, 1.0), 0.0)


@dataclass
class Problem:
    """Measured profiles of one channel and the rig model to explain them.

    Attributes:
        angles_deg: world angles phi of the stacks used (degrees), shape (N,).
        x_mm: world x of the profile pixels' centres (mm), shape (W,).
        measured: radiance (e-/s per pixel), shape (N, W).
        variance: its variance ((e-/s)^2), shape (N, W); inf where unmeasured.
        geometry: rig geometry whose profile window is exactly these pixels (in the
            possibly binned pixel grid of the stacks).
        beam: calibrated beam map of this channel.
        channel: filter name.
        wavelength_nm: centre wavelength of the filter (None if the rig config lacks it).
        valid: bool (N, W): pixels measured (finite variance, mask 1) to use in a fit.
        stack_ids: the stack id of each row.
        session_path: the session directory.
        missing: stack ids of the channel that were missing or corrupt (allow_partial only).
        angle_correction_deg: added to the recorded angles of a session captured before
            capture applied the calibrated rotation zero (its plan has no stage_offset_deg):
            180 - rotation_zero_deg; 0 otherwise.
        y_shape: the recording's shape across the rows around the profile row, shape
            (N, 2 TRUNCATION_PX + 1, W): h(x, dy) = I(x, row + dy) / I(x, row) at
            dy = -TRUNCATION_PX..TRUNCATION_PX (`y_shape_from_rows`), for the lens blur of
            profile renders (`estimate.extensions.lens_blur`); None = unknown (h = 1).
        merge_fill: the HDR merge's mean squared fill of the well per profile pixel, shape
            (N, W) (`merge_fill_from_rows`), for the sensor compression of profile renders;
            None = unknown (a stack without its bracket or the sensor's full well).
        beam_fill: the beam calibration frame's power shares, merge fills and pixels
            (`_beam_fill`), for the sensor compression of the calibrated power and of the
            map's shape; None = unknown.
        recording_paths: light paths per image behind the profile row's frozen Monte Carlo
            noise, when the simulated camera declared a light-engine render
            (`recorded_light_paths`); None = no such noise (a real camera) or undeclared.
    """

    angles_deg: np.ndarray
    x_mm: np.ndarray
    measured: np.ndarray
    variance: np.ndarray
    geometry: RigGeometry
    beam: BeamProfile
    channel: str
    wavelength_nm: float | None
    valid: np.ndarray = field(default=None)  # type: ignore[assignment, arg-type]  # set in __post_init__
    stack_ids: list[str] = field(default_factory=list)
    session_path: str = ""
    missing: list[str] = field(default_factory=list)
    angle_correction_deg: float = 0.0
    y_shape: np.ndarray | None = None
    merge_fill: np.ndarray | None = None
    beam_fill: BeamFill | None = None
    recording_paths: int | None = None

    def __post_init__(self) -> None:
        if self.valid is None:
            self.valid = np.isfinite(self.variance) & np.isfinite(self.measured)

    def y_shapes(self) -> dict[float, np.ndarray]:
        """`y_shape` per angle (degrees -> (2 TRUNCATION_PX + 1, W)); empty when unknown.
        What `estimate.forward.ForwardModel(profile_y_shape=...)` takes."""
        if self.y_shape is None:
            return {}
        return {float(a): self.y_shape[i] for i, a in enumerate(self.angles_deg)}

    def merge_fills(self) -> dict[float, np.ndarray]:
        """`merge_fill` per angle (degrees -> (W,)); empty when unknown. What
        `estimate.forward.ForwardModel(profile_merge_fill=...)` takes."""
        if self.merge_fill is None:
            return {}
        return {float(a): self.merge_fill[i] for i, a in enumerate(self.angles_deg)}

    @property
    def n_angles(self) -> int:
        return int(self.measured.shape[0])

    @property
    def n_px(self) -> int:
        return int(self.measured.shape[1])

    def subset(self, angle_indices: Sequence[int]) -> Problem:
        """The same problem restricted to some angles (for diagnosis / cross-validation)."""
        idx = list(angle_indices)
        return Problem(self.angles_deg[idx], self.x_mm, self.measured[idx], self.variance[idx],
                       self.geometry, self.beam, self.channel, self.wavelength_nm,
                       self.valid[idx], [self.stack_ids[i] for i in idx], self.session_path,
                       list(self.missing), self.angle_correction_deg,
                       None if self.y_shape is None else self.y_shape[idx],
                       None if self.merge_fill is None else self.merge_fill[idx], self.beam_fill,
                       self.recording_paths)


def _merge_fills(session: Any, sensor: Any, bands: Sequence[tuple[np.ndarray, np.ndarray, int]],
                 brackets: Sequence[Any], merges: Sequence[dict[str, Any]],
                 kept_counts: Sequence[np.ndarray | None], columns: tuple[int, int],
                 bin_px: int) -> np.ndarray | None:
    """`merge_fill_from_rows` of every stack, (N, W); None when the session lacks what it
    needs (a bracket record, the noise model, the sensor's full well)."""
    noise = session.noise_model()
    full_well = getattr(sensor, "full_well_e", None)
    if noise is None or not full_well or any(not b for b in brackets):
        return None

    def merged_with(m: dict[str, Any]) -> Any:
        # The level the merge itself saturated at, where the stack records it (a well that
        # clipped below the noise model's level: `capture.hdr.plateau_saturation_adu`).
        level = m.get("saturation_adu")
        return noise if level is None else dataclasses.replace(noise, saturation_adu=float(level))

    try:
        return np.stack([merge_fill_from_rows(rad, j, columns, [float(t) for t in b], merged_with(m),
                                              float(full_well), bin_px=bin_px, bloom_rows=int(m.get("bloom_rows", 2)),
                                              bloom_cols=int(m.get("bloom_cols", 0)), n_valid=n)
                         for (rad, _, j), b, m, n in zip(bands, brackets, merges, kept_counts)])
    except (TypeError, ValueError, IndexError):
        return None   # a malformed bracket record or n_valid channel: the full-well form


def session_channels(session_dir: str | os.PathLike[str]) -> list[str]:
    """The filter names of a session's plan."""
    from capture.errors import SessionError
    from capture.session import Session

    try:
        s = Session.open(session_dir)
    except SessionError as e:
        raise DataError(str(e)) from None
    return list(s.plan.filters)


def _pair(v: Any, name: str) -> tuple[float, float]:
    try:
        a, b = (float(x) for x in v)
    except (TypeError, ValueError):
        raise DataError(f"{name}={v!r} is not a pair of numbers") from None
    return a, b


def _beam_origin(img: Any, entry: dict[str, Any], path: Path) -> tuple[float, float]:
    """Full-sensor pixel of the beam map's sample [0, 0] (attribute, metadata or YAML)."""
    for src in (img.attributes, img.meta, entry):
        if "origin_px" in src:
            return _pair(src["origin_px"], f"{path.name} origin_px")
        if "origin_px_x" in src and "origin_px_y" in src:
            return float(src["origin_px_x"]), float(src["origin_px_y"])
    raise DataError(f"beam map {path} does not say its origin_px")


def _beam_kept_counts(raw_path: Path, origin_px: tuple[float, float], shape: tuple[int, int],
                      noise: Any) -> tuple[np.ndarray, float] | None:
    """How many exposures the beam calibration's merge kept at each pixel of its map, and
    the level it saturated at: its saturation and bloom masks (`capture.hdr.merge_hdr`'s,
    plateau included) run again on the light frames the calibration keeps (`raw/`), cropped
    to the map. None when those frames are missing, unreadable or do not cover the map."""
    from capture.exr_io import read_frames
    from capture.hdr import plateau_saturation_adu, saturation_mask

    try:
        light = [f for f in read_frames(raw_path) if not f.dark]
    except (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile):
        return None
    if not light or len({f.data.shape for f in light}) != 1:
        return None
    stack = np.stack([f.data for f in light])
    level = plateau_saturation_adu(stack, noise)
    level = float(noise.saturation_adu if level is None else level)
    # The merge's default bloom reach; the calibration does not change it (`calibrate.beam`).
    n_valid = (~saturation_mask(stack, level)).sum(axis=0)
    roi = light[0].roi
    y0, x0 = int(round(origin_px[1])) - roi.y, int(round(origin_px[0])) - roi.x
    if y0 < 0 or x0 < 0 or y0 + shape[0] > n_valid.shape[0] or x0 + shape[1] > n_valid.shape[1]:
        return None
    return n_valid[y0:y0 + shape[0], x0:x0 + shape[1]], level


def _beam_fill(noise: Any, sensor: Any, pixel_image: np.ndarray, exposures_s: Any,
               kept: tuple[np.ndarray, float] | None,
               to_profile: Callable[[np.ndarray], BeamProfile] | None = None) -> BeamFill | None:
    """The beam calibration frame's power shares and merge fills (`BeamFill`): each pixel's
    share of the map's read power, and `merge_fill_from_rows` over the map's rows, from the
    exposures the calibration's merge kept there (`_beam_kept_counts`) or, without its
    frames, replayed from the map and its bracket (an uncompressed prediction, which keeps
    too few exposures where the compression pulled a sample below the saturation level:
    0.4 % short of the true power at c = 0.06 in `tests/test_extensions.py`). The
    calibration's frames are unbinned (`calibrate.beam`). `noise`: the session's noise model.
    None without the bracket, the noise model or the sensor's full well: the calibrated
    power is then taken as read."""
    full_well = getattr(sensor, "full_well_e", None)
    total = float(pixel_image.sum())
    try:
        t = [float(x) for x in exposures_s]
    except (TypeError, ValueError):
        return None
    if noise is None or not full_well or not t or not total > 0:
        return None
    n_valid = None
    if kept is not None:
        n_valid, level = kept
        noise = dataclasses.replace(noise, saturation_adu=level)
    cols = (0, pixel_image.shape[1])
    fill = np.stack([merge_fill_from_rows(pixel_image, j, cols, t, noise, float(full_well), n_valid=n_valid)
                     for j in range(pixel_image.shape[0])])
    lit = pixel_image > 0
    return BeamFill(weights=pixel_image[lit] / total, fill=fill[lit], pixels=pixel_image, fill_map=fill,
                    to_profile=to_profile, source="replayed" if kept is None else "kept frames")


def _load_beam(session: Any, cal: dict[str, Any], channel: str, pitch_mm: float,
               center_px: tuple[float, float], sensor: Any = None) -> tuple[BeamProfile, BeamFill | None]:
    from capture.exr_io import read_exr

    filters = ((cal.get("beam") or {}).get("filters") or {})
    entry = filters.get(channel)
    if not isinstance(entry, dict) or "map" not in entry:
        raise DataError(f"the calibration of {session.path} has no beam map for channel {channel!r}")
    path = Path(session.calibration_dir) / str(entry["map"])
    if not path.is_file():
        raise DataError(f"beam map {path} is missing; copy it back from the calibration rig calibrate-beam wrote")
    try:
        img = read_exr(path)
        rad = np.asarray(img["radiance"], dtype=np.float64)
    except (OSError, KeyError, ValueError, RuntimeError) as e:
        raise DataError(f"cannot read beam map {path}: {str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
    x0, y0 = _beam_origin(img, entry, path)
    if not np.all(np.isfinite(rad)):
        raise DataError(f"beam map {path} holds NaN or infinite radiance")
    # Dark-subtracted noise can dip below zero off the beam; the irradiance cannot. Off the
    # beam's support the frame is dark noise, whose clipped positive half would light the
    # slab as a faint wide halo: zero there (estimate.beam.beam_support). The frame is
    # pixel-integrated and the map is read bilinearly: undo both (estimate.beam).
    try:
        var = np.asarray(img["variance"], dtype=np.float64)
    except KeyError:
        var = None
    if var is not None and var.shape != rad.shape:
        var = None
    pixels = np.where(beam_support(rad, var), np.clip(rad, 0.0, None), 0.0)
    exposures = entry.get("exposures_s", (getattr(img, "meta", None) or {}).get("exposures_s"))
    cx, cy = center_px
    # Pixel centre (i, j) is at x = (i + 0.5 - cx) p, y = -(j + 0.5 - cy) p (estimate.geometry).
    axis = (cx - 0.5 - x0, cy - 0.5 - y0)

    def to_profile(pix: np.ndarray) -> BeamProfile:
        return BeamProfile.from_camera_image(map_from_pixel_image(pix) / pitch_mm ** 2, pitch_mm, axis)

    fill = None
    if sensor is not None:
        noise = session.noise_model()
        kept = None
        if entry.get("raw") and noise is not None:
            kept = _beam_kept_counts(Path(session.calibration_dir) / str(entry["raw"]), (x0, y0), pixels.shape, noise)
        fill = _beam_fill(noise, sensor, pixels, exposures, kept, to_profile)
    return to_profile(pixels), fill


def load_problem(session_dir: str | os.PathLike[str], channel: str, columns: int | None = None, *,
                 allow_partial: bool = False) -> Problem:
    """Read the estimation problem of one channel from a session.

    Args:
        session_dir: the session directory.
        channel: filter name (e.g. "r").
        columns: width of the profile window in (binned) pixels, centred on the beam
            column; None = DEFAULT_COLUMNS (clipped to the ROI).
        allow_partial: proceed with the stacks that are there when some are missing
            (pending or failing their checksum); otherwise refuse.

    Raises:
        DataError (one line): the session cannot be opened, unknown channel, no
            calibration, missing or corrupt stacks (named), NaN or negative radiance
            (stack and pixel named), too few usable stacks.
    """
    from capture.errors import SessionError
    from capture.session import Session

    try:
        s = Session.open(session_dir)
    except SessionError as e:
        raise DataError(str(e)) from None
    filters = list(s.plan.filters)
    if channel not in filters:
        raise DataError(f"unknown channel {channel!r}; the session has {', '.join(filters)}")
    if s.calibration_dir is None:
        raise DataError(f"{s.path} has no beam calibration; capture with --calibration CALDIR")
    try:
        cal = s.load_calibration()
    except SessionError as e:
        raise DataError(str(e)) from None

    # Stacks: done and sound, else missing.
    problems = s.verify()
    # file -> what is wrong with it, as `Session.verify` words it ("is missing", "is corrupt
    # (checksum mismatch)", "is unreadable: ...")
    bad_files = {p.split(" ", 1)[0]: p.split(" ", 1)[1] if " " in p else "is damaged" for p in problems}
    cal_bad = [p for p in problems if p.startswith("calibration/")]
    if cal_bad:
        raise DataError(f"calibration of {s.path} is damaged: {cal_bad[0]}; copy it back from the folder "
                        "rig calibrate-beam wrote")
    recs = [r for r in s.stacks() if r.key.filter == channel]
    missing: list[str] = []
    usable = []
    for r in recs:
        if not r.done:
            missing.append(f"{r.id} (not captured)")
        elif bad := [f.file for f in r.files.values() if f.file.startswith("hdr/") and f.file in bad_files]:
            missing.append(f"{r.id} ({bad[0]} {bad_files[bad[0]]})")
        else:
            usable.append(r)
    if missing and not allow_partial:
        raise DataError(f"channel {channel!r}: {len(missing)} of {len(recs)} stacks missing or corrupt: "
                        f"{', '.join(missing)}; use --allow-partial to estimate from the rest")
    if len(usable) < 2:
        raise DataError(f"channel {channel!r}: only {len(usable)} usable stack(s); need at least 2")

    # Sessions captured before capture commanded world angle + (rotation zero - 180) (plan
    # without stage_offset_deg) recorded the stage angle: the beam met the slab at
    # angle + 180 - rotation_zero_deg.
    from capture.plan import MAX_STAGE_OFFSET_DEG

    correction = 0.0
    zero = cal.get("rotation_zero_deg")
    if "stage_offset_deg" not in (s.manifest.get("plan") or {}) and isinstance(zero, (int, float)) \
            and math.isfinite(zero) and abs(zero - 180.0) <= MAX_STAGE_OFFSET_DEG:
        correction = 180.0 - float(zero)
    geo = dict(s.geometry() or {})
    beam_cal = cal.get("beam") or {}
    sensor = s.sensor()
    sensor_w = int(getattr(sensor, "width", 0) or 512)
    sensor_h = int(getattr(sensor, "height", 0) or 512)
    pixel_um = float(getattr(sensor, "pixel_size_um", 0) or 20.0)
    pitch = geo.get("pixel_pitch_mm", cal.get("pixel_pitch_mm"))
    if pitch is None:
        raise DataError(f"{s.path}: neither the session geometry nor the calibration gives pixel_pitch_mm")
    pitch = float(pitch)
    # CONTRACTS.md names `center_px` / `roi`; `rig capture` also writes `beam_center_px` / `camera_roi`.
    center = geo.get("center_px", geo.get("beam_center_px", beam_cal.get("center_px")))
    cx, cy = _pair(center, "center_px") if center is not None else (sensor_w / 2.0, sensor_h / 2.0)
    row = int(geo["profile_row"]) if geo.get("profile_row") is not None else round(cy)
    thickness = float(geo.get("thickness_mm", 1.0))

    beam, beam_fill = _load_beam(s, cal, channel, pitch, (cx, cy), sensor)

    # Read the stacks: one row each.
    angles: list[float] = []
    meas_rows: list[np.ndarray] = []
    var_rows: list[np.ndarray] = []
    mask_rows: list[np.ndarray] = []
    bands: list[tuple[np.ndarray, np.ndarray, int]] = []   # (radiance, usable, profile row index)
    brackets: list[Any] = []                                # exposure times of each stack's bracket
    merges: list[dict[str, Any]] = []                       # each stack's merge options
    kept_counts: list[np.ndarray | None] = []              # each stack's n_valid channel, if recorded
    ids: list[str] = []
    roi0: dict[str, int] | None = None
    for r in usable:
        try:
            img = s.load_hdr(r.key)
            rad = np.asarray(img["radiance"], dtype=np.float64)
            var = np.asarray(img["variance"], dtype=np.float64)
        except (SessionError, OSError, KeyError, ValueError, RuntimeError) as e:
            if not allow_partial:
                raise DataError(f"stack {r.id} of {s.path} is unreadable ({type(e).__name__}); "
                                "use --allow-partial to estimate from the rest") from None
            missing.append(f"{r.id} (unreadable)")
            continue
        mask = np.asarray(img.channels.get("mask", np.ones_like(rad)), dtype=np.float64)
        roi = dict(r.info.get("roi") or geo.get("roi") or geo.get("camera_roi") or {})
        roi = {"x": int(roi.get("x", 0)), "y": int(roi.get("y", 0)), "bin_x": int(roi.get("bin_x", 1)),
               "bin_y": int(roi.get("bin_y", 1))}
        if roi0 is None:
            roi0 = roi
        elif roi != roi0:
            raise DataError(f"stack {r.id} has ROI {roi}, other stacks {roi0}; one window per channel is needed")
        j = (row - roi["y"]) // roi["bin_y"]
        if not 0 <= j < rad.shape[0]:
            raise DataError(f"stack {r.id}: profile row {row} lies outside its ROI rows "
                            f"{roi['y']}..{roi['y'] + rad.shape[0] * roi['bin_y'] - 1}")
        angles.append(float(r.angle_deg) + correction)
        meas_rows.append(rad[j])
        var_rows.append(var[j])
        mask_rows.append(mask[j])
        bands.append((rad, np.isfinite(var) & (var > 0) & (mask > 0.5), j))
        kept_counts.append(img.channels.get("n_valid"))
        brackets.append((r.info.get("bracket") or {}).get("exposures_s"))
        merges.append(dict(r.info.get("merge") or {}))
        ids.append(r.id)
    if len(ids) < 2 or roi0 is None:
        raise DataError(f"channel {channel!r}: only {len(ids)} readable stack(s); need at least 2")

    # The profile window in the stacks' (binned) pixel grid.
    bx, by = roi0["bin_x"], roi0["bin_y"]
    n_cols = meas_rows[0].shape[0]
    width = min(int(columns or DEFAULT_COLUMNS), n_cols)
    if width < 2:
        raise DataError(f"columns={columns!r}: need at least 2 pixels")
    centre_col = (cx - roi0["x"]) / bx            # continuous ROI column of the beam axis
    if not 0 <= centre_col < n_cols:
        raise DataError(f"the beam centre column {cx:g} lies outside the stacks' ROI columns "
                        f"{roi0['x']}..{roi0['x'] + n_cols * bx - 1}")
    c0 = round(centre_col - width / 2.0)
    c0 = max(0, min(n_cols - width, c0))
    c1 = c0 + width
    measured = np.stack([m[c0:c1] for m in meas_rows])
    variance = np.stack([v[c0:c1] for v in var_rows])
    mask = np.stack([m[c0:c1] for m in mask_rows])

    bad = ~np.isfinite(measured)
    if bad.any():
        i, k = map(int, np.argwhere(bad)[0])
        raise DataError(f"stack {ids[i]}: radiance is NaN or infinite at column {roi0['x'] + (c0 + k) * bx} "
                        f"(row {row}); {int(bad.sum())} such pixel(s)")
    # A dark-subtracted pixel may dip below zero by its noise; clearly negative is broken data.
    sd = np.sqrt(np.where(np.isfinite(variance) & (variance >= 0), variance, 0.0))
    neg = measured < -5.0 * sd - 1e-9
    if neg.any():
        i, k = map(int, np.argwhere(neg)[0])
        raise DataError(f"stack {ids[i]}: negative radiance {measured[i, k]:.4g} e-/s at column "
                        f"{roi0['x'] + (c0 + k) * bx} (row {row}); {int(neg.sum())} such pixel(s)")
    if np.any(np.isnan(variance)) or np.any(variance < 0):
        i, k = map(int, np.argwhere(np.isnan(variance) | (variance < 0))[0])
        raise DataError(f"stack {ids[i]}: variance NaN or negative at column {roi0['x'] + (c0 + k) * bx}")
    valid = np.isfinite(variance) & (mask > 0.5) & (variance > 0)
    y_shape = np.stack([y_shape_from_rows(b_rad, b_ok, b_j, (c0, c1)) for b_rad, b_ok, b_j in bands])
    merge_fill = _merge_fills(s, sensor, bands, brackets, merges, kept_counts, (c0, c1),
                              roi0["bin_x"] * roi0["bin_y"])

    # Geometry in the stacks' pixel grid: a binned pixel is one bigger pixel; the ROI
    # origin shifts the continuous centre coordinate.
    sensor_cols = max(n_cols + (roi0["x"] // bx), math.ceil(sensor_w / bx))
    sensor_rows = math.ceil(sensor_h / by)
    g_cx = (cx - roi0["x"]) / bx + roi0["x"] / bx
    g_cy = cy / by
    magnification = pixel_um * 1e-3 / pitch
    geometry = RigGeometry(
        thickness_mm=thickness,
        sensor_px=(sensor_cols, sensor_rows),
        pixel_um=pixel_um * bx,
        magnification=magnification,
        image_center_px=(g_cx, g_cy),
        profile_row=min(sensor_rows - 1, row // by),
        profile_columns=(roi0["x"] // bx + c0, roi0["x"] // bx + c1),
    )
    x_mm = np.asarray(geometry.pixel_x_mm(geometry.profile_window()))
    wl = None
    try:
        wl_map = (s.rig_config.get("filter") or {}).get("wavelengths_nm") or {}
        if channel in wl_map:
            wl = float(wl_map[channel])
    except AttributeError:
        wl = None
    order = np.argsort(angles, kind="stable")
    return Problem(
        angles_deg=np.asarray(angles)[order], x_mm=x_mm, measured=measured[order],
        variance=variance[order], geometry=geometry, beam=beam, channel=channel, wavelength_nm=wl,
        valid=valid[order], stack_ids=[ids[i] for i in order], session_path=str(s.path), missing=missing,
        angle_correction_deg=correction, y_shape=y_shape[order],
        merge_fill=None if merge_fill is None else merge_fill[order], beam_fill=beam_fill,
        recording_paths=recorded_light_paths(s.render_noise(), row, by),
    )


def recorded_light_paths(declared: Mapping[str, Any] | None, row: int, bin_y: int = 1) -> int | None:
    """Light paths per image of the render tier that holds the profile row (unbinned sensor
    `row`, the `bin_y` rows from it), from a session's declared render noise
    (`capture.session.Session.render_noise`); None unless a light-engine render covers
    them all (the camera engine's noise is white: the noise floor measures it)."""
    if not declared or declared.get("engine") != "light":
        return None
    r0, r1 = row - row % max(1, bin_y), row - row % max(1, bin_y) + max(1, bin_y)
    for t in declared.get("tiers") or []:
        try:
            lo, hi = (int(v) for v in t["rows"])
            paths = int(t["paths_per_image"])
        except (KeyError, TypeError, ValueError):
            continue
        if lo <= r0 and r1 <= hi and paths > 0:
            return paths
    return None
