"""What other threads ask of the control loop, handed to it at the start of a tick (``LoopRequests``): the
controller to make active next (a mode asked for, a task's claim, the hand-back), the operator's fault reset, the
modes the run refuses, and what came of each mode request once the tick that applied it has run."""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass

from humanoid_prime.control.controller import Controller
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode


@dataclass(frozen=True)
class ModeOutcome:
    """What became of a mode request, once the tick that applied it has run: the mode asked for, the mode
    active at the end of that tick, and why they differ (empty when they do not)."""

    requested: Mode
    active: Mode | None
    reason: str = ""


class LoopRequests:
    """Thread-safe on the asking side (``ask``, ``hand_back``, ``ask_reset``, ``refuse``, ``wait``); ``take`` and
    ``tell`` are the loop's, once per tick. The latest request wins; each is numbered by a ticket."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._told = threading.Condition(self._lock)
        self._controller: Controller | None = None
        self._reset = False
        self._refused: dict[Mode, str] = {}  # modes this run may not enter, and why
        self._tickets = 0  # requests made; the latest one is the one applied
        self._applying: tuple[int, Controller] | None = None  # the request taken in this tick, until it is told
        self._outcome: tuple[int, ModeOutcome] | None = None  # the latest applied request and what came of it

    @property
    def waiting(self) -> bool:
        """A request or a reset waits for the next tick (read without the lock: the loop's quick look)."""
        return self._controller is not None or self._reset

    def refuse(self, modes: Sequence[Mode], reason: str) -> None:
        """From now on, a request for any of ``modes`` is refused with ``reason``."""
        with self._lock:
            self._refused.update({mode: reason for mode in modes})

    def ask(self, controller: Controller) -> int:
        """``controller`` to be made active at the next tick; its ticket. A mode the run refuses raises
        PrimeError with the reason, and changes nothing."""
        with self._lock:
            refused = self._refused.get(controller.mode) if controller.mode is not None else None
            if refused is None:
                self._controller = controller
                self._tickets += 1
                return self._tickets
        assert controller.mode is not None  # only a mode is refused
        raise PrimeError(f"{controller.mode.value} refused: {refused}")

    def hand_back(self, controller: Controller, to: Controller, active: Controller | None) -> None:
        """``to`` instead of ``controller``, if ``controller`` is ``active`` or is the request waiting."""
        with self._lock:
            if active is controller or self._controller is controller:
                self._controller = to
                self._tickets += 1

    def ask_reset(self) -> None:
        with self._lock:
            self._reset = True

    def take(self) -> tuple[Controller | None, bool]:
        """The loop's: the controller asked for (None: none) and whether a reset was asked, both cleared."""
        with self._lock:
            controller, self._controller = self._controller, None
            reset, self._reset = self._reset, False
            if controller is not None:
                self._applying = (self._tickets, controller)
        return controller, reset

    @property
    def taken(self) -> bool:
        """A request was taken in this tick and is not told yet."""
        return self._applying is not None

    def tell(self, active: Mode | None, fallback: str) -> None:
        """The loop's, once the request taken in this tick has had its first update: ``active`` is the mode active
        now, ``fallback`` why the last fallback happened (used when ``active`` is not the mode asked for)."""
        if self._applying is None:
            return
        ticket, controller = self._applying
        self._applying = None
        requested = controller.mode
        if requested is None:
            return  # a task's claim or hand-back: no mode outcome to tell
        reason = ""
        if active is not requested:
            reason = f"fell back to {active.value if active is not None else 'a limp command'}: {fallback}"
        with self._told:
            self._outcome = (ticket, ModeOutcome(requested, active, reason))
            self._told.notify_all()

    def wait(self, ticket: int, timeout: float) -> ModeOutcome | None:
        """What came of request ``ticket`` once the tick that applied it (or a later one, which superseded it) has
        run; None if no tick applied it within ``timeout`` seconds."""
        with self._told:
            if not self._told.wait_for(lambda: self._outcome is not None and self._outcome[0] >= ticket, timeout):
                return None
            assert self._outcome is not None  # the wait above ended on it
            applied, outcome = self._outcome
        if applied != ticket:
            return ModeOutcome(outcome.requested, outcome.active, f"superseded by a later request for "
                                                                  f"{outcome.requested.value}")
        return outcome
