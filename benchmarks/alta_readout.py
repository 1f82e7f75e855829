"""Readout of a full 512 x 512 Alta-U frame through the pyusb twin.

Two numbers per frame kind (dark, light with the default analytic spot):

* ``software``: the twin at time_scale 1e6 (the simulated exposure and the
  simulated 0.27 s CCD readout cost nothing), so the wall time is the cost of
  the driver's control transfers, status polls, frame synthesis in the twin
  (Poisson, blooming, read noise), five bulk reads of <= 126,976 bytes and the
  removal of the extra pixel per row. ``download`` is the bulk-read part alone
  (from image-done to the last byte, including the twin's lazy frame synthesis).
* ``real-time``: the twin at time_scale 1, where a 10 us exposure is followed by
  the modelled readout (512 row shifts x 10 us + 512 x 513 pixels x 1 us =
  0.268 s, an *unconfirmed* model of the U260 at 1 MHz).

Median of N frames. Writes benchmarks/results/alta_readout.json.
"""

from __future__ import annotations

import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from drivers.apogee_alta import AltaCamera
from sim_devices.alta_usb import PIXEL_TIME_S, ROW_SHIFT_TIME_S, AltaBackend

N = 15


def run(time_scale: float, dark: bool, n: int) -> dict[str, float]:
    with AltaCamera(backend=AltaBackend("bench-alta-readout", time_scale=time_scale, seed=1)) as cam:
        cam.expose(1e-5, dark=dark)  # warm-up
        totals, downloads = [], []
        for _ in range(n):
            t = time.perf_counter()
            f = cam.expose(1e-5, dark=dark)
            totals.append(time.perf_counter() - t)
            downloads.append(f.extra["download_s"])
            assert f.data.shape == (512, 512)
    return {"expose_s": statistics.median(totals), "download_s": statistics.median(downloads)}


def main() -> None:
    modelled = 512 * ROW_SHIFT_TIME_S + 512 * 513 * PIXEL_TIME_S
    rows: list[dict[str, float | str]] = []
    for label, scale, n in (("software", 1e6, N), ("real-time", 1.0, 5)):
        for dark in (True, False):
            r = run(scale, dark, n)
            rows.append({"mode": label, "time_scale": scale, "frame": "dark" if dark else "light", **r})
    print(f"{'mode':<10} {'frame':<6} {'expose (s)':>11} {'download (s)':>13}")
    for row in rows:
        print(f"{row['mode']:<10} {row['frame']:<6} {row['expose_s']:>11.4f} {row['download_s']:>13.4f}")
    print(f"modelled CCD readout at time_scale 1: {modelled:.4f} s")
    out = ROOT / "benchmarks" / "results" / "alta_readout.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"frames_per_point": N, "modelled_ccd_readout_s": modelled, "results": rows}, indent=2))


if __name__ == "__main__":
    main()
