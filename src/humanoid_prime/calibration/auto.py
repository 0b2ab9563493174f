# Over 450 lines: one procedure (each joint to its stops, then the directions settled at the end) over one run's
# state; the parts that stand alone are beside it (hold, approach, drive, report, operator).
"""Hands-free calibration (DESIGN §5): Prime drives each joint into its mechanical stops itself, gently, finds its
offset from both stops and measures what its impedance really is. This module is the procedure; the per-tick law
is a controller of the manager (``calibration.hold``), so every command it makes passes the manager's gate; what
it found is ``calibration.report``.

One joint moves at a time, arm by arm from the hand to the shoulder; the others hold where they are. For the joint
that moves (``calibration.approach``):

- impedance: approach gains that follow from its contact-effort cap; an eRob on a ring gets them in its loop-gain
  registers with a wide enough following-error window and its own torque limit lowered (``calibration.drive``);
  every other joint (a Sito wrist, a simulated joint) gets them in its per-tick MIT command;
- effort feed-forward: the holding effort measured before it moves, plus the model's change of gravity since
  (``calibration.gravity``), plus what free motion teaches, so the cap is the force at the stop, not the arm's
  weight;
- motion: to the nearer stop, then the other, then back to where it started, at the speed cap, the target on a
  leash and contact seen from three signs together; the stop's position is recorded while it is pressed, and the
  effort is logged while the press eases and while it pushes with a velocity command (realised stiffness and
  damping); a stop it rested on at the start is approached again once free motion has learnt its weight;
- budgets: the target never leaves the joint's range plus a margin around where it started; a stop not found
  within its travel or time budget fails the joint;
- the body: before it moves, its whole range is checked against the robot's collision geometry with the other
  joints where they are (``BodyCheck.sweep``): a joint whose range would bring its arm within the margin of the
  other arm or the body is not driven. While it moves, the gate checks every tick's command; a refusal (the
  margin reached) fails the joint, which backs off to where it started.

The gate can check only what it knows: the run's host frame is the prior's directions with offsets 0, moved into
the model's by the best calibration known. A joint asked for is unknown to the gate (its bodies out of the body
check, its limits not applied) until its stops and its limits have told its frame, and so is a joint whose prior
offset is 0 (the template's); ``frame_known``: every joint known from the start, as in MuJoCo alone, where the prior
is the model's own frame. A joint whose carrying joints are unknown is driven on its effort cap and speed alone, as
before any collision model, and the report says so; a joint pressing its stop is never held to its limits.

Offsets come from both stops with the sweep's formula (``calibration.math``). Directions are settled at the end,
proximal first, once every joint's offset is known: from the limits (an asymmetric range) and the gravity measured
along each sweep (``calibration.direction``); where neither tells, one small motion and a plain question for each
joint whose proximal joints are known (``Operator``), or the prior's with ``assume_direction``. A flip is written
only on such evidence, and reported.

Any fault or lost device (an ERROR on ``/safety_status``), a held joint that moves, or ``abort()`` (a key
press) stops the moving joint where it is, restores its drive and ends the run.

``attach`` hands the run's commands to the controller (``ControllerManager.claim``), ``detach`` hands them back;
the sequence (drive settings over SDO, the operator) runs in ``run`` and waits for ticks through ``Ticks``: the
loop's, or in virtual time a stepper it drives itself.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol, TypeVar

import numpy as np
import numpy.typing as npt

from humanoid_prime.calibration.approach import (
    MAX_SPEED_RAD_S,
    Approach,
    Hold,
    JointRun,
    Move,
    Segment,
    Trace,
    approach_gains,
)
from humanoid_prime.calibration.direction import direction_from_gravity, direction_from_limits, view_of
from humanoid_prime.calibration.drive import approach_drive
from humanoid_prime.calibration.gravity import GravityModel
from humanoid_prime.calibration.hold import CalibrationController
from humanoid_prime.calibration.math import flip_direction
from humanoid_prime.calibration.operator import Operator, Unattended
from humanoid_prime.calibration.report import AutoResult, JointOutcome, fit_stiffness
from humanoid_prime.config.calibration import Calibration, JointCalibration
from humanoid_prime.config.robot import JointSpec, Robot
from humanoid_prime.control.body import BodyCheck
from humanoid_prime.control.flags import Level
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.topics import SAFETY_STATUS, SafetyStatus
from humanoid_prime.drivers.erob.gains import gains_to_registers, registers_to_gains
from humanoid_prime.drivers.ethercat.sdo_client import SdoClient
from humanoid_prime.errors import ConfigError, PrimeError
from humanoid_prime.modes import Mode

CONTACT_FRACTION = 0.1  # default contact-effort cap: this fraction of the joint's effort limit
BACKOFF_RAD = 0.05
RESTING_RAD = 0.02  # a stop found this close to where the joint started: it rested on it
RESTING_BACKOFF_RAD = 0.15  # then it moves this far off before it approaches again
TRAVEL_MARGIN_RAD = 0.1  # beyond the joint's range (plus 5 %), the most the target travels toward a stop
SPAN_TOLERANCE = 0.05  # the stops' spacing must be the described range within this share
ANCHOR_S = 0.2  # the holding torque is averaged this long before a joint moves
PROMPT_RAD = 0.15  # the prompted motion that asks the operator for a direction
GRAVITY_SAMPLES = 60
TICK_TIMEOUT_S = 5.0  # wall seconds without a control tick: the loop is gone
SWEEP_STEP_RAD = 0.02  # a joint's range is checked against the body at angles this far apart

Floats = npt.NDArray[np.float64]
S = TypeVar("S", bound=Segment)


class Aborted(PrimeError):
    """The run was stopped: a fault, a lost device, a held joint that moved, a key press or a signal."""


class JointFailed(PrimeError):
    """This joint could not be calibrated (no stop within the budgets, a span that is not its range, ...)."""


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


def travel_budget(spec: JointSpec) -> float:
    """How far (rad) a joint's target may travel from where it started toward a stop: its range and a margin."""
    return (spec.upper - spec.lower) * (1 + SPAN_TOLERANCE) + TRAVEL_MARGIN_RAD


def distal_first(robot: Robot, joints: Sequence[str]) -> list[str]:
    """``joints`` in the order they are calibrated: arm by arm (left first), from the hand to the shoulder."""
    def key(joint: str) -> tuple[int, int]:
        return (0 if joint.startswith("left_") else 1, -robot.index(joint))
    return sorted(joints, key=key)


# ---- waiting for ticks ----------------------------------------------------------------------------------------

class Ticks(Protocol):
    def until(self, done: Callable[[], bool]) -> None:
        """Return once ``done()`` holds, checked after each control tick."""


class LoopTicks:
    """The control loop runs in another thread (``run_loop``); ``ticked`` is called at the end of each tick."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._condition = threading.Condition()
        self._count = 0
        self.clock = clock
        self.stopped = threading.Event()  # the loop is ending: nothing waits for its ticks any more

    def ticked(self) -> None:
        with self._condition:
            self._count += 1
            self._condition.notify_all()

    def until(self, done: Callable[[], bool]) -> None:
        with self._condition:
            seen, last = self._count, self.clock()
            while not done():
                if self.stopped.is_set():
                    raise Aborted("the control loop stopped")
                self._condition.wait(0.1)
                if self._count != seen:
                    seen, last = self._count, self.clock()
                elif self.clock() - last > TICK_TIMEOUT_S:
                    raise Aborted(f"no control tick for {TICK_TIMEOUT_S:g} s")


class SteppedTicks:
    """Virtual time: ``step()`` runs one control tick (and the physics of one period); nothing runs between."""

    def __init__(self, step: Callable[[], None]) -> None:
        self.step = step

    def until(self, done: Callable[[], bool]) -> None:
        while not done():
            self.step()


@dataclass
class _Sweep:
    """What a joint's stops and its sweep between them left for its direction: the calibration either way, the
    limits' verdict, where every joint was meanwhile (host frame) and (position, effort) in free motion."""

    same: JointCalibration
    flipped: JointCalibration
    by_limits: int | None
    config: Floats
    samples: Floats


# ---- the procedure ------------------------------------------------------------------------------------------

class AutoCalibration:
    """Calibrates ``joints`` of the running broadcaster-only ``manager`` (module docstring).

    ``model``: the gravity model to use (its compiled model is shared; build it before the buses run).
    ``prior``: the calibration the run's host frame is built from (its directions, offsets 0) and the one kept
    for joints not done. ``rings``: joint -> (SDO client, ring position) for every joint whose impedance is its
    drive's registers (eRob on a ring); every other joint takes gains per tick. ``settle_s``: before the first
    joint moves, every joint is held this long, the per-tick ones with the model's gravity (a robot that begins
    limp, as MuJoCo alone does).
    """

    def __init__(self, manager: ControllerManager, prior: Calibration, joints: Sequence[str], *,
                 rings: Mapping[str, tuple[SdoClient, int]] | None = None, operator: Operator | None = None,
                 ticks: Ticks, speed: float = MAX_SPEED_RAD_S, assume_direction: bool = False,
                 measure: bool = True, report: Callable[[str], None] | None = None,
                 model: GravityModel | None = None, frame_known: bool = False, settle_s: float = 0.0) -> None:
        robot = manager.robot
        if not 0 < speed <= MAX_SPEED_RAD_S:
            raise PrimeError(f"speed {speed:g} rad/s: the hands-free calibration moves a joint at most "
                             f"{MAX_SPEED_RAD_S:g} rad/s; give 0 < speed <= {MAX_SPEED_RAD_S:g}")
        if not manager.broadcaster_only:
            raise PrimeError("the hands-free calibration commands the joints itself: it needs a broadcaster-only run")
        for joint in joints:
            robot.index(joint)  # KeyError names the known joints
        self.manager = manager
        self.robot = robot
        self.prior = prior
        self.joints = tuple(distal_first(robot, joints))
        self.rings = dict(rings or {})
        self.operator = operator or Unattended()
        self.ticks = ticks
        self.speed = speed
        self.assume_direction = assume_direction
        self.measure = measure
        self.settle_s = settle_s
        self.report = report or (lambda text: None)
        self.caps = {j: contact_cap(robot, j) for j in self.joints}
        self.gravity = model or GravityModel(robot)  # the loop's
        self.model = GravityModel(robot, self.gravity.model)  # the sequence's (the threads never share data)
        self.body = BodyCheck(robot, robot.hardware.collision_margin, model=self.gravity.model)  # the sequence's
        self.prior_direction = prior.direction_array(robot.names)
        self.prior_offset = prior.offset_array(robot.names)
        self.direction = self.prior_direction.copy()  # best knowledge: the prior, the new values where done
        self.offset = self.prior_offset.copy()
        # A joint not asked for is known from the prior, unless the prior's offset is 0: the template's, not a
        # robot's (no calibrated joint reads exactly 0).
        known = np.array([frame_known or (j not in self.joints and prior.joints[j].homing_offset != 0.0)
                          for j in robot.names])
        self.controller = CalibrationController(
            robot, np.array([j not in self.rings for j in robot.names]), manager.config.mode_gains()[Mode.STANDBY],
            self.host_gravity, (self.prior_direction, self.direction, self.offset), known,
            settle_effort=settle_s > 0)
        self.outcomes: dict[str, JointOutcome] = {
            j: JointOutcome(j, "not_reached", prior=prior.joints[j], cap_nm=self.caps[j]) for j in self.joints}
        self.traces: dict[str, Trace] = {}
        self._sweeps: dict[str, _Sweep] = {}

    @property
    def moving(self) -> JointRun | None:
        runs = self.controller.runs
        return runs[0] if runs else None

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
        """Stop the run as soon as possible (any thread): the moving joint holds where it is."""
        if self.controller.abort_request is None:
            self.controller.abort_request = reason

    def _on_status(self, status: SafetyStatus) -> None:
        self.controller.status = status

    def _errors(self) -> list[str]:
        status = self.controller.status
        if status is None:
            return []
        return [f"{key}: {status.flags[key]}" for key, level in status.levels.items() if level is Level.ERROR]

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

    # -- the sequence ---------------------------------------------------------------------------------------
    def run(self) -> AutoResult:
        """Calibrate every joint asked for, then ask for the directions the physics could not tell."""
        try:
            self._start()
            self.operator.begin(self.joints)
            for joint in self.joints:
                if self.aborted is not None:
                    break
                if not self.operator.confirm(joint):
                    self.outcomes[joint].status = "skipped"
                    self.outcomes[joint].message = "skipped by the operator"
                    continue
                self._joint(joint)
            if self.aborted is None:
                self._resolve_directions()
                self._ask_directions()
        except Aborted as exc:
            if self.controller.aborted is None:
                self.controller.aborted = str(exc)
        return self.result()

    def _start(self) -> None:
        errors = self._errors()
        if errors:
            raise PrimeError("the robot reports problems; nothing was moved: " + "; ".join(errors))
        self._wait(lambda: True)  # the controller took the commands: every joint held from here, where it is
        began = self.manager.resources.state.stamp
        self._wait(lambda: self.manager.resources.state.stamp - began >= self.settle_s)

    def _wait(self, done: Callable[[], bool]) -> None:
        seen = self.manager.tick_count

        def ended() -> bool:
            if self.manager.tick_count > seen and self.manager.active is not self.controller and self.aborted is None:
                fallbacks = self.manager.fallbacks
                why = fallbacks[-1]["reason"] if fallbacks else "another controller has the commands"
                self.controller.aborted = f"the calibration lost the commands: {why}"
            return self.aborted is not None or (self.manager.tick_count > seen and done())

        self.ticks.until(ended)
        if self.aborted is not None:
            raise Aborted(self.aborted)

    def _segment(self, run: JointRun, segment: S) -> S:
        run.segment = segment
        self._wait(lambda: segment.finished or segment.failure is not None)
        if segment.failure is not None:
            raise JointFailed(segment.failure)
        return segment

    def result(self) -> AutoResult:
        joints = dict(self.prior.joints)
        for joint, outcome in self.outcomes.items():
            if outcome.done and outcome.calibration is not None:
                joints[joint] = outcome.calibration
        return AutoResult(Calibration(joints), self.outcomes, self.traces, self.joints, self.aborted, self.robot)

    def _check_range(self, joint: str) -> None:
        """Its whole range against the body, with the other joints where they are: JointFailed if it would bring
        its arm within the margin; said in the report when its carrying joints are unknown (nothing to check)."""
        i = self.robot.index(joint)
        spec = self.robot.joints[i]
        controller = self.controller
        angles = np.linspace(spec.lower, spec.upper, max(2, math.ceil((spec.upper - spec.lower) / SWEEP_STEP_RAD)))
        found = self.body.sweep(self.manager.resources.state.position, i, angles, controller.frame_now())
        if found is None:
            self.report(f"{joint}: its range was not checked against the body (the joints that carry it are not "
                        "calibrated yet)")
            return
        contact, angle = found
        if contact is not None:
            raise JointFailed(f"not driven: at {angle:+.2f} rad its range would bring {contact.words(self.body.margin)}"
                              " with the other joints where they are; move them, or calibrate it by hand")

    @contextlib.contextmanager
    def _moving(self, joint: str) -> Iterator[JointRun]:
        """``joint`` anchored where it is (its holding effort measured), on its approach impedance, for the
        block; afterwards anchored where it ended, on the impedance it had, and held there. A joint the gate
        refused goes back to where it started first."""
        robot, controller = self.robot, self.controller
        i = robot.index(joint)
        spec = robot.joints[i]
        cap = self.caps[joint]
        gains = approach_gains(cap)
        ring = self.rings.get(joint)
        leash_gains = gains
        registers = None
        if ring is not None:
            hw = robot.hardware
            registers = gains_to_registers(*gains, kt=hw.erob_kt[joint], gear=hw.erob_gear[joint],
                                           efficiency=hw.erob_torque_efficiency[joint])
            # The leash assumes the most stiffness the registers can give (a drive realises at most its nominal).
            leash_gains = registers_to_gains(registers, kt=hw.erob_kt[joint], gear=hw.erob_gear[joint])
        run = JointRun(i, joint, cap=cap, gains=gains, leash_gains=leash_gains, speed=self.speed,
                        rate=self.manager.update_rate, effort_limit=spec.effort_limit)
        if run.leash <= 0:
            raise JointFailed(f"the speed {self.speed:g} rad/s leaves no leash under the cap of {cap:g} Nm")
        self._check_range(joint)
        run.trace = self.traces.setdefault(joint, run.trace)  # the question's motion goes on the same trace
        state = self.manager.resources.state
        start = float(state.position[i])
        run.budget = travel_budget(spec)
        run.bounds = (start - run.budget, start + run.budget)
        q = state.position.copy()
        reach = []  # the model's gravity on the joint over its travel: how heavy it can be
        for value in np.linspace(*run.bounds, 17):
            q[i] = value
            reach.append(abs(float(self.host_gravity(q, self.model)[i])))
        run.weight = max(reach)
        hold = Hold(run, start, ANCHOR_S, passive=True)
        run.segment = hold
        run.gravity0 = float(self.host_gravity(state.position, self.model)[i])
        controller.runs = (run,)
        try:
            self._wait(lambda: hold.finished)
            run.anchor = float(np.mean(hold.efforts))
            run.gravity0 = float(self.host_gravity(state.position, self.model)[i])
            drive = approach_drive(robot, joint, run, registers, ring) if ring is not None and registers is not None \
                else contextlib.nullcontext("")
            with drive as torque_limit:
                self.outcomes[joint].drive_torque_limit = torque_limit
                try:
                    yield run
                finally:  # however it ended: held where it is, with the effort it applies, before the gains go
                    if self.aborted is None and run.refused is not None:
                        self.report(f"{joint}: the gate refused its command ({run.refused}); back to where it "
                                    "started")
                        self._segment(run, Move(run, start, float(state.position[i])))
                    if self.aborted is None:
                        self._segment(run, Hold(run, None, ANCHOR_S))
        finally:
            controller.capture.add(i)  # held from here where it ended, with the effort it applies there
            with contextlib.suppress(Aborted):  # (a controller that lost the commands takes nothing)
                self.ticks.until(lambda: i not in controller.capture or self.manager.active is not controller)
            if i in controller.capture:  # no tick came: take it here
                controller.capture.discard(i)
                controller.hold[i], controller.hold_effort[i] = float(state.position[i]), float(state.effort[i])
            controller.runs = ()

    def _joint(self, joint: str) -> None:
        robot, outcome = self.robot, self.outcomes[joint]
        i = robot.index(joint)
        spec = robot.joints[i]
        state = self.manager.resources.state
        began = state.stamp
        try:
            with self._moving(joint) as run:
                start = float(state.position[i])
                # The nearer stop first (by the prior's estimate of where the joint is).
                here = self.description_angles(state.position)[i]
                first = -1 if here - spec.lower <= spec.upper - here else 1
                self.report(f"{joint}: toward its {'upper' if first > 0 else 'lower'} stop "
                            f"(at most {self.caps[joint]:.2f} Nm into it)")
                a = self._segment(run, Approach(run, first, start, run.budget, self.measure))
                assert a.stop is not None
                if abs(a.stop - start) < RESTING_RAD:
                    # It rested on that stop: its weight there was the stop's, not in its feed-forward. Off the stop
                    # (where free motion teaches the feed-forward what gravity asks) and onto it again.
                    self.report(f"{joint}: it rested on that stop; again, from {RESTING_BACKOFF_RAD:g} rad off it")
                    off = self._segment(run, Move(run, a.stop - first * RESTING_BACKOFF_RAD,
                                                  a.unloaded(state.position[i]), leaving=True))
                    a = self._segment(run, Approach(run, first, off.target, run.budget, self.measure))
                assert a.stop is not None
                self.report(f"{joint}: stop at {a.stop:+.4f} rad; now the other one")
                backed = self._segment(run, Move(run, a.stop - first * BACKOFF_RAD, a.unloaded(state.position[i]),
                                                 leaving=True))
                b = Approach(run, -first, backed.target, run.budget, self.measure)
                self._segment(run, b)
                assert b.stop is not None
                self.report(f"{joint}: stop at {b.stop:+.4f} rad; back to where it started")
                self._segment(run, Move(run, start, b.unloaded(state.position[i]), leaving=True))
                outcome.peak_contact_nm = max(a.peak, b.peak)
                outcome.first_side = first
                self._conclude(joint, run, a, b)
            if outcome.calibration is not None:  # the joint has stopped: the loop's model may take it now
                self._know(i, outcome.calibration, settled=self._sweeps[joint].by_limits is not None)
        except JointFailed as exc:
            outcome.status, outcome.message = "failed", str(exc)
        except Aborted as exc:
            outcome.status, outcome.message = "aborted", str(exc)
            raise
        except PrimeError as exc:  # a drive setting that could not be made or restored: nothing more moves
            outcome.status, outcome.message = "aborted", str(exc)
            self.abort(str(exc))
            raise Aborted(str(exc)) from None
        finally:
            outcome.seconds = state.stamp - began
            if outcome.status == "direction_unknown":  # measured; its direction is settled at the end
                low, high = outcome.stops or (math.nan, math.nan)
                self.report(f"{joint}: stops {high - low:.3f} rad apart; its direction is settled at the end")
            else:
                self.report(f"{joint}: {outcome.status}" + (f" ({outcome.message})" if outcome.message else ""))

    def _conclude(self, joint: str, run: JointRun, a: Approach, b: Approach) -> None:
        robot, outcome = self.robot, self.outcomes[joint]
        i = robot.index(joint)
        spec = robot.joints[i]
        assert a.stop is not None and b.stop is not None  # both approaches ended pressing their stops
        low, high = sorted((a.stop, b.stop))
        outcome.stops = (low, high)
        outcome.stiffness = fit_stiffness(robot, joint, joint in self.rings, (run.kp, run.kd), [a.points, b.points])
        span, described = high - low, spec.upper - spec.lower
        if abs(span - described) > SPAN_TOLERANCE * described:
            outcome.status = "failed"
            outcome.message = (f"the stops are {span:.3f} rad apart, the description says {described:.3f}: something "
                               "stopped the joint short of a stop, or this is not the joint the file says")
            return
        same, flipped, by_limits = direction_from_limits(int(self.prior_direction[i]), (low, high), spec)
        # The direction is settled at the end, proximal first, when every other joint's calibration is known and
        # the model's gravity along this sweep can be trusted; meanwhile the limits' verdict, or the prior's.
        outcome.status = "direction_unknown"
        outcome.calibration = flipped if by_limits == -1 else same
        self._sweeps[joint] = _Sweep(same, flipped, by_limits, self.manager.resources.state.position.copy(),
                                     np.array(b.free))

    def _know(self, i: int, cal: JointCalibration, *, settled: bool) -> None:
        """Joint ``i``'s calibration, for the loop's model and, once ``settled`` (its direction told), the gate."""
        self.direction[i] = cal.direction
        self.offset[i] = cal.homing_offset
        if settled:
            self.controller.settled[i] = True
        self.controller.forget_gravity()

    def _resolve_directions(self) -> None:
        """Proximal first: each measured joint's direction from its limits and from the gravity measured along
        its sweep, fitted with the model in the configuration the other joints had then (their calibration known
        by now, the proximal ones' directions settled just before)."""
        for joint in sorted(self._sweeps, key=self._proximal_first):
            if self.outcomes[joint].status != "direction_unknown":
                continue
            outcome, sweep = self.outcomes[joint], self._sweeps[joint]
            by_gravity, gravity_text = self._gravity_verdict(joint, sweep)
            verdicts = {v for v in (sweep.by_limits, by_gravity) if v is not None}
            if len(verdicts) > 1:
                outcome.message = f"the limits and gravity disagree about the direction ({gravity_text})"
                outcome.calibration = sweep.same
                continue
            if not verdicts:
                outcome.message = f"the physics cannot tell the direction ({gravity_text})"
                continue
            verdict = verdicts.pop()
            outcome.calibration = sweep.same if verdict == 1 else sweep.flipped
            outcome.direction_source = " and ".join(name for name, v in (("limits", sweep.by_limits),
                                                                          ("gravity", by_gravity)) if v is not None)
            outcome.status = "done"
            outcome.message = f"direction from the {outcome.direction_source}; {gravity_text}"
            self._know(self.robot.index(joint), outcome.calibration, settled=True)

    def _proximal_first(self, joint: str) -> tuple[int, int]:
        return (0 if joint.startswith("left_") else 1, self.robot.index(joint))

    def _gravity_verdict(self, joint: str, sweep: _Sweep) -> tuple[int | None, str]:
        """Fit the effort measured along the sweep between the stops with the model's gravity under either
        direction."""
        if len(sweep.samples) < 10:
            return None, "too few free-motion samples"
        i = self.robot.index(joint)
        samples = sweep.samples
        take = np.linspace(0, len(samples) - 1, min(GRAVITY_SAMPLES, len(samples))).astype(int)
        samples = samples[take]
        q = sweep.config.copy()
        predicted: dict[int, Floats] = {}
        for hypothesis, cal in ((1, sweep.same), (-1, sweep.flipped)):
            direction, offset = self.direction.copy(), self.offset.copy()
            direction[i], offset[i] = cal.direction, cal.homing_offset
            values = []
            for position in samples[:, 0]:
                q[i] = position
                values.append(float(self.host_gravity(q, self.model, direction, offset)[i]))
            predicted[hypothesis] = np.array(values)
        return direction_from_gravity(samples[:, 0], samples[:, 1], predicted)

    # -- directions the physics could not tell --------------------------------------------------------------
    def _ask_directions(self) -> None:
        """Proximal first (so every axis is known when its question comes): one small motion toward the middle
        of the range, the question, and back; or the prior's direction with ``assume_direction``."""
        unknown = [j for j in self.joints if self.outcomes[j].status == "direction_unknown"
                   and self.outcomes[j].calibration is not None]
        unknown.sort(key=self._proximal_first)
        for joint in unknown:
            outcome = self.outcomes[joint]
            waiting = [j for j in self.joints if self._proximal_first(j)[0] == self._proximal_first(joint)[0]
                       and self.robot.index(j) < self.robot.index(joint) and not self.outcomes[j].done]
            if waiting and not self.assume_direction:  # its axis in the world depends on theirs
                outcome.message += f"; not asked: {', '.join(waiting)} must be calibrated first"
                continue
            if self.assume_direction:
                outcome.status = "done"
                outcome.direction_source = "assumed (--assume-direction)"
                outcome.message = "direction as in the prior file (assumed); " + outcome.message
                continue
            if isinstance(self.operator, Unattended):
                outcome.message += "; nobody to ask: give --assume-direction or run at the robot"
                continue
            self._ask(joint)
            if self.aborted is not None:
                return

    def _ask(self, joint: str) -> None:
        outcome = self.outcomes[joint]
        i = self.robot.index(joint)
        assert outcome.calibration is not None and outcome.stops is not None
        try:
            with self._moving(joint) as run:
                start = float(self.manager.resources.state.position[i])
                middle = 0.5 * (outcome.stops[0] + outcome.stops[1])
                side = 1 if middle >= start else -1
                desc = self.description_angles(self.manager.resources.state.position).copy()
                view, where = view_of(self.model.axis(joint, desc))
                self.operator.watch(joint)
                moved = self._segment(run, Move(run, start + side * PROMPT_RAD, start, leaving=True))  # it may rest
                answer = self.operator.turned_counter_clockwise(joint, view, where)
                self._segment(run, Move(run, start, moved.target))
        except JointFailed as exc:
            outcome.status, outcome.message = "failed", f"while asking for its direction: {exc}"
            return
        except Aborted as exc:
            outcome.status, outcome.message = "aborted", f"while asking for its direction: {exc}"
            raise
        except PrimeError as exc:
            outcome.status, outcome.message = "aborted", f"while asking for its direction: {exc}"
            self.abort(str(exc))
            raise Aborted(str(exc)) from None
        if answer is None:
            outcome.message += "; the direction question was not answered"
            return
        # With the prior's direction, a positive host motion turns the joint positive: counter-clockwise here.
        same = answer == (side > 0)
        if not same:
            spec = self.robot.joints[i]
            outcome.calibration = flip_direction(outcome.calibration, spec.lower, spec.upper)
        outcome.status = "done"
        outcome.direction_source = self.operator.answered_by
        outcome.message = (f"direction from {self.operator.answered_by}"
                           + ("" if same else ": it is wired the other way round, the flip is written"))
        self._know(i, outcome.calibration, settled=True)
