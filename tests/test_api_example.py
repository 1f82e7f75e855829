"""The Python API's example script runs end to end on the simulated rig (quick mode),
and the API raises the command line's one-line errors."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_example_script_runs_the_whole_job(tmp_path):
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, str(ROOT / "examples" / "simulated_session.py"), str(out), "--quick"],
                       capture_output=True, text=True, timeout=900, cwd=tmp_path, stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "checksums OK: True" in r.stdout
    assert (out / "session" / "report.html").is_file()
    assert list((out / "session" / "estimates").glob("*/results.yaml"))
    assert list((out / "session" / "diagnoses").glob("*/diagnosis.yaml"))


def test_api_bad_input_raises_the_one_line_error(tmp_path):
    from rig import api
    from rig.cli import _user_errors
    from rig.errors import UsageError

    with pytest.raises(_user_errors()) as e:
        api.capture(tmp_path / "s", angles=0, filters="r", sim=True)
    assert "\n" not in str(e.value)
    assert not (tmp_path / "s").exists()
    with pytest.raises(UsageError):
        api.load_results(tmp_path)
    with pytest.raises(_user_errors()):
        api.estimate(tmp_path / "missing-session")
