"""``--apply``: a measured eRob torque efficiency per joint goes into the robot's hardware file, and everything that
turns gains into registers takes each joint's own."""

from __future__ import annotations

import pytest

from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.config.hardware import load_hardware, write_erob_torque_efficiency
from humanoid_prime.config.robot import load_robot
from humanoid_prime.drivers.erob.gains import gains_to_registers
from humanoid_prime.drivers.ethercat.fold import startup_sdos
from humanoid_prime.errors import ConfigError
from humanoid_prime.files import bundled
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.impedance import ImpedanceManager


def hardware_copy(folder):
    """The bundled hardware file, as a robot's own copy."""
    path = folder / "prime_hardware.yaml"
    path.write_text(bundled("prime_hardware.yaml").read_text())
    return path


def test_apply_sets_the_joints_measured_and_keeps_every_other_line(tmp_path):
    path = hardware_copy(tmp_path)
    before = path.read_text()
    write_erob_torque_efficiency(path, {"left_elbow_pitch": 0.712, "right_wrist_yaw": 0.69})
    after = path.read_text()
    hardware = load_hardware(path)
    assert hardware.erob_torque_efficiency["left_elbow_pitch"] == 0.712
    assert hardware.erob_torque_efficiency["right_wrist_yaw"] == 0.69
    assert hardware.erob_torque_efficiency["left_shoulder_pitch"] == 1.0  # not measured: the scalar
    kept = [line for line in before.splitlines() if "erob_torque_efficiency" not in line]
    assert all(line in after.splitlines() for line in kept)  # every comment and key as it was


def test_a_second_apply_updates_and_keeps_the_earlier_joints(tmp_path):
    path = hardware_copy(tmp_path)
    write_erob_torque_efficiency(path, {"left_elbow_pitch": 0.7, "left_wrist_yaw": 0.71})
    write_erob_torque_efficiency(path, {"left_elbow_pitch": 0.72})
    hardware = load_hardware(path)
    assert hardware.erob_torque_efficiency["left_elbow_pitch"] == 0.72
    assert hardware.erob_torque_efficiency["left_wrist_yaw"] == 0.71
    assert path.read_text().count("erob_torque_efficiency:") == 1


def test_a_file_without_the_key_gets_it_under_joints(tmp_path):
    path = tmp_path / "prime_hardware.yaml"
    path.write_text(bundled("prime_hardware.yaml").read_text().replace("  erob_torque_efficiency: {}\n", ""))
    write_erob_torque_efficiency(path, {"right_elbow_pitch": 0.7})
    assert load_hardware(path).erob_torque_efficiency["right_elbow_pitch"] == 0.7


def test_a_wrist_is_refused_and_the_file_is_left_as_it_was(tmp_path):
    path = hardware_copy(tmp_path)
    before = path.read_bytes()
    with pytest.raises(ConfigError, match="left_wrist_roll is not an eRob joint"):
        write_erob_torque_efficiency(path, {"left_wrist_roll": 0.7})
    assert path.read_bytes() == before


def test_the_impedance_manager_the_fold_and_the_gain_check_take_each_joints_efficiency(tmp_path):
    path = hardware_copy(tmp_path)
    write_erob_torque_efficiency(path, {"left_elbow_pitch": 0.7})
    robot = load_robot(path)
    config = load_controllers(robot.names)
    kp, kd = config.mode_gains()[Mode.STANDBY]
    manager = ImpedanceManager(robot, object(), config.mode_gains(), parallel=False)
    hw = robot.hardware
    elbow, shoulder = hw.erob_slaves["left_elbow_pitch"], hw.erob_slaves["left_shoulder_pitch"]
    assert manager.targets[Mode.STANDBY][elbow] == gains_to_registers(kp, kd, efficiency=0.7)
    assert manager.targets[Mode.STANDBY][shoulder] == gains_to_registers(kp, kd, efficiency=1.0)
    sdos = {(w["index"], w["sub_index"]): w["value"]
            for w in startup_sdos(robot.joints[robot.index("left_elbow_pitch")], hw, config.mode_gains())}
    assert sdos[(0x2381, 1)] == gains_to_registers(kp, kd, efficiency=0.7).vel_reg
