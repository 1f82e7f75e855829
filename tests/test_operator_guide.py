"""Every command of docs/operator-guide.md runs, in order, against the simulated rig.

The guide is written for the real rig (`--config rig.yaml`); here `rig.yaml` names the
byte-level twins and a cheap copy of the default world (a few samples per pixel), so the
commands run exactly as printed. The only change: the fitting commands get budget flags
(fewer iterations, samples and profile columns) so the test stays fast; they are listed in FAST_FLAGS.
"""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "docs" / "operator-guide.md"
FAST_FLAGS = {
    "estimate": ["--max-iterations", "3", "--spp-max", "64", "--polish-steps", "1", "--final-spp", "128",
                 "--columns", "64"],
    "diagnose": ["--spp", "32", "--no-plots"],
}


def guide_commands() -> list[list[str]]:
    """The `$ rig ...` lines of the guide's console blocks, in order."""
    text = GUIDE.read_text(encoding="utf-8")
    cmds = []
    for block in re.findall(r"```console\n(.*?)```", text, flags=re.DOTALL):
        for line in block.splitlines():
            if line.startswith("$ rig "):
                cmds.append(shlex.split(line[2:]))
    return cmds


def test_the_guide_shows_the_whole_job():
    names = [c[1] for c in guide_commands()]
    for step in ("doctor", "devices", "selftest", "snap", "calibrate-beam", "capture", "info",
                 "estimate", "diagnose", "report"):
        assert step in names, f"the guide never shows rig {step}"


@pytest.mark.slow
def test_every_guide_command_runs_on_the_simulated_rig(tmp_path):
    from sim_devices.world import write_quick_world

    world = write_quick_world(tmp_path / "world.yaml", cache_dir=tmp_path / "render-cache")
    cfg = yaml.safe_load((ROOT / "configs" / "rig-sim.yaml").read_text())
    cfg["sim"]["world"] = str(world)
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))

    rig = [sys.executable, "-m", "rig.cli"]
    for cmd in guide_commands():
        argv = cmd[1:] + FAST_FLAGS.get(cmd[1], [])
        r = subprocess.run(rig + argv, check=False, cwd=tmp_path, capture_output=True, text=True, timeout=600,
                           stdin=subprocess.DEVNULL)
        assert r.returncode == 0, f"`{shlex.join(cmd)}` exited {r.returncode}:\n{r.stderr[-2000:]}"
        assert "Traceback" not in r.stderr
    session = tmp_path / "sessions" / "slab"
    assert (session / "session.yaml").is_file()
    assert list((session / "estimates").glob("*/results.yaml"))
    assert (session / "report.html").is_file()
