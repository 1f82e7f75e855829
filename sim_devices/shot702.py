"""Simulated Sigma Koki stage controller (SHOT-702 and its variants) driving an
SGSP-120YAW rotation stage on the virtual bench.

It parses and answers with :mod:`drivers.shot_protocol`, so it speaks exactly
the bytes the real controller does. Motion is a trapezoidal profile (start speed
S, top speed F, ramp R ms, as set with ``D:``) evaluated lazily from the
simulated clock; the rotation axis writes its physical angle into the named
:class:`~sim_devices.bench.Bench` whenever the twin is touched.

Physical model: every axis tracks its position in *full steps* from the
mechanical origin (the origin sensor), so changing the microstep division with
``S:`` changes the size of a count but not where the stage is. The position
count keeps its value across ``S:`` (*unconfirmed* on the real controller).
The physical angle of the rotation axis is
``zero_offset_deg + full_steps * degrees_per_pulse``.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

from drivers import shot_protocol as sp
from drivers.errors import ProtocolError
from sim_devices.bench import get_bench
from sim_devices.faults import FaultPlan
from sim_devices.serial_twin import SerialTwin, SimClock

#: Longest command line the twin buffers before discarding garbage.
MAX_LINE = 256
#: Controller processing time before the first reply byte, seconds (*unconfirmed*).
LATENCY_S = 0.0005


@dataclass
class Profile:
    """A monotonic move as kinematic segments (duration, start speed, acceleration)
    in full steps, starting at ``t0`` (simulated s) from ``x0`` in ``direction`` (+1/-1).

    ``stops_at_limit`` marks a move cut short by a limit switch; ``homing`` one that
    ends by zeroing the count.
    """

    t0: float
    x0: float
    direction: int
    segments: list[tuple[float, float, float]]
    stops_at_limit: bool = False
    homing: bool = False

    @property
    def duration(self) -> float:
        return sum(d for d, _, _ in self.segments)

    @property
    def end_time(self) -> float:
        return self.t0 + self.duration

    def _distance(self, tau: float) -> tuple[float, float]:
        """(distance travelled, speed) ``tau`` seconds after the start."""
        s = 0.0
        for dur, v0, acc in self.segments:
            if tau <= dur:
                return s + v0 * tau + 0.5 * acc * tau * tau, v0 + acc * tau
            s += v0 * dur + 0.5 * acc * dur * dur
            tau -= dur
        return s, 0.0

    def position(self, t: float) -> float:
        return self.x0 + self.direction * self._distance(max(0.0, t - self.t0))[0]

    def speed(self, t: float) -> float:
        return self._distance(max(0.0, t - self.t0))[1]

    @property
    def end_position(self) -> float:
        return self.x0 + self.direction * self._distance(math.inf)[0] if math.isfinite(self.duration) else math.nan

    def cut_at_distance(self, d: float) -> None:
        """End the move abruptly after ``d`` full steps (a limit switch cuts the drive)."""
        s, kept = 0.0, []
        for dur, v0, acc in self.segments:
            seg = v0 * dur + 0.5 * acc * dur * dur if math.isfinite(dur) else math.inf
            if s + seg >= d:
                rem = d - s
                disc = max(0.0, v0 * v0 + 2.0 * acc * rem)
                tau = 2.0 * rem / (v0 + math.sqrt(disc)) if v0 + math.sqrt(disc) > 0 else 0.0
                kept.append((min(tau, dur), v0, acc))
                self.segments = kept
                self.stops_at_limit = True
                return
            kept.append((dur, v0, acc))
            s += seg


def trapezoid(distance: float, v_start: float, v_max: float, ramp_s: float) -> list[tuple[float, float, float]]:
    """Segments of a move over ``distance`` full steps: ramp from the start speed to the
    top speed in ``ramp_s``, cruise, ramp down; a triangle if the move is too short."""
    if distance <= 0:
        return []
    v_start = min(v_start, v_max)
    if ramp_s <= 0 or v_max <= v_start:
        return [(distance / v_max, v_max, 0.0)]
    a = (v_max - v_start) / ramp_s
    d_ramp = 0.5 * (v_start + v_max) * ramp_s
    if 2 * d_ramp <= distance:
        return [(ramp_s, v_start, a), ((distance - 2 * d_ramp) / v_max, v_max, 0.0), (ramp_s, v_max, -a)]
    v_peak = math.sqrt(v_start * v_start + a * distance)
    t1 = (v_peak - v_start) / a
    return [(t1, v_start, a), (t1, v_peak, -a)]


@dataclass
class AxisState:
    """One axis: ``steps`` (full steps from the mechanical origin) when idle, the
    full-step position of count 0, the division and speed table, the running move."""

    steps: float = 0.0
    zero_steps: float = 0.0
    division: int = 2
    speed: sp.Speed = field(default_factory=lambda: sp.Speed(500, 5000, 200))
    profile: Profile | None = None
    at_limit: bool = False
    excited: bool = True

    def position(self, now: float) -> float:
        return self.profile.position(now) if self.profile is not None else self.steps

    def count(self, now: float) -> int:
        return round((self.position(now) - self.zero_steps) * self.division)

    def busy(self, now: float) -> bool:
        return self.profile is not None and now < self.profile.end_time


class Shot702Twin(SerialTwin):
    """Byte-level twin of a Sigma Koki controller with an SGSP-120YAW on one axis.

    Args:
        clock: simulated clock (its time scale makes moves faster, not different).
        faults: seeded faults: ``drop`` (reply lost after the command was executed),
            ``garble`` (one reply byte corrupted), ``ng`` (command refused, not
            executed), ``limit`` (a limit switch hit part-way through a move).
        model: controller model name (replies and commands differ, see shot_protocol).
        bench: name of the bench whose ``stage_angle_deg`` the rotation axis drives.
        degrees_per_pulse: stage angle per full step (SGSP-120YAW: 0.005 deg).
        division: microstep division at power-on.
        zero_offset_deg: physical (world) angle of the mechanical origin.
        start_deg: physical angle at power-on (count 0 there); default the origin.
        limits_pulses: (minus, plus) limit switch positions in counts from the
            mechanical origin at the power-on division; None: no switches
            (the SGSP-120YAW turns freely).
        rotation_axis: axis (1-based) the rotation stage is connected to.
        stray_nul: emit a ``\\x00`` before the first reply, as some units do.
    """

    def __init__(self, clock: SimClock, faults: FaultPlan | None = None, *, model: str = "SHOT-702",
                 bench: str = "default", degrees_per_pulse: float = 0.005, division: int = 2,
                 zero_offset_deg: float = 0.0, start_deg: float | None = None,
                 limits_pulses: tuple[int, int] | None = None, rotation_axis: int = 1,
                 stray_nul: bool = False, version: str = "V1.00") -> None:
        super().__init__(clock, faults)
        if model not in sp.MODELS:
            raise ValueError(f"unknown model {model!r}; known: {', '.join(sp.MODELS)}")
        self.model = sp.MODELS[model]
        if not 1 <= rotation_axis <= self.model.axes:
            raise ValueError(f"rotation axis {rotation_axis} not in 1..{self.model.axes}")
        if not (math.isfinite(degrees_per_pulse) and degrees_per_pulse > 0):
            raise ValueError(f"degrees_per_pulse must be > 0, got {degrees_per_pulse}")
        if self.model.divisions and division not in self.model.divisions:
            raise ValueError(f"division {division} not in {self.model.divisions}")
        if not self.model.divisions:
            division = 2  # GSC-02: fixed half step
        if limits_pulses is not None and not limits_pulses[0] < 0 < limits_pulses[1]:
            raise ValueError(f"limit switches {limits_pulses} must straddle the origin (minus < 0 < plus)")
        self.bench_name = bench
        self.degrees_per_pulse = degrees_per_pulse
        self.zero_offset_deg = zero_offset_deg
        self.rotation_axis = rotation_axis
        self.version = version
        self._stray_nul = stray_nul
        self.limits_steps = None if limits_pulses is None else (limits_pulses[0] / division, limits_pulses[1] / division)
        start = 0.0 if start_deg is None else (start_deg - zero_offset_deg) / degrees_per_pulse
        s, f, r = self.model.default_speed_pps
        self.axes = [AxisState(steps=start, zero_steps=start, division=division, speed=sp.Speed(s, f, r))
                     for _ in range(self.model.axes)]
        self.accepted = True
        self.armed: sp.Arm | sp.Jog | None = None
        #: The latest complete lines received (for tests and debugging; bounded).
        self.commands: deque[bytes] = deque(maxlen=10_000)
        self._sync(self.clock.now())

    # ------------------------------------------------------------ physical state
    def _sync(self, now: float) -> None:
        """Finish moves whose time has come and publish the angle on the bench."""
        for ax in self.axes:
            p = ax.profile
            if p is not None and now >= p.end_time:
                ax.steps = p.end_position
                ax.at_limit = ax.at_limit or p.stops_at_limit
                if p.homing and not p.stops_at_limit:
                    ax.zero_steps = ax.steps  # count 0 at the origin sensor
                ax.profile = None
        bench = get_bench(self.bench_name)
        with bench.lock:
            bench.stage_angle_deg = self._angle(now)

    def _angle(self, now: float) -> float:
        return self.zero_offset_deg + self.axes[self.rotation_axis - 1].position(now) * self.degrees_per_pulse

    def angle_deg(self) -> float:
        """Physical angle of the rotation axis now (degrees, world frame)."""
        with self.lock:
            now = self.clock.now()
            self._sync(now)
            return self._angle(now)

    def busy(self) -> bool:
        with self.lock:
            now = self.clock.now()
            self._sync(now)
            return any(ax.busy(now) for ax in self.axes)

    def read_ready(self, size: int | None = None) -> bytes:
        with self.lock:
            self._sync(self.clock.now())
            return super().read_ready(size)

    # ------------------------------------------------------------ faults
    def should_fault(self, kind: str, cmd: sp.Command | None) -> bool:
        """Whether a fault of ``kind`` strikes this exchange (tests may override)."""
        return self.faults.hit(kind)

    # ------------------------------------------------------------ bytes in
    def consume(self, buf: bytearray) -> None:
        while True:
            ends = [i for i in (buf.find(b"\r"), buf.find(b"\n")) if i >= 0]
            if not ends:
                if len(buf) > MAX_LINE:  # line noise without a terminator
                    del buf[:]
                return
            i = min(ends)
            line = bytes(buf[:i])
            del buf[: i + 1]
            if line.replace(b"\x00", b"").strip() == b"":
                continue  # the LF of CR LF, or stray NULs
            self.commands.append(line)
            self._execute(line)

    def _send(self, data: bytes, cmd: sp.Command | None) -> None:
        drop = self.should_fault("drop", cmd)
        garble = self.should_fault("garble", cmd)
        if drop:
            return
        if garble:
            data = self.faults.garble(data)
        if self._stray_nul:
            data = b"\x00" + data
            self._stray_nul = False
        self.reply(data, LATENCY_S + len(data) * 10.0 / self.model.baudrate)

    def _ack(self, ok: bool, cmd: sp.Command | None) -> None:
        self.accepted = ok
        if self.model.acknowledges:
            self._send(sp.format_ack(ok), cmd)

    def _execute(self, line: bytes) -> None:
        now = self.clock.now()
        self._sync(now)
        try:
            cmd = sp.parse_command(self.model, line + sp.TERMINATOR)
        except ProtocolError:
            self._ack(False, None)
            return
        busy = any(ax.busy(now) for ax in self.axes)
        if busy and not isinstance(cmd, sp.ALLOWED_WHILE_BUSY):
            self._ack(False, cmd)
            return
        if isinstance(cmd, sp.Status):
            self._send(self._status(now), cmd)
        elif isinstance(cmd, sp.Ready):
            self._send(sp.format_ready(busy), cmd)
        elif isinstance(cmd, sp.Info):
            text = {"N": self.model.name, "V": self.version}.get(cmd.what)
            if text is None:
                self._ack(False, cmd)
            else:
                self._send(sp.format_info(text), cmd)
        elif self.should_fault("ng", cmd):
            self._ack(False, cmd)
        else:
            self._ack(self._apply(cmd, now), cmd)

    def _status(self, now: float) -> bytes:
        st = sp.StatusReply(
            positions=tuple(ax.count(now) for ax in self.axes),
            accepted=self.accepted,
            limits=frozenset(i + 1 for i, ax in enumerate(self.axes) if ax.at_limit),
            busy=any(ax.busy(now) for ax in self.axes),
        )
        return sp.format_status(self.model, st)

    # ------------------------------------------------------------ commands
    def _apply(self, cmd: sp.Command, now: float) -> bool:
        if isinstance(cmd, sp.Home):
            self.armed = None
            for a in cmd.axes:
                self._start(a, 0.0, now, homing=True, cmd=cmd)
            return True
        if isinstance(cmd, sp.Arm):
            for a, p in zip(cmd.axes, cmd.pulses):
                target = p if cmd.absolute else self.axes[a - 1].count(now) + p
                if abs(target) > self.model.pulse_limit:
                    return False
            self.armed = cmd
            return True
        if isinstance(cmd, sp.Jog):
            self.armed = cmd
            return True
        if isinstance(cmd, sp.Go):
            armed, self.armed = self.armed, None
            if armed is None:
                return False
            if isinstance(armed, sp.Jog):
                for a, d in zip(armed.axes, armed.directions):
                    self._start(a, math.inf if d == "+" else -math.inf, now, cmd=cmd)
                return True
            for a, p in zip(armed.axes, armed.pulses):
                ax = self.axes[a - 1]
                count = p if armed.absolute else ax.count(now) + p
                self._start(a, ax.zero_steps + count / ax.division, now, cmd=cmd)
            return True
        if isinstance(cmd, sp.Stop):
            self.armed = None
            for a in cmd.axes:
                self._stop(a, now, emergency=cmd.emergency)
            return True
        if isinstance(cmd, sp.SetZero):
            for a in cmd.axes:
                self.axes[a - 1].zero_steps = self.axes[a - 1].position(now)
            return True
        if isinstance(cmd, sp.SetSpeed):
            for a, speed in zip(cmd.axes, cmd.speeds):
                self.axes[a - 1].speed = speed
            return True
        if isinstance(cmd, sp.SetDivision):
            ax = self.axes[cmd.axis - 1]
            count = ax.count(now)
            ax.division = cmd.division
            ax.zero_steps = ax.position(now) - count / cmd.division  # the count keeps its value
            return True
        if isinstance(cmd, sp.Excite):
            self.axes[cmd.axis - 1].excited = cmd.on
            return True
        return False

    def _start(self, axis: int, target_steps: float, now: float, *, homing: bool = False,
               cmd: sp.Command | None = None) -> None:
        ax = self.axes[axis - 1]
        x = ax.position(now)
        ax.at_limit = False
        direction = 1 if target_steps >= x else -1
        distance = abs(target_steps - x)
        # A limit switch in the way stops the axis there.
        stop_at: float | None = None
        if self.limits_steps is not None:
            switch = self.limits_steps[1] if direction > 0 else self.limits_steps[0]
            to_switch = (switch - x) * direction
            if to_switch <= 0 and distance > 0:
                ax.at_limit = True  # already on the switch: the drive refuses to move further
                return
            if to_switch < distance:
                stop_at = to_switch
        # Injected fault: a limit switch reports part-way through the move.
        if self.should_fault("limit", cmd) and distance > 0 and math.isfinite(distance):
            frac = self.faults.uniform(0.2, 0.8) * distance
            stop_at = frac if stop_at is None else min(stop_at, frac)
        div = ax.division
        if math.isinf(distance):
            segments = [(math.inf, ax.speed.s / div, 0.0)]  # jog: minimum speed until stopped
        else:
            segments = trapezoid(distance, ax.speed.s / div, ax.speed.f / div, ax.speed.r_ms / 1000.0)
        prof = Profile(now, x, direction, segments, homing=homing)
        if stop_at is not None:
            prof.cut_at_distance(stop_at)
        ax.profile = prof
        if prof.duration <= 0:
            self._sync(now)

    def _stop(self, axis: int, now: float, *, emergency: bool) -> None:
        ax = self.axes[axis - 1]
        p = ax.profile
        if p is None or now >= p.end_time:
            return
        x, v = p.position(now), p.speed(now)
        div = ax.division
        v_start = ax.speed.s / div
        ramp = ax.speed.r_ms / 1000.0
        if emergency or ramp <= 0 or v <= v_start:
            segments: list[tuple[float, float, float]] = []
        else:
            a = (ax.speed.f / div - v_start) / ramp if ax.speed.f > ax.speed.s else math.inf
            t_dec = (v - v_start) / a if math.isfinite(a) else 0.0
            if p.end_time - now <= t_dec:
                return  # already ramping down to the target: it stops no later than asked
            segments = [(t_dec, v, -a)] if t_dec > 0 else []
        new = Profile(now, x, p.direction, segments)
        if self.limits_steps is not None and segments:
            switch = self.limits_steps[1] if p.direction > 0 else self.limits_steps[0]
            d_new = new._distance(math.inf)[0]
            if (switch - x) * p.direction < d_new:
                new.cut_at_distance(max(0.0, (switch - x) * p.direction))
        ax.profile = new
        self._sync(now)
