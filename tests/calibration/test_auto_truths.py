"""The hands-free calibration on the virtual Prime in virtual time (``virtual.lockstep``): random truths (offsets
within +-0.5 rad, any directions, the arms mirrored and not), the emulator's own device models, MuJoCo stepped in
lockstep with the controller manager.

Twenty truths, each calibrating two of the fourteen joints (every joint twice or more over the set) on a
robot whose other joints are calibrated already, and one truth calibrating all fourteen in one run from the bundled
calibration (every offset unknown, so the gravity model starts out wrong everywhere, as on a new robot). Moving a
joint through both stops and back at the speed cap takes robot minutes: all fourteen take about eight;
``PRIME_AUTO_ALL=1`` runs every truth on all fourteen joints (several minutes).
"""

from __future__ import annotations

import os
import random

import numpy as np
import pytest

from humanoid_prime.calibration.auto import contact_cap
from humanoid_prime.config.calibration import Calibration, JointCalibration, load_calibration
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.virtual.lockstep import calibrate_in_lockstep
from humanoid_prime.virtual.ring.drive import REALISED_EFFICIENCY

TRUTHS = 20
PER_TRUTH = 2
OFFSET_RANGE_RAD = 0.5
TOLERANCE_RAD = 1e-3
STIFFNESS_TOLERANCE = 0.05  # realised stiffness within 5 % of what the emulated drive models
ALL = os.environ.get("PRIME_AUTO_ALL") == "1"


def draw_truth(robot, seed: int, mirrored: bool) -> Calibration:
    """Every joint's wiring and factory offset at random; ``mirrored``: the right arm built as the left one's
    mirror image (same directions, an offset the mirror check expects: sign-flipped where the limits are)."""
    rng = random.Random(seed)
    joints = {j: JointCalibration(rng.choice((1, -1)), round(rng.uniform(-OFFSET_RANGE_RAD, OFFSET_RANGE_RAD), 5))
              for j in robot.names}
    if mirrored:
        for left in (j for j in robot.names if j.startswith("left_")):
            right = "right_" + left.removeprefix("left_")
            spec_l, spec_r = robot.joints[robot.index(left)], robot.joints[robot.index(right)]
            flips = (spec_l.lower, spec_l.upper) != (spec_r.lower, spec_r.upper)
            cal = joints[left]
            joints[right] = JointCalibration(cal.direction, -cal.homing_offset if flips else cal.homing_offset)
    return Calibration(joints)


def chosen_joints(robot, k: int) -> list[str]:
    if ALL:
        return list(robot.names)
    return [robot.names[(k + step * 5) % robot.n] for step in range(PER_TRUTH)]


@pytest.fixture  # per test, so that parallel workers can take the truths one by one
def setup(robot):
    return load_controllers(robot.names), load_calibration(robot.hardware)


FREE_RAD = 0.05  # a joint's contacts count from here on: before, a wrist may rest on a stop under its own weight


class ContactWatch:
    """Each joint's peak contact effort (the rig's truth: its actuator's push into a stop beyond gravity) during its
    own run, from the moment it has moved ``FREE_RAD`` from where it started."""

    def __init__(self) -> None:
        self.peaks: dict[str, float] = {}
        self._joint: str | None = None
        self._start = 0.0
        self._watching = False

    def __call__(self, rig, auto) -> None:
        moving = auto.moving.name if auto.moving is not None else None
        if moving != self._joint:
            if self._joint is not None and self._watching:
                self.peaks[self._joint] = max(self.peaks.get(self._joint, 0.0),
                                              float(rig.contact_peak[rig.robot.index(self._joint)]))
            self._joint, self._watching = moving, False
            if moving is not None:
                self._start = rig.true_state.position[rig.robot.index(moving)]
        if moving is not None and not self._watching:
            i = rig.robot.index(moving)
            if abs(rig.true_state.position[i] - self._start) > FREE_RAD:
                self._watching = True
                rig.contact_peak[i] = 0.0


def calibrate(robot, config, prior, truth, joints):
    watch = ContactWatch()
    result, rig = calibrate_in_lockstep(robot, config, prior, truth, joints, each_tick=watch)
    watch(rig, type("Done", (), {"moving": None})())
    return result, rig, watch.peaks


def check(robot, prior: Calibration, truth: Calibration, joints, result, rig, peaks) -> list[float]:
    """The assertions every run must meet; returns the offset errors (rad)."""
    assert result.aborted is None, result.aborted
    assert result.complete, {j: (o.status, o.message) for j, o in result.outcomes.items()}
    errors = []
    for joint in joints:
        outcome, true = result.outcomes[joint], truth.joints[joint]
        assert outcome.calibration.direction == true.direction, (joint, outcome.message)
        error = outcome.calibration.homing_offset - true.homing_offset
        assert abs(error) <= TOLERANCE_RAD, (joint, error)
        errors.append(abs(error))
        assert peaks[joint] <= contact_cap(robot, joint), (joint, peaks[joint])
        stiffness = outcome.stiffness
        expected = REALISED_EFFICIENCY if joint in robot.hardware.erob_slaves else 1.0  # the Sito realise it all
        assert stiffness.kp_ratio == pytest.approx(expected, rel=STIFFNESS_TOLERANCE), (joint, stiffness)
    assert all(int(drive.gate.value) == 0 for drive in rig.erob.values())  # every gate back on factory gains
    assert all(int(drive.max_torque.value) == 1500 for drive in rig.erob.values())  # every torque limit restored
    assert not any(motor.enabled for motor in rig.sito.values())  # every wrist off
    for joint in robot.names:
        if joint not in joints:
            assert result.calibration.joints[joint] == prior.joints[joint]  # not asked for: kept
    return errors


@pytest.mark.parametrize("k", range(TRUTHS))
def test_random_truths_are_recovered_within_a_milliradian(robot, setup, k):
    config, bundled = setup
    truth = draw_truth(robot, 3600 + k, mirrored=k % 2 == 0)
    joints = chosen_joints(robot, k)
    # The joints asked for start from the bundled file (offset 0, direction +1), the others are calibrated.
    prior = Calibration({j: bundled.joints[j] if j in joints else truth.joints[j] for j in robot.names})
    result, rig, peaks = calibrate(robot, config, prior, truth, joints)
    errors = check(robot, prior, truth, joints, result, rig, peaks)
    print(f"truth {k}: worst offset error {1e3 * max(errors):.4f} mrad over {', '.join(joints)}")


def test_all_fourteen_joints_in_one_run(robot, setup):
    """The default: every joint, distal to proximal, one run; the written calibration is the truth."""
    config, prior = setup
    truth = draw_truth(robot, 3700, mirrored=False)
    result, rig, peaks = calibrate(robot, config, prior, truth, robot.names)
    errors = check(robot, prior, truth, robot.names, result, rig, peaks)
    assert list(result.asked) == [  # arm by arm, from the hand to the shoulder
        "left_wrist_yaw", "left_wrist_pitch", "left_wrist_roll", "left_elbow_pitch", "left_shoulder_yaw",
        "left_shoulder_roll", "left_shoulder_pitch", "right_wrist_yaw", "right_wrist_pitch", "right_wrist_roll",
        "right_elbow_pitch", "right_shoulder_yaw", "right_shoulder_roll", "right_shoulder_pitch"]
    for joint in robot.names:
        assert result.calibration.joints[joint].direction == truth.joints[joint].direction
        assert np.isclose(result.calibration.joints[joint].homing_offset, truth.joints[joint].homing_offset,
                          atol=TOLERANCE_RAD)
    print(f"all fourteen: worst offset error {1e3 * max(errors):.4f} mrad, "
          f"{rig.sim_time:.0f} s of robot time")
