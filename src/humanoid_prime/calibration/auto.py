"""Hands-free calibration (DESIGN §5): Prime drives each joint into its mechanical stops itself, gently, finds its
offset from both stops, and measures what its impedance really is when asked to. This module is the run; the
per-tick law is a controller of the manager (``calibration.hold``), so every command it makes passes the manager's
gate; what it found is ``calibration.report``.

The arms are independent, so one joint of each arm moves at a time (a pair, the same joint of both arms, from the
hand to the shoulder), each with its own contact detection, hold and abort, while every other joint holds where it
is; on the robot one Enter moves a pair. A joint whose frame no robot's prior gives (a new robot) first goes alone
to its nearer stop and back (``joint.first_stop``: nothing can place an arm whose offsets are unknown, so the arms
never move together then), which tells its offset; its second stop follows with the pairs, once every joint of its
arm has its offset, checked under every direction still possible (``_check_found``). For each joint that moves
(``calibration.joint``, ``calibration.approach``):

- impedance: approach gains that follow from its contact-effort cap; an eRob on a ring gets them in its loop-gain
  registers with a wide enough following-error window and its own torque limit lowered (``calibration.drive``,
  recorded in the robot's state folder first, so a run killed outright leaves the next one what to restore);
  every other joint (a Sito wrist, a simulated joint) gets them in its per-tick MIT command;
- effort feed-forward: the holding effort measured before it moves, plus the model's change of gravity since
  (``calibration.gravity``), what free motion teaches, and its inertia times the target's acceleration, so the
  cap is the force at the stop, not the arm's weight;
- motion where the stops can be (``calibration.plan``): from the model's limits, the prior calibration when it is
  a robot's (a recalibration searches near the old stops first) and the offsets allowed (``offset_range``), the
  windows where each stop may lie. The joint travels at the travel speed where no stop can be and at the contact
  speed (at most 0.2 rad/s) within a window; to the stop whose windows cost the least, then the other (the
  described range away), then back to where it started; the target on a leash and contact seen from three signs
  together, the stop's position averaged once it is still against it; with ``measure``, the effort logged while
  the press eases and while it pushes with a velocity command (realised stiffness and damping);
- the body: before a pair moves, the whole range of each, and of both together, is checked against the robot's
  collision geometry with the other joints where they are (``BodyCheck.sweep``, ``BodyCheck.sweep_pair``): a
  joint whose range would bring its arm within the margin of the other arm or the body is not driven. While they
  move, the gate checks every tick's command; a refusal (the margin reached) fails the joint it holds, which backs
  off to where it started.

The gate can check only what it knows: the run's host frame is the prior's directions with offsets 0, moved into
the model's by the best calibration known. A joint is known to the gate (its bodies in the body check, its limits
applied) from the start when its prior is a robot's (a non-zero offset: within the plan's window of the truth,
with the prior's direction), else once its stops have told its offset and its limits or the end its direction;
``frame_known``: every joint known from the start, as in MuJoCo alone, where the prior is the model's own frame.
A joint whose carrying joints are unknown is driven on its effort cap and speeds alone, and the report says so;
a joint pressing its stop is never held to its limits.

Offsets come from both stops with the sweep's formula (``calibration.math``); directions are settled at the end
(``calibration.resolve``). Any fault or lost device (an ERROR on ``/safety_status``), a held joint that moves, or
``abort()`` (a key press) stops every moving joint where it is, restores its drive and ends the run.

``attach`` hands the run's commands to the controller (``ControllerManager.claim``), ``detach`` hands them back;
the sequence (drive settings over SDO, the operator) runs in ``run`` and waits for ticks through
``calibration.sequence``: the loop's, or in virtual time a stepper it drives itself.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import numpy.typing as npt

from humanoid_prime.calibration import plan
from humanoid_prime.calibration.approach import MAX_SPEED_RAD_S, JointRun, Trace
from humanoid_prime.calibration.gravity import GravityModel
from humanoid_prime.calibration.hold import CalibrationController
from humanoid_prime.calibration.joint import FirstStop, Sweep, calibrate, first_stop
from humanoid_prime.calibration.journal import OverrideJournal
from humanoid_prime.calibration.operator import Operator, Unattended
from humanoid_prime.calibration.report import AutoResult, JointOutcome
from humanoid_prime.calibration.resolve import ask, may_ask, settle, unknown
from humanoid_prime.calibration.sequence import Aborted, Steps, Ticks, Until, side_by_side
from humanoid_prime.config.calibration import Calibration, JointCalibration
from humanoid_prime.config.robot import Robot
from humanoid_prime.control.body import BodyCheck
from humanoid_prime.control.flags import Level
from humanoid_prime.control.interfaces import Frame
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.topics import SAFETY_STATUS, SafetyStatus
from humanoid_prime.drivers.ethercat.sdo_client import SdoClient
from humanoid_prime.errors import ConfigError, PrimeError
from humanoid_prime.modes import Mode

CONTACT_FRACTION = 0.1  # default contact-effort cap: this fraction of the joint's effort limit
SWEEP_STEP_RAD = 0.02  # a joint's range is checked against the body at angles this far apart,
PAIR_STEP_RAD = 0.04  # and two joints' ranges against each other on a grid this fine

Floats = npt.NDArray[np.float64]


def _apart(a: tuple[float, float] | None, b: tuple[float, float] | None, margin: float) -> bool:
    """Whether two arms' reaches across the robot (lowest, highest y) leave a plane between them with ``margin``
    to spare (None: a reach not known)."""
    if a is None or b is None:
        return False
    return a[0] > b[1] + margin or b[0] > a[1] + margin


def _spread(reaches: Sequence[Floats]) -> tuple[float, float]:
    """The lowest and the highest y of rows of reaches (lowest, highest y)."""
    return min(float(r[:, 0].min()) for r in reaches), max(float(r[:, 1].max()) for r in reaches)


def contact_cap(robot: Robot, joint: str) -> float:
    """The joint's contact-effort cap (Nm): ``joints.contact_effort_cap`` of the hardware file, else
    ``CONTACT_FRACTION`` of its effort limit. ConfigError if the file asks for more than the effort limit."""
    spec = robot.joints[robot.index(joint)]
    cap = robot.hardware.contact_effort_cap.get(joint)
    if cap is None:
        return CONTACT_FRACTION * spec.effort_limit
    if cap > spec.effort_limit:
        raise ConfigError(robot.hardware.path, f"joints.contact_effort_cap.{joint}",
                          f"{cap:g} Nm is above the joint's effort limit of {spec.effort_limit:g} Nm",
                          f"use a small fraction of it (the default is {CONTACT_FRACTION * spec.effort_limit:g} Nm)")
    return cap


def distal_first(robot: Robot, joints: Sequence[str]) -> list[str]:
    """``joints`` in the order they are calibrated: arm by arm (left first), from the hand to the shoulder."""
    def key(joint: str) -> tuple[int, int]:
        return (0 if joint.startswith("left_") else 1, -robot.index(joint))
    return sorted(joints, key=key)


def pairs(robot: Robot, joints: Sequence[str]) -> list[tuple[str, ...]]:
    """``joints`` in the pairs that move together: each arm's from the hand to the shoulder, the k-th of the left
    arm with the k-th of the right; a joint with no partner moves alone."""
    ordered = distal_first(robot, joints)
    left = [j for j in ordered if j.startswith("left_")]
    right = [j for j in ordered if not j.startswith("left_")]
    return [tuple(j for j in (left[k] if k < len(left) else None, right[k] if k < len(right) else None) if j)
            for k in range(max(len(left), len(right)))]


class AutoCalibration:
    """Calibrates ``joints`` of the running broadcaster-only ``manager`` (module docstring).

    ``model``: the gravity model to use (its compiled model is shared; build it before the buses run).
    ``prior``: the calibration the run's host frame is built from (its directions, offsets 0), the one kept
    for joints not done, and where a robot's (a non-zero offset) the one the plan searches near first.
    ``rings``: joint -> (SDO client, ring position) for every joint whose impedance is its drive's registers (eRob
    on a ring); every other joint takes gains per tick. ``journal``: where an eRob's drive settings are recorded
    before they are made (None: not recorded). ``settle_s``: before the first joint moves, every joint is held this
    long, the per-tick ones with the model's gravity (a robot that begins limp, as MuJoCo alone does).
    ``measure``: the realised stiffness and damping, pushed against each stop. ``offset_range``: how far from 0 an
    offset may be where the prior is not a robot's.
    """

    def __init__(self, manager: ControllerManager, prior: Calibration, joints: Sequence[str], *,
                 rings: Mapping[str, tuple[SdoClient, int]] | None = None, operator: Operator | None = None,
                 ticks: Ticks, speed: float = MAX_SPEED_RAD_S, assume_direction: bool = False,
                 measure: bool = False, report: Callable[[str], None] | None = None,
                 model: GravityModel | None = None, frame_known: bool = False, settle_s: float = 0.0,
                 offset_range: float = plan.OFFSET_RANGE_RAD, journal: OverrideJournal | None = None) -> None:
        robot = manager.robot
        if not 0 < speed <= MAX_SPEED_RAD_S:
            raise PrimeError(f"speed {speed:g} rad/s: the hands-free calibration moves a joint at most "
                             f"{MAX_SPEED_RAD_S:g} rad/s into a stop; give 0 < speed <= {MAX_SPEED_RAD_S:g}")
        if not manager.broadcaster_only:
            raise PrimeError("the hands-free calibration commands the joints itself: it needs a broadcaster-only run")
        for joint in joints:
            robot.index(joint)  # KeyError names the known joints
        self.manager = manager
        self.robot = robot
        self.prior = prior
        self.joints = tuple(distal_first(robot, joints))
        self.rings = dict(rings or {})
        self.journal = journal
        self.operator = operator or Unattended()
        self.ticks = ticks
        self.speed = speed
        self.assume_direction = assume_direction
        self.measure = measure
        self.settle_s = settle_s
        self.offset_range = offset_range
        self.report = report or (lambda text: None)
        self.caps = {j: contact_cap(robot, j) for j in self.joints}
        self.gravity = model or GravityModel(robot)  # the loop's
        self.model = GravityModel(robot, self.gravity.model)  # the sequence's (the threads never share data)
        self.body = BodyCheck(robot, robot.hardware.collision_margin, model=self.gravity.model)  # the sequence's
        self.prior_direction = prior.direction_array(robot.names)
        self.prior_offset = prior.offset_array(robot.names)
        self.direction = self.prior_direction.copy()  # best knowledge: the prior, the new values where done
        self.offset = self.prior_offset.copy()
        # A joint whose prior offset is 0 is the template's, not a robot's (no calibrated joint reads exactly 0).
        self.robots_prior = {j: frame_known or prior.joints[j].homing_offset != 0.0 for j in robot.names}
        known = np.array([self.robots_prior[j] for j in robot.names])
        self.controller = CalibrationController(
            robot, np.array([j not in self.rings for j in robot.names]), manager.config.mode_gains()[Mode.STANDBY],
            self.host_gravity, (self.prior_direction, self.direction, self.offset), known,
            settle_effort=settle_s > 0)
        self.outcomes: dict[str, JointOutcome] = {
            j: JointOutcome(j, "not_reached", prior=prior.joints[j], cap_nm=self.caps[j]) for j in self.joints}
        self.traces: dict[str, Trace] = {}
        self.sweeps: dict[str, Sweep] = {}
        self.firsts: dict[str, FirstStop] = {}  # a new robot's joints: what their first stop told
        self.clear: dict[str, float] = {}  # how far toward its other stop the body check lets a joint travel fast
        self.timeline: list[tuple[str, float, float]] = []  # (what, from, to): robot time
        self._began = (0.0, 0.0)  # (robot, wall) when the run began
        self._claimed = False  # the controller has had the commands

    @property
    def moving(self) -> tuple[JointRun, ...]:
        """The joints moving now (one per arm at most)."""
        return self.controller.runs

    @property
    def aborted(self) -> str | None:
        return self.controller.aborted

    # -- the loop side --------------------------------------------------------------------------------------
    def attach(self) -> None:
        """The run's commands to the calibration's controller from the next tick; /safety_status watched."""
        self.manager.topics.subscribe(SAFETY_STATUS, self._on_status, latched=True)
        self.manager.claim(self.controller)

    def detach(self) -> None:
        self.manager.release(self.controller)
        self.manager.topics.unsubscribe(SAFETY_STATUS, self._on_status)

    def abort(self, reason: str) -> None:
        """Stop the run as soon as possible (any thread): every moving joint holds where it is."""
        if self.controller.abort_request is None:
            self.controller.abort_request = reason

    def _on_status(self, status: SafetyStatus) -> None:
        self.controller.status = status

    def _errors(self) -> list[str]:
        status = self.controller.status
        if status is None:
            return []
        return [f"{key}: {status.flags[key]}" for key, level in status.levels.items() if level is Level.ERROR]

    # -- frames -----------------------------------------------------------------------------------------------
    def description_angles(self, q: Floats, direction: Floats | None = None, offset: Floats | None = None) -> Floats:
        """The joints' description angles from host-frame ``q``, with the best calibration known (or the one given)."""
        direction = self.direction if direction is None else direction
        offset = self.offset if offset is None else offset
        return direction * (self.prior_direction * q - offset)

    def host_gravity(self, q: Floats, model: GravityModel | None = None, direction: Floats | None = None,
                     offset: Floats | None = None) -> Floats:
        """The model's holding torque of every joint at host-frame ``q``, in the host frame (``model``: the loop's
        unless given; the calibration: the best known unless given)."""
        direction = self.direction if direction is None else direction
        angles = self.description_angles(q, direction, offset)
        angles[~np.isfinite(angles)] = 0.0  # a joint off this run's buses: taken as hanging
        torques = (model or self.gravity).torques(angles)
        return np.asarray(self.prior_direction * direction * torques, dtype=np.float64)

    def hypotheses(self, joint: str, start: float) -> tuple[list[plan.Hypothesis], list[plan.Hypothesis]]:
        """Where ``joint`` reading ``start`` can have its stops: the windows searched first and those searched after
        them (``calibration.plan``): a robot's prior, then any offset allowed; else any offset allowed."""
        spec = self.robot.joints[self.robot.index(joint)]
        wide = plan.holding(plan.wide(self.offset_range), spec, start)
        if not self.robots_prior[joint]:
            return wide, []
        cal = self.prior.joints[joint]
        return plan.holding(plan.prior(cal.direction, cal.homing_offset), spec, start), wide

    def assume(self, i: int, found: Sequence[plan.Hypothesis]) -> None:
        """Joint ``i``'s first stop gave the offsets ``found`` (one per direction still possible): the loop's model
        takes the prior's direction where it is still possible (not the gate: the direction is not settled)."""
        if not found:
            return
        h = next((h for h in found if h.relative == 1), found[0])
        p = int(self.prior_direction[i])
        self.know(i, JointCalibration(h.relative * p, p * h.low), settled=False)

    def know(self, i: int, cal: JointCalibration, *, settled: bool) -> None:
        """Joint ``i``'s calibration, for the loop's model and, once ``settled`` (its direction told), the gate."""
        self.direction[i] = cal.direction
        self.offset[i] = cal.homing_offset
        if settled:
            self.controller.settled[i] = True
        self.controller.forget_gravity()

    # -- the sequence ---------------------------------------------------------------------------------------
    def run(self) -> AutoResult:
        """Calibrate every joint asked for, a pair at a time, then settle the directions."""
        state = self.manager.resources.state
        self._began = (state.stamp, time.monotonic())
        try:
            self._start()
            self.operator.begin(self.joints)
            self._first_stops()
            for pair in pairs(self.robot, self.joints):
                pair = tuple(j for j in pair if self.outcomes[j].status == "not_reached")
                if self.aborted is not None:
                    break
                if not pair:
                    continue
                if not self.operator.confirm(pair):
                    for joint in pair:
                        self.outcomes[joint].status = "skipped"
                        self.outcomes[joint].message = "skipped by the operator"
                    continue
                checked = self._check_found(pair) if any(j in self.firsts for j in pair) else self._check_pair(pair)
                for group in checked:
                    if self._stopped() is not None:
                        break
                    began = state.stamp
                    self._together([calibrate(self, joint) for joint in group])
                    self.timeline.append((" and ".join(group), began, state.stamp))
            if self.aborted is None:
                began = state.stamp
                settle(self)
                for joint in unknown(self):
                    if self._stopped() is not None:
                        break
                    if may_ask(self, joint):
                        self._together([ask(self, joint)])
                if state.stamp > began:
                    self.timeline.append(("direction questions", began, state.stamp))
        except Aborted as exc:
            if self.controller.aborted is None:
                self.controller.aborted = str(exc)
        return self.result()

    def _first_stops(self) -> None:
        """A new robot's joints (no robot's prior), one at a time (neither arm's bodies can be placed yet, so the
        arms never move together), hand to shoulder: each to its first stop at the contact speed and back, which
        tells its offset (``joint.first_stop``); the second stops follow, both arms at once where the body check
        clears them."""
        state = self.manager.resources.state
        for joint in (j for j in self.joints if not self.robots_prior[j]):
            if self._stopped() is not None:
                break
            if not self.operator.confirm((joint,)):
                self.outcomes[joint].status = "skipped"
                self.outcomes[joint].message = "skipped by the operator"
                continue
            if self._drivable(joint) is False:
                continue
            began = state.stamp
            self._together([first_stop(self, joint)])
            self.timeline.append((f"{joint}: first stop", began, state.stamp))

    def _start(self) -> None:
        errors = self._errors()
        if errors:
            raise PrimeError("the robot reports problems; nothing was moved: " + "; ".join(errors))
        state = self.manager.resources.state
        began = state.stamp
        self._together([self._settle()])
        if self.aborted is not None:
            raise Aborted(self.aborted)
        if state.stamp > began:
            self.timeline.append(("start", began, state.stamp))

    def _settle(self) -> Steps:
        """A tick, so the controller has the commands and every joint is held where it is; then ``settle_s``."""
        state = self.manager.resources.state
        began = state.stamp
        yield Until(lambda: True)
        yield Until(lambda: state.stamp - began >= self.settle_s)

    def _together(self, procedures: list[Steps]) -> None:
        side_by_side(procedures, self.ticks, lambda: self.manager.tick_count, self._stopped, self.abort)

    def _stopped(self) -> str | None:
        """Why the run stops (None: it goes on): an abort, or the commands lost to another controller once it had
        them."""
        manager = self.manager
        if manager.active is self.controller:
            self._claimed = True
        elif self._claimed and self.aborted is None:
            fallbacks = manager.fallbacks
            why = fallbacks[-1]["reason"] if fallbacks else "another controller has the commands"
            self.controller.aborted = f"the calibration lost the commands: {why}"
        return self.aborted

    def result(self) -> AutoResult:
        joints = dict(self.prior.joints)
        for joint, outcome in self.outcomes.items():
            if outcome.done and outcome.calibration is not None:
                joints[joint] = outcome.calibration
        robot_began, wall_began = self._began
        return AutoResult(Calibration(joints), self.outcomes, self.traces, self.joints, self.aborted, self.robot,
                          robot_seconds=self.manager.resources.state.stamp - robot_began,
                          wall_seconds=time.monotonic() - wall_began,
                          timeline=[(what, a - robot_began, b - robot_began) for what, a, b in self.timeline])

    # -- the body, before a pair moves ------------------------------------------------------------------------
    def _check_pair(self, pair: tuple[str, ...]) -> list[list[str]]:
        """The joints of ``pair`` to drive, in the groups that move together: each joint whose range keeps its arm
        beyond the margin with the other joints where they are (the others fail, not driven; a range whose carrying
        joints are not known is not checked, and the report says so); both at once where their ranges together
        keep the arms apart, else (or where the bodies' places are not known) one after the other."""
        robot, frame = self.robot, self.controller.frame_now()
        measured = self.manager.resources.state.position
        driven: list[str] = []
        checked = True
        for joint in pair:
            verdict = self._drivable(joint)
            if verdict is None:
                driven.append(joint)
                checked = False
            elif verdict:
                driven.append(joint)
        if len(driven) < 2:
            return [driven] if driven else []
        a, b = driven
        together = self.body.sweep_pair(measured, (robot.index(a), self._angles(a, PAIR_STEP_RAD)),
                                        (robot.index(b), self._angles(b, PAIR_STEP_RAD)), frame) if checked else None
        contact = together[0] if together is not None else None
        if together is None or contact is not None:
            why = ("the joints that carry them are not calibrated yet" if together is None else
                   f"with {a} at {together[1]:+.2f} and {b} at {together[2]:+.2f} rad their ranges could bring "
                   f"{contact.words(self.body.margin) if contact is not None else ''}")
            self.report(f"{a} and {b}: one after the other ({why})")
            return [[a], [b]]
        return [[a, b]]

    def _check_found(self, pair: tuple[str, ...]) -> list[list[str]]:
        """The joints of ``pair`` (at least one with its first stop found) in the groups that move together, and how
        far toward its other stop each may travel fast (``clear``: a host reading; absent, it moves at the contact
        speed all the way, as where no frame is known): as far as its arm stays beyond the margin of the body under
        every frame its arm may still have (``_frames``: each joint's offset found, either direction where it is not
        told) and its reach across the robot keeps a plane between it and the other arm. Both at once where their
        whole ways keep apart so, else one after the other, each against the other arm where it is."""
        ways = {joint: self._way(joint) for joint in pair}
        along: dict[str, list[Floats]] = {}  # each frame's reach (lowest, highest y) at each point of the way
        reaches: dict[str, tuple[float, float]] = {}
        for joint, way in ways.items():
            if way is not None:
                along[joint] = [self._reaches(self.robot.index(joint), frame, angles)
                                for frame, angles in zip(way[1], way[2], strict=True)]
                reaches[joint] = _spread(along[joint])
        together = len(pair) == 2 and len(reaches) == 2 and _apart(reaches[pair[0]], reaches[pair[1]],
                                                                   self.body.margin)
        for joint in pair:
            other = next((j for j in pair if j != joint), None)
            beside = reaches[other] if together and other is not None else self._other_arm(joint)
            limit, certain = self._clear_until(joint, ways[joint], along.get(joint), beside)
            self.clear.pop(joint, None)
            if certain is not None:
                self._not_driven(joint, certain)
            elif limit is not None:
                self.clear[joint] = limit
            else:
                self.report(f"{joint}: at the contact speed all the way (the body check cannot place its arm under "
                            "every frame still possible)")
        if len(pair) == 2 and not together:
            self.report(f"{pair[0]} and {pair[1]}: one after the other (their arms' reaches under the frames still "
                        "possible could meet)")
        driven = [j for j in pair if self.outcomes[j].status == "not_reached"]
        return [driven] if together and len(driven) == 2 else [[j] for j in driven]

    def _way(self, joint: str) -> tuple[Floats, list[Frame], list[Floats]] | None:
        """Where ``joint`` goes for its other stop (host readings from where it is to the far end of where the stop
        may be, ``SWEEP_STEP_RAD`` apart), the frames its arm may have, and that way in each frame's angles. None:
        no first stop, or an arm not placed."""
        first = self.firsts.get(joint)
        frames = self._frames(joint)
        if first is None or frames is None or first.approach.stop is None:
            return None
        i = self.robot.index(joint)
        spec = self.robot.joints[i]
        here = float(self.manager.resources.state.position[i])
        far = first.approach.stop - first.side * (spec.upper - spec.lower) * (1 + plan.SPAN_TOLERANCE) \
            - first.side * plan.STOP_MARGIN_RAD
        path = np.linspace(here, far, max(2, math.ceil(abs(far - here) / SWEEP_STEP_RAD) + 1))
        return path, frames, [frame.scale[i] * path + frame.shift[i] for frame in frames]

    def _clear_until(self, joint: str, way: tuple[Floats, list[Frame], list[Floats]] | None,
                     reach: list[Floats] | None, beside: tuple[float, float] | None
                     ) -> tuple[float | None, str | None]:
        """How far along ``way`` (a host reading) ``joint``'s arm keeps beyond the margin of the body in every frame,
        and its ``reach`` there (each frame's, ``_reaches``) apart from ``beside`` (the other arm's): None, not even
        where it is; and why it must not be driven, where its way brings its arm within the margin of the body in
        every frame (None: not so)."""
        if way is None or reach is None or beside is None:
            return None, None
        path, frames, angles = way
        i = self.robot.index(joint)
        measured = self.manager.resources.state.position
        reached = len(path)
        certain: list[str] = []
        for frame, along, reaches in zip(frames, angles, reach, strict=True):
            found = self.body.sweep(measured, i, along, frame)
            if found is None:
                return None, None
            contact, angle = found
            if contact is not None:
                k = int(np.argmin(np.abs(along - angle)))
                reached = min(reached, k)
                certain.append(f"at {path[k]:+.2f} rad its way would bring {contact.words(self.body.margin)} with the "
                               "other joints where they are")
            for k in range(min(reached, len(path))):
                if not _apart((float(reaches[k, 0]), float(reaches[k, 1])), beside, self.body.margin):
                    reached = k
                    break
        if len(certain) == len(frames):  # whichever way it turns
            return None, certain[0]
        return (None if reached == 0 else float(path[reached - 1])), None

    def _arm(self, joint: str) -> list[int]:
        prefix = joint.split("_", 1)[0] + "_"
        return [i for i, name in enumerate(self.robot.names) if name.startswith(prefix)]

    def _frames(self, joint: str) -> list[Frame] | None:
        """Every frame ``joint``'s arm may still have: each of its joints as the gate knows it (settled, or a
        robot's prior), or at the offset its first stop gave in each direction still possible (the other arm left
        out: its bodies are not checked). None: a joint of the arm is not known at all."""
        base = self.controller.frame_now()
        base.known[:] = 0
        options: list[list[tuple[int, float, float]]] = []
        for i in self._arm(joint):
            name = self.robot.names[i]
            first = self.firsts.get(name)
            if self.controller.settled[i] or (self.robots_prior[name] and first is None):
                direction, offset = self.direction[i], self.offset[i]
                options.append([(i, float(direction * self.prior_direction[i]), float(-direction * offset))])
            elif first is not None and first.found:
                options.append([(i, float(h.relative), float(-h.relative * h.low)) for h in first.found])
            else:
                return None
        frames = []
        for choice in itertools.product(*options):
            frame = Frame(base.scale.copy(), base.shift.copy(), base.known.copy(), base.limited.copy())
            for i, scale, shift in choice:
                frame.scale[i], frame.shift[i], frame.known[i] = scale, shift, 1
            frames.append(frame)
        return frames

    def _reaches(self, i: int, frame: Frame, angles: Floats) -> Floats:
        """Joint ``i``'s arm's reach across the robot (lowest, highest y, m) in ``frame``, the joint at each of
        ``angles``: one row per angle."""
        pose = frame.scale * self.manager.resources.state.position + frame.shift
        arm = self._arm(self.robot.names[i])
        out = np.empty((len(angles), 2))
        for k, angle in enumerate(angles):
            pose[i] = angle
            out[k] = self.model.lateral(pose, arm)
        return out

    def _other_arm(self, joint: str) -> tuple[float, float] | None:
        """The other arm's reach where it is, under every frame it may still have (None: not placed)."""
        other = next((j for j in self.robot.names if not j.startswith(joint.split("_", 1)[0] + "_")), None)
        if other is None:
            return None
        frames = self._frames(other)
        if frames is None:
            return None
        i, measured = self.robot.index(other), self.manager.resources.state.position
        return _spread([self._reaches(i, frame, frame.scale[i:i + 1] * measured[i] + frame.shift[i:i + 1])
                        for frame in frames])

    def _drivable(self, joint: str) -> bool | None:
        """Whether ``joint``'s whole range keeps its arm beyond the margin of the other arm and the body with the
        other joints where they are (False: it is not driven, and fails saying why); None: its place cannot be
        known (the joints that carry it are not calibrated yet), which the report says."""
        found = self.body.sweep(self.manager.resources.state.position, self.robot.index(joint),
                                self._angles(joint, SWEEP_STEP_RAD), self.controller.frame_now())
        if found is None:
            self.report(f"{joint}: its range was not checked against the body (the joints that carry it are not "
                        "calibrated yet)")
            return None
        contact, angle = found
        if contact is not None:
            self._not_driven(joint, f"at {angle:+.2f} rad its range would bring {contact.words(self.body.margin)}"
                                    " with the other joints where they are")
            return False
        return True

    def _angles(self, joint: str, step: float) -> Floats:
        """``joint``'s range (model frame) at angles ``step`` apart."""
        spec = self.robot.joints[self.robot.index(joint)]
        return np.linspace(spec.lower, spec.upper, max(2, math.ceil((spec.upper - spec.lower) / step) + 1))

    def _not_driven(self, joint: str, why: str) -> None:
        outcome = self.outcomes[joint]
        outcome.status = "failed"
        outcome.message = f"not driven: {why}; move them, or calibrate it by hand"
        self.report(f"{joint}: {outcome.status} ({outcome.message})")
