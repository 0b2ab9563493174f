"""The hands-free calibration on the virtual Prime in virtual time (``virtual.lockstep``): twenty random truths
(offsets within +-0.5 rad, any directions, the arms mirrored and not), all fourteen joints each run, the emulator's
own device models, MuJoCo stepped in lockstep with the controller manager; once from the bundled calibration (a new
robot: every offset unknown, so the gravity model starts out wrong everywhere) and once with a prior calibration
(the truth within 20 mrad: a recalibration).

Every run: complete, every direction right, every offset within a milliradian, every joint's peak contact effort
(the rig's truth: its actuator's push into a stop beyond gravity) within its cap and its speed when it met a stop
at most the contact speed, no arm touching the other or the body, every drive back on its factory gains and torque
limit, every wrist off; within its robot-time budget. Each run's robot and wall time are printed (``-s``).
"""

from __future__ import annotations

import functools
import os
import random
import time

import pytest

from humanoid_prime.calibration.approach import MAX_SPEED_RAD_S
from humanoid_prime.calibration.auto import contact_cap
from humanoid_prime.config.calibration import Calibration, JointCalibration, load_calibration
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.config.robot import load_robot
from humanoid_prime.virtual.lockstep import calibrate_in_lockstep
from humanoid_prime.virtual.ring.drive import REALISED_EFFICIENCY

TRUTHS = 20
# A new robot's run costs ~25 s of CPU against a recalibration's ~7 s: make test runs the twenty recalibrations
# and the first five new robots (mirrored and not); PRIME_AUTO_ALL=1 runs all twenty new robots as well.
NEW_IN_SUITE = TRUTHS if os.environ.get("PRIME_AUTO_ALL") == "1" else 5
OFFSET_RANGE_RAD = 0.5
PRIOR_ERROR_RAD = 0.02
TOLERANCE_RAD = 1e-3
STIFFNESS_TOLERANCE = 0.05  # realised stiffness within 5 % of what the emulated drive models
NEW_ROBOT_S = 220.0  # robot time a run from the bundled calibration takes at most (first stops one joint at a time)
PRIOR_S = 60.0  # robot time a recalibration takes at most (one joint of each arm at a time)
FREE_RAD = 0.05  # a joint's contacts count from here on: before, a wrist may rest on a stop under its own weight


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


def near(truth: Calibration, seed: int) -> Calibration:
    """A robot's earlier calibration: the truth's directions, each offset within ``PRIOR_ERROR_RAD``."""
    rng = random.Random(seed)
    return Calibration({j: JointCalibration(c.direction, round(c.homing_offset + rng.uniform(
        -PRIOR_ERROR_RAD, PRIOR_ERROR_RAD), 5)) for j, c in truth.joints.items()})


class ContactWatch:
    """Each joint's peak contact effort and the speed it met a stop at (the rig's truths) while it moves, from the
    moment it has moved ``FREE_RAD`` from where it started."""

    def __init__(self) -> None:
        self.blind_pairs = 0  # ticks in which both arms moved while a moving joint's arm could not be placed
        self.peaks: dict[str, float] = {}
        self.speeds: dict[str, float] = {}
        self._start: dict[str, float] = {}
        self._watching: set[str] = set()

    def __call__(self, rig, auto) -> None:
        moving = {run.name for run in auto.moving}
        arms = {joint.split("_", 1)[0] for joint in moving}
        if len(arms) > 1 and any(j not in auto.firsts and not auto.robots_prior[j] for j in moving):
            self.blind_pairs += 1
        for joint in [j for j in self._start if j not in moving]:
            self._collect(rig, joint)
        for joint in moving:
            i = rig.robot.index(joint)
            q = float(rig.true_state.position[i])
            self._start.setdefault(joint, q)
            if joint not in self._watching and abs(q - self._start[joint]) > FREE_RAD:
                self._watching.add(joint)
                rig.contact_peak[i] = rig.touch_speed[i] = 0.0

    def _collect(self, rig, joint: str) -> None:
        if joint in self._watching:
            i = rig.robot.index(joint)
            self.peaks[joint] = max(self.peaks.get(joint, 0.0), float(rig.contact_peak[i]))
            self.speeds[joint] = max(self.speeds.get(joint, 0.0), float(rig.touch_speed[i]))
        del self._start[joint]
        self._watching.discard(joint)

    def finish(self, rig) -> None:
        for joint in list(self._start):
            self._collect(rig, joint)


@functools.cache
def run(kind: str, k: int):
    """Truth ``k`` calibrated on all fourteen joints, from the bundled calibration (``new``) or a prior (``prior``):
    (truth, result, rig, watch, wall seconds)."""
    robot = load_robot()
    config, bundled = load_controllers(robot.names), load_calibration(robot.hardware)
    truth = draw_truth(robot, 3600 + k, mirrored=k % 2 == 0)
    prior = bundled if kind == "new" else near(truth, 9000 + k)
    watch = ContactWatch()
    began = time.monotonic()
    result, rig = calibrate_in_lockstep(robot, config, prior, truth, robot.names, each_tick=watch)
    watch.finish(rig)
    return truth, result, rig, watch, time.monotonic() - began


def check(robot, kind: str, k: int, budget_s: float) -> None:
    truth, result, rig, watch, wall = run(kind, k)
    assert result.aborted is None, result.aborted
    assert result.complete, {j: (o.status, o.message) for j, o in result.outcomes.items() if not o.done}
    errors = []
    for joint in robot.names:
        outcome, true = result.outcomes[joint], truth.joints[joint]
        assert outcome.calibration.direction == true.direction, (joint, outcome.message)
        errors.append(abs(outcome.calibration.homing_offset - true.homing_offset))
        assert errors[-1] <= TOLERANCE_RAD, (joint, errors[-1])
        assert watch.peaks[joint] <= contact_cap(robot, joint), (joint, watch.peaks[joint])
        assert watch.speeds[joint] <= MAX_SPEED_RAD_S, (joint, watch.speeds[joint])
        assert outcome.stiffness is None  # no pushes unless asked for
    assert all(int(drive.gate.value) == 0 for drive in rig.erob.values())  # every gate back on factory gains
    assert all(int(drive.max_torque.value) == 1500 for drive in rig.erob.values())  # every torque limit restored
    assert not any(motor.enabled for motor in rig.sito.values())  # every wrist off
    assert rig.body_contacts == {}  # no arm ever touched the other arm or the body
    assert watch.blind_pairs == 0  # both arms moved only once every moving joint's first stop had placed its arm
    print(f"{kind} truth {k}: {result.robot_seconds:.1f} s robot time, {wall:.1f} s wall; worst offset error "
          f"{1e3 * max(errors):.4f} mrad, fastest contact {max(watch.speeds.values()):.3f} rad/s")
    assert result.robot_seconds <= budget_s


@pytest.mark.parametrize("k", range(NEW_IN_SUITE))
def test_a_new_robot_is_calibrated_on_all_fourteen_joints(robot, k):
    check(robot, "new", k, NEW_ROBOT_S)


@pytest.mark.parametrize("k", range(TRUTHS))
def test_a_recalibration_searches_near_the_prior_one_joint_of_each_arm_at_a_time(robot, k):
    check(robot, "prior", k, PRIOR_S)
    result = run("prior", k)[1]
    together = [what for what, _, _ in result.timeline if " and " in what]
    assert together  # both arms moved at once where the body check cleared them


def test_the_run_is_distal_first_and_its_time_is_reported_by_what_it_went_to(robot):
    result = run("new", 0)[1]
    assert list(result.asked) == [  # arm by arm, from the hand to the shoulder
        "left_wrist_yaw", "left_wrist_pitch", "left_wrist_roll", "left_elbow_pitch", "left_shoulder_yaw",
        "left_shoulder_roll", "left_shoulder_pitch", "right_wrist_yaw", "right_wrist_pitch", "right_wrist_roll",
        "right_elbow_pitch", "right_shoulder_yaw", "right_shoulder_roll", "right_shoulder_pitch"]
    firsts = [what.removesuffix(": first stop") for what, _, _ in result.timeline if what.endswith("first stop")]
    assert firsts == list(result.asked)  # a new robot's first stops, one joint at a time, before any second one
    seconds = [what for what, _, _ in result.timeline[len(firsts) + 1:]]
    assert any(" and " in what for what in seconds)  # then both arms at once where their arms' reaches keep apart
    report = result.as_dict()
    assert report["robot_seconds"] == result.robot_seconds > 0 and report["wall_seconds"] > 0
    kinds = report["joint_seconds_by_kind"]
    assert kinds["travel"] > 0 and kinds["search"] > 0 and kinds["settle"] > 0 and kinds["push"] == 0
    for joint in robot.names:
        outcome = result.outcomes[joint]
        assert sum(outcome.times.values()) == pytest.approx(outcome.seconds, abs=0.1)


def test_the_stiffness_pushes_measure_the_realised_impedance_when_asked(robot):
    config, bundled = load_controllers(robot.names), load_calibration(robot.hardware)
    truth = draw_truth(robot, 3700, mirrored=False)
    joints = ["left_elbow_pitch", "right_wrist_roll"]
    prior = Calibration({j: bundled.joints[j] if j in joints else truth.joints[j] for j in robot.names})
    result, _ = calibrate_in_lockstep(robot, config, prior, truth, joints, measure=True)
    assert result.complete
    for joint in joints:
        outcome = result.outcomes[joint]
        expected = REALISED_EFFICIENCY if joint in robot.hardware.erob_slaves else 1.0  # the Sito realise it all
        assert outcome.stiffness.kp_ratio == pytest.approx(expected, rel=STIFFNESS_TOLERANCE), (joint, outcome)
        assert outcome.times["push"] > 0
