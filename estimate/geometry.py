"""Rig geometry for the forward model: slab size, camera sampling in object space.

Frame (DESIGN.md): the slab's front face is z = 0 with normal +z towards the camera, the
slab fills -d <= z <= 0; the camera looks along -z; image x is world x, image y is world y.
Image pixel (column i, row j), rows counted top-down, has its centre at world
x = (i + 0.5 - cx) * pitch, y = -(j + 0.5 - cy) * pitch, with (cx, cy) = `image_center_px`,
the continuous pixel coordinate where the rotation axis on the front face (world origin)
is imaged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from estimate.errors import ModelParameterError

__all__ = ["PixelWindow", "RigGeometry"]


def _positive(name: str, v: float) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ModelParameterError(f"{name}={v!r} is not a number") from None
    if not math.isfinite(f) or f <= 0:
        raise ModelParameterError(f"{name}={v!r} must be a finite number > 0")
    return f


@dataclass(frozen=True)
class PixelWindow:
    """A rectangle of sensor pixels: columns [col0, col1), rows [row0, row1)."""

    col0: int
    col1: int
    row0: int
    row1: int

    @property
    def width(self) -> int:
        return self.col1 - self.col0

    @property
    def height(self) -> int:
        return self.row1 - self.row0


@dataclass(frozen=True)
class RigGeometry:
    """Geometry of slab and camera.

    Attributes:
        thickness_mm: nominal slab thickness d (mm), > 0.
        half_width_mm: half the slab's lateral size in x and y (mm); the slab is square.
        sensor_px: (columns, rows) of the sensor (Alta U260: 512 x 512).
        pixel_um: physical pixel size on the sensor (um; Alta U260: 20).
        magnification: lens magnification (TEC-M55: not confirmed, a parameter).
        image_center_px: (cx, cy) continuous pixel coordinate of the world origin; None =
            sensor centre.
        profile_row: sensor row used as the estimation profile; None = the row below the
            image centre (cy rounded down).
        profile_columns: (col0, col1) of the profile; None = the whole sensor row.
    """

    thickness_mm: float
    half_width_mm: float = 12.5
    sensor_px: tuple[int, int] = (512, 512)
    pixel_um: float = 20.0
    magnification: float = 0.5
    image_center_px: tuple[float, float] | None = None
    profile_row: int | None = None
    profile_columns: tuple[int, int] | None = None
    _checked: bool = field(default=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        _positive("thickness_mm", self.thickness_mm)
        _positive("half_width_mm", self.half_width_mm)
        _positive("pixel_um", self.pixel_um)
        _positive("magnification", self.magnification)
        cols, rows = self.sensor_px
        if int(cols) < 1 or int(rows) < 1:
            raise ModelParameterError(f"sensor_px={self.sensor_px!r} must be positive")
        if self.image_center_px is not None:
            for name, v in zip(("cx", "cy"), self.image_center_px):
                if not math.isfinite(float(v)):
                    raise ModelParameterError(f"image_center_px {name}={v!r} must be finite")
        if self.profile_row is not None and not 0 <= int(self.profile_row) < rows:
            raise ModelParameterError(f"profile_row={self.profile_row!r} outside the sensor's {rows} rows")
        if self.profile_columns is not None:
            c0, c1 = self.profile_columns
            if not 0 <= c0 < c1 <= cols:
                raise ModelParameterError(f"profile_columns={self.profile_columns!r} outside 0..{cols}")

    @property
    def pixel_mm(self) -> float:
        """Pixel pitch in object space (mm)."""
        return self.pixel_um * 1e-3 / self.magnification

    @property
    def center_px(self) -> tuple[float, float]:
        if self.image_center_px is not None:
            return float(self.image_center_px[0]), float(self.image_center_px[1])
        return self.sensor_px[0] / 2.0, self.sensor_px[1] / 2.0

    @property
    def row(self) -> int:
        if self.profile_row is not None:
            return int(self.profile_row)
        return min(self.sensor_px[1] - 1, math.floor(self.center_px[1]))

    def profile_window(self) -> PixelWindow:
        c0, c1 = self.profile_columns if self.profile_columns is not None else (0, self.sensor_px[0])
        return PixelWindow(int(c0), int(c1), self.row, self.row + 1)

    def full_window(self) -> PixelWindow:
        return PixelWindow(0, self.sensor_px[0], 0, self.sensor_px[1])

    def window(self, columns: tuple[int, int] | None = None,
               rows: tuple[int, int] | None = None) -> PixelWindow:
        """A window; None columns = profile columns, None rows = the profile row."""
        pw = self.profile_window()
        c0, c1 = columns if columns is not None else (pw.col0, pw.col1)
        r0, r1 = rows if rows is not None else (pw.row0, pw.row1)
        cols, nrows = self.sensor_px
        if not (0 <= c0 < c1 <= cols and 0 <= r0 < r1 <= nrows):
            raise ModelParameterError(
                f"pixel window columns={c0}..{c1} rows={r0}..{r1} outside the {cols}x{nrows} sensor")
        return PixelWindow(int(c0), int(c1), int(r0), int(r1))

    def pixel_x_mm(self, window: PixelWindow) -> list[float]:
        """World x (mm) of the centres of the window's columns."""
        cx, _ = self.center_px
        return [(i + 0.5 - cx) * self.pixel_mm for i in range(window.col0, window.col1)]

    def window_center_mm(self, window: PixelWindow) -> tuple[float, float]:
        """World (x, y) of the window's centre."""
        cx, cy = self.center_px
        p = self.pixel_mm
        return ((0.5 * (window.col0 + window.col1) - cx) * p,
                -(0.5 * (window.row0 + window.row1) - cy) * p)
