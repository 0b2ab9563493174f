"""Prime's own wake-up latency probe: how late a thread of this interpreter, at the control loop's real-time
priority where permitted, wakes from a timed sleep; judged against the periods the robot will run at.

It measures what the control loop itself would see (the kernel, the machine and the interpreter together), for a
second, as ``cyclictest`` does for a C thread (``prime bench --only khz`` runs that one). A wake-up a whole period
late is a tick the loop misses.
"""

from __future__ import annotations

import math
import os
import threading
import time
from dataclasses import dataclass

from humanoid_prime.doctor.report import Check, failed, passed, warned
from humanoid_prime.runtime.realtime import FIFO_PRIORITY

GROUP = "host"
PROBE_S = 1.0
PROBE_INTERVAL_S = 0.001
WARN_FRACTION = 0.25  # a worst wake-up this late, in periods, leaves the tick too little of its period
P99_WARN_FRACTION = 0.1


@dataclass(frozen=True)
class Wakeups:
    """How late each wake-up came (s), in order, at ``interval_s``, under ``scheduling``."""

    lateness_s: tuple[float, ...]
    interval_s: float
    scheduling: str

    def quantile(self, q: float) -> float:
        ordered = sorted(self.lateness_s)
        return ordered[min(len(ordered) - 1, math.ceil(q * len(ordered)) - 1)] if ordered else math.nan

    @property
    def worst_s(self) -> float:
        return max(self.lateness_s, default=math.nan)

    def as_dict(self) -> dict[str, object]:
        return {"wakeups": len(self.lateness_s), "interval_s": self.interval_s, "scheduling": self.scheduling,
                "worst_us": round(self.worst_s * 1e6, 1), "p99_us": round(self.quantile(0.99) * 1e6, 1),
                "median_us": round(self.quantile(0.5) * 1e6, 1)}


def probe(seconds: float = PROBE_S, interval_s: float = PROBE_INTERVAL_S, priority: int = FIFO_PRIORITY) -> Wakeups:
    """Wake every ``interval_s`` for ``seconds`` in a thread of its own at SCHED_FIFO ``priority`` (where permitted)
    and record how late each wake-up was. A wake-up later than the next deadline restarts the schedule from then,
    so one stall counts once."""
    count = max(1, round(seconds / interval_s))
    lateness = [0.0] * count
    scheduling: list[str] = []

    def run() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            scheduling.append(f"SCHED_FIFO {priority}")
        except (OSError, AttributeError):
            scheduling.append("SCHED_OTHER (real-time scheduling refused)")
        deadline = time.monotonic()
        for k in range(count):
            deadline += interval_s
            remaining = deadline - time.monotonic()
            if remaining > 0:
                time.sleep(remaining)
            now = time.monotonic()
            lateness[k] = now - deadline
            if now > deadline + interval_s:
                deadline = now

    thread = threading.Thread(target=run, name="prime-doctor-latency")
    thread.start()
    thread.join()
    return Wakeups(tuple(lateness), interval_s, scheduling[0])


def latency_check(wakeups: Wakeups, periods: list[tuple[float, str]]) -> Check:
    """Judge the wake-ups against each period (s, where it comes from): a worst wake-up a whole period late fails,
    a quarter of one (or a p99 a tenth of one) warns."""
    worst, p99 = wakeups.worst_s, wakeups.quantile(0.99)
    measured = (f"worst wake-up {worst * 1e3:.2f} ms late, p99 {p99 * 1e3:.2f} ms, of {len(wakeups.lateness_s)} at "
                f"{1 / wakeups.interval_s:g} Hz ({wakeups.scheduling})")
    verdicts = []
    for period, source in sorted(periods):
        share = f"{worst / period:.0%} of the {period * 1e3:g} ms period ({source})"
        if worst >= period:
            verdicts.append(("fail", f"{share}: the loop would miss ticks"))
        elif worst >= WARN_FRACTION * period or p99 >= P99_WARN_FRACTION * period:
            verdicts.append(("warn", f"{share}: little of the period is left for the tick"))
        else:
            verdicts.append(("pass", share))
    text = f"{measured}; " + "; ".join(words for _, words in verdicts)
    fix = ("a PREEMPT_RT kernel, a CPU of its own (isolcpus, --cpu N) and the performance governor (the lines "
           "above), or a lower rate")
    kinds = {kind for kind, _ in verdicts}
    if "fail" in kinds:
        return failed(GROUP, "latency", text, fix)
    if "warn" in kinds:
        return warned(GROUP, "latency", text, fix)
    return passed(GROUP, "latency", text)
