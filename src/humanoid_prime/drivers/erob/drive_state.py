"""What Prime does with each eRob drive beside the CiA402 state the drive reports: a state machine in two tables,
read like the CiA402 chart. No bus access; ``EthercatSystem`` holds one ``Drive`` per joint and the compiled tick
(``drivers/ethercat/_tick.pyx``) moves it with every frame through ``FRAME_CHART``.

- ENABLING: stepped toward operation enabled, one controlword a frame (CiA402's shutdown, switch on, enable);
- ENABLED: operation enabled;
- FAULT: in fault, latched: held in disable voltage until the operator's reset;
- RESETTING: the operator's fault reset went out; a drive that leaves its fault now left it by that reset;
- HELD: dropped out (it left operation, or its fault, by itself: its slave lost power or link and came back):
  held disabled, so it cannot snap to the active mode's target, until the operator's reset;
- RESTORING: held, and its impedance settings, which a power loss clears, are being put back: no reset releases
  it until they are.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np
import numpy.typing as npt


class Drive(IntEnum):
    ENABLING = 0
    ENABLED = 1
    FAULT = 2
    RESETTING = 3
    HELD = 4
    RESTORING = 5


class Seen(IntEnum):
    """What a frame's statusword says (CiA402: operation enabled, fault, or any other state)."""

    ENABLED = 0
    FAULT = 1
    OTHER = 2


class Event(IntEnum):
    """What happens to a drive between frames."""

    RESET = 0  # the operator's reset
    RESTORED = 1  # its impedance settings are back (its slave in OP)
    LEFT_OP = 2  # its slave left OP again: the settings may be gone again
    RESTORE_NEEDED = 3  # it was held, and somebody restores settings after a drop (the impedance manager)
    RESETTING_OVER = 4  # its fault reset's grace frames passed with the drive still in fault


# frame by frame: the state after a frame, by the state before it and what the frame says
FRAME_CHART: dict[Drive, dict[Seen, Drive]] = {
    Drive.ENABLING: {Seen.ENABLED: Drive.ENABLED, Seen.FAULT: Drive.FAULT, Seen.OTHER: Drive.ENABLING},
    Drive.ENABLED: {Seen.ENABLED: Drive.ENABLED, Seen.FAULT: Drive.FAULT, Seen.OTHER: Drive.HELD},
    Drive.FAULT: {Seen.ENABLED: Drive.HELD, Seen.FAULT: Drive.FAULT, Seen.OTHER: Drive.HELD},
    Drive.RESETTING: {Seen.ENABLED: Drive.ENABLED, Seen.FAULT: Drive.RESETTING, Seen.OTHER: Drive.ENABLING},
    Drive.HELD: {Seen.ENABLED: Drive.HELD, Seen.FAULT: Drive.HELD, Seen.OTHER: Drive.HELD},
    Drive.RESTORING: {Seen.ENABLED: Drive.RESTORING, Seen.FAULT: Drive.RESTORING, Seen.OTHER: Drive.RESTORING},
}

# between frames: the state after an event (a state an event does not name stays as it is)
EVENT_CHART: dict[Event, dict[Drive, Drive]] = {
    Event.RESET: {Drive.FAULT: Drive.RESETTING, Drive.HELD: Drive.ENABLING},
    Event.RESTORED: {Drive.RESTORING: Drive.HELD},
    Event.LEFT_OP: {Drive.HELD: Drive.RESTORING},
    Event.RESTORE_NEEDED: {Drive.HELD: Drive.RESTORING},
    Event.RESETTING_OVER: {Drive.RESETTING: Drive.FAULT},
}

HELD_STATES = (Drive.HELD, Drive.RESTORING)


def frame_table() -> npt.NDArray[np.uint8]:
    """``FRAME_CHART`` as the compiled tick reads it: ``table[state * 3 + seen]``."""
    return np.array([FRAME_CHART[state][seen] for state in Drive for seen in Seen], dtype=np.uint8)


def after(state: Drive, event: Event) -> Drive:
    """The state of a drive in ``state`` after ``event``."""
    return EVENT_CHART[event].get(state, state)


def apply_event(states: npt.NDArray[np.uint8], event: Event,
                where: npt.NDArray[np.bool_] | None = None) -> npt.NDArray[np.bool_]:
    """``event`` on every drive of ``states`` (uint8, changed in place) where ``where`` is true; the drives it
    changed."""
    before = states.copy()
    for old, new in EVENT_CHART[event].items():
        hit = before == old if where is None else (before == old) & where
        states[hit] = new
    changed: npt.NDArray[np.bool_] = states != before
    return changed
