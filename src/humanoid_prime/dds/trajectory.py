"""Joint trajectories executed through REMOTE: what a ``control_msgs/FollowJointTrajectory`` goal asks, checked
against the robot's limits, then interpolated to one MIT command per tick that enters the stack on REMOTE's
topic, so the manager's command gate checks every one of them as it checks any other.

Nothing here knows ROS: the action servers (``rclpy_node.py``) turn a goal into a ``Goal`` and wait on its
``Execution``. The executor is a consumer of the loop's tick tap: on each tick it reads the measured state,
checks the path tolerances, and sends the command for the next tick (the desired position and velocity of the
goal's joints, every other joint held where it was when the first goal began, gravity fed forward from the
model), at REMOTE's gains. As ros2_control's joint_trajectory_controller does, it
- interpolates from the state at the start to the first point, then between points (cubic where the points give
  velocities, else linear);
- holds the last point once a goal ends, and the measured position once it is cancelled, for as long as REMOTE
  stays active (REMOTE damps when its commands stop);
- stops a goal when the mode leaves REMOTE, and a goal on the same joints replaces the one running.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from humanoid_prime.config.controllers import ControllersConfig
from humanoid_prime.config.robot import Robot
from humanoid_prime.control.tap import TickSample
from humanoid_prime.control.topics import ControlMode, JointState, MitCommand, SafetyStatus, TopicBus
from humanoid_prime.modes import Mode

Array = npt.NDArray[np.float64]

# control_msgs/action/FollowJointTrajectory's result codes.
SUCCESSFUL = 0
INVALID_GOAL = -1
INVALID_JOINTS = -2
OLD_HEADER_TIMESTAMP = -3
PATH_TOLERANCE_VIOLATED = -4
GOAL_TOLERANCE_VIOLATED = -5

DEFAULT_GOAL_TOLERANCE_RAD = 0.05  # where a goal gives none (joint_trajectory_controller's default is none at all)
START_SPEED_FRACTION = 0.5  # the move from the measured state to the first point: at most this share of the limit


@dataclass(frozen=True)
class Point:
    """One point of a trajectory: seconds from its start, positions, and velocities (empty: not given)."""

    time_s: float
    positions: Sequence[float]
    velocities: Sequence[float] = ()


@dataclass(frozen=True)
class Tolerance:
    """One joint's tolerance as the goal gives it: 0 not given, -1 none, else the largest error."""

    name: str
    position: float = 0.0
    velocity: float = 0.0


@dataclass(frozen=True)
class Goal:
    """What a FollowJointTrajectory goal asks, as the server passes it on."""

    joint_names: tuple[str, ...]
    points: tuple[Point, ...]
    path_tolerance: tuple[Tolerance, ...] = ()
    goal_tolerance: tuple[Tolerance, ...] = ()
    goal_time_tolerance_s: float = 0.0
    multi_dof: bool = False  # the goal has a multi-DOF trajectory (Prime has no multi-DOF joints)


class Refused(Exception):
    """A goal this server does not take: the result code and why."""

    def __init__(self, code: int, reason: str) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason


@dataclass
class Plan:
    """A checked goal, in the goal's joint order: the joints it moves (canonical indices), knots (seconds from the
    start) and the positions and velocities there (``velocities`` None: linear between points), tolerances per
    moved joint."""

    joints: npt.NDArray[np.intp]
    times: Array
    positions: Array  # (points, joints)
    velocities: Array | None
    path_tolerance: Array  # rad; inf: none
    goal_tolerance: Array
    goal_velocity_tolerance: Array
    goal_time_tolerance_s: float

    @property
    def duration(self) -> float:
        return float(self.times[-1])


def _tolerances(joint_names: tuple[str, ...], given: tuple[Tolerance, ...], default: float,
                attribute: str = "position") -> Array:
    values = np.full(len(joint_names), default)
    for tolerance in given:
        if tolerance.name not in joint_names:
            raise Refused(INVALID_JOINTS, f"a tolerance names {tolerance.name!r}, which the trajectory does not move")
        value = getattr(tolerance, attribute)
        values[joint_names.index(tolerance.name)] = math.inf if value < 0 else (value if value > 0 else default)
    return values


def plan(robot: Robot, goal: Goal, controller_joints: tuple[str, ...], speed_limits: Array) -> Plan:
    """``goal`` checked (Refused with the result code and reason): the controller's joints, each exactly once,
    increasing times, one value per joint, every position within the joint's limits, and no segment faster than
    the joint's velocity limit (``speed_limits``, rad/s, canonical order)."""
    names = goal.joint_names
    if goal.multi_dof:
        raise Refused(INVALID_GOAL, "Prime has no multi-DOF joints: the goal's multi_dof_trajectory must be empty")
    if sorted(names) != sorted(controller_joints) or len(set(names)) != len(names):
        raise Refused(INVALID_JOINTS, f"the trajectory's joints {list(names)} are not this controller's "
                                      f"{list(controller_joints)} (each once, any order)")
    if not goal.points:
        raise Refused(INVALID_GOAL, "the trajectory has no points")
    joints = np.array([robot.index(name) for name in names], dtype=np.intp)
    times = np.array([point.time_s for point in goal.points])
    if times[0] < 0 or np.any(np.diff(times) <= 0) or not np.all(np.isfinite(times)):
        raise Refused(INVALID_GOAL, "time_from_start must be finite, not negative and increasing from point to point")
    if times[-1] <= 0:
        raise Refused(INVALID_GOAL, "the trajectory must end after it starts (its last time_from_start is 0)")
    rows = []
    for k, point in enumerate(goal.points):
        if len(point.positions) != len(names):
            raise Refused(INVALID_GOAL, f"point {k} has {len(point.positions)} positions for {len(names)} joints")
        if point.velocities and len(point.velocities) != len(names):
            raise Refused(INVALID_GOAL, f"point {k} has {len(point.velocities)} velocities for {len(names)} joints")
        rows.append(point.positions)
    positions = np.array(rows, dtype=np.float64)
    if not np.all(np.isfinite(positions)):
        raise Refused(INVALID_GOAL, "a position is not a finite number")
    lower = np.array([robot.joints[j].lower for j in joints])
    upper = np.array([robot.joints[j].upper for j in joints])
    outside = np.argwhere((positions < lower) | (positions > upper))
    if outside.size:
        k, i = outside[0]
        raise Refused(INVALID_GOAL, f"point {k}: {names[i]} at {positions[k, i]:.4f} rad is outside its limits "
                                    f"[{lower[i]:.4f}, {upper[i]:.4f}]")
    limits = speed_limits[joints]
    given = all(len(point.velocities) for point in goal.points)
    velocities = np.array([point.velocities for point in goal.points], dtype=np.float64) if given else None
    if velocities is not None:
        fast = np.argwhere(~np.isfinite(velocities) | (np.abs(velocities) > limits))
        if fast.size:
            k, i = fast[0]
            raise Refused(INVALID_GOAL, f"point {k}: {names[i]} velocity {velocities[k, i]:.3f} rad/s is beyond its "
                                        f"limit {limits[i]:.3f} rad/s")
    if len(times) > 1:
        speeds = np.abs(np.diff(positions, axis=0)) / np.diff(times)[:, None]
        fast = np.argwhere(speeds > limits)
        if fast.size:
            k, i = fast[0]
            raise Refused(INVALID_GOAL, f"points {k}-{k + 1}: {names[i]} would move at {speeds[k, i]:.3f} rad/s, "
                                        f"beyond its limit {limits[i]:.3f} rad/s (too fast)")
    return Plan(joints=joints, times=times, positions=positions, velocities=velocities,
                path_tolerance=_tolerances(names, goal.path_tolerance, math.inf),
                goal_tolerance=_tolerances(names, goal.goal_tolerance, DEFAULT_GOAL_TOLERANCE_RAD),
                goal_velocity_tolerance=_tolerances(names, goal.goal_tolerance, math.inf, "velocity"),
                goal_time_tolerance_s=max(goal.goal_time_tolerance_s, 0.0))


def sample(times: Array, positions: Array, velocities: Array | None, t: float) -> tuple[Array, Array]:
    """Position and velocity at ``t`` seconds: cubic Hermite between knots where velocities are given, linear
    otherwise; before the first knot the first point, after the last the last point at rest."""
    if t <= times[0]:
        return positions[0], (velocities[0] if velocities is not None else np.zeros(positions.shape[1]))
    if t >= times[-1]:
        return positions[-1], np.zeros(positions.shape[1])
    k = int(np.searchsorted(times, t, side="right")) - 1
    h = times[k + 1] - times[k]
    s = (t - times[k]) / h
    p0, p1 = positions[k], positions[k + 1]
    if velocities is None:
        return p0 + s * (p1 - p0), (p1 - p0) / h
    v0, v1 = velocities[k], velocities[k + 1]
    h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
    d00, d10, d01, d11 = 6 * s**2 - 6 * s, 3 * s**2 - 4 * s + 1, -6 * s**2 + 6 * s, 3 * s**2 - 2 * s
    position = h00 * p0 + h10 * h * v0 + h01 * p1 + h11 * h * v1
    velocity = (d00 * p0 + d10 * h * v0 + d01 * p1 + d11 * h * v1) / h
    return position, velocity


@dataclass
class Execution:
    """One goal as it runs: ``done`` is set when it has ended, with its code and reason; ``feedback`` is the
    latest (desired, actual, error) positions and velocities of its joints, and the point being executed."""

    plan: Plan
    joint_names: tuple[str, ...]
    done: threading.Event = field(default_factory=threading.Event)
    code: int = SUCCESSFUL
    reason: str = ""
    cancelled: bool = False
    started_at: float | None = None  # loop time of the tick it began on
    knots: tuple[Array, Array, Array | None] | None = None  # times, positions, velocities from the start state
    feedback: tuple[Array, Array, Array, Array, int] | None = None  # desired q, qd, actual q, qd, point index

    def finish(self, code: int, reason: str) -> None:
        if not self.done.is_set():
            self.code, self.reason = code, reason
            self.done.set()


class TrajectoryExecutor:
    """Runs goals for the controllers ``controllers`` (name -> joints, canonical order): a tick tap's consumer
    (``on_tick`` on the tap's thread) that sends REMOTE's commands on ``topics``. ``gravity(q)`` gives the
    holding torque of every joint at ``q`` (None: no feed-forward)."""

    def __init__(self, robot: Robot, config: ControllersConfig, topics: TopicBus, *, period: float,
                 gravity: Callable[[Array], Array] | None = None) -> None:
        self.robot = robot
        self.names = robot.names
        self.topics = topics
        self.remote_topic = config.remote.topic
        self.joint_states_topic = config.joint_states_topic
        self.period = period
        self.gravity = gravity
        limits = robot.hardware.command_limits
        self.speed_limits = np.array([min(j.velocity_limit, limits[j.family].velocity) for j in robot.joints])
        erob = np.array([j.family == "erob" for j in robot.joints])
        self.stiffness = np.where(erob, config.remote.erob_kp, config.standby.kp)
        self.damping = np.where(erob, config.remote.erob_kd, config.standby.kd)
        self.effort_limits = np.array([j.effort_limit for j in robot.joints])
        self._lock = threading.Lock()
        self._running: list[Execution] = []
        self._hold: Array | None = None  # the target of every joint no goal moves now (None: not streaming)
        self._mode: str | None = None
        self.sent = 0

    @property
    def remote_active(self) -> bool:
        return self._mode == Mode.REMOTE.value

    def start(self, goal: Goal, controller_joints: tuple[str, ...]) -> Execution:
        """Check ``goal`` (Refused: the result code and why) and run it from the next tick on; a goal running on
        any of the same joints is replaced (it ends with ``INVALID_GOAL``, "replaced")."""
        if not self.remote_active:
            raise Refused(INVALID_GOAL, f"the trajectory controllers run in REMOTE, and Prime is in {self._mode}; "
                                        "switch to REMOTE first (~/switch_mode, or activate remote_policy_controller)")
        execution = Execution(plan(self.robot, goal, controller_joints, self.speed_limits), goal.joint_names)
        with self._lock:
            for other in self._running:
                if np.intersect1d(other.plan.joints, execution.plan.joints).size:
                    other.finish(INVALID_GOAL, "replaced by a newer goal on the same joints")
            self._running = [other for other in self._running if not other.done.is_set()] + [execution]
        return execution

    def cancel(self, execution: Execution) -> None:
        """Stop ``execution``: its joints hold where they are measured on the next tick."""
        with self._lock:
            execution.cancelled = True

    # ---- the tap's consumer ----------------------------------------------------------------------

    def on_tick(self, sample: TickSample) -> None:
        q, qd = sample.data[0], sample.data[1]
        # The command is for the tick after the newest one, which may be later than this sample's when the tap
        # runs behind the loop (a busy machine): a target computed for an old tick would lag the path.
        newest = self.topics.latest(self.joint_states_topic)
        now = max(sample.stamp, newest.stamp) if isinstance(newest, JointState) else sample.stamp
        with self._lock:
            if not self.remote_active:
                self._hold = None
                return
            running = list(self._running)
            if not running and self._hold is None:
                return  # REMOTE is someone else's (a MitCommand stream) until a goal comes
            if self._hold is None:
                self._hold = np.where(np.isfinite(q), q, 0.0)
            target, velocity = self._hold.copy(), np.zeros(len(q))
            for execution in running:
                self._step(execution, sample.stamp, now, q, qd, target, velocity)
            self._running = [e for e in running if not e.done.is_set()]
        effort = np.zeros(len(q)) if self.gravity is None else np.clip(self.gravity(target), -self.effort_limits,
                                                                       self.effort_limits)
        self.topics.publish(self.remote_topic, MitCommand(
            joint_names=self.names, position=target, velocity=velocity, effort=effort,
            stiffness=self.stiffness.copy(), damping=self.damping.copy(), stamp=now))
        self.sent += 1

    def _step(self, execution: Execution, measured_at: float, now: float, q: Array, qd: Array, target: Array,
              velocity: Array) -> None:
        """One goal's part of the command for the tick after ``now``, from the state measured at ``measured_at``
        (its path and goal checked there)."""
        plan = execution.plan
        joints = plan.joints
        hold = self._hold
        assert hold is not None
        if execution.cancelled:
            hold[joints] = q[joints]
            target[joints] = q[joints]
            execution.finish(SUCCESSFUL, "cancelled")
            return
        if execution.knots is None:  # the first tick: from the measured state to the first point
            execution.started_at = measured_at
            start_q, start_qd = q[joints].copy(), np.zeros(len(joints))
            first = plan.times[0]
            reach = float(np.max(np.abs(plan.positions[0] - start_q) / (self.speed_limits[joints] *
                                                                         START_SPEED_FRACTION)))
            if first <= 0 and reach > self.period:
                execution.finish(INVALID_GOAL, f"the first point is at time 0 but {reach:.2f} s away from where the "
                                               "joints are: give it a time_from_start")
                return
            offset = 0.0 if first > 0 else self.period
            times = np.concatenate([[0.0], plan.times + offset]) if first > 0 else plan.times
            positions = np.vstack([start_q, plan.positions]) if first > 0 else plan.positions
            velocities = None
            if plan.velocities is not None:
                velocities = np.vstack([start_qd, plan.velocities]) if first > 0 else plan.velocities
            execution.knots = (times, positions, velocities)
        assert execution.started_at is not None
        times, positions, velocities = execution.knots
        elapsed = measured_at - execution.started_at
        desired_now, desired_velocity_now = sample(times, positions, velocities, elapsed)
        error = q[joints] - desired_now
        index = int(np.searchsorted(times[-len(plan.times):], elapsed, side="left"))  # the point being approached
        execution.feedback = (desired_now, desired_velocity_now, q[joints].copy(), qd[joints].copy(),
                              min(index, len(plan.times) - 1))
        violated = np.flatnonzero(np.abs(error) > plan.path_tolerance)
        if violated.size and elapsed < times[-1]:
            i = violated[0]
            hold[joints] = q[joints]
            target[joints] = q[joints]
            execution.finish(PATH_TOLERANCE_VIOLATED, f"{execution.joint_names[i]} is "
                                                      f"{abs(error[i]):.4f} rad from its path, beyond the path "
                                                      f"tolerance {plan.path_tolerance[i]:.4f} rad")
            return
        next_q, next_qd = sample(times, positions, velocities, now - execution.started_at + self.period)
        target[joints] = next_q
        velocity[joints] = next_qd
        if elapsed < times[-1]:
            return
        hold[joints] = positions[-1]  # from now on the last point is held
        at_goal = np.abs(q[joints] - positions[-1]) <= plan.goal_tolerance
        still = np.abs(qd[joints]) <= plan.goal_velocity_tolerance
        if np.all(at_goal & still):
            execution.finish(SUCCESSFUL, "")
        elif elapsed > times[-1] + plan.goal_time_tolerance_s:
            i = int(np.flatnonzero(~(at_goal & still))[0])
            what = (f"{abs(q[joints][i] - positions[-1][i]):.4f} rad from its goal, beyond the goal tolerance "
                    f"{plan.goal_tolerance[i]:.4f} rad" if not at_goal[i] else
                    f"moving at {abs(qd[joints][i]):.4f} rad/s, beyond the goal velocity tolerance "
                    f"{plan.goal_velocity_tolerance[i]:.4f} rad/s")
            execution.finish(GOAL_TOLERANCE_VIOLATED, f"{execution.joint_names[i]} is {what} "
                                                      f"{plan.goal_time_tolerance_s:g} s after the trajectory's end")

    def on_mode(self, message: ControlMode) -> None:
        with self._lock:
            self._mode = message.mode
            if message.mode != Mode.REMOTE.value:
                for execution in self._running:
                    execution.finish(INVALID_GOAL, f"stopped: Prime left REMOTE for {message.mode}")
                self._running = []
                self._hold = None

    def on_safety(self, message: SafetyStatus) -> None:
        """Not used: a fault that matters ends REMOTE, and ``on_mode`` stops the goals."""

    def on_remote(self, message: MitCommand) -> None:
        """Not used: the executor sends REMOTE's commands, it does not read them."""

    def stop(self) -> None:
        """End every goal (the node is going away)."""
        with self._lock:
            for execution in self._running:
                execution.finish(INVALID_GOAL, "stopped: Prime's node is shutting down")
            self._running = []
            self._hold = None
