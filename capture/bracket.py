"""Automatic exposure bracket and the matched dark frames.

Policy (one stack = one stage angle and one filter):

1. Expose ``first_exposure_s`` (short first, so the beam's peak is unlikely
   to saturate). The *profile rows* are the band of ``2*profile_halfwidth_rows+1``
   rows around ``profile_row`` (default: the row with the largest sum in the
   first frame, i.e. the row through the scattering spot).
2. After every exposure the frames so far are merged on the profile rows with
   the nominal dark (bias + mean dark current of the noise model; the real
   dark frames come after the bracket). The *pixels that matter* are those of
   the profile rows whose estimate is at least ``dim_fraction`` of the rows'
   peak. The bracket is complete when
   (a) every profile-row pixel was unsaturated in at least one exposure (the
       peak is measured), and
   (b) the lowest SNR (estimate / standard deviation) among the pixels that
       matter reaches ``target_snr``.
3. Otherwise: while the peak is saturated even in the shortest exposure taken
   and the camera can go shorter, the next exposure is the shortest divided by
   ``ratio``; else the next is the longest times ``ratio``, capped at
   ``max_exposure_s``.
4. It always stops after ``max_exposures`` frames, or when the longest
   exposure already is ``max_exposure_s`` and more signal is wanted, or when
   the peak cannot be desaturated at the camera's shortest exposure and the
   dim pixels are satisfied. The status records why it stopped, so a session
   shows stacks whose peak stayed saturated or whose SNR fell short.

Dark frames: *matched darks*. After the light frames of a stack, ``n_darks``
shutter-closed frames are taken at every exposure time of the bracket, at the
same CCD temperature (seconds apart) and read through the same ROI; the merge
subtracts their mean per exposure time and accounts for its noise. This is
preferred over a fitted dark model because it captures per-pixel bias
structure, hot pixels and any non-linearity of dark current in time with no
model assumptions; it costs the dark exposure time once more per stack.
:class:`capture.hdr.FittedDark` (per-pixel bias + dark rate fitted to darks at
several exposure times) is the alternative for a dark library made once, e.g.
by the calibration; the merge takes either.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from capture.errors import PlanError
from capture.hdr import NoiseModel, NominalDark, merge_hdr
from drivers.interfaces import Camera, Frame

DEFAULT_FIRST_EXPOSURE_S = 0.001
DEFAULT_MAX_EXPOSURE_S = 60.0


@dataclass(frozen=True)
class BracketPolicy:
    """Parameters of the automatic bracket (times in seconds).

    Attributes:
        first_exposure_s: the first (short) exposure; None = the camera's shortest.
        max_exposure_s: no exposure is longer; None = the shorter of 60 s and the camera's longest.
        max_exposures: no bracket has more light frames.
        ratio: factor between successive exposure times (> 1).
        target_snr: SNR the dimmest pixels that matter must reach.
        dim_fraction: pixels of the profile rows at or above this fraction of the peak matter.
        profile_row: frame row through the scattering spot; None = brightest row of the first frame.
        profile_halfwidth_rows: rows on each side of the profile row that are checked too.
        n_darks: dark frames per exposure time (matched darks).
    """

    first_exposure_s: float | None = None
    max_exposure_s: float | None = None
    max_exposures: int = 8
    ratio: float = 4.0
    target_snr: float = 20.0
    dim_fraction: float = 1e-3
    profile_row: int | None = None
    profile_halfwidth_rows: int = 1
    n_darks: int = 2

    def resolved(self, exposure_range_s: tuple[float, float] | None = None) -> BracketPolicy:
        """The policy with its exposure limits filled in from the camera's range, checked.

        Without a range, the defaults are 1 ms and 60 s.

        Raises:
            PlanError: inconsistent values, or exposures outside the camera's range.
        """
        lo, hi = exposure_range_s if exposure_range_s is not None else (DEFAULT_FIRST_EXPOSURE_S, DEFAULT_MAX_EXPOSURE_S)
        first = self.first_exposure_s if self.first_exposure_s is not None else float(lo)
        longest = self.max_exposure_s if self.max_exposure_s is not None else float(min(hi, DEFAULT_MAX_EXPOSURE_S))
        out = replace(self, first_exposure_s=float(first), max_exposure_s=float(longest))
        out.check(exposure_range_s)
        return out

    def check(self, exposure_range_s: tuple[float, float] | None = None) -> None:
        """Raise PlanError if the policy is inconsistent or outside the camera's exposure range."""
        if self.first_exposure_s is None or self.max_exposure_s is None:
            self.resolved(exposure_range_s)
            return
        errs = []
        if not (self.first_exposure_s > 0 and math.isfinite(self.first_exposure_s)):
            errs.append(f"first exposure must be > 0 s, got {self.first_exposure_s}")
        if not (self.max_exposure_s >= self.first_exposure_s and math.isfinite(self.max_exposure_s)):
            errs.append(f"max exposure {self.max_exposure_s} s is shorter than the first {self.first_exposure_s} s")
        if self.max_exposures < 1:
            errs.append(f"max exposures must be >= 1, got {self.max_exposures}")
        if not self.ratio > 1.0:
            errs.append(f"exposure ratio must be > 1, got {self.ratio}")
        if not self.target_snr > 0:
            errs.append(f"target SNR must be > 0, got {self.target_snr}")
        if not 0.0 < self.dim_fraction <= 1.0:
            errs.append(f"dim fraction must be in (0, 1], got {self.dim_fraction}")
        if self.profile_halfwidth_rows < 0 or (self.profile_row is not None and self.profile_row < 0):
            errs.append("profile row and half-width must be >= 0")
        if self.n_darks < 1:
            errs.append(f"n_darks must be >= 1, got {self.n_darks}")
        if exposure_range_s is not None:
            lo, hi = exposure_range_s
            if self.first_exposure_s < lo or self.max_exposure_s > hi:
                errs.append(
                    f"bracket exposures [{self.first_exposure_s:g}, {self.max_exposure_s:g}] s "
                    f"outside the camera's range [{lo:g}, {hi:g}] s"
                )
        if errs:
            raise PlanError("bad bracket policy: " + "; ".join(errs))

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> BracketPolicy:
        known = {k: d[k] for k in cls.__dataclass_fields__ if k in d}
        return cls(**known)


@dataclass
class BracketStatus:
    """How a bracket ended."""

    exposures_s: list[float] = field(default_factory=list)
    reason: str = ""
    peak_unsaturated: bool = False
    min_snr: float = 0.0
    profile_rows: tuple[int, int] = (0, 0)  # [start, stop) in frame rows

    def to_dict(self) -> dict[str, Any]:
        return {
            "exposures_s": [float(t) for t in self.exposures_s],
            "reason": self.reason,
            "peak_unsaturated": bool(self.peak_unsaturated),
            "min_snr": float(self.min_snr),
            "profile_rows": [int(r) for r in self.profile_rows],
        }


class BracketController:
    """Decides the next exposure from the frames so far (no device access; see :func:`acquire_bracket`)."""

    def __init__(self, policy: BracketPolicy, noise: NoiseModel, exposure_range_s: tuple[float, float]) -> None:
        self.policy = policy.resolved(exposure_range_s)
        self.noise = noise
        self.t_min = float(exposure_range_s[0])
        self._rows: slice | None = None
        self._frames: list[np.ndarray] = []
        self.status = BracketStatus()

    def first(self) -> float:
        assert self.policy.first_exposure_s is not None  # resolved in __init__
        return self.policy.first_exposure_s

    def _profile_rows(self, data: np.ndarray) -> slice:
        p = self.policy
        row = p.profile_row
        if row is None:
            row = int(np.argmax(data.astype(np.float64).sum(axis=1)))
        row = min(row, data.shape[0] - 1)
        return slice(max(0, row - p.profile_halfwidth_rows), min(data.shape[0], row + p.profile_halfwidth_rows + 1))

    def add(self, data: np.ndarray, exposure_s: float) -> float | None:
        """Record a light frame; return the next exposure time, or None when the bracket is complete."""
        p = self.policy
        if self._rows is None:
            self._rows = self._profile_rows(data)
            self.status.profile_rows = (self._rows.start, self._rows.stop)
        self._frames.append(data[self._rows])
        self.status.exposures_s.append(float(exposure_s))
        times = self.status.exposures_s
        res = merge_hdr(np.stack(self._frames), times, NominalDark(self.noise), self.noise)
        peak_ok = bool(res.mask.all())
        est = np.where(res.mask, res.radiance, -np.inf)
        peak = float(est.max())
        matter = res.mask & (res.radiance >= p.dim_fraction * peak) & (res.radiance > 0)
        if peak > 0 and matter.any():
            snr = res.radiance[matter] / np.sqrt(res.variance[matter])
            min_snr = float(snr.min())
        else:
            min_snr = 0.0
        self.status.peak_unsaturated = peak_ok
        self.status.min_snr = min_snr
        shortest, longest = min(times), max(times)
        can_go_shorter = shortest > self.t_min * (1 + 1e-9)

        if peak_ok and min_snr >= p.target_snr:
            self.status.reason = "target SNR reached"
            return None
        if len(times) >= p.max_exposures:
            self.status.reason = "maximum number of exposures"
            return None
        if not peak_ok and can_go_shorter:
            return max(shortest / p.ratio, self.t_min)
        if min_snr >= p.target_snr:
            self.status.reason = "peak saturated at the shortest exposure"
            return None
        assert p.max_exposure_s is not None  # resolved in __init__
        if longest >= p.max_exposure_s * (1 - 1e-9):
            self.status.reason = "maximum exposure time"
            return None
        return min(longest * p.ratio, p.max_exposure_s)


def acquire_bracket(camera: Camera, policy: BracketPolicy, noise: NoiseModel) -> tuple[list[Frame], BracketStatus]:
    """Take the light frames of one stack (shutter in normal mode, the caller positions stage and filter)."""
    ctl = BracketController(policy, noise, camera.exposure_range_s)
    frames: list[Frame] = []
    t: float | None = ctl.first()
    while t is not None:
        fr = camera.expose(t, dark=False)
        frames.append(fr)
        t = ctl.add(fr.data, fr.exposure_s)
    return frames, ctl.status


def acquire_darks(camera: Camera, exposures_s: Sequence[float], n_darks: int) -> list[Frame]:
    """Take ``n_darks`` shutter-closed frames at each distinct exposure time (sorted, shortest first)."""
    frames: list[Frame] = []
    lo = float(camera.exposure_range_s[0])
    for t in sorted(set(float(x) for x in exposures_s)):
        # ``t`` is a light frame's *actual* exposure, which the camera's timer may have
        # quantised below its shortest request (Alta: floor(t / 2.56 us) ticks, so a
        # 10 us request runs 7.68 us); asking for the shortest again repeats those ticks.
        for _ in range(n_darks):
            frames.append(camera.expose(max(t, lo), dark=True))
    return frames
