"""Sigma Koki byte protocol: golden lines from shared/reference/device-protocols.md
(and the vendor's Micro-Manager adapter), round trips, and fuzzing of every parser."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers import shot_protocol as sp
from drivers.errors import ProtocolError

SHOT702 = sp.MODELS["SHOT-702"]
SHOT304 = sp.MODELS["SHOT-304GS"]
GSC01 = sp.MODELS["GSC-01"]
GSC02 = sp.MODELS["GSC-02"]


# ----------------------------------------------------------------- golden status lines


def test_documented_status_line_with_minus_sign_columns():
    st = sp.parse_status(SHOT702, b"-    50000,-    50000,K,K,R\r\n")
    assert st == sp.StatusReply((-50000, -50000), True, frozenset(), False)


@pytest.mark.parametrize(
    "field, value",
    [("-    50000", -50000), ("+    50000", 50000), ("     50000", 50000), ("         0", 0),
     ("-268435455", -268435455), (" 268435455", 268435455)],
)
def test_sign_column_blank_plus_or_minus(field, value):
    assert sp.parse_position(field) == value


@pytest.mark.parametrize("field", ["-   50000", "-     50000", "-  5 0000 ", "*    50000", "    -50000", "          "])
def test_malformed_position_fields(field):
    with pytest.raises(ProtocolError):
        sp.parse_position(field)


def test_status_line_lengths_match_the_vendor_adapter():
    # The vendor's Micro-Manager adapter tells models apart by the Q: length:
    # 16 (one axis), 27 (two axes), 49 (four axes), terminator excluded.
    for model, n in ((GSC01, 16), (SHOT702, 27), (SHOT304, 49)):
        line = sp.format_status(model, sp.StatusReply((0,) * model.axes, True, frozenset(), False))
        assert len(line) - 2 == n


@pytest.mark.parametrize("ack2, axes", [("K", set()), ("L", {1}), ("M", {2}), ("W", {1, 2})])
def test_two_axis_limit_letters(ack2, axes):
    st = sp.parse_status(SHOT702, f"     12345,-        1,K,{ack2},B\r\n".encode())
    assert st.limits == axes and st.busy and st.positions == (12345, -1)


@pytest.mark.parametrize("ack2, axes", [("K", set()), ("1", {1}), ("5", {1, 3}), ("A", {2, 4}), ("E", {2, 3, 4}),
                                        ("W", {1, 2, 3, 4}), ("F", {1, 2, 3, 4})])
def test_shot304gs_limit_bitmask(ack2, axes):
    line = ",".join([sp.format_position(i) for i in (1, 2, 3, 4)] + ["K", ack2, "R"]) + "\r\n"
    assert sp.parse_status(SHOT304, line.encode()).limits == axes


def test_one_axis_status_and_error_flag():
    st = sp.parse_status(GSC01, b"-      100,X,L,R\r\n")
    assert st == sp.StatusReply((-100,), False, frozenset({1}), False)
    with pytest.raises(ProtocolError):
        sp.parse_status(GSC01, b"-      100,X,M,R\r\n")  # no axis 2 on a GSC-01
    with pytest.raises(ProtocolError):
        sp.parse_status(SHOT702, b"-      100,X,L,R\r\n")  # a SHOT-702 sends two positions


def test_stray_nul_bytes_are_tolerated():
    assert sp.parse_ack(b"\x00OK\r\n") is True
    assert sp.parse_status(SHOT702, b"\x00-    50000,-    50000,K,K,R\x00\r\n").positions == (-50000, -50000)
    assert sp.parse_ready(b"\x00\x00B\r\n") is True


def test_ok_ng_ready_info():
    assert sp.parse_ack(b"OK\r\n") is True
    assert sp.parse_ack(b"NG\r\n") is False
    assert sp.parse_ready(b"R\r\n") is False
    assert sp.parse_info(b"SHOT-702  \r\n") == "SHOT-702"
    for bad in (b"OC\r\n", b"O\r\n", b"", b"OK OK\r\n", b"ok\r\n"):
        with pytest.raises(ProtocolError):
            sp.parse_ack(bad)
    with pytest.raises(ProtocolError):
        sp.parse_info(b"NG\r\n")
    assert sp.same_product("SHOT-702H", SHOT702) and not sp.same_product("GSC-01", SHOT702)


# ----------------------------------------------------------------- golden commands


@pytest.mark.parametrize(
    "model, cmd, line",
    [
        (SHOT702, sp.Home((1,)), b"H:1\r\n"),
        (SHOT702, sp.Home((1, 2)), b"H:W\r\n"),
        (GSC02, sp.Home((1,), ("+",)), b"H:1+\r\n"),
        (SHOT702, sp.Arm(False, (1,), (1000,)), b"M:1+P1000\r\n"),
        (SHOT702, sp.Arm(True, (1,), (-5000,)), b"A:1-P5000\r\n"),
        (SHOT702, sp.Arm(False, (1, 2), (1000, 0)), b"M:W+P1000+P0\r\n"),
        (SHOT702, sp.Jog((1,), ("+",)), b"J:1+\r\n"),
        (SHOT702, sp.Go(), b"G:\r\n"),
        (SHOT702, sp.Stop((1,)), b"L:1\r\n"),
        (SHOT702, sp.Stop((1, 2)), b"L:W\r\n"),
        (SHOT702, sp.Stop((1, 2), emergency=True), b"L:E\r\n"),
        (SHOT702, sp.SetZero((1,)), b"R:1\r\n"),
        (SHOT702, sp.SetSpeed((1,), (sp.Speed(100, 1000, 100),)), b"D:1S100F1000R100\r\n"),
        (GSC01, sp.SetSpeed((1,), (sp.Speed(100, 20000, 1000),)), b"D:1S100F20000R1000\r\n"),
        (GSC02, sp.SetSpeed((1, 2), (sp.Speed(50, 2000, 100),) * 2), b"D:2S50F2000R100S50F2000R100\r\n"),
        (SHOT702, sp.SetDivision(1, 20), b"S:120\r\n"),
        (SHOT702, sp.Excite(1, True), b"C:11\r\n"),
        (SHOT702, sp.Excite(1, False), b"C:10\r\n"),
        (SHOT702, sp.Status(), b"Q:\r\n"),
        (SHOT702, sp.Ready(), b"!:\r\n"),
        (SHOT702, sp.Info("V"), b"?:V\r\n"),
        (SHOT702, sp.Info("N"), b"?:N\r\n"),
    ],
)
def test_golden_commands_format_and_parse_back(model, cmd, line):
    assert sp.format_command(model, cmd) == line
    assert sp.parse_command(model, line) == cmd


def test_go_without_colon_is_accepted():
    assert sp.parse_command(SHOT702, b"G\r\n") == sp.Go()


@pytest.mark.parametrize(
    "model, cmd",
    [
        (GSC02, sp.Arm(True, (1,), (10,))),               # GSC-02 has no A:
        (GSC02, sp.Home((1,))),                           # GSC-02 homes with a direction
        (SHOT702, sp.Home((1,), ("+",))),                 # the SHOT-702 does not
        (GSC01, sp.SetSpeed((1,), (sp.Speed(150, 1000, 100),))),   # GSC-01: steps of 100 pps
        (GSC01, sp.SetSpeed((1,), (sp.Speed(100, 20100, 100),))),  # GSC-01: at most 20000 pps
        (SHOT702, sp.SetSpeed((1,), (sp.Speed(100, 500001, 100),))),
        (SHOT702, sp.SetSpeed((1,), (sp.Speed(2000, 1000, 100),))),  # S above F
        (SHOT702, sp.SetSpeed((1,), (sp.Speed(100, 1000, 1001),))),
        (SHOT702, sp.SetDivision(1, 3)),
        (GSC02, sp.SetDivision(1, 2)),
        (SHOT702, sp.Arm(True, (3,), (1,))),              # no axis 3
        (GSC01, sp.Stop((1, 2))),
        (SHOT702, sp.Arm(True, (1,), (268435456,))),      # beyond the pulse range
    ],
)
def test_commands_the_controller_would_refuse(model, cmd):
    with pytest.raises(ProtocolError):
        sp.format_command(model, cmd)


@pytest.mark.parametrize("line", [b"A:1+P\r\n", b"A:3+P1\r\n", b"A:1P100\r\n", b"X:1\r\n", b"H:1 \r\n",
                                  b"D:1S100F1000\r\n", b"S:13\r\n", b"C:12\r\n", b"A:1+P1_000\r\n",
                                  b"A:1+P\xd9\xa1\r\n", b"M:W+P1\r\n", b"J:1\r\n", b"Q\r\n"])
def test_malformed_commands(line):
    with pytest.raises(ProtocolError):
        sp.parse_command(SHOT702, line)


def test_degrees_and_pulses():
    # SGSP-120YAW: 0.005 deg per full step; at division 2 a count is 0.0025 deg.
    assert sp.degrees_to_pulses(90.0, 0.005, 2) == pytest.approx(36000)
    assert sp.pulses_to_degrees(-50000, 0.005, 20) == pytest.approx(-12.5)
    assert sp.round_pulses(35999.6) == 36000
    with pytest.raises(ProtocolError):
        sp.round_pulses(float("nan"))


def test_unknown_model():
    with pytest.raises(ProtocolError):
        sp.get_model("SHOT-999")
    assert sp.get_model("GSC-01").line_settings["baudrate"] == 9600
    assert sp.get_model("SHOT-702").line_settings == {"baudrate": 38400, "bytesize": 8, "parity": "N",
                                                      "stopbits": 1, "rtscts": True}


# ----------------------------------------------------------------- round trips (property based)

models = st.sampled_from(list(sp.MODELS.values()))


@st.composite
def statuses(draw):
    m = draw(models)
    pos = tuple(draw(st.integers(-m.pulse_limit, m.pulse_limit)) for _ in range(m.axes))
    if m.limit_bitmask or m.axes == 2:
        limits = frozenset(draw(st.sets(st.integers(1, m.axes))))
    else:
        limits = frozenset(draw(st.sets(st.just(1))))
    return m, sp.StatusReply(pos, draw(st.booleans()), limits, draw(st.booleans()))


@given(statuses())
def test_status_round_trip(case):
    m, status = case
    assert sp.parse_status(m, sp.format_status(m, status)) == status


@st.composite
def commands(draw):
    m = draw(models)
    axis = draw(st.integers(1, m.axes))
    lo, hi = m.speed_range_pps
    step = m.speed_step_pps
    f = draw(st.integers(lo // step + (lo % step > 0), hi // step)) * step
    s = draw(st.integers(lo // step + (lo % step > 0), f // step)) * step
    speed = sp.Speed(s, f, draw(st.integers(*m.accel_range_ms)))
    options = [
        sp.Go(), sp.Status(), sp.Ready(), sp.Info(draw(st.sampled_from(["V", "N", "SW", "DW"]))),
        sp.Stop((axis,)), sp.SetZero((axis,)), sp.Excite(axis, draw(st.booleans())),
        sp.Arm(False, (axis,), (draw(st.integers(-m.pulse_limit, m.pulse_limit)),)),
        sp.Jog((axis,), (draw(st.sampled_from("+-")),)),
        sp.Home((axis,), (draw(st.sampled_from("+-")),) if m.home_needs_direction else ()),
    ]
    if m.absolute_moves:
        options.append(sp.Arm(True, (axis,), (draw(st.integers(-m.pulse_limit, m.pulse_limit)),)))
    if m.divisions:
        options.append(sp.SetDivision(axis, draw(st.sampled_from(m.divisions))))
    if m.speed_range_prefix is None:
        options.append(sp.SetSpeed((axis,), (speed,)))
    else:
        options.append(sp.SetSpeed(tuple(range(1, m.axes + 1)), (speed,) * m.axes))
    return m, draw(st.sampled_from(options))


@given(commands())
def test_command_round_trip(case):
    m, cmd = case
    assert sp.parse_command(m, sp.format_command(m, cmd)) == cmd


# ----------------------------------------------------------------- fuzzing: only ProtocolError

VALID_LINES = [
    b"-    50000,-    50000,K,K,R\r\n", b"     12345,K,L,B\r\n", b"OK\r\n", b"NG\r\n", b"B\r\n", b"R\r\n",
    b"SHOT-702\r\n", b"A:1-P5000\r\n", b"D:1S100F1000R100\r\n", b"M:W+P1000+P0\r\n", b"H:1+\r\n",
    b"     1,     2,     3,     4,K,5,R\r\n",
]


@st.composite
def mutated(draw):
    """Valid lines with bytes flipped, inserted or deleted, plus arbitrary bytes."""
    if draw(st.booleans()):
        return draw(st.binary(max_size=80))
    data = bytearray(draw(st.sampled_from(VALID_LINES)))
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["flip", "insert", "delete"]))
        i = draw(st.integers(0, max(0, len(data) - 1)))
        if op == "flip" and data:
            data[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "insert":
            data.insert(i, draw(st.integers(0, 255)))
        elif data:
            del data[i]
    return bytes(data)


PARSERS = [
    ("ack", sp.parse_ack),
    ("ready", sp.parse_ready),
    ("info", sp.parse_info),
    *[(f"status-{m.name}", lambda b, m=m: sp.parse_status(m, b)) for m in sp.MODELS.values()],
    *[(f"command-{m.name}", lambda b, m=m: sp.parse_command(m, b)) for m in sp.MODELS.values()],
]


@pytest.mark.parametrize("name, parse", PARSERS, ids=[n for n, _ in PARSERS])
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=mutated())
def test_parsers_raise_only_protocol_error(name, parse, data):
    try:
        parse(data)
    except ProtocolError:
        pass


@settings(max_examples=100, deadline=None)
@given(st.integers(-(10**10), 10**10))
def test_position_field_accepts_only_what_fits(n):
    try:
        field = sp.format_position(n)
    except ProtocolError:
        assert abs(n) >= 10**9
        return
    assert len(field) == sp.FIELD_WIDTH and sp.parse_position(field) == n
