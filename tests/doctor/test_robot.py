"""The robot's checks: its files loaded as every command loads them, a calibration that is a robot's, directions
as the eRob configs carry them, and the last run's summary."""

from __future__ import annotations

import json
import random

import pytest

from humanoid_prime.config.calibration import VIRTUAL_MARK, Calibration, JointCalibration, save_calibration
from humanoid_prime.config.location import resolve_all
from humanoid_prime.doctor import robot as doctor_robot
from humanoid_prime.doctor.report import Verdict
from humanoid_prime.drivers.ethercat.fold import write_folded_configs
from humanoid_prime.errors import PrimeError
from humanoid_prime.files import bundled


@pytest.fixture
def calibrated(robot, tmp_path):
    """A robot's calibration: measured offsets, two joints wired backwards."""
    rng = random.Random(44)
    cal = Calibration({j: JointCalibration(-1 if j in ("left_shoulder_roll", "right_wrist_yaw") else 1,
                                           round(rng.uniform(-0.5, 0.5), 5)) for j in robot.names})
    path = tmp_path / "prime_calibration.yaml"
    save_calibration(path, cal, robot.hardware)
    return Calibration(cal.joints, path)


def by_name(checks):
    return {c.name: c for c in checks}


def test_the_bundled_identity_template_fails_with_how_to_calibrate(robot):
    files = resolve_all()
    check = doctor_robot.calibration_check(
        Calibration({j: JointCalibration() for j in robot.names}, files.calibration.path), files.calibration)
    assert files.calibration.template and check.verdict is Verdict.FAIL
    assert check.found.startswith("the bundled identity template")
    assert check.fix == "prime calibrate --auto (hands-free), or prime calibrate (by hand)"


def test_a_copy_of_the_identity_in_the_robot_s_folder_fails_too(robot, tmp_path):
    path = tmp_path / "prime_calibration.yaml"
    path.write_bytes(bundled("prime_calibration.yaml").read_bytes())
    files = resolve_all(calibration=path)
    checks = by_name(doctor_robot.robot_checks(files)[0])
    assert checks["calibration_file"].verdict is Verdict.PASS  # a valid file...
    assert checks["calibration"].verdict is Verdict.FAIL  # ...that calibrates nothing
    assert "every homing_offset is 0" in checks["calibration"].found


def test_a_robot_s_calibration_passes_and_one_a_virtual_run_wrote_warns(robot, calibrated, tmp_path):
    files = resolve_all(calibration=calibrated.path)
    check = doctor_robot.calibration_check(calibrated, files.calibration)
    assert check.verdict is Verdict.PASS and "2 with direction -1" in check.found
    save_calibration(calibrated.path, calibrated, robot.hardware, comment=VIRTUAL_MARK)
    assert doctor_robot.calibration_check(calibrated, files.calibration).verdict is Verdict.WARN


def test_a_file_that_does_not_load_fails_with_its_own_error(tmp_path):
    broken = tmp_path / "prime_controllers.yaml"
    broken.write_text("controller_manager: [")
    checks = by_name(doctor_robot.robot_checks(resolve_all(controllers=broken))[0])
    assert checks["controllers"].verdict is Verdict.FAIL and str(broken) in checks["controllers"].found
    assert checks["hardware"].verdict is Verdict.WARN  # the bundled template: loads, but is no robot's


def test_every_file_is_named_with_its_sha256(calibrated):
    files = resolve_all(calibration=calibrated.path)
    check = by_name(doctor_robot.robot_checks(files)[0])["calibration_file"]
    assert check.found == f"{calibrated.path} (--calibration), sha256 {files.calibration.sha256()[:16]}"


def test_directions_fold_into_the_erob_configs_and_name_the_reversed_joints(robot, calibrated):
    check = doctor_robot.directions_check(robot, calibrated)
    assert check.verdict is Verdict.PASS
    assert "direction -1: left_shoulder_roll, right_wrist_yaw" in check.found


def test_folded_configs_from_another_calibration_fail_with_the_fold_command(robot, calibrated, tmp_path):
    folded = tmp_path / "erob"
    write_folded_configs(robot, calibrated, folded)
    assert doctor_robot.directions_check(robot, calibrated, folded).verdict is Verdict.PASS
    flipped = calibrated.with_joint("left_elbow_pitch", JointCalibration(-1, 0.1))
    check = doctor_robot.directions_check(robot, flipped, folded)
    assert check.verdict is Verdict.FAIL
    assert "left_elbow_pitch folded with direction +1" in check.found and "the calibration says -1" in check.found
    assert check.fix == f"prime calibration fold --output {folded}"


def test_an_offset_past_half_a_turn_warns_as_a_probable_flip(robot, calibrated):
    check = doctor_robot.directions_check(robot, calibrated.with_joint("left_elbow_pitch", JointCalibration(1, 3.5)))
    assert check.verdict is Verdict.WARN and check.fix == "prime calibration flip left_elbow_pitch, or sweep it again"


def test_the_last_run_s_problems_and_changed_files_are_named(calibrated, tmp_path):
    files = resolve_all(calibration=calibrated.path)
    summary_path = tmp_path / "summary.json"
    summary_path.write_text(json.dumps({
        "ok": False, "problems": ["1 of 4 Sito wrists silent at the end"],
        "faults": [{"key": "sito/rx_timeout/left_wrist_pitch", "text": "no feedback for 100 ms"}],
        "config": {"calibration": {"path": str(calibrated.path), "sha256": "0" * 64}}}))
    check = doctor_robot.last_run_check(summary_path, doctor_robot.read_summary(summary_path), files)
    assert check.verdict is Verdict.WARN
    assert "not ok; flagged sito/rx_timeout/left_wrist_pitch: no feedback for 100 ms" in check.found
    assert "files changed since: calibration" in check.found
    assert "problems: 1 of 4 Sito wrists silent at the end" in check.found


def test_a_file_that_is_no_run_summary_is_refused_in_one_line(tmp_path):
    path = tmp_path / "notes.json"
    path.write_text('{"hello": 1}')
    with pytest.raises(PrimeError, match="is no run summary"):
        doctor_robot.read_summary(path)
