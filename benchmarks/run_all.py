"""Run the benchmarks one after another (`make bench`).

Each script measures one issue's targets and writes its own results
(benchmarks/results/*.json and .md; the README's benchmark table quotes them). This runner
only starts them in turn with their default arguments and prints, per script, the exit
status and the wall time, then a summary; it exits 1 when any script failed.

By default it runs the benchmarks that finish within minutes on 2 CPU cores. `--all` adds
the long ones: the paper's simulation experiment (8 cases x 2 models, 2-7 min a fit), the
diagnosis proof suite (from its cache when the cases are there), the kill-and-resume and
device-fault trials, and the simulated bench's render timings.

    python benchmarks/run_all.py [--all] [--only NAME[,NAME...]] [--list]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

#: (script, what it measures), minutes on 2 cores at most.
QUICK = [
    ("alta_readout", "full-frame readout through the Alta-U USB twin (issue 2)"),
    ("bench_phase_fit", "9 phase models x 26 Mie datasets (issue 3)"),
    ("bench_forward", "forward and adjoint render cost, plugin overhead, render noise (issues 3, 4)"),
    ("bench_hdr", "HDR merge bias, SNR and speed (issue 5)"),
    ("bench_capture", "simulated `rig capture --angles 10 --filters rgb` end to end (issue 5)"),
    ("bench_estimate", "one channel, 10 angles, session to converged parameters (issue 6)"),
]
#: Longer: tens of minutes to hours on 2 cores.
LONG = [
    ("bench_crash", "SIGKILL at random moments + --resume (issue 5)"),
    ("bench_faults", "injected device faults (issue 5)"),
    ("sim_render", "the simulated bench's render cost and noise"),
    ("bench_coverage", "reported uncertainties against eight independent noise draws (issue 6)"),
    ("bench_paper_sim", "the paper's simulation experiment, exp3 and two-term HG (issue 6)"),
    ("bench_diagnose", "diagnosis proof suite on concealed effects (issue 7)"),
    ("bench_profile_blur", "profile-row lens blur against the bench's 2D blur (issue 7; after bench_diagnose)"),
]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--all", action="store_true", help="also run the long benchmarks")
    ap.add_argument("--only", default=None, help="comma-separated script names (without .py)")
    ap.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    args = ap.parse_args(argv)
    known = dict(QUICK + LONG)
    if args.list:
        for group, items in (("quick", QUICK), ("long (--all)", LONG)):
            print(f"{group}:")
            for name, what in items:
                print(f"  {name:<16} {what}")
        return 0
    if args.only:
        names = [n.strip().removesuffix(".py") for n in args.only.split(",") if n.strip()]
        unknown = [n for n in names if n not in known]
        if unknown:
            print(f"run_all: unknown benchmark {unknown[0]!r}; --list shows them", file=sys.stderr)
            return 2
    else:
        names = [n for n, _ in QUICK + (LONG if args.all else [])]
    results = []
    for name in names:
        print(f"=== {name}: {known[name]}", flush=True)
        t0 = time.perf_counter()
        rc = subprocess.run([sys.executable, str(HERE / f"{name}.py")], cwd=HERE.parent, check=False).returncode
        results.append((name, rc, time.perf_counter() - t0))
        print(f"=== {name}: {'ok' if rc == 0 else f'FAILED (exit {rc})'} in {results[-1][2]:.0f} s", flush=True)
    print("\nsummary:")
    for name, rc, dt in results:
        print(f"  {name:<16} {'ok' if rc == 0 else f'exit {rc}':<8} {dt:7.0f} s")
    return 0 if all(rc == 0 for _, rc, _ in results) else 1


if __name__ == "__main__":
    sys.exit(main())
