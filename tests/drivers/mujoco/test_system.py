"""The simulated Prime: a MuJoCo model that agrees with the description, and the MIT law inside it."""

import time
from pathlib import Path

import mujoco
import numpy as np
import pytest

from humanoid_prime.config.model import MODEL_FILE, load_model
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.drivers.mujoco.system import MujocoSystem
from humanoid_prime.errors import ConfigError, PrimeError
from humanoid_prime.files import bundled


@pytest.fixture(scope="module")
def system(sim_robot):
    return MujocoSystem(sim_robot)


def _edited_model(tmp_path: Path, old: str, new: str) -> Path:
    text = bundled(MODEL_FILE).read_text()
    assert old in text
    path = tmp_path / "prime.xml"
    path.write_text(text.replace(old, new, 1))
    return path


def test_model_has_the_14_joints_in_canonical_order(system, sim_robot):
    names = [system.model.joint(int(i)).name for i in range(system.model.njnt)]
    assert names == list(sim_robot.names)
    assert system.joints == sim_robot.names


def test_joint_ranges_are_the_description_limits(system, sim_robot):
    np.testing.assert_array_equal(system.model.jnt_range[:, 0], sim_robot.lower)
    np.testing.assert_array_equal(system.model.jnt_range[:, 1], sim_robot.upper)
    assert system.model.jnt_limited.all()


def test_actuator_force_range_is_the_effort_limit(system, sim_robot):
    np.testing.assert_array_equal(system.model.actuator_forcerange[:, 1], sim_robot.effort_limit)
    np.testing.assert_array_equal(system.model.actuator_forcerange[:, 0], -sim_robot.effort_limit)


def test_joints_have_armature_damping_and_friction(system, sim_robot):
    erob = sim_robot.index("left_shoulder_pitch")
    sito = sim_robot.index("left_wrist_roll")
    assert 0.01 <= system.model.dof_armature[erob] <= 0.1
    assert 0 < system.model.dof_armature[sito] < system.model.dof_armature[erob]
    assert (system.model.dof_damping > 0).all()
    assert (system.model.dof_frictionloss > 0).all()


def test_physics_runs_at_1khz_with_5_substeps_per_200hz_tick(system):
    assert system.model.opt.timestep == 0.001
    assert system.substeps == 5
    assert system.period == pytest.approx(0.005)


def test_one_write_advances_exactly_one_control_period(sim_robot):
    sim = MujocoSystem(sim_robot)
    command = CommandArrays(sim_robot.n)
    for _ in range(40):
        sim.write(0.0, command)
    assert sim.sim_time == pytest.approx(40 * 0.005, abs=1e-12)


def test_a_writes_plant_time_is_the_physics_steps_it_ran(sim_robot):
    sim = MujocoSystem(sim_robot)
    spans: list[tuple[float, float]] = []

    def advance(dt: float) -> None:
        began = time.perf_counter()
        mujoco.mj_step(sim.model, sim.data)
        spans.append((began, time.perf_counter()))

    sim.advance = advance
    sim.write(0.0, CommandArrays(sim_robot.n))
    assert len(spans) == sim.substeps
    assert sim.io_s >= spans[-1][1] - spans[0][0] > 0


def test_rates_that_are_not_a_whole_multiple_are_refused(sim_robot):
    with pytest.raises(PrimeError, match="whole multiple"):
        MujocoSystem(sim_robot, physics_rate=1000.0, update_rate=300.0)


def test_description_limits_override_a_range_written_in_the_model(tmp_path, sim_robot):
    path = _edited_model(tmp_path, 'name="left_elbow_pitch" class="erob"',
                         'name="left_elbow_pitch" class="erob" range="-0.5 0.5"')
    model = load_model(sim_robot, path)
    assert tuple(model.joint("left_elbow_pitch").range) == (-2.356, 0.0)


def test_a_joint_axis_that_disagrees_with_the_description_fails_at_load(tmp_path, sim_robot):
    path = _edited_model(tmp_path, 'name="right_wrist_yaw" class="erob_wrist" axis="1 0 0"',
                         'name="right_wrist_yaw" class="erob_wrist" axis="0 1 0"')
    with pytest.raises(ConfigError, match="joint right_wrist_yaw: axis") as err:
        load_model(sim_robot, path)
    assert str(path) in str(err.value)


def test_a_joint_origin_that_disagrees_with_the_description_fails_at_load(tmp_path, sim_robot):
    path = _edited_model(tmp_path, '<body name="left_forearm_link" pos="0 0 -0.20">',
                         '<body name="left_forearm_link" pos="0 0 -0.25">')
    with pytest.raises(ConfigError, match="joint left_elbow_pitch: body left_forearm_link is at pos"):
        load_model(sim_robot, path)


def test_a_missing_joint_fails_at_load(tmp_path, sim_robot):
    path = _edited_model(tmp_path, '<joint name="left_wrist_roll" class="sito" axis="0 0 1"/>', "")
    with pytest.raises(ConfigError, match="joint left_wrist_roll: missing from the MuJoCo model"):
        load_model(sim_robot, path)


def test_a_joint_the_description_does_not_know_fails_at_load(tmp_path, sim_robot):
    path = _edited_model(tmp_path, '<joint name="left_shoulder_pitch" class="erob" axis="0 1 0"/>',
                         '<joint name="left_shoulder_pitch" class="erob" axis="0 1 0"/>'
                         '<joint name="left_shoulder_spin" class="erob" axis="0 0 1" range="-1 1"/>')
    with pytest.raises(ConfigError, match="joint left_shoulder_spin: is not an actuated joint"):
        load_model(sim_robot, path)


def test_a_missing_model_file_fails_with_its_name(tmp_path, sim_robot):
    with pytest.raises(ConfigError, match="missing.xml"):
        load_model(sim_robot, tmp_path / "missing.xml")


def test_actuators_apply_the_mit_law_with_the_live_state(sim_robot):
    sim = MujocoSystem(sim_robot, initial_pose={"left_elbow_pitch": -1.0, "right_shoulder_roll": -0.4})
    sim.data.qvel[:] = np.linspace(-0.5, 0.5, sim_robot.n)
    command = CommandArrays(sim_robot.n)
    command.position[:] = np.linspace(-0.2, 0.0, sim_robot.n)
    command.velocity[:] = 0.1
    command.effort[:] = np.linspace(-0.3, 0.3, sim_robot.n)
    command.stiffness[:] = 3.0
    command.damping[:] = 0.5
    sim.write(0.0, command)
    mujoco.mj_forward(sim.model, sim.data)
    q, qd = sim.data.qpos[sim.qpos_adr], sim.data.qvel[sim.dof_adr]
    expected = 3.0 * (command.position - q) + 0.5 * (command.velocity - qd) + command.effort
    np.testing.assert_allclose(sim.data.actuator_force, expected, atol=1e-12)


def test_read_reports_the_applied_torque_saturated_at_the_effort_limit(sim_robot):
    sim = MujocoSystem(sim_robot)
    command = CommandArrays(sim_robot.n)
    command.effort[:] = 100.0
    sim.write(0.0, command)
    state = StateArrays(sim_robot.n)
    sim.read(0.0, state)
    np.testing.assert_array_equal(state.effort, sim_robot.effort_limit)


def test_read_reports_position_and_velocity_in_canonical_order(sim_robot):
    pose = {"left_elbow_pitch": -1.0, "right_wrist_pitch": 0.3}
    sim = MujocoSystem(sim_robot, initial_pose=pose)
    state = StateArrays(sim_robot.n)
    sim.read(0.0, state)
    assert state.position[sim_robot.index("left_elbow_pitch")] == -1.0
    assert state.position[sim_robot.index("right_wrist_pitch")] == 0.3
    assert np.count_nonzero(state.position) == 2
    assert not state.velocity.any()


def test_an_initial_pose_outside_the_limits_is_refused(sim_robot):
    with pytest.raises(PrimeError, match=r"left_elbow_pitch = 0.5 rad is outside its limits \[-2.356, 0\]"):
        MujocoSystem(sim_robot, initial_pose={"left_elbow_pitch": 0.5})


def test_an_initial_pose_naming_no_joint_is_refused(sim_robot):
    with pytest.raises(PrimeError, match="'left_knee' matches no joint"):
        MujocoSystem(sim_robot, initial_pose={"left_knee": 0.0})


def test_deactivating_leaves_every_joint_limp(sim_robot):
    sim = MujocoSystem(sim_robot)
    sim.configure()
    sim.activate()
    command = CommandArrays(sim_robot.n)
    command.stiffness[:] = 20.0
    command.position[:] = -0.3
    sim.write(0.0, command)
    sim.deactivate()
    mujoco.mj_forward(sim.model, sim.data)
    assert not sim.data.actuator_force.any()
