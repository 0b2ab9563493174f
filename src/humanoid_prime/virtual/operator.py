"""A scripted operator for the virtual Prime: backdrives joints to their mechanical stops through the plant,
as a person's hand does during calibration, so the whole workflow runs unattended.

An eRob joint is made damped-limp first (the same procedure as ``prime limp``: gate, position gain 0,
integral 0, damping kept, restored afterwards) with its CSP target following the joint; a Sito wrist is
limp already. The hand moves the joint slowly toward the lower stop and presses it there (at most a fraction of the
joint's effort limit), waits until it rests, does the same at the upper stop, brings the joint back to where it was
and holds it there until its drive holds it again, then lets go.

``WatchingOperator`` is the operator of the hands-free calibration: it lets every joint move and answers the
direction question from what the virtual robot's joint really did.

The operator has two hands: ``by_hand`` works through the left arm's joints with one and the other joints with
the other, at the same time, as a person at the robot does. The arms hang from a fixed torso, so one hand's
joint does not move under the other's; a calibration of all fourteen joints takes half as long.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence

import numpy as np

from humanoid_prime.calibration.gravity import GravityModel
from humanoid_prime.calibration.limp import DampedLimp
from humanoid_prime.config.robot import Robot
from humanoid_prime.drivers.erob.gains import vel_reg_exact
from humanoid_prime.errors import PrimeError
from humanoid_prime.runtime.session import Session
from humanoid_prime.virtual.ring.control import RingControl

PUSH_FRACTION = 0.5  # of the joint's effort limit: the most the hand pushes; overcomes gravity on every joint
HAND_SPEED_RAD_S = 1.0  # how fast the hand moves a joint toward a stop, as a person does
REST_SPEED_RAD_S = 0.005  # a joint slower than this for REST_S is resting against its stop
REST_S = 0.3
RETURN_TOLERANCE_RAD = 0.01  # a joint brought back within this of where it was is there
RETURN_GAIN = 3.0  # 1/s: the hand slows down as the joint nears where it was,
RETURN_SPEED_MIN_RAD_S = 0.05  # never below this


class ScriptedOperator:
    """Moves joints of the running ``session`` by hand through the virtual Prime's ``control`` channel."""

    def __init__(self, session: Session, control: RingControl, *, limp_kd: float = 2.0, timeout_s: float = 3.0,
                 stop: threading.Event | None = None) -> None:
        self.session = session
        self.robot = session.robot
        self.manager = session.manager
        self.control = control
        self.limp_kd = limp_kd
        self.timeout_s = timeout_s
        self.stop = stop or threading.Event()  # set when the run ends: let go at once

    def _wait_at_rest(self, index: int, travel_s: float = 0.0) -> float:
        """Wait until the joint rests (at most ``travel_s`` plus the timeout); returns its reading.

        Counted in control ticks, not wall time: "at rest" means slower than ``REST_SPEED_RAD_S`` in every
        measurement for ``REST_S`` worth of ticks, so a loop starved by a busy machine cannot fake it."""
        manager = self.manager
        velocity, position = manager.resources.state.velocity, manager.resources.state.position
        rest_ticks = max(1, round(REST_S * manager.update_rate))
        last_tick = manager.tick_count + round((travel_s + self.timeout_s) * manager.update_rate)
        seen = manager.tick_count
        still = 0
        while manager.tick_count < last_tick and not self.stop.is_set():
            if manager.tick_count == seen:
                time.sleep(0.25 * manager.period)  # until the next tick has measured the joint
                continue
            seen = manager.tick_count
            still = still + 1 if abs(float(velocity[index])) < REST_SPEED_RAD_S else 0
            if still >= rest_ticks:
                break
        return float(position[index])

    @contextlib.contextmanager
    def limp(self, joint: str) -> Iterator[None]:
        """Damped limp of an eRob joint for the duration (no-op for a Sito wrist, limp by default)."""
        hw = self.robot.hardware
        if joint not in hw.erob_slaves:
            yield
            return
        ethercat = self.session.ethercat
        if ethercat is None:
            raise PrimeError(f"{joint} is an eRob joint but this run has no EtherCAT bus")
        vel_reg = round(vel_reg_exact(self.limp_kd, kt=hw.erob_kt[joint], gear=hw.erob_gear[joint],
                                      efficiency=hw.erob_torque_efficiency[joint]))
        self.session.mark_limp(joint, True)
        try:
            with DampedLimp(ethercat.master, hw.erob_slaves[joint], vel_reg):
                yield
                self._wait_at_rest(self.robot.index(joint))
        finally:
            self.session.mark_limp(joint, False)

    def push_to(self, joint: str, side: int) -> float:
        """Move ``joint`` to its upper (side +1) or lower (side -1) stop and press it there; returns the reading
        once it rests."""
        spec = self.robot.joints[self.robot.index(joint)]
        self.control.call("hand", joint=joint, speed_rad_s=math.copysign(HAND_SPEED_RAD_S, side),
                          force_nm=PUSH_FRACTION * spec.effort_limit)
        return self._wait_at_rest(spec.index, (spec.upper - spec.lower) / HAND_SPEED_RAD_S)

    def let_go(self, joint: str) -> None:
        self.control.call("hand", joint=joint, speed_rad_s=0.0, force_nm=0.0)

    def by_hand(self, joints: Sequence[str], work: Callable[[str], None]) -> None:
        """``work(joint)`` for each of ``joints`` in order, the left arm's with one hand (a thread) and the rest
        with the other (this thread). A hand that fails makes the other let go (``stop``); its error is raised
        once both are done."""
        left = [j for j in joints if j.startswith("left_")]
        rest = [j for j in joints if not j.startswith("left_")]
        errors: list[BaseException] = []

        def hand(chosen: list[str]) -> None:
            try:
                for joint in chosen:
                    if self.stop.is_set():
                        return
                    work(joint)
            except BaseException as exc:  # the other hand lets go; the error is raised below
                errors.append(exc)
                self.stop.set()

        other = threading.Thread(target=hand, args=(left,), name="scripted-operator-left", daemon=True)
        other.start()
        try:
            hand(rest)
        finally:
            other.join()
        if errors:
            raise errors[0]

    def bring_back(self, joint: str, angle: float) -> None:
        """Move ``joint`` back to ``angle`` (its true angle: where the person sees it) and keep holding it there."""
        spec = self.robot.joints[self.robot.index(joint)]
        force, manager = PUSH_FRACTION * spec.effort_limit, self.manager
        last_tick = manager.tick_count + round(((spec.upper - spec.lower) / HAND_SPEED_RAD_S + self.timeout_s)
                                               * manager.update_rate)
        seen = manager.tick_count
        while manager.tick_count < last_tick and not self.stop.is_set():
            if manager.tick_count == seen:
                time.sleep(0.25 * manager.period)
                continue
            seen = manager.tick_count
            error = angle - float(self.control.call("joints")[joint])
            if abs(error) < RETURN_TOLERANCE_RAD:
                break
            speed = min(HAND_SPEED_RAD_S, max(RETURN_SPEED_MIN_RAD_S, RETURN_GAIN * abs(error)))
            self.control.call("hand", joint=joint, speed_rad_s=math.copysign(speed, error), force_nm=force)
        self.control.call("hand", joint=joint, speed_rad_s=0.0, force_nm=force)

    def stops(self, joint: str) -> tuple[float, float]:
        """The joint's readings at its lower and its upper stop; then, as a person returns a swept joint near where
        it was before its drive takes it again, it is brought back and held there by hand until its drive holds it,
        and let go. Every joint is swept from where the robot started, so no sweep folds an arm into the other or
        the torso that another sweep left somewhere else."""
        start = float(self.control.call("joints")[joint])
        try:
            with self.limp(joint):
                readings = self.push_to(joint, -1), self.push_to(joint, +1)
                self.bring_back(joint, start)
        finally:
            self.let_go(joint)
        return readings

    def sweep(self, joint: str) -> None:
        """Both stops, then back to where it was (``stops``)."""
        self.stops(joint)


class WatchingOperator:
    """The virtual robot's operator for the hands-free calibration (``calibration.auto.Operator``): lets every joint
    move, and answers the direction question as a person watching the robot does, from the joint's true motion
    (``true_angles()``: every joint's true angle, description frame) seen along the axis the question names."""

    answered_by = "the simulated operator's answer (it saw the joint's true motion; no one was asked)"

    def __init__(self, robot: Robot, true_angles: Callable[[], Mapping[str, float]],
                 model: GravityModel | None = None) -> None:
        self.robot = robot
        self.true_angles = true_angles
        self.model = GravityModel(robot, model.model if model is not None else None)
        self._before: Mapping[str, float] = {}

    def begin(self, joints: Sequence[str]) -> None:
        pass

    def confirm(self, joint: str) -> bool:
        return True

    def watch(self, joint: str) -> None:
        self._before = self.true_angles()

    def turned_counter_clockwise(self, joint: str, view: np.ndarray, where: str) -> bool | None:
        after = self.true_angles()
        turned = after[joint] - self._before[joint]
        q = np.array([after[name] for name in self.robot.names])
        facing = float(self.model.axis(joint, q) @ view)  # the true axis, toward the person or away
        if abs(turned) < 1e-3 or abs(facing) < 0.3:
            return None  # too small to see, or seen edge-on
        return turned * facing > 0
