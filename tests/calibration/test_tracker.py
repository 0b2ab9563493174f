"""The sweep tracker keeps per-joint min/max and coverage of the described range."""

import numpy as np
import pytest

from humanoid_prime.calibration.tracker import SweepTracker
from humanoid_prime.control.topics import JOINT_STATES, JointState, TopicBus


def test_min_max_follow_the_samples(robot):
    tracker = SweepTracker(robot, ["left_elbow_pitch", "left_wrist_roll"])
    for value in (-0.2, -1.5, -0.7, 0.1):
        q = np.zeros(robot.n)
        q[robot.index("left_elbow_pitch")] = value
        tracker.update(q)
    row = tracker.rows()[0]
    assert (row.minimum, row.maximum, row.position) == (-1.5, 0.1, 0.1)
    assert row.sweep == pytest.approx(1.6)


def test_coverage_is_fraction_of_described_range(robot):
    tracker = SweepTracker(robot, ["left_elbow_pitch"])
    q = np.zeros(robot.n)
    tracker.update(q)
    q[robot.index("left_elbow_pitch")] = -2.356
    tracker.update(q)
    assert tracker.rows()[0].coverage == pytest.approx(1.0)


def test_non_finite_samples_are_ignored(robot):
    tracker = SweepTracker(robot, ["left_shoulder_pitch"])
    q = np.zeros(robot.n)
    tracker.update(q)
    q[0] = np.nan
    tracker.update(q)
    row = tracker.rows()[0]
    assert (row.minimum, row.maximum, row.position) == (0.0, 0.0, 0.0)


def test_unseen_joint_has_no_sweep(robot):
    tracker = SweepTracker(robot, ["right_wrist_yaw"])
    assert tracker.sweeps() == {}
    assert tracker.rows()[0].sweep == 0.0


def test_tracker_listens_to_joint_states(robot):
    topics = TopicBus()
    tracker = SweepTracker(robot, ["right_wrist_pitch"])
    tracker.attach(topics)
    q = np.zeros(robot.n)
    q[robot.index("right_wrist_pitch")] = 0.5
    topics.publish(JOINT_STATES, JointState(0.0, robot.names, q, np.zeros(robot.n), np.zeros(robot.n)))
    assert tracker.sweeps() == {"right_wrist_pitch": (0.5, 0.5)}


def _sweep(tracker, robot, joint, values):
    for value in values:
        q = np.zeros(robot.n)
        q[robot.index(joint)] = value
        tracker.update(q)


def test_order_says_which_extreme_came_first(robot):
    tracker = SweepTracker(robot, ["left_wrist_roll", "right_wrist_roll"])
    _sweep(tracker, robot, "left_wrist_roll", [0.0, -0.3, -0.7, -0.2, 0.4, 0.7, 0.1])
    assert tracker.order()["left_wrist_roll"] == "min"
    tracker = SweepTracker(robot, ["left_wrist_roll"])
    _sweep(tracker, robot, "left_wrist_roll", [0.0, 0.7, 0.0, -0.7, 0.0])
    assert tracker.order()["left_wrist_roll"] == "max"


def test_order_is_unknown_for_a_joint_that_starts_at_a_stop(robot):
    tracker = SweepTracker(robot, ["left_elbow_pitch"])
    _sweep(tracker, robot, "left_elbow_pitch", [0.0, -1.0, -2.356, -1.0, 0.0])  # hanging on its upper stop
    assert tracker.order()["left_elbow_pitch"] is None


def test_a_reading_that_rises_first_is_flagged_as_a_flip(robot):
    from humanoid_prime.calibration.math import Status, calibrate_from_sweeps
    from humanoid_prime.config.calibration import identity_calibration

    sweeps = {"left_wrist_roll": (-0.698, 0.698)}
    _, reports = calibrate_from_sweeps(sweeps, identity_calibration(robot.hardware), robot,
                                       max_first={"left_wrist_roll"})
    report = next(r for r in reports if r.joint == "left_wrist_roll")
    assert report.status is Status.PROBABLE_FLIP and "lower stop first" in report.message


def test_a_sweep_short_of_stop_to_stop_is_called_out(robot):
    from humanoid_prime.calibration.math import Status, calibrate_from_sweeps
    from humanoid_prime.config.calibration import identity_calibration

    _, reports = calibrate_from_sweeps({"left_wrist_pitch": (-0.6, 0.5)}, identity_calibration(robot.hardware), robot)
    report = next(r for r in reports if r.joint == "left_wrist_pitch")
    assert report.status is Status.CALIBRATED
    assert "70% of the described range: short of stop to stop" in report.message
