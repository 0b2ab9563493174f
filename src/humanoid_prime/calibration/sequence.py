"""How the hands-free calibration's sequence (``calibration.auto``) waits for the control loop, and runs the
procedures of two joints (one per arm) side by side.

The sequence waits for ticks through ``Ticks``: the loop's, running in another thread (``LoopTicks``), or in
virtual time a stepper it drives itself (``SteppedTicks``). A joint's procedure is a generator that yields what it
waits for (``Steps``): a ``Segment`` of its motion (yielded, it becomes its run's segment, which the loop runs
tick by tick), or an ``Until`` condition.
``side_by_side`` runs several such procedures at once: each waits for its own, the others go on, and the ticks
are the loop's, so nothing is threaded and virtual time stays deterministic.

What ends a wait: a segment that finished (the procedure goes on), or failed (``JointFailed`` is raised in the
procedure); an abort (``Aborted`` raised in every procedure, which then runs its way out: the waits it yields
while leaving, ``Until(..., abortable=False)``, are still served, as long as ticks come); a loop that stopped
ticking (``Aborted`` in every procedure, whatever it waits for).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass
from typing import Protocol

from humanoid_prime.calibration.approach import Segment
from humanoid_prime.errors import PrimeError

TICK_TIMEOUT_S = 5.0  # wall seconds without a control tick: the loop is gone


class Aborted(PrimeError):
    """The run was stopped: a fault, a lost device, a held joint that moved, a key press or a signal."""


class JointFailed(PrimeError):
    """This joint could not be calibrated (no stop where it can be, a span that is not its range, ...)."""


class Ticks(Protocol):
    def until(self, done: Callable[[], bool]) -> None:
        """Return once ``done()`` holds, checked after each control tick."""


class LoopTicks:
    """The control loop runs in another thread (``run_loop``); ``ticked`` is called at the end of each tick."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._condition = threading.Condition()
        self._count = 0
        self.clock = clock
        self.stopped = threading.Event()  # the loop is ending: nothing waits for its ticks any more

    def ticked(self) -> None:
        with self._condition:
            self._count += 1
            self._condition.notify_all()

    def until(self, done: Callable[[], bool]) -> None:
        with self._condition:
            seen, last = self._count, self.clock()
            while not done():
                if self.stopped.is_set():
                    raise Aborted("the control loop stopped")
                self._condition.wait(0.1)
                if self._count != seen:
                    seen, last = self._count, self.clock()
                elif self.clock() - last > TICK_TIMEOUT_S:
                    raise Aborted(f"no control tick for {TICK_TIMEOUT_S:g} s")


class SteppedTicks:
    """Virtual time: ``step()`` runs one control tick (and the physics of one period); nothing runs between."""

    def __init__(self, step: Callable[[], None]) -> None:
        self.step = step

    def until(self, done: Callable[[], bool]) -> None:
        while not done():
            self.step()


@dataclass
class Until:
    """A procedure waits until ``done()``; ``abortable``: an abort ends the wait (False: a step of leaving that
    must run to its end while ticks come)."""

    done: Callable[[], bool]
    abortable: bool = True


Wait = Segment | Until
Steps = Generator[Wait, None, None]


class _Running:
    def __init__(self, steps: Steps) -> None:
        self.steps = steps
        self.wait: Wait | None = None
        self.since = 0  # the tick count its wait began at: a wait lasts one tick at least


def side_by_side(procedures: Sequence[Steps], ticks: Ticks, tick_count: Callable[[], int],
                 aborted: Callable[[], str | None], abort: Callable[[str], None]) -> None:
    """Run ``procedures`` at once until each has ended (module docstring). ``aborted()``: why the run stops (None:
    it goes on), asked after every tick; ``abort(why)`` stops it. An error other than ``Aborted`` or
    ``JointFailed`` escaping a procedure stops the run (the others leave as from any abort) and is raised once
    all have ended."""
    running = [_Running(steps) for steps in procedures]
    errors: list[BaseException] = []
    lost: list[Aborted] = []  # the loop stopped ticking

    def ready(entry: _Running) -> bool:
        wait = entry.wait
        if lost:
            return True
        if tick_count() <= entry.since:
            return False
        if isinstance(wait, Until):
            return (wait.abortable and aborted() is not None) or wait.done()
        assert wait is not None
        return aborted() is not None or wait.finished or wait.failure is not None

    def advance(entry: _Running) -> bool:
        """Resume ``entry`` with what ended its wait; False once it has ended."""
        wait, why = entry.wait, aborted()
        try:
            if lost:
                entry.wait = entry.steps.throw(lost[0])
            elif wait is None:
                entry.wait = next(entry.steps)
            elif why is not None and (not isinstance(wait, Until) or wait.abortable):
                entry.wait = entry.steps.throw(Aborted(why))
            elif isinstance(wait, Segment) and wait.failure is not None:
                entry.wait = entry.steps.throw(JointFailed(wait.failure))
            else:
                entry.wait = entry.steps.send(None)
        except StopIteration:
            return False
        except (Aborted, JointFailed):
            return False
        except BaseException as exc:  # raised below, once every other procedure has left
            errors.append(exc)
            abort(f"{type(exc).__name__}: {exc}")
            return False
        if isinstance(entry.wait, Segment):
            entry.wait.run.segment = entry.wait
        entry.since = tick_count()
        return True

    def any_ready() -> bool:
        return any(ready(entry) for entry in running)

    running = [entry for entry in running if advance(entry)]
    while running:
        if not lost:
            try:
                ticks.until(any_ready)
            except Aborted as exc:
                lost.append(exc)
        running = [entry for entry in running if not ready(entry) or advance(entry)]
    if errors:
        raise errors[0]
