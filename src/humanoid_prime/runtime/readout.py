"""What a display shows of a running controller manager besides its topics: how long it has run, the loop rate it
holds against the rate asked for, each joint's measured effort, and each eRob drive's own state (its statusword and
its slave's AL state).

A display (the live table, the page, the control socket's ``state``) reads this when it draws, from its own thread,
out of what the loop and the bus supervision leave behind: nothing here runs in the control tick or costs it.
A joint with no drive of its own to ask (a Sito wrist, a simulated joint) has no entry in ``drives``; the displays
show "—" there.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from humanoid_prime.control.hardware import DriveStatus
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.topics import Snapshot
from humanoid_prime.drivers.erob.cia402 import drive_state
from humanoid_prime.drivers.ethercat.wire import describe_al_state

RATE_WINDOW_S = 1.0  # the loop rate is measured over about the last second of ticks
NONE = "—"
JsonObject = dict[str, object]  # what the control socket and the page carry (JSON)


@dataclass(frozen=True)
class DriveWords:
    """One drive's state as a display words it."""

    statusword: str  # "0x1637"
    state: str  # the CiA402 state, "operation enabled"
    al_state: str  # "OP", "SAFE-OP + ERROR"

    @classmethod
    def of(cls, drive: DriveStatus | None) -> DriveWords:
        if drive is None:
            return cls(NONE, NONE, NONE)
        return cls(f"0x{drive.statusword:04X}", drive_state(drive.statusword).value, describe_al_state(drive.al_state))


@dataclass(frozen=True)
class Readout:
    elapsed_s: float | None  # since the manager started (None before)
    rate_hz: float | None  # the loop's rate lately, 1 / mean period (None before two ticks)
    update_rate_hz: float  # the rate the loop is asked to hold
    effort: list[float]  # measured, per joint in canonical order (Nm)
    drives: dict[str, DriveStatus]  # by joint, the joints with a drive of their own

    def words(self, joint: str) -> DriveWords:
        return DriveWords.of(self.drives.get(joint))

    def loop_words(self) -> str:
        return loop_words(self.elapsed_s, self.rate_hz, self.update_rate_hz)

    def as_dict(self) -> JsonObject:
        """For the control socket's ``state`` and the page (JSON)."""
        return {"elapsed_s": self.elapsed_s, "rate_hz": self.rate_hz, "update_rate_hz": self.update_rate_hz,
                "effort": [None if v != v else v for v in self.effort],
                "drives": {joint: {"statusword": d.statusword, "error_code": d.error_code, "al_state": d.al_state}
                           for joint, d in self.drives.items()}}


def loop_words(elapsed_s: float | None, rate_hz: float | None, update_rate_hz: float | None) -> str:
    """'elapsed 12.3 s  loop 49.9 Hz of 50 Hz'."""
    elapsed = NONE if elapsed_s is None else f"{elapsed_s:.1f} s"
    rate = NONE if rate_hz is None else f"{rate_hz:.1f} Hz"
    asked = NONE if update_rate_hz is None else f"{update_rate_hz:g} Hz"
    return f"elapsed {elapsed}  loop {rate} of {asked}"


def drive_from_dict(joint: str, entry: dict[str, int]) -> DriveStatus:
    """A drive's status as ``Readout.as_dict`` sent it."""
    return DriveStatus(joint, int(entry["statusword"]), int(entry["error_code"]), int(entry["al_state"]))


class LoopReadout:
    """Reads a manager's ``Readout``, from any thread. The loop rate is the inverse of the mean tick-to-tick period
    over about the last ``window_s`` of ticks, as the loop records them (``LoopStats.periods``, in the loop's own
    time: simulated time in a simulation), the figure the run's summary reports as its mean period."""

    def __init__(self, manager: ControllerManager, *, window_s: float = RATE_WINDOW_S) -> None:
        self.manager = manager
        self.window_s = window_s

    def read(self) -> Readout:
        manager = self.manager
        started = manager.started_at
        drives: dict[str, DriveStatus] = {}
        for component in manager.resources.components:
            for drive in component.drive_states():
                drives[drive.joint] = drive
        return Readout(elapsed_s=None if started is None else manager.clock() - started, rate_hz=self._rate(),
                       update_rate_hz=manager.update_rate, effort=manager.resources.state.data[2].tolist(),
                       drives=drives)

    def _rate(self) -> float | None:
        stats = self.manager.stats
        ticks = stats.ticks
        count = min(ticks, stats.capacity, max(2, round(self.manager.update_rate * self.window_s)))
        periods = stats.periods[np.arange(ticks - count, ticks) % stats.capacity]
        periods = periods[np.isfinite(periods)]
        mean = float(periods.mean()) if periods.size else 0.0
        return 1.0 / mean if mean > 0 else None


def state_source(manager: ControllerManager) -> tuple[Callable[[], JsonObject], Callable[[], None]]:
    """A run's state for a view and the control socket's ``state`` request, and the function that detaches it: the
    latest joints, mode and flags off the topics (``Snapshot``: one copy of 14 positions a tick) with the readout,
    read at each call."""
    snapshot = Snapshot(manager.topics, manager.robot.names, manager.config.joint_states_topic)
    readout = LoopReadout(manager)
    return (lambda: {**snapshot.as_dict(), **readout.read().as_dict()}), snapshot.detach
