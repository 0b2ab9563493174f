"""The one gate: every command the controller manager commits passes it, once per tick, whatever controller wrote
it (a mode, the hands-free calibration, the broadcaster-only run's passive command with its limp joints, REMOTE,
a policy, an add-on's controller). Nothing else writes the command the hardware components send: its arrays are
read-only, and only the gate's compiled commit copies a checked proposal into them.

1. The bounds (control/bounds.py): finite values, gains and efforts within the hardware file's command limits,
   targets within the joint limits (clipped within ``POSITION_MARGIN``). A controller that ``releases`` may leave
   a joint with no command (a NaN position, the rest zero): its drive holds on its own gains, a Sito is limp. A
   controller whose positions are in a frame of its own (a calibration's host frame) has the joint limits moved
   into it, and none where it does not know a joint's frame (the joint being found, held to the calibration's
   travel budget). A command out of bounds is a fault of its controller: the manager replaces the controller by
   its fallback within the tick.
2. The body (control/body.py): the pose the command asks for (targets where a joint has one, the measured position
   where it does not) against the robot's collision geometry. A command that brings two bodies of different
   classes (the left arm, the right arm, the body: torso, base and pedestal) closer than
   ``safety.collision_margin``, and nearer than they are now, does not reach the bus: every arm it drives into
   the other or into the body holds its last command (every joint that carries the arm keeps its last target,
   stiffness, damping and effort, and is asked no velocity),
   and the rest of the command goes through, checked again with the held arm in it (an arm that now closes on the
   held one holds too). The whole arm holds, not only the joints that close the distance: holding some joints of
   an arm while the others go on changes the arm's shape, which can close another distance, while its last
   command was checked. A command with no target on an arm (ZERO_TORQUE, DAMPING, a limp joint) leaves it where
   it is measured: nothing is held, and a command that widens a distance already under the margin (an arm
   leaving the torso it rests on) passes. Every refusal is counted by the pair of bodies, flagged on
   ``/safety_status`` with the two bodies and their distance, and told to the controller (``on_refused``).

A plan (STANDBY's entry trajectory) is checked once, when it is made (``check_plan``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from humanoid_prime.config.robot import Robot
from humanoid_prime.control._tick import OutputCheck
from humanoid_prime.control.body import BodyCheck, Contact
from humanoid_prime.control.bounds import CommandBounds
from humanoid_prime.control.controller import Controller
from humanoid_prime.control.flags import Level, SafetyFlags
from humanoid_prime.control.interfaces import CommandArrays, Frame, StateArrays

PLAN_STEP_RAD = 0.02  # a plan is checked at poses this far apart on its largest joint motion


@dataclass
class Refusal:
    """The gate's refusals in a run: how many, by pair of bodies, and the latest (the tick, the two bodies, their
    distance, the arms held)."""

    count: int = 0
    by_pair: dict[str, int] = field(default_factory=dict)
    last: Contact | None = None
    last_tick: int = -1
    held: tuple[str, ...] = ()

    def as_dict(self) -> dict[str, object]:
        last = self.last
        return {"count": self.count, "by_pair": dict(self.by_pair),
                "last": None if last is None else {"tick": self.last_tick, "bodies": [last.body1, last.body2],
                                                   "distance_m": round(last.distance, 4), "held": list(self.held)}}


class CommandGate:
    """The gate over the manager's ``proposal`` and ``command`` (5 x n each): ``propose`` starts the proposal as
    the last command, ``check_bounds`` and ``check_body`` check it, ``commit`` copies it into the command.

    ``body``: whether the body is checked; every run checks it (False only measures what it costs, in
    ``prime bench``). ``flags``: where a refusal is flagged (the manager's)."""

    def __init__(self, robot: Robot, proposal: CommandArrays, command: CommandArrays, flags: SafetyFlags, *,
                 body: bool = True) -> None:
        self.robot = robot
        self.proposal, self.command = proposal, command
        self.flags = flags
        self.bounds = CommandBounds(robot, release=True)
        self._output = OutputCheck(proposal.data, command.data, self.bounds.check)
        command.freeze()  # from here on only the compiled commit writes it
        hardware = robot.hardware
        self.body = BodyCheck(robot, hardware.collision_margin, hardware.stopping_time) if body else None
        self.margin = robot.hardware.collision_margin
        self.refused = Refusal()
        self._frame: Frame | None = None
        self._model_lower, self._model_upper = self.bounds.lower.copy(), self.bounds.upper.copy()
        self._a, self._b = np.zeros(robot.n), np.zeros(robot.n)
        self.held = np.zeros(robot.n, dtype=bool)  # the joints the last refusal held
        self._flagged = False  # a refusal stands on /safety_status

    def bind(self, controller: Controller) -> None:
        """Check ``controller``'s commands from now on: whether it may leave a joint with no command, and in which
        frame its positions are (the body's poses and the joint limits move with it)."""
        self.bounds.check.release = controller.releases
        self._frame = controller.frame
        if self.body is not None:
            self.body.frame(controller.frame)
        if self._frame is None:
            np.copyto(self.bounds.lower, self._model_lower)
            np.copyto(self.bounds.upper, self._model_upper)

    def _limits_in_frame(self) -> None:
        """The joint limits in the bound frame, as it is now (a calibration's changes as it learns): a limited
        joint's moved by the frame, another's none (the calibration holds it to its travel budget)."""
        frame = self._frame
        assert frame is not None  # called only while a frame is bound
        scale, shift = frame.scale, frame.shift
        with np.errstate(divide="ignore", invalid="ignore"):
            np.divide(self._model_lower - shift, scale, out=self._a)
            np.divide(self._model_upper - shift, scale, out=self._b)
        np.fmin(self._a, self._b, out=self.bounds.lower)
        np.fmax(self._a, self._b, out=self.bounds.upper)
        free = frame.limited == 0
        self.bounds.lower[free] = -np.inf
        self.bounds.upper[free] = np.inf

    def propose(self) -> None:
        self._output.propose()

    def commit(self) -> None:
        self._output.commit()

    def check_bounds(self) -> int:
        """The bounds' check of the proposal (OK, or what was found: ``bounds.refusal`` words it)."""
        if self._frame is not None:
            self._limits_in_frame()
        return int(self._output.check())

    def check_body(self, state: StateArrays, tick: int) -> Contact | None:
        """The body's check of the proposal; a refused arm holds its last command in the proposal. Returns the
        nearest pair refused (None: the proposal passed as it was)."""
        body, proposal = self.body, self.proposal.data
        if body is None or not body.check(proposal, state.position, state.velocity):
            if self._flagged:
                self._clear()
            return None
        closing = body.closing_found(proposal, state.position)
        if not closing:
            if self._flagged:
                self._clear()
            return None
        refused = body.contact(*closing[0])
        held = self.held
        held[:] = False
        arms: list[str] = []
        while closing:
            added = [arm for pair, _ in closing for arm in body.arms_of(pair) if arm not in arms]
            if not added:
                break  # every arm it closes is held: its last command was checked
            for arm in dict.fromkeys(added):
                arms.append(arm)
                held |= body.arm_joints[arm]
            np.copyto(proposal, self.command.data, where=held)
            self.proposal.velocity[held] = 0.0  # held still: no speed asked of it
            closing = body.closing_found(proposal, state.position) if body.check(proposal, state.position,
                                                                                   state.velocity) else []
        self._record(refused, tuple(arms), tick)
        return refused

    def _record(self, contact: Contact, arms: tuple[str, ...], tick: int) -> None:
        refused = self.refused
        key = f"{contact.body1}/{contact.body2}"
        refused.count += 1
        refused.by_pair[key] = refused.by_pair.get(key, 0) + 1
        fresh = refused.last_tick != tick - 1 or refused.held != arms or refused.last is None or \
            (refused.last.body1, refused.last.body2) != (contact.body1, contact.body2)
        refused.last, refused.last_tick, refused.held = contact, tick, arms
        self._flagged = True
        if fresh:  # one flag per episode: a stream pushing on is not a new flag every tick
            held = " and the ".join(arms) if arms else "nothing"
            verb = "hold their" if len(arms) > 1 else "holds its"
            self.flags.set_flag("body", f"command refused: {contact.words(self.margin)}; the {held} {verb} last "
                                        "command", Level.WARN)

    def _clear(self) -> None:
        self._flagged = False
        self.flags.clear_flag("body")

    def check_plan(self, positions: npt.NDArray[np.float64], stiffness: float,
                   state: StateArrays) -> tuple[Contact, float] | None:
        """Check a plan once: the straight lines in joint space through ``positions`` (k x n targets, held with
        ``stiffness``), at poses ``PLAN_STEP_RAD`` apart. The first pair it closes and how far along the plan (0 to
        1), or None."""
        body = self.body
        if body is None or stiffness <= 0.0 or len(positions) == 0:
            return None
        poses = [positions[0]]
        for a, b in zip(positions[:-1], positions[1:], strict=True):
            steps = max(1, int(np.ceil(np.abs(b - a).max() / PLAN_STEP_RAD)))
            poses += [a + (b - a) * (s / steps) for s in range(1, steps + 1)]
        command = np.zeros((5, self.robot.n))
        command[3] = stiffness
        for k, pose in enumerate(poses):
            command[0] = pose
            closing = body.closing(command, state.position)
            if closing:
                return closing[0], k / max(1, len(poses) - 1)
        return None
