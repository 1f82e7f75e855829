"""A filter changer worked by hand: the operator is asked to insert each filter.

For rigs without a motorised wheel. The operator is the device: the changer
asks at the terminal, waits for the confirmation and remembers what was
confirmed. Nothing is known before the first confirmation, and nothing after an
aborted change (the operator may have taken the old filter out).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

from drivers.errors import StateError
from drivers.interfaces import FilterChanger

#: Answers that confirm a change (compared lower-cased, blanks stripped); '' is Enter.
CONFIRM = ("", "y", "yes")
#: Answers that abort.
ABORT = ("q", "quit")
#: Unclear answers tolerated before the change is abandoned; a scripted or piped
#: input that never confirms must not loop for ever.
MAX_UNCLEAR_ANSWERS = 5


class ManualFilterChanger(FilterChanger):
    """Filter changes confirmed by an operator.

    Args:
        positions: filter name -> slot number (labels for the operator; any
            distinct integers).
        ask: shows a prompt and returns the operator's answer (``input``);
            may raise EOFError.
        say: shows a message (``print``).

    ``select`` waits for the operator, not for a device, so it has no deadline;
    ``timeout_s`` is accepted for the interface and ignored. The operator
    aborts with ``q`` (or end of input), which raises :class:`StateError`.
    """

    def __init__(
        self,
        positions: Mapping[str, int],
        *,
        ask: Callable[[str], str] = input,
        say: Callable[[str], None] = print,
    ) -> None:
        super().__init__(positions)
        self._ask = ask
        self._say = say
        self._confirmed: int | None = None
        self._closed = False

    def identity(self) -> str:
        return "manual filter changer"

    def current(self) -> str | None:
        """The filter the operator last confirmed, or None (none yet, or a change was aborted)."""
        return None if self._confirmed is None else self._name_of(self._confirmed)

    def _do_current(self) -> int:
        if self._confirmed is None:
            raise StateError("no filter has been confirmed yet", device=self.device_name)
        return self._confirmed

    def _do_select(self, position: int, timeout_s: float | None) -> None:
        if self._closed:
            raise StateError("the manual filter changer is closed", device=self.device_name)
        if self._confirmed == position:
            return  # already in place: do not make the operator touch the rig
        name = next(n for n, p in self.positions.items() if p == position)
        previous = self._confirmed
        self._confirmed = None  # from now on the operator may have the old filter out
        prompt = (f"Insert filter '{name}' (slot {position}) into the beam, then press Enter "
                  f"(or 'y'); 'q' aborts: ")
        for _ in range(MAX_UNCLEAR_ANSWERS + 1):
            try:
                answer = self._ask(prompt)
            except EOFError:
                raise StateError(f"no confirmation for filter {name!r}: end of input", device=self.device_name) from None
            reply = (answer or "").strip().lower()
            if reply in CONFIRM:
                self._confirmed = position
                return
            if reply in ABORT:
                raise StateError(
                    f"operator aborted the change to filter {name!r}"
                    + (f" (was {self._name_of(previous)!r})" if previous is not None else ""),
                    device=self.device_name)
            self._say(f"Please press Enter (or type 'y') once filter '{name}' is in, or 'q' to abort.")
        raise StateError(f"no confirmation for filter {name!r} after {MAX_UNCLEAR_ANSWERS + 1} unclear answers",
                         device=self.device_name)

    def _name_of(self, position: int) -> str | None:
        return next((n for n, p in self.positions.items() if p == position), None)

    def close(self) -> None:
        self._closed = True
