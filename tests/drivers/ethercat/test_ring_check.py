"""The ring must hold the hardware file's eRob at the hardware file's ring positions, or fail with one error."""

from __future__ import annotations

import pytest

from doubles.master import FakeMaster, erob_ring
from humanoid_prime.drivers.ethercat.errors import RingError
from humanoid_prime.drivers.ethercat.ring import SlaveInfo, check_ring, expected_ring


def test_the_bundled_ring_expects_ten_erob_with_wrist_yaw_at_positions_4_and_9(robot):
    expected = expected_ring(robot.hardware.erob_slaves)
    assert [e.position for e in expected] == list(range(10))
    assert expected[4].joint == "left_wrist_yaw"
    assert expected[9].joint == "right_wrist_yaw"
    assert {(e.vendor_id, e.product_code) for e in expected} == {(0x5A65726F, 0x00029252)}


def test_a_matching_ring_passes(robot):
    check_ring(erob_ring(10), expected_ring(robot.hardware.erob_slaves), "eth0")


def test_a_foreign_slave_is_named_with_found_and_expected_identity(robot):
    found = erob_ring(10)
    found[3] = SlaveInfo(3, "EK1100", 0x00000002, 0x044C2C52)
    with pytest.raises(RingError) as err:
        check_ring(found, expected_ring(robot.hardware.erob_slaves), "eth0")
    text = str(err.value)
    assert "ring 3: expected left_elbow_pitch (eRob vendor 0x5A65726F product 0x00029252), " \
           "found 'EK1100' (vendor 0x00000002 product 0x044C2C52)" in text
    assert "(found ring: 0-2 'eRob' (eRob vendor 0x5A65726F product 0x00029252), 3 'EK1100' (vendor 0x00000002 " \
           "product 0x044C2C52), 4-9 'eRob' (eRob vendor 0x5A65726F product 0x00029252))" in text
    assert "eth0" in text and "joints.erob_slaves" in text
    assert "\n" not in text


def test_a_missing_slave_lists_every_position_that_is_empty(robot):
    with pytest.raises(RingError) as err:
        check_ring(erob_ring(8), expected_ring(robot.hardware.erob_slaves), "eth0")
    text = str(err.value)
    assert "found 8 slaves, expected 10" in text
    assert "ring 8: expected right_elbow_pitch" in text and "ring 9: expected right_wrist_yaw" in text
    assert "found nothing" in text


def test_an_extra_slave_is_a_mismatch(robot):
    with pytest.raises(RingError, match="ring 10: found 'eRob' .* expected no slave"):
        check_ring(erob_ring(11), expected_ring(robot.hardware.erob_slaves), "eth0")


def test_start_refuses_a_mismatched_ring_before_touching_it(robot):
    found = erob_ring(10)
    found[0] = SlaveInfo(0, "other", 0x1, 0x2)
    master = FakeMaster(found)
    with pytest.raises(RingError, match="ring 0: expected left_shoulder_pitch"):
        master.start(expected_ring(robot.hardware.erob_slaves))
    assert master.frames == 0
