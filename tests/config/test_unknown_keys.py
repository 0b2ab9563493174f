"""A misspelt key is refused with the key and the closest known one, in all three files: a default silently in
force where the operator meant a value is the worst kind of configuration error."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml

from humanoid_prime.cli import main
from humanoid_prime.config.calibration import load_calibration
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.config.hardware import load_hardware
from humanoid_prime.errors import ConfigError
from humanoid_prime.files import bundled

FILES = {name: yaml.safe_load(bundled(name).read_text())
         for name in ("prime_hardware.yaml", "prime_calibration.yaml", "prime_controllers.yaml")}


def written(tmp_path: Path, name: str, edit) -> Path:
    data = copy.deepcopy(FILES[name])
    edit(data)
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def rename(mapping: dict, old: str, new: str) -> None:
    mapping[new] = mapping.pop(old)


CASES = [
    ("prime_hardware.yaml", lambda d: rename(d, "torque_efficiency", "torque_eficiency"), "torque_eficiency",
     "torque_efficiency"),
    ("prime_hardware.yaml", lambda d: rename(d["buses"]["can"], "bitrate", "bit_rate"), "buses.can.bit_rate",
     "bitrate"),
    ("prime_hardware.yaml", lambda d: rename(d["joints"], "erob_gear", "erob_gears"), "joints.erob_gears",
     "erob_gear"),
    ("prime_calibration.yaml", lambda d: rename(d["joints"]["left_elbow_pitch"], "homing_offset", "homing_ofset"),
     "joints.left_elbow_pitch.homing_ofset", "homing_offset"),
    ("prime_calibration.yaml", lambda d: d.update(joint={}), "joint", "joints"),
    ("prime_controllers.yaml", lambda d: rename(d["standby_controller"]["ros__parameters"], "duration", "durration"),
     "standby_controller.ros__parameters.durration", "duration"),
    ("prime_controllers.yaml", lambda d: rename(d, "damping_controller", "damping_controler"),
     "damping_controler", "damping_controller"),
    ("prime_controllers.yaml", lambda d: d["controller_manager"].update(ros_parameters={}),
     "controller_manager.ros_parameters", "ros__parameters"),
    ("prime_controllers.yaml",
     lambda d: d["controller_manager"]["ros__parameters"]["standby_controller"].update(typ="x"),
     "controller_manager.ros__parameters.standby_controller.typ", "type"),
]


def load(name: str, path: Path, robot) -> None:
    if name == "prime_hardware.yaml":
        load_hardware(path)
    elif name == "prime_calibration.yaml":
        load_calibration(robot.hardware, path)
    else:
        load_controllers(robot.names, path)


@pytest.mark.parametrize(("name", "edit", "key", "closest"), CASES, ids=[c[2] for c in CASES])
def test_an_unknown_key_is_refused_with_the_closest_known_one(robot, tmp_path, name, edit, key, closest):
    path = written(tmp_path, name, edit)
    with pytest.raises(ConfigError) as caught:
        load(name, path, robot)
    assert caught.value.key == key and caught.value.problem == "unknown key"
    assert caught.value.fix == f"did you mean {closest!r}?"


def test_every_bundled_template_uses_only_known_keys(robot):
    for name in FILES:
        load(name, bundled(name), robot)


@pytest.mark.parametrize("command", [["sim", "--fast", "--duration", "0.1"], ["bringup"],
                                     ["gains", "--mode", "STANDBY"]])
def test_sim_and_bringup_refuse_the_same_update_rate(tmp_path, capsys, command):
    path = written(tmp_path, "prime_controllers.yaml",
                   lambda d: d["controller_manager"]["ros__parameters"].update(update_rate=5000))
    assert main([*command, "--controllers", str(path)]) == 1
    err = capsys.readouterr().err
    assert "controller_manager.ros__parameters.update_rate: must be <= 2000, got 5000" in err


def test_a_robots_hardware_file_written_before_command_limits_existed_loads_with_the_templates(tmp_path):
    def drop_limits(d):
        del d["command_limits"]["sito"]["damping"]
        del d["command_limits"]["erob"]

    hardware = load_hardware(written(tmp_path, "prime_hardware.yaml", drop_limits))
    template = load_hardware()
    assert hardware.command_limits == template.command_limits
