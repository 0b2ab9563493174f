"""The mode controllers, unchanged, on the simulated Prime: gravity, stiffness and hard stops."""

import mujoco
import numpy as np
import pytest

from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.control.controller import pose_array
from humanoid_prime.modes import Mode
from humanoid_prime.sim.demo import Simulation, Step, build_simulation


@pytest.fixture(scope="module")
def config(sim_robot):
    return load_controllers(sim_robot.names)


def gravity_torque(system) -> np.ndarray:
    """Gravity torque per joint at the current pose (MuJoCo's bias force with the joints at rest)."""
    data = mujoco.MjData(system.model)
    data.qpos[:] = system.data.qpos
    mujoco.mj_forward(system.model, data)
    return data.qfrc_bias[system.dof_adr].copy()


def test_standby_holds_the_pose_against_gravity_with_the_error_its_stiffness_predicts(sim_robot, config):
    system, manager = build_simulation(sim_robot, config)
    target = pose_array(sim_robot, config.standby.poses[config.standby.default_pose])
    kp = config.standby.kp
    assert (kp, config.standby.kd) == (20.0, 2.0)
    with manager:
        manager.start()
        # The 2 s entry trajectory, then time to settle.
        Simulation(system, manager, schedule=(Step(0.0, Mode.STANDBY),), realtime=False).run(6.0)
        state = manager.resources.state
        assert manager.active_mode is Mode.STANDBY
        assert np.abs(state.velocity).max() < 1e-2
        sag_predicted = gravity_torque(system) / kp
        error = target - state.position
    shoulder = sim_robot.index("left_shoulder_pitch")
    assert abs(sag_predicted[shoulder]) > 0.1  # the arm's weight visibly pulls the shoulder off target
    # Static balance kp*(q_target - q) = tau_g, up to the joint's Coulomb friction.
    tolerance = system.model.dof_frictionloss[system.dof_adr] / kp + 1e-3
    np.testing.assert_array_less(np.abs(error - sag_predicted), tolerance)


def test_zero_torque_lets_gravity_drive_the_raised_forearm_onto_its_elbow_stop(sim_robot, config):
    elbows = [sim_robot.index("left_elbow_pitch"), sim_robot.index("right_elbow_pitch")]
    stop = sim_robot.upper[elbows]
    assert stop.tolist() == [0.0, 0.0]
    system, manager = build_simulation(sim_robot, config,
                                       initial_pose={"left_elbow_pitch": -1.2, "right_elbow_pitch": -1.2})
    highest = np.full(2, -np.inf)
    with manager:
        manager.start()
        assert manager.active_mode is Mode.ZERO_TORQUE

        def track() -> None:
            np.maximum(highest, manager.resources.state.position[elbows], out=highest)

        Simulation(system, manager, realtime=False).run(2.0, on_tick=track)
        final = manager.resources.state.position[elbows]
        assert not manager.resources.command.data[1:].any()  # limp: no velocity, effort, stiffness, damping
    np.testing.assert_allclose(final, stop, atol=3e-3)
    np.testing.assert_array_less(highest, stop + 3e-3)  # a hard stop: the forearm does not swing past it


def test_damping_brings_a_falling_arm_to_rest(sim_robot, config):
    system, manager = build_simulation(sim_robot, config, initial_pose={"left_shoulder_pitch": -1.0})
    with manager:
        manager.start()
        Simulation(system, manager, schedule=(Step(0.3, Mode.DAMPING),), realtime=False).run(3.0)
        assert manager.active_mode is Mode.DAMPING
        assert np.abs(manager.resources.state.velocity).max() < 0.05
        assert manager.resources.command.damping.tolist() == [config.damping_kd] * sim_robot.n
