"""The trajectory actions of the rclpy node (``rclpy_node.py``): ``control_msgs/action/FollowJointTrajectory`` for
each arm and for both, as joint_trajectory_controller names them (``/<name>_controller/follow_joint_trajectory``),
run by the trajectory executor (``trajectory.py``) through REMOTE. A goal is rejected when the run takes no
control from the graph, when it fails the checks of ``trajectory.plan`` (the reason goes to /rosout: an action's
rejection carries none), or when REMOTE is not active; feedback comes at up to 50 Hz; the result has
control_msgs' codes and a reason."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node

from humanoid_prime.control.flags import Level
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.dds.controllers import arm_controllers
from humanoid_prime.dds.domain import in_namespace
from humanoid_prime.dds.rclpy_services import NOT_CONTROLLING, Duration, interface, seconds
from humanoid_prime.dds.trajectory import Goal, Point, Refused, Tolerance, TrajectoryExecutor, plan

FEEDBACK_PERIOD_S = 0.02  # action feedback at 50 Hz at most


class _Tolerance(Protocol):
    name: str
    position: float
    velocity: float


class _Point(Protocol):
    positions: Sequence[float]
    velocities: Sequence[float]
    time_from_start: Duration


class _Trajectory(Protocol):
    joint_names: Sequence[str]
    points: Sequence[_Point]


class _MultiDofTrajectory(Protocol):
    points: Sequence[object]


class _GoalRequest(Protocol):
    trajectory: _Trajectory
    multi_dof_trajectory: _MultiDofTrajectory
    path_tolerance: Sequence[_Tolerance]
    goal_tolerance: Sequence[_Tolerance]
    goal_time_tolerance: Duration


class _GoalHandle(Protocol):
    request: _GoalRequest
    is_cancel_requested: bool

    def abort(self) -> None: ...
    def succeed(self) -> None: ...
    def canceled(self) -> None: ...
    def publish_feedback(self, feedback: object) -> None: ...


class TrajectoryActions:
    """The node's trajectory action servers; mixed into the node, whose attributes below they use."""

    node: Node
    namespace: str
    manager: ControllerManager
    control: bool
    missing: list[str]
    trajectories: TrajectoryExecutor
    _group: ReentrantCallbackGroup

    def _log(self, text: str, level: Level | None, outer: bool = True) -> None:
        raise NotImplementedError

    def _actions(self) -> None:
        action = interface("control_msgs.action")
        self._action_servers: list[ActionServer] = []
        if action is None:
            self.missing.append("control_msgs (the FollowJointTrajectory actions left out)")
            return
        self._fjt = action.FollowJointTrajectory
        for name, joints in arm_controllers(self.manager.robot.names).items():
            self._action_servers.append(ActionServer(
                self.node, self._fjt, in_namespace(self.namespace, f"/{name}/follow_joint_trajectory"),
                execute_callback=lambda handle, j=joints: self._execute(handle, j),
                goal_callback=lambda goal, n=name, j=joints: self._accept(goal, n, j),
                cancel_callback=lambda _: CancelResponse.ACCEPT, callback_group=self._group))

    def _goal(self, request: _GoalRequest) -> Goal:
        def tolerances(items: Sequence[_Tolerance]) -> tuple[Tolerance, ...]:
            return tuple(Tolerance(t.name, t.position, t.velocity) for t in items)

        return Goal(
            joint_names=tuple(request.trajectory.joint_names),
            points=tuple(Point(seconds(p.time_from_start), list(p.positions), list(p.velocities))
                         for p in request.trajectory.points),
            path_tolerance=tolerances(request.path_tolerance), goal_tolerance=tolerances(request.goal_tolerance),
            goal_time_tolerance_s=seconds(request.goal_time_tolerance),
            multi_dof=bool(request.multi_dof_trajectory.points))

    def _accept(self, request: _GoalRequest, name: str, joints: tuple[str, ...]) -> GoalResponse:
        if not self.control:
            self._log(f"{name}: goal rejected: {NOT_CONTROLLING}", Level.WARN)
            return GoalResponse.REJECT
        try:
            plan(self.manager.robot, self._goal(request), joints, self.trajectories.speed_limits)
        except Refused as exc:
            self._log(f"{name}: goal rejected: {exc.reason}", Level.WARN)
            return GoalResponse.REJECT
        if not self.trajectories.remote_active:
            self._log(f"{name}: goal rejected: the trajectory controllers run in REMOTE; switch to REMOTE first",
                      Level.WARN)
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def _execute(self, handle: _GoalHandle, joints: tuple[str, ...]) -> object:
        result = self._fjt.Result()
        try:
            execution = self.trajectories.start(self._goal(handle.request), joints)
        except Refused as exc:
            result.error_code, result.error_string = exc.code, exc.reason
            handle.abort()
            return result
        feedback = self._fjt.Feedback()
        feedback.joint_names = list(execution.joint_names)
        while not execution.done.wait(FEEDBACK_PERIOD_S):
            if handle.is_cancel_requested:
                self.trajectories.cancel(execution)
            elif execution.feedback is not None:
                desired_q, desired_qd, q, qd, _index = execution.feedback
                feedback.desired.positions, feedback.desired.velocities = desired_q.tolist(), desired_qd.tolist()
                feedback.actual.positions, feedback.actual.velocities = q.tolist(), qd.tolist()
                feedback.error.positions = (desired_q - q).tolist()
                feedback.error.velocities = (desired_qd - qd).tolist()
                if hasattr(feedback, "index"):  # Kilted's feedback has it, Jazzy's not
                    feedback.index = _index
                feedback.header.stamp = self.node.get_clock().now().to_msg()
                handle.publish_feedback(feedback)
        result.error_code, result.error_string = execution.code, execution.reason
        if execution.cancelled:
            handle.canceled()
        elif execution.code == 0:
            handle.succeed()
        else:
            handle.abort()
        ended = "cancelled" if execution.cancelled else (execution.reason or "done")
        self._log(f"trajectory of {len(joints)} joints ({joints[0]}, ...): {ended}",
                  None if execution.code == 0 else Level.WARN)
        return result
