"""Hands-free calibration (DESIGN §5): Prime drives each joint into its mechanical stops itself, gently, finds its
offset from both stops and measures what its impedance really is.

One joint moves at a time, arm by arm from the hand to the shoulder; the others hold where they are (an eRob on
its drive's own gains, any other joint on the standby gains with the effort it applied when its hold began, plus
a slow integral of its sag: no push where it rests, no model needed). For the joint that moves
(``calibration.approach``):

- impedance: approach gains that follow from its contact-effort cap; an eRob on a ring gets them in its loop-gain
  registers (gate, changed-only writes in the never-stiffer order), with a following-error window wide enough for
  them and its own torque limit (0x6072) lowered where it has one, all restored as found (``GainOverride``); every
  other joint (a Sito wrist, a simulated joint) gets them in its per-tick MIT command;
- effort feed-forward: the holding effort measured before it moves, plus the model's change of gravity since
  (``calibration.gravity``), plus what free motion teaches (the model is only as good as the calibration it is
  evaluated with), so the cap is the force at the stop, not the arm's weight;
- motion: to the nearer stop, then the other, then back to where it started, at the speed cap, the target on a
  leash and contact seen from three signs together; the stop's position is recorded while it is pressed with the
  leash, and the effort is logged while the press eases and while it pushes with a velocity command (realised
  stiffness and damping); a stop it rested on at the start is approached again once free motion has learnt its
  weight;
- budgets: the target never leaves the joint's range plus a margin around where it started; a stop not found
  within its travel or time budget fails the joint.

Offsets come from both stops with the sweep's formula (``calibration.math``). Directions are settled at the end,
proximal first, once every joint's offset is known: from the limits (an asymmetric range) and the gravity measured
along each sweep (``calibration.direction``); where neither tells, one small motion and a plain question for each
joint whose proximal joints are known (``Operator``), or the prior's with ``assume_direction``. A flip is written
only on such evidence, and reported.

Any fault or lost device (an ERROR on ``/safety_status``), a held joint that moves, or ``abort()`` (a key
press) stops the moving joint where it is, restores its drive and ends the run.

The per-tick part runs in the control loop (a ``/prime/joint_states`` subscriber, between read and write, in a
broadcaster-only run that leaves the commands to it); the sequence (drive settings over SDO, the operator)
runs in ``run`` and waits for ticks through ``Ticks``: the loop's, or in virtual time a stepper it drives itself.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from humanoid_prime.calibration.approach import (
    MAX_SPEED_RAD_S,
    Approach,
    Hold,
    JointRun,
    Move,
    Segment,
    Tick,
    Trace,
    approach_gains,
)
from humanoid_prime.calibration.direction import direction_from_gravity, direction_from_limits, view_of
from humanoid_prime.calibration.gravity import GravityModel
from humanoid_prime.calibration.limp import GainOverride, GainSnapshot
from humanoid_prime.calibration.math import flip_direction, mirror_check
from humanoid_prime.config.calibration import Calibration, JointCalibration
from humanoid_prime.config.robot import Robot
from humanoid_prime.control.flags import Level
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.topics import JOINT_STATES, SAFETY_STATUS, JointState, SafetyStatus
from humanoid_prime.drivers.erob.constants import COUNTS_PER_RAD, RATED_TORQUE_NM
from humanoid_prime.drivers.erob.gains import ErobRegisters, gains_to_registers, registers_to_gains
from humanoid_prime.drivers.erob.objects import FOLLOWING_ERROR_WINDOW, RATED_TORQUE
from humanoid_prime.drivers.ethercat.sdo_client import SdoClient, SizedSdo
from humanoid_prime.drivers.sito.protocol import sito_model
from humanoid_prime.errors import ConfigError, PrimeError
from humanoid_prime.modes import Mode

CONTACT_FRACTION = 0.1  # default contact-effort cap: this fraction of the joint's effort limit
BACKOFF_RAD = 0.05
RESTING_RAD = 0.02  # a stop found this close to where the joint started: it rested on it
RESTING_BACKOFF_RAD = 0.15  # then it moves this far off before it approaches again
TRAVEL_MARGIN_RAD = 0.1  # beyond the joint's range (plus 5 %), the most the target travels toward a stop
SPAN_TOLERANCE = 0.05  # the stops' spacing must be the described range within this share
HOLD_TOLERANCE_RAD = 0.05  # a held joint that moves further has been pushed: stop
HOLD_INTEGRAL_S = 0.5  # time constant with which a per-tick hold takes up a changing load
ANCHOR_S = 0.2  # the holding torque is averaged this long before a joint moves
PROMPT_RAD = 0.15  # the prompted motion that asks the operator for a direction
GRAVITY_SAMPLES = 60
GRAVITY_STEP_RAD = 0.005  # the loop evaluates the model's gravity again once a joint has moved this far
TICK_TIMEOUT_S = 5.0  # wall seconds without a control tick: the loop is gone
DRIVE_LIMIT_MARGIN = 1.25  # the drive's own torque limit over the most the approach asks of it

# CiA402 0x6072 max torque, UNSIGNED16 per mille of 0x6076. ZeroErr's EDS V1.5 does not list it, so it is probed.
MAX_TORQUE = (0x6072, 0x00)
WINDOW = (FOLLOWING_ERROR_WINDOW, 0x00)


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


def distal_first(robot: Robot, joints: Sequence[str]) -> list[str]:
    """``joints`` in the order they are calibrated: arm by arm (left first), from the hand to the shoulder."""
    def key(joint: str) -> tuple[int, int]:
        return (0 if joint.startswith("left_") else 1, -robot.index(joint))
    return sorted(joints, key=key)


# ---- the operator -------------------------------------------------------------------------------------------


class Operator(Protocol):
    """The person (or the virtual robot's scripted operator) at the robot."""

    answered_by: str  # where an answer comes from, in the report: "the operator's answer", ...

    def begin(self, joints: Sequence[str]) -> None:
        """Before anything moves (on the robot: the e-stop reminder)."""

    def confirm(self, joint: str) -> bool:
        """May ``joint`` move now? (On the robot: Enter moves it, anything else skips it.)"""

    def watch(self, joint: str) -> None:
        """``joint`` is about to make the prompted motion."""

    def turned_counter_clockwise(self, joint: str, view: np.ndarray, where: str) -> bool | None:
        """Seen from ``where`` (looking along -``view``), did ``joint`` just turn counter-clockwise? None: cannot
        tell."""


class Unattended:
    """No one at the robot: every joint may move, no question can be answered."""

    answered_by = "nobody"

    def begin(self, joints: Sequence[str]) -> None:
        pass

    def confirm(self, joint: str) -> bool:
        return True

    def watch(self, joint: str) -> None:
        pass

    def turned_counter_clockwise(self, joint: str, view: np.ndarray, where: str) -> bool | None:
        return None


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


# ---- results ------------------------------------------------------------------------------------------------

@dataclass
class Stiffness:
    """The impedance a joint realised against its stops: torque over position error, and over speed error."""

    family: str
    kp_asked: float  # what the host asked for (eRob: the registers' nominal stiffness)
    kd_asked: float
    kp: float
    kd: float
    points: int

    @property
    def kp_ratio(self) -> float:
        return self.kp / self.kp_asked

    @property
    def kd_ratio(self) -> float:
        return self.kd / self.kd_asked

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"kp_asked": self.kp_asked, "kp_realised": self.kp, "kp_ratio": self.kp_ratio,
                               "kd_asked": self.kd_asked, "kd_realised": self.kd, "kd_ratio": self.kd_ratio,
                               "points": self.points}
        if self.family == "erob":
            out["torque_efficiency"] = self.kp_ratio  # realised/nominal: the hardware file's correction
        else:
            model = sito_model("TA40-50")
            out["kp_divisor"] = model.kp_divisor * self.kp_ratio  # what the firmware divides by, measured
            out["kd_divisor"] = model.kd_divisor * self.kd_ratio
        return out


@dataclass
class JointOutcome:
    joint: str
    status: str  # done | skipped | failed | aborted | direction_unknown | not_reached
    message: str = ""
    prior: JointCalibration = field(default_factory=JointCalibration)
    calibration: JointCalibration | None = None  # what is written (None: the prior is kept)
    stops: tuple[float, float] | None = None  # identity frame (prior direction, offset 0), lower reading first
    first_side: int = 0
    direction_source: str = ""
    stiffness: Stiffness | None = None
    peak_contact_nm: float = 0.0
    cap_nm: float = 0.0
    seconds: float = 0.0  # robot time the joint took
    drive_torque_limit: str = ""  # what became of the drive's own torque limit

    @property
    def done(self) -> bool:
        return self.status == "done"

    @property
    def flipped(self) -> bool:
        return self.calibration is not None and self.calibration.direction != self.prior.direction

    def as_dict(self) -> dict[str, Any]:
        cal = self.calibration
        return {"status": self.status, "message": self.message,
                "direction": cal.direction if cal else self.prior.direction,
                "homing_offset": cal.homing_offset if cal else self.prior.homing_offset,
                "prior_direction": self.prior.direction, "prior_offset": self.prior.homing_offset,
                "flipped": self.flipped, "direction_source": self.direction_source,
                "stops": list(self.stops) if self.stops else None, "cap_nm": self.cap_nm,
                "peak_contact_nm": self.peak_contact_nm, "seconds": self.seconds,
                "drive_torque_limit": self.drive_torque_limit,
                "stiffness": self.stiffness.as_dict() if self.stiffness else None}


@dataclass
class AutoResult:
    calibration: Calibration  # every joint: the new one where done, the prior elsewhere
    outcomes: dict[str, JointOutcome]
    traces: dict[str, Trace]
    asked: tuple[str, ...]
    aborted: str | None
    robot: Robot

    @property
    def complete(self) -> bool:
        """Every joint asked for was calibrated and nothing stopped the run."""
        return self.aborted is None and all(self.outcomes[j].done for j in self.asked)

    def as_dict(self) -> dict[str, Any]:
        mirror = mirror_check(self.calibration, self.robot)
        return {"complete": self.complete, "aborted": self.aborted,
                "joints": {j: self.outcomes[j].as_dict() for j in self.asked},
                "mirror": [{"left": m.left, "right": m.right, "left_offset": m.left_offset,
                            "right_offset": m.right_offset, "relation": m.relation, "residual": m.residual,
                            "ok": m.ok} for m in mirror]}


@dataclass
class _Sweep:
    """What a joint's stops and its sweep between them left for its direction: the calibration either way, the
    limits' verdict, where every joint was meanwhile (host frame) and (position, effort) in free motion."""

    same: JointCalibration
    flipped: JointCalibration
    by_limits: int | None
    config: np.ndarray
    samples: np.ndarray


# ---- the procedure ------------------------------------------------------------------------------------------

class AutoCalibration:
    """Calibrates ``joints`` of the running broadcaster-only ``manager`` (module docstring).

    ``model``: the gravity model to use (its compiled model is shared; build it before the buses run).
    ``prior``: the calibration the run's host frame is built from (its directions, offsets 0) and the one kept
    for joints not done. ``rings``: joint -> (SDO client, ring position) for every joint whose impedance is its
    drive's registers (eRob on a ring); every other joint takes gains per tick. ``config``: the controllers file
    (the standby gains hold the per-tick joints).
    """

    def __init__(self, manager: ControllerManager, prior: Calibration, joints: Sequence[str], *,
                 rings: Mapping[str, tuple[SdoClient, int]] | None = None, operator: Operator | None = None,
                 ticks: Ticks, speed: float = MAX_SPEED_RAD_S, assume_direction: bool = False,
                 measure: bool = True, report: Callable[[str], None] | None = None,
                 model: GravityModel | None = None) -> None:
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
        self.report = report or (lambda text: None)
        self.caps = {j: contact_cap(robot, j) for j in self.joints}
        self.gravity = model or GravityModel(robot)  # the loop's
        self.model = GravityModel(robot, self.gravity.model)  # the sequence's (the threads never share data)
        self.hold_gains = manager.config.mode_gains()[Mode.STANDBY]
        n = robot.n
        self.prior_direction = prior.direction_array(robot.names)
        self.prior_offset = prior.offset_array(robot.names)
        self.direction = self.prior_direction.copy()  # best knowledge: the prior, the new values where done
        self.offset = self.prior_offset.copy()
        self.per_tick = np.array([j not in self.rings for j in robot.names])
        self.hold = np.full(n, np.nan)  # where each joint is held (NaN until the run's first tick)
        # A per-tick joint holds with the effort it applied when its hold began plus what a slow integral of its sag
        # adds since (as the arm moves, gravity on it changes): no push where it rests, no model needed.
        self.hold_effort = np.zeros(n)
        self.effort_limit = robot.effort_limit
        self._capture: set[int] = set()  # joints whose hold is taken afresh at the next tick
        self.outcomes: dict[str, JointOutcome] = {
            j: JointOutcome(j, "not_reached", prior=prior.joints[j], cap_nm=self.caps[j]) for j in self.joints}
        self.traces: dict[str, Trace] = {}
        self._sweeps: dict[str, _Sweep] = {}
        self.moving: JointRun | None = None
        self.aborted: str | None = None
        self._abort_request: str | None = None
        self._status: SafetyStatus | None = None
        self._running = False
        self._last_t: float | None = None
        self._gravity, self._gravity_at = np.zeros(n), None

    # -- the loop side --------------------------------------------------------------------------------------
    def attach(self) -> None:
        topics = self.manager.topics
        topics.subscribe(SAFETY_STATUS, self._on_status, latched=True)
        topics.subscribe(JOINT_STATES, self._on_joint_states)

    def detach(self) -> None:
        topics = self.manager.topics
        topics.unsubscribe(JOINT_STATES, self._on_joint_states)
        topics.unsubscribe(SAFETY_STATUS, self._on_status)

    def abort(self, reason: str) -> None:
        """Stop the run as soon as possible (any thread): the moving joint holds where it is."""
        if self._abort_request is None:
            self._abort_request = reason

    def _on_status(self, status: SafetyStatus) -> None:
        self._status = status

    def _errors(self) -> list[str]:
        status = self._status
        if status is None:
            return []
        return [f"{key}: {status.flags[key]}" for key, level in status.levels.items() if level is Level.ERROR]

    def description_angles(self, q: np.ndarray, direction: np.ndarray | None = None,
                           offset: np.ndarray | None = None) -> np.ndarray:
        """The joints' description angles from host-frame ``q``, with the best calibration known (or the one given)."""
        direction = self.direction if direction is None else direction
        offset = self.offset if offset is None else offset
        return direction * (self.prior_direction * q - offset)

    def host_gravity(self, q: np.ndarray, model: GravityModel | None = None, direction: np.ndarray | None = None,
                     offset: np.ndarray | None = None) -> np.ndarray:
        """The model's holding torque of every joint at host-frame ``q``, in the host frame (``model``: the loop's
        unless given; the calibration: the best known unless given)."""
        direction = self.direction if direction is None else direction
        angles = self.description_angles(q, direction, offset)
        angles[~np.isfinite(angles)] = 0.0  # a joint off this run's buses: taken as hanging
        torques = (model or self.gravity).torques(angles)
        return self.prior_direction * direction * torques

    def _on_joint_states(self, msg: JointState) -> None:
        if not self._running:
            return
        resources = self.manager.resources
        state, command = resources.state, resources.command
        q = state.position
        t = msg.stamp
        dt = 1.0 / self.manager.update_rate if self._last_t is None else max(t - self._last_t, 1e-6)
        self._last_t = t
        if not np.isfinite(self.hold).any():  # the first tick of the run: hold every joint where it is now
            self._capture.update(range(self.robot.n))
        if self._capture:
            taken = list(self._capture)
            self._capture.clear()
            self.hold[taken] = q[taken]
            self.hold_effort[taken] = state.effort[taken]
        if self._abort_request is not None and self.aborted is None:
            self.aborted = self._abort_request
        if self.aborted is None:
            errors = self._errors()
            if errors:
                self.aborted = "fault: " + "; ".join(errors)
        moving = self.moving
        segment = moving.segment if moving is not None else None
        active = moving is not None and not (isinstance(segment, Hold) and segment.passive)
        held = np.isfinite(self.hold)
        if active:
            held[moving.index] = False
        if self.aborted is None:
            drift = np.abs(q - self.hold)
            drift[~held] = 0.0
            if drift.max(initial=0.0) > HOLD_TOLERANCE_RAD:
                k = int(np.argmax(drift))
                self.aborted = (f"{self.robot.names[k]} moved {drift[k]:.3f} rad while it was held (pushed, or "
                                "its drive let go)")
        kp, kd = self.hold_gains
        hold = held & self.per_tick
        sag = np.where(hold, self.hold - q, 0.0)
        self.hold_effort += min(1.0, dt / HOLD_INTEGRAL_S) * kp * sag
        np.clip(self.hold_effort, -self.effort_limit, self.effort_limit, out=self.hold_effort)
        command.position[hold] = self.hold[hold]
        command.velocity[hold] = 0.0
        command.effort[hold] = self.hold_effort[hold]
        command.stiffness[hold] = kp
        command.damping[hold] = kd
        release = ~self.per_tick  # drives holding on their own gains: no command
        if active:
            release[moving.index] = False
        command.data[:, release] = 0.0
        command.position[release] = np.nan
        if moving is None:
            return
        i = moving.index
        if self._gravity_at is None or np.abs(q - self._gravity_at).max() > GRAVITY_STEP_RAD:
            self._gravity, self._gravity_at = self.host_gravity(q), q.copy()  # the model, when it has changed
        gravity = self._gravity
        ff = moving.anchor + gravity[i] - moving.gravity0 + moving.correction
        ff = min(max(ff, -moving.effort_limit), moving.effort_limit)
        if self.aborted is not None and not isinstance(segment, Hold):
            segment = moving.segment = Hold(moving)  # stop here, at once
        if segment is not None and not segment.finished and segment.failure is None:
            segment.update(Tick(t, dt, float(q[i]), float(state.velocity[i]), float(state.effort[i]), ff))
            ff = moving.anchor + gravity[i] - moving.gravity0 + moving.correction  # what the update taught it
            ff = min(max(ff, -moving.effort_limit), moving.effort_limit)
        if not active or segment is None or segment.target is None:
            return
        low, high = moving.bounds
        command.position[i] = min(max(segment.target, low), high)
        command.velocity[i] = min(max(segment.velocity, -moving.speed), moving.speed)
        command.effort[i] = ff
        command.stiffness[i] = moving.kp
        command.damping[i] = moving.kd
        trace = moving.trace
        trace.t.append(t)
        trace.q.append(float(q[i]))
        trace.target.append(float(command.position[i]))
        trace.effort.append(float(state.effort[i]))

    # -- the sequence ---------------------------------------------------------------------------------------
    def run(self) -> AutoResult:
        """Calibrate every joint asked for, then ask for the directions the physics could not tell."""
        self._start()
        try:
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
            if self.aborted is None:
                self.aborted = str(exc)
        finally:
            self._finish()
        return self.result()

    def _start(self) -> None:
        errors = self._errors()
        if errors:
            raise PrimeError("the robot reports problems; nothing was moved: " + "; ".join(errors))
        self._running = True
        self._wait(lambda: True)  # one tick: the joints hold from here on, where that tick found them

    def _finish(self) -> None:
        self._running = False

    def _wait(self, done: Callable[[], bool]) -> None:
        seen = self.manager.tick_count
        self.ticks.until(lambda: self.aborted is not None or (self.manager.tick_count > seen and done()))
        if self.aborted is not None:
            raise Aborted(self.aborted)

    def _segment(self, run: JointRun, segment: Segment) -> Segment:
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

    @contextlib.contextmanager
    def _moving(self, joint: str) -> Iterator[JointRun]:
        """``joint`` anchored where it is (its holding effort measured), on its approach impedance, for the
        block; afterwards anchored where it ended, on the impedance it had, and held there."""
        robot = self.robot
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
        run.trace = self.traces.setdefault(joint, run.trace)  # the question's motion goes on the same trace
        state = self.manager.resources.state
        start = float(state.position[i])
        span = spec.upper - spec.lower
        budget = span * (1 + SPAN_TOLERANCE) + TRAVEL_MARGIN_RAD
        run.bounds = (start - budget, start + budget)
        q = state.position.copy()
        reach = []  # the model's gravity on the joint over its travel: how heavy it can be
        for value in np.linspace(start - budget, start + budget, 17):
            q[i] = value
            reach.append(abs(float(self.host_gravity(q, self.model)[i])))
        run.weight = max(reach)
        hold = Hold(run, start, ANCHOR_S, passive=True)
        run.segment = hold
        run.gravity0 = float(self.host_gravity(state.position, self.model)[i])
        self.moving = run
        try:
            self._wait(lambda: hold.finished)
            run.anchor = float(np.mean(hold.efforts))
            run.gravity0 = float(self.host_gravity(state.position, self.model)[i])
            with self._impedance(joint, run, registers, ring, start, budget):
                try:
                    yield run
                finally:  # however it ended: held where it is, with the effort it applies, before the gains go
                    if self.aborted is None:
                        self._segment(run, Hold(run, None, ANCHOR_S))
        finally:
            self._capture.add(i)  # held from here where it ended, with the effort it applies there
            with contextlib.suppress(Aborted):
                self.ticks.until(lambda: i not in self._capture)
            if i in self._capture:  # no tick came: take it here
                self._capture.discard(i)
                self.hold[i], self.hold_effort[i] = float(state.position[i]), float(state.effort[i])
            self.moving = None

    @contextlib.contextmanager
    def _impedance(self, joint: str, run: JointRun, registers: ErobRegisters | None,
                   ring: tuple[SdoClient, int] | None, start: float, budget: float) -> Iterator[None]:
        if ring is None or registers is None:
            yield
            return
        sdo, position = ring
        objects = SizedSdo(sdo)
        kp_nominal, _ = registers_to_gains(registers, kt=self.robot.hardware.erob_kt[joint],
                                           gear=self.robot.hardware.erob_gear[joint])
        # The most effort the approach asks: the gravity along the travel, the anchor's offset from it, the cap.
        most = run.weight + abs(run.anchor - run.gravity0) + run.cap
        window = math.ceil(2.0 * most / kp_nominal * COUNTS_PER_RAD)
        try:
            rated = objects.read(position, (RATED_TORQUE, 0)) / 1000.0 or RATED_TORQUE_NM
        except PrimeError:
            rated = RATED_TORQUE_NM
        limit = math.ceil(DRIVE_LIMIT_MARGIN * most / rated * 1000.0)

        def wanted(snapshot: GainSnapshot) -> ErobRegisters:
            return registers

        override = _ApproachOverride(sdo, position, wanted, window, limit)
        with override:
            outcome = self.outcomes[joint]
            if MAX_TORQUE in override.missing:
                outcome.drive_torque_limit = "none: the drive has no 0x6072 (" + override.missing[MAX_TORQUE] + ")"
            else:
                outcome.drive_torque_limit = (f"0x6072 {override.torque_limit} per mille of {rated:g} Nm "
                                              f"({override.torque_limit * rated / 1000.0:.2f} Nm) while it moved, "
                                              f"then {override.extra_snapshot[MAX_TORQUE]} again")
            yield

    def _joint(self, joint: str) -> None:
        robot, outcome = self.robot, self.outcomes[joint]
        i = robot.index(joint)
        spec = robot.joints[i]
        began = self.manager.resources.state.stamp
        try:
            with self._moving(joint) as run:
                start = float(self.manager.resources.state.position[i])
                # The nearer stop first (by the prior's estimate of where the joint is).
                here = self.description_angles(self.manager.resources.state.position)[i]
                first = -1 if here - spec.lower <= spec.upper - here else 1
                span = spec.upper - spec.lower
                budget = span * (1 + SPAN_TOLERANCE) + TRAVEL_MARGIN_RAD
                self.report(f"{joint}: toward its {'upper' if first > 0 else 'lower'} stop "
                            f"(at most {self.caps[joint]:.2f} Nm into it)")
                a = self._segment(run, Approach(run, first, start, budget, self.measure))
                assert isinstance(a, Approach) and a.stop is not None
                if abs(a.stop - start) < RESTING_RAD:
                    # It rested on that stop: its weight there was the stop's, not in its feed-forward. Off the stop
                    # (where free motion teaches the feed-forward what gravity asks) and onto it again.
                    self.report(f"{joint}: it rested on that stop; again, from {RESTING_BACKOFF_RAD:g} rad off it")
                    position = self.manager.resources.state.position
                    off = self._segment(run, Move(run, a.stop - first * RESTING_BACKOFF_RAD, a.unloaded(position[i]),
                                                   leaving=True))
                    a = self._segment(run, Approach(run, first, off.target, budget, self.measure))
                    assert isinstance(a, Approach) and a.stop is not None
                self.report(f"{joint}: stop at {a.stop:+.4f} rad; now the other one")
                position = self.manager.resources.state.position
                backed = self._segment(run, Move(run, a.stop - first * BACKOFF_RAD, a.unloaded(position[i]),
                                                  leaving=True))
                b = Approach(run, -first, backed.target, budget, self.measure)
                self._segment(run, b)
                assert b.stop is not None
                self.report(f"{joint}: stop at {b.stop:+.4f} rad; back to where it started")
                self._segment(run, Move(run, start, b.unloaded(position[i]), leaving=True))
                outcome.seconds = self.manager.resources.state.stamp - began
                outcome.peak_contact_nm = max(a.peak, b.peak)
                outcome.first_side = first
                self._conclude(joint, run, a, b)
            if outcome.calibration is not None:  # the joint has stopped: the loop's model may take it now
                self._know(i, outcome.calibration)  # (its direction may still change at the end)
        except JointFailed as exc:
            outcome.status, outcome.message = "failed", str(exc)
            outcome.seconds = self.manager.resources.state.stamp - began
        except Aborted as exc:
            outcome.status, outcome.message = "aborted", str(exc)
            outcome.seconds = self.manager.resources.state.stamp - began
            raise
        except PrimeError as exc:  # a drive setting that could not be made or restored: nothing more moves
            outcome.status, outcome.message = "aborted", str(exc)
            outcome.seconds = self.manager.resources.state.stamp - began
            self.abort(str(exc))
            raise Aborted(str(exc)) from None
        finally:
            if outcome.status == "direction_unknown":  # measured; its direction is settled at the end
                low, high = outcome.stops or (math.nan, math.nan)
                self.report(f"{joint}: stops {high - low:.3f} rad apart; its direction is settled at the end")
            else:
                self.report(f"{joint}: {outcome.status}" + (f" ({outcome.message})" if outcome.message else ""))

    def _conclude(self, joint: str, run: JointRun, a: Approach, b: Approach) -> None:
        robot, outcome = self.robot, self.outcomes[joint]
        i = robot.index(joint)
        spec = robot.joints[i]
        low, high = sorted((a.stop, b.stop))
        outcome.stops = (low, high)
        outcome.stiffness = self._stiffness(joint, run, (a, b))
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

    def _know(self, i: int, cal: JointCalibration) -> None:
        self.direction[i] = cal.direction
        self.offset[i] = cal.homing_offset
        self._gravity_at = None  # the loop's model is evaluated afresh with it

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
            self._know(self.robot.index(joint), outcome.calibration)

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
        predicted: dict[int, np.ndarray] = {}
        for hypothesis, cal in ((1, sweep.same), (-1, sweep.flipped)):
            direction, offset = self.direction.copy(), self.offset.copy()
            direction[i], offset[i] = cal.direction, cal.homing_offset
            values = []
            for position in samples[:, 0]:
                q[i] = position
                values.append(float(self.host_gravity(q, self.model, direction, offset)[i]))
            predicted[hypothesis] = np.array(values)
        return direction_from_gravity(samples[:, 0], samples[:, 1], predicted)

    def _stiffness(self, joint: str, run: JointRun, stops: Sequence[Approach]) -> Stiffness | None:
        """Realised stiffness and damping: the effort pressed into both stops against the lag and the velocity
        command, ``effort = kp * lag + kd * speed + (one constant per stop)``, by least squares."""
        pressed = [stop for stop in stops if len(stop.points) >= 5]
        if not pressed:
            return None
        rows, efforts = [], []
        for k, stop in enumerate(pressed):
            for lag, speed, effort in stop.points:
                rows.append([lag, speed, *(1.0 if m == k else 0.0 for m in range(len(pressed)))])
                efforts.append(effort)
        (kp, kd, *_), *_ = np.linalg.lstsq(np.array(rows), np.array(efforts), rcond=None)
        hw = self.robot.hardware
        if joint in self.rings:
            registers = gains_to_registers(run.kp, run.kd, kt=hw.erob_kt[joint], gear=hw.erob_gear[joint],
                                           efficiency=hw.erob_torque_efficiency[joint])
            kp_asked, kd_asked = registers_to_gains(registers, kt=hw.erob_kt[joint], gear=hw.erob_gear[joint])
            family = "erob"
        else:
            kp_asked, kd_asked = run.kp, run.kd
            family = "erob" if joint in hw.erob_slaves else "sito"
        return Stiffness(family, kp_asked, kd_asked, float(kp), float(kd), len(efforts))

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
        self._know(i, outcome.calibration)


class _ApproachOverride(GainOverride):
    """The approach gains with a following-error window wide enough for them and the drive's own torque limit
    lowered to what the approach needs (never raised)."""

    def __init__(self, sdo: SdoClient, position: int, wanted: Callable[[GainSnapshot], ErobRegisters],
                 window: int, torque_limit: int) -> None:
        super().__init__(sdo, position, wanted, objects={WINDOW: window}, optional={MAX_TORQUE: torque_limit})
        self.window = window
        self.torque_limit = torque_limit

    def __enter__(self) -> _ApproachOverride:
        # Widen the window only, and lower the torque limit only, from what the drive holds.
        self.snapshot = None
        objects = self.objects
        try:
            found = objects.read(self.position, WINDOW)
            self.extra[WINDOW] = max(found, self.window)
        except PrimeError:
            pass
        try:
            found = objects.read(self.position, MAX_TORQUE)
            self.torque_limit = min(found, self.torque_limit)
            self.optional[MAX_TORQUE] = self.torque_limit
        except PrimeError:
            pass
        super().__enter__()
        return self
