"""FollowJointTrajectory goals as Prime checks and runs them, without ROS: the limits a goal is held to, the
interpolation, and the executor's commands on REMOTE's topic as a tick tap hands it the ticks."""

from __future__ import annotations

import numpy as np
import pytest

from humanoid_prime.control.tap import TickSample
from humanoid_prime.control.topics import ControlMode, JointState, MitCommand, TopicBus
from humanoid_prime.dds.controllers import arm_controllers
from humanoid_prime.dds.trajectory import (
    GOAL_TOLERANCE_VIOLATED,
    INVALID_GOAL,
    INVALID_JOINTS,
    PATH_TOLERANCE_VIOLATED,
    SUCCESSFUL,
    Goal,
    Point,
    Refused,
    Tolerance,
    TrajectoryExecutor,
    plan,
    sample,
)

RATE_HZ = 100.0


@pytest.fixture
def left(sim_robot):
    return arm_controllers(sim_robot.names)["left_arm_controller"]


@pytest.fixture
def executor(sim_robot, config):
    topics = TopicBus()
    sent: list[MitCommand] = []
    topics.subscribe(config.remote.topic, sent.append)
    executor = TrajectoryExecutor(sim_robot, config, topics, period=1.0 / RATE_HZ)
    executor.sent_commands = sent
    executor.on_mode(ControlMode("REMOTE", "remote_policy_controller"))
    return executor


def rest(sim_robot):
    """A pose inside every limit (the middle of each range)."""
    return (sim_robot.lower + sim_robot.upper) / 2


def goal(names, points, **kwargs):
    return Goal(joint_names=tuple(names), points=tuple(points), **kwargs)


def tick(executor, t, q, qd=None):
    data = np.zeros((3, len(q)))
    data[0], data[1] = q, (np.zeros(len(q)) if qd is None else qd)
    executor.on_tick(TickSample(stamp=t, data=data, queued_at=0.0))


def test_a_goal_must_name_the_controllers_joints_each_once(sim_robot, left):
    start = rest(sim_robot)
    arm = [start[sim_robot.index(j)] for j in left]
    with pytest.raises(Refused) as refused:
        plan(sim_robot, goal(left[:6], [Point(1.0, arm[:6])]), left, np.full(14, 3.0))
    assert refused.value.code == INVALID_JOINTS
    with pytest.raises(Refused) as refused:
        plan(sim_robot, goal([*left[:6], left[0]], [Point(1.0, arm)]), left, np.full(14, 3.0))
    assert refused.value.code == INVALID_JOINTS


def test_a_position_beyond_a_limit_is_refused_naming_the_joint_and_point(sim_robot, left):
    arm = [rest(sim_robot)[sim_robot.index(j)] for j in left]
    beyond = list(arm)
    beyond[left.index("left_elbow_pitch")] = 0.3  # its upper limit is 0
    with pytest.raises(Refused) as refused:
        plan(sim_robot, goal(left, [Point(1.0, arm), Point(2.0, beyond)]), left, np.full(14, 3.0))
    assert refused.value.code == INVALID_GOAL
    assert refused.value.reason.startswith("point 1: left_elbow_pitch at 0.3000 rad is outside its limits")


def test_a_segment_faster_than_the_velocity_limit_is_refused(sim_robot, left):
    arm = np.array([rest(sim_robot)[sim_robot.index(j)] for j in left])
    moved = arm.copy()
    moved[0] -= 1.0  # 1 rad in 0.1 s: 10 rad/s
    with pytest.raises(Refused) as refused:
        plan(sim_robot, goal(left, [Point(1.0, arm), Point(1.1, moved)]), left, np.full(14, 3.0))
    assert "too fast" in refused.value.reason and "left_shoulder_pitch" in refused.value.reason
    with pytest.raises(Refused, match="velocity 5.000 rad/s is beyond its limit 3.000"):
        plan(sim_robot, goal(left, [Point(1.0, arm, [5.0] + [0.0] * 6)]), left, np.full(14, 3.0))


def test_times_must_increase(sim_robot, left):
    arm = [rest(sim_robot)[sim_robot.index(j)] for j in left]
    with pytest.raises(Refused, match="increasing"):
        plan(sim_robot, goal(left, [Point(1.0, arm), Point(1.0, arm)]), left, np.full(14, 3.0))


def test_interpolation_is_linear_without_velocities_and_hermite_with_them():
    times = np.array([0.0, 1.0])
    positions = np.array([[0.0], [1.0]])
    q, qd = sample(times, positions, None, 0.25)
    assert q[0] == pytest.approx(0.25) and qd[0] == pytest.approx(1.0)
    q, qd = sample(times, positions, np.array([[0.0], [0.0]]), 0.5)
    assert q[0] == pytest.approx(0.5) and qd[0] == pytest.approx(1.5)  # smoothstep: 1.5x the mean at the middle
    q, qd = sample(times, positions, np.array([[0.0], [0.0]]), 2.0)
    assert q[0] == 1.0 and qd[0] == 0.0


def test_a_goal_runs_from_the_measured_state_through_its_points_and_succeeds(executor, sim_robot, left):
    q = rest(sim_robot)
    joints = [sim_robot.index(j) for j in left]
    target = q[joints] + 0.1
    execution = executor.start(goal(left, [Point(0.5, target)]), left)
    for k in range(60):  # the arm follows the command exactly
        tick(executor, k / RATE_HZ, q)
        q = executor.sent_commands[-1].position.copy()
    assert execution.done.is_set() and execution.code == SUCCESSFUL
    np.testing.assert_allclose(q[joints], target)
    first = executor.sent_commands[0]
    assert first.joint_names == sim_robot.names
    np.testing.assert_allclose(first.position[joints], rest(sim_robot)[joints] + 0.1 * 0.02, atol=1e-9)
    others = [i for i in range(14) if i not in joints]
    np.testing.assert_array_equal(first.position[others], rest(sim_robot)[others])  # held where they were


def test_a_joint_off_its_path_aborts_with_the_joint_named(executor, sim_robot, left):
    q = rest(sim_robot)
    joints = [sim_robot.index(j) for j in left]
    execution = executor.start(goal(left, [Point(1.0, q[joints] + 0.2)],
                                    path_tolerance=(Tolerance("left_elbow_pitch", 0.05),)), left)
    stuck = q.copy()
    for k in range(100):
        tick(executor, k / RATE_HZ, stuck)  # the arm does not move at all
        if execution.done.is_set():
            break
    assert execution.code == PATH_TOLERANCE_VIOLATED
    assert execution.reason.startswith("left_elbow_pitch is 0.05")


def test_a_goal_not_reached_within_the_goal_time_tolerance_fails(executor, sim_robot, left):
    q = rest(sim_robot)
    joints = [sim_robot.index(j) for j in left]
    execution = executor.start(goal(left, [Point(0.2, q[joints] + 0.1)], goal_time_tolerance_s=0.1), left)
    for k in range(50):
        tick(executor, k / RATE_HZ, q)
    assert execution.code == GOAL_TOLERANCE_VIOLATED
    assert "beyond the goal tolerance 0.0500 rad" in execution.reason


def test_cancel_holds_the_measured_position(executor, sim_robot, left):
    q = rest(sim_robot)
    joints = [sim_robot.index(j) for j in left]
    execution = executor.start(goal(left, [Point(2.0, q[joints] + 0.3)]), left)
    for k in range(50):
        tick(executor, k / RATE_HZ, q)
        q = executor.sent_commands[-1].position.copy()
    executor.cancel(execution)
    tick(executor, 0.5, q)
    assert execution.done.is_set() and execution.cancelled
    for k in range(51, 60):
        tick(executor, k / RATE_HZ, q)
    np.testing.assert_array_equal(executor.sent_commands[-1].position, q)
    np.testing.assert_array_equal(executor.sent_commands[-1].velocity, 0.0)


def test_leaving_remote_stops_the_goal_and_the_commands(executor, sim_robot, left):
    q = rest(sim_robot)
    joints = [sim_robot.index(j) for j in left]
    execution = executor.start(goal(left, [Point(2.0, q[joints] + 0.3)]), left)
    tick(executor, 0.0, q)
    executor.on_mode(ControlMode("DAMPING", "damping_controller"))
    assert execution.code == INVALID_GOAL and execution.reason == "stopped: Prime left REMOTE for DAMPING"
    sent = len(executor.sent_commands)
    tick(executor, 0.01, q)
    assert len(executor.sent_commands) == sent
    with pytest.raises(Refused, match="switch to REMOTE first"):
        executor.start(goal(left, [Point(2.0, q[joints])]), left)


def test_a_newer_goal_on_the_same_joints_replaces_the_running_one(executor, sim_robot, left):
    q = rest(sim_robot)
    joints = [sim_robot.index(j) for j in left]
    first = executor.start(goal(left, [Point(2.0, q[joints] + 0.3)]), left)
    second = executor.start(goal(left, [Point(2.0, q[joints] - 0.1)]), left)
    assert first.done.is_set() and first.reason == "replaced by a newer goal on the same joints"
    assert not second.done.is_set()


def test_a_tap_running_behind_the_loop_still_commands_the_next_tick(executor, sim_robot, left, config):
    """The sample handed over is old (the machine was busy) but the loop is already further on: the command is for
    the tick after the newest one, not for a tick long past."""
    q = rest(sim_robot)
    joints = [sim_robot.index(j) for j in left]
    executor.start(goal(left, [Point(1.0, q[joints] + 0.5)]), left)
    tick(executor, 0.0, q)
    executor.topics.publish(config.joint_states_topic, JointState(0.5, sim_robot.names, q, q * 0, q * 0))
    tick(executor, 0.01, q)  # a sample from 0.49 s ago
    command = executor.sent_commands[-1]
    np.testing.assert_allclose(command.position[joints], q[joints] + 0.5 * 0.51)
    assert command.stamp == 0.5
