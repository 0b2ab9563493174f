"""Holding the control period on a busy machine: real-time scheduling, locked memory, CPU affinity, and the
garbage collector kept out of the tick.

``lock_memory`` is called before the buses open and ``enter_realtime`` by the control thread just before its
loop. Each measure is taken where the process is allowed to and reported where it is not; the run goes on
either way:

- ``SCHED_FIFO`` for the control thread (root or ``CAP_SYS_NICE``), with ``SCHED_RESET_ON_FORK`` so the
  threads it starts later (a gate reset, a recorder) run at normal priority instead of inheriting it;
- the threads already running beside it (a CAN notifier, a socket server, DDS) at
  ``SCHED_FIFO`` ``OTHERS_PRIORITY`` where they ran at normal priority, back at ``leave_realtime``. They share the
  loop's interpreter lock, and at normal priority a busy host preempts one while it holds the lock: with
  ``stress-ng --cpu 4`` on two cores the loop then waited 105 ms for it, past the drives' 100 ms watchdog. As
  real-time threads they are preempted only by the loop (which takes the lock within the switch interval) and
  by one another;
- ``mlockall`` of current and future memory as it is touched (root, ``CAP_IPC_LOCK``, or a large enough
  ``ulimit -l``), so a page the tick has used is never paged out; ``MCL_ONFAULT``, because populating every
  mapping at once (400 MB, and 8 MB of stack for each new thread) holds the address space long enough, on a
  busy machine, to stall the frames past the drives' 100 ms watchdog;
- with ``cpu``, the control thread pinned to that CPU, and every other thread of the process with it. They share
  the loop's interpreter lock: on the loop's CPU, below its priority, they run only while the loop sleeps, and
  one that holds the lock when the loop wakes is preempted there by the loop alone, and hands the lock over
  within the switch interval. On another CPU, anything of higher priority there (the emulated robot, which
  runs real time to answer in hardware time) could hold it preempted for milliseconds while the loop waits;
  at 1 kHz on the emulated robot that was most of the overruns;
- the interpreter's thread switch interval cut to a tenth of the period (at most its 5 ms default): a thread
  that returns from C (a frame received with the GIL released) waits at most that long for the interpreter;
- ``gc.freeze()`` of everything built during start-up (without a full collection first: that holds the
  interpreter for tens of ms) and automatic collection off; ``GcBetweenTicks`` then runs the collections the
  allocator asks for, between ticks, never inside one.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import gc
import os
import sys
import threading
from dataclasses import dataclass, field

FIFO_PRIORITY = 80  # above the kernel's threaded IRQs (50), below its watchdogs (99)
OTHERS_PRIORITY = 20  # the process's other threads while the loop runs: below the EtherCAT helpers and the IRQs
_MCL_CURRENT, _MCL_FUTURE, _MCL_ONFAULT = 1, 2, 4


@dataclass
class RealtimeReport:
    """What ``enter_realtime`` could do; ``refused`` has one line per measure the process was not allowed."""

    scheduling: str = "SCHED_OTHER"
    memory_locked: bool = False
    cpu: int | None = None
    switch_interval_s: float = 0.005
    previous_switch_interval_s: float = 0.005
    gc_frozen: int = 0
    refused: list[str] = field(default_factory=list)
    threads_raised: list[int] = field(default_factory=list)  # native ids of the other threads made real-time

    @property
    def fifo(self) -> bool:
        """The thread runs at real-time priority."""
        return self.scheduling != "SCHED_OTHER"

    def line(self) -> str:
        parts = [self.scheduling, "memory locked" if self.memory_locked else "memory not locked",
                 f"CPU {self.cpu}" if self.cpu is not None else "any CPU",
                 f"GC frozen ({self.gc_frozen} objects) and run between ticks"]
        text = "real time: " + ", ".join(parts)
        return text + ("; NOT real time: " + "; ".join(self.refused) if self.refused else "")

    def as_dict(self) -> dict[str, object]:
        return {"scheduling": self.scheduling, "memory_locked": self.memory_locked, "cpu": self.cpu,
                "switch_interval_s": self.switch_interval_s, "gc_frozen": self.gc_frozen, "refused": self.refused,
                "threads_raised": len(self.threads_raised)}


def check_cpu(cpu: int) -> None:
    """Raise ValueError unless this process may run on ``cpu`` (for argument checking before anything opens)."""
    allowed = sorted(os.sched_getaffinity(0))
    if cpu not in allowed:
        raise ValueError(f"CPU {cpu} is not one this process may run on (allowed: "
                         f"{', '.join(map(str, allowed))})")


def lock_memory() -> str | None:
    """Lock the process's current and future memory; None when done, else the refusal, in one line."""
    libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE | _MCL_ONFAULT) == 0:
        return None
    why = os.strerror(ctypes.get_errno())
    return f"memory not locked ({why}: run as root, grant CAP_IPC_LOCK or raise ulimit -l)"


def enter_realtime(period_s: float, *, cpu: int | None = None, priority: int = FIFO_PRIORITY,
                   memory_refused: str | None = "memory not locked (lock_memory was not called)") -> RealtimeReport:
    """Make the calling thread the real-time control thread (module docstring); ``memory_refused`` is what
    ``lock_memory`` returned."""
    report = RealtimeReport()
    if cpu is not None:
        check_cpu(cpu)
        _pin(cpu)
        report.cpu = cpu
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(priority))
        report.scheduling = f"SCHED_FIFO {priority}"
        report.threads_raised = _raise_others(min(OTHERS_PRIORITY, priority))
    except PermissionError:
        report.refused.append("real-time scheduling refused (run as root or grant CAP_SYS_NICE)")
    except OSError as exc:
        report.refused.append(f"real-time scheduling unavailable ({exc.strerror})")
    if memory_refused is None:
        report.memory_locked = True
    else:
        report.refused.append(memory_refused)
    report.previous_switch_interval_s = tighten_switch_interval(period_s)
    report.switch_interval_s = sys.getswitchinterval()
    gc.freeze()
    report.gc_frozen = gc.get_freeze_count()
    gc.disable()
    return report


def tighten_switch_interval(period_s: float) -> float:
    """Cut the interpreter's thread switch interval to a tenth of ``period_s`` (never raise it); returns the
    interval it replaced.

    A session does this before its buses open, not only when the loop starts: between bring-up and the loop the
    EtherCAT keeper thread sends the frames while the main thread builds controllers, and at the default 5 ms a
    busy main thread kept the keeper waiting five 1 kHz periods at a time. The drives fault after five late
    frames in a row.
    """
    previous = sys.getswitchinterval()
    sys.setswitchinterval(min(previous, period_s / 10))
    return previous


def leave_realtime(report: RealtimeReport) -> None:
    """Back to normal scheduling and automatic collection (the teardown after the loop allocates freely)."""
    with contextlib.suppress(OSError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    for task in report.threads_raised:
        with contextlib.suppress(OSError):  # a thread that has ended meanwhile
            os.sched_setscheduler(task, os.SCHED_OTHER, os.sched_param(0))
    gc.unfreeze()
    gc.enable()
    sys.setswitchinterval(report.previous_switch_interval_s)


class GcBetweenTicks:
    """The collections automatic GC would have run, run by the loop between ticks instead (with automatic
    collection off and the start-up heap frozen, only what the loop allocates since is looked at)."""

    def __init__(self) -> None:
        self.threshold0, self.threshold1, self.threshold2 = gc.get_threshold()
        self.collections = [0, 0, 0]

    def __call__(self) -> None:
        young, middle, old = gc.get_count()
        if young < self.threshold0:
            return
        generation = 0
        if middle >= self.threshold1:
            generation = 2 if old >= self.threshold2 else 1
        gc.collect(generation)
        self.collections[generation] += 1


def _pin(cpu: int) -> None:
    """Every thread of the process on ``cpu`` (threads started later inherit it)."""
    for task in os.listdir("/proc/self/task"):
        with contextlib.suppress(OSError):  # a thread that has just ended
            os.sched_setaffinity(int(task), {cpu})


def _raise_others(priority: int) -> list[int]:
    """Every other thread of the process that runs at normal priority to ``SCHED_FIFO`` ``priority`` (module
    docstring); returns their native ids."""
    raised = []
    me = threading.get_native_id()
    for task in map(int, os.listdir("/proc/self/task")):
        with contextlib.suppress(OSError):  # a thread that has just ended
            if task != me and os.sched_getscheduler(task) & ~os.SCHED_RESET_ON_FORK == os.SCHED_OTHER:
                os.sched_setscheduler(task, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(priority))
                raised.append(task)
    return raised
