"""Injected device faults: every capture completes, or stops cleanly and resumes.

For each fault kind the twins can inject (``sim_devices.faults``: ``drop``,
``garble`` and ``ng`` on the serial links of the stage and the filter wheel,
``pipe``, ``disconnect`` and ``short`` on the camera's USB, ``limit`` on the
stage) a small simulated capture (2 angles x 3 filters, 8-row band, 3-frame
brackets, time scale 1000) runs with that fault at a modest rate, for several
seeds. Each run is classified:

* survived: exit 0, session complete, every checksum right (the drivers
  retried or resolved what they could);
* stopped cleanly: exit 2 or 3 with exactly one ``rig capture: error:`` line
  naming the device, no traceback, and then: when the session exists, the line
  gives the ``--resume`` command and the session resumes with faults off to
  completion without changing any stack completed before the fault; when the
  fault struck while the rig was opening (no session yet, nothing written),
  the same command run again with faults off completes;
* failed badly: anything else (traceback, other exit status, hang, a resume
  that fails, a changed or corrupt stack).

The byte transcript (``--log-io``) of each run is scanned for the anomalies the
drivers noted there (retries, garbled replies, stalls, failed transfers); the
Sigma Koki driver retries without a transcript note, so its recoveries do not
show in that count.
The camera sees a cheap copy of the default world (few samples per pixel,
renders cached on disk by a fault-free warm-up run) when the rendered bench is
installed, else the analytic spot. Writes benchmarks/results/bench_faults.json.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from capture.session import Session
from rig.config import PACKAGED_SIM_CONFIG

#: Fault kind -> probability per draw (per serial exchange, USB control transfer,
#: bulk read, or stage move as the twin draws it).
RATES = {"drop": 0.02, "garble": 0.02, "ng": 0.02, "limit": 0.15, "pipe": 0.01, "disconnect": 0.01, "short": 0.02}
DEVICE = {"drop": "serial", "garble": "serial", "ng": "serial", "limit": "stage", "pipe": "camera",
          "disconnect": "camera", "short": "camera"}
SEEDS = (1, 2, 3, 4)
PLAN = ["--angles", "2", "--filters", "rgb", "--band-rows", "8", "--max-exposures", "3", "--darks", "1",
        "--no-progress", "--sim"]
TIMEOUT_S = 180
WORLD: list[Path] = []  # the cheap world, once made
ANOMALY = re.compile(r" ! .*(retry|attempt|garbled|stall|failed)", re.IGNORECASE)


def cheap_world(tmp: Path) -> Path | None:
    """A cheap copy of the default world (renders cached under ``tmp``), or None without the
    rendered bench: these runs test robustness, not the physics."""
    try:
        from sim_devices.world import write_quick_world
    except ImportError:
        return None
    return write_quick_world(tmp / "cheap-world.yaml", cache_dir=tmp / "cache")


def _config(path: Path, faults: str, seed: int) -> Path:
    data = yaml.safe_load(PACKAGED_SIM_CONFIG.read_text())
    data["sim"].update(time_scale=1000.0, faults=faults, seed=seed)
    if WORLD:
        data["sim"]["world"] = str(WORLD[0])
    path.write_text(yaml.safe_dump(data))
    return path


def _capture(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rig.cli", "capture", *args], check=False, cwd=ROOT, capture_output=True,
                          text=True, timeout=TIMEOUT_S)


def _done(out: Path) -> dict[str, tuple]:
    s = Session.open(out)
    return {r.id: (r.completed, tuple(sorted((k, f.sha256) for k, f in r.files.items()))) for r in s.stacks() if r.done}


def _one(tmp: Path, kind: str, seed: int, clean_cfg: Path) -> dict:
    out = tmp / f"{kind}-{seed}"
    log = tmp / f"{kind}-{seed}.io"
    cfg = _config(tmp / f"{kind}-{seed}.yaml", f"{kind}:{RATES[kind]}", seed)
    res: dict = {"kind": kind, "seed": seed}
    try:
        p = _capture(*PLAN, "--config", str(cfg), "--out", str(out), "--log-io", str(log))
    except subprocess.TimeoutExpired:
        return {**res, "outcome": "failed badly", "why": f"hung for {TIMEOUT_S} s"}
    res["exit"] = p.returncode
    res["driver_anomalies"] = sum(bool(ANOMALY.search(ln)) for ln in log.read_text(errors="replace").splitlines()) if log.exists() else 0
    errors = [ln for ln in p.stderr.splitlines() if ln.startswith("rig capture: error:")]
    if p.returncode == 0:
        s = Session.open(out)
        ok = s.complete and not s.verify()
        return {**res, "outcome": "survived" if ok else "failed badly", **({} if ok else {"why": "incomplete or corrupt"})}
    res["message"] = errors[0] if errors else p.stderr.strip().splitlines()[-1:]
    if "Traceback" in p.stderr or p.returncode not in (2, 3) or len(errors) != 1:
        return {**res, "outcome": "failed badly", "why": "no single clean error line"}
    if (out / "session.yaml").exists():
        if "--resume" not in errors[0]:
            return {**res, "outcome": "failed badly", "why": "the error line does not say how to resume"}
        again = ["--resume", str(out), "--config", str(clean_cfg), "--sim", "--no-progress"]
    elif out.exists() and any(out.iterdir()) and (out / "raw").exists() and any((out / "raw").iterdir()):
        return {**res, "outcome": "failed badly", "why": "frames written but no manifest"}
    else:  # the fault struck while the rig was opening: no session yet, the same command is run again
        res["before_session"] = True
        again = [*PLAN, "--config", str(clean_cfg), "--out", str(out)]
    before = _done(out) if (out / "session.yaml").exists() else {}
    res["stacks_before_fault"] = len(before)
    try:
        r = _capture(*again)
    except subprocess.TimeoutExpired:
        return {**res, "outcome": "failed badly", "why": "resume hung"}
    if r.returncode != 0:
        return {**res, "outcome": "failed badly", "why": f"resume exited {r.returncode}: {r.stderr.strip().splitlines()[-1:]}"}
    s = Session.open(out)
    after = _done(out)
    if not s.complete or s.verify() or any(after.get(k) != v for k, v in before.items()):
        return {**res, "outcome": "failed badly", "why": "resumed session incomplete, corrupt, or a completed stack changed"}
    return {**res, "outcome": "stopped cleanly"}


def main() -> int:
    runs = []
    with tempfile.TemporaryDirectory(prefix="bench-faults-") as tmp:
        tmpd = Path(tmp)
        world = cheap_world(tmpd)
        WORLD[:] = [world] if world is not None else []
        clean = _config(tmpd / "clean.yaml", "", 0)
        warm = _capture(*PLAN, "--config", str(clean), "--out", str(tmpd / "warm-up"))  # fills the render cache
        if warm.returncode != 0:
            raise SystemExit(f"fault-free capture failed: {warm.stderr.strip()}")
        for kind in RATES:
            for seed in SEEDS:
                r = _one(tmpd, kind, seed, clean)
                runs.append(r)
                msg = r.get("message") or ""
                print(f"{kind:<11} seed {seed}: {r['outcome']:<15} exit {r.get('exit', '-')!s:<3} "
                      f"anomalies {r.get('driver_anomalies', 0):<3} {r.get('why', '')}{str(msg)[:110]}")
    table = {}
    for kind, rate in RATES.items():
        rs = [r for r in runs if r["kind"] == kind]
        table[kind] = {
            "device": DEVICE[kind], "rate": rate, "runs": len(rs),
            "survived": sum(r["outcome"] == "survived" for r in rs),
            "stopped_cleanly": sum(r["outcome"] == "stopped cleanly" for r in rs),
            "stopped_before_session": sum(bool(r.get("before_session")) for r in rs),
            "failed_badly": sum(r["outcome"] == "failed badly" for r in rs),
            "driver_anomalies": sum(r.get("driver_anomalies", 0) for r in rs),
        }
    print(f"\n{'fault':<11}{'device':<8}{'rate':>6}{'runs':>6}{'survived':>10}{'stopped':>9}{'bad':>5}{'anomalies':>11}")
    for kind, t in table.items():
        print(f"{kind:<11}{t['device']:<8}{t['rate']:>6g}{t['runs']:>6}{t['survived']:>10}{t['stopped_cleanly']:>9}"
              f"{t['failed_badly']:>5}{t['driver_anomalies']:>11}")
    result = {
        "command": "rig capture " + " ".join(PLAN) + " --config FAULTY.yaml --out DIR; on a stop: --resume DIR with faults off",
        "scene": "cheap default world (rendered bench)" if WORLD else "analytic spot",
        "seeds": list(SEEDS), "table": table, "runs": runs,
        "failed_badly": sum(t["failed_badly"] for t in table.values()),
    }
    (ROOT / "benchmarks" / "results" / "bench_faults.json").write_text(json.dumps(result, indent=2) + "\n")
    return 0 if result["failed_badly"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
