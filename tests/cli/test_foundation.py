"""The foundation commands: prime info, gains, decode, calibration fold|flip|check."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from humanoid_prime.cli import main
from humanoid_prime.config.calibration import load_calibration
from humanoid_prime.drivers.ethercat.slave_config import load_slave_config
from humanoid_prime.files import bundled


def prime(capsys, *argv: str) -> tuple[int, str, str]:
    try:
        code = main(list(argv))
    except SystemExit as exc:  # argparse reports bad arguments by exiting
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def prime_json(capsys, *argv: str):
    code, out, err = prime(capsys, *argv, "--json")
    assert (code, err) == (0, "")
    return json.loads(out)


def assert_one_line_error(code: int, err: str, fragment: str) -> None:
    assert code != 0
    assert err.endswith("\n") and err.count("\n") == 1, err
    assert "Traceback" not in err
    assert fragment in err


@pytest.fixture
def calibration_file(tmp_path) -> Path:
    path = tmp_path / "prime_calibration.yaml"
    shutil.copy(bundled("prime_calibration.yaml"), path)
    return path


# info -------------------------------------------------------------------------------------------------------

def test_info_json_lists_the_joints_in_canonical_order(capsys, robot):
    rows = prime_json(capsys, "info")
    assert [r["joint"] for r in rows] == list(robot.names)
    assert {r["family"] for r in rows} == {"erob", "sito"}


def test_info_json_has_bus_address_and_limits(capsys):
    rows = {r["joint"]: r for r in prime_json(capsys, "info")}
    wrist_yaw, wrist_roll = rows["left_wrist_yaw"], rows["right_wrist_roll"]
    assert (wrist_yaw["family"], wrist_yaw["bus"], wrist_yaw["address"]) == ("erob", "ethercat", "ring 4")
    assert (wrist_roll["family"], wrist_roll["bus"], wrist_roll["can_id"]) == ("sito", "can", 38)
    assert (rows["right_shoulder_roll"]["lower"], rows["right_shoulder_roll"]["upper"]) == (-1.920, 1.571)
    assert rows["left_elbow_pitch"]["direction"] == 1


def test_info_table_names_every_joint(capsys, robot):
    code, out, _ = prime(capsys, "info")
    assert code == 0
    assert all(name in out for name in robot.names)


# gains ------------------------------------------------------------------------------------------------------

def test_gains_for_standby_values(capsys):
    rows = prime_json(capsys, "gains", "--kp", "20", "--kd", "2")
    assert len(rows) == 10
    for r in rows:
        assert (r["vel_reg"], r["pos_reg"], r["integral"]) == (19, 515, 0)
        assert r["vel_reg_exact"] == pytest.approx(18.81, abs=0.01)
        assert r["pos_reg_exact"] == pytest.approx(514.7)


def test_gains_of_damping_mode_for_one_joint(capsys):
    row = prime_json(capsys, "gains", "--mode", "DAMPING", "--joint", "left_elbow_pitch")
    assert (row["joint"], row["mode"], row["pos_reg"], row["vel_reg"], row["integral"]) == (
        "left_elbow_pitch", "DAMPING", 0, 56, 0)


def test_gains_of_zero_torque_are_zero(capsys):
    rows = prime_json(capsys, "gains", "--mode", "zero_torque")
    assert {(r["vel_reg"], r["pos_reg"], r["integral"]) for r in rows} == {(0, 0, 0)}


def test_gains_efficiency_divides_vel_reg(capsys):
    row = prime_json(capsys, "gains", "--kp", "20", "--kd", "2", "--joint", "right_wrist_yaw", "--efficiency", "0.7")
    assert row["vel_reg_exact"] == pytest.approx(2 / 0.1063 / 0.7)
    assert row["pos_reg"] == 515


def test_gains_use_the_per_joint_kt_of_the_hardware_file(capsys, tmp_path):
    data = yaml.safe_load(bundled("prime_hardware.yaml").read_text())
    data["joints"]["erob_kt"] = {"left_elbow_pitch": 0.134e-3}
    path = tmp_path / "prime_hardware.yaml"
    path.write_text(yaml.safe_dump(data))
    rows = {r["joint"]: r for r in prime_json(capsys, "gains", "--kp", "20", "--kd", "2", "--hardware", str(path))}
    ratio = rows["left_elbow_pitch"]["vel_reg_exact"] / rows["left_shoulder_pitch"]["vel_reg_exact"]
    assert ratio == pytest.approx(0.132 / 0.134)


@pytest.mark.parametrize("argv, fragment", [
    (["--kp", "20"], "give --kp and --kd"),
    (["--mode", "STANDBY", "--kp", "1"], "either --mode or --kp/--kd"),
    (["--mode", "dancing"], "unknown mode 'dancing'"),
    (["--kp", "20", "--kd", "0"], "stiffness needs damping"),
    (["--kp", "20", "--kd", "2", "--joint", "left_wrist_roll"], "left_wrist_roll is a Sito joint"),
    (["--kp", "20", "--kd", "2", "--joint", "nose"], "unknown joint 'nose'"),
    (["--kp", "20", "--kd", "2", "--efficiency", "2"], "argument --efficiency: must be at most 1, got 2"),
    (["--kp", "twenty", "--kd", "2"], "argument --kp: 'twenty' is not a number"),
    (["--kp", "nan", "--kd", "2"], "argument --kp: nan is not a finite number"),
])
def test_gains_bad_arguments_are_one_line(capsys, argv, fragment):
    code, _, err = prime(capsys, "gains", *argv)
    assert_one_line_error(code, err, fragment)


# decode -----------------------------------------------------------------------------------------------------

def test_decode_5687_is_operation_enabled(capsys):
    result = prime_json(capsys, "decode", "statusword", "5687")
    assert (result["state"], result["hex"]) == ("operation enabled", "0x1637")


def test_decode_4616_is_fault(capsys):
    assert prime_json(capsys, "decode", "statusword", "4616")["state"] == "fault"


def test_decode_accepts_hex(capsys):
    assert prime_json(capsys, "decode", "statusword", "0x1208")["statusword"] == 4616


def test_decode_error_meaning(capsys):
    assert prime_json(capsys, "decode", "error", "0xA000")["meaning"] == "EtherCAT communication error"
    assert prime_json(capsys, "decode", "error", "34048")["meaning"] == "position (following) error over limit"


def test_decode_unknown_error_is_named(capsys):
    assert prime_json(capsys, "decode", "error", "0x1234")["meaning"] == "unknown eRob error 0x1234"


def test_decode_al_status(capsys):
    assert prime_json(capsys, "decode", "al-status", "0x1B")["meaning"] == "sync manager watchdog"


@pytest.mark.parametrize("argv, fragment", [
    (["statusword", "five"], "'five' is not a number"),
    (["statusword", "0x10000"], "outside 0..0xFFFF"),
    (["error", "-1"], "outside 0..0xFFFF"),
    (["statusword"], "required: N"),
    (["register", "1"], "invalid choice"),
])
def test_decode_bad_arguments_are_one_line(capsys, argv, fragment):
    code, _, err = prime(capsys, "decode", *argv)
    assert_one_line_error(code, err, fragment)


# calibration fold | flip | check ----------------------------------------------------------------------------

def test_fold_writes_one_config_per_erob(capsys, tmp_path, calibration_file):
    rows = prime_json(capsys, "calibration", "fold", "--calibration", str(calibration_file), "--out",
                      str(tmp_path / "erob"))
    assert [r["ring_position"] for r in rows] == list(range(10))
    for r in rows:
        config = load_slave_config(r["path"])
        assert Path(r["path"]).name == f"{r['joint']}.yaml"
        assert config.state("position").factor == pytest.approx(2 * 3.141592653589793 / 524288)


def test_fold_into_a_file_is_refused(capsys, tmp_path, calibration_file):
    blocker = tmp_path / "file"
    blocker.write_text("")
    code, _, err = prime(capsys, "calibration", "fold", "--calibration", str(calibration_file), "--out",
                         str(blocker))
    assert_one_line_error(code, err, "is a file, not a folder")


def test_flip_rewrites_the_file(capsys, robot, calibration_file):
    result = prime_json(capsys, "calibration", "flip", "left_elbow_pitch", "--calibration", str(calibration_file))
    assert result["new"] == {"direction": -1, "homing_offset": pytest.approx(-2.356)}
    cal = load_calibration(robot.hardware, calibration_file)
    assert cal.joints["left_elbow_pitch"].direction == -1
    assert cal.joints["left_elbow_pitch"].homing_offset == pytest.approx(-2.356)
    assert cal.joints["right_elbow_pitch"].direction == 1


def test_flip_leaves_a_symmetric_offset_unchanged(capsys, robot, calibration_file):
    prime_json(capsys, "calibration", "flip", "right_wrist_pitch", "--calibration", str(calibration_file))
    cal = load_calibration(robot.hardware, calibration_file).joints["right_wrist_pitch"]
    assert (cal.direction, cal.homing_offset) == (-1, 0.0)


def test_flip_unknown_joint_is_one_line(capsys, calibration_file):
    code, _, err = prime(capsys, "calibration", "flip", "tail", "--calibration", str(calibration_file))
    assert_one_line_error(code, err, "unknown joint 'tail'")


def test_check_of_a_good_file(capsys, calibration_file):
    result = prime_json(capsys, "calibration", "check", str(calibration_file))
    assert result["flags"] == []
    assert len(result["mirror"]) == 7
    assert {m["left"]: m["relation"] for m in result["mirror"]}["left_shoulder_roll"] == "opposite"


def test_check_flags_an_offset_over_pi_and_exits_1(capsys, calibration_file):
    data = yaml.safe_load(calibration_file.read_text())
    data["joints"]["left_shoulder_yaw"]["homing_offset"] = -3.5
    calibration_file.write_text(yaml.safe_dump(data))
    code, out, _ = prime(capsys, "calibration", "check", str(calibration_file), "--json")
    assert code == 1
    assert [f["joint"] for f in json.loads(out)["flags"]] == ["left_shoulder_yaw"]


def test_check_of_a_malformed_file_names_file_and_key(capsys, calibration_file):
    data = yaml.safe_load(calibration_file.read_text())
    data["joints"]["left_wrist_roll"]["direction"] = 2
    calibration_file.write_text(yaml.safe_dump(data))
    code, _, err = prime(capsys, "calibration", "check", str(calibration_file))
    assert_one_line_error(code, err, f"{calibration_file}: joints.left_wrist_roll.direction: must be 1 or -1")


# the installed console script ------------------------------------------------------------------------------

PRIME = Path(sys.executable).with_name("prime")


def test_console_script_decodes():
    done = subprocess.run([str(PRIME), "decode", "statusword", "5687", "--json"], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0
    assert json.loads(done.stdout)["state"] == "operation enabled"


def test_console_script_reports_a_bad_argument_in_one_line():
    done = subprocess.run([str(PRIME), "gains", "--kp", "20", "--kd", "0"], capture_output=True, text=True,
                          timeout=60)
    assert_one_line_error(done.returncode, done.stderr, "stiffness needs damping")
    assert done.stdout == ""
