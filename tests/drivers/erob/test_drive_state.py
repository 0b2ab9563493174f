"""What Prime does with a drive, read like the CiA402 chart: a row per state, what a frame says or what happens
between frames, and where the drive goes."""

from __future__ import annotations

import numpy as np
import pytest

from humanoid_prime.drivers.erob.drive_state import (
    EVENT_CHART,
    FRAME_CHART,
    Drive,
    Event,
    Seen,
    after,
    apply_event,
    frame_table,
)


def walk(state: Drive, *steps: Seen | Event) -> Drive:
    for step in steps:
        state = FRAME_CHART[state][step] if isinstance(step, Seen) else after(state, step)
    return state


@pytest.mark.parametrize(("steps", "end"), [
    ((Seen.OTHER, Seen.OTHER, Seen.ENABLED), Drive.ENABLED),  # shutdown, switch on, enable: one step a frame
    ((Seen.ENABLED, Seen.OTHER), Drive.HELD),  # enabled, then neither enabled nor in fault: dropped out
    ((Seen.ENABLED, Seen.FAULT), Drive.FAULT),  # a fault latches
    ((Seen.ENABLED, Seen.FAULT, Seen.OTHER), Drive.HELD),  # left its fault by itself: it lost power
    ((Seen.FAULT, Event.RESET, Seen.OTHER, Seen.ENABLED), Drive.ENABLED),  # left it by the operator's reset
    ((Seen.FAULT, Event.RESET, Seen.FAULT, Event.RESETTING_OVER), Drive.FAULT),  # the reset did not clear it
])
def test_a_drive_goes_where_the_chart_says(steps, end):
    assert walk(Drive.ENABLING, *steps) == end


def test_a_held_drive_stays_held_whatever_its_frames_say():
    assert {walk(state, seen) for state in (Drive.HELD, Drive.RESTORING) for seen in Seen} == \
        {Drive.HELD, Drive.RESTORING}
    assert walk(Drive.HELD, Seen.ENABLED, Seen.ENABLED) == Drive.HELD


def test_a_dropped_drive_waiting_for_its_settings_is_released_only_once_they_are_back():
    waiting = walk(Drive.ENABLED, Seen.OTHER, Event.RESTORE_NEEDED)
    assert waiting == Drive.RESTORING
    assert walk(waiting, Event.RESET) == Drive.RESTORING  # the operator's reset does not release it yet
    assert walk(waiting, Event.RESTORED, Event.RESET) == Drive.ENABLING


def test_a_held_drive_whose_slave_left_op_again_waits_for_its_settings_again():
    assert walk(Drive.HELD, Event.LEFT_OP) == Drive.RESTORING
    assert walk(Drive.ENABLED, Event.LEFT_OP) == Drive.ENABLED  # a running drive's slave is the supervision's


def test_events_apply_only_where_asked_and_say_which_drives_they_moved():
    states = np.array([Drive.FAULT, Drive.HELD, Drive.RESTORING, Drive.HELD], dtype=np.uint8)
    moved = apply_event(states, Event.RESET, where=np.array([True, True, True, False]))
    assert list(states) == [Drive.RESETTING, Drive.ENABLING, Drive.RESTORING, Drive.HELD]
    assert list(moved) == [True, True, False, False]


def test_the_compiled_tick_reads_the_frame_chart_by_state_then_what_the_frame_says():
    table = frame_table()
    assert len(table) == len(Drive) * len(Seen)
    assert all(table[state * len(Seen) + seen] == FRAME_CHART[state][seen] for state in Drive for seen in Seen)
    assert all(set(row) <= set(Drive) for row in EVENT_CHART.values())
