"""The hands-free calibration's per-tick law, as a controller of the manager (``calibration.auto`` runs the
sequence around it): what every joint is commanded each tick, through the manager's gate like any command.

- Every joint not moving holds where it was when its hold began: an eRob on a ring on its drive's own gains (no
  command: the drive keeps its target), any other joint (a Sito wrist, a simulated joint) on the standby gains with
  the effort it applied when its hold began plus a slow integral of its sag (no push where it rests, no model
  needed). ``settle_effort``: the per-tick joints start with the model's gravity as that effort instead (a robot
  that begins limp, as a simulation does, is held up at once).
- Each moving joint (``runs``: one ``JointRun`` per joint, several may move at once, each with its own segment)
  follows its segment's target on its approach gains, with its effort feed-forward (``JointRun.feed_forward``:
  the holding effort measured before it moved, the model's change of gravity since, what free motion taught it).
- A fault or lost device (an ERROR on ``/safety_status``), a held joint that moves further than
  ``HOLD_TOLERANCE_RAD``, or ``abort()`` sets ``aborted``: every moving joint holds where it is from that tick.
- The gate refusing a moving joint's command (``on_refused``: its arm would come within the margin of the other
  arm or the body) fails that joint's segment with the gate's words; the sequence then backs it off.

``frame``: the host frame (the prior's directions, offsets 0) moved into the model's by the best calibration known,
and which joints the gate may take as known (not asked for in this run, or settled in it), so the gate checks the
bodies whose place is known.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from humanoid_prime.calibration.approach import Hold, JointRun
from humanoid_prime.calibration.contact import Tick
from humanoid_prime.config.robot import Robot
from humanoid_prime.control.controller import Controller
from humanoid_prime.control.flags import Level
from humanoid_prime.control.interfaces import CommandArrays, Frame, StateArrays
from humanoid_prime.control.topics import SafetyStatus, TopicBus

CALIBRATION_CONTROLLER = "calibration_controller"
HOLD_TOLERANCE_RAD = 0.05  # a held joint that moves further has been pushed: stop
HOLD_INTEGRAL_S = 0.15  # time constant with which a per-tick hold takes up a changing load
GRAVITY_STEP_RAD = 0.005  # the model's gravity is evaluated again once a joint has moved this far

Floats = npt.NDArray[np.float64]


class CalibrationController(Controller):
    """``per_tick``: the joints held by their command (the others hold on their drives' gains); ``hold_gains``:
    the standby (kp, kd); ``gravity``: the host-frame holding torques at a host-frame pose (the loop's model);
    ``known``: the joints whose frame is known from the start."""

    releases = True

    def __init__(self, robot: Robot, per_tick: npt.NDArray[np.bool_], hold_gains: tuple[float, float],
                 gravity: Callable[[Floats], Floats], calibration: tuple[Floats, Floats, Floats],
                 known: npt.NDArray[np.bool_], *, settle_effort: bool = False) -> None:
        super().__init__(CALIBRATION_CONTROLLER, None)
        n = robot.n
        self.robot = robot
        self.per_tick = per_tick
        self.hold_gains = hold_gains
        self.gravity = gravity
        self.settle_effort = settle_effort
        self.hold = np.full(n, np.nan)  # where each joint is held (captured on activation)
        self.hold_effort = np.zeros(n)
        self.effort_limit = robot.effort_limit
        self.capture: set[int] = set()  # joints whose hold is taken afresh at the next tick (any thread)
        self.runs: tuple[JointRun, ...] = ()  # the moving joints (set by the sequence, read per tick)
        self.aborted: str | None = None
        self.abort_request: str | None = None
        self.status: SafetyStatus | None = None  # the latest /safety_status (set by the sequence's subscriber)
        # The gate's frame: model = scale * host + shift per joint; the known joints' bodies, and their limits
        # except the moving joints' (they press their stops).
        self._frame = Frame(np.ones(n), np.zeros(n), known.astype(np.uint8), known.astype(np.uint8))
        self.frame = self._frame
        self.frame_dirty = True  # the sequence set what it knows: the frame is taken afresh at the next tick
        self._lower, self._upper = robot.lower, robot.upper
        self.hold_low, self.hold_high = np.full(n, -np.inf), np.full(n, np.inf)  # a held target's range (host)
        # The prior's directions and the best calibration known (shared with the sequence, which writes them).
        self.prior_direction, self.direction, self.offset = calibration
        self.settled = known.copy()  # joints the frame may take as known (the sequence marks them)
        self._gravity: Floats = np.zeros(n)
        self._gravity_at: Floats | None = None
        self._last_t: float | None = None
        self._held = np.zeros(n, dtype=bool)
        self._release = np.zeros(n, dtype=bool)

    def on_configure(self, robot: Robot, topics: TopicBus) -> None:
        pass

    def on_activate(self, state: StateArrays, now: float) -> None:
        """Every joint held from here, where it is, with the effort it applies (or the model's, ``settle_effort``)."""
        np.copyto(self.hold, state.position)
        np.copyto(self.hold_effort, self.gravity(state.position) if self.settle_effort else state.effort)
        self.capture.clear()
        self._last_t = None

    def frame_now(self) -> Frame:
        """The frame as the calibration known now gives it (a copy, for the sequence's own checks)."""
        known = self.settled.astype(np.uint8)
        return Frame(self.direction * self.prior_direction, -self.direction * self.offset, known, known.copy())

    def forget_gravity(self) -> None:
        """The calibration known changed: the model's gravity is evaluated afresh at the next tick."""
        self._gravity_at = None
        self.frame_dirty = True

    def on_refused(self, reason: str, held: npt.NDArray[np.bool_]) -> None:
        for run in self.runs:
            segment = run.segment
            if held[run.index] and segment is not None and not isinstance(segment, Hold):
                run.refused = reason
                segment.failure = f"the gate refused its command: {reason}"

    def update(self, now: float, dt: float, state: StateArrays, command: CommandArrays) -> None:
        q = state.position
        dt = dt if self._last_t is None else max(now - self._last_t, 1e-6)
        self._last_t = now
        if self.capture:
            taken = list(self.capture)
            self.capture.difference_update(taken)
            self.hold[taken] = q[taken]
            self.hold_effort[taken] = state.effort[taken]
        runs = self.runs
        if self.frame_dirty:
            self.frame_dirty = False
            self._take_frame()
        frame = self._frame
        np.copyto(frame.limited, frame.known)
        for run in runs:
            if run.active:
                frame.limited[run.index] = 0
        self._watch(q)
        held = self._held
        np.isfinite(self.hold, out=held)
        for run in runs:
            if run.active:
                held[run.index] = False
        if self.aborted is None:
            drift = np.where(held, np.abs(q - self.hold), 0.0)
            if drift.max(initial=0.0) > HOLD_TOLERANCE_RAD:
                k = int(np.argmax(drift))
                self.aborted = (f"{self.robot.names[k]} moved {drift[k]:.3f} rad while it was held (pushed, or "
                                "its drive let go)")
        self._hold(q, dt, held, command)
        if not runs:
            return
        if self._gravity_at is None or np.abs(q - self._gravity_at).max() > GRAVITY_STEP_RAD:
            self._gravity, self._gravity_at = self.gravity(q), q.copy()  # the model, when it has changed
        for run in runs:
            self._drive(run, now, dt, state, command)

    def _take_frame(self) -> None:
        """The frame from the calibration known now, and the range each held target is kept in (the limits, where
        the frame is known: a joint resting beyond one, by the prior's error, is held on it)."""
        frame = self._frame
        np.multiply(self.direction, self.prior_direction, out=frame.scale)
        np.multiply(self.direction, self.offset, out=frame.shift)
        np.negative(frame.shift, out=frame.shift)
        frame.known[:] = self.settled
        a, b = (self._lower - frame.shift) / frame.scale, (self._upper - frame.shift) / frame.scale
        np.copyto(self.hold_low, np.where(self.settled, np.minimum(a, b), -np.inf))
        np.copyto(self.hold_high, np.where(self.settled, np.maximum(a, b), np.inf))

    def _watch(self, q: Floats) -> None:
        """``aborted`` from a request or an error on /safety_status."""
        if self.aborted is not None:
            return
        if self.abort_request is not None:
            self.aborted = self.abort_request
            return
        status = self.status
        if status is not None:
            errors = [f"{key}: {status.flags[key]}" for key, level in status.levels.items() if level is Level.ERROR]
            if errors:
                self.aborted = "fault: " + "; ".join(errors)

    def _hold(self, q: Floats, dt: float, held: npt.NDArray[np.bool_], command: CommandArrays) -> None:
        """The held joints: per-tick ones on the standby gains and their integrating effort, the others released to
        their drives (no command)."""
        kp, kd = self.hold_gains
        hold = held & self.per_tick
        sag = np.where(hold, self.hold - q, 0.0)
        self.hold_effort += min(1.0, dt / HOLD_INTEGRAL_S) * kp * sag
        np.clip(self.hold_effort, -self.effort_limit, self.effort_limit, out=self.hold_effort)
        command.position[hold] = np.clip(self.hold, self.hold_low, self.hold_high)[hold]
        command.velocity[hold] = 0.0
        command.effort[hold] = self.hold_effort[hold]
        command.stiffness[hold] = kp
        command.damping[hold] = kd
        release = self._release
        np.logical_not(self.per_tick, out=release)
        for run in self.runs:
            if run.active:
                release[run.index] = False
        command.data[:, release] = 0.0
        command.position[release] = np.nan

    def _drive(self, run: JointRun, now: float, dt: float, state: StateArrays, command: CommandArrays) -> None:
        """One moving joint: its segment's step, and its command while it is active."""
        i = run.index
        gravity = float(self._gravity[i])
        active = run.active
        segment = run.segment
        if self.aborted is not None and not isinstance(segment, Hold):
            segment = run.segment = Hold(run)  # stop here, at once
        if segment is not None and not segment.finished and segment.failure is None:
            segment.update(Tick(now, dt, float(state.position[i]), float(state.velocity[i]), float(state.effort[i]),
                                run.feed_forward(gravity)))
        run.count(dt)
        wanted = segment.command() if segment is not None else None
        if not active or wanted is None:
            return
        target, velocity = wanted
        low, high = run.bounds
        command.position[i] = min(max(target, low), high)
        fastest = max(run.travel_speed, getattr(segment, "top_speed", 0.0))
        command.velocity[i] = min(max(velocity, -fastest), fastest)
        command.effort[i] = run.feed_forward(gravity)  # with what this tick's step taught it
        command.stiffness[i] = run.kp
        command.damping[i] = run.kd
        trace = run.trace
        trace.t.append(now)
        trace.q.append(float(state.position[i]))
        trace.target.append(float(command.position[i]))
        trace.effort.append(float(state.effort[i]))
        trace.kind.append(run.kind)
