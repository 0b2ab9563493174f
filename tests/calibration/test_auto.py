"""The hands-free calibration's parts, each against its specification: the contact-effort cap and the approach
gains that keep a contact under it, contact as three signs together (never one sample), direction from the
limits and from gravity, the plain question's view, and the stops, faults and key presses of a run."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from humanoid_prime.calibration import approach
from humanoid_prime.calibration.approach import CAP_SHARE, MAX_SPEED_RAD_S, approach_gains
from humanoid_prime.calibration.auto import CONTACT_FRACTION, contact_cap, distal_first
from humanoid_prime.calibration.direction import direction_from_gravity, direction_from_limits, view_of
from humanoid_prime.calibration.journal import OverrideJournal
from humanoid_prime.config.calibration import Calibration, JointCalibration, load_calibration
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.config.hardware import load_hardware
from humanoid_prime.config.robot import load_robot
from humanoid_prime.drivers.sito.protocol import counts_to_velocity
from humanoid_prime.errors import ConfigError
from humanoid_prime.files import bundled
from humanoid_prime.virtual.lockstep import calibrate_in_lockstep
from humanoid_prime.virtual.ring.drive import FACTORY_INTEGRAL, FACTORY_POS_REG, FACTORY_VEL_REG


def test_the_default_cap_is_a_tenth_of_the_effort_limit(robot):
    assert contact_cap(robot, "left_shoulder_pitch") == pytest.approx(CONTACT_FRACTION * 30.0)
    assert contact_cap(robot, "left_wrist_roll") == pytest.approx(CONTACT_FRACTION * 4.8)


def test_a_cap_from_the_hardware_file_is_used_and_one_above_the_effort_limit_is_refused(tmp_path):
    text = bundled("prime_hardware.yaml").read_text().replace(
        "contact_effort_cap: {}", "contact_effort_cap: {left_elbow_pitch: 2.0, left_wrist_yaw: 11.0}")
    path = tmp_path / "prime_hardware.yaml"
    path.write_text(text)
    robot = load_robot(path)
    assert contact_cap(robot, "left_elbow_pitch") == 2.0
    with pytest.raises(ConfigError, match=r"contact_effort_cap\.left_wrist_yaw.*above the joint's effort limit"):
        contact_cap(robot, "left_wrist_yaw")


@pytest.mark.parametrize("cap", [0.48, 1.0, 3.0])
def test_the_leash_and_stopping_the_motion_spend_no_more_than_the_cap_share(cap):
    kp, kd = approach_gains(cap)
    leash = (CAP_SHARE * cap - kd * MAX_SPEED_RAD_S) / kp
    assert leash > 0
    assert kp * leash + kd * MAX_SPEED_RAD_S == pytest.approx(CAP_SHARE * cap)


def test_joints_go_arm_by_arm_from_the_hand_to_the_shoulder(robot):
    order = distal_first(robot, ["right_shoulder_pitch", "left_elbow_pitch", "left_wrist_yaw", "right_wrist_roll"])
    assert order == ["left_wrist_yaw", "left_elbow_pitch", "right_wrist_roll", "right_shoulder_pitch"]


def _stops(spec, cal: JointCalibration, prior_direction: int = 1) -> tuple[float, float]:
    """Where the two stops read in the host frame (the prior's direction, offset 0) for a true calibration."""
    readings = [prior_direction * (cal.direction * q + cal.homing_offset) for q in (spec.lower, spec.upper)]
    return min(readings), max(readings)


@pytest.mark.parametrize("truth_direction", [1, -1])
@pytest.mark.parametrize("joint", ["left_shoulder_pitch", "left_elbow_pitch"])
def test_an_asymmetric_range_tells_the_direction(robot, joint, truth_direction):
    spec = robot.joints[robot.index(joint)]
    truth = JointCalibration(truth_direction, 0.37)
    same, flipped, verdict = direction_from_limits(1, _stops(spec, truth), spec)
    assert verdict == truth_direction
    chosen = same if verdict == 1 else flipped
    assert chosen.direction == truth.direction
    assert chosen.homing_offset == pytest.approx(truth.homing_offset, abs=1e-12)


def test_a_symmetric_range_cannot_tell_and_gives_one_offset_either_way(robot):
    spec = robot.joints[robot.index("left_wrist_yaw")]
    same, flipped, verdict = direction_from_limits(1, _stops(spec, JointCalibration(-1, 0.2)), spec)
    assert verdict is None
    assert same.homing_offset == pytest.approx(flipped.homing_offset) == pytest.approx(0.2)


def test_an_implausible_offset_either_way_is_not_a_verdict(robot):
    spec = robot.joints[robot.index("left_elbow_pitch")]  # lower + upper = -2.356
    stops = (-1.178 - 1.178 + 1.178, 1.178)  # centred so both offsets are about half the asymmetry
    assert direction_from_limits(1, stops, spec)[2] is None


def test_gravity_picks_the_direction_whose_curve_fits_and_refuses_when_the_curves_agree():
    q = np.linspace(-1.5, 1.8, 60)
    measured = -6.0 * np.sin(q - 0.1) + 0.2  # the true load plus friction
    predicted = {1: -6.0 * np.sin(q - 0.1), -1: -6.0 * np.sin(q - 0.1 - 0.349)}
    assert direction_from_gravity(q, measured, predicted)[0] == 1
    assert direction_from_gravity(q, measured, {1: predicted[-1], -1: predicted[1]})[0] == -1
    same = {1: predicted[1], -1: predicted[1] + 0.5}  # an offset only: friction could be it
    assert direction_from_gravity(q, measured, same)[0] is None


def test_the_question_is_asked_along_the_nearest_world_axis_looking_at_its_tip():
    view, where = view_of(np.array([0.1, -0.9, 0.3]))
    assert view.tolist() == [0.0, -1.0, 0.0]
    assert where == "at the robot's right side"
    assert view_of(np.array([0.0, 0.2, 0.95]))[1] == "above the robot"


def _tick(q: float, qd: float, effort: float, t: float = 0.0) -> approach.Tick:
    return approach.Tick(t, 0.02, q, qd, effort, 0.0)


def _run(cap: float = 3.0) -> approach.JointRun:
    gains = approach_gains(cap)
    return approach.JointRun(0, "j", cap=cap, gains=gains, leash_gains=gains, speed=MAX_SPEED_RAD_S, rate=50.0,
                          effort_limit=30.0)


def test_contact_needs_every_sign_for_the_debounce_time_never_one_sample():
    run = _run()
    detector = approach.ContactDetector(run, 1)
    detector.start(_tick(0.0, 0.2, 0.0), 0.0)
    lag, push = run.leash, 0.5 * run.cap
    assert not detector.update(_tick(0.0, 0.0, push), lag, free=False)  # one sample: not yet
    assert not detector.update(_tick(0.0, 0.0, push), lag, free=False)
    assert not detector.update(_tick(0.0, 0.2, push), lag, free=False)  # it moved again: counting restarts
    hits = [detector.update(_tick(0.0, 0.0, push), lag, free=False) for _ in range(detector.needed)]
    assert hits[-1] and not any(hits[:-1])


@pytest.mark.parametrize("missing", ["lag", "motion", "effort"])
def test_two_signs_of_three_are_no_contact(missing):
    run = _run()
    detector = approach.ContactDetector(run, 1)
    detector.start(_tick(0.0, 0.2, 0.0), 0.0)
    lag = 0.0 if missing == "lag" else run.leash
    qd = run.speed if missing == "motion" else 0.0
    effort = 0.0 if missing == "effort" else 0.5 * run.cap
    assert not any(detector.update(_tick(0.0, qd, effort), lag, free=False) for _ in range(20))


def test_a_stop_met_at_the_travel_speed_is_seen_with_that_speed_and_a_stall_it_moved_on_from_is_forgotten():
    run = _run()
    detector = approach.ContactDetector(run, 1)
    detector.start(_tick(0.0, 1.0, 0.0), 0.0)
    detector.update(_tick(0.0, 1.0, 0.0, t=0.0), 0.0, free=True, speed=1.0, accel=-1.0)  # the target slows down
    detector.update(_tick(0.0, 0.0, 0.0, t=0.02), 0.0, free=True)  # and the joint stopped at 1 rad/s
    assert detector.stalled_at == pytest.approx(1.0)
    for k in range(10):  # it moved on: no stop held it
        detector.update(_tick(0.0, 0.17, 0.0, t=0.5 + 0.02 * k), 0.0, free=True, speed=0.17)
    push = 0.5 * run.cap
    k = 0
    while not detector.update(_tick(0.0, 0.0, push, t=0.7 + 0.02 * k), run.leash, free=False):
        k += 1
        assert k < 10
    assert detector.impact == pytest.approx(0.17)  # the stop met later, at the speed it came in at


def test_the_leash_holds_the_target_to_the_baseline_lag_plus_the_leash():
    run = _run()
    detector = approach.ContactDetector(run, -1)
    detector.start(_tick(1.0, 0.0, 0.0), 1.0)
    assert detector.leash(_tick(1.0, 0.0, 0.0), 0.5) == pytest.approx(1.0 - run.leash)
    assert detector.leash(_tick(1.0, 0.0, 0.0), 0.99) == 0.99


# ---- runs in virtual time: faults, key presses and pushes stop everything, restored ---------------------------

@pytest.fixture(scope="module")
def setup(robot):
    truth = Calibration({j: JointCalibration(1, 0.1) for j in robot.names}).with_joint(
        "left_elbow_pitch", JointCalibration(-1, -0.2))
    return load_controllers(robot.names), load_calibration(robot.hardware), truth


def _moving(auto_run, joint: str):
    return next((run for run in auto_run.moving if run.name == joint), None)


def _approaching(auto_run, joint: str, past_rad: float = 0.2) -> bool:
    moving = _moving(auto_run, joint)
    segment = moving.segment if moving is not None else None
    return (isinstance(segment, approach.Approach) and segment.phase == "moving"
            and segment.search.along(segment.target) > past_rad)


def test_a_drive_fault_mid_approach_stops_the_run_with_its_gains_restored(robot, setup):
    config, prior, truth = setup
    injected = []

    def fault(rig, auto_run) -> None:
        if not injected and _approaching(auto_run, "left_elbow_pitch"):
            rig.inject_fault("left_elbow_pitch", 0x8500)
            injected.append(rig.sim_time)

    result, rig = calibrate_in_lockstep(robot, config, prior, truth, ["left_elbow_pitch", "left_shoulder_roll"],
                                        each_tick=fault)
    assert injected
    assert result.aborted is not None and "ring3/fault" in result.aborted and "0x8500" in result.aborted
    assert not result.complete
    assert result.outcomes["left_elbow_pitch"].status == "aborted"
    assert result.outcomes["left_shoulder_roll"].status == "not_reached"  # nothing moved after the fault
    elbow = rig.erob["left_elbow_pitch"]
    assert int(elbow.gate.value) == 0  # gains back on the factory set, the gate reset
    assert (int(elbow.pos_reg.value), int(elbow.vel_reg.value), int(elbow.integral_reg.value)) == \
        (FACTORY_POS_REG, FACTORY_VEL_REG, FACTORY_INTEGRAL)
    assert int(elbow.max_torque.value) == 1500 and int(elbow.following_window.value) == round(0.5 * 524288 / math.tau)
    assert result.calibration == prior  # nothing was written over


def test_an_erob_override_is_recorded_before_it_is_made_and_cleared_once_restored(robot, setup, tmp_path):
    """A run killed outright leaves its record, from which the next run on the ring restores the drive."""
    config, prior, truth = setup
    journal = OverrideJournal(tmp_path, "master", "prime calibrate --auto")
    seen = []

    def look(rig, auto_run) -> None:
        if _approaching(auto_run, "left_elbow_pitch") and not seen:
            seen.extend(json.loads(path.read_text()) for path in tmp_path.glob("erob-ring*-gains-*.json"))

    result, rig = calibrate_in_lockstep(robot, config, prior, truth, ["left_elbow_pitch"], each_tick=look,
                                        journal=journal)
    assert result.outcomes["left_elbow_pitch"].status == "done"
    position = robot.hardware.erob_slaves["left_elbow_pitch"]
    assert [(record["position"], record["joint"], record["via"]) for record in seen] == \
        [(position, "left_elbow_pitch", "master")]
    assert seen[0]["found"]["pos_reg"] == FACTORY_POS_REG  # what the drive held, to restore
    assert not list(tmp_path.glob("erob-ring*")) and journal.left() == []  # restored: the record is gone


def test_a_key_press_stops_the_joint_where_it_is(robot, setup):
    config, prior, truth = setup
    where = []

    def key(rig, auto_run) -> None:
        if not where and _approaching(auto_run, "left_wrist_roll", 0.1):
            auto_run.abort("key 'x' pressed")
            where.append(rig.true_state.position[robot.index("left_wrist_roll")])

    result, rig = calibrate_in_lockstep(robot, config, prior, truth, ["left_wrist_roll"], each_tick=key)
    assert result.aborted == "key 'x' pressed" and not result.complete
    stopped = rig.true_state.position[robot.index("left_wrist_roll")]
    assert abs(stopped - where[0]) < 0.02  # it stopped at once, where it was
    assert not any(motor.enabled for motor in rig.sito.values())


def test_a_held_joint_pushed_away_stops_the_run(robot, setup):
    config, prior, truth = setup
    pushed = []

    def push(rig, auto_run) -> None:
        if not pushed and _approaching(auto_run, "left_elbow_pitch"):
            dof = rig.physics.dof_adr[robot.index("left_wrist_roll")]
            rig.physics.data.qfrc_applied[dof] = 3.0  # a hand on the held wrist
            pushed.append(True)

    result, rig = calibrate_in_lockstep(robot, config, prior, truth, ["left_elbow_pitch"], each_tick=push)
    assert result.aborted is not None and result.aborted.startswith("left_wrist_roll moved")
    assert int(rig.erob["left_elbow_pitch"].gate.value) == 0


def test_assume_direction_keeps_the_prior_where_the_physics_cannot_tell(robot, setup):
    config, prior, truth = setup
    result, _ = calibrate_in_lockstep(robot, config, prior, truth, ["left_wrist_yaw"], assume_direction=True)
    outcome = result.outcomes["left_wrist_yaw"]
    assert outcome.done and outcome.direction_source.startswith("assumed")
    assert outcome.calibration == JointCalibration(1, pytest.approx(0.1, abs=1e-3))


def test_hardware_file_cap_and_efficiency_keys_are_checked(tmp_path):
    path = tmp_path / "prime_hardware.yaml"
    text = bundled("prime_hardware.yaml").read_text()
    path.write_text(text.replace("erob_torque_efficiency: {}", "erob_torque_efficiency: {left_wrist_roll: 0.7}"))
    with pytest.raises(ConfigError, match="left_wrist_roll.*is not an eRob joint"):
        load_hardware(path)
    path.write_text(text.replace("erob_torque_efficiency: {}", "erob_torque_efficiency: {left_elbow_pitch: 1.2}"))
    with pytest.raises(ConfigError, match=r"erob_torque_efficiency\.left_elbow_pitch.*above 1"):
        load_hardware(path)
    path.write_text(text.replace("contact_effort_cap: {}", "contact_effort_cap: {nose: 1.0}"))
    with pytest.raises(ConfigError, match=r"contact_effort_cap\.nose"):
        load_hardware(path)
    path.write_text(text.replace("erob_torque_efficiency: {}", "erob_torque_efficiency: {left_elbow_pitch: 0.7}"))
    hardware = load_hardware(path)
    assert hardware.erob_torque_efficiency["left_elbow_pitch"] == 0.7
    assert hardware.erob_torque_efficiency["left_shoulder_pitch"] == hardware.torque_efficiency == 1.0


# ---- through the gate --------------------------------------------------------------------------------------

def test_the_calibration_is_the_controller_that_owns_the_commands_while_it_runs(robot, setup):
    config, prior, truth = setup
    owners = set()

    def watch(rig, auto_run) -> None:
        if auto_run.moving:
            owners.add(auto_run.manager.command_owner)

    result, _ = calibrate_in_lockstep(robot, config, prior, truth, ["left_elbow_pitch"], each_tick=watch)
    assert owners == {"calibration_controller"}
    assert result.outcomes["left_elbow_pitch"].status == "done"


def test_a_calibration_command_beyond_the_hardware_files_limits_never_reaches_a_bus(tmp_path, setup):
    """The approach moves a wrist at 0.2 rad/s; a hardware file that allows the wrists 0.1 rad/s makes the gate
    refuse it: the wrist never gets the command, and the run stops with the gate's words."""
    config, prior, truth = setup
    path = tmp_path / "prime_hardware.yaml"
    path.write_text(bundled("prime_hardware.yaml").read_text().replace("velocity: 3.14", "velocity: 0.1"))
    robot = load_robot(path)
    fastest = []

    def watch(rig, auto_run) -> None:
        motor = rig.sito["left_wrist_roll"]
        fastest.append(abs(counts_to_velocity(motor.velocity_counts)))

    result, _ = calibrate_in_lockstep(robot, config, prior, truth, ["left_wrist_roll"], each_tick=watch)
    assert result.aborted is not None and result.aborted.startswith(
        "the calibration lost the commands: calibration_controller: velocity of left_wrist_roll is 0.1")
    assert "beyond its limit of 0.1 rad/s (the Sito maximum, command_limits.sito.velocity" in result.aborted
    assert max(fastest) <= 0.1 + 1e-3  # what the motor was told: never the refused speed
    assert result.outcomes["left_wrist_roll"].status == "aborted"


def test_a_joint_whose_range_reaches_the_torso_is_not_driven(robot, setup):
    """With the left arm hanging, shoulder_roll's inner stop is inside the torso: checked before it moves, the
    joint is not driven, and nothing touches."""
    config, prior, truth = setup
    known = Calibration({j: truth.joints[j] if j != "left_shoulder_roll" else prior.joints[j] for j in robot.names})
    touched = []

    def watch(rig, auto_run) -> None:
        touched.append(rig.physics.data.ncon)

    result, rig = calibrate_in_lockstep(robot, config, known, truth, ["left_shoulder_roll"], each_tick=watch,
                                        initial_pose={"left_elbow_pitch": -0.9})  # the left arm hangs
    outcome = result.outcomes["left_shoulder_roll"]
    assert outcome.status == "failed" and outcome.message.startswith("not driven: at ")
    assert "torso_link and left_" in outcome.message
    assert max(touched) == 0
    assert abs(rig.true_state.position[robot.index("left_shoulder_roll")]) < 0.02  # it never moved


def test_a_joint_the_gate_refuses_backs_off_to_where_it_started_and_the_run_goes_on(robot, setup):
    config, prior, truth = setup
    known = Calibration({j: truth.joints[j] if j not in ("left_elbow_pitch", "right_elbow_pitch") else prior.joints[j]
                         for j in robot.names})
    started, refused = [], []

    def refuse(rig, auto_run) -> None:
        i = robot.index("left_elbow_pitch")
        if not started and _moving(auto_run, "left_elbow_pitch") is not None:
            started.append(rig.true_state.position[i])
        if not refused and _approaching(auto_run, "left_elbow_pitch", 0.3):
            held = np.array([name.startswith("left_") for name in robot.names])
            auto_run.controller.on_refused("left_hand_link and torso_link 0.029 m apart (margin 0.030 m)", held)
            refused.append(rig.true_state.position[i])

    result, rig = calibrate_in_lockstep(robot, config, known, truth, ["left_elbow_pitch", "right_elbow_pitch"],
                                        each_tick=refuse)
    assert refused and result.aborted is None
    outcome = result.outcomes["left_elbow_pitch"]
    assert outcome.status == "failed"
    assert outcome.message == ("the gate refused its command: left_hand_link and torso_link 0.029 m apart "
                               "(margin 0.030 m)")
    assert abs(rig.true_state.position[robot.index("left_elbow_pitch")] - started[0]) < 0.05  # backed off
    assert result.outcomes["right_elbow_pitch"].status == "done"  # the run went on with the next joint


@pytest.mark.parametrize(("prior_error", "source"), [(0.01, "prior calibration"),
                                                     (0.3, "the simulated operator's answer")])
def test_a_recalibration_keeps_the_prior_direction_only_where_both_stops_are_where_the_prior_put_them(
        robot, setup, prior_error, source):
    """A symmetric range and a wrist yaw's gravity cannot tell its direction: a recalibration whose stops are where
    the prior put them is the same joint as before and asks nothing; one whose stops moved is asked. A prior 0.3 rad
    wrong puts its first stop where the plan travels fast: it is met there, seen at once (not pressed at the drive's
    torque limit until the time runs out), taken as the stop it is, and the run says the prior is wrong."""
    config, _, truth = setup
    joint = "left_wrist_yaw"
    prior = truth.with_joint(joint, JointCalibration(1, 0.1 + prior_error))
    result, rig = calibrate_in_lockstep(robot, config, prior, truth, [joint])
    outcome = result.outcomes[joint]
    assert outcome.done and outcome.calibration == JointCalibration(1, pytest.approx(0.1, abs=1e-3))
    assert outcome.direction_source.startswith(source)
    assert (outcome.times.get("question", 0.0) > 0) == (source != "prior calibration")
    if source == "prior calibration":
        assert outcome.warnings == [] and outcome.impact_rad_s <= MAX_SPEED_RAD_S
    else:
        assert len(outcome.warnings) == 1 and "prior calibration put none" in outcome.warnings[0]
        assert rig.contact_peak[robot.index(joint)] < 2 * contact_cap(robot, joint)  # released at once


def test_a_joint_comes_back_across_what_it_crossed_with_what_it_needed_at_each_point():
    taught = approach.Taught(side=-1)
    for q, correction in [(0.5, 0.1), (0.495, 9.0), (0.3, 0.2), (0.1, 0.4)]:  # (one value per step of the way)
        taught.add(q, correction)
    assert taught.positions == [0.5, 0.3, 0.1]
    assert taught.correction(0.2) == pytest.approx(0.3) and taught.correction(0.4) == pytest.approx(0.15)
    assert taught.covers(0.08, 0.5, 0.0) and not taught.covers(0.08, 0.7, 0.0)
    assert taught.covers(0.05, 0.5, 0.04)  # a target pressing the stop the way ended at leads the joint
    assert not approach.Taught(side=1).covers(0.0, 0.0, 1.0)  # nothing crossed


def test_an_arms_reach_across_the_robot_is_its_collision_geometry_where_it_is(robot):
    from humanoid_prime.calibration.gravity import GravityModel
    from humanoid_prime.sim.demo import START_POSE

    model = GravityModel(robot)
    left = [i for i, name in enumerate(robot.names) if name.startswith("left_")]
    right = [i for i, name in enumerate(robot.names) if name.startswith("right_")]
    pose = np.array([START_POSE.get(name, 0.0) for name in robot.names])
    (left_low, left_high), (right_low, right_high) = model.lateral(pose, left), model.lateral(pose, right)
    assert 0.1 < left_low < left_high and right_low < right_high < -0.1  # each arm on its side
    assert left_low == pytest.approx(-right_high) and left_high == pytest.approx(-right_low)  # mirrored
    pose[robot.index("left_shoulder_roll")] = -1.0  # the arm across the chest
    pose[robot.index("left_elbow_pitch")] = -1.2
    assert model.lateral(pose, left)[0] < 0.0
