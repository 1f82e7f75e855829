"""Byte protocol of the Thorlabs FW102C / FW212C motorised filter wheel.

Pure functions, no I/O: the driver (:mod:`drivers.fw102c`) and the simulated
twin (:mod:`sim_devices.fw102c`) both build and read bytes through this module,
so that both are checked against the documented protocol
(``shared/reference/device-protocols.md`` section 3).

Line: 115200 baud, 8N1, no flow control. A command is ASCII text ending in
``CR``. The wheel answers with one *exchange*:

- the echo of the command and its ``CR``,
- then, for a query, the reply text and ``CR``; for a refused command the line
  ``Command error <CODE>`` ending in ``LF CR`` (note the unusual order);
  for an accepted setting, nothing,
- then the prompt ``"> "``, which is the only reliable end of an exchange
  (read until the prompt, never until a newline). After ``pos=N`` the prompt
  comes only once the wheel has arrived.

Positions are 1-based. Queries ``speed?``, ``sensors?`` and ``trig?`` are not in
the reference table; they are taken from odemis ``tlfw.py`` (its notes show
``speed?\\r1\\r>``) and are *unconfirmed*.

Every parser raises only :class:`drivers.errors.ProtocolError` on malformed input.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from drivers.errors import ParameterError, ProtocolError

DEVICE = "filter"

BAUDRATE = 115200
CR = b"\r"
PROMPT = b"> "
ERROR_PREFIX = b"Command error "
ERROR_END = b"\n\r"  # the FW102C ends an error line with LF then CR
#: Error codes named in the reference; other upper-case codes are passed through.
NOT_DEFINED = "CMD_NOT_DEFINED"
ARG_INVALID = "CMD_ARG_INVALID"
#: Wheel sizes the firmware knows: FW102C has 6 positions, FW212C 12.
POSITION_COUNTS = (6, 12)
#: The identity string of a compatible wheel contains one of these model names.
MODELS = ("FW102C", "FW212C")

_ERROR_CODE = re.compile(rb"[A-Z][A-Z_]{0,39}")
_NAME = re.compile(r"\*?[A-Za-z]{1,16}")
_UINT = re.compile(r"[0-9]{1,6}")
_MAX_COMMAND = 64  # longer input is not an FW102C command


def _fail(message: str) -> ProtocolError:
    return ProtocolError(message, device=DEVICE)


def _printable(data: bytes, what: str) -> str:
    """ASCII 0x20..0x7E only (the wheel never sends anything else in a field)."""
    if any(b < 0x20 or b > 0x7E for b in data):
        raise _fail(f"{what} holds a non-printable byte: {data!r}")
    return data.decode("ascii")


# --------------------------------------------------------------------------- commands (host -> wheel)


def command(text: str) -> bytes:
    """``text`` + CR as bytes; the text must be printable ASCII without CR or the prompt."""
    if not isinstance(text, str) or not text or len(text) > _MAX_COMMAND:
        raise ParameterError(f"not an FW102C command: {text!r}", device=DEVICE)
    if any(not 0x20 <= ord(c) <= 0x7E for c in text):
        raise ParameterError(f"FW102C commands are printable ASCII: {text!r}", device=DEVICE)
    return text.encode("ascii") + CR


def _flag(value: int | bool, what: str) -> int:
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, int) and value in (0, 1):
        return value
    raise ParameterError(f"{what} must be 0 or 1, got {value!r}", device=DEVICE)


def idn_query() -> bytes:
    """``*idn?``: model and firmware version."""
    return command("*idn?")


def pos_query() -> bytes:
    """``pos?``: the position the wheel is at (1-based)."""
    return command("pos?")


def pos_set(position: int) -> bytes:
    """``pos=N``: turn to position N (1-based); the prompt comes once the wheel is there."""
    if isinstance(position, bool) or not isinstance(position, int) or not 1 <= position <= max(POSITION_COUNTS):
        raise ParameterError(
            f"wheel position must be an integer 1..{max(POSITION_COUNTS)}, got {position!r}", device=DEVICE
        )
    return command(f"pos={position}")


def pcount_query() -> bytes:
    """``pcount?``: number of positions of the fitted wheel (6 or 12)."""
    return command("pcount?")


def pcount_set(count: int) -> bytes:
    """``pcount=6|12``: tell the controller which wheel is fitted."""
    if isinstance(count, bool) or count not in POSITION_COUNTS:
        raise ParameterError(f"position count must be 6 or 12, got {count!r}", device=DEVICE)
    return command(f"pcount={count}")


def speed_query() -> bytes:
    """``speed?``: 0 slow, 1 high speed (*unconfirmed* query, see module notes)."""
    return command("speed?")


def speed_set(high: int | bool) -> bytes:
    """``speed=0|1``: 0 slow, 1 high speed."""
    return command(f"speed={_flag(high, 'speed')}")


def sensors_query() -> bytes:
    """``sensors?`` (*unconfirmed* query)."""
    return command("sensors?")


def sensors_set(on: int | bool) -> bytes:
    """``sensors=0|1``: 0 switches the position sensors off when idle, 1 keeps them on."""
    return command(f"sensors={_flag(on, 'sensors')}")


def trig_query() -> bytes:
    """``trig?`` (*unconfirmed* query)."""
    return command("trig?")


def trig_set(mode: int | bool) -> bytes:
    """``trig=0|1``: external trigger pin as input (0) or output (1)."""
    return command(f"trig={_flag(mode, 'trig')}")


def save() -> bytes:
    """``save``: store the present settings as power-on defaults."""
    return command("save")


# --------------------------------------------------------------------------- exchanges (wheel -> host)


@dataclass(frozen=True)
class Exchange:
    """One parsed exchange.

    Attributes:
        echo: the command as the wheel echoed it, without CR.
        reply: reply text without CR ('' when the command has no reply).
        error: the code of a ``Command error`` reply (e.g. ``CMD_NOT_DEFINED``), or None.
    """

    echo: str
    reply: str = ""
    error: str | None = None


def format_exchange(echo: bytes, reply: str | None = None, error: str | None = None) -> bytes:
    """The bytes the wheel sends for one command (used by the twin).

    Args:
        echo: the command line as received, without CR.
        reply: the reply text of a query, or None.
        error: an error code instead of a reply, or None.
    """
    out = bytes(echo) + CR
    if error is not None:
        out += ERROR_PREFIX + error.encode("ascii") + ERROR_END
    elif reply is not None:
        out += reply.encode("ascii") + CR
    return out + PROMPT


def parse_exchange(raw: bytes) -> Exchange:
    """Split one complete exchange (everything up to and including the prompt).

    Leading NUL bytes are skipped: odemis notes that the wheel may send some
    after power-on.

    Raises:
        ProtocolError: no prompt at the end, no echo line, a non-printable byte,
            or a body that is neither a reply line nor an error line.
    """
    if not isinstance(raw, (bytes, bytearray)):
        raise _fail(f"exchange must be bytes, got {type(raw).__name__}")
    raw = bytes(raw).lstrip(b"\x00")
    if not raw.endswith(PROMPT):
        raise _fail(f"exchange does not end with the prompt '> ': {raw!r}")
    body = raw[: -len(PROMPT)]
    if CR not in body:
        raise _fail(f"exchange has no echo line: {raw!r}")
    echo_b, rest = body.split(CR, 1)
    echo = _printable(echo_b, "echo")
    if not rest:
        return Exchange(echo)
    if rest.startswith(ERROR_PREFIX):
        code = rest[len(ERROR_PREFIX):]
        if not code.endswith(ERROR_END) or not _ERROR_CODE.fullmatch(code[: -len(ERROR_END)]):
            raise _fail(f"malformed error reply: {raw!r}")
        return Exchange(echo, "", code[: -len(ERROR_END)].decode("ascii"))
    if not rest.endswith(CR):
        raise _fail(f"reply line does not end with CR: {raw!r}")
    return Exchange(echo, _printable(rest[:-1], "reply"))


def check_echo(exchange: Exchange, sent: bytes) -> None:
    """Raise ProtocolError unless the wheel echoed exactly the command ``sent``
    (with or without its CR). A different echo means the line corrupted the
    command or the reply, or the bytes belong to another exchange."""
    expected = bytes(sent)
    if expected.endswith(CR):
        expected = expected[:-1]
    if exchange.echo.encode("ascii") != expected:
        raise _fail(f"echo {exchange.echo!r} does not match the command {expected!r}")


# --------------------------------------------------------------------------- reply fields


def parse_uint(reply: str, what: str = "reply") -> int:
    """A decimal number (surrounding blanks allowed)."""
    if not isinstance(reply, str):
        raise _fail(f"{what} must be text, got {type(reply).__name__}")
    text = reply.strip(" ")
    if not _UINT.fullmatch(text):
        raise _fail(f"{what} is not a number: {reply!r}")
    return int(text)


def parse_position(reply: str, count: int) -> int:
    """Reply of ``pos?``: a position 1..count."""
    pos = parse_uint(reply, "position")
    if not 1 <= pos <= count:
        raise _fail(f"position {pos} outside 1..{count}")
    return pos


def parse_pcount(reply: str) -> int:
    """Reply of ``pcount?``: 6 or 12."""
    n = parse_uint(reply, "position count")
    if n not in POSITION_COUNTS:
        raise _fail(f"position count {n} is neither 6 nor 12")
    return n


def parse_flag(reply: str, what: str = "flag") -> int:
    """Reply of ``speed?``, ``sensors?``, ``trig?``: 0 or 1."""
    v = parse_uint(reply, what)
    if v not in (0, 1):
        raise _fail(f"{what} {v} is neither 0 nor 1")
    return v


def parse_identity(reply: str) -> str:
    """Reply of ``*idn?``, e.g. ``THORLABS FW102C/FW212C Filter Wheel version 1.07``."""
    if not isinstance(reply, str):
        raise _fail(f"identity must be text, got {type(reply).__name__}")
    text = reply.strip()
    if not text or any(not 0x20 <= ord(c) <= 0x7E for c in text):
        raise _fail(f"identity is empty or not printable: {reply!r}")
    return text


def is_fw102c(identity: str) -> bool:
    """True if an identity string names a wheel that speaks this protocol."""
    up = identity.upper()
    return any(m in up for m in MODELS)


# --------------------------------------------------------------------------- commands as the wheel reads them


@dataclass(frozen=True)
class Command:
    """A command line as the wheel parses it.

    Attributes:
        name: e.g. ``pos``, ``*idn``, ``save``.
        kind: ``"?"`` query, ``"="`` setting, ``""`` bare command.
        arg: text after ``=`` ('' otherwise).
    """

    name: str
    kind: str
    arg: str = ""


def parse_command(line: bytes) -> Command:
    """Parse one command line (without its CR).

    Raises:
        ProtocolError: empty, too long, non-printable, or not ``name``,
            ``name?`` or ``name=arg``.
    """
    if not isinstance(line, (bytes, bytearray)):
        raise _fail(f"command must be bytes, got {type(line).__name__}")
    if not line or len(line) > _MAX_COMMAND:
        raise _fail(f"empty or overlong command: {bytes(line)!r}")
    text = _printable(bytes(line), "command")
    if "=" in text:
        name, arg = text.split("=", 1)
        kind = "="
    elif text.endswith("?"):
        name, arg, kind = text[:-1], "", "?"
    else:
        name, arg, kind = text, "", ""
    if not _NAME.fullmatch(name):
        raise _fail(f"not a command name: {name!r}")
    return Command(name, kind, arg)
