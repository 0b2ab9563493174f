"""``prime sim --hil can``: the same controllers drive the Sito wrists through SitoSystem, real CAN frames
on a virtual bus and emulated motors whose plants are the wrists of the simulated model."""

import json
import signal
import subprocess
import sys

import can
import mujoco
import numpy as np
import pytest

from humanoid_prime.cli import main
from humanoid_prime.config.calibration import JointCalibration, load_calibration
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.control.controller import pose_array
from humanoid_prime.control.hardware import Lifecycle
from humanoid_prime.control.interfaces import CommandArrays
from humanoid_prime.control.topics import SAFETY_STATUS
from humanoid_prime.drivers.mujoco.system import MujocoSystem
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode
from humanoid_prime.sim.demo import Simulation, Step
from humanoid_prime.virtual.hil import build_hil_simulation

DEMO_TICKS = 4000  # 20 s at 200 Hz
# Where the wrists are when the simulated robot powers up: well away from the ready pose (all zero).
WRISTS_OFF = {"left_wrist_roll": 0.5, "left_wrist_pitch": -0.6, "right_wrist_roll": -0.5, "right_wrist_pitch": 0.6}


@pytest.fixture(scope="module")
def config(sim_robot):
    return load_controllers(sim_robot.names)


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("hil")
    summary = tmp_path / "summary.json"
    code = main(["sim", "--hil", "can", "--duration", "20", "--fast", "--summary", str(summary),
                 "--socket", str(tmp_path / "control.sock")])
    return code, json.loads(summary.read_text())


def gravity_torque(system: MujocoSystem, dofs: np.ndarray) -> np.ndarray:
    data = mujoco.MjData(system.model)
    data.qpos[:] = system.data.qpos
    mujoco.mj_forward(system.model, data)
    return data.qfrc_bias[dofs].copy()


# --- the demonstration -------------------------------------------------------------------------------

def test_the_demonstration_over_can_visits_every_mode_with_no_fallbacks(demo):
    code, summary = demo
    assert code == 0
    assert summary["modes_visited"] == ["ZERO_TORQUE", "DAMPING", "STANDBY", "LOCOMOTION", "REMOTE", "DAMPING"]
    assert summary["fallbacks"] == []
    assert (summary["ticks"], summary["sim_seconds"]) == (DEMO_TICKS, 20.0)
    assert summary["hil"] == "can"


def test_every_tick_sends_one_command_frame_per_wrist_and_the_motors_take_every_frame(demo):
    frames = demo[1]["can"]
    assert frames["host_frames_sent"] >= 4 * DEMO_TICKS
    assert frames["emulator_frames_received"] == frames["host_frames_sent"]
    assert frames["host_send_failures"] == 0


def test_feedback_comes_back_from_every_wrist_every_control_period(demo):
    frames = demo[1]["can"]
    assert frames["host_frames_received"] >= 2 * 4 * DEMO_TICKS  # 0xB1 and 0xB2 from four motors
    assert frames["host_frames_received"] == frames["emulator_frames_sent"]
    assert frames["host_invalid_frames"] == frames["emulator_invalid_frames"] == 0


def test_the_demonstration_ends_with_every_motor_disabled(demo):
    frames = demo[1]["can"]
    assert frames["emulator_disable_frames"] == 4
    assert frames["emulator_motors_enabled"] == 0


def test_sigterm_stops_the_run_and_disables_every_motor(tmp_path):
    summary = tmp_path / "summary.json"
    child = subprocess.Popen([sys.executable, "-m", "humanoid_prime.cli", "sim", "--hil", "can", "--mode", "standby",
                              "--summary", str(summary), "--socket", str(tmp_path / "c.sock")],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().startswith("staged start:")
        assert "STANDBY" in child.stdout.readline()  # the loop runs
        child.send_signal(signal.SIGTERM)
        assert child.wait(timeout=20) == 0
    finally:
        child.kill()
        child.communicate()
    data = json.loads(summary.read_text())
    assert data["stopped_by"] == "interrupt"
    assert data["can"]["emulator_disable_frames"] >= 4
    assert data["can"]["emulator_motors_enabled"] == 0


def test_without_hil_the_summary_says_none(tmp_path, capsys):
    assert main(["sim", "--duration", "0.5", "--fast", "--json", "--socket", str(tmp_path / "c.sock")]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["hil"] == "none"
    assert "can" not in summary


def test_an_unknown_hil_is_one_line_and_exit_2(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["sim", "--hil", "ethercat", "--socket", str(tmp_path / "c.sock")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "invalid choice: 'ethercat'" in err


# --- the wrists through frames -----------------------------------------------------------------------

def flipped_calibration(robot):
    calibration = load_calibration(robot.hardware)
    for joint in ("left_wrist_roll", "right_wrist_pitch"):
        calibration = calibration.with_joint(joint, JointCalibration(-1, 0.3))
    return calibration


@pytest.mark.parametrize("calibration", [None, flipped_calibration], ids=["bundled", "flipped-and-offset"])
def test_standby_drives_the_wrists_to_their_pose_through_frames(sim_robot, config, calibration):
    wrists = sim_robot.indices("sito")
    target = pose_array(sim_robot, config.standby.poses[config.standby.default_pose])
    kp = config.standby.kp
    with build_hil_simulation(sim_robot, config, initial_pose=WRISTS_OFF,
                              calibration=calibration(sim_robot) if calibration else None) as hil:
        hil.start()
        system, manager = hil.system, hil.manager
        start = manager.resources.state.position[wrists].copy()
        Simulation(system, manager, schedule=(Step(0.0, Mode.STANDBY),), realtime=False).run(4.0)
        state = manager.resources.state
        assert manager.active_mode is Mode.STANDBY and manager.fallbacks == []
        dofs = np.array([system.model.joint(sim_robot.names[i]).dofadr[0] for i in wrists])
        model_q = system.data.qpos[[system.model.joint(sim_robot.names[i]).qposadr[0] for i in wrists]]
        sag_predicted = gravity_torque(system, dofs) / kp
        tolerance = system.model.dof_frictionloss[dofs] / kp + 1e-3
        motor_kp = [motor.kp for motor in hil.emulator.motors.values()]
        np.testing.assert_allclose(state.position[wrists], model_q, atol=1e-4)  # the host reads the model's angle
    np.testing.assert_allclose(start, [WRISTS_OFF[sim_robot.names[i]] for i in wrists], atol=1e-4)
    np.testing.assert_array_less(np.abs(target[wrists] - model_q - sag_predicted), tolerance)
    np.testing.assert_allclose(motor_kp, kp, rtol=1e-6)  # the firmware realises the stiffness asked for


def test_the_world_applies_the_emulated_motor_torque_to_a_wrist_and_no_actuator_torque(sim_robot, config):
    with build_hil_simulation(sim_robot, config, initial_pose=WRISTS_OFF) as hil:
        hil.start()
        Simulation(hil.system, hil.manager, schedule=(Step(0.0, Mode.STANDBY),), realtime=False).run(0.5)
        model, data = hil.system.model, hil.system.data
        for motor, joint in zip(hil.emulator.motors.values(), sim_robot.hardware.sito_joints, strict=True):
            assert data.qfrc_applied[model.joint(joint).dofadr[0]] == motor.torque
            assert abs(motor.torque) > 0.01
            actuator = sim_robot.index(joint)
            assert data.actuator_force[actuator] == 0.0
            assert model.actuator_biasprm[actuator, 1:3].tolist() == [0.0, 0.0]


def test_a_wrist_that_goes_silent_raises_its_rx_timeout_while_the_loop_runs_on(sim_robot, config):
    key = "PrimeSitoCAN/can2/rx_timeout/22"
    with build_hil_simulation(sim_robot, config) as hil:
        hil.start()
        sim = Simulation(hil.system, hil.manager, schedule=(Step(0.0, Mode.STANDBY),), realtime=False)
        raised: list = []
        hil.manager.topics.subscribe(SAFETY_STATUS, lambda status: raised.append(status) if key in status.flags
                                     and not raised else None)
        sim.run(1.0)
        assert not raised
        silent_at = hil.system.sim_time
        hil.emulator.motors[22].silent = True
        sim.run(0.5)
        assert hil.manager.tick_count == 300
        assert hil.manager.active_mode is Mode.STANDBY and hil.manager.fallbacks == []
        assert hil.manager.topics.latest(SAFETY_STATUS) is raised[0]
    status = raised[0]
    assert not status.ok
    assert [flag for flag in status.flags if "rx_timeout" in flag] == [key]
    assert "left_wrist_roll (CAN id 22)" in status.flags[key]
    # The host's clock is firmware time: the 200 ms timeout counts simulated time, to the control period.
    assert 0.2 - 1e-9 <= status.stamp - silent_at <= 0.2 + 0.005 + 1e-9


def test_a_wrist_that_never_answers_fails_the_start_and_everything_is_shut_down(sim_robot, config):
    hil = build_hil_simulation(sim_robot, config)
    hil.emulator.motors[39].silent = True
    with pytest.raises(PrimeError, match=r"no feedback on can2 from right_wrist_pitch \(CAN id 39\)"):
        hil.start()
    hil.close()
    assert hil.channel not in can.interfaces.virtual.channels
    assert all(motor.disables == 1 and not motor.enabled for motor in hil.emulator.motors.values())


def test_closing_disables_every_motor_and_closes_both_buses(sim_robot, config):
    with build_hil_simulation(sim_robot, config) as hil:
        hil.start()
        assert all(motor.enabled for motor in hil.emulator.motors.values())
        Simulation(hil.system, hil.manager, realtime=False).run(0.1)
    assert all(motor.disables == 1 and not motor.enabled for motor in hil.emulator.motors.values())
    assert hil.channel not in can.interfaces.virtual.channels
    assert hil.sito.lifecycle is Lifecycle.FINALIZED


def test_the_emulator_firmware_runs_at_the_physics_rate(sim_robot, config):
    with build_hil_simulation(sim_robot, config) as hil:
        hil.start()
        ticks = hil.emulator.ticks
        Simulation(hil.system, hil.manager, realtime=False).run(1.0)
        assert hil.emulator.dt == hil.system.physics_dt == 0.001
        assert hil.emulator.ticks - ticks == 1000
        assert hil.system.sim_time == pytest.approx(1.0, abs=1e-9)


# --- MujocoSystem options ----------------------------------------------------------------------------

def test_a_mujoco_system_owning_the_erob_joints_leaves_the_wrist_actuators_at_zero(sim_robot):
    system = MujocoSystem(sim_robot, joints=sim_robot.hardware.erob_joints)
    assert system.joints == sim_robot.hardware.erob_joints
    command = CommandArrays(sim_robot.n)
    command.stiffness[:] = 20.0
    command.damping[:] = 2.0
    command.position[:] = 0.1
    command.effort[:] = 0.5
    system.write(0.0, command)
    wrists = sim_robot.indices("sito")
    assert not system.model.actuator_biasprm[wrists, 1:3].any()
    assert not system.data.ctrl[wrists].any()
    erob = sim_robot.indices("erob")
    np.testing.assert_array_equal(system.model.actuator_biasprm[erob, 1], -20.0)
    np.testing.assert_allclose(system.data.ctrl[erob], 20.0 * 0.1 + 0.5)


def test_advance_replaces_the_physics_step_once_per_substep(sim_robot):
    calls: list[float] = []
    system = MujocoSystem(sim_robot, advance=calls.append)
    system.write(0.0, CommandArrays(sim_robot.n))
    assert calls == [0.001] * 5
    assert system.sim_time == 0.0  # nothing stepped the world but the callback


def test_a_joint_subset_naming_an_unknown_joint_is_refused(sim_robot):
    with pytest.raises(PrimeError, match="left_wrist_twist"):
        MujocoSystem(sim_robot, joints=("left_wrist_twist",))
