"""Fixed-rate pacing: the one loop helper of the project, with an injectable clock and one overrun policy.

The controller manager, the EtherCAT bring-up, enable, keeper and supervision loops, the Sito emulator, the
simulation and the benchmarks all pace themselves with ``Rate``:

    rate = Rate(50.0)
    while running:
        rate.wait()     # the first call starts the schedule and returns at once
        work()

Deadlines fall every ``period`` from the first ``wait()``. ``wait()`` sleeps until the next deadline and
busy-waits its last ``spin_s`` (``sleep()`` wakes up to ~0.1 ms late on Linux). Overrun policy: an iteration
that ends after the next deadline is an overrun; it is counted, ``wait()`` returns at once, and the schedule
restarts from now, so a late loop never bursts to catch up.

``sleep`` may return early with a true value (``threading.Event.wait`` when the event is set): ``wait()``
then returns at once too, so a loop wakes for a stop request or an alarm without waiting out the period.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

from humanoid_prime.errors import PrimeError


class Rate:
    def __init__(self, rate: float, *, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], object] = time.sleep, spin_s: float = 0.0) -> None:
        if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not math.isfinite(rate) or rate <= 0:
            raise PrimeError(f"a loop rate must be a positive number of Hz, got {rate!r}")
        self.rate = float(rate)
        self.period = 1.0 / self.rate
        self.clock = clock
        self.sleep = sleep
        self.spin_s = spin_s
        self.overruns = 0
        self._deadline: float | None = None

    @property
    def deadline(self) -> float | None:
        """The deadline the last ``wait()`` returned at (None before the first)."""
        return self._deadline

    def wait(self) -> bool:
        """Block until the next deadline; False (at once, counted) when the iteration that just ended overran."""
        now = self.clock()
        if self._deadline is None:
            self._deadline = now
            return True
        self._deadline += self.period
        if now > self._deadline:
            self.overruns += 1
            self._deadline = now
            return False
        remaining = self._deadline - now
        if remaining > self.spin_s and self.sleep(remaining - self.spin_s):
            return True  # woken early (an event)
        while self.clock() < self._deadline:  # pure spin: even sleep(0) costs a timer-slack wake-up (~50 us)
            pass
        return True
