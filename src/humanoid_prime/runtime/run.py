"""The run policy of a session: the control-rate loop until the duration, the end of a mode sequence or a
stop; and on the way out the eRob gate reset while the loop still ticks."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence

from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.realtime import GcBetweenTicks, enter_realtime, leave_realtime
from humanoid_prime.runtime.session import Session


class ModeSequence:
    """Visits ``modes`` in order, one every ``dwell`` seconds, from the control loop's tick callback."""

    def __init__(self, modes: Sequence[Mode], dwell: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.modes = list(modes)
        self.dwell = dwell
        self.clock = clock
        self._next = clock()

    def __call__(self, manager: ControllerManager) -> None:
        if self.modes and self.clock() >= self._next:
            manager.request_mode(self.modes.pop(0))
            self._next = self.clock() + self.dwell

    @property
    def done(self) -> bool:
        return not self.modes


def run_loop(session: Session, stop: threading.Event,
             on_tick: Callable[[ControllerManager], None] | None = None,
             report: Callable[[str], None] | None = None, at_end: Callable[[], None] | None = None) -> None:
    """The control-rate loop until ``stop``, the duration, or the end of the mode sequence plus one dwell.
    With ``options.realtime`` this thread becomes the real-time control thread for the loop and the gate reset
    after it (``runtime/realtime.py``; ``report`` is told what it could and could not take). When the loop
    ends, before anything is torn down (the drives still hold the mode's last command), the session keeps
    the last measured joint angles and ``at_end`` runs."""
    options = session.options
    if options.mode is not None:
        session.manager.request_mode(options.mode)
    sequence = ModeSequence(options.sequence, options.dwell) if options.sequence else None
    deadline = None if options.duration is None else time.monotonic() + options.duration
    settle_until: list[float] = []

    def tick(manager: ControllerManager) -> None:
        if sequence is not None:
            sequence(manager)
            if sequence.done and not settle_until:
                settle_until.append(time.monotonic() + options.dwell)
        if on_tick is not None:
            on_tick(manager)
        now = time.monotonic()
        if (deadline is not None and now >= deadline) or (settle_until and now >= settle_until[0]
                                                          and options.duration is None):
            stop.set()

    realtime = None
    between_ticks = None
    if options.realtime:
        realtime = enter_realtime(session.manager.period, cpu=options.cpu, memory_refused=session.plan.memory_refused)
        between_ticks = GcBetweenTicks()
        realtime_report: dict[str, object] = realtime.as_dict()
        session.reports["realtime"] = realtime_report
        if report is not None:
            report(realtime.line())
    try:
        session.manager.run(stop=stop, on_tick=tick, between_ticks=between_ticks)
        session.keep_final_position()
        if at_end is not None:
            at_end()
        if session.impedance is not None:
            session.impedance.wait_idle(5.0)
            close_impedance_while_ticking(session, between_ticks)
    finally:
        if realtime is not None:
            leave_realtime(realtime)
        if between_ticks is not None:  # with realtime
            realtime_report["gc_between_ticks"] = between_ticks.collections


def close_impedance_while_ticking(session: Session, between_ticks: Callable[[], None] | None = None,
                                  timeout: float = 10.0) -> None:
    """Reset the eRob gain gate with the loop still running, so every drive keeps a live target (the
    active mode's, or the actual position while limp) at the moment its factory gains take over; a
    stopped loop would leave a stale target that the stiff factory gains snap to."""
    impedance = session.impedance
    assert impedance is not None  # called for a run that has one
    done = threading.Event()

    def close() -> None:
        try:
            session.gate_reset_failures.extend(impedance.close())
        finally:
            done.set()

    threading.Thread(target=close, name="erob-gate-reset", daemon=True).start()
    deadline = time.monotonic() + timeout

    def until_done(manager: ControllerManager) -> None:
        if time.monotonic() > deadline:
            done.set()

    session.manager.run(stop=done, on_tick=until_done, between_ticks=between_ticks)
