"""Each injection of the soak judged from the run's own fault history (``judge``), and whether a flag of the run
is explained by an injection (``explained``): every ERROR flag that none explains (a drive fault nobody injected,
above all) is reported as unexpected."""

from __future__ import annotations

import fnmatch
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TypedDict

from humanoid_prime.bench.soak_faults import SETTLE_S, Fault
from humanoid_prime.runtime.report import FaultRecord

READ_ONLY_ABORT = "0X06010002"  # CiA 301 abort: attempt to write a read-only object


class InjectionDict(TypedDict):
    """``Injection.as_dict``: one injection in the soak's figures."""

    fault: str
    bus: str
    expected: str
    at_s: float
    outcome: str
    as_designed: bool
    detail: str
    flags: list[str]


@dataclass
class Injection:
    fault: Fault
    at_s: float  # since the run began
    done_s: float = 0.0  # when the fault ended (its ``end`` ran)
    outcome: str = ""
    detail: str = ""
    flags: list[str] = field(default_factory=list)
    released_wrong: str | None = None  # what ``Fault.verify`` found wrong after the reset

    @property
    def ended_s(self) -> float:
        return self.done_s or self.at_s

    def as_dict(self) -> InjectionDict:
        return {"fault": self.fault.name, "bus": self.fault.bus, "expected": self.fault.expect,
                "at_s": round(self.at_s, 3),
                "outcome": self.outcome, "as_designed": self.outcome == self.fault.expect, "detail": self.detail,
                "flags": self.flags}


def judge(injection: Injection, faults: Sequence[FaultRecord], ended_s: float, next_at_s: float = float("inf"),
          resets: Sequence[float] = ()) -> None:
    """``injection.outcome`` from the run's fault history (module docstring) and the times the operator's
    resets were sent; a fault that must raise no flag is judged until the next injection at the latest.

    A latched flag must clear only after a reset sent since the injection: its own, or a later fault's when
    the ring took longer than the settle time to be whole again (the soak resets only a whole ring, so a drive
    whose slave relocks slowly under load waits, disabled, for the next reset)."""
    fault = injection.fault
    window_end = injection.ended_s + fault.settle_s
    if fault.flag is None:
        window_end = min(window_end, next_at_s)
        raised = [r for r in faults if injection.at_s <= r.since_s <= window_end and r.level.name == "ERROR"]
        injection.flags = [r.key for r in raised]
        if fault.expect == "refused":
            # the drive's abort, or the master's refusal while ring 0 recovers: either way nothing was written
            refused = READ_ONLY_ABORT in injection.detail.upper() or "refused:" in injection.detail
            injection.outcome = "refused" if refused and not raised else "not refused"
        else:
            injection.outcome = "counted" if not raised else "flagged"
        return
    raised = [r for r in faults if fnmatch.fnmatch(r.key, fault.flag) and injection.at_s <= r.since_s <= window_end]
    injection.flags = [r.key for r in raised]
    if not raised:
        injection.outcome = "not flagged"
    elif any(r.until_s is None for r in raised) and window_end < ended_s:
        injection.outcome = "held"  # still flagged long after it ended
    elif fault.expect == "latched":
        by_reset = all(r.until_s is None or any(injection.at_s <= t <= r.until_s for t in resets) for r in raised)
        injection.outcome = ("recovered without a reset" if not by_reset
                             else "released on settings nobody chose" if injection.released_wrong else "latched")
    else:
        injection.outcome = "recovered"


def explained(record: FaultRecord, injections: Sequence[Injection], faults: Sequence[FaultRecord]) -> bool:
    """A flag is explained by an injection whose flag (or a consequence of it) it matches, in its window: from
    the injection until ``SETTLE_S`` after the fault ended, or after its own flag cleared if that was later (a
    mode switch while a returned slave is still recovering is refused, as it must be)."""
    for injection in injections:
        ended = injection.ended_s
        settle = injection.fault.settle_s
        own = [r for r in faults if injection.fault.flag and fnmatch.fnmatch(r.key, injection.fault.flag)
               and injection.at_s <= r.since_s <= ended + settle]
        cleared = max((float("inf") if r.until_s is None else r.until_s for r in own), default=ended + settle)
        window_end = max(ended + settle, cleared + SETTLE_S)
        if injection.at_s <= record.since_s <= window_end and any(fnmatch.fnmatch(record.key, p)
                                                                   for p in injection.fault.patterns):
            return True
    return False
