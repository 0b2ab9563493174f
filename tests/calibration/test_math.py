"""Calibration math: offsets from sweeps, statuses, flips without re-sweep, the mirror check (DESIGN §5)."""

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from humanoid_prime.calibration.math import (
    Status,
    SweepStats,
    calibrate_from_sweeps,
    flip_direction,
    mirror_check,
    offset_from_sweep,
    probable_flips,
)
from humanoid_prime.config.calibration import Calibration, JointCalibration, identity_calibration

ELBOW = (-2.356, 0.0)
WRIST_ROLL = (-0.698, 0.698)


def identity_sweep(lower: float, upper: float, direction: int, offset: float) -> SweepStats:
    """What a stop-to-stop sweep reads in the identity frame on a joint with this true calibration."""
    ends = [direction * (direction * q + offset) for q in (lower, upper)]  # direction * raw, raw = d*q + offset
    return SweepStats(min(ends), max(ends))


def test_offset_from_sweep_averages_both_stops():
    assert offset_from_sweep(-2.256, 0.1, *ELBOW, 1) == pytest.approx(0.1)


def test_offset_from_sweep_applies_direction():
    assert offset_from_sweep(-2.256, 0.1, *ELBOW, -1) == pytest.approx(-0.1)


@given(direction=st.sampled_from([1, -1]), offset=st.floats(-3.0, 3.0))
def test_sweep_recovers_the_true_offset(direction, offset):
    sweep = identity_sweep(*ELBOW, direction, offset)
    assert offset_from_sweep(sweep.min, sweep.max, *ELBOW, direction) == pytest.approx(offset, abs=1e-9)


def test_a_sweep_just_under_half_a_radian_keeps_the_prior_and_one_just_over_is_used(robot, prior):
    lower = ELBOW[0]
    for width, status in ((0.499, Status.SKIPPED), (0.501, Status.CALIBRATED)):
        _, reports = calibrate_from_sweeps({"left_elbow_pitch": SweepStats(lower, lower + width)}, prior, robot)
        assert next(r for r in reports if r.joint == "left_elbow_pitch").status is status


@pytest.fixture
def prior(robot) -> Calibration:
    cal = identity_calibration(robot.hardware)
    return cal.with_joint("left_wrist_roll", JointCalibration(1, 0.05))


def report_of(reports, joint):
    return next(r for r in reports if r.joint == joint)


def test_full_sweep_calibrates(robot, prior):
    cal, reports = calibrate_from_sweeps({"left_elbow_pitch": identity_sweep(*ELBOW, 1, 0.3)}, prior, robot)
    assert cal.joints["left_elbow_pitch"] == JointCalibration(1, pytest.approx(0.3))
    assert report_of(reports, "left_elbow_pitch").status is Status.CALIBRATED


def test_short_sweep_keeps_the_prior(robot, prior):
    cal, reports = calibrate_from_sweeps({"left_wrist_roll": (0.0, 0.49)}, prior, robot)
    assert cal.joints["left_wrist_roll"] == JointCalibration(1, 0.05)
    assert report_of(reports, "left_wrist_roll").status is Status.SKIPPED


def test_joint_without_samples_is_carried(robot, prior):
    cal, reports = calibrate_from_sweeps({}, prior, robot)
    assert cal == prior
    assert {r.status for r in reports} == {Status.CARRIED}
    assert len(reports) == 14


def test_tuple_sweeps_are_accepted(robot, prior):
    cal, _ = calibrate_from_sweeps({"left_elbow_pitch": (-2.256, 0.1)}, prior, robot)
    assert cal.joints["left_elbow_pitch"].homing_offset == pytest.approx(0.1)


def test_offset_over_pi_is_a_probable_flip(robot, prior):
    cal, reports = calibrate_from_sweeps({"left_wrist_roll": identity_sweep(*WRIST_ROLL, 1, 3.3)}, prior, robot)
    report = report_of(reports, "left_wrist_roll")
    assert report.status is Status.PROBABLE_FLIP
    assert cal.joints["left_wrist_roll"].homing_offset == pytest.approx(3.3)
    assert "prime calibration flip left_wrist_roll" in report.message


def test_sweep_missing_the_limits_is_a_probable_flip(robot, prior):
    # elbow wired backwards: true direction -1, swept with the prior +1, offset 0.1
    sweep = SweepStats(0.1, 0.1 + 2.356)
    _, reports = calibrate_from_sweeps({"left_elbow_pitch": sweep}, prior, robot)
    assert report_of(reports, "left_elbow_pitch").status is Status.PROBABLE_FLIP


def test_probable_flip_fixed_by_flip_without_resweep(robot, prior):
    true = JointCalibration(-1, 0.1)
    swept_with_wrong_direction = identity_sweep(*ELBOW, -1, 0.1)
    wrong = SweepStats(-swept_with_wrong_direction.max, -swept_with_wrong_direction.min)  # read with +1
    cal, _ = calibrate_from_sweeps({"left_elbow_pitch": wrong}, prior, robot)
    fixed = flip_direction(cal.joints["left_elbow_pitch"], *ELBOW)
    assert fixed.direction == true.direction
    assert fixed.homing_offset == pytest.approx(true.homing_offset)


def test_unknown_sweep_joint_is_refused(robot, prior):
    with pytest.raises(ValueError, match="waist_yaw"):
        calibrate_from_sweeps({"waist_yaw": (0.0, 1.0)}, prior, robot)


def test_non_finite_sweep_is_carried(robot, prior):
    _, reports = calibrate_from_sweeps({"left_elbow_pitch": (math.inf, -math.inf)}, prior, robot)
    assert report_of(reports, "left_elbow_pitch").status is Status.CARRIED


# flips ------------------------------------------------------------------------------------------------------

def test_flip_leaves_symmetric_joint_offset_unchanged():
    assert flip_direction(JointCalibration(1, 0.05), *WRIST_ROLL) == JointCalibration(-1, 0.05)


def test_flip_adds_lower_plus_upper_on_plus_one_to_minus_one():
    flipped = flip_direction(JointCalibration(1, 0.1), *ELBOW)
    assert flipped.direction == -1
    assert flipped.homing_offset == pytest.approx(0.1 + (-2.356 + 0.0))


def test_flip_twice_restores_the_calibration():
    cal = JointCalibration(1, 0.1)
    twice = flip_direction(flip_direction(cal, *ELBOW), *ELBOW)
    assert twice.direction == 1 and twice.homing_offset == pytest.approx(0.1)


@given(direction=st.sampled_from([1, -1]), offset=st.floats(-3.0, 3.0),
       lower=st.floats(-3.0, -0.1), upper=st.floats(0.0, 3.0))
def test_flip_equals_a_resweep_with_the_other_direction(direction, offset, lower, upper):
    sweep = identity_sweep(lower, upper, direction, offset)  # sampled with this direction
    flipped = flip_direction(JointCalibration(direction, offset), lower, upper)
    resweep = SweepStats(-sweep.max, -sweep.min)  # the same motion read with the other direction
    expected = offset_from_sweep(resweep.min, resweep.max, lower, upper, -direction)
    assert flipped.homing_offset == pytest.approx(expected, abs=1e-9)


def test_probable_flips_lists_offsets_over_pi(robot):
    cal = identity_calibration(robot.hardware).with_joint("right_elbow_pitch", JointCalibration(1, -3.2))
    assert probable_flips(cal) == ["right_elbow_pitch"]


# mirror check -----------------------------------------------------------------------------------------------

def test_mirror_check_pairs_every_joint(robot):
    rows = mirror_check(identity_calibration(robot.hardware), robot)
    assert [r.left for r in rows] == [n for n in robot.names if n.startswith("left_")]
    assert all(r.right == "right_" + r.left.removeprefix("left_") for r in rows)


def test_shoulder_roll_expects_opposite_offsets_others_equal(robot):
    rows = {r.left: r for r in mirror_check(identity_calibration(robot.hardware), robot)}
    assert rows["left_shoulder_roll"].relation == "opposite"
    assert {r.relation for n, r in rows.items() if n != "left_shoulder_roll"} == {"equal"}


def test_mirror_residual_of_sign_flipped_shoulder_roll_is_zero(robot):
    cal = (identity_calibration(robot.hardware)
           .with_joint("left_shoulder_roll", JointCalibration(1, 0.2))
           .with_joint("right_shoulder_roll", JointCalibration(1, -0.2)))
    row = next(r for r in mirror_check(cal, robot) if r.left == "left_shoulder_roll")
    assert row.residual == pytest.approx(0.0) and row.ok


def test_mirror_residual_flags_unequal_elbows(robot):
    cal = identity_calibration(robot.hardware).with_joint("left_elbow_pitch", JointCalibration(1, 0.3))
    row = next(r for r in mirror_check(cal, robot) if r.left == "left_elbow_pitch")
    assert row.residual == pytest.approx(0.3) and not row.ok
