"""Filter changers: the FW102C driver against its twin through real bytes (URL
handler and pty), the manual changer with a scripted operator, fault injection,
and the shared FilterChanger suite run against both."""

from __future__ import annotations

import io
import subprocess
import sys
import textwrap
import threading
import time
import uuid
from collections.abc import Callable, Iterator

import pytest
import serial
from filter_suite import POSITIONS, FilterChangerSuite

import sim_devices  # noqa: F401 - registers sim-fw102c://
from drivers import fw102c_protocol as proto
from drivers.errors import (
    DeviceConnectionError,
    DeviceError,
    DeviceTimeout,
    LimitError,
    ParameterError,
    ProtocolError,
    StateError,
)
from drivers.fw102c import FW102C
from drivers.iolog import Transcript
from drivers.manual_filter import MAX_UNCLEAR_ANSWERS, ManualFilterChanger
from sim_devices.bench import Bench, drop_bench, set_bench
from sim_devices.faults import FaultPlan
from sim_devices.fw102c import FW102CTwin
from sim_devices.serial_twin import SimClock, serve_on_pty

TIME_SCALE = 100.0  # 1 s per position on the twin -> 10 ms
POSITION_TIME_S = 1.0 / TIME_SCALE  # what the driver is told: the same wheel, seen at that scale


class QuickFW102C(FW102C):
    """The driver with a short reply deadline, so that dropped replies cost little.
    The twin answers in-process within a millisecond."""

    reply_timeout_s = 0.1


@pytest.fixture
def bench() -> Iterator[tuple[str, Bench]]:
    name = f"fw{uuid.uuid4().hex[:10]}"
    b = set_bench(name, Bench(time_scale=TIME_SCALE, filter_by_position={p: n for n, p in POSITIONS.items()}))
    yield name, b
    drop_bench(name)


def url(bench_name: str, **query: object) -> str:
    q = "&".join(f"{k}={v}" for k, v in {"timescale": TIME_SCALE, **query}.items())
    return f"sim-fw102c://{bench_name}?{q}"


def sent_lines(log: io.StringIO) -> list[str]:
    """Byte strings the driver wrote, as logged by the transcript."""
    out = []
    for line in log.getvalue().splitlines():
        parts = line.split(None, 3)
        if len(parts) >= 3 and parts[2] == ">":
            out.append(parts[3] if len(parts) > 3 else "")
    return out


def read_exchange(port: serial.Serial) -> bytes:
    return port.read_until(proto.PROMPT)


# --------------------------------------------------------------------------- the shared suite


class TestFW102CInterface(FilterChangerSuite):
    @pytest.fixture
    def log(self) -> io.StringIO:
        return io.StringIO()

    @pytest.fixture
    def changer(self, bench, log) -> Iterator[FW102C]:
        wheel = FW102C(url(bench[0]), positions=POSITIONS, transcript=Transcript(stream=log),
                       position_time_s=POSITION_TIME_S)
        yield wheel
        wheel.close()

    @pytest.fixture
    def activity(self, log) -> Callable[[], int]:
        return lambda: len(sent_lines(log))


class ScriptedOperator:
    """Answers prompts from a list (Enter when it runs out); records what was shown."""

    def __init__(self, answers: list[str] | None = None, *, eof_after: int | None = None) -> None:
        self.answers = list(answers or [])
        self.prompts: list[str] = []
        self.messages: list[str] = []
        self.eof_after = eof_after

    def ask(self, prompt: str) -> str:
        self.prompts.append(prompt)
        if self.eof_after is not None and len(self.prompts) > self.eof_after:
            raise EOFError
        return self.answers.pop(0) if self.answers else ""

    def say(self, message: str) -> None:
        self.messages.append(message)


class TestManualInterface(FilterChangerSuite):
    @pytest.fixture
    def operator(self) -> ScriptedOperator:
        return ScriptedOperator()

    @pytest.fixture
    def changer(self, operator) -> ManualFilterChanger:
        return ManualFilterChanger(POSITIONS, ask=operator.ask, say=operator.say)

    @pytest.fixture
    def activity(self, operator) -> Callable[[], int]:
        return lambda: len(operator.prompts) + len(operator.messages)


# --------------------------------------------------------------------------- FW102C on the twin


def test_open_reads_identity_count_speed_and_position(bench) -> None:
    log = io.StringIO()
    with FW102C(url(bench[0], pcount=12, pos=5), positions={"r": 1, "g": 2, "b": 3, "ir": 12},
                transcript=Transcript(stream=log), position_time_s=POSITION_TIME_S) as wheel:
        assert wheel.identity() == "THORLABS FW102C/FW212C Filter Wheel version 1.07"
        assert wheel.position_count == 12
        assert wheel.high_speed
        assert wheel.current() is None  # position 5 has no name
        assert sent_lines(log)[:5] == [r"\r", r"*idn?\r", r"pcount?\r", r"speed?\r", r"pos?\r"]
        wheel.select("ir")
        assert wheel.current() == "ir"
        assert r"pos=12\r" in sent_lines(log)


def test_select_sets_the_bench_filter(bench) -> None:
    name, b = bench
    with FW102C(url(name), positions=POSITIONS, position_time_s=POSITION_TIME_S) as wheel:
        assert b.filter_name == "r"  # the wheel starts at 1
        for f in ["b", "g", "r"]:
            wheel.select(f)
            assert b.filter_name == f  # set by the time select returns


def test_wheel_starts_where_the_bench_filter_is(bench) -> None:
    name, b = bench
    b.filter_name = "g"
    with FW102C(url(name), positions=POSITIONS, position_time_s=POSITION_TIME_S) as wheel:
        assert wheel.current() == "g"


def test_select_waits_for_the_wheel(bench) -> None:
    """1 -> 4 on a 6-position wheel is 3 positions: the prompt cannot come before 30 ms."""
    with FW102C(url(bench[0]), positions={"r": 1, "x": 4}, position_time_s=POSITION_TIME_S) as wheel:
        t = time.monotonic()
        wheel.select("x")
        assert time.monotonic() - t >= 3 * POSITION_TIME_S


def test_move_timeout_follows_short_way_travel(bench) -> None:
    with FW102C(url(bench[0], pcount=12), positions={"a": 1}, position_time_s=0.5) as wheel:
        assert wheel.travel(1, 12) == 1 and wheel.travel(12, 1) == 1
        assert wheel.travel(1, 7) == 6 and wheel.travel(3, 5) == 2
        assert wheel.travel(None, 5) == 6
        base = wheel.reply_timeout_s
        assert wheel.move_timeout_s(1, 1) == pytest.approx(base)
        assert wheel.move_timeout_s(3, 5) == pytest.approx(base + wheel.move_safety_factor * 2 * 0.5)
        assert wheel.move_timeout_s(1, 12) < wheel.move_timeout_s(1, 4)


def test_positions_beyond_the_wheel_are_refused(bench) -> None:
    with pytest.raises(LimitError, match="6-position"):
        FW102C(url(bench[0]), positions={"r": 1, "uv": 7})


@pytest.mark.parametrize("kwargs", [
    {"positions": {"r": 0}}, {"positions": {"r": 1}, "position_time_s": 0.0},
    {"positions": {"r": 1}, "retries": -1}, {"positions": {"r": 1, "g": 1}},
])
def test_bad_arguments_fail_before_opening(kwargs) -> None:
    with pytest.raises(ParameterError):
        FW102C("sim-fw102c://never-opened?bogus=1", **kwargs)


def test_port_answering_as_another_device(bench) -> None:
    with pytest.raises(DeviceConnectionError, match=r"answers as 'ACME Shutter 2\.0', not a FW102C"):
        FW102C(url(bench[0], idn="ACME%20Shutter%202.0"), positions=POSITIONS)


def test_silent_port_is_a_connection_error_within_its_deadline() -> None:
    """``loop://`` echoes every byte and never prompts: a port with something else on it."""
    t = time.monotonic()
    with pytest.raises(DeviceConnectionError, match="nothing on port loop://"):
        QuickFW102C("loop://", positions=POSITIONS, retries=1)
    # wake + 2 identity attempts, each bounded by the reply deadline
    assert time.monotonic() - t < 3 * QuickFW102C.reply_timeout_s + 1.0


def test_bad_url_is_a_connection_error() -> None:
    with pytest.raises(DeviceConnectionError, match="cannot open port"):
        FW102C("sim-fw102c://x?pcout=6", positions=POSITIONS)


def test_refusing_wheel_at_open(bench) -> None:
    with pytest.raises(DeviceConnectionError, match="CMD_NOT_DEFINED"):
        FW102C(url(bench[0], faults="ng:1"), positions=POSITIONS)


def test_twin_line_settings_must_match(bench) -> None:
    port = serial.serial_for_url(url(bench[0]), baudrate=9600, timeout=0.05)
    try:
        port.write(b"*idn?\r")
        assert read_exchange(port) == b""
        port.baudrate = 115200
        port.write(b"*idn?\r")
        assert read_exchange(port).startswith(b"*idn?\rTHORLABS")
    finally:
        port.close()


def test_closed_wheel_refuses_queries(bench) -> None:
    wheel = FW102C(url(bench[0]), positions=POSITIONS, position_time_s=POSITION_TIME_S)
    wheel.close()
    wheel.close()
    with pytest.raises(StateError):
        wheel.current()


# --------------------------------------------------------------------------- the twin's physics


def test_twin_short_way_round_and_speed() -> None:
    twin = FW102CTwin(SimClock(1e6), pcount=12, position=1)
    assert twin.travel(1, 12) == 1 and twin.travel(2, 9) == 5 and twin.travel(1, 7) == 6
    twin.write(b"pos=11\r")
    m = twin.moves[-1]
    assert m.t_end - m.t_start == pytest.approx(2 * 1.0)
    twin.write(b"speed=0\r")
    twin.write(b"pos=8\r")
    m = twin.moves[-1]
    assert m.t_end - m.t_start == pytest.approx(3 * 2.0)  # slow speed: 2 s per position
    assert m.t_start >= twin.moves[-2].t_end  # commands wait for the wheel


def test_twin_bench_filter_is_none_while_turning() -> None:
    bench = Bench(filter_by_position={1: "r", 2: "g"})
    clock = SimClock(10.0)  # 1 position = 0.1 s real
    twin = FW102CTwin(clock, bench=bench, position=1)
    assert bench.filter_name == "r"
    twin.write(b"pos=2\r")
    assert bench.filter_name is None
    out = b""
    deadline = time.monotonic() + 2.0
    while not out.endswith(proto.PROMPT) and time.monotonic() < deadline:
        out += twin.read_ready()
        time.sleep(0.002)
    assert out == b"pos=2\r> "
    assert clock.now() >= 1.0
    assert bench.filter_name == "g"


def test_twin_sets_bench_on_arrival_without_being_read() -> None:
    bench = Bench(filter_by_position={1: "r", 2: "g"})
    twin = FW102CTwin(SimClock(50.0), bench=bench, position=1)
    twin.write(b"pos=2\r")
    deadline = time.monotonic() + 2.0
    while bench.filter_name != "g" and time.monotonic() < deadline:
        time.sleep(0.005)
    assert bench.filter_name == "g"


def test_twin_settings_and_errors() -> None:
    twin = FW102CTwin(SimClock(1e9), pcount=6)

    def ask(cmd: bytes) -> bytes:
        twin.write(cmd)
        return twin.read_ready()

    assert ask(b"pcount=12\r") == b"pcount=12\r> "
    assert ask(b"pcount?\r") == b"pcount?\r12\r> "
    assert ask(b"pcount=7\r") == b"pcount=7\rCommand error CMD_ARG_INVALID\n\r> "
    assert ask(b"trig=1\r") == b"trig=1\r> "
    assert ask(b"trig?\r") == b"trig?\r1\r> "
    assert ask(b"sensors=2\r") == b"sensors=2\rCommand error CMD_ARG_INVALID\n\r> "
    assert ask(b"pos=x\r") == b"pos=x\rCommand error CMD_ARG_INVALID\n\r> "
    assert ask(b"foo?\r") == b"foo?\rCommand error CMD_NOT_DEFINED\n\r> "
    assert ask(b"save\r") == b"save\r> "
    assert twin.saved == {"speed": 1, "sensors": 0, "trig": 1, "pcount": 12}


# --------------------------------------------------------------------------- the twin on a pty


def test_unmodified_pyserial_client_in_a_thread_over_pty() -> None:
    bench = Bench(filter_by_position={1: "r", 2: "g", 3: "b"})
    twin = FW102CTwin(SimClock(TIME_SCALE), bench=bench, position=1)
    path, stop = serve_on_pty(twin)
    got: list[bytes] = []

    def client() -> None:
        with serial.Serial(path, 115200, timeout=2.0) as port:
            for cmd in [b"*idn?\r", b"pos=3\r", b"pos?\r", b"pos=9\r"]:
                port.write(cmd)
                got.append(port.read_until(b"> "))

    try:
        th = threading.Thread(target=client, daemon=True)
        th.start()
        th.join(timeout=10)
        assert not th.is_alive()
    finally:
        stop.set()
    assert got == [
        b"*idn?\rTHORLABS FW102C/FW212C Filter Wheel version 1.07\r> ",
        b"pos=3\r> ",
        b"pos?\r3\r> ",
        b"pos=9\rCommand error CMD_ARG_INVALID\n\r> ",
    ]
    assert bench.filter_name == "b"


def test_unmodified_pyserial_client_in_another_process_over_pty() -> None:
    twin = FW102CTwin(SimClock(TIME_SCALE), position=2)
    path, stop = serve_on_pty(twin)
    script = textwrap.dedent(f"""
        import serial
        with serial.Serial({path!r}, 115200, timeout=2.0) as port:
            port.write(b"pos?\\r")
            print(repr(port.read_until(b"> ")))
    """)
    try:
        res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=20)
    finally:
        stop.set()
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == repr(b"pos?\r2\r> ")


@pytest.fixture
def pty_wheel() -> Iterator[tuple[FW102CTwin, Callable[..., FW102C]]]:
    """A twin on a pty and a factory for drivers that talk to it (the real pyserial Serial)."""
    bench = Bench(filter_by_position={1: "r", 2: "g", 3: "b"})
    twin = FW102CTwin(SimClock(TIME_SCALE), bench=bench, position=1)
    path, stop = serve_on_pty(twin)
    opened: list[FW102C] = []

    def make(**kw) -> FW102C:
        w = QuickFW102C(path, positions=POSITIONS, position_time_s=POSITION_TIME_S, **kw)
        opened.append(w)
        return w

    yield twin, make
    for w in opened:
        w.close()
    stop.set()


class ScriptedFaults(FaultPlan):
    """Faults on chosen commands: {command index: {"drop"|"garble"|"ng", ...}};
    ``inbound`` picks the direction of a garble."""

    def __init__(self, script: dict[int, set[str]], *, inbound: bool = False, seed: int = 0,
                 corrupt: Callable[[bytes], bytes] | None = None) -> None:
        super().__init__({}, seed)
        self.script = script
        self.inbound = inbound
        self.corrupt = corrupt
        self.index = -1

    def garble(self, data: bytes) -> bytes:
        return self.corrupt(data) if self.corrupt else super().garble(data)

    def hit(self, kind: str) -> bool:
        if kind == "drop":  # the twin draws drop first for every command
            self.index += 1
        if kind in self.script.get(self.index, set()):
            self.counts[kind] = self.counts.get(kind, 0) + 1
            return True
        return False

    def uniform(self, lo: float, hi: float) -> float:
        return lo if self.inbound else hi


def test_driver_over_pty(pty_wheel) -> None:
    twin, make = pty_wheel
    wheel = make()
    assert proto.is_fw102c(wheel.identity())
    wheel.select("b")
    assert wheel.current() == "b" and twin.bench.filter_name == "b"


def test_refusal_is_a_protocol_error_and_not_retried(pty_wheel) -> None:
    twin, make = pty_wheel
    wheel = make()
    twin.faults = FaultPlan({"ng": 1.0})
    with pytest.raises(ProtocolError, match="refused 'pos=3' with 'Command error CMD_ARG_INVALID'"):
        wheel.select("b")
    assert twin.log.count(b"pos=3") == 1


def test_dropped_move_answer_is_read_back_not_resent(pty_wheel) -> None:
    twin, make = pty_wheel
    wheel = make()
    n = len(twin.log)
    twin.faults = ScriptedFaults({0: {"drop"}})  # the answer to pos=3 never comes
    wheel.select("b")
    assert twin.log[n:] == [b"pos=3", b"pos?", b"pos?"]  # new reading: confirmed twice
    assert wheel.current() == "b"


def test_garbled_command_is_resent(pty_wheel) -> None:
    twin, make = pty_wheel
    wheel = make()
    n = len(twin.log)
    twin.faults = ScriptedFaults({0: {"garble"}}, inbound=True, seed=4)
    wheel.select("b")
    first = twin.log[n]
    assert first != b"pos=3"  # what the wheel heard
    assert twin.log[-1] == b"pos=3" and twin.log.count(b"pos=3") == 1
    assert wheel.current() == "b" and twin.bench.filter_name == "b"


@pytest.mark.parametrize("seed", [0, 1])
def test_garbled_or_dropped_query_is_retried(pty_wheel, seed: int) -> None:
    twin, make = pty_wheel
    wheel = make()
    n = len(twin.log)
    twin.faults = ScriptedFaults({0: {"garble"}, 1: {"drop"}}, seed=seed)
    assert wheel.current() == "r"
    assert twin.log[n:n + 3] == [b"pos?"] * 3
    assert twin.faults.counts == {"garble": 1, "drop": 1}


def test_silent_digit_flip_is_caught_by_a_second_read(pty_wheel) -> None:
    """'1' -> '3' is one bit and passes every check; the known position exposes it."""
    twin, make = pty_wheel
    wheel = make()
    n = len(twin.log)
    twin.faults = ScriptedFaults({0: {"garble"}}, corrupt=lambda d: d.replace(b"\r1\r", b"\r3\r"))
    assert wheel.current() == "r"
    assert twin.log[n:] == [b"pos?"] * 3  # 3 (new: read again), 1, 1 (agree)
    assert twin.faults.counts == {"garble": 1}


def test_query_gives_up_after_its_retries(pty_wheel) -> None:
    twin, make = pty_wheel
    wheel = make(retries=1)
    n = len(twin.log)
    twin.faults = FaultPlan({"drop": 1.0})
    t = time.monotonic()
    with pytest.raises(DeviceTimeout, match="after 2 attempts"):
        wheel.current()
    assert time.monotonic() - t < 2 * QuickFW102C.reply_timeout_s + 1.0
    assert twin.log[n:] == [b"pos?", b"pos?"]


def test_jammed_wheel_times_out(pty_wheel) -> None:
    twin, make = pty_wheel
    wheel = make(retries=0)
    twin.position_time_s = 1000.0  # 10 s real per position: far beyond the driver's estimate
    t = time.monotonic()
    with pytest.raises(DeviceTimeout):
        wheel.select("b")
    elapsed = time.monotonic() - t
    assert elapsed < wheel.move_timeout_s(1, 3) + 2 * QuickFW102C.reply_timeout_s + 1.0
    with pytest.raises(DeviceTimeout):
        wheel.select("g", timeout_s=0.05)  # an explicit deadline is honoured too


@pytest.mark.parametrize("seed", [1, 2])
def test_random_faults_end_in_success_or_typed_errors(bench, seed: int) -> None:
    """Seeded drops, garbles and refusals: every call either does the right thing
    (checked against the bench, the simulated truth) or raises a DeviceError."""
    name, b = bench
    wheel = None
    for attempt in range(5):  # opening itself may fail under faults
        try:
            wheel = QuickFW102C(url(name, faults="drop:0.08,garble:0.08,ng:0.02", seed=seed * 10 + attempt),
                                positions=POSITIONS, position_time_s=POSITION_TIME_S)
            break
        except DeviceError:
            continue
    assert wheel is not None
    ok = failed = 0
    try:
        for f in ["g", "b", "r", "b", "g", "r"] * 3:
            try:
                wheel.select(f)
                assert b.filter_name == f
                assert wheel.current() == f
                ok += 1
            except (DeviceTimeout, ProtocolError):
                failed += 1
    finally:
        wheel.close()
    assert ok >= 12, (ok, failed)


# --------------------------------------------------------------------------- manual changer


def test_manual_asks_and_remembers() -> None:
    op = ScriptedOperator(["", "y"])
    ch = ManualFilterChanger(POSITIONS, ask=op.ask, say=op.say)
    assert ch.identity() == "manual filter changer"
    assert ch.current() is None
    ch.select("g")
    assert "'g'" in op.prompts[0] and "slot 2" in op.prompts[0]
    assert ch.current() == "g"
    ch.select("g")  # already in: nobody is asked
    assert len(op.prompts) == 1
    ch.select("b")
    assert ch.current() == "b" and len(op.prompts) == 2


def test_manual_unclear_answer_is_asked_again() -> None:
    op = ScriptedOperator(["maybe", " Y "])
    ch = ManualFilterChanger(POSITIONS, ask=op.ask, say=op.say)
    ch.select("r")
    assert ch.current() == "r"
    assert len(op.prompts) == 2 and len(op.messages) == 1


def test_manual_gives_up_on_endless_unclear_answers() -> None:
    op = ScriptedOperator(["?"] * 100)
    ch = ManualFilterChanger(POSITIONS, ask=op.ask, say=op.say)
    with pytest.raises(StateError, match="unclear"):
        ch.select("r")
    assert len(op.prompts) == MAX_UNCLEAR_ANSWERS + 1
    assert ch.current() is None


@pytest.mark.parametrize("op", [ScriptedOperator(["", "q"]), ScriptedOperator([""], eof_after=1)])
def test_manual_abort(op: ScriptedOperator) -> None:
    ch = ManualFilterChanger(POSITIONS, ask=op.ask, say=op.say)
    ch.select("r")
    with pytest.raises(StateError):
        ch.select("g")
    assert ch.current() is None  # the operator may have taken 'r' out


def test_manual_default_io_is_the_terminal() -> None:
    ch = ManualFilterChanger(POSITIONS)
    assert ch._ask is input and ch._say is print
