"""Byte protocol of Sigma Koki (OptoSigma) stage controllers: SHOT-702, SHOT-302GS,
SHOT-304GS, GSC-01 and GSC-02.

Pure functions, no I/O: commands are formatted from small dataclasses and parsed
back (the simulated twin parses what the driver sends with the same code);
replies (``OK``/``NG``, the ``Q:`` status line, the ``!:`` busy flag, ``?:``
information) are parsed and formatted. Every malformed input raises
:class:`~drivers.errors.ProtocolError` and nothing else.

Line settings: 8N1, RTS/CTS, ``CR LF`` after every command and reply. Some units
emit stray ``\\x00`` bytes (at power-up, after a break); they are dropped before
parsing.

Facts marked *unconfirmed* in ``shared/reference/device-protocols.md`` are kept in
the :data:`MODELS` table so they can be corrected in one place.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from drivers.errors import ProtocolError

DEVICE = "stage"
TERMINATOR = b"\r\n"

#: Microstep divisions the SHOT controllers accept for ``S:``.
SHOT_DIVISIONS: tuple[int, ...] = (1, 2, 4, 5, 8, 10, 20, 25, 40, 50, 80, 100, 125, 200, 250)


@dataclass(frozen=True)
class ShotModel:
    """Facts of one controller model.

    Attributes:
        name: product name as ``?:N`` reports it (compared without spaces).
        axes: number of axes; the ``Q:`` line carries one position field per axis.
        baudrate: line speed (SHOT-702: fixed 38400; the others' factory default 9600).
        acknowledges: ``OK``/``NG`` after every non-query command (GSC-02: no reply;
            the host confirms with ``Q:``'s ACK1).
        absolute_moves: has ``A:`` (GSC-02 has only relative ``M:``).
        home_needs_direction: ``H:1+`` instead of ``H:1`` (GSC-02).
        speed_range_pps: (min, max) of the ``D:`` S and F values, pulses per second.
        speed_step_pps: S and F must be multiples of this (GSC-01: 100).
        accel_range_ms: (min, max) of the ``D:`` R value, milliseconds.
        pulse_limit: largest absolute position count.
        limit_bitmask: ACK2 is a hex digit, bit ``n-1`` = axis ``n`` at a limit
            (SHOT-304GS), instead of the letters ``L``/``M``/``W``.
        divisions: divisions ``S:`` accepts; empty if the model has no ``S:``
            (GSC-02: fixed half step).
        speed_range_prefix: GSC-02 ``D:`` starts with a speed-range digit
            (``2`` = high-speed range) and carries both axes, not an axis number.
        default_speed_pps: power-on (S, F, R ms) the twin starts with and the
            driver assumes before it has set a speed (*unconfirmed*).
    """

    name: str
    axes: int
    baudrate: int
    acknowledges: bool
    absolute_moves: bool
    home_needs_direction: bool
    speed_range_pps: tuple[int, int]
    speed_step_pps: int
    pulse_limit: int
    limit_bitmask: bool = False
    divisions: tuple[int, ...] = SHOT_DIVISIONS
    speed_range_prefix: str | None = None
    accel_range_ms: tuple[int, int] = (0, 1000)
    default_speed_pps: tuple[int, int, int] = (500, 5000, 200)

    @property
    def line_settings(self) -> dict[str, object]:
        """pyserial keyword arguments for this model's line."""
        return {"baudrate": self.baudrate, "bytesize": 8, "parity": "N", "stopbits": 1, "rtscts": True}


MODELS: dict[str, ShotModel] = {
    m.name: m
    for m in (
        ShotModel("SHOT-702", axes=2, baudrate=38400, acknowledges=True, absolute_moves=True,
                  home_needs_direction=False, speed_range_pps=(1, 500_000), speed_step_pps=1,
                  pulse_limit=268_435_455),
        ShotModel("SHOT-302GS", axes=2, baudrate=9600, acknowledges=True, absolute_moves=True,
                  home_needs_direction=False, speed_range_pps=(1, 500_000), speed_step_pps=1,
                  pulse_limit=268_435_455),
        ShotModel("SHOT-304GS", axes=4, baudrate=9600, acknowledges=True, absolute_moves=True,
                  home_needs_direction=False, speed_range_pps=(1, 500_000), speed_step_pps=1,
                  pulse_limit=268_435_455, limit_bitmask=True),
        # GSC-01: pulse range and S: support unconfirmed (taken as the SHOT's).
        ShotModel("GSC-01", axes=1, baudrate=9600, acknowledges=True, absolute_moves=True,
                  home_needs_direction=False, speed_range_pps=(100, 20_000), speed_step_pps=100,
                  pulse_limit=16_777_214, default_speed_pps=(500, 5000, 200)),
        ShotModel("GSC-02", axes=2, baudrate=9600, acknowledges=False, absolute_moves=False,
                  home_needs_direction=True, speed_range_pps=(50, 20_000), speed_step_pps=1,
                  pulse_limit=16_777_214, divisions=(), speed_range_prefix="2"),
    )
}


def get_model(name: str) -> ShotModel:
    """The model of that name (``SHOT-702``, ``SHOT-302GS``, ``SHOT-304GS``, ``GSC-01``, ``GSC-02``)."""
    try:
        return MODELS[name]
    except KeyError:
        raise ProtocolError(f"unknown controller model {name!r}; known: {', '.join(MODELS)}", device=DEVICE) from None


# --------------------------------------------------------------------------- units


def pulses_to_degrees(pulses: float, degrees_per_pulse: float, division: int) -> float:
    """Stage angle change (degrees) of ``pulses`` counts; ``degrees_per_pulse`` is at full step."""
    return pulses * degrees_per_pulse / division


def degrees_to_pulses(degrees: float, degrees_per_pulse: float, division: int) -> float:
    """Counts (not rounded) for an angle change in degrees."""
    return degrees * division / degrees_per_pulse


# --------------------------------------------------------------------------- commands


@dataclass(frozen=True)
class Home:
    """``H:`` drive to the mechanical origin; ``directions`` only for models that need one."""

    axes: tuple[int, ...]
    directions: tuple[str, ...] = ()


@dataclass(frozen=True)
class Arm:
    """``A:`` (absolute) or ``M:`` (relative) move, armed until ``G:``; pulses per axis."""

    absolute: bool
    axes: tuple[int, ...]
    pulses: tuple[int, ...]


@dataclass(frozen=True)
class Jog:
    """``J:`` continuous move at the minimum speed, armed until ``G:``."""

    axes: tuple[int, ...]
    directions: tuple[str, ...]


@dataclass(frozen=True)
class Go:
    """``G:`` execute the armed move."""


@dataclass(frozen=True)
class Stop:
    """``L:`` decelerate and stop; ``emergency`` (``L:E``): all axes at once."""

    axes: tuple[int, ...]
    emergency: bool = False


@dataclass(frozen=True)
class SetZero:
    """``R:`` the present position becomes 0 (electrical origin)."""

    axes: tuple[int, ...]


@dataclass(frozen=True)
class Speed:
    """One axis's speed: start ``s`` and top ``f`` in pulses/s, ramp ``r_ms`` milliseconds."""

    s: int
    f: int
    r_ms: int


@dataclass(frozen=True)
class SetSpeed:
    """``D:`` speed table, one :class:`Speed` per axis named."""

    axes: tuple[int, ...]
    speeds: tuple[Speed, ...]


@dataclass(frozen=True)
class SetDivision:
    """``S:`` microstep division of one axis."""

    axis: int
    division: int


@dataclass(frozen=True)
class Excite:
    """``C:`` motor excitation on (hold) or off (free)."""

    axis: int
    on: bool


@dataclass(frozen=True)
class Status:
    """``Q:`` status query."""


@dataclass(frozen=True)
class Ready:
    """``!:`` busy/ready query."""


@dataclass(frozen=True)
class Info:
    """``?:<what>`` information query: ``V`` version, ``N`` product name, ``SW``, ``DW``..."""

    what: str


Command = Home | Arm | Jog | Go | Stop | SetZero | SetSpeed | SetDivision | Excite | Status | Ready | Info

#: Commands that are answered with data, never with OK/NG.
QUERIES = (Status, Ready, Info)
#: Commands a busy controller still accepts.
ALLOWED_WHILE_BUSY = (Stop, Status, Ready)


def _err(msg: str) -> ProtocolError:
    return ProtocolError(msg, device=DEVICE)


def _axes_field(model: ShotModel, axes: tuple[int, ...]) -> str:
    """``1``..``n`` for one axis, ``W`` for all axes in order."""
    if len(axes) == 1 and 1 <= axes[0] <= model.axes:
        return str(axes[0])
    if model.axes > 1 and tuple(axes) == tuple(range(1, model.axes + 1)):
        return "W"
    raise _err(f"{model.name} has axes 1..{model.axes}; cannot address {axes}")


def _check_dirs(directions: tuple[str, ...], n: int) -> None:
    if len(directions) != n or any(d not in "+-" or len(d) != 1 for d in directions):
        raise _err(f"need {n} directions '+' or '-', got {directions}")


def check_speed(model: ShotModel, sp: Speed) -> None:
    """Raise ProtocolError if the controller would refuse this speed (NG)."""
    lo, hi = model.speed_range_pps
    rlo, rhi = model.accel_range_ms
    for v in (sp.s, sp.f):
        if not lo <= v <= hi or v % model.speed_step_pps:
            raise _err(f"{model.name} speed {v} pps outside {lo}..{hi} in steps of {model.speed_step_pps}")
    if sp.s > sp.f:
        raise _err(f"start speed {sp.s} pps above top speed {sp.f} pps")
    if not rlo <= sp.r_ms <= rhi:
        raise _err(f"{model.name} acceleration time {sp.r_ms} ms outside {rlo}..{rhi} ms")


def format_command(model: ShotModel, cmd: Command) -> bytes:
    """Bytes to send for ``cmd`` on ``model``, terminator included.

    Raises:
        ProtocolError: the model has no such command or the parameters are out of
            its range (the controller would answer NG).
    """
    if isinstance(cmd, Home):
        text = "H:" + _axes_field(model, cmd.axes)
        if model.home_needs_direction:
            _check_dirs(cmd.directions, len(cmd.axes))
            text += "".join(cmd.directions)
        elif cmd.directions:
            raise _err(f"{model.name} homes without a direction")
    elif isinstance(cmd, Arm):
        if cmd.absolute and not model.absolute_moves:
            raise _err(f"{model.name} has no absolute move (A:); use M:")
        if len(cmd.pulses) != len(cmd.axes):
            raise _err(f"{len(cmd.axes)} axes but {len(cmd.pulses)} pulse counts")
        text = ("A:" if cmd.absolute else "M:") + _axes_field(model, cmd.axes)
        for p in cmd.pulses:
            if not isinstance(p, int) or abs(p) > model.pulse_limit:
                raise _err(f"pulse count {p!r} outside +/-{model.pulse_limit}")
            text += f"{'-' if p < 0 else '+'}P{abs(p)}"
    elif isinstance(cmd, Jog):
        _check_dirs(cmd.directions, len(cmd.axes))
        text = "J:" + _axes_field(model, cmd.axes) + "".join(cmd.directions)
    elif isinstance(cmd, Go):
        text = "G:"
    elif isinstance(cmd, Stop):
        text = "L:E" if cmd.emergency else "L:" + _axes_field(model, cmd.axes)
    elif isinstance(cmd, SetZero):
        text = "R:" + _axes_field(model, cmd.axes)
    elif isinstance(cmd, SetSpeed):
        if len(cmd.speeds) != len(cmd.axes):
            raise _err(f"{len(cmd.axes)} axes but {len(cmd.speeds)} speeds")
        for sp in cmd.speeds:
            check_speed(model, sp)
        if model.speed_range_prefix is not None:
            # GSC-02: D:<range> then S/F/R of every axis; the range digit is not an axis.
            if tuple(cmd.axes) != tuple(range(1, model.axes + 1)):
                raise _err(f"{model.name} sets the speed of all {model.axes} axes at once")
            head = model.speed_range_prefix
        else:
            head = _axes_field(model, cmd.axes)
        text = "D:" + head + "".join(f"S{sp.s}F{sp.f}R{sp.r_ms}" for sp in cmd.speeds)
    elif isinstance(cmd, SetDivision):
        if not model.divisions:
            raise _err(f"{model.name} has a fixed step division (no S:)")
        if cmd.division not in model.divisions:
            raise _err(f"division {cmd.division} not in {model.divisions}")
        text = "S:" + _axes_field(model, (cmd.axis,)) + str(cmd.division)
    elif isinstance(cmd, Excite):
        text = "C:" + _axes_field(model, (cmd.axis,)) + ("1" if cmd.on else "0")
    elif isinstance(cmd, Status):
        text = "Q:"
    elif isinstance(cmd, Ready):
        text = "!:"
    elif isinstance(cmd, Info):
        if not re.fullmatch(r"[A-Z]{1,4}", cmd.what):
            raise _err(f"bad information query {cmd.what!r}")
        text = "?:" + cmd.what
    else:
        raise _err(f"not a command: {cmd!r}")
    return text.encode("ascii") + TERMINATOR


def clean_line(line: bytes) -> str:
    """ASCII text of one line: stray NULs dropped, the CR LF (or CR / LF) removed.

    Raises ProtocolError for non-ASCII or control bytes (a garbled line).
    """
    if not isinstance(line, (bytes, bytearray)):
        raise _err(f"expected bytes, got {type(line).__name__}")
    data = bytes(line).replace(b"\x00", b"")
    if data.endswith(b"\r\n"):
        data = data[:-2]
    elif data.endswith((b"\r", b"\n")):
        data = data[:-1]
    if any(b < 0x20 or b > 0x7E for b in data):
        raise _err(f"garbled line {bytes(line)!r}")
    return data.decode("ascii")


_AXIS_RE = re.compile(r"[1-9]|W")


def _parse_axes(model: ShotModel, field: str, text: str) -> tuple[int, ...]:
    if field == "W" and model.axes > 1:
        return tuple(range(1, model.axes + 1))
    if field.isdigit() and len(field) == 1 and 1 <= int(field) <= model.axes:
        return (int(field),)
    raise _err(f"bad axis {field!r} in {text!r} for {model.name}")


def _int(text: str, whole: str, lo: int, hi: int) -> int:
    # Python's int() accepts '_' and unicode digits; the protocol has plain ASCII digits only.
    if not text or len(text) > 10 or not all("0" <= c <= "9" for c in text):
        raise _err(f"bad number {text!r} in {whole!r}")
    v = int(text)
    if not lo <= v <= hi:
        raise _err(f"number {v} outside {lo}..{hi} in {whole!r}")
    return v


def parse_command(model: ShotModel, line: bytes) -> Command:
    """Parse one command line (what a controller receives). ``G`` alone is accepted as ``G:``.

    Raises:
        ProtocolError: unknown command, bad axis, bad or out-of-range parameter
            (what the controller answers with NG).
    """
    text = clean_line(line)
    if text in ("G", "G:"):
        return Go()
    if text == "Q:":
        return Status()
    if text == "!:":
        return Ready()
    if text == "L:E":
        return Stop(tuple(range(1, model.axes + 1)), emergency=True)
    if len(text) < 3 or text[1] != ":":
        raise _err(f"unknown command {text!r}")
    code, rest = text[0], text[2:]
    if code == "?":
        if not re.fullmatch(r"[A-Z]{1,4}", rest):
            raise _err(f"bad information query {text!r}")
        return Info(rest)
    axis_field, tail = rest[0], rest[1:]
    if code in "HLR":
        axes = _parse_axes(model, axis_field, text)
        if code == "H":
            if model.home_needs_direction:
                _check_dirs(tuple(tail), len(axes))
                return Home(axes, tuple(tail))
            if tail:
                raise _err(f"unexpected {tail!r} in {text!r}")
            return Home(axes)
        if tail:
            raise _err(f"unexpected {tail!r} in {text!r}")
        return Stop(axes) if code == "L" else SetZero(axes)
    if code in "AM":
        if code == "A" and not model.absolute_moves:
            raise _err(f"{model.name} has no A: command")
        axes = _parse_axes(model, axis_field, text)
        parts = re.fullmatch(r"(?:[+-]P[0-9]{1,10})+", tail)
        if not parts:
            raise _err(f"bad move parameters in {text!r}")
        pulses = []
        for sign, digits in re.findall(r"([+-])P([0-9]{1,10})", tail):
            v = _int(digits, text, 0, model.pulse_limit)
            pulses.append(-v if sign == "-" else v)
        if len(pulses) != len(axes):
            raise _err(f"{len(axes)} axes but {len(pulses)} pulse counts in {text!r}")
        return Arm(code == "A", axes, tuple(pulses))
    if code == "J":
        axes = _parse_axes(model, axis_field, text)
        _check_dirs(tuple(tail), len(axes))
        return Jog(axes, tuple(tail))
    if code == "D":
        if model.speed_range_prefix is not None:
            if axis_field != model.speed_range_prefix:
                raise _err(f"{model.name} speed range must be {model.speed_range_prefix!r} in {text!r}")
            axes = tuple(range(1, model.axes + 1))
        else:
            axes = _parse_axes(model, axis_field, text)
        groups = re.findall(r"S([0-9]{1,10})F([0-9]{1,10})R([0-9]{1,10})", tail)
        if not re.fullmatch(r"(?:S[0-9]{1,10}F[0-9]{1,10}R[0-9]{1,10})+", tail) or len(groups) != len(axes):
            raise _err(f"bad speed parameters in {text!r}")
        speeds = []
        for s, f, r in groups:
            sp = Speed(_int(s, text, 0, 10**10), _int(f, text, 0, 10**10), _int(r, text, 0, 10**10))
            check_speed(model, sp)
            speeds.append(sp)
        return SetSpeed(axes, tuple(speeds))
    if code == "S":
        if not model.divisions:
            raise _err(f"{model.name} has no S: command")
        (axis,) = _parse_axes(model, axis_field, text) if axis_field != "W" else (0,)
        if axis == 0:
            raise _err(f"S: takes one axis in {text!r}")
        div = _int(tail, text, 0, 1000)
        if div not in model.divisions:
            raise _err(f"division {div} not in {model.divisions}")
        return SetDivision(axis, div)
    if code == "C":
        if axis_field == "W":
            raise _err(f"C: takes one axis in {text!r}")
        (axis,) = _parse_axes(model, axis_field, text)
        if tail not in ("0", "1"):
            raise _err(f"bad excitation {tail!r} in {text!r}")
        return Excite(axis, tail == "1")
    raise _err(f"unknown command {text!r}")


# --------------------------------------------------------------------------- replies


OK = b"OK\r\n"
NG = b"NG\r\n"


def parse_ack(line: bytes) -> bool:
    """``OK`` -> True, ``NG`` -> False; anything else (garbled, truncated) raises ProtocolError."""
    text = clean_line(line)
    if text == "OK":
        return True
    if text == "NG":
        return False
    raise _err(f"expected OK or NG, got {bytes(line)!r}")


def format_ack(ok: bool) -> bytes:
    return OK if ok else NG


@dataclass(frozen=True)
class StatusReply:
    """A parsed ``Q:`` line.

    Attributes:
        positions: position count of every axis (pulses).
        accepted: ACK1 ``K`` (last command accepted) or ``X`` (command or parameter error).
        limits: axes (1-based) that stopped at a limit switch (ACK2).
        busy: ACK3 ``B`` (moving) or ``R`` (ready).
    """

    positions: tuple[int, ...]
    accepted: bool
    limits: frozenset[int]
    busy: bool


FIELD_WIDTH = 10
_FIELD_RE = re.compile(r"([ +-])( *)([0-9]+)")
# ACK2 letters of two-axis controllers; one-axis controllers use K and L only.
_ACK2_LETTERS = {"K": frozenset(), "L": frozenset({1}), "M": frozenset({2}), "W": frozenset({1, 2})}


def format_position(pulses: int) -> str:
    """One 10-column position field: sign column (``-`` or blank), number right-aligned."""
    digits = str(abs(int(pulses)))
    if len(digits) > FIELD_WIDTH - 1:
        raise _err(f"position {pulses} does not fit the status field")
    return ("-" if pulses < 0 else " ") + digits.rjust(FIELD_WIDTH - 1)


def parse_position(field: str) -> int:
    """Parse one 10-column position field (sign column ``-``, ``+`` or blank)."""
    m = _FIELD_RE.fullmatch(field)
    if len(field) != FIELD_WIDTH or not m:
        raise _err(f"bad position field {field!r}")
    v = int(m.group(3))
    return -v if m.group(1) == "-" else v


def _format_ack2(model: ShotModel, limits: frozenset[int]) -> str:
    if model.limit_bitmask:
        mask = sum(1 << (a - 1) for a in limits)
        if mask == 0:
            return "K"
        if mask == (1 << model.axes) - 1:
            return "W"
        return f"{mask:X}"
    for letter, axes in _ACK2_LETTERS.items():
        if axes == limits and (model.axes > 1 or letter in "KL"):
            return letter
    raise _err(f"{model.name} cannot report limits on axes {sorted(limits)}")


def _parse_ack2(model: ShotModel, c: str, text: str) -> frozenset[int]:
    if model.limit_bitmask:
        if c == "K":
            return frozenset()
        if c == "W":
            return frozenset(range(1, model.axes + 1))
        if len(c) == 1 and c in "0123456789ABCDEF":
            mask = int(c, 16)
            if mask < 1 << model.axes:
                return frozenset(a for a in range(1, model.axes + 1) if mask & (1 << (a - 1)))
        raise _err(f"bad ACK2 {c!r} in {text!r}")
    axes = _ACK2_LETTERS.get(c)
    if axes is None or (model.axes == 1 and c not in "KL"):
        raise _err(f"bad ACK2 {c!r} in {text!r}")
    return axes


def format_status(model: ShotModel, st: StatusReply) -> bytes:
    """The ``Q:`` reply line, e.g. ``-    50000,-    50000,K,K,R\\r\\n``."""
    if len(st.positions) != model.axes:
        raise _err(f"{model.name} reports {model.axes} positions, got {len(st.positions)}")
    fields = [format_position(p) for p in st.positions]
    fields += ["K" if st.accepted else "X", _format_ack2(model, st.limits), "B" if st.busy else "R"]
    return ",".join(fields).encode("ascii") + TERMINATOR


def parse_status(model: ShotModel, line: bytes) -> StatusReply:
    """Parse a ``Q:`` reply: ``model.axes`` position fields, then ACK1, ACK2, ACK3."""
    text = clean_line(line)
    parts = text.split(",")
    if len(parts) != model.axes + 3:
        raise _err(f"{model.name} status needs {model.axes} positions and 3 flags, got {text!r}")
    positions = tuple(parse_position(f) for f in parts[: model.axes])
    ack1, ack2, ack3 = parts[model.axes:]
    if ack1 not in ("K", "X"):
        raise _err(f"bad ACK1 {ack1!r} in {text!r}")
    if ack3 not in ("B", "R"):
        raise _err(f"bad ACK3 {ack3!r} in {text!r}")
    return StatusReply(positions, ack1 == "K", _parse_ack2(model, ack2, text), ack3 == "B")


def parse_ready(line: bytes) -> bool:
    """``!:`` reply: ``B`` -> True (busy), ``R`` -> False (ready)."""
    text = clean_line(line)
    if text == "B":
        return True
    if text == "R":
        return False
    raise _err(f"expected B or R, got {bytes(line)!r}")


def format_ready(busy: bool) -> bytes:
    return b"B\r\n" if busy else b"R\r\n"


def parse_info(line: bytes) -> str:
    """``?:N`` / ``?:V`` reply: the text without padding. Empty, ``NG`` or garbled raise ProtocolError."""
    text = clean_line(line).strip()
    if not text:
        raise _err("empty information reply")
    if text == "NG":
        raise _err("information query refused (NG; the controller refuses ?: while an axis moves)")
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9 ._/()+-]*", text):
        raise _err(f"garbled information reply {bytes(line)!r}")
    return text


def format_info(text: str) -> bytes:
    return text.encode("ascii") + TERMINATOR


def same_product(reported: str, model: ShotModel) -> bool:
    """True if a ``?:N`` reply names this model (spaces, hyphens and case ignored;
    suffixes such as ``SHOT-702H`` accepted)."""
    def norm(s: str) -> str:
        return re.sub(r"[^A-Z0-9]", "", s.upper())

    return norm(reported).startswith(norm(model.name))


def round_pulses(value: float) -> int:
    """Nearest integer count; ProtocolError for NaN or infinity."""
    if not math.isfinite(value):
        raise _err(f"pulse count {value} is not finite")
    return round(value)
