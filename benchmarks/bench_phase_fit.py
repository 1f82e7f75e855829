"""Benchmark: the paper's nine phase models fitted to the 26 Mie datasets.

13 diameters (30 .. 0.01 um) x {mono, poly} at 600 nm with the settings that reproduce
the paper's table (estimate.mie.PAPER_SETTINGS; poly = the MieSimulatorGUI v1 model by
default). Times the Mie tables and the 234 fits separately (fits spread over
``--workers`` processes; target <= 30 s on 2 cores), prints the SAD table and writes
benchmarks/results/bench_phase_fit.json.

    .venv/bin/python benchmarks/bench_phase_fit.py [--workers 2] [--poly-model lognormal]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimate.mie import PAPER_DIAMETERS_UM, PAPER_SETTINGS, mie_mono, mie_poly
from estimate.phase_fit import PAPER_MODELS, fit_models
from estimate.phase_table import PhaseTable


def _fit_one(table: PhaseTable) -> tuple[str, list[dict[str, Any]], float, float]:
    t0, c0 = time.perf_counter(), time.process_time()
    fits = fit_models(table, PAPER_MODELS)
    return table.label, [f.to_json() for f in fits], time.perf_counter() - t0, time.process_time() - c0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--poly-model", choices=("miesimulatorgui", "lognormal"), default="miesimulatorgui")
    args = ap.parse_args()

    load_before = os.getloadavg()
    t0 = time.perf_counter()
    tables = [mie_mono(d, PAPER_SETTINGS) for d in PAPER_DIAMETERS_UM]
    tables += [mie_poly(d, 0.1, PAPER_SETTINGS, poly_model=args.poly_model) for d in PAPER_DIAMETERS_UM]
    t_mie = time.perf_counter() - t0

    t1 = time.perf_counter()
    if args.workers > 1:
        with ProcessPoolExecutor(max_workers=args.workers) as ex:
            results = list(ex.map(_fit_one, tables))
    else:
        results = [_fit_one(t) for t in tables]
    t_fit = time.perf_counter() - t1

    header = f"{'dataset':<14}{'g':>9}" + "".join(f"{m:>9}" for m in PAPER_MODELS)
    print(f"SAD of ln p over {tables[0].p.size} angles (natural log); -- = polynomial <= 0 on the grid")
    print(header)
    rows: list[dict[str, Any]] = []
    cpu_fit = sum(r[3] for r in results)
    for t, (label, fits, dt, _) in zip(tables, results):
        sads = {f["model"]: f["sad"] for f in fits}
        rows.append({"dataset": label, "kind": t.meta["kind"], "diameter_um": t.diameter_um, "g": t.g,
                     "sad": sads, "params": {f["model"]: f["params"] for f in fits}, "fit_seconds": dt})
        print(f"{label:<14}{t.g:>9.4f}" + "".join(
            f"{'--' if sads[m] is None else format(sads[m], '.1f'):>9}" for m in PAPER_MODELS))
    # how often each model is the best (lowest SAD) per dataset
    wins = {m: 0 for m in PAPER_MODELS}
    for r in rows:
        ok: dict[str, float] = {m: s for m, s in r["sad"].items() if s is not None}
        wins[min(ok, key=ok.__getitem__)] += 1
    load_after = os.getloadavg()
    print(f"\nMie tables: {t_mie:.2f} s; fits (26 datasets x 9 models, {args.workers} workers): {t_fit:.2f} s wall, "
          f"{cpu_fit:.2f} CPU-s (= {cpu_fit / max(1, args.workers):.2f} s on {args.workers} idle cores; target <= 30 s)")
    print(f"load average before/after: {load_before[0]:.2f} / {load_after[0]:.2f} (other jobs inflate wall time)")
    print("best model per dataset:", ", ".join(f"{m} {n}" for m, n in wins.items() if n))

    out = ROOT / "benchmarks" / "results"
    out.mkdir(parents=True, exist_ok=True)
    doc = {"benchmark": "bench_phase_fit", "models": list(PAPER_MODELS), "poly_model": args.poly_model,
           "settings": {"wavelength_nm": PAPER_SETTINGS.wavelength_nm, "n_particle": 1.377,
                        "n_medium": PAPER_SETTINGS.n_medium, "n_theta": PAPER_SETTINGS.n_theta, "spread": 0.1},
           "seconds_mie": t_mie, "seconds_fit": t_fit, "cpu_seconds_fit": cpu_fit,
           "load_average_before_after": [load_before[0], load_after[0]], "workers": args.workers, "target_seconds": 30.0,
           "cpu_count": os.cpu_count(), "python": platform.python_version(), "wins": wins, "rows": rows}
    name = "bench_phase_fit" if args.poly_model == "miesimulatorgui" else "bench_phase_fit_lognormal"
    (out / f"{name}.json").write_text(json.dumps(doc, indent=1))
    print(f"wrote {out / (name + '.json')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
