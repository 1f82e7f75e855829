"""Sigma Koki (OptoSigma) stage controller driving an SGSP-120YAW rotation stage.

The controller counts pulses; the driver converts with
``angle = count * degrees_per_pulse / division + zero_offset_deg``.

Exchanges follow the protocol's own safety rules (see :mod:`drivers.shot_protocol`):

- Queries (``Q:``, ``!:``, ``?:``) are idempotent: after a timeout or a garbled
  reply the input is flushed and the query resent, up to ``retries`` times.
- A lost or garbled ``OK`` leaves a command's fate unknown. Settings (``D:``,
  ``S:``, ``L:``) are simply resent. An armed move (``A:``/``M:``) is cancelled
  with ``L:`` before it is armed again. ``G:`` and ``H:`` are never resent
  blindly: the driver reads the status first and only drives again if the stage
  neither moves nor already stands at the target.
- ``NG`` (or ACK1 ``X`` on the GSC-02, which sends no OK/NG) raises
  :class:`~drivers.errors.ProtocolError` naming the command.
- A position or a "ready" used for a decision is read twice and must agree, so a
  corrupted digit in one reply cannot pass for a position.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from typing import TypeVar

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
from drivers.interfaces import AngleRange, RotationStage
from drivers.iolog import Transcript
from drivers.serial_link import SerialLink

T = TypeVar("T")


class SigmaKokiStage(RotationStage):
    """Rotation stage on one axis of a Sigma Koki controller.

    Args:
        url: port for ``serial.serial_for_url`` (``/dev/ttyUSB0``, a pty, ``sim-shot702://bench``).
        allowed: angle interval (degrees) the stage may occupy; no call leaves it.
        model: ``SHOT-702`` (default), ``SHOT-302GS``, ``SHOT-304GS``, ``GSC-01`` or ``GSC-02``.
        axis: controller axis (1-based) the stage is wired to.
        degrees_per_pulse: stage angle per pulse at full step (SGSP-120YAW: 0.005 deg).
        division: microstep division, sent with ``S:`` at connection (GSC-02: fixed 2).
        zero_offset_deg: angle (degrees) of the mechanical origin, where ``H:`` leaves count 0.
        speed_deg_s: top speed in degrees per second sent with ``D:`` at connection;
            None: the model's power-on table (``ShotModel.default_speed_pps``).
        accel_ms: ramp time from start to top speed, milliseconds.
        transcript: byte log of every exchange.
        retries: resends after a timeout or garbled reply (>= 0).
        reply_timeout_s: time allowed for each reply line, seconds.
        settle_margin_s: margin added to the kinematic time of a move for its timeout.
        home_direction: ``+`` or ``-``, for models whose ``H:`` needs one (GSC-02).

    Raises:
        ParameterError: a bad argument (nothing is opened).
        DeviceConnectionError: the port cannot be opened, nothing answers, or the
            controller names itself as another model.
        StateError: the stage is moving when the driver connects.
    """

    def __init__(
        self,
        url: str,
        *,
        allowed: AngleRange,
        model: str = "SHOT-702",
        axis: int = 1,
        degrees_per_pulse: float = 0.005,
        division: int = 2,
        zero_offset_deg: float = 0.0,
        speed_deg_s: float | None = None,
        accel_ms: int = 100,
        transcript: Transcript | None = None,
        retries: int = 2,
        reply_timeout_s: float = 1.0,
        settle_margin_s: float = 2.0,
        home_direction: str = "+",
    ) -> None:
        name = self.device_name
        if model not in sp.MODELS:
            raise ParameterError(f"unknown controller model {model!r}; known: {', '.join(sp.MODELS)}", device=name)
        self._model = m = sp.MODELS[model]
        if not isinstance(axis, int) or not 1 <= axis <= m.axes:
            raise ParameterError(f"{model} has axes 1..{m.axes}, got axis {axis!r}", device=name)
        if not (isinstance(degrees_per_pulse, (int, float)) and math.isfinite(degrees_per_pulse) and degrees_per_pulse > 0):
            raise ParameterError(f"degrees_per_pulse must be > 0, got {degrees_per_pulse!r}", device=name)
        allowed_divs = m.divisions or (2,)  # GSC-02 counts half steps
        if division not in allowed_divs:
            raise ParameterError(f"{model} division must be one of {allowed_divs}, got {division!r}", device=name)
        if not (isinstance(zero_offset_deg, (int, float)) and math.isfinite(zero_offset_deg)):
            raise ParameterError(f"zero_offset_deg must be finite, got {zero_offset_deg!r}", device=name)
        lo, hi = m.accel_range_ms
        if not isinstance(accel_ms, int) or not lo <= accel_ms <= hi:
            raise ParameterError(f"accel_ms must be an integer in {lo}..{hi}, got {accel_ms!r}", device=name)
        if not isinstance(retries, int) or retries < 0:
            raise ParameterError(f"retries must be an integer >= 0, got {retries!r}", device=name)
        if not (math.isfinite(reply_timeout_s) and reply_timeout_s > 0):
            raise ParameterError(f"reply_timeout_s must be > 0, got {reply_timeout_s!r}", device=name)
        if home_direction not in ("+", "-"):
            raise ParameterError(f"home_direction must be '+' or '-', got {home_direction!r}", device=name)
        super().__init__(allowed, settle_margin_s=settle_margin_s)
        self._axis = axis
        self._dpp = float(degrees_per_pulse)
        self._division = division
        self._zero = float(zero_offset_deg)
        self._accel_ms = accel_ms
        self._retries = retries
        self._reply_timeout_s = float(reply_timeout_s)
        self._home_dir = home_direction
        self._lock = threading.RLock()
        self._target: int | None = None  # count the last move was sent to, checked when it ends
        if speed_deg_s is None:
            s, f, _ = m.default_speed_pps
            self._speed = sp.Speed(s, f, accel_ms)
        else:
            v = _positive(speed_deg_s, "speed_deg_s")
            self._speed = self._speed_table(v)
        self._link: SerialLink | None = SerialLink(url, device=name, transcript=transcript, **m.line_settings)
        try:
            self._connect(url)
        except BaseException:
            self._link.close()
            self._link = None
            raise

    def _connect(self, url: str) -> None:
        try:
            reported = self._query(sp.Info("N"), sp.parse_info)
        except DeviceTimeout as e:
            raise DeviceConnectionError(f"no {self._model.name} answers on {url!r} ({e})", device=self.device_name) from None
        if not sp.same_product(reported, self._model):
            raise DeviceConnectionError(
                f"the controller on {url!r} says it is {reported!r}, not a {self._model.name}; fix 'model' in rig.yaml",
                device=self.device_name,
            )
        if self._status(confirm=True).busy:
            raise StateError("the stage is moving; wait for it to stop, then connect again", device=self.device_name)
        if self._model.divisions:
            self._command(sp.SetDivision(self._axis, self._division))
        self._send_speed(self._speed)

    # ------------------------------------------------------------------ facts
    @property
    def model(self) -> sp.ShotModel:
        return self._model

    @property
    def degrees_per_count(self) -> float:
        """Angle of one position count at the configured division, degrees."""
        return self._dpp / self._division

    def identity(self) -> str:
        """``"<product> <version>"`` as ``?:N`` and ``?:V`` report them, e.g. ``SHOT-702 V1.00``."""
        with self._lock:
            name = self._query(sp.Info("N"), sp.parse_info)
            version = self._query(sp.Info("V"), sp.parse_info)
            return f"{name} {version}"

    def speed(self) -> float:
        return self._speed.f * self.degrees_per_count

    def acceleration_time_s(self) -> float:
        return self._speed.r_ms / 1000.0

    def home_angle(self) -> float:
        return self._zero

    def angle_of_count(self, count: int) -> float:
        """Angle in degrees of a position count."""
        return count * self.degrees_per_count + self._zero

    # ------------------------------------------------------------------ state
    def angle(self) -> float:
        """Current angle in degrees (read twice when idle: both reads must agree)."""
        with self._lock:
            return self.angle_of_count(self._status(confirm=True).positions[self._axis - 1])

    def is_busy(self) -> bool:
        """Polls ``!:``; a "ready" is confirmed with two agreeing ``Q:`` replies."""
        with self._lock:
            if self._query(sp.Ready(), sp.parse_ready):
                return True
            return self._status(confirm=True).busy

    def status(self) -> sp.StatusReply:
        """The controller's ``Q:`` status (positions of all axes, flags)."""
        with self._lock:
            return self._status(confirm=True)

    # ------------------------------------------------------------------ motion
    def _target_count(self, angle_deg: float) -> int:
        """The count nearest ``angle_deg`` whose angle lies inside the allowed range."""
        c = sp.round_pulses((angle_deg - self._zero) / self.degrees_per_count)
        if self.angle_of_count(c) not in self._allowed:
            c += 1 if self.angle_of_count(c) < self._allowed.lo else -1
            if self.angle_of_count(c) not in self._allowed:  # range narrower than one count
                raise LimitError(f"no position count lies inside [{self._allowed.lo}, {self._allowed.hi}] deg",
                                 device=self.device_name)
        if abs(c) > self._model.pulse_limit:
            raise LimitError(f"{angle_deg:.4f} deg is count {c}, beyond the controller's +/-{self._model.pulse_limit}",
                             device=self.device_name)
        return c

    def _do_move_to(self, angle_deg: float) -> None:
        with self._lock:
            target = self._target_count(angle_deg)
            self._target = target
            self._arm(target)
            self._command(sp.Go(), resolve=lambda: self._resolve_go(target))

    def _do_home(self) -> None:
        with self._lock:
            self._target = 0
            before = self._status(confirm=True).positions[self._axis - 1]
            dirs = (self._home_dir,) if self._model.home_needs_direction else ()
            self._command(sp.Home((self._axis,), dirs), resolve=lambda: self._resolve_home(before))

    def _do_stop(self) -> None:
        with self._lock:
            self._target = None
            self._command(sp.Stop((self._axis,)))

    def _do_set_speed(self, deg_per_s: float) -> None:
        with self._lock:
            table = self._speed_table(deg_per_s)
            if self.is_busy():
                raise StateError("cannot change the speed while the stage moves", device=self.device_name)
            self._send_speed(table)

    def _check_limit_switch(self) -> None:
        """After a move: LimitError if ACK2 reports a limit switch on our axis,
        StateError if the stage stopped short of the target for another reason."""
        with self._lock:
            st = self._status(confirm=True)
            target, self._target = self._target, None
            count = st.positions[self._axis - 1]
            if self._axis in st.limits:
                raise LimitError(
                    f"limit switch hit at {self.angle_of_count(count):.3f} deg"
                    + (f" on the way to {self.angle_of_count(target):.3f} deg" if target is not None else ""),
                    device=self.device_name,
                )
            if target is not None and count != target:
                raise StateError(
                    f"stage stopped at {self.angle_of_count(count):.3f} deg instead of "
                    f"{self.angle_of_count(target):.3f} deg (stopped from the front panel or another client?)",
                    device=self.device_name,
                )

    def close(self) -> None:
        """Stop the axis (decelerating) and release the port; a second call does nothing."""
        with self._lock:
            if self._link is None:
                return
            try:
                self._do_stop()
            finally:
                self._link.close()
                self._link = None

    # ------------------------------------------------------------------ helpers
    def _speed_table(self, deg_per_s: float) -> sp.Speed:
        m = self._model
        step = m.speed_step_pps
        f = round(deg_per_s / self.degrees_per_count / step) * step
        lo, hi = m.speed_range_pps
        if not lo <= f <= hi:
            raise LimitError(
                f"{deg_per_s} deg/s is {f} pulses/s, outside the {m.name}'s {lo}..{hi} pulses/s "
                f"({lo * self.degrees_per_count:g}..{hi * self.degrees_per_count:g} deg/s)",
                device=self.device_name,
            )
        # Start speed: half the top speed, at most 30000 pps (the vendor's own adapter's rule).
        s = f // 2 if f <= 50_000 else 30_000
        s = max(lo, s // step * step)
        return sp.Speed(s, f, self._accel_ms)

    def _send_speed(self, table: sp.Speed) -> None:
        m = self._model
        if m.speed_range_prefix is not None:
            # GSC-02 sets both axes in one D: command; the other axis gets the same table.
            cmd = sp.SetSpeed(tuple(range(1, m.axes + 1)), (table,) * m.axes)
        else:
            cmd = sp.SetSpeed((self._axis,), (table,))
        self._command(cmd)
        self._speed = table

    def _arm(self, target: int) -> None:
        def arm_command() -> sp.Arm:
            if self._model.absolute_moves:
                return sp.Arm(True, (self._axis,), (target,))
            here = self._status(confirm=True).positions[self._axis - 1]
            return sp.Arm(False, (self._axis,), (target - here,))

        def cancel_pending() -> bool:
            # A lost OK: the move may be armed or not. L: cancels a pending A:/M:, so
            # arming again cannot leave two moves queued.
            self._command(sp.Stop((self._axis,)))
            return False

        self._command(arm_command(), resolve=cancel_pending, rebuild=arm_command)

    def _resolve_go(self, target: int) -> bool:
        """After a lost reply to G:: True if the move runs or is done; else re-arm and return False."""
        st = self._status(confirm=True)
        if st.busy or st.positions[self._axis - 1] == target or self._axis in st.limits:
            return True
        self._arm(target)
        return False

    def _resolve_home(self, count_before: int) -> bool:
        """After a lost reply to H:: True if homing runs or has ended (the count, not 0
        before, reads 0 now); otherwise H: is sent again, which is harmless (homing is idempotent)."""
        st = self._status(confirm=True)
        return st.busy or self._axis in st.limits or (count_before != 0 and st.positions[self._axis - 1] == 0)

    # ------------------------------------------------------------------ exchanges
    def _link_or_fail(self) -> SerialLink:
        if self._link is None:
            raise StateError("the stage connection is closed", device=self.device_name)
        return self._link

    def _flush(self) -> None:
        """Discard unread input. A vanished pty or USB adapter makes the flush itself
        fail (``termios.error``, not an OSError), which is reported as a lost connection."""
        link = self._link_or_fail()
        try:
            link.reset_input()
        except Exception as e:  # noqa: BLE001 - re-raised as the typed error below
            raise DeviceConnectionError(f"port {link.url!r} failed: {e!r}", device=self.device_name) from None

    def _exchange(self, cmd: sp.Command) -> bytes:
        link = self._link_or_fail()
        # A reply that came after its timeout must not be taken for this command's.
        self._flush()
        link.write(sp.format_command(self._model, cmd))
        return link.read_until(sp.TERMINATOR, self._reply_timeout_s)

    def _query(self, cmd: sp.Command, parse: Callable[[bytes], T]) -> T:
        """A query with resends after a timeout or a malformed reply."""
        last: DeviceError | None = None
        for attempt in range(self._retries + 1):
            try:
                return parse(self._exchange(cmd))
            except (DeviceTimeout, ProtocolError) as e:
                last = e
        raise _again(last, self._retries + 1, _text(self._model, cmd))

    def _status(self, *, confirm: bool = False) -> sp.StatusReply:
        """``Q:``; with ``confirm``, an idle status must be read twice identically."""
        def parse(line: bytes) -> sp.StatusReply:
            return sp.parse_status(self._model, line)

        st = self._query(sp.Status(), parse)
        if not confirm:
            return st
        for _ in range(self._retries + 2):
            if st.busy:
                return st
            again = self._query(sp.Status(), parse)
            if again == st:
                return st
            st = again
        raise ProtocolError(f"status replies keep disagreeing (last {st})", device=self.device_name)

    def _command(self, cmd: sp.Command, *, resolve: Callable[[], bool] | None = None,
                 rebuild: Callable[[], sp.Command] | None = None) -> None:
        """Send a non-query command and make sure it was accepted.

        Args:
            resolve: after a lost or garbled reply, decides from the device state
                whether the command took effect (True) or must be sent again (False);
                None: the command is idempotent and is simply resent.
            rebuild: makes the command afresh for a resend (relative moves).
        """
        text = _text(self._model, cmd)
        last: DeviceError | None = None
        for attempt in range(self._retries + 1):
            if attempt:
                self._flush()
                if rebuild is not None:
                    cmd = rebuild()
                    text = _text(self._model, cmd)
            if not self._model.acknowledges:
                # GSC-02: no reply; ACK1 of the next status says whether it was accepted.
                self._link_or_fail().write(sp.format_command(self._model, cmd))
                if not self._status().accepted:
                    raise ProtocolError(f"controller refused {text!r} (ACK1=X)", device=self.device_name)
                return
            try:
                ok = sp.parse_ack(self._exchange(cmd))
            except (DeviceTimeout, ProtocolError) as e:
                last = e
                self._flush()
                if resolve is not None and resolve():
                    return
                continue
            if not ok:
                raise ProtocolError(f"controller refused {text!r} (NG)", device=self.device_name)
            return
        raise _again(last, self._retries + 1, text)


def _text(model: sp.ShotModel, cmd: sp.Command) -> str:
    return sp.format_command(model, cmd).decode("ascii").strip()


def _again(err: DeviceError | None, attempts: int, text: str) -> DeviceError:
    """The last error of a failed exchange, re-made with the command and attempt count."""
    kind = type(err) if err is not None else DeviceTimeout
    msg = f"{text!r} failed after {attempts} attempt(s): {err.args[0] if err is not None else 'no reply'}"
    return kind(msg, device="stage")


def _positive(value: float, what: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"{what} must be a number, got {value!r}", device="stage") from None
    if not (math.isfinite(v) and v > 0):
        raise ParameterError(f"{what} must be > 0, got {value!r}", device="stage")
    return v
