"""HDR merge benchmark on synthetic stacks with known radiance.

A 512 x 512 sensor (the test KAF-0261E noise model: gain 3 e-/ADU, bias 1000
ADU, read noise 15 e-, dark current 2 e-/s, full well 200 ke- with blooming,
16-bit ADC) sees 16 horizontal bands of uniform radiance, log-spaced from
10 to 3e6 e-/s. Six exposures (1 ms x 4^k, k = 0..5) and two matched darks per
exposure are simulated, then merged by ``capture.hdr.merge_hdr``.

Per band (interior rows, away from the bloom at band edges) it reports:
* relative bias of the merge and its z-score (bias / standard error);
* SNR (radiance / RMS error) of the merge, of the oracle estimator that uses
  the TRUE radiance for its weights on the same frames, and their ratio;
* the mean predicted variance over the empirical one (calibration of the variance channel).

Pass criteria (issue 5): |z| < 4 for every band (unbiased within noise),
SNR ratio >= 0.98 for every band, and a 512 x 512 x 6 merge <= 0.1 s (median of 15).
Writes benchmarks/results/bench_hdr.json.
"""

from __future__ import annotations

import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from fakes import TEST_SENSOR, simulate_frame

from capture.hdr import (
    MatchedDarks,
    NoiseModel,
    merge_hdr,
    optimal_reference,
    saturation_mask,
)
from drivers.interfaces import ROI, Frame

SEED = 20261121
N_BANDS = 16
SIZE = 512
EXPOSURES_S = [0.001 * 4**k for k in range(6)]
N_DARKS = 2
EDGE = 8  # rows excluded at each band edge for the statistics


def make_stack(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, list[Frame]]:
    levels = np.logspace(1, np.log10(3e6), N_BANDS)
    rows_per = SIZE // N_BANDS
    truth = np.repeat(levels, rows_per)[:, None] * np.ones((1, SIZE))
    bias_map = TEST_SENSOR.bias_adu + rng.normal(0, 3.0, (SIZE, SIZE))  # fixed-pattern bias the darks must remove
    light = np.stack([simulate_frame(rng, truth, t, TEST_SENSOR, bias_map=bias_map) for t in EXPOSURES_S])
    roi = ROI()
    darks = [
        Frame(simulate_frame(rng, truth, t, TEST_SENSOR, dark=True, bias_map=bias_map), t, True, -20.0, 0.0, t, roi)
        for t in EXPOSURES_S
        for _ in range(N_DARKS)
    ]
    return truth, light, darks


def main() -> int:
    rng = np.random.default_rng(SEED)
    truth, light, dark_frames = make_stack(rng)
    noise = NoiseModel.from_sensor(TEST_SENSOR)
    darks = MatchedDarks.from_frames(dark_frames, noise)

    res = merge_hdr(light, EXPOSURES_S, darks, noise)
    valid = ~saturation_mask(light, noise.saturation_adu, bloom_rows=2)
    oracle = optimal_reference(light, EXPOSURES_S, darks, noise, truth, valid)

    rows_per = SIZE // N_BANDS
    bands = []
    ok_bias = ok_snr = True
    for b in range(N_BANDS):
        sl = slice(b * rows_per + EDGE, (b + 1) * rows_per - EDGE)
        L = float(truth[sl][0, 0])
        est = res.radiance[sl].astype(np.float64)
        ora = oracle[sl]
        err = est - L
        n = err.size
        bias = float(err.mean())
        z = bias / (float(err.std(ddof=1)) / np.sqrt(n))
        snr = L / float(np.sqrt(np.mean(err**2)))
        snr_opt = L / float(np.sqrt(np.mean((ora - L) ** 2)))
        ratio = snr / snr_opt
        var_cal = float(res.variance[sl].mean() / err.var(ddof=1))
        ok_bias &= abs(z) < 4
        ok_snr &= ratio >= 0.98
        bands.append(
            {
                "radiance_e_per_s": L,
                "relative_bias": bias / L,
                "bias_z": z,
                "snr": snr,
                "snr_optimal": snr_opt,
                "snr_ratio": ratio,
                "variance_calibration": var_cal,
                "exposures_used": float(res.n_valid[sl].mean()),
            }
        )

    # timing: the merge alone, and with averaging the darks
    for _ in range(2):
        merge_hdr(light, EXPOSURES_S, darks, noise)
    times = []
    for _ in range(15):
        t0 = time.perf_counter()
        merge_hdr(light, EXPOSURES_S, darks, noise)
        times.append(time.perf_counter() - t0)
    times_d = []
    for _ in range(5):
        t0 = time.perf_counter()
        merge_hdr(light, EXPOSURES_S, MatchedDarks.from_frames(dark_frames, noise), noise)
        times_d.append(time.perf_counter() - t0)
    t_med = statistics.median(times)
    ok_time = t_med <= 0.1

    print(f"{'L (e-/s)':>10} {'rel.bias':>10} {'z':>6} {'SNR':>8} {'SNR opt':>8} {'ratio':>7} {'var cal':>7} {'n exp':>5}")
    for r in bands:
        print(
            f"{r['radiance_e_per_s']:10.3g} {r['relative_bias']:10.2e} {r['bias_z']:6.2f} {r['snr']:8.1f} "
            f"{r['snr_optimal']:8.1f} {r['snr_ratio']:7.4f} {r['variance_calibration']:7.3f} {r['exposures_used']:5.2f}"
        )
    print(f"min SNR ratio {min(r['snr_ratio'] for r in bands):.4f} (>= 0.98: {ok_snr}); max |z| "
          f"{max(abs(r['bias_z']) for r in bands):.2f} (< 4: {ok_bias})")
    print(f"merge 512x512x6: median {t_med * 1e3:.1f} ms, min {min(times) * 1e3:.1f} ms (<= 100 ms: {ok_time}); "
          f"with dark averaging: median {statistics.median(times_d) * 1e3:.1f} ms")

    out = {
        "seed": SEED,
        "shape": [SIZE, SIZE],
        "exposures_s": EXPOSURES_S,
        "n_darks": N_DARKS,
        "bands": bands,
        "min_snr_ratio": min(r["snr_ratio"] for r in bands),
        "max_abs_bias_z": max(abs(r["bias_z"]) for r in bands),
        "merge_time_median_s": t_med,
        "merge_time_min_s": min(times),
        "merge_with_darks_time_median_s": statistics.median(times_d),
        "pass": {"unbiased": bool(ok_bias), "snr_ratio": bool(ok_snr), "time": bool(ok_time)},
    }
    dest = ROOT / "benchmarks" / "results" / "bench_hdr.json"
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_text(json.dumps(out, indent=2))
    return 0 if (ok_bias and ok_snr and ok_time) else 1


if __name__ == "__main__":
    raise SystemExit(main())
