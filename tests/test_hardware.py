"""The self-test's checks on the real rig: ``pytest -m hardware tests/test_hardware.py``.

Which rig comes from the environment:

- ``RIG_CONFIG=/path/to/rig.yaml``: the real rig's configuration; or
- ``RIG_STAGE_PORT`` and/or ``RIG_WHEEL_PORT``: the serial ports, every other
  setting (and a port not given) from ``configs/rig-real.yaml``.

Without any of them the hardware tests are skipped; they are deselected by
default anyway (``-m 'not hardware'`` in pyproject.toml). Each test opens the
rig itself (the camera can be held by one handle only), uses the same check
functions as ``rig selftest``, and leaves the stage stopped and the shutter
closed. Byte transcripts go to ``RIG_TRANSCRIPT_DIR`` when set (to send with a
report), else to pytest's temporary folder.

The tests without the hardware marker check how the environment is read.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping
from pathlib import Path

import pytest
import yaml

from drivers.errors import DeviceError
from drivers.interfaces import ROI, ShutterMode
from rig.config import RigConfig, load_config, parse_config
from rig.selftest import (
    SelfTestOptions,
    check_bias_and_noise,
    check_cooler,
    check_dark,
    check_filters,
    check_identity,
    check_shutter,
    check_stage_motion,
    describe_open_problem,
    expected_identities,
    selftest_from_config,
)
from rig.wiring import Rig, open_rig

REAL_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "rig-real.yaml"
OPTIONS = SelfTestOptions()
SKIP_REASON = "no rig in the environment: set RIG_CONFIG, or RIG_STAGE_PORT / RIG_WHEEL_PORT"


def hardware_config(env: Mapping[str, str] = os.environ) -> RigConfig | None:
    """The real rig's configuration from the environment, or None when it names none."""
    if env.get("RIG_CONFIG"):
        return load_config(env["RIG_CONFIG"])
    stage_port, wheel_port = env.get("RIG_STAGE_PORT"), env.get("RIG_WHEEL_PORT")
    if not (stage_port or wheel_port):
        return None
    raw = yaml.safe_load(REAL_CONFIG.read_text(encoding="utf-8"))
    if stage_port:
        raw["stage"]["port"] = stage_port
    if wheel_port:
        raw["filter"]["port"] = wheel_port
    return parse_config(raw, f"{REAL_CONFIG.name} with ports from the environment")


def _transcript_dir(tmp_path: Path) -> Path:
    d = os.environ.get("RIG_TRANSCRIPT_DIR")
    return Path(d) if d else tmp_path


@pytest.fixture
def hw_config() -> RigConfig:
    cfg = hardware_config()
    if cfg is None:
        pytest.skip(SKIP_REASON)
    return cfg


@pytest.fixture
def rig(hw_config: RigConfig, tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[Rig]:
    log = _transcript_dir(tmp_path) / f"hardware-{request.node.name}.log"
    problem = None
    try:
        opened = open_rig(hw_config, log_io=str(log))
    except DeviceError as e:
        problem = str(describe_open_problem(e, hw_config))
    if problem is not None:  # one line naming the device and the fix, outside the except block
        pytest.fail(problem, pytrace=False)
    try:
        yield opened
    finally:
        # whatever the test did: the stage stands still and the shutter is closed
        try:
            opened.stage.stop()
            opened.camera.set_shutter(ShutterMode.CLOSED)
        finally:
            opened.close()


def _lines(results) -> str:
    return "\n".join(r.line() for r in results)


@pytest.mark.hardware
def test_identities(rig: Rig):
    expected = expected_identities(rig.config, rig.camera)
    results = [check_identity(role, dev, expected[role])
               for role, dev in (("stage", rig.stage), ("camera", rig.camera), ("filter", rig.changer))]
    assert all(r.status == "ok" for r in results), _lines(results)


@pytest.mark.hardware
def test_stage_homes_moves_inside_its_range_and_returns(rig: Rig):
    start = rig.stage.angle()
    results = list(check_stage_motion(rig.stage, OPTIONS))
    assert [r.name for r in results] == ["stage.home", "stage.moves", "stage.return"], _lines(results)
    assert all(r.status != "fail" for r in results), _lines(results)
    r = rig.stage.allowed_range
    for t in results[1].measured["targets_deg"]:
        assert t in r
    assert rig.stage.angle() in r
    if start in r:
        assert results[2].status == "ok", _lines(results)


@pytest.mark.hardware
def test_every_filter_position(rig: Rig):
    before = rig.changer.current()
    results = list(check_filters(rig.changer))
    assert results and all(r.status == "ok" for r in results), _lines(results)
    if before is not None:
        assert rig.changer.current() == before


@pytest.mark.hardware
def test_cooler_switches_on_and_cools(rig: Rig):
    result = check_cooler(rig.camera, rig.config.camera.cooler_setpoint_c, OPTIONS)
    assert result.status != "fail", result.line()


@pytest.mark.hardware
def test_bias_read_noise_dark_and_shutter(rig: Rig):
    cam = rig.camera
    cam.set_roi(ROI(0, 0, cam.sensor.width, cam.sensor.height))
    results, pair = check_bias_and_noise(cam, OPTIONS)
    results.append(check_dark(cam, pair, OPTIONS))
    results.append(check_shutter(cam, pair, OPTIONS))  # "no light" is a warning: the beam may be off
    assert all(r.status != "fail" for r in results), _lines(results)


@pytest.mark.hardware
def test_full_selftest_passes_and_writes_its_transcript(hw_config: RigConfig, tmp_path: Path):
    path = _transcript_dir(tmp_path) / "hardware-selftest.log"
    problem = None
    try:
        report = selftest_from_config(hw_config, transcript_path=path)
    except DeviceError as e:
        problem = str(e)
    if problem is not None:
        pytest.fail(problem, pytrace=False)
    assert report.ok, _lines(report.results)
    text = path.read_text()
    assert "stage    >" in text and "filter" in text and "camera   >" in text
    assert report.summary().split(";")[0] in text


# ----------------------------------------------------------------- reading the environment (no hardware)


def test_no_environment_means_no_rig():
    assert hardware_config({}) is None


def test_ports_from_the_environment_override_the_real_config():
    real = load_config(REAL_CONFIG)
    cfg = hardware_config({"RIG_STAGE_PORT": "/dev/ttyS7"})
    assert cfg is not None
    assert cfg.stage.port == "/dev/ttyS7" and cfg.filter.port == real.filter.port
    assert cfg.stage.allowed_range_deg == real.stage.allowed_range_deg
    cfg = hardware_config({"RIG_WHEEL_PORT": "/dev/serial/by-id/usb-FTDI-wheel"})
    assert cfg is not None and cfg.filter.port.endswith("wheel") and cfg.stage.port == real.stage.port


def test_rig_config_from_the_environment_wins(tmp_path: Path):
    p = tmp_path / "rig.yaml"
    raw = yaml.safe_load(REAL_CONFIG.read_text())
    raw["stage"]["port"] = "/dev/ttyUSB9"
    p.write_text(yaml.safe_dump(raw))
    cfg = hardware_config({"RIG_CONFIG": str(p), "RIG_STAGE_PORT": "/dev/ttyS0"})
    assert cfg is not None and cfg.stage.port == "/dev/ttyUSB9"
