"""SigmaKokiStage against its byte-level twin: the shared interface suite for the
SHOT-702 and GSC-01, then the driver's own duties (limit switches, faults,
ambiguous commands, timeouts, identity, the pty path)."""

from __future__ import annotations

import io
import itertools
import threading
import time

import pytest
import serial

import sim_devices  # noqa: F401 - registers sim-shot702://
from drivers import shot_protocol as sp
from drivers.errors import (
    DeviceConnectionError,
    DeviceError,
    DeviceTimeout,
    LimitError,
    ParameterError,
    ProtocolError,
    StateError,
)
from drivers.interfaces import AngleRange
from drivers.iolog import Transcript
from drivers.sigma_koki import SigmaKokiStage
from sim_devices.bench import drop_bench, get_bench
from sim_devices.serial_twin import SimClock, serve_on_pty
from sim_devices.shot702 import Profile, Shot702Twin, trapezoid
from tests.stage_suite import ALLOWED, RotationStageSuite

TIMESCALE = 500.0
HOME_DEG = 90.0
_names = itertools.count()


@pytest.fixture
def bench_name():
    name = f"stage-test-{next(_names)}"
    yield name
    drop_bench(name)


@pytest.fixture
def opened():
    stages: list = []
    yield stages
    for s in stages:
        try:
            s.close()
        except DeviceError:
            pass


def url(bench: str, model: str = "SHOT-702", **opts: object) -> str:
    q = "&".join(f"{k}={v}" for k, v in {"model": model, "timescale": TIMESCALE,
                                          "zero_offset_deg": HOME_DEG, **opts}.items())
    return f"sim-shot702://{bench}?{q}"


def open_stage(opened, bench, model="SHOT-702", allowed=ALLOWED, twin_opts=None, **kw) -> SigmaKokiStage:
    kw.setdefault("zero_offset_deg", HOME_DEG)
    kw.setdefault("speed_deg_s", 10.0)
    kw.setdefault("reply_timeout_s", 0.05)
    s = SigmaKokiStage(url(bench, model, **(twin_opts or {})), allowed=allowed, model=model, **kw)
    opened.append(s)
    return s


# ------------------------------------------------------------------ shared interface suite


@pytest.fixture(params=["SHOT-702", "GSC-01"])
def make_stage(request, opened, bench_name):
    # A reply timeout ten times the fault tests' 0.05 s: the twin answers at once, but under a
    # loaded CI (renders beside the tests) its thread can be late; the shared suite tests motion.
    return lambda allowed: open_stage(opened, bench_name, request.param, allowed, reply_timeout_s=0.5)


@pytest.fixture
def slow_speed_deg_s():
    return 0.5


class TestRotationStageInterface(RotationStageSuite):
    pass


# ------------------------------------------------------------------ URL handler and twin


def test_url_handler_is_found_under_its_hyphenated_name(bench_name):
    port = serial.serial_for_url(url(bench_name), timeout=0.2)
    try:
        assert type(port).__module__.endswith("protocol_sim-shot702")
        port.write(b"?:N\r\n")
        assert port.readline() == b"SHOT-702\r\n"
    finally:
        port.close()


@pytest.mark.parametrize("bad", ["model=SHOT-999", "colour=red", "limits=5", "timescale=0", "faults=fire:0.1"])
def test_bad_twin_url_is_a_connection_error(opened, bench_name, bad):
    with pytest.raises(DeviceConnectionError):
        SigmaKokiStage(f"sim-shot702://{bench_name}?{bad}", allowed=ALLOWED)


def test_trapezoid_profile_timing():
    # 10000 steps, start 500/s, top 5000/s, 0.2 s ramps: ramps cover 550 steps each.
    segs = trapezoid(10000, 500, 5000, 0.2)
    p = Profile(0.0, 0.0, 1, segs)
    assert p.duration == pytest.approx(0.4 + (10000 - 2 * 550) / 5000)
    assert p.end_position == pytest.approx(10000)
    xs = [p.position(t) for t in [i * p.duration / 50 for i in range(51)]]
    assert all(b >= a for a, b in itertools.pairwise(xs)) and xs[-1] == pytest.approx(10000)
    tri = Profile(0.0, 0.0, -1, trapezoid(100, 500, 5000, 0.2))  # too short to reach top speed
    assert len(tri.segments) == 2 and tri.end_position == pytest.approx(-100)


def test_twin_refuses_commands_while_busy_and_cancels_armed_moves(bench_name):
    port = serial.serial_for_url(url(bench_name, timescale=1.0), timeout=0.2)

    def ask(line: bytes) -> bytes:
        port.write(line + b"\r\n")
        return port.readline()

    try:
        assert ask(b"A:1+P40000") == b"OK\r\n"
        assert ask(b"L:1") == b"OK\r\n"       # cancels the armed move
        assert ask(b"G:") == b"NG\r\n"        # nothing armed
        assert ask(b"A:1+P40000") == b"OK\r\n"
        assert ask(b"G:") == b"OK\r\n"
        assert ask(b"!:") == b"B\r\n"
        for refused in (b"D:1S100F1000R100", b"?:V", b"A:1+P0", b"H:1", b"S:12"):
            assert ask(refused) == b"NG\r\n"
        assert sp.parse_status(sp.MODELS["SHOT-702"], ask(b"Q:")).accepted is False
        assert ask(b"L:1") == b"OK\r\n"
        assert ask(b"Q:").endswith(b",K,K,B\r\n")  # decelerating
    finally:
        port.close()


def test_bench_follows_the_physical_angle_including_a_hidden_zero_offset(opened, bench_name):
    # The twin's origin sits 1.5 deg away from where the driver's configuration says.
    s = open_stage(opened, bench_name, twin_opts={"zero_offset_deg": HOME_DEG + 1.5})
    s.move_to(120.0)
    assert s.angle() == pytest.approx(120.0)
    assert get_bench(bench_name).stage_angle_deg == pytest.approx(121.5)


def test_two_twins_on_one_bench_share_it(opened, bench_name):
    other = Shot702Twin(SimClock(TIMESCALE), bench=bench_name, zero_offset_deg=10.0)
    assert get_bench(bench_name).stage_angle_deg == pytest.approx(10.0)
    s = open_stage(opened, bench_name)
    s.move_to(100.0)
    assert get_bench(bench_name).stage_angle_deg == pytest.approx(100.0)
    assert other.angle_deg() == pytest.approx(10.0)  # touching the other twin publishes its own angle
    assert get_bench(bench_name).stage_angle_deg == pytest.approx(10.0)


def test_division_and_speed_are_sent_at_connection(opened, bench_name):
    s = open_stage(opened, bench_name, division=20, speed_deg_s=2.0)
    twin = s._link._port.twin  # test-only peek at what the controller received
    assert b"S:120" in twin.commands
    assert b"D:1S4000F8000R100" in twin.commands  # 2 deg/s / (0.005/20 deg) = 8000 pps, start at half
    s.move_to(100.0)
    assert twin.angle_deg() == pytest.approx(100.0)


def test_gsc01_speed_is_rounded_to_its_steps_and_bounded(opened, bench_name):
    s = open_stage(opened, bench_name, "GSC-01", speed_deg_s=1.0)
    assert b"D:1S200F400R100" in s._link._port.twin.commands
    with pytest.raises(LimitError):
        s.set_speed(100.0)  # 40000 pps > 20000


def test_gsc02_moves_relatively_without_acknowledgements(opened, bench_name):
    s = open_stage(opened, bench_name, "GSC-02")
    s.move_to(100.0)
    s.move_to(80.0)
    assert s.angle() == pytest.approx(80.0)
    s.home()
    assert s.angle() == pytest.approx(HOME_DEG)
    cmds = s._link._port.twin.commands
    assert b"M:1+P4000" in cmds and b"M:1-P8000" in cmds and b"H:1+" in cmds
    assert not any(c.startswith(b"A:") for c in cmds)


def test_wrong_model_is_a_connection_error(opened, bench_name):
    with pytest.raises(DeviceConnectionError, match="GSC-01"):
        SigmaKokiStage(url(bench_name, "GSC-01"), allowed=ALLOWED, model="SHOT-702", reply_timeout_s=0.05)


def test_identity_and_transcript(opened, bench_name):
    log = io.StringIO()
    s = open_stage(opened, bench_name, transcript=Transcript(stream=log), twin_opts={"version": "V2.06"})
    assert s.identity() == "SHOT-702 V2.06"
    s.move_to(95.0)
    text = log.getvalue()
    assert "stage    > ?:N\\r\\n" in text and "stage    < SHOT-702\\r\\n" in text
    assert "> A:1+P2000\\r\\n" in text and "> G:\\r\\n" in text


def test_stray_nul_before_first_reply(opened, bench_name):
    s = open_stage(opened, bench_name, twin_opts={"stray_nul": 1})
    assert s.identity().startswith("SHOT-702")


@pytest.mark.parametrize("kw", [{"model": "SHOT-999"}, {"axis": 3}, {"division": 3}, {"degrees_per_pulse": 0.0},
                                {"zero_offset_deg": float("nan")}, {"accel_ms": 5000}, {"retries": -1},
                                {"speed_deg_s": 0.0}])
def test_bad_arguments_are_refused_before_opening(kw):
    # The URL would fail to open: a ParameterError proves nothing was opened.
    with pytest.raises(ParameterError):
        SigmaKokiStage("sim-shot702://x?colour=red", allowed=ALLOWED, **kw)


def test_speed_outside_the_controller_range_is_a_limit_error():
    with pytest.raises(LimitError):
        SigmaKokiStage("sim-shot702://x?colour=red", allowed=ALLOWED, model="GSC-01", speed_deg_s=500.0)


def test_target_is_rounded_inward_at_the_range_edges(opened, bench_name):
    s = open_stage(opened, bench_name, allowed=AngleRange(15.0012, 100.0))
    s.move_to(15.0012)  # the nearest count is 15.0000, outside: the driver takes 15.0025
    assert s.angle() == pytest.approx(15.0025)
    assert s.angle() in s.allowed_range


# ------------------------------------------------------------------ limit switches


def test_limit_switch_mid_move_raises_and_stage_can_come_back(opened, bench_name):
    # Switches 4000 counts (10 deg at division 2) each side of the origin.
    s = open_stage(opened, bench_name, twin_opts={"limits": "-4000:4000"})
    with pytest.raises(LimitError, match="limit switch"):
        s.move_to(120.0)
    assert s.angle() == pytest.approx(HOME_DEG + 10.0)
    assert get_bench(bench_name).stage_angle_deg == pytest.approx(HOME_DEG + 10.0)
    assert s.status().limits == {1}
    s.move_to(95.0)  # away from the switch: allowed, and the flag clears
    assert s.angle() == pytest.approx(95.0) and s.status().limits == frozenset()
    with pytest.raises(LimitError):
        s.move_to(60.0)
    assert s.angle() == pytest.approx(HOME_DEG - 10.0)


def test_injected_limit_fault_stops_part_way(opened, bench_name):
    s = open_stage(opened, bench_name, twin_opts={"faults": "limit:1.0", "seed": 3})
    with pytest.raises(LimitError):
        s.move_to(150.0)
    assert HOME_DEG < s.angle() < 150.0


# ------------------------------------------------------------------ injected faults


@pytest.mark.parametrize("faults, seed", [("drop:0.1", 1), ("garble:0.1", 2), ("drop:0.05,garble:0.05", 3)])
def test_driver_rides_through_lost_and_garbled_replies(opened, bench_name, faults, seed):
    s = open_stage(opened, bench_name, retries=4, twin_opts={"faults": faults, "seed": seed})
    twin = s._link._port.twin
    for target in (120.0, 60.0, 150.0, 30.0, 95.0):
        s.move_to(target)
        assert twin.angle_deg() == pytest.approx(target)
        assert s.angle() == pytest.approx(target)
    assert sum(twin.faults.counts.values()) > 3  # the faults did happen
    # No move was driven twice: one G: per move (a resend happens only if the first did not start).
    assert sum(c == b"G:" for c in twin.commands) <= 5 + twin.faults.counts.get("drop", 0)


@pytest.mark.parametrize("seed", range(3))
def test_heavy_faults_give_only_typed_errors_and_never_leave_the_range(opened, bench_name, seed):
    s = None
    try:
        s = open_stage(opened, bench_name, retries=1, twin_opts={"faults": "drop:0.3,garble:0.2,ng:0.1", "seed": seed})
    except DeviceError:
        return  # typed refusal to connect is acceptable
    twin = s._link._port.twin
    for target in (40.0, 170.0, 100.0, 20.0):
        try:
            s.move_to(target)
        except (DeviceTimeout, ProtocolError, StateError):
            try:
                s.wait(5.0)
            except DeviceError:
                pass
        assert ALLOWED.lo - 1e-9 <= twin.angle_deg() <= ALLOWED.hi + 1e-9


def test_ng_names_the_refused_command(bench_name):
    with pytest.raises(ProtocolError, match=r"'S:12'.*NG"):
        SigmaKokiStage(url(bench_name, faults="ng:1.0"), allowed=ALLOWED, reply_timeout_s=0.05)


def test_silent_controller_times_out_quickly(bench_name):
    t0 = time.monotonic()
    with pytest.raises(DeviceConnectionError, match="no SHOT-702 answers"):
        SigmaKokiStage(url(bench_name, faults="drop:1.0"), allowed=ALLOWED, reply_timeout_s=0.05, retries=2)
    assert time.monotonic() - t0 < 0.5  # 3 attempts x 0.05 s


# ------------------------------------------------------------------ ambiguous commands, over a pty


class ScriptedTwin(Shot702Twin):
    """Drops the reply to chosen commands (by their text), once each."""

    def __init__(self, *a, drop_once: tuple[bytes, ...] = (), **kw) -> None:
        self._drop = list(drop_once)
        self._last_line = b""
        super().__init__(*a, **kw)

    def _execute(self, line: bytes) -> None:
        self._last_line = line
        super()._execute(line)

    def should_fault(self, kind, cmd):
        if kind == "drop" and self._last_line in self._drop:
            self._drop.remove(self._last_line)
            return True
        return super().should_fault(kind, cmd)


@pytest.fixture
def pty_twin(bench_name):
    served = []

    def serve(**kw):
        twin = ScriptedTwin(SimClock(TIMESCALE), bench=bench_name, zero_offset_deg=HOME_DEG, **kw)
        path, stop = serve_on_pty(twin)
        stage = SigmaKokiStage(path, allowed=ALLOWED, zero_offset_deg=HOME_DEG, speed_deg_s=10.0,
                               reply_timeout_s=0.1)
        served.append((stage, stop))
        return twin, stage, stop

    yield serve
    for stage, stop in served:
        try:
            stage.close()  # while the pty is still served
        except DeviceError:
            pass
        stop.set()


def test_lost_reply_to_go_does_not_drive_twice(pty_twin):
    twin, s, _ = pty_twin(drop_once=(b"G:",))
    s.move_to(150.0)
    assert s.angle() == pytest.approx(150.0)
    assert list(twin.commands).count(b"G:") == 1


def test_lost_reply_to_arm_cancels_before_arming_again(pty_twin):
    twin, s, _ = pty_twin(drop_once=(b"A:1+P24000",))
    s.move_to(150.0)
    assert s.angle() == pytest.approx(150.0)
    cmds = list(twin.commands)
    i = cmds.index(b"A:1+P24000")
    assert cmds[i + 1: i + 3] == [b"L:1", b"A:1+P24000"]
    assert cmds.count(b"G:") == 1


def test_lost_reply_to_home_does_not_home_twice(pty_twin):
    twin, s, _ = pty_twin(drop_once=(b"H:1",))
    s.move_to(150.0)
    s.home()
    assert s.angle() == pytest.approx(HOME_DEG)
    assert list(twin.commands).count(b"H:1") == 1


def test_controller_that_goes_silent_mid_session_times_out(pty_twin):
    _, s, stop = pty_twin()
    s.move_to(100.0)
    stop.set()  # the cable is pulled
    time.sleep(0.02)
    t0 = time.monotonic()
    with pytest.raises(DeviceError):
        s.angle()
    assert time.monotonic() - t0 < 1.0


def test_unmodified_pyserial_client_in_another_thread(bench_name):
    twin = Shot702Twin(SimClock(TIMESCALE), bench=bench_name)
    path, stop = serve_on_pty(twin)
    replies: list[bytes] = []

    def client() -> None:
        with serial.Serial(path, baudrate=38400, rtscts=True, timeout=1.0) as port:
            for line in (b"?:N", b"A:1+P4000", b"G", b"Q:"):
                port.write(line + b"\r\n")
                replies.append(port.readline())

    try:
        t = threading.Thread(target=client)
        t.start()
        t.join(10.0)
        assert not t.is_alive()
    finally:
        stop.set()
    assert replies[:3] == [b"SHOT-702\r\n", b"OK\r\n", b"OK\r\n"]
    assert sp.parse_status(twin.model, replies[3]).positions[1] == 0
    deadline = time.monotonic() + 5.0
    while twin.busy():
        assert time.monotonic() < deadline
        time.sleep(0.01)
    assert twin.angle_deg() == pytest.approx(10.0)  # 4000 counts x 0.0025 deg


def test_twin_jog_division_change_and_electrical_zero(bench_name):
    port = serial.serial_for_url(url(bench_name, timescale=1000.0, limits="-8000:8000"), timeout=0.2)
    model = sp.MODELS["SHOT-702"]

    def ask(line: bytes) -> bytes:
        port.write(line + b"\r\n")
        return port.readline()

    def wait_ready() -> sp.StatusReply:
        deadline = time.monotonic() + 5.0
        while (st := sp.parse_status(model, ask(b"Q:"))).busy:
            assert time.monotonic() < deadline
            time.sleep(0.005)
        return st

    try:
        twin = port.twin
        assert ask(b"J:1+") == b"OK\r\n" and ask(b"G") == b"OK\r\n"
        st = wait_ready()  # a jog runs at the start speed until the +20 deg switch
        assert st.positions[0] == 8000 and st.limits == {1}
        assert twin.angle_deg() == pytest.approx(HOME_DEG + 20.0)
        assert ask(b"S:120") == b"OK\r\n"  # finer division: same count, same place
        assert wait_ready().positions[0] == 8000 and twin.angle_deg() == pytest.approx(HOME_DEG + 20.0)
        assert ask(b"A:1+P0") == b"OK\r\n" and ask(b"G:") == b"OK\r\n"
        assert wait_ready().positions[0] == 0
        # 8000 counts at division 20 are 2 deg: back at +18 deg, off the switch.
        assert twin.angle_deg() == pytest.approx(HOME_DEG + 18.0)
        assert ask(b"R:1") == b"OK\r\n"
        assert wait_ready().positions[0] == 0 and twin.angle_deg() == pytest.approx(HOME_DEG + 18.0)
        assert ask(b"H:1") == b"OK\r\n"
        st = wait_ready()
        assert st.positions[0] == 0 and st.limits == frozenset()
        assert twin.angle_deg() == pytest.approx(HOME_DEG)
        assert get_bench(bench_name).stage_angle_deg == pytest.approx(HOME_DEG)
    finally:
        port.close()


def test_twin_emergency_stop_halts_at_once(bench_name):
    port = serial.serial_for_url(url(bench_name, timescale=1.0), timeout=0.2)
    try:
        for line in (b"A:1+P40000", b"G:"):
            port.write(line + b"\r\n")
            assert port.readline() == b"OK\r\n"
        time.sleep(0.05)
        port.write(b"L:E\r\n")
        assert port.readline() == b"OK\r\n"
        port.write(b"!:\r\n")
        assert port.readline() == b"R\r\n"  # no deceleration ramp
        assert 0 < port.twin.angle_deg() - HOME_DEG < 1.0
    finally:
        port.close()


def test_range_narrower_than_one_count_refuses_every_move(opened, bench_name):
    s = open_stage(opened, bench_name, allowed=AngleRange(90.0011, 90.0019))
    with pytest.raises(LimitError, match="no position count"):
        s.move_to(90.0015)
