"""The mode controllers, as the manager runs them on a plant owning all 14 joints."""

from dataclasses import replace

import numpy as np
import pytest

from doubles.control import Plant, constant_policy, with_policy
from humanoid_prime.control.controllers.standby import min_jerk
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.policy import Policy
from humanoid_prime.control.topics import REMOTE_COMMAND, SAFETY_STATUS, MitCommand
from humanoid_prime.errors import PrimeError
from humanoid_prime.files import bundled
from humanoid_prime.modes import Mode

READY = {"left_shoulder_pitch": -0.3, "left_shoulder_roll": 0.2, "left_elbow_pitch": -0.6,
         "right_shoulder_pitch": -0.3, "right_shoulder_roll": -0.2, "right_elbow_pitch": -0.6}


def pose(robot, values):
    out = np.zeros(robot.n)
    for name, angle in values.items():
        out[robot.index(name)] = angle
    return out


def enter(manager, mode, t=0.0):
    manager.request_mode(mode)
    manager.tick(t)


def message(robot, names=None, **rows):
    n = robot.n
    values = {k: np.zeros(n) for k in ("position", "velocity", "effort", "stiffness", "damping")}
    values.update({k: np.asarray(v, float) for k, v in rows.items()})
    return MitCommand(joint_names=robot.names if names is None else names, **values)


@pytest.fixture
def erob(robot):
    return robot.indices("erob")


@pytest.fixture
def sito(robot):
    return robot.indices("sito")


# ---- per-mode eRob gains on the uniform surface ---------------------------------------------------

@pytest.mark.parametrize("mode", list(Mode))
def test_every_mode_writes_its_erob_gains_onto_the_erob_joints(manager, plant, config, robot, erob, mode):
    enter(manager, mode)
    if mode is Mode.REMOTE:
        manager.topics.publish(REMOTE_COMMAND, message(robot, stiffness=np.full(14, 99.0),
                                                       damping=np.full(14, 9.0)))
        manager.tick(0.01)
    kp, kd = config.mode_gains()[mode]
    assert plant.last[3][erob].tolist() == [kp] * 10
    assert plant.last[4][erob].tolist() == [kd] * 10


# ---- ZERO_TORQUE ---------------------------------------------------------------------------------

def test_zero_torque_commands_nothing_and_keeps_the_target_on_the_measured_position(manager, plant):
    plant.position[:] = np.linspace(-1.0, 0.0, 14)
    manager.tick(0.0)
    np.testing.assert_array_equal(plant.last[0], plant.position)
    assert plant.last[1:].tolist() == [[0.0] * 14] * 4


def test_zero_torque_keeps_the_last_target_of_a_joint_whose_measurement_is_lost(manager, plant):
    plant.position[:] = np.linspace(-1.0, 0.0, 14)
    manager.tick(0.0)
    before = plant.position.copy()
    plant.position[:] += 0.1
    plant.position[3] = np.nan
    manager.tick(0.02)
    expected = plant.position.copy()
    expected[3] = before[3]
    np.testing.assert_array_equal(plant.last[0], expected)
    assert plant.last[1:].tolist() == [[0.0] * 14] * 4


# ---- DAMPING -------------------------------------------------------------------------------------

def test_damping_holds_the_captured_position_with_zero_stiffness(manager, plant):
    captured = np.linspace(-0.4, 0.0, 14)
    plant.position[:] = captured
    enter(manager, Mode.DAMPING)
    plant.position[:] += 0.2  # the arm is pushed away
    plant.velocity[:] = 0.5
    manager.tick(0.01)
    position, velocity, effort, stiffness, damping = plant.last
    np.testing.assert_array_equal(position, captured)
    assert stiffness.tolist() == [0.0] * 14
    assert damping.tolist() == [6.0] * 14
    assert velocity.tolist() == [0.0] * 14 and effort.tolist() == [0.0] * 14


def test_damping_takes_a_per_joint_kd(robot, config, clock):
    plant = Plant("plant", robot.names)
    with ControllerManager(robot, [plant], config, clock=clock) as manager:
        manager.controllers["damping_controller"].kd = np.arange(14.0) / 2
        manager.start()
        enter(manager, Mode.DAMPING)
        assert plant.last[4].tolist() == list(np.arange(14.0) / 2)


# ---- STANDBY -------------------------------------------------------------------------------------

def test_standby_entered_from_a_moving_arm_starts_at_the_measured_pose(robot, config, clock):
    plant = Plant("plant", robot.names, inertia=0.05)
    plant.position[:] = (robot.lower + robot.upper) / 2
    plant.velocity[:] = 0.8  # swinging when the mode is requested
    with ControllerManager(robot, [plant], config, update_rate=100.0, clock=clock) as manager:
        manager.start()
        for k in range(5):
            manager.tick(k * 0.01)
        measured = plant.position.copy()
        enter(manager, Mode.STANDBY, 0.05)
        assert manager.active_mode is Mode.STANDBY
        np.testing.assert_array_equal(plant.last[0], measured)
        assert plant.last[1].tolist() == [0.0] * 14  # no velocity step either


def test_standby_follows_a_minimum_jerk_path_to_the_default_pose(manager, plant, robot, config):
    start = np.full(14, -0.1)
    plant.position[:] = start
    enter(manager, Mode.STANDBY, 0.0)
    target = pose(robot, READY)
    manager.tick(1.0)  # halfway through the 2 s entry
    np.testing.assert_allclose(plant.last[0], start + 0.5 * (target - start))
    np.testing.assert_allclose(plant.last[1], (target - start) * min_jerk(0.5)[1] / 2.0)
    manager.tick(2.0)
    np.testing.assert_allclose(plant.last[0], target)
    assert plant.last[1].tolist() == [0.0] * 14


def test_standby_holds_with_kp_20_and_kd_2_on_every_joint(manager, plant):
    enter(manager, Mode.STANDBY)
    assert plant.last[3].tolist() == [20.0] * 14
    assert plant.last[4].tolist() == [2.0] * 14


def test_standby_moves_to_a_selected_pose_on_reentry(manager, plant, robot):
    enter(manager, Mode.STANDBY, 0.0)
    manager.tick(2.0)
    manager.controllers["standby_controller"].select_pose("elbows_up")
    plant.position[:] = plant.last[0]
    enter(manager, Mode.STANDBY, 3.0)
    np.testing.assert_allclose(plant.last[0], pose(robot, READY))  # starts where the arm is
    manager.tick(5.0)
    np.testing.assert_allclose(plant.last[0], pose(robot, {
        "left_shoulder_pitch": -0.5, "left_elbow_pitch": -1.5, "right_shoulder_pitch": -0.5,
        "right_elbow_pitch": -1.5}))


def test_an_unknown_standby_pose_names_the_known_ones(manager):
    with pytest.raises(PrimeError, match="unknown standby pose 'wave'; known poses: ready, zero, elbows_up"):
        manager.controllers["standby_controller"].select_pose("wave")


# ---- LOCOMOTION ----------------------------------------------------------------------------------

def test_locomotion_commands_the_bundled_policy_around_the_default_pose(manager, plant, robot):
    plant.position[:] = pose(robot, READY)
    enter(manager, Mode.LOCOMOTION, 0.0)
    manager.tick(1.5)  # past the 1 s entry blend
    # the same model on the observation the controller packed gives the action it scaled
    reference = Policy(bundled("standby_policy.onnx"), robot.names)
    reference.observation[:] = manager.controllers["locomotion_controller"].policy.observation
    expected = pose(robot, READY) + 0.25 * reference.run()
    np.testing.assert_allclose(plant.last[0], expected, atol=1e-6)
    assert 0.01 < np.max(np.abs(plant.last[0] - pose(robot, READY))) < 0.2  # a gentle swing


def test_locomotion_observation_packs_relative_position_velocity_last_action_and_phase(manager, plant, robot):
    plant.position[:] = pose(robot, READY) + 0.01
    plant.velocity[:] = 0.5
    enter(manager, Mode.LOCOMOTION, 0.0)
    manager.tick(0.75)  # a quarter of the bundled policy's 3 s phase period
    controller = manager.controllers["locomotion_controller"]
    obs = controller.policy.observation[0]
    np.testing.assert_allclose(obs[:14], 0.01, rtol=1e-5)
    np.testing.assert_allclose(obs[14:28], 0.5)
    np.testing.assert_allclose(obs[42:], [1.0, 0.0], atol=1e-6)
    assert np.any(obs[28:42] != 0.0)  # the action of the first tick


def test_locomotion_uses_the_policy_gains_on_sito_and_the_mode_gains_on_erob(manager, plant, erob, sito):
    enter(manager, Mode.LOCOMOTION)
    assert plant.last[3][erob].tolist() == [20.0] * 10 and plant.last[4][erob].tolist() == [2.0] * 10
    assert plant.last[3][sito].tolist() == [8.0] * 4 and plant.last[4][sito].tolist() == [0.5] * 4


def test_locomotion_starts_at_the_measured_pose(manager, plant):
    plant.position[:] = -0.05
    enter(manager, Mode.LOCOMOTION, 0.0)
    np.testing.assert_allclose(plant.last[0], -0.05)


def test_locomotion_clips_policy_targets_to_the_joint_limits(robot, config, clock, tmp_path):
    plant = Plant("plant", robot.names)
    policy = constant_policy(tmp_path / "big.onnx", robot, 100.0)
    # every joint at its upper limit folds the arms into each other: the bounds alone are what is shown here
    with ControllerManager(robot, [plant], with_policy(config, policy), clock=clock, check_body=False) as manager:
        manager.start()
        enter(manager, Mode.LOCOMOTION, 0.0)
        manager.tick(1.0)
        assert manager.active_mode is Mode.LOCOMOTION
        np.testing.assert_allclose(plant.last[0], robot.upper)


# ---- REMOTE --------------------------------------------------------------------------------------

def test_remote_applies_the_message_with_fixed_erob_gains_and_the_messages_sito_gains(manager, plant, robot,
                                                                                        erob, sito):
    enter(manager, Mode.REMOTE)
    rows = dict(position=np.linspace(-0.12, 0.0, 14), velocity=np.full(14, 0.1), effort=np.full(14, 0.5),
                stiffness=np.full(14, 12.0), damping=np.full(14, 0.7))
    manager.topics.publish(REMOTE_COMMAND, message(robot, **rows))
    manager.tick(0.01)
    position, velocity, effort, stiffness, damping = plant.last
    np.testing.assert_array_equal(position, rows["position"])
    assert velocity.tolist() == [0.1] * 14 and effort.tolist() == [0.5] * 14
    assert stiffness[sito].tolist() == [12.0] * 4 and damping[sito].tolist() == [0.7] * 4
    assert stiffness[erob].tolist() == [20.0] * 10 and damping[erob].tolist() == [2.0] * 10


def test_remote_rejects_a_message_in_another_joint_order(manager, plant, robot):
    enter(manager, Mode.REMOTE)
    names = list(robot.names)
    names[4], names[6] = names[6], names[4]
    manager.topics.publish(REMOTE_COMMAND, message(robot, names=tuple(names), position=np.full(14, -0.05)))
    manager.tick(0.01)
    remote = manager.controllers["remote_policy_controller"]
    assert (remote.accepted, remote.rejected) == (0, 1)
    assert remote.last_rejection == "joint 4 is 'left_wrist_yaw', expected 'left_wrist_roll' (canonical order)"
    assert "joint 4 is 'left_wrist_yaw'" in manager.topics.latest(SAFETY_STATUS).flags[
        "remote_policy_controller/rejected"]
    assert -0.05 not in plant.last[0]


@pytest.mark.parametrize(("names", "rows", "problem"), [
    ("short", {}, "13 joint names, expected 14 in canonical order"),
    ("full", {"damping": np.zeros(13)}, "damping has shape (13,), expected (14,)"),
    ("full", {"position": np.zeros(15)}, "position has shape (15,), expected (14,)"),
])
def test_remote_rejects_a_message_of_the_wrong_length(manager, robot, names, rows, problem):
    enter(manager, Mode.REMOTE)
    joint_names = robot.names[:13] if names == "short" else robot.names
    manager.topics.publish(REMOTE_COMMAND, message(robot, names=joint_names, **rows))
    remote = manager.controllers["remote_policy_controller"]
    assert remote.rejected == 1 and remote.last_rejection == problem


@pytest.mark.parametrize(("rows", "accepted"), [
    ({"position": [0.0] * 14, "stiffness": [5] * 14}, True),  # lists, integers
    ({"position": np.zeros(14, dtype=np.float32)}, True),
    ({"position": np.zeros(28)[::2]}, True),  # a strided view
    ({"damping": np.ones((14, 1))}, False),
    ({"damping": 1.0}, False),
    ({"effort": ["x"] * 14}, False),
    ({"effort": [[0.0, 1.0]] * 14}, False),
    ({"velocity": None}, False),
])
def test_remote_takes_rows_of_any_kind_that_are_one_number_per_joint(manager, robot, rows, accepted):
    remote = manager.controllers["remote_policy_controller"]
    m = replace(message(robot), **rows)  # as given, not made arrays
    manager.topics.publish(REMOTE_COMMAND, m)
    assert (remote.accepted, remote.rejected) == ((1, 0) if accepted else (0, 1)), remote.last_rejection


def test_remote_falls_back_to_a_damped_hold_after_100_ms_of_silence(manager, plant, robot, erob, sito):
    enter(manager, Mode.REMOTE, 0.0)
    manager.topics.publish(REMOTE_COMMAND, message(robot, position=np.full(14, -0.05), stiffness=np.full(14, 5.0)))
    manager.tick(0.01)  # arrives
    manager.tick(0.11)  # 100 ms later: still fresh
    assert plant.last[0].tolist() == [-0.05] * 14
    plant.position[:] = -0.15
    manager.tick(0.12)  # 110 ms: stale
    position, velocity, effort, stiffness, damping = plant.last
    assert manager.active_mode is Mode.REMOTE
    assert position.tolist() == [-0.15] * 14  # the live position
    assert velocity.tolist() == [0.0] * 14 and effort.tolist() == [0.0] * 14
    assert stiffness[sito].tolist() == [0.0] * 4 and damping[sito].tolist() == [6.0] * 4
    assert stiffness[erob].tolist() == [20.0] * 10 and damping[erob].tolist() == [2.0] * 10
    assert "no command on /remote_policy_controller/command for more than 100 ms" in \
        manager.topics.latest(SAFETY_STATUS).flags["remote_policy_controller/stale"]


def test_remote_resumes_when_commands_return(manager, plant, robot):
    enter(manager, Mode.REMOTE, 0.0)
    manager.tick(0.5)
    manager.topics.publish(REMOTE_COMMAND, message(robot, position=np.full(14, -0.1)))
    manager.tick(0.51)
    assert plant.last[0].tolist() == [-0.1] * 14
    assert manager.topics.latest(SAFETY_STATUS).ok


def test_remote_damps_until_the_first_command_after_entry(manager, plant, robot):
    manager.topics.publish(REMOTE_COMMAND, message(robot, position=np.full(14, -0.3)))  # before the switch
    plant.position[:] = -0.05
    enter(manager, Mode.REMOTE, 0.0)
    assert plant.last[0].tolist() == [-0.05] * 14
    assert manager.controllers["remote_policy_controller"].accepted == 1
    assert manager.topics.latest(SAFETY_STATUS).flags == {
        "remote_policy_controller/stale": "waiting for the first command on /remote_policy_controller/command; "
                                          "damping meanwhile"}


def test_remote_reports_only_rejections_made_while_active(manager, robot):
    manager.topics.publish(REMOTE_COMMAND, message(robot, names=robot.names[:13]))  # before the switch
    enter(manager, Mode.REMOTE, 0.0)
    assert "remote_policy_controller/rejected" not in manager.topics.latest(SAFETY_STATUS).flags


def test_remote_hold_policy_keeps_the_last_command_when_stale(robot, config, clock):
    plant = Plant("plant", robot.names)
    held = with_policy(config, config.locomotion.policy)
    held = replace(held, remote=replace(config.remote, stale_policy="hold"))
    with ControllerManager(robot, [plant], held, clock=clock) as manager:
        manager.start()
        enter(manager, Mode.REMOTE, 0.0)
        manager.topics.publish(REMOTE_COMMAND, message(robot, position=np.full(14, -0.05),
                                                       stiffness=np.full(14, 5.0)))
        manager.tick(0.01)
        plant.position[:] = -0.15
        manager.tick(0.5)
        assert plant.last[0].tolist() == [-0.05] * 14
        assert plant.last[3][robot.indices("sito")].tolist() == [5.0] * 4
