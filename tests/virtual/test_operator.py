"""The scripted operator's two hands: the left arm with one, every other joint with the other, at once."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import pytest

from humanoid_prime.virtual.operator import ScriptedOperator

JOINTS = ("left_shoulder_pitch", "right_shoulder_pitch", "left_elbow_pitch", "right_elbow_pitch", "right_wrist_yaw")


def operator(robot) -> ScriptedOperator:
    return ScriptedOperator(SimpleNamespace(robot=robot, manager=None), control=None)


def test_each_hand_works_through_its_joints_in_order_while_the_other_works_through_its_own(robot):
    hands = operator(robot)
    both_busy = threading.Barrier(2, timeout=10.0)  # each hand's first joint waits for the other hand's first
    done: dict[str, list[str]] = {"left": [], "other": []}

    def work(joint: str) -> None:
        side = "left" if joint.startswith("left_") else "other"
        if not done[side]:
            both_busy.wait()  # a BrokenBarrierError here: one hand waited for the other in vain
        done[side].append(joint)

    hands.by_hand(JOINTS, work)
    assert done == {"left": ["left_shoulder_pitch", "left_elbow_pitch"],
                    "other": ["right_shoulder_pitch", "right_elbow_pitch", "right_wrist_yaw"]}


def test_a_hand_that_fails_makes_the_other_let_go_and_its_error_is_raised(robot):
    hands = operator(robot)
    started: list[str] = []
    other_busy = threading.Event()
    told_to_let_go: list[bool] = []

    def work(joint: str) -> None:
        started.append(joint)
        if joint == "left_shoulder_pitch":
            assert other_busy.wait(10.0)
            raise RuntimeError("the hand slipped")
        other_busy.set()
        told_to_let_go.append(hands.stop.wait(10.0))

    with pytest.raises(RuntimeError, match="the hand slipped"):
        hands.by_hand(JOINTS, work)
    assert told_to_let_go == [True]
    assert sorted(started) == ["left_shoulder_pitch", "right_shoulder_pitch"]  # neither took another joint
