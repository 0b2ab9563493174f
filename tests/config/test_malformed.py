"""Every validation rule of the config loaders fails loudly, naming the file and the key (DESIGN §1).

Each case takes a bundled file, breaks one thing in a copy under tmp_path, and checks the ConfigError.
"""

import copy
import math
import shutil
from pathlib import Path

import pytest
import yaml

from humanoid_prime.config.calibration import load_calibration
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.config.description import XACRO_FILE, load_description
from humanoid_prime.config.hardware import load_hardware
from humanoid_prime.errors import ConfigError
from humanoid_prime.files import bundled

HARDWARE = yaml.safe_load(bundled("prime_hardware.yaml").read_text())
CALIBRATION = yaml.safe_load(bundled("prime_calibration.yaml").read_text())
CONTROLLERS = yaml.safe_load(bundled("prime_controllers.yaml").read_text())


def broken(tmp_path: Path, name: str, original: dict, edit) -> Path:
    data = copy.deepcopy(original)
    result = edit(data)
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data if result is None else result, sort_keys=False))
    return path


def drop(mapping: dict, key: str) -> None:
    del mapping[key]


def assert_names(error: ConfigError, path: Path, key: str, problem: str) -> None:
    assert error.file == str(path)
    assert error.key == key
    assert problem in error.problem
    text = str(error)
    assert str(path) in text and key in text and problem in text


# prime_hardware.yaml ----------------------------------------------------------------------------------------

def _joints(d):
    return d["joints"]


HARDWARE_CASES = [
    ("top level not a mapping", lambda d: ["buses", "joints"], "", "expected a mapping"),
    ("no buses", lambda d: drop(d, "buses"), "buses", "missing or not a mapping"),
    ("no ethercat bus", lambda d: drop(d["buses"], "ethercat"), "buses.ethercat", "missing or not a mapping"),
    ("no can bus", lambda d: drop(d["buses"], "can"), "buses.can", "missing or not a mapping"),
    ("empty NIC name", lambda d: d["buses"]["ethercat"].update(interface=""), "buses.ethercat.interface",
     "non-empty string"),
    ("master not an integer", lambda d: d["buses"]["ethercat"].update(master="zero"), "buses.ethercat.master",
     "expected an integer"),
    ("no CAN channel", lambda d: drop(d["buses"]["can"], "channel"), "buses.can.channel", "non-empty string"),
    ("CAN interface not a name", lambda d: d["buses"]["can"].update(interface=5), "buses.can.interface",
     "non-empty string"),
    ("bitrate not an integer", lambda d: d["buses"]["can"].update(bitrate="1M"), "buses.can.bitrate",
     "expected an integer"),
    ("bitrate zero", lambda d: d["buses"]["can"].update(bitrate=0), "buses.can.bitrate", "must be 1..1000000"),
    ("no joints", lambda d: drop(d, "joints"), "joints", "missing or not a mapping"),
    ("empty joint list", lambda d: _joints(d).update(all_joints=[]), "joints.all_joints", "missing or empty"),
    ("joint name not a string", lambda d: _joints(d)["all_joints"].__setitem__(3, 7), "joints.all_joints[3]",
     "non-empty string"),
    ("joint listed twice", lambda d: _joints(d)["all_joints"].__setitem__(3, "left_shoulder_pitch"),
     "joints.all_joints[3]", "listed twice"),
    ("erob_slaves not a mapping", lambda d: _joints(d).update(erob_slaves=["left_shoulder_pitch"]),
     "joints.erob_slaves", "expected a mapping"),
    ("mit_joints not a mapping", lambda d: _joints(d).update(mit_joints=[22, 23]), "joints.mit_joints",
     "expected a mapping"),
    ("eRob joint not in all_joints", lambda d: _joints(d)["erob_slaves"].update(waist_yaw=10),
     "joints.erob_slaves.waist_yaw", "not in joints.all_joints"),
    ("ring position not an integer", lambda d: _joints(d)["erob_slaves"].update(left_shoulder_roll="one"),
     "joints.erob_slaves.left_shoulder_roll", "expected an integer"),
    ("negative ring position", lambda d: _joints(d)["erob_slaves"].update(left_shoulder_roll=-1),
     "joints.erob_slaves.left_shoulder_roll", "must be >= 0"),
    ("ring position used twice", lambda d: _joints(d)["erob_slaves"].update(left_shoulder_roll=0),
     "joints.erob_slaves.left_shoulder_roll", "ring position 0 is already used by left_shoulder_pitch"),
    ("Sito joint not in all_joints", lambda d: _joints(d)["mit_joints"].update(left_gripper=40),
     "joints.mit_joints.left_gripper", "not in joints.all_joints"),
    ("joint on both buses", lambda d: _joints(d)["mit_joints"].update(left_wrist_yaw=40),
     "joints.mit_joints.left_wrist_yaw", "also an eRob"),
    ("CAN id not an integer", lambda d: _joints(d)["mit_joints"].update(left_wrist_roll="0x16"),
     "joints.mit_joints.left_wrist_roll", "expected an integer"),
    ("CAN id above range", lambda d: _joints(d)["mit_joints"].update(left_wrist_roll=256),
     "joints.mit_joints.left_wrist_roll", "CAN id 256 is out of range"),
    ("CAN id zero", lambda d: _joints(d)["mit_joints"].update(left_wrist_roll=0),
     "joints.mit_joints.left_wrist_roll", "CAN id 0 is out of range"),
    ("CAN id used twice", lambda d: _joints(d)["mit_joints"].update(left_wrist_pitch=22),
     "joints.mit_joints.left_wrist_pitch", "CAN id 22 is already used by left_wrist_roll"),
    ("joint without a bus", lambda d: drop(_joints(d)["mit_joints"], "left_wrist_roll"),
     "joints.all_joints.left_wrist_roll", "joint has no bus"),
    ("erob_kt not a mapping", lambda d: _joints(d).update(erob_kt=[0.134e-3]), "joints.erob_kt",
     "expected a mapping"),
    ("erob_kt for a Sito joint", lambda d: _joints(d).update(erob_kt={"left_wrist_roll": 0.134e-3}),
     "joints.erob_kt.left_wrist_roll", "is not an eRob joint"),
    ("negative Kt", lambda d: _joints(d).update(erob_kt={"left_elbow_pitch": -0.134e-3}),
     "joints.erob_kt.left_elbow_pitch", "positive finite number"),
    ("non-finite gear", lambda d: _joints(d).update(erob_gear={"left_elbow_pitch": math.nan}),
     "joints.erob_gear.left_elbow_pitch", "positive finite number"),
    ("efficiency zero", lambda d: d.update(torque_efficiency=0.0), "torque_efficiency", "positive finite number"),
    ("efficiency above one", lambda d: d.update(torque_efficiency=1.4), "torque_efficiency", "above 1"),
    ("command limits not a mapping", lambda d: d.update(command_limits=[1, 2]), "command_limits",
     "expected a mapping"),
    ("a family that is not Prime's", lambda d: d["command_limits"].update(hydraulic={}),
     "command_limits.hydraulic", "unknown key"),
    ("negative stiffness maximum", lambda d: d["command_limits"]["erob"].update(stiffness=-1.0),
     "command_limits.erob.stiffness", "positive finite number"),
    ("safety not a mapping", lambda d: d.update(safety=0.03), "safety", "expected a mapping"),
    ("a collision margin of zero", lambda d: d["safety"].update(collision_margin=0), "safety.collision_margin",
     "positive finite number"),
    ("a collision margin in centimetres", lambda d: d["safety"].update(collision_margin=3), "safety.collision_margin",
     "3 m is more than 0.2 m"),
    ("a stopping time in milliseconds", lambda d: d["safety"].update(stopping_time=200), "safety.stopping_time",
     "200 s is more than 1 s"),
    ("an unknown safety key", lambda d: d["safety"].update(margin=0.03), "safety.margin", "unknown key"),
]


def test_a_hardware_file_without_the_safety_section_has_the_templates(tmp_path):
    path = broken(tmp_path, "prime_hardware.yaml", HARDWARE, lambda d: drop(d, "safety"))
    hardware = load_hardware(path)
    assert (hardware.collision_margin, hardware.stopping_time) == (0.03, 0.2)


@pytest.mark.parametrize("edit, key, problem", [c[1:] for c in HARDWARE_CASES], ids=[c[0] for c in HARDWARE_CASES])
def test_hardware_file_rule(tmp_path, edit, key, problem):
    path = broken(tmp_path, "prime_hardware.yaml", HARDWARE, edit)
    with pytest.raises(ConfigError) as info:
        load_hardware(path)
    assert_names(info.value, path, key, problem)


def test_malformed_yaml_names_file_and_line(tmp_path):
    path = tmp_path / "prime_hardware.yaml"
    path.write_text("buses:\n  ethercat: {interface: eth0\n")
    with pytest.raises(ConfigError) as info:
        load_hardware(path)
    assert info.value.file == str(path)
    assert info.value.key.startswith("line ")
    assert "malformed YAML" in str(info.value)


def test_missing_file_is_named(tmp_path):
    path = tmp_path / "nowhere.yaml"
    with pytest.raises(ConfigError, match="file not found") as info:
        load_hardware(path)
    assert info.value.file == str(path)


# prime_calibration.yaml -------------------------------------------------------------------------------------

def _entry(d, joint="left_elbow_pitch"):
    return d["joints"][joint]


CALIBRATION_CASES = [
    ("no joints mapping", lambda d: drop(d, "joints"), "joints", "missing or not a mapping"),
    ("key that matches no joint", lambda d: d["joints"].update(waist_yaw={"direction": 1, "homing_offset": 0.0}),
     "joints.waist_yaw", "matches no joint of prime_hardware.yaml"),
    ("joint missing", lambda d: drop(d["joints"], "left_elbow_pitch"), "joints.left_elbow_pitch", "missing"),
    ("direction 2", lambda d: _entry(d).update(direction=2), "joints.left_elbow_pitch.direction",
     "must be 1 or -1"),
    ("direction 0", lambda d: _entry(d).update(direction=0), "joints.left_elbow_pitch.direction",
     "must be 1 or -1"),
    ("direction true", lambda d: _entry(d).update(direction=True), "joints.left_elbow_pitch.direction",
     "must be 1 or -1"),
    ("direction missing", lambda d: drop(_entry(d), "direction"), "joints.left_elbow_pitch.direction",
     "must be 1 or -1"),
    ("offset nan", lambda d: _entry(d).update(homing_offset=math.nan), "joints.left_elbow_pitch.homing_offset",
     "must be a finite number"),
    ("offset inf", lambda d: _entry(d).update(homing_offset=-math.inf), "joints.left_elbow_pitch.homing_offset",
     "must be a finite number"),
    ("offset text", lambda d: _entry(d).update(homing_offset="0.1"), "joints.left_elbow_pitch.homing_offset",
     "must be a finite number"),
]


@pytest.mark.parametrize("edit, key, problem", [c[1:] for c in CALIBRATION_CASES],
                         ids=[c[0] for c in CALIBRATION_CASES])
def test_calibration_file_rule(tmp_path, robot, edit, key, problem):
    path = broken(tmp_path, "prime_calibration.yaml", CALIBRATION, edit)
    with pytest.raises(ConfigError) as info:
        load_calibration(robot.hardware, path)
    assert_names(info.value, path, key, problem)


def test_malformed_calibration_yaml(tmp_path, robot):
    path = tmp_path / "prime_calibration.yaml"
    path.write_text("joints:\n  left_elbow_pitch: [direction: 1\n")
    with pytest.raises(ConfigError, match="malformed YAML") as info:
        load_calibration(robot.hardware, path)
    assert info.value.file == str(path)


# prime_controllers.yaml -------------------------------------------------------------------------------------

def _params(d, node):
    return d[node]["ros__parameters"]


STANDBY = "standby_controller.ros__parameters"
CONTROLLER_CASES = [
    ("top level not a mapping", lambda d: [1, 2], "", "expected a mapping of keys to values at the top"),
    ("node without ros__parameters", lambda d: drop(d, "damping_controller"), "damping_controller.ros__parameters",
     "missing or not a mapping"),
    ("controller not declared", lambda d: drop(_params(d, "controller_manager"), "remote_policy_controller"),
     "controller_manager.ros__parameters.remote_policy_controller", "controller not declared"),
    ("no poses", lambda d: drop(_params(d, "standby_controller"), "poses"), f"{STANDBY}.poses", "missing or empty"),
    ("pose not a mapping", lambda d: _params(d, "standby_controller")["poses"].update(ready=[0.1]),
     f"{STANDBY}.poses.ready", "expected a mapping joint -> rad"),
    ("pose joint matches no joint", lambda d: _params(d, "standby_controller")["poses"]["ready"].update(waist=0.1),
     f"{STANDBY}.poses.ready.waist", "matches no joint"),
    ("pose angle nan",
     lambda d: _params(d, "standby_controller")["poses"]["ready"].update(left_elbow_pitch=math.nan),
     f"{STANDBY}.poses.ready.left_elbow_pitch", "expected a finite angle"),
    ("kp nan", lambda d: _params(d, "standby_controller").update(kp=math.nan), f"{STANDBY}.kp",
     "expected a finite number"),
    ("kp negative", lambda d: _params(d, "standby_controller").update(kp=-1.0), f"{STANDBY}.kp", "must be >= 0"),
    ("duration zero", lambda d: _params(d, "standby_controller").update(duration=0), f"{STANDBY}.duration",
     "must be > 0"),
    ("update rate zero", lambda d: _params(d, "controller_manager").update(update_rate=0),
     "controller_manager.ros__parameters.update_rate", "must be > 0"),
    ("update rate beyond the eRob cycle", lambda d: _params(d, "controller_manager").update(update_rate=5000),
     "controller_manager.ros__parameters.update_rate", "must be <= 2000, got 5000"),
    ("damping kd text", lambda d: _params(d, "damping_controller").update(kd="six"),
     "damping_controller.ros__parameters.kd", "expected a finite number"),
    ("policy not a string", lambda d: _params(d, "locomotion_controller").update(policy=3),
     "locomotion_controller.ros__parameters.policy", "expected a string"),
    ("default pose undefined", lambda d: _params(d, "standby_controller").update(default_pose="sideways"),
     f"{STANDBY}.default_pose", "pose 'sideways' is not defined"),
    ("unknown stale policy", lambda d: _params(d, "remote_policy_controller").update(stale_policy="panic"),
     "remote_policy_controller.ros__parameters.stale_policy", "expected 'damp' or 'hold'"),
    ("efficiency set twice", lambda d: _params(d, "erob_impedance_manager").update(torque_efficiency=0.7),
     "erob_impedance_manager.ros__parameters.torque_efficiency", "set here and in the hardware file"),
    ("parallel_sdo not a bool", lambda d: _params(d, "erob_impedance_manager").update(parallel_sdo="yes"),
     "erob_impedance_manager.ros__parameters.parallel_sdo", "expected true or false"),
    ("too many retries", lambda d: _params(d, "erob_impedance_manager").update(sdo_retries=50),
     "erob_impedance_manager.ros__parameters.sdo_retries", "expected an integer 0..20"),
]


@pytest.mark.parametrize("edit, key, problem", [c[1:] for c in CONTROLLER_CASES],
                         ids=[c[0] for c in CONTROLLER_CASES])
def test_controllers_file_rule(tmp_path, robot, edit, key, problem):
    path = broken(tmp_path, "prime_controllers.yaml", CONTROLLERS, edit)
    with pytest.raises(ConfigError) as info:
        load_controllers(robot.names, path)
    assert_names(info.value, path, key, problem)


def test_malformed_controllers_yaml(tmp_path, robot):
    path = tmp_path / "prime_controllers.yaml"
    path.write_text("controller_manager:\n  ros__parameters:\n    update_rate: 50\n   bad: indent\n")
    with pytest.raises(ConfigError, match="malformed YAML") as info:
        load_controllers(robot.names, path)
    assert info.value.file == str(path)


# the description (xacro) ------------------------------------------------------------------------------------

ARM = "prime_dummy.arm.xacro"
ROS2_CONTROL = "prime_dummy.ros2_control.xacro"


def description_copy(tmp_path: Path, name: str, old: str, new: str) -> Path:
    """A copy of the bundled description with one text edit in ``name``; returns the top xacro."""
    folder = tmp_path / "description"
    shutil.copytree(bundled(XACRO_FILE).parent, folder)
    target = folder / name
    text = target.read_text()
    assert old in text, f"{old!r} not in {name}"
    target.write_text(text.replace(old, new, 1))
    return folder / Path(XACRO_FILE).name


DESCRIPTION_CASES = [
    ("xacro that does not parse", ARM, "<robot ", "<robot <", "", "xacro failed"),
    ("actuated joint without a limit", ARM,
     '<limit lower="${lower}" upper="${upper}" effort="${effort}" velocity="${velocity}"/>', "",
     "joint left_shoulder_pitch", "actuated joint has no <limit>"),
    ("limit that is not a number", ARM, 'effort="4.8"', 'effort="strong"', "joint left_wrist_roll.limit",
     "limit values are not numbers"),
    ("lower not below upper", ARM, 'lower="-0.698" upper="0.698"', 'lower="0.698" upper="-0.698"',
     "joint left_wrist_roll.limit", "is not below upper"),
    ("joint without the MIT surface", ROS2_CONTROL, '<command_interface name="damping"/>', "",
     "ros2_control PrimeEtherCATSide.left_shoulder_pitch", "are not the MIT surface"),
    ("joint owned by two blocks", ROS2_CONTROL,
     '<xacro:sito_joints names="${[j for j in all_joints if j in mit_joints]}" ids="${mit_joints}"/>',
     '<xacro:sito_joints names="${[j for j in all_joints if j in mit_joints]}" ids="${mit_joints}"/>'
     '<xacro:sim_joints names="${[\'left_shoulder_pitch\']}"/>',
     "ros2_control PrimeSitoCAN.left_shoulder_pitch", "also owned by PrimeEtherCATSide"),
    ("joint without a hardware block", ROS2_CONTROL, "if j in erob_slaves]",
     "if j in erob_slaves and j != 'right_wrist_yaw']", "ros2_control", "joints without a hardware block"),
]


@pytest.mark.parametrize("name, old, new, key, problem", [c[1:] for c in DESCRIPTION_CASES],
                         ids=[c[0] for c in DESCRIPTION_CASES])
def test_description_rule(tmp_path, robot, name, old, new, key, problem):
    xacro_file = description_copy(tmp_path, name, old, new)
    with pytest.raises(ConfigError) as info:
        load_description(robot.hardware, xacro_file=xacro_file)
    assert_names(info.value, xacro_file, key, problem)


def test_description_and_hardware_file_naming_different_joints(tmp_path):
    renamed = bundled("prime_hardware.yaml").read_text().replace("left_wrist_yaw", "left_wrist_twist")
    path = tmp_path / "prime_hardware.yaml"
    path.write_text(renamed)
    with pytest.raises(ConfigError) as info:
        load_description(load_hardware(path))
    error = info.value
    assert_names(error, bundled(XACRO_FILE), "joints", "name different joints")
    assert "only in description: ['left_wrist_yaw']" in str(error)
    assert "only in hardware file: ['left_wrist_twist']" in str(error)
    assert "prime_hardware.yaml" in str(error)
