"""The virtual optical bench: the shared physical state the twins act on.

The stage twin writes the beam angle, the filter twin the filter in the beam,
and the camera twin asks the bench what irradiance reaches the sensor. Benches
are named so a URL (``sim-shot702://default``) and a pyusb backend built for the
same name meet on the same bench.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np


class SceneFunction(Protocol):
    """What the camera sees.

    Args:
        angle_deg: physical stage angle (world frame, degrees; see DESIGN.md).
        filter_name: filter in the beam, or None between positions / unnamed.
        rows, cols: slices of the full 512x512 sensor to return.

    Returns:
        Photo-electron rate in e-/s per (unbinned) pixel, float64, shape of the slices.
    """

    def __call__(self, angle_deg: float, filter_name: str | None, rows: slice, cols: slice) -> np.ndarray: ...


def analytic_spot(angle_deg: float, filter_name: str | None, rows: slice, cols: slice,
                  *, width: int = 512, height: int = 512) -> np.ndarray:
    """A simple analytic scattering spot: a Gaussian core plus an exponential tail
    whose brightness and width depend on the angle (front-lit brighter, back-lit wider).
    Enough for device tests; the physically rendered bench replaces it for capture."""
    y, x = np.mgrid[0:height, 0:width][:, rows, cols].astype(np.float64)
    cx, cy = width / 2 + 40.0 * np.sin(np.radians(angle_deg)), height / 2
    r = np.hypot(x - cx, y - cy)
    front = np.cos(np.radians(angle_deg)) > 0
    peak = 2.0e5 if front else 2.0e4
    scale = {"r": 1.0, "g": 0.8, "b": 0.6}.get(filter_name or "", 0.05)
    tail = 12.0 if front else 25.0
    return scale * peak * (0.7 * np.exp(-0.5 * (r / 3.0) ** 2) + 0.3 * np.exp(-r / tail))


@dataclass
class Bench:
    """Shared state of one simulated rig.

    Attributes:
        scene: irradiance model the camera twin samples.
        stage_angle_deg: physical angle of the beam arm, set by the stage twin.
        filter_name: filter in the beam, set by the filter twin.
        filter_by_position: wheel position (1-based) -> filter name.
        time_scale: simulated seconds per real second (100 = a 1 s move takes 10 ms).
    """

    scene: SceneFunction = analytic_spot
    stage_angle_deg: float = 0.0
    filter_name: str | None = None
    filter_by_position: dict[int, str] = field(default_factory=lambda: {1: "r", 2: "g", 3: "b"})
    time_scale: float = 1.0
    lock: threading.RLock = field(default_factory=threading.RLock, repr=False)


_BENCHES: dict[str, Bench] = {}
_REG_LOCK = threading.Lock()


def get_bench(name: str = "default") -> Bench:
    """The bench of that name, made with defaults on first use."""
    with _REG_LOCK:
        if name not in _BENCHES:
            _BENCHES[name] = Bench()
        return _BENCHES[name]


def set_bench(name: str, bench: Bench) -> Bench:
    """Install (or replace) a named bench, e.g. one whose scene is the rendered rig."""
    with _REG_LOCK:
        _BENCHES[name] = bench
    return bench


def drop_bench(name: str) -> None:
    with _REG_LOCK:
        _BENCHES.pop(name, None)


Clock = Callable[[], float]
