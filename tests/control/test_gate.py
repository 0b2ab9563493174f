"""The one gate: nothing but the manager's commit writes the command the hardware components send, and what it
commits has passed the bounds and the body. A refused arm holds its last command and is asked no velocity; the
other arm goes on; a command with no target, or one that widens a distance already under the margin, is never
held; STANDBY's entry path is checked when it is planned; every refusal is counted, named and flagged."""

from __future__ import annotations

import numpy as np
import pytest

from doubles.control import Plant
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.control.controller import pose_array
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.topics import REMOTE_COMMAND, SAFETY_STATUS, MitCommand
from humanoid_prime.modes import Mode

# Both hands brought together in front of the chest (the left hand 1 cm into the right one).
HANDS_TOGETHER = {"left_shoulder_pitch": -1.3, "left_shoulder_roll": -0.6, "left_elbow_pitch": -0.4,
                  "right_shoulder_pitch": -1.3, "right_shoulder_roll": 0.6, "right_elbow_pitch": -0.4}
LEFT_INTO_TORSO = {"left_shoulder_pitch": 0.43, "left_shoulder_roll": 0.33, "left_shoulder_yaw": -1.17,
                   "left_elbow_pitch": -2.01}  # the left hand into the torso from behind


@pytest.fixture
def ready(robot):
    return pose_array(robot, load_controllers(robot.names).standby.poses["ready"])


@pytest.fixture
def remote(robot, ready):
    """REMOTE active on a plant standing at the ready pose; ``send(pose)`` ticks one message at ``pose``."""
    plant = Plant("plant", robot.names)
    plant.position[:] = ready
    manager = ControllerManager(robot, [plant], load_controllers(robot.names), update_rate=100.0)
    manager.start(now=0.0)
    manager.request_mode(Mode.REMOTE)
    manager.tick(0.01)
    clock = [0.01]

    def send(pose, velocity=None):
        clock[0] += 0.01
        n = robot.n
        manager.topics.publish(REMOTE_COMMAND, MitCommand(
            joint_names=robot.names, position=np.asarray(pose, float), stamp=clock[0],
            velocity=np.zeros(n) if velocity is None else np.asarray(velocity, float), effort=np.zeros(n),
            stiffness=np.full(n, 8.0), damping=np.full(n, 0.5)))
        manager.tick(clock[0])

    yield manager, plant, send
    manager.shutdown()


def test_nothing_but_the_managers_commit_writes_the_command(remote):
    manager, _, _ = remote
    command = manager.resources.command
    for row in (command.data, command.position, command.velocity, command.effort, command.stiffness, command.damping):
        with pytest.raises(ValueError, match="read-only"):
            row[0] = 1.0


def test_a_pose_that_brings_the_hands_within_the_margin_holds_both_arms_on_their_last_command(remote, robot, ready):
    manager, plant, send = remote
    step = ready.copy()
    step[robot.index("left_wrist_yaw")] = 0.1  # a pose clear of everything: it goes through
    send(step, velocity=np.full(robot.n, 0.2))
    assert plant.last[0].tolist() == step.tolist()
    send(pose_array(robot, HANDS_TOGETHER), velocity=np.full(robot.n, 0.2))
    assert plant.last[0].tolist() == step.tolist()  # every joint of both arms where the last command had it
    assert plant.last[1].tolist() == [0.0] * robot.n  # held still
    refused = manager.gate.refused
    assert refused.count == 1 and refused.held == ("left arm", "right arm")
    assert refused.last is not None and {refused.last.group1, refused.last.group2} == {"left arm", "right arm"}
    assert refused.last.distance < robot.hardware.collision_margin


def test_the_arm_that_is_not_driven_into_anything_goes_on(remote, robot, ready):
    manager, plant, send = remote
    pose = ready.copy()
    for name, value in LEFT_INTO_TORSO.items():  # the left hand into the torso
        pose[robot.index(name)] = value
    pose[robot.index("right_wrist_yaw")] = 0.3  # the right arm asks something harmless
    send(pose)
    left = [i for i, name in enumerate(robot.names) if name.startswith("left_")]
    right = [i for i, name in enumerate(robot.names) if name.startswith("right_")]
    assert manager.gate.refused.held == ("left arm",)
    assert plant.last[0][left].tolist() == ready[left].tolist()
    assert plant.last[0][right].tolist() == pose[right].tolist()


def test_a_refusal_is_flagged_with_the_two_bodies_and_their_distance_and_cleared_when_commands_pass(remote, robot,
                                                                                                       ready):
    manager, _, send = remote
    seen = []
    manager.topics.subscribe(SAFETY_STATUS, lambda status: seen.append(dict(status.flags)), latched=True)
    send(pose_array(robot, HANDS_TOGETHER))
    flag = seen[-1]["controller_manager/body"]
    last = manager.gate.refused.last
    assert f"{last.body1} and {last.body2} {last.distance:.3f} m apart (margin 0.030 m)" in flag
    assert "the left arm and the right arm hold their last command" in flag
    send(ready)
    assert "controller_manager/body" not in seen[-1]
    assert manager.gate.refused.as_dict()["by_pair"] == {f"{last.body1}/{last.body2}": 1}


def test_a_command_that_widens_a_distance_already_under_the_margin_passes(robot, ready):
    """The robot measured with its hands 1 cm apart (powered up so, or pushed there): a command that moves them
    apart is what gets it out, and is not held."""
    close = ready + 0.68 * (pose_array(robot, HANDS_TOGETHER) - ready)  # the hands 11 mm apart
    plant = Plant("plant", robot.names)
    plant.position[:] = close
    with ControllerManager(robot, [plant], load_controllers(robot.names), update_rate=100.0) as manager:
        manager.start(now=0.0)
        manager.request_mode(Mode.STANDBY)
        for k in range(1, 250):  # the whole entry trajectory (2 s)
            manager.tick(0.01 * k)
            plant.position[:] = plant.last[0]
        assert manager.active_mode is Mode.STANDBY and manager.gate.refused.count == 0
        np.testing.assert_allclose(plant.last[0], ready, atol=0.02)


@pytest.mark.parametrize("mode", [Mode.ZERO_TORQUE, Mode.DAMPING])
def test_a_mode_without_position_targets_is_never_held(robot, mode):
    plant = Plant("plant", robot.names)
    plant.position[:] = pose_array(robot, HANDS_TOGETHER)  # measured in contact
    with ControllerManager(robot, [plant], load_controllers(robot.names), update_rate=100.0) as manager:
        manager.start(now=0.0)
        manager.request_mode(mode)
        for k in range(1, 5):
            plant.position += 0.01  # moving on its own
            manager.tick(0.01 * k)
        assert manager.gate.refused.count == 0 and not manager.fallbacks
        assert (plant.last[3] == 0.0).all()


def test_standbys_path_through_the_other_arm_is_refused_when_planned(robot, ready, tmp_path):
    """A standby pose whose straight path from where the arms are passes the hands through each other: STANDBY is
    refused on entry, naming the bodies, and DAMPING takes over in the same tick."""
    text = (load_controllers(robot.names).path.read_text()
            .replace("      zero: {}", "      zero: {}\n      crossed:\n" + "".join(
                f"        {name}: {value}\n" for name, value in {
                    "left_shoulder_pitch": -1.3, "left_shoulder_roll": 0.6, "left_elbow_pitch": -0.4,
                    "right_shoulder_pitch": -1.3, "right_shoulder_roll": -0.6, "right_elbow_pitch": -0.4}.items()))
            .replace("default_pose: ready\n    poses", "default_pose: crossed\n    poses"))
    path = tmp_path / "prime_controllers.yaml"
    path.write_text(text)
    plant = Plant("plant", robot.names)
    # the arms crossed the other way: to swap them, the hands would pass through each other
    plant.position[:] = pose_array(robot, {"left_shoulder_pitch": -1.3, "left_shoulder_roll": -0.7,
                                           "left_elbow_pitch": -0.4, "right_shoulder_pitch": -1.3,
                                           "right_shoulder_roll": 0.7, "right_elbow_pitch": -0.4})
    with ControllerManager(robot, [plant], load_controllers(robot.names, path), update_rate=100.0) as manager:
        manager.start(now=0.0)
        manager.request_mode(Mode.STANDBY)
        manager.tick(0.01)
        assert manager.active_mode is Mode.DAMPING
        reason = manager.fallbacks[-1]["reason"]
        assert "standby_controller could not activate: its path would bring" in reason
        assert "the gate refused it when it was planned" in reason


def test_a_joint_nobody_measures_takes_the_bodies_it_carries_out_of_the_check(robot):
    """A run on the wrist bus alone does not know where the arms are: their bodies are not checked, rather than
    checked where they are not."""
    plant = Plant("wrists", robot.hardware.sito_joints)
    with ControllerManager(robot, [plant], load_controllers(robot.names), broadcaster_only=True) as manager:
        manager.start(now=0.0)
        manager.tick(0.01)
        body = manager.gate.body
        assert body is not None and not body.live.any()
        assert manager.gate.refused.count == 0


def test_the_passive_command_of_a_broadcaster_only_run_passes_the_gate_with_its_limp_joints(robot):
    plant = Plant("plant", robot.names)
    plant.position[:] = 0.1
    plant.position[robot.index("left_elbow_pitch")] = 0.2  # beyond its upper limit (0)
    with ControllerManager(robot, [plant], load_controllers(robot.names), broadcaster_only=True) as manager:
        manager.start(now=0.0)
        assert manager.command_owner == "passive_controller"
        manager.passive.mark_limp(robot.index("left_elbow_pitch"), True)
        manager.tick(0.01)
        position, *rest = plant.last
        assert position[robot.index("left_elbow_pitch")] == 0.0  # follows the joint, within the limits
        assert np.isnan(np.delete(position, robot.index("left_elbow_pitch"))).all()
        assert not np.any(rest)
        assert not manager.fallbacks
