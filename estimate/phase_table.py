"""Tabulated phase functions: the container, and a reader for a user's CSV table.

A table holds p(theta) [1/sr] on scattering angles theta [deg] (0 = straight on). The CSV
reader accepts a header line (optional) and two columns: the angle (degrees, or the cosine
mu when the header's first column is named ``mu``/``cos``) and p. Every problem is a
:class:`~estimate.errors.DataError` with one line naming the row.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from estimate.errors import DataError

__all__ = ["PhaseTable", "parse_phase_csv", "read_phase_csv", "simpson_weights"]


def simpson_weights(n: int) -> np.ndarray:
    """Composite Simpson weights (step 1) for n (odd) equally spaced points; trapezoid if even."""
    if n < 2:
        return np.ones(n)
    if n % 2 == 0:
        w = np.ones(n)
        w[0] = w[-1] = 0.5
        return w
    w = np.ones(n)
    w[1:-1:2] = 4.0
    w[2:-1:2] = 2.0
    return w / 3.0


@dataclass(frozen=True)
class PhaseTable:
    """p(theta) on a grid of scattering angles.

    Attributes:
        theta_deg: increasing angles in [0, 180] [deg].
        p: phase function [1/sr], all > 0.
        g: asymmetry (mean cosine); from the source (exact Mie) when known, else the
            table's own quadrature.
        label: short name for tables and plots.
        diameter_um: particle (mean) diameter [um] for Mie data, else None.
        meta: provenance (settings of the Mie computation, file name...).
    """

    theta_deg: np.ndarray
    p: np.ndarray
    g: float
    label: str = ""
    diameter_um: float | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def mu(self) -> np.ndarray:
        """cos(theta)."""
        return np.cos(np.radians(self.theta_deg))

    @property
    def log_p(self) -> np.ndarray:
        """Natural log of p."""
        return np.log(self.p)

    def _weights(self) -> np.ndarray:
        th = np.radians(self.theta_deg)
        d = np.diff(th)
        if th.size >= 3 and np.allclose(d, d[0], rtol=1e-9, atol=1e-12):
            return simpson_weights(th.size) * d[0] * np.sin(th)
        # uneven grid: trapezoid in theta
        w = np.zeros_like(th)
        w[:-1] += 0.5 * d
        w[1:] += 0.5 * d
        return w * np.sin(th)

    def normalisation(self) -> float:
        """2 pi int p sin(theta) dtheta by quadrature over the table (1 for a normalised table
        whose grid covers [0, 180] deg)."""
        return float(2.0 * math.pi * np.sum(self._weights() * self.p))

    def g_quadrature(self) -> float:
        """Mean cosine by quadrature over the table (Simpson on an even grid)."""
        w = self._weights() * self.p
        return float(np.sum(w * self.mu) / np.sum(w))


def parse_phase_csv(text: str, source: str = "<table>") -> PhaseTable:
    """Parse CSV text (see module doc) into a :class:`PhaseTable` normalised to 1.

    Raises:
        DataError: empty table, a row that is not two numbers, NaN/inf, p <= 0, angles
            outside [0, 180] deg (or mu outside [-1, 1]), angles not strictly monotone,
            fewer than 5 rows. One line, naming the row (1-based line number).
    """
    rows = list(csv.reader(io.StringIO(text)))
    use_mu = False
    data: list[tuple[int, float, float]] = []
    for lineno, row in enumerate(rows, start=1):
        cells = [c.strip() for c in row]
        if not cells or all(c == "" for c in cells) or cells[0].startswith("#"):
            continue
        if len(cells) < 2:
            raise DataError(f"{source}: line {lineno}: expected two columns (angle, p), got {len(cells)}")
        try:
            a, v = float(cells[0]), float(cells[1])
        except ValueError:
            if not data and not use_mu:
                head = cells[0].lower()
                use_mu = head.startswith(("mu", "cos"))
                continue  # header line
            raise DataError(f"{source}: line {lineno}: not a number: {','.join(cells[:2])!r}") from None
        if not (math.isfinite(a) and math.isfinite(v)):
            raise DataError(f"{source}: line {lineno}: NaN or infinite value")
        if v <= 0.0:
            raise DataError(f"{source}: line {lineno}: phase value {v:g} <= 0 (a phase function is positive)")
        data.append((lineno, a, v))
    if len(data) < 5:
        raise DataError(f"{source}: needs at least 5 data rows, found {len(data)}")
    lines = np.array([d[0] for d in data])
    ang = np.array([d[1] for d in data])
    p = np.array([d[2] for d in data])
    if use_mu:
        bad = np.flatnonzero((ang < -1.0) | (ang > 1.0))
        if bad.size:
            raise DataError(f"{source}: line {lines[bad[0]]}: mu {ang[bad[0]]:g} outside [-1, 1]")
        theta = np.degrees(np.arccos(ang))
    else:
        bad = np.flatnonzero((ang < 0.0) | (ang > 180.0))
        if bad.size:
            raise DataError(f"{source}: line {lines[bad[0]]}: angle {ang[bad[0]]:g} deg outside [0, 180]")
        theta = ang
    d = np.diff(theta)
    if np.all(d < 0):
        theta, p, lines, ang = theta[::-1], p[::-1], lines[::-1], ang[::-1]
        d = np.diff(theta)
    nonmono = np.flatnonzero(d <= 0)
    if nonmono.size:
        i = nonmono[0] + 1
        col = "mu" if use_mu else "angle"
        raise DataError(f"{source}: line {lines[i]}: {col} {ang[i]:g} breaks the strictly monotone order "
                        f"(previous row has {ang[i - 1]:g})")
    t = PhaseTable(theta_deg=theta, p=p, g=float("nan"), label=Path(source).stem, meta={"source": source})
    n = t.normalisation()
    if not (n > 0 and math.isfinite(n)):
        raise DataError(f"{source}: the table integrates to {n!r}; cannot normalise")
    t = PhaseTable(theta_deg=theta, p=p / n, g=float("nan"), label=t.label,
                   meta={"source": source, "normalisation_of_input": n})
    return PhaseTable(theta_deg=theta, p=t.p, g=t.g_quadrature(), label=t.label, meta=t.meta)


def read_phase_csv(path: str | Path) -> PhaseTable:
    """Read a CSV phase-function table (see :func:`parse_phase_csv`).

    Raises:
        DataError: unreadable file or bad content (one line).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"{path}: cannot read: {e.__class__.__name__}: {e}") from None
    return parse_phase_csv(text, source=str(path))
