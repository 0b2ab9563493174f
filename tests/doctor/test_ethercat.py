"""The EtherCAT checks on what the drives said of themselves: identities by ring position, firmware revisions
against the tested list, the rated torque against the model the hardware file says, errors now and in history, AL
status codes left set, DC. The reads themselves are exercised against the virtual Prime (tests/cli)."""

from __future__ import annotations

from dataclasses import replace

import pytest

from humanoid_prime.doctor import ethercat
from humanoid_prime.doctor.ethercat import DriveReading
from humanoid_prime.doctor.report import Verdict
from humanoid_prime.drivers.erob.constants import PRODUCT_CODE, VENDOR_ID
from humanoid_prime.drivers.erob.tested import TESTED_REVISIONS
from humanoid_prime.drivers.ethercat.ring import SlaveInfo, expected_ring
from humanoid_prime.drivers.ethercat.wire import AL_ERROR, AlState
from humanoid_prime.errors import PrimeError


@pytest.fixture
def expected(robot):
    return expected_ring(robot.hardware.erob_slaves)


@pytest.fixture
def found(expected):
    return [SlaveInfo(e.position, "ZeroErr Driver", VENDOR_ID, PRODUCT_CODE, 0x00000001, AlState.PRE_OP)
            for e in expected]


@pytest.fixture
def readings(found, expected):
    return [DriveReading(s, e.joint, dc=True, software="V1.2", rated_torque_nm=23.0, error_code=0, statusword=0x0250,
                         history=[]) for s, e in zip(found, expected, strict=True)]


def test_the_revision_eRob_ships_with_is_the_one_prime_is_tested_with():
    assert 0x00000001 in TESTED_REVISIONS


def test_a_healthy_ring_passes_every_drive_check(robot, found, expected, readings):
    checks = [ethercat.scan_check(found, expected, "enp3s0"),
              ethercat.identity_check(found, expected, "enp3s0", "prime_hardware.yaml"),
              ethercat.revision_check(readings), ethercat.al_status_check(found), ethercat.dc_check(readings),
              ethercat.rated_torque_check(readings, robot.hardware), ethercat.errors_check(readings),
              ethercat.history_check(readings)]
    assert [c.verdict for c in checks] == [Verdict.PASS] * len(checks)


def test_a_missing_slave_fails_the_count(found, expected):
    check = ethercat.scan_check(found[:9], expected, "enp3s0")
    assert check.verdict is Verdict.FAIL and check.found == "9 slaves on enp3s0, in PRE-OP; the hardware file places 10"


def test_another_device_at_a_ring_position_fails_naming_position_joint_and_the_file(found, expected):
    found[3] = replace(found[3], name="EK1100", vendor_id=0x2, product_code=0x044C2C52)
    check = ethercat.identity_check(found, expected, "enp3s0", "/robot/prime_hardware.yaml")
    assert check.verdict is Verdict.FAIL
    assert "ring 3: expected left_elbow_pitch (eRob vendor 0x5A65726F product 0x00029252), found 'EK1100'" \
        in check.found
    assert check.fix == "fix the cabling order, or joints.erob_slaves in /robot/prime_hardware.yaml"


def test_a_revision_not_in_the_tested_list_warns_naming_the_drives(readings):
    readings[6] = replace(readings[6], slave=replace(readings[6].slave, revision=0x00000002))
    check = ethercat.revision_check(readings)
    assert check.verdict is Verdict.WARN
    assert check.found.startswith("ring 6 (right_shoulder_roll): revision 0x00000002, not one Prime is tested with "
                                  "(0x00000001, drivers/erob/tested.py)")
    assert "ZeroErr's tool" in check.fix


def test_a_rated_torque_of_another_model_fails_naming_both(robot, readings):
    readings[2] = replace(readings[2], rated_torque_nm=31.0)
    check = ethercat.rated_torque_check(readings, robot.hardware)
    assert check.verdict is Verdict.FAIL
    assert check.found == ("ring 2 (left_shoulder_yaw): reads 31 N*m, what an eRob80H120I reports; the hardware file's "
                           "Kt 0.000132 N*m/mA, gear 50 (joints.erob_kt/erob_gear) is an eRob70 50:1, which reports 23")
    assert "joints.erob_kt and joints.erob_gear" in check.fix


def test_a_rated_torque_that_is_not_the_file_s_model_s_fails_and_one_unknown_or_unread_warns(robot, readings):
    readings[0] = replace(readings[0], rated_torque_nm=40.0)
    assert ethercat.rated_torque_check(readings, robot.hardware).verdict is Verdict.FAIL
    erob80 = replace(robot.hardware, erob_kt={**robot.hardware.erob_kt, readings[0].joint: 0.134e-3})
    check = ethercat.rated_torque_check(readings, erob80)
    assert check.verdict is Verdict.WARN and "no tested model has Kt 0.000134 N*m/mA, gear 50" in check.found
    readings[0] = replace(readings[0], rated_torque_nm=None, rated_problem="aborted 0x06020000")
    check = ethercat.rated_torque_check(readings, robot.hardware)
    assert check.verdict is Verdict.WARN and "aborted 0x06020000" in check.found


def test_a_drive_in_fault_fails_with_its_code_in_words(readings):
    readings[4] = replace(readings[4], error_code=0x8500, statusword=0x0208)
    check = ethercat.errors_check(readings)
    assert check.verdict is Verdict.FAIL
    assert check.found.startswith("ring 4 (left_wrist_yaw) error 0x8500")
    assert "prime reset" in check.fix


def test_errors_in_a_drive_s_history_warn_newest_first_with_how_to_clear_them(readings):
    readings[5] = replace(readings[5], history=[0xA000, 0x730F])
    check = ethercat.history_check(readings)
    assert check.verdict is Verdict.WARN
    assert "ring 5 (right_shoulder_pitch) 0xA000" in check.found and ", 0x730F" in check.found
    assert "prime ec sdo write 5 0x1003:0 0" in check.fix


def test_an_al_error_fails_and_a_code_left_set_warns(found):
    found[1] = replace(found[1], al_state=AlState.SAFE_OP | AL_ERROR, al_status_code=0x001B)
    assert ethercat.al_status_check(found).verdict is Verdict.FAIL
    found[1] = replace(found[1], al_state=AlState.PRE_OP, al_status_code=0x001B)
    check = ethercat.al_status_check(found)
    assert check.verdict is Verdict.WARN and "ring 1 0x001B" in check.found


def test_a_drive_without_a_distributed_clock_fails(readings):
    readings[8] = replace(readings[8], dc=False)
    assert ethercat.dc_check(readings).verdict is Verdict.FAIL


def test_the_doctor_s_sdo_client_writes_nothing():
    with pytest.raises(PrimeError, match="writes to no drive"):
        ethercat.PreopSdo(registers=None).sdo_write(0, 0x2383, 0, b"\x01")  # type: ignore[arg-type]


def test_the_mailbox_line_names_the_layer_the_hardware_file_chooses(robot):
    assert ethercat.mailbox_check(robot.hardware).verdict is Verdict.PASS
    soem = replace(robot.hardware, ethercat=replace(robot.hardware.ethercat, mailbox="soem"))
    check = ethercat.mailbox_check(soem)
    assert check.verdict is Verdict.WARN
    assert "SOEM does the mailbox work alone (buses.ethercat.mailbox: soem" in check.found
    assert "remove buses.ethercat.mailbox" in check.fix
