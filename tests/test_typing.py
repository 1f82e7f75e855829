"""The annotations hold: mypy over the packages estimate, rig, drivers, capture, calibrate and
sim_devices and over the benchmark scripts in benchmarks/ (pyproject.toml's [tool.mypy]), so
the typed public API stays true as the code changes and the benchmarks keep to it. About 11 s
from a cold cache on 2 cores (the benchmarks add little: mypy reads the packages anyway)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_packages_type_check(tmp_path: Path) -> None:
    # A cache of its own: the run sees the code as it is, whatever an earlier run left.
    run = subprocess.run([sys.executable, "-m", "mypy", "--cache-dir", str(tmp_path / "mypy-cache")],
                         cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "Success: no issues found" in run.stdout
