"""Noise and charge model of the Kodak KAF-0261E full-frame CCD, for the camera twin.

From photo-electron rate to ADU, in the order charge flows through the chip:

1. photo-electrons and thermal (dark) electrons collected during the exposure,
   Poisson distributed (the sum of two Poisson processes is one);
2. full-well clipping with **blooming**: the KAF-0261E has no anti-blooming
   drain, so charge above the full well spills into the neighbouring pixels of
   the same column (up and down, half each way, filling each pixel to full well
   before moving on); charge that reaches the end of a column is lost;
3. an optional response-compression hook (``nonlinearity``: electrons ->
   electrons), used by the simulated bench's sensor-nonlinearity effect;
4. binning: charge of bin_x x bin_y pixels summed before the output amplifier;
5. read noise (Gaussian, once per output pixel), gain (e-/ADU), bias offset,
   16-bit ADC rounding and saturation.

Dark current vs temperature is a *model*: D(T) = D_ref * 2^((T - T_ref) / 6 C),
the usual rule of thumb for silicon CCDs ("doubles every ~6 C"); D_ref is the
sensor's ``dark_current_e_per_s`` at the -20 C default set-point (unconfirmed).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from drivers.alta_protocol import DEFAULT_SETPOINT_C, KAF0261E
from drivers.interfaces import SensorInfo

Nonlinearity = Callable[[np.ndarray], np.ndarray]


@dataclass
class CcdModel:
    """The KAF-0261E (or another full-frame CCD given its :class:`SensorInfo`).

    Attributes:
        sensor: gain, bias, read noise, full well, ADC range, reference dark current.
        dark_ref_temp_c: temperature at which ``sensor.dark_current_e_per_s`` holds.
        dark_doubling_c: temperature step that doubles the dark current.
        nonlinearity: optional compression of the collected charge (electrons in,
            electrons out, elementwise, monotonic), applied after blooming.
    """

    sensor: SensorInfo = KAF0261E
    dark_ref_temp_c: float = DEFAULT_SETPOINT_C
    dark_doubling_c: float = 6.0
    nonlinearity: Nonlinearity | None = None

    def dark_rate(self, temp_c: float) -> float:
        """Thermal electrons per second per unbinned pixel at ``temp_c`` (C)."""
        return self.sensor.dark_current_e_per_s * 2.0 ** ((temp_c - self.dark_ref_temp_c) / self.dark_doubling_c)

    def collect(self, rate_e_per_s: np.ndarray | None, exposure_s: float, temp_c: float,
                rng: np.random.Generator, shape: tuple[int, int] | None = None) -> np.ndarray:
        """Electrons collected per pixel (float64): Poisson of (light + dark) * t.

        ``rate_e_per_s`` is the photo-electron rate per unbinned pixel (None: shutter
        closed, only dark current; then ``shape`` gives the array shape).
        """
        if rate_e_per_s is None:
            if shape is None:
                raise ValueError("shape is needed when no light reaches the sensor")
            mean = np.full(shape, self.dark_rate(temp_c) * exposure_s)
        else:
            mean = (np.clip(np.asarray(rate_e_per_s, dtype=np.float64), 0.0, None) + self.dark_rate(temp_c)) * exposure_s
        return rng.poisson(mean).astype(np.float64)

    def bloom(self, electrons: np.ndarray) -> np.ndarray:
        """Clip every pixel at the full well, spilling the excess along its column.

        Axis 0 is the column direction (rows). Charge is conserved except what
        spills past the first or last row.
        """
        fw = self.sensor.full_well_e
        q = np.array(electrons, dtype=np.float64, copy=True)
        cols = np.flatnonzero((q > fw).any(axis=0))
        for c in cols:
            q[:, c] = _bloom_column(q[:, c], fw)
        return q

    def digitise(self, electrons: np.ndarray, bin_x: int, bin_y: int, rng: np.random.Generator) -> np.ndarray:
        """Bin, add read noise, convert to ADU with bias, round and saturate to uint16."""
        rows, cols = electrons.shape
        if rows % bin_y or cols % bin_x:
            raise ValueError(f"{rows}x{cols} pixels do not bin by {bin_x}x{bin_y}")
        binned = electrons.reshape(rows // bin_y, bin_y, cols // bin_x, bin_x).sum(axis=(1, 3))
        s = self.sensor
        signal = binned + rng.normal(0.0, s.read_noise_e, size=binned.shape)
        adu = np.rint(signal / s.gain_e_per_adu + s.bias_adu)
        return np.clip(adu, 0, s.adc_max).astype(np.uint16)

    def read_noise_pixels(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` pixels with no charge (bias + read noise), e.g. the extra pixel per row."""
        s = self.sensor
        adu = np.rint(rng.normal(0.0, s.read_noise_e, size=n) / s.gain_e_per_adu + s.bias_adu)
        return np.clip(adu, 0, s.adc_max).astype(np.uint16)

    def expose(self, rate_e_per_s: np.ndarray | None, exposure_s: float, temp_c: float,
               rng: np.random.Generator, *, bin_x: int = 1, bin_y: int = 1,
               shape: tuple[int, int] | None = None, crop: tuple[slice, slice] | None = None) -> np.ndarray:
        """One frame in ADU (uint16).

        Args:
            rate_e_per_s: photo-electron rate per unbinned pixel, or None (shutter closed).
                Pass whole columns (all rows) so that blooming from outside the ROI is seen;
                ``crop`` then selects the ROI rows/cols (unbinned) after blooming.
            exposure_s: integration time, seconds.
            temp_c: CCD temperature during the exposure (dark current).
            bin_x, bin_y: on-chip binning.
        """
        q = self.collect(rate_e_per_s, exposure_s, temp_c, rng, shape)
        q = self.bloom(q)
        if crop is not None:
            q = q[crop]
        if self.nonlinearity is not None:
            q = np.asarray(self.nonlinearity(q), dtype=np.float64)
        return self.digitise(q, bin_x, bin_y, rng)


def _bloom_column(q: np.ndarray, fw: float) -> np.ndarray:
    """Spill the excess of every run of over-full pixels half up, half down the column.

    Each half fills the pixels beyond the run to the full well in turn (pixels
    already full pass it on) until it is used up or leaves the column.
    """
    q = q.copy()
    over = q > fw
    # runs of consecutive over-full pixels: [start, end)
    edges = np.flatnonzero(np.diff(np.concatenate(([0], over.view(np.int8), [0]))))
    for start, end in zip(edges[::2], edges[1::2]):
        excess = float(np.sum(q[start:end] - fw))
        q[start:end] = fw
        down = excess / 2.0
        up = excess - down
        _fill(q[end:], down, fw)
        _fill(q[:start][::-1], up, fw)
    return q


def _fill(view: np.ndarray, amount: float, fw: float) -> None:
    """Add ``amount`` electrons to ``view`` in order, topping each pixel up to ``fw`` (in place)."""
    if amount <= 0 or view.size == 0:
        return
    room = np.clip(fw - view, 0.0, None)
    filled = np.cumsum(room)
    k = int(np.searchsorted(filled, amount, side="left"))  # pixels [0, k) are filled completely
    if k >= view.size:
        view[:] += room  # everything full; the rest leaves the column
        return
    view[:k] += room[:k]
    view[k] += amount - (filled[k - 1] if k > 0 else 0.0)
