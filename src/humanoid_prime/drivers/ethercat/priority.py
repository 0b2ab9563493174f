"""Real-time priorities of the threads that feed the drives' output watchdogs and of the ring's helper threads."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

# SCHED_FIFO of the threads that feed the drives' output watchdogs before and beside the control loop (the bring-up
# loop, the drives' enabling, the keeper), where permitted: below the virtual Prime's 70 and the control loop's 80.
# At normal priority a busy host kept them off the CPU past the drives' 100 ms watchdog.
FEEDING_PRIORITY = 60
# SCHED_FIFO of the ring's helper threads (supervision, SDO workers): below the kernel's threaded interrupts (50).
# Preempted by a host's other work while holding Python's interpreter lock, a helper kept the control loop and the
# keeper waiting for that lock past the drives' watchdog; as real-time threads they block, never spin.
HELPER_PRIORITY = 40


def raise_thread(priority: int) -> tuple[int, os.sched_param] | None:
    """The calling thread at ``priority`` (SCHED_FIFO) where permitted and it runs lower; its scheduling before
    (None: left as it was)."""
    try:
        previous = os.sched_getscheduler(0), os.sched_getparam(0)
        if previous[0] in (os.SCHED_FIFO, os.SCHED_RR) and previous[1].sched_priority >= priority:
            return None
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return previous
    except (OSError, AttributeError):
        return None


@contextlib.contextmanager
def feeding_priority(priority: int = FEEDING_PRIORITY) -> Iterator[None]:
    """The calling thread at ``priority`` (``raise_thread``) while it feeds the drives, its scheduling back after."""
    previous = raise_thread(priority)
    try:
        yield
    finally:
        if previous is not None:
            with contextlib.suppress(OSError):
                os.sched_setscheduler(0, *previous)
