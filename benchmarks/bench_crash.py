"""Crash safety: SIGKILL the capture process at random moments, then ``--resume`` until complete.

Each trial starts a small simulated capture (3 angles x 2 filters, an 8-row
band, 3-frame brackets, time scale 1000) in a subprocess and kills it with
SIGKILL at a seeded random moment: a quarter of the kills uniformly over the
start-up of an unkilled run (imports, connections, session creation), the rest
uniformly over its capture, timed from the moment this run writes its first
manifest (creates it, or records the resumption), so kills land during moves,
exposures, merges, file writes and manifest updates. With probability 1/2 the following resume is
killed too (at most twice per trial); the last resume runs to the end.

After every kill the manifest is read (when one exists; a kill before the
first manifest leaves an "unborn" directory and the original command is simply
run again in it). Checked after each step and at the end:

* every stack done before a kill is still done afterwards with the same
  ``completed`` timestamp and checksums, and its files keep their mtime and
  content (nothing lost, redone or rewritten);
* the final session is complete, ``Session.verify()`` finds every checksum
  correct, no temporary file is left, every HDR image reads back, and ``rig info`` exits 0.

The camera sees a cheap copy of the default world (few samples per pixel,
renders cached on disk after a warm-up run) when the rendered bench is
installed, else the analytic spot. Writes benchmarks/results/bench_crash.json.
"""

from __future__ import annotations

import json
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import TypedDict

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from capture.atomic import is_temp_name
from capture.errors import SessionError
from capture.session import Session
from rig.config import PACKAGED_SIM_CONFIG

SEED = 20261121
TRIALS = 24
EARLY_FRACTION = 0.25
PLAN = ["--angles", "3", "--filters", "rg", "--band-rows", "8", "--max-exposures", "3", "--darks", "1",
        "--no-progress", "--sim"]


class Trial(TypedDict):
    """One trial's entry in the results."""

    trial: int
    kills: int
    runs: int
    kill_phases: list[str]
    stacks_done_before_final_resume: int
    ok: bool
    violations: list[str]


def cheap_world(tmp: Path) -> Path | None:
    """A cheap copy of the default world (renders cached under ``tmp``), or None without the
    rendered bench: these runs test robustness, not the physics."""
    try:
        from sim_devices.world import write_quick_world
    except ImportError:
        return None
    return write_quick_world(tmp / "cheap-world.yaml", cache_dir=tmp / "cache")


def _cmd(cfg: Path, *rest: str) -> list[str]:
    return [sys.executable, "-m", "rig.cli", "capture", "--config", str(cfg), *rest]


def _done(out: Path) -> dict[str, dict]:
    """Done stacks: completion time, checksums, and (mtime, size) of their files."""
    if not (out / "session.yaml").exists():
        return {}
    s = Session.open(out)
    res = {}
    for r in s.stacks():
        if r.done:
            stat = {f.file: ((out / f.file).stat().st_mtime_ns, (out / f.file).stat().st_size) for f in r.files.values()}
            res[r.id] = {"completed": r.completed, "sha": {k: f.sha256 for k, f in r.files.items()}, "stat": stat}
    return res


def _manifest_mtime(out: Path) -> int | None:
    try:
        return (out / "session.yaml").stat().st_mtime_ns
    except FileNotFoundError:
        return None


def _run_killed(cmd: list[str], out: Path, kill: tuple[str, float] | None) -> tuple[int, str, float]:
    """Run ``cmd``; ``kill`` = ("start", t): SIGKILL t s after start; ("manifest", t): t s after this
    run first writes the manifest (creates it, or records the resumption). Returns (exit status, stderr,
    seconds from start to the manifest write or -1)."""
    before = _manifest_mtime(out)
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    t_manifest = -1.0
    deadline = None if kill is None or kill[0] != "start" else t0 + kill[1]
    while p.poll() is None:
        now = time.perf_counter()
        if t_manifest < 0 and _manifest_mtime(out) != before:
            t_manifest = now - t0
            if kill is not None and kill[0] == "manifest":
                deadline = now + kill[1]
        if deadline is not None and now >= deadline:
            p.send_signal(signal.SIGKILL)
            break
        time.sleep(0.002)
    _, err = p.communicate(timeout=300)
    if t_manifest < 0 and _manifest_mtime(out) != before:
        t_manifest = time.perf_counter() - t0
    return p.returncode, err, t_manifest


def main() -> int:
    rng = random.Random(SEED)
    results: list[Trial] = []
    with tempfile.TemporaryDirectory(prefix="bench-crash-") as tmp:
        tmpd = Path(tmp)
        data = yaml.safe_load(PACKAGED_SIM_CONFIG.read_text())
        data["sim"]["time_scale"] = 1000.0
        world = cheap_world(tmpd)
        if world is not None:
            data["sim"]["world"] = str(world)
        cfg = tmpd / "rig.yaml"
        cfg.write_text(yaml.safe_dump(data))
        _run_killed(_cmd(cfg, *PLAN, "--out", str(tmpd / "warm-up")), tmpd / "warm-up", None)  # fills the render cache
        t0 = time.perf_counter()
        rc, err, start_s = _run_killed(_cmd(cfg, *PLAN, "--out", str(tmpd / "baseline")), tmpd / "baseline", None)
        capture_s = time.perf_counter() - t0 - start_s
        if rc != 0:
            raise SystemExit(f"baseline capture failed: {err.strip()}")
        print(f"unkilled run: {start_s:.2f} s to the first manifest, then {capture_s:.2f} s of capture")

        def draw() -> tuple[str, float]:
            # a quarter of the kills during start-up and session creation, the rest during the capture
            if rng.random() < EARLY_FRACTION:
                return ("start", rng.uniform(0.0, start_s))
            return ("manifest", rng.uniform(0.0, capture_s))

        for trial in range(TRIALS):
            out = tmpd / f"t{trial:02d}"
            create = _cmd(cfg, *PLAN, "--out", str(out))
            resume = _cmd(cfg, "--resume", str(out), "--sim", "--no-progress")
            kills, runs = 0, 0
            phases: list[str] = []
            violations: list[str] = []
            seen: dict[str, dict] = {}
            cmd = create
            extra_kills = 0
            kill_at: tuple[str, float] | None = draw()
            while True:
                runs += 1
                rc, err, _ = _run_killed(cmd, out, kill_at)
                killed = rc == -signal.SIGKILL
                if not killed and rc != 0:
                    violations.append(f"run {runs} exited {rc}: {err.strip().splitlines()[-1:] }")
                    break
                try:
                    now = _done(out)
                except SessionError as e:
                    violations.append(f"after run {runs}: {e}")
                    break
                for sid, rec in seen.items():
                    if now.get(sid) != rec:
                        violations.append(f"stack {sid} changed after run {runs}: {rec} -> {now.get(sid)}")
                if killed:
                    kills += 1
                    phases.append("before manifest" if not (out / "session.yaml").exists()
                                  else f"{len(now)} stacks done")
                seen = now
                if not killed:
                    break
                cmd = resume if (out / "session.yaml").exists() else create
                if extra_kills < 2 and rng.random() < 0.5:
                    extra_kills += 1
                    kill_at = draw()
                else:
                    kill_at = None
            ok = not violations
            if ok:
                s = Session.open(out)
                problems = s.verify()
                if not s.complete or problems:
                    violations.append(f"final session complete={s.complete}, problems={problems}")
                stray = [f.name for f in out.rglob("*") if is_temp_name(f.name)]
                if stray:
                    violations.append(f"temporary files left behind: {stray}")
                for stack, img in s.iter_hdr():
                    if img["radiance"].shape != tuple(s.manifest["frame_shape"]):
                        violations.append(f"{stack.id}: HDR shape {img['radiance'].shape}")
                info = subprocess.run([sys.executable, "-m", "rig.cli", "info", str(out)], check=False, cwd=ROOT, capture_output=True)
                if info.returncode != 0:
                    violations.append(f"rig info exited {info.returncode}")
            results.append({"trial": trial, "kills": kills, "runs": runs, "kill_phases": phases,
                            "stacks_done_before_final_resume": len(seen), "ok": not violations, "violations": violations})
            print(f"trial {trial:2d}: {kills} kill(s) at [{'; '.join(phases) or 'process had ended'}], "
                  f"{runs} run(s): {'OK' if not violations else 'FAIL ' + violations[0]}")

    total_kills = sum(r["kills"] for r in results)
    summary = {
        "seed": SEED,
        "trials": len(results),
        "kills": total_kills,
        "kills_before_manifest": sum(p == "before manifest" for r in results for p in r["kill_phases"]),
        "kills_mid_capture": sum(p != "before manifest" for r in results for p in r["kill_phases"]),
        "trials_completed": sum(r["ok"] for r in results),
        "stacks_lost_redone_or_corrupted": sum(len(r["violations"]) for r in results),
        "unkilled_run_s": {"to_first_manifest": round(start_s, 2), "capture": round(capture_s, 2)},
        "scene": "cheap default world (rendered bench)" if world is not None else "analytic spot",
        "command": "rig capture " + " ".join(PLAN) + " --out DIR  (time_scale 1000), SIGKILL, then --resume DIR",
        "results": results,
    }
    print(f"\n{summary['trials']} trials, {total_kills} SIGKILLs ({summary['kills_before_manifest']} before the first "
          f"manifest, {summary['kills_mid_capture']} later); sessions completed: {summary['trials_completed']}/"
          f"{summary['trials']}; stacks lost/redone/corrupted: {summary['stacks_lost_redone_or_corrupted']}")
    out = ROOT / "benchmarks" / "results" / "bench_crash.json"
    out.write_text(json.dumps(summary, indent=2) + "\n")
    return 0 if summary["trials_completed"] == summary["trials"] else 1


if __name__ == "__main__":
    sys.exit(main())
