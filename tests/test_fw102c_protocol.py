"""FW102C byte protocol: golden transcripts from the reference (device-protocols.md
section 3) checked against the protocol module and the twin, and hypothesis
fuzzing of every parser (malformed input raises only ProtocolError)."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers import fw102c_protocol as proto
from drivers.errors import ParameterError, ProtocolError
from sim_devices.fw102c import FW102CTwin
from sim_devices.serial_twin import SimClock

IDN = "THORLABS FW102C/FW212C Filter Wheel version 1.07"

# (sent, received, parsed): the table of device-protocols.md section 3, byte for byte.
GOLDEN = [
    (b"pos?\r", b"pos?\r3\r> ", proto.Exchange("pos?", "3", None)),
    (b"pos=2\r", b"pos=2\r> ", proto.Exchange("pos=2", "", None)),
    (b"qwz=3\r", b"qwz=3\rCommand error CMD_NOT_DEFINED\n\r> ", proto.Exchange("qwz=3", "", "CMD_NOT_DEFINED")),
    (b"pos=9\r", b"pos=9\rCommand error CMD_ARG_INVALID\n\r> ", proto.Exchange("pos=9", "", "CMD_ARG_INVALID")),
    (b"*idn?\r", b"*idn?\r" + IDN.encode() + b"\r> ", proto.Exchange("*idn?", IDN, None)),
]


@pytest.mark.parametrize("sent,received,parsed", GOLDEN)
def test_golden_exchange_parses(sent: bytes, received: bytes, parsed: proto.Exchange) -> None:
    ex = proto.parse_exchange(received)
    assert ex == parsed
    proto.check_echo(ex, sent)


@pytest.mark.parametrize("sent,received,parsed", GOLDEN)
def test_golden_exchange_formats(sent: bytes, received: bytes, parsed: proto.Exchange) -> None:
    reply = parsed.reply if (parsed.reply or parsed.echo.endswith("?")) else None
    assert proto.format_exchange(sent[:-1], reply, parsed.error) == received


@pytest.mark.parametrize("sent,received,parsed", GOLDEN)
def test_twin_answers_golden_bytes(sent: bytes, received: bytes, parsed: proto.Exchange) -> None:
    """A 6-position twin at position 3 says exactly what the reference says."""
    twin = FW102CTwin(SimClock(1e6), pcount=6, position=3)  # 1 s per position -> 1 us
    twin.write(sent)
    out = b""
    for _ in range(10_000):
        out += twin.read_ready()
        if out.endswith(proto.PROMPT):
            break
    assert out == received


def test_golden_field_values() -> None:
    assert proto.parse_position(proto.parse_exchange(GOLDEN[0][1]).reply, 6) == 3
    idn = proto.parse_identity(proto.parse_exchange(GOLDEN[4][1]).reply)
    assert idn == IDN and proto.is_fw102c(idn)
    assert not proto.is_fw102c("SHOT-702 V1.03")


def test_command_bytes() -> None:
    assert proto.idn_query() == b"*idn?\r"
    assert proto.pos_query() == b"pos?\r"
    assert proto.pos_set(2) == b"pos=2\r"
    assert proto.pos_set(12) == b"pos=12\r"
    assert proto.pcount_query() == b"pcount?\r"
    assert proto.pcount_set(6) == b"pcount=6\r"
    assert proto.pcount_set(12) == b"pcount=12\r"
    assert proto.speed_set(0) == b"speed=0\r"
    assert proto.speed_set(True) == b"speed=1\r"
    assert proto.sensors_set(1) == b"sensors=1\r"
    assert proto.trig_set(0) == b"trig=0\r"
    assert proto.save() == b"save\r"
    assert proto.speed_query() == b"speed?\r"
    assert proto.command("qwz=3") == b"qwz=3\r"


@pytest.mark.parametrize("call", [
    lambda: proto.pos_set(0), lambda: proto.pos_set(13), lambda: proto.pos_set(True),
    lambda: proto.pos_set(2.0), lambda: proto.pcount_set(7), lambda: proto.speed_set(2),
    lambda: proto.trig_set(-1), lambda: proto.command("pos?\r"), lambda: proto.command(""),
    lambda: proto.command("pos=\u00e9"),
])
def test_bad_commands_are_refused_before_any_byte(call) -> None:
    with pytest.raises(ParameterError):
        call()


@pytest.mark.parametrize("raw", [
    b"pos?\r3\r",                       # no prompt (truncated)
    b"3\r> "[2:],                       # prompt only, no echo line
    b"> ",                              # nothing but the prompt
    b"pos?\r3> ",                       # reply without its CR
    b"pos=9\rCommand error CMD_ARG_INVALID\r> ",  # error line without LF CR
    b"pos=9\rCommand error \n\r> ",     # error without a code
    b"pos=9\rCommand error cmd bad\n\r> ",
    b"pos?\r3\r4\r> ",                  # two reply lines
    b"p\xf6s?\r3\r> ",                  # non-ASCII echo
    b"pos?\r\x013\r> ",                 # control byte in the reply
])
def test_malformed_exchanges(raw: bytes) -> None:
    with pytest.raises(ProtocolError):
        proto.parse_exchange(raw)


def test_leading_nuls_are_skipped() -> None:
    assert proto.parse_exchange(b"\x00\x00pos?\r3\r> ") == proto.Exchange("pos?", "3")


def test_echo_mismatch() -> None:
    ex = proto.parse_exchange(b"pgs?\rCommand error CMD_NOT_DEFINED\n\r> ")
    with pytest.raises(ProtocolError, match="echo"):
        proto.check_echo(ex, b"pos?\r")
    proto.check_echo(ex, b"pgs?")  # CR optional


@pytest.mark.parametrize("parse,text", [
    (lambda r: proto.parse_position(r, 6), "7"), (lambda r: proto.parse_position(r, 6), "0"),
    (lambda r: proto.parse_position(r, 6), "-1"), (lambda r: proto.parse_position(r, 6), "3a"),
    (lambda r: proto.parse_position(r, 6), ""), (proto.parse_pcount, "8"), (proto.parse_pcount, "six"),
    (proto.parse_flag, "2"), (proto.parse_identity, "  "), (proto.parse_identity, "FW102C\x7f"),
])
def test_bad_fields(parse, text: str) -> None:
    with pytest.raises(ProtocolError):
        parse(text)


def test_good_fields() -> None:
    assert proto.parse_position(" 12", 12) == 12
    assert proto.parse_pcount("12") == 12
    assert proto.parse_flag("0") == 0
    assert proto.parse_command(b"pos=2") == proto.Command("pos", "=", "2")
    assert proto.parse_command(b"*idn?") == proto.Command("*idn", "?")
    assert proto.parse_command(b"save") == proto.Command("save", "")


# --------------------------------------------------------------------------- fuzzing

# Pieces that real exchanges are made of, so that random joins reach deep branches.
_TOKENS = st.sampled_from([
    b"pos?", b"pos=2", b"*idn?", b"\r", b"\n", b"\n\r", b"> ", b">", b" ", b"3", b"12", b"\x00",
    b"Command error ", b"CMD_NOT_DEFINED", b"CMD_ARG_INVALID", b"THORLABS FW102C", b"\xff", b"=", b"?",
])
_FRAGMENTS = st.lists(_TOKENS, max_size=12).map(b"".join)
_ANY_BYTES = st.one_of(st.binary(max_size=80), _FRAGMENTS)
_PRINTABLE = st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E), max_size=40)


@settings(max_examples=300, deadline=None)
@given(_ANY_BYTES)
def test_fuzz_parse_exchange(raw: bytes) -> None:
    try:
        ex = proto.parse_exchange(raw)
    except ProtocolError:
        return
    assert isinstance(ex, proto.Exchange)
    assert raw.endswith(proto.PROMPT)


@settings(max_examples=200, deadline=None)
@given(_ANY_BYTES, _ANY_BYTES)
def test_fuzz_check_echo(raw: bytes, sent: bytes) -> None:
    try:
        proto.check_echo(proto.parse_exchange(raw), sent)
    except ProtocolError:
        pass


@settings(max_examples=200, deadline=None)
@given(st.one_of(_PRINTABLE, st.text(max_size=20)))
def test_fuzz_field_parsers(text: str) -> None:
    for parse in (lambda r: proto.parse_position(r, 6), lambda r: proto.parse_position(r, 12),
                  proto.parse_pcount, proto.parse_flag, proto.parse_identity, proto.parse_uint):
        try:
            parse(text)
        except ProtocolError:
            pass


@settings(max_examples=200, deadline=None)
@given(_ANY_BYTES)
def test_fuzz_parse_command(line: bytes) -> None:
    try:
        cmd = proto.parse_command(line)
    except ProtocolError:
        return
    assert cmd.kind in ("?", "=", "")


@settings(max_examples=200, deadline=None)
@given(
    _PRINTABLE,
    st.one_of(st.none(), _PRINTABLE.filter(lambda r: not r.startswith("Command error "))),
    st.one_of(st.none(), st.sampled_from([proto.NOT_DEFINED, proto.ARG_INVALID])),
)
def test_round_trip(echo: str, reply: str | None, error: str | None) -> None:
    raw = proto.format_exchange(echo.encode(), reply, error)
    ex = proto.parse_exchange(raw)
    assert ex == proto.Exchange(echo, "" if error or reply is None else reply, error)
    proto.check_echo(ex, echo.encode() + b"\r")


@settings(max_examples=150, deadline=None)
@given(st.lists(st.one_of(_PRINTABLE.filter(lambda s: len(s) < 60), _FRAGMENTS.filter(lambda b: b"\r" not in b)),
                min_size=1, max_size=4))
def test_twin_always_answers_one_parsable_exchange(lines: list) -> None:
    """Whatever line arrives, the twin answers one exchange that echoes it (if printable)."""
    twin = FW102CTwin(SimClock(1e9), pcount=12)
    for line in lines:
        data = line.encode() if isinstance(line, str) else line
        twin.write(data + b"\r")
        out = b""
        for _ in range(10_000):
            out += twin.read_ready()
            if out.endswith(proto.PROMPT):
                break
        if all(0x20 <= b <= 0x7E for b in data):
            proto.check_echo(proto.parse_exchange(out), data)
        else:  # the wheel echoes what it hears; an unprintable echo is the host's to reject
            try:
                proto.parse_exchange(out)
            except ProtocolError:
                pass
