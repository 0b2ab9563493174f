"""Where a failing controller falls back to, and the record of each fallback.

A mode falls back by ``FALLBACK`` (to DAMPING, then ZERO_TORQUE, then nowhere: the manager then writes a limp
command); a task controller (one that claimed a broadcaster-only run) to the passive command; the passive command
nowhere. Each fallback is recorded for the run's summary and said in the manager's ``fallback`` flag.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TypedDict

from humanoid_prime.control.controller import Controller
from humanoid_prime.control.flags import SafetyFlags
from humanoid_prime.modes import Mode

FALLBACK: dict[Mode, Mode | None] = {
    Mode.LOCOMOTION: Mode.DAMPING,
    Mode.REMOTE: Mode.DAMPING,
    Mode.STANDBY: Mode.DAMPING,
    Mode.DAMPING: Mode.ZERO_TORQUE,
    Mode.ZERO_TORQUE: None,
}
NO_FALLBACK_YET = "no mode controller is active"

# A fallback as the run's summary lists it.
Fallback = TypedDict("Fallback", {"tick": int, "from": str, "to": str, "reason": str})


class FallbackChain:
    """The fallbacks of one run's controllers (``by_mode``, and ``passive`` in a broadcaster-only run);
    ``records`` lists every fallback so far, and ``flags`` carries the latest."""

    def __init__(self, by_mode: Mapping[Mode, Controller], passive: Controller | None, flags: SafetyFlags) -> None:
        self._by_mode = by_mode
        self._passive = passive
        self._flags = flags
        self.records: list[Fallback] = []

    def after(self, controller: Controller) -> Controller | None:
        """The controller that takes over from a failing ``controller``; None: nothing does."""
        if controller.mode is not None:
            fallback = FALLBACK[controller.mode]
            return None if fallback is None else self._by_mode[fallback]
        return None if controller is self._passive else self._passive

    def record(self, tick: int, failed: Controller, to: Controller, reason: str) -> None:
        names = [c.mode.value if c.mode is not None else c.name for c in (failed, to)]
        self.records.append({"tick": tick, "from": names[0], "to": names[1], "reason": reason})
        self._flags.set_flag("fallback", f"{reason}; fell back from {names[0]} to {names[1]}")

    @property
    def last_reason(self) -> str:
        """Why the latest fallback happened."""
        return self.records[-1]["reason"] if self.records else NO_FALLBACK_YET
