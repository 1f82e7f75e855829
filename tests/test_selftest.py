"""``rig selftest`` against the twins (fast simulated time): a healthy rig passes, the
stage never leaves its range and ends where it started, a fault mid-run leaves the
stage stopped and the shutter closed, faults of the devices fail the right check,
the transcript holds the exchanges, and devices that cannot be opened give one line
naming the device and the fix."""

from __future__ import annotations

import argparse
import itertools
import math
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Self

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers import alta_protocol as ap
from drivers import shot_protocol as sp
from drivers.apogee_alta import AltaCamera
from drivers.errors import DeviceTimeout
from drivers.interfaces import AngleRange, ShutterMode
from drivers.iolog import Transcript
from rig import cli
from rig.commands import selftest as selftest_cmd
from rig.config import load_config
from rig.selftest import (
    STAGE_CHECKS,
    SelfTestOptions,
    level_adu,
    read_noise_adu,
    run_selftest,
    selftest_from_config,
    stage_test_points,
)
from rig.wiring import Rig, open_changer, open_stage, prepare_bench
from sim_devices.alta_usb import AltaBackend
from sim_devices.bench import drop_bench, get_bench
from sim_devices.ccd_sensor import CcdModel
from sim_devices.faults import FaultPlan

FAST = 1000.0  # simulated seconds per real second
HOME_DEG = 90.0
OPTS = SelfTestOptions(cooler_poll_s=0.005, cooler_wait_s=5.0)
_names = itertools.count()


@pytest.fixture
def bench():
    name = f"selftest-{next(_names)}"
    yield name
    drop_bench(name)


def write_config(tmp_path: Path, bench: str, *, stage_port: str = "sim", filter_port: str = "sim",
                 allowed: tuple[float, float] = (15.0, 185.0), faults: str = "") -> Path:
    p = tmp_path / f"{bench}.yaml"
    p.write_text(f"""
stage:
  driver: sigma-koki
  port: "{stage_port}"
  model: SHOT-702
  zero_offset_deg: {HOME_DEG}
  allowed_range_deg: [{allowed[0]}, {allowed[1]}]
  speed_deg_s: 10.0
camera:
  driver: apogee-alta
  cooler_setpoint_c: -20.0
filter:
  driver: fw102c
  port: "{filter_port}"
  positions: {{r: 1, g: 2, b: 3}}
  wavelengths_nm: {{r: 630, g: 530, b: 465}}
sim:
  bench: {bench}
  time_scale: {FAST}
  faults: "{faults}"
""")
    return p


def opener(backend: AltaBackend):
    """An ``open_rig`` whose camera is the given twin backend (so a test can hold it,
    deny access, or look at its shutter); stage and wheel come from the wiring."""

    def open_(cfg, *, sim: bool, log_io: str | None) -> Rig:
        tr = Transcript(log_io) if log_io else None
        prepare_bench(cfg)
        devs: list = []
        try:
            devs.append(open_stage(cfg, sim=True, transcript=tr))
            devs.append(AltaCamera(backend=backend, transcript=tr))
            devs.append(open_changer(cfg, sim=True, transcript=tr))
        except BaseException:
            for d in devs:
                d.close()
            if tr is not None:
                tr.close()
            raise
        return Rig(*devs, cfg, True, tr)

    return open_


def make_rig(tmp_path: Path, bench: str, backend: AltaBackend | None = None, **cfg_kw) -> tuple[Rig, AltaBackend]:
    cfg = load_config(write_config(tmp_path, bench, **cfg_kw))
    be = backend or AltaBackend(bench, time_scale=FAST, seed=3)
    return opener(be)(cfg, sim=True, log_io=str(tmp_path / f"{bench}.log")), be


def stage_twin(rig: Rig):
    return rig.stage._link._port.twin  # the Shot702Twin behind the sim-shot702:// port


def commanded_angles(rig: Rig) -> list[float]:
    """Every angle the controller was told to go to (A: targets, H: home), from the twin's log."""
    twin, stage = stage_twin(rig), rig.stage
    out = []
    for line in twin.commands:
        cmd = sp.parse_command(twin.model, line + sp.TERMINATOR)
        if isinstance(cmd, sp.Arm) and cmd.absolute:
            out.append(stage.angle_of_count(cmd.pulses[0]))
        elif isinstance(cmd, sp.Home):
            out.append(stage.home_angle())
    return out


class AngleSampler:
    """Samples the twin's physical angle in a thread while the self-test runs."""

    def __init__(self, twin) -> None:
        self.twin, self.angles, self._stop = twin, [], threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.angles.append(self.twin.angle_deg())
            time.sleep(0.0005)

    def __enter__(self) -> Self:
        self._t.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._t.join()


def by_name(report) -> dict:
    return {r.name: r for r in report.results}


# ----------------------------------------------------------------- a healthy rig


@pytest.mark.parametrize("allowed, start", [((15.0, 185.0), 100.0), ((85.0, 91.0), 86.0)])
def test_healthy_rig_passes_stays_in_range_and_ends_where_it_started(tmp_path, bench, allowed, start):
    rig, be = make_rig(tmp_path, bench, allowed=allowed)
    rng = AngleRange(*allowed)
    with rig:
        rig.stage.move_to(start)
        twin = stage_twin(rig)
        twin.commands.clear()
        with AngleSampler(twin) as sampler:
            report = run_selftest(rig, OPTS)
        assert report.ok, "\n".join(r.line() for r in report.results)
        assert all(r.status == "ok" for r in report.results), [r.line() for r in report.results if r.status != "ok"]
        names = [r.name for r in report.results]
        assert names == ["stage.identity", "camera.identity", "filter.identity", *STAGE_CHECKS,
                         "filter.r", "filter.g", "filter.b", "camera.cooler", "camera.bias", "camera.read_noise",
                         "camera.dark", "camera.shutter"]
        # never outside the range: every commanded target, and the angle sampled during the run
        targets = commanded_angles(rig)
        assert len(targets) >= 5 and all(t in rng for t in targets), targets
        assert len(sampler.angles) > 10
        assert min(sampler.angles) >= rng.lo - 1e-9 and max(sampler.angles) <= rng.hi + 1e-9
        # the small moves went both ways and the stage is back at its start, at rest
        moves = by_name(report)["stage.moves"].measured["targets_deg"]
        assert max(moves) - min(moves) > 0
        assert not twin.busy()
        assert twin.angle_deg() == pytest.approx(start, abs=rig.stage.degrees_per_count)
        # the filter that was in the beam is back, the shutter was forced closed at the end
        assert rig.changer.current() == "r"
        assert be.camera.forced_shutter() == "closed"
    assert be.camera.forced_shutter() is None  # close() returns the shutter to normal (closed when idle)


def test_measured_sensor_values_match_the_twin_sensor(tmp_path, bench):
    rig, _ = make_rig(tmp_path, bench)
    with rig:
        report = by_name(run_selftest(rig, OPTS))
    s = ap.KAF0261E
    assert report["camera.bias"].measured["bias_adu"] == pytest.approx(s.bias_adu, abs=0.5)
    assert report["camera.read_noise"].measured["read_noise_e"] == pytest.approx(s.read_noise_e, rel=0.03)
    dark = report["camera.dark"].measured
    assert dark["dark_current_e_per_s"] == pytest.approx(dark["expected_e_per_s"], rel=0.1)


# ----------------------------------------------------------------- checks that fail or warn


def test_a_camera_off_its_specs_fails_bias_and_read_noise(tmp_path, bench):
    be = AltaBackend(bench, time_scale=FAST, seed=5)
    be.ccd = CcdModel(sensor=replace(ap.KAF0261E, bias_adu=600.0, read_noise_e=40.0))
    rig, _ = make_rig(tmp_path, bench, backend=be)
    with rig:
        report = run_selftest(rig, OPTS)
    r = by_name(report)
    assert not report.ok
    assert r["camera.bias"].status == "fail" and r["camera.bias"].measured["bias_adu"] == pytest.approx(600, abs=1)
    assert r["camera.read_noise"].status == "fail"
    assert r["camera.read_noise"].fix and "-> fix:" in r["camera.read_noise"].line()
    assert r["stage.moves"].status == "ok"


def test_no_light_is_a_warning_and_a_stuck_shutter_a_failure(tmp_path, bench):
    rig, be = make_rig(tmp_path, bench)
    with rig:
        get_bench(bench).scene = lambda a, f, rows, cols: np.zeros((rows.stop - rows.start, cols.stop - cols.start))
        report = by_name(run_selftest(rig, OPTS))
    assert report["camera.shutter"].status == "warn"
    assert "no light" in report["camera.shutter"].message and "beam" in report["camera.shutter"].fix

    rig, be = make_rig(tmp_path, f"{bench}-stuck")
    try:
        with rig:
            # the shutter forced open behind the driver's back: light reaches the dark frames
            be.camera.regs[ap.Reg.OP_A] = be.camera.regs.get(ap.Reg.OP_A, 0) | ap.OP_A_FORCE_SHUTTER
            report = by_name(run_selftest(rig, OPTS))
    finally:
        drop_bench(f"{bench}-stuck")
    assert report["camera.shutter"].status == "fail"
    assert report["camera.shutter"].measured["lit_pixels_dark"] >= OPTS.min_lit_pixels


def test_a_cooler_still_cooling_is_reported_not_waited_for(tmp_path, bench):
    rig, _ = make_rig(tmp_path, bench)
    opts = replace(OPTS, cooler_wait_s=0.01)  # 10 simulated seconds: half way down
    t0 = time.monotonic()
    with rig:
        report = by_name(run_selftest(rig, opts))
    assert report["camera.cooler"].status == "warn"
    assert "still cooling" in report["camera.cooler"].message
    assert report["camera.cooler"].measured["cooled_by_c"] > 0.5
    # the dark current is judged at the temperature the darks were taken at
    assert report["camera.dark"].status == "ok"
    assert time.monotonic() - t0 < 10


# ----------------------------------------------------------------- faults mid-run


def test_interrupt_mid_move_stops_the_stage_and_closes_the_shutter(tmp_path, bench):
    # a slow stage (real time) so that the interrupt arrives while it moves
    port = f"sim-shot702://{bench}?timescale=1&zero_offset_deg={HOME_DEG}"
    rig, be = make_rig(tmp_path, bench, stage_port=port)
    with rig:
        twin = stage_twin(rig)
        original_wait = rig.stage.wait

        def wait(timeout_s: float) -> None:
            if twin.busy():
                raise KeyboardInterrupt
            original_wait(timeout_s)

        rig.stage.wait = wait  # type: ignore[method-assign]
        with pytest.raises(KeyboardInterrupt):
            run_selftest(rig, OPTS)
        lines = list(twin.commands)
        last_go = max(i for i, c in enumerate(lines) if c == b"G:")
        assert b"L:1" in lines[last_go:]
        deadline = time.monotonic() + 2.0
        while twin.busy():
            assert time.monotonic() < deadline, "the stage did not stop"
            time.sleep(0.01)
        angle = twin.angle_deg()
        assert HOME_DEG < angle < HOME_DEG + OPTS.stage_step_deg  # stopped part-way, inside the range
        assert be.camera.forced_shutter() == "closed"


def test_camera_fault_during_the_light_frame_leaves_the_shutter_closed(tmp_path, bench):
    rig, be = make_rig(tmp_path, bench)
    with rig:
        cam = rig.camera
        original = cam.expose

        def expose(seconds, *, dark=False, timeout_s=None):
            if not dark:  # the shutter is open when the camera stops answering
                cam.set_shutter(ShutterMode.OPEN)
                raise DeviceTimeout("image not done within the time limit", device="camera")
            return original(seconds, dark=dark, timeout_s=timeout_s)

        cam.expose = expose  # type: ignore[method-assign]
        report = run_selftest(rig, OPTS)
        r = by_name(report)
        assert r["camera.shutter"].status == "fail" and "DeviceTimeout" == r["camera.shutter"].measured["error"]
        assert be.camera.forced_shutter() == "closed"
        assert not stage_twin(rig).busy()
        assert r["stage.return"].status == "ok"


def test_camera_lost_mid_readout_is_reported_and_the_rest_still_runs(tmp_path, bench):
    be = AltaBackend(bench, time_scale=FAST, seed=1, faults=FaultPlan({"disconnect": 1.0}))
    rig, _ = make_rig(tmp_path, bench, backend=be)
    with rig:
        report = run_selftest(rig, OPTS)
        assert not stage_twin(rig).busy()
    r = by_name(report)
    assert r["camera.bias"].status == "fail" and "USB cable" in r["camera.bias"].message
    assert r["camera.dark"].status == "fail" and r["camera.dark"].message.startswith("not run")
    assert r["safety.shutter"].status == "fail"  # nothing to talk to: said so, not raised
    assert all(r[n].status == "ok" for n in (*STAGE_CHECKS, "filter.r", "filter.g", "filter.b"))


def test_limit_switch_mid_move_fails_the_moves_and_skips_the_return(tmp_path, bench, capsys):
    cfg = write_config(tmp_path, bench, faults="limit:1.0")
    rc = cli.main(["selftest", "--config", str(cfg), "--transcript", str(tmp_path / "t.log")])
    out = capsys.readouterr().out
    assert rc == 1
    lines = {ln.split()[1]: ln for ln in out.splitlines() if ln[:4].strip() in ("OK", "WARN", "FAIL")}
    assert lines["stage.moves"].startswith("FAIL") and "limit switch" in lines["stage.moves"]
    assert lines["stage.return"].startswith("FAIL") and "not run" in lines["stage.return"]
    assert "-> fix:" in lines["stage.moves"]


# ----------------------------------------------------------------- command line and transcript


def test_cli_prints_one_line_per_check_and_writes_the_transcript(tmp_path, bench, capsys):
    cfg = write_config(tmp_path, bench)
    log = tmp_path / "run.log"
    rc = cli.main(["selftest", "--config", str(cfg), "--transcript", str(log)])
    out = capsys.readouterr().out.splitlines()
    assert rc == 0, "\n".join(out)
    checks = [ln for ln in out if ln.startswith(("OK ", "WARN", "FAIL"))]
    assert len(checks) == 14 and all(ln.startswith("OK") for ln in checks)
    assert out[-1].startswith("selftest: 14 ok, 0 warn, 0 fail") and str(log) in out[-1]
    text = log.read_text()
    # the exchanges of all three devices, and the verdicts
    assert "stage    > ?:N\\r\\n" in text and "stage    < SHOT-702\\r\\n" in text
    assert "filter   > *idn?\\r" in text and "THORLABS FW102C" in text
    assert "camera   > REG CMD_A" in text and "bulk 0x86" in text
    assert "OK    stage.moves" in text and "selftest: 14 ok" in text


def test_cli_json(tmp_path, bench, capsys):
    import json

    cfg = write_config(tmp_path, bench)
    rc = cli.main(["selftest", "--config", str(cfg), "--transcript", str(tmp_path / "j.log"), "--json"])
    doc = json.loads(capsys.readouterr().out)
    assert rc == 0 and doc["ok"] and doc["counts"]["ok"] == len(doc["checks"]) == 14
    assert {"name", "status", "message", "measured", "expected", "fix"} <= set(doc["checks"][0])


def test_default_transcript_goes_to_the_current_folder(tmp_path, bench, capsys, monkeypatch):
    cfg = write_config(tmp_path, bench)
    work = tmp_path / "lab"
    work.mkdir()
    monkeypatch.chdir(work)
    assert cli.main(["selftest", "--config", str(cfg)]) == 0
    logs = list(work.glob("selftest-*.log"))
    assert len(logs) == 1 and "stage.identity" in logs[0].read_text()


@pytest.mark.parametrize("argv, needle", [
    (["--config", "/nonexistent/rig.yaml"], "no such file"),
    (["--transcript", "/nonexistent/dir/t.log"], "does not exist"),
    (["--transcript", "EXISTING"], "exists"),
])
def test_bad_input_is_one_line_exit_2(tmp_path, bench, capsys, argv, needle):
    cfg = write_config(tmp_path, bench)
    existing = tmp_path / "old.log"
    existing.write_text("keep me")
    argv = [str(existing) if a == "EXISTING" else a for a in argv]
    if "--config" not in argv:
        argv = ["--config", str(cfg), *argv]
    rc = cli.main(["selftest", *argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and needle in err[0]
    assert existing.read_text() == "keep me"


# ----------------------------------------------------------------- devices that cannot be opened


def test_port_answering_as_another_device(tmp_path, bench, capsys):
    port = f"sim-fw102c://{bench}?timescale={FAST}&idn=THORLABS%20PM100USB%20power%20meter"
    cfg = write_config(tmp_path, bench, filter_port=port)
    log = tmp_path / "idn.log"
    rc = cli.main(["selftest", "--config", str(cfg), "--transcript", str(log)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 3 and len(err) == 1, err
    line = err[0]
    assert f"filter wheel (FW102C on {port})" in line and "PM100USB" in line
    assert "-> fix:" in line and "rig devices --scan" in line and "filter.port" in line
    text = log.read_text()
    assert "*idn?" in text and "cannot open" in text  # the exchange that shows what answered


def _run_cmd(tmp_path, bench, backend) -> int:
    args = argparse.Namespace(config=str(write_config(tmp_path, bench)), sim=False,
                              transcript=str(tmp_path / "cam.log"), json=False)
    return selftest_cmd.run(args, open_rig=opener(backend))


def test_camera_busy_in_another_process(tmp_path, bench, capsys):
    be = AltaBackend(bench, time_scale=FAST)
    with AltaCamera(backend=be):  # another program holds interface 0
        rc = _run_cmd(tmp_path, bench, be)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 3 and len(err) == 1, err
    assert err[0].startswith("rig selftest: camera (Apogee Alta-U, USB 125c:0010)")
    assert "in use by another program" in err[0] and "-> fix:" in err[0] and "fuser" in err[0]


def test_camera_without_udev_permission(tmp_path, bench, capsys):
    be = AltaBackend(bench, time_scale=FAST)
    be.access_denied = True
    rc = _run_cmd(tmp_path, bench, be)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 3 and len(err) == 1, err
    assert "camera (Apogee Alta-U" in err[0] and "no permission" in err[0]
    assert "-> fix:" in err[0] and "udev" in err[0] and "99-apogee-alta.rules" in err[0]


def test_open_problem_is_raised_with_the_fix_from_the_api(tmp_path, bench):
    from drivers.errors import DeviceConnectionError

    be = AltaBackend(bench, time_scale=FAST)
    be.access_denied = True
    cfg = load_config(write_config(tmp_path, bench))
    with pytest.raises(DeviceConnectionError) as e:
        selftest_from_config(cfg, transcript_path=tmp_path / "x.log", open_rig=opener(be))
    assert e.value.device.startswith("camera") and "-> fix:" in str(e.value)


# ----------------------------------------------------------------- the arithmetic


@pytest.mark.parametrize("sigma_adu", [1.0, 5.0, 20.0])
def test_read_noise_from_two_bias_frames(sigma_adu):
    rng = np.random.default_rng(7)
    pattern = 250 + rng.normal(0, 3, (256, 256))  # fixed bias structure cancels in the difference
    pattern[rng.integers(0, 256, 40), rng.integers(0, 256, 40)] += 3000  # hot pixels, in both frames
    a = np.rint(pattern + rng.normal(0, sigma_adu, pattern.shape))
    b = np.rint(pattern + rng.normal(0, sigma_adu, pattern.shape))
    b[rng.integers(0, 256, 20), rng.integers(0, 256, 20)] += 5000  # cosmic rays in one frame only
    assert read_noise_adu(a, b) == pytest.approx(sigma_adu, rel=0.02)
    assert level_adu(a) == pytest.approx(250.0, abs=0.1)


@settings(max_examples=200, deadline=None)
@given(lo=st.floats(-170, 300), width=st.floats(0.01, 300), frac=st.floats(-0.5, 1.5), step=st.floats(0.001, 10))
def test_stage_test_points_stay_inside_the_range(lo, width, frac, step):
    r = AngleRange(lo, lo + width)
    around = lo + frac * width
    centre, s = stage_test_points(r, around, step)
    assert 0 < s <= step
    assert all(t in r for t in (centre - s, centre, centre + s))
    if width >= 4 * step and r.lo + step <= around <= r.hi - step:
        assert centre == around and s == step  # a wide range: the moves are centred on the home angle


def test_options_are_checked():
    with pytest.raises(ValueError):
        SelfTestOptions(stage_step_deg=-1)
    with pytest.raises(ValueError):
        SelfTestOptions(dark_exposures_s=())
    assert math.isfinite(SelfTestOptions().light_exposure_s)


def test_missing_serial_port_names_the_port_and_the_fix(tmp_path, bench, capsys):
    cfg = write_config(tmp_path, bench, stage_port=str(tmp_path / "ttyUSB-gone"))
    rc = cli.main(["selftest", "--config", str(cfg), "--transcript", str(tmp_path / "gone.log")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 3 and len(err) == 1, err
    assert "stage (SHOT-702 on" in err[0] and "does not exist" in err[0]
    assert "-> fix:" in err[0] and "rig devices --scan" in err[0]


def test_manual_filter_changer_is_not_driven(tmp_path, bench):
    p = write_config(tmp_path, bench)
    p.write_text(p.read_text().replace('driver: fw102c\n  port: "sim"', "driver: manual"))
    cfg = load_config(p)
    assert cfg.filter.driver == "manual"
    asked: list[str] = []
    be = AltaBackend(bench, time_scale=FAST, seed=2)
    rig = opener(be)(cfg, sim=True, log_io=None)
    rig.changer._ask = asked.append  # the operator is never asked during a self-test
    with rig:
        report = by_name(run_selftest(rig, OPTS))
    assert report["filter.identity"].status == "ok"
    assert report["filter.positions"].status == "ok" and "manual" in report["filter.positions"].message
    assert asked == [] and all(r.status == "ok" for r in report.values())
