"""Node ``prime`` as an rclpy node, on whatever middleware the user's ROS 2 is set to: the topics of the bare
backend (``graph.py``: the same names, types, QoS and bytes) and what only a real ROS 2 node serves:

- parameters: the run, read-only, and ``remote.timeout_s`` settable within its bounds (``parameters.py``);
  ``use_sim_time`` as every rclpy node has it (on in simulation, where the stamps are simulated time);
- logs on ``/rosout``: the start-up line, each flag of /safety_status at its level as it appears, and QoS
  mismatches;
- services ``~/switch_mode`` and ``~/reset_faults`` (prime_msgs), answered once the loop has applied them, as
  ``prime switch`` and ``prime reset`` are, and the controller manager's ``list_controllers`` and
  ``switch_controller`` (``controllers.py``);
- ``control_msgs/action/FollowJointTrajectory`` for each arm and both (``/<arm>_controller/follow_joint_trajectory``
  as joint_trajectory_controller names it), executed through REMOTE (``trajectory.py``).

What moves the robot (mode requests, MitCommands, the mode and reset services, switch_controller and trajectory
goals) is taken only when the run takes control from the graph (``--dds-control``); without it each is refused
with that reason. The loop never waits on rclpy: ticks reach the publisher through a tick tap, as on the bare
backend, and rclpy's executor runs on threads of its own (it waits in C, without the interpreter's lock).
Interfaces that are not installed (prime_msgs, tf2_msgs, control_msgs, controller_manager_msgs have no PyPI
wheels) leave out what needs them, and the start-up line says which.
"""

from __future__ import annotations

import importlib
import threading
import time
from collections.abc import Callable, Sequence
from types import ModuleType
from typing import Protocol, TypeVar

import numpy as np
import numpy.typing as npt
import rclpy
from cyclonedds.idl import IdlStruct
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.context import Context
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

from humanoid_prime.control.flags import Level
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.tap import SLOTS, TickSample, TickTap
from humanoid_prime.control.topics import ControlMode, SafetyStatus
from humanoid_prime.dds import messages as msg
from humanoid_prime.dds.controllers import (
    NAMESPACE,
    Switch,
    SwitchRefused,
    SwitchResult,
    arm_controllers,
    controllers,
    mode_to_activate,
)
from humanoid_prime.dds.domain import in_namespace
from humanoid_prime.dds.graph import NODE_NAME, GraphBridge, Report
from humanoid_prime.dds.parameters import run_parameters
from humanoid_prime.dds.trajectory import Goal, Point, Refused, Tolerance, TrajectoryExecutor
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode

Array = npt.NDArray[np.float64]

STRICT = 2  # controller_manager_msgs/SwitchController's strictness: refuse a request that cannot be done as asked
DEFAULT_WAIT_S = 2.0  # how long a service waits for the loop to apply a switch or reset when not told
FEEDBACK_PERIOD_S = 0.02  # action feedback at 50 Hz at most
EXECUTOR_THREADS = 4  # services that wait for the loop, goals that run for seconds, and everything else
NOT_CONTROLLING = "this run takes no commands from the ROS 2 graph (start Prime with --dds-control)"
LEVELS = {Level.WARN: "warning", Level.ERROR: "error"}

R = TypeVar("R")
S = TypeVar("S")


# The fields Prime reads and writes of the ROS 2 messages it serves (rclpy's generated classes, untyped).
class _Publisher(Protocol):
    def publish(self, message: bytes) -> None: ...
    def get_subscription_count(self) -> int: ...


class _Duration(Protocol):
    sec: int
    nanosec: int


class _SwitchModeRequest(Protocol):
    mode: str
    timeout: float


class _SwitchModeResponse(Protocol):
    success: bool
    outcome: str
    active_mode: str
    message: str


class _ResetFaultsResponse(Protocol):
    success: bool
    faults: list[str]
    message: str


class _ListControllersResponse(Protocol):
    controller: list[object]


class _SwitchControllerRequest(Protocol):
    activate_controllers: Sequence[str]
    deactivate_controllers: Sequence[str]
    strictness: int
    timeout: _Duration


class _SwitchControllerResponse(Protocol):
    ok: bool
    message: str


class _Tolerance(Protocol):
    name: str
    position: float
    velocity: float


class _Point(Protocol):
    positions: Sequence[float]
    velocities: Sequence[float]
    time_from_start: _Duration


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
    goal_time_tolerance: _Duration


class _GoalHandle(Protocol):
    request: _GoalRequest
    is_cancel_requested: bool

    def abort(self) -> None: ...
    def succeed(self) -> None: ...
    def canceled(self) -> None: ...
    def publish_feedback(self, feedback: object) -> None: ...


def _seconds(duration: _Duration) -> float:
    return float(duration.sec + duration.nanosec * 1e-9)


def _interface(name: str) -> ModuleType | None:
    """``pkg.msg`` (or ``.srv``, ``.action``), or None where the package is not installed."""
    try:
        return importlib.import_module(name)
    except ImportError:
        return None


def _qos(latched: bool, depth: int) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def _policy(event: object) -> str:
    kind = getattr(event, "last_policy_kind", None)
    return str(getattr(kind, "name", kind)).lower().replace("_", " ")


class RclpyBridge(GraphBridge):
    """Node ``prime`` on rclpy (module docstring); ``close`` takes it off the graph."""

    backend = "rclpy"

    def __init__(self, manager: ControllerManager, *, domain: int, namespace: str = "/", control: bool = False,
                 request_mode: Callable[[str], object] | None = None, switch: Switch | None = None,
                 epoch_offset: float = 0.0, sim_clock: bool = False, report: Report | None = None,
                 slots: int = SLOTS, clock: Callable[[], float] = time.perf_counter,
                 gravity: Callable[[Array], Array] | None = None) -> None:
        super().__init__(manager, request_mode=request_mode, control=control, epoch_offset=epoch_offset,
                         sim_clock=sim_clock, clock=clock, report=None)
        self.outer_report = report
        self.report = self._log
        self.domain = domain
        self.namespace = namespace
        self.switch = switch
        self.missing: list[str] = []
        self._closed = False
        self._flags_logged: dict[str, str] = {}
        self.context = Context()
        # Prime prints its own lines (the node's go to /rosout); its signals are its own to handle.
        rclpy.init(args=["--ros-args", "--disable-stdout-logs"], context=self.context, domain_id=domain,
                   signal_handler_options=SignalHandlerOptions.NO)
        try:
            # use_sim_time stays off, as in any node, even where the stamps are simulated time: following /clock
            # would cost a callback of the executor's every tick; setting it makes the node's logs follow /clock.
            self.node = Node(NODE_NAME, namespace=namespace, context=self.context)
            self.rmw = rclpy.get_rmw_implementation_identifier()
            self._group = ReentrantCallbackGroup()
            self._publishers = self._make_topics()
            self.publish_static()
            self._declare_parameters()
            self._services()
            self._executor = MultiThreadedExecutor(num_threads=EXECUTOR_THREADS, context=self.context)
            self._executor.add_node(self.node)
            self._spinner = threading.Thread(target=self._spin, name="rclpy-executor", daemon=True)
            self._spinner.start()
            self.trajectories = TrajectoryExecutor(manager.robot, manager.config, manager.topics,
                                                   period=manager.period, gravity=gravity)
            self._actions()
            self.tap = TickTap(manager, self, name="rclpy-publish", on_drop=self.on_drop, slots=slots, clock=clock)
        except BaseException:
            self._teardown()
            raise

    # ---- topics ----------------------------------------------------------------------------------

    def _make_topics(self) -> dict[str, _Publisher]:
        publishers: dict[str, _Publisher] = {}
        for topic, spec in self.specs.items():
            package, kind, name = spec.ros_type.split("/")
            module = _interface(f"{package}.{kind}")
            if module is None:
                self.missing.append(f"{package} ({topic} left out)")
                self.counts.pop(topic)
                continue
            ros_type = getattr(module, name)
            qos = _qos(spec.latched, spec.depth)
            full = in_namespace(self.namespace, topic)
            if spec.direction == "out":
                events = PublisherEventCallbacks(
                    incompatible_qos=lambda event, t=topic: self.qos_mismatch(t, _policy(event), "subscription"))
                publishers[topic] = self.node.create_publisher(ros_type, full, qos, event_callbacks=events)
            else:
                events = SubscriptionEventCallbacks(
                    incompatible_qos=lambda event, t=topic: self.qos_mismatch(t, _policy(event), "publisher"))
                handler = self._on_command_bytes if topic == self.remote_topic else self._on_mode_request_bytes
                self.node.create_subscription(ros_type, full, handler, qos, event_callbacks=events, raw=True,
                                              callback_group=self._group)
        return publishers

    def on_tick(self, sample: TickSample) -> None:
        self.trajectories.on_tick(sample)  # first: the next tick's command, then what the graph reads
        super().on_tick(sample)

    def on_mode(self, message: ControlMode) -> None:
        self.trajectories.on_mode(message)
        super().on_mode(message)

    def write(self, topic: str, message: IdlStruct) -> None:
        self._publishers[topic].publish(message.serialize())

    def _on_command_bytes(self, data: bytes) -> None:
        self.on_command(msg.MitCommand.deserialize(data))

    def _on_mode_request_bytes(self, data: bytes) -> None:
        self.on_mode_request(msg.String.deserialize(data))

    def on_safety(self, message: SafetyStatus) -> None:
        super().on_safety(message)
        for key, text in message.flags.items():  # each flag on /rosout at its level as it appears or changes
            if self._flags_logged.get(key) != text:
                self._log(f"{key}: {text}", message.levels.get(key, Level.ERROR), outer=False)
        for key in [key for key in self._flags_logged if key not in message.flags]:
            self._log(f"{key}: cleared", None, outer=False)
        self._flags_logged = dict(message.flags)

    def _log(self, text: str, level: Level | None, outer: bool = True) -> None:
        logger = self.node.get_logger()  # one call per severity: rclpy keeps one severity per call site
        if level is None:
            logger.info(text)
        elif level is Level.WARN:
            logger.warning(text)
        else:
            logger.error(text)
        if outer and self.outer_report is not None:
            self.outer_report(text, level)

    # ---- parameters ------------------------------------------------------------------------------

    def _declare_parameters(self) -> None:
        from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, SetParametersResult

        self._settable: dict[str, Callable[[float], None]] = {}
        for parameter in run_parameters(self.manager, backend=self.backend, control=self.control):
            descriptor = ParameterDescriptor(description=parameter.description, read_only=parameter.bounds is None)
            if parameter.bounds is not None:
                low, high = parameter.bounds
                descriptor.floating_point_range = [FloatingPointRange(from_value=low, to_value=high, step=0.0)]
                assert parameter.apply is not None
                self._settable[parameter.name] = parameter.apply
            self.node.declare_parameter(parameter.name, parameter.value, descriptor)

        def on_set(parameters: list[Parameter]) -> SetParametersResult:
            for parameter in parameters:  # rclpy has checked read-only and the bounds; apply what is settable
                apply = self._settable.get(parameter.name)
                if apply is not None:
                    apply(float(parameter.value))
                    self._log(f"{parameter.name} set to {parameter.value}", None)
            return SetParametersResult(successful=True)

        self.node.add_on_set_parameters_callback(on_set)

    # ---- services --------------------------------------------------------------------------------

    def _guarded(self, name: str, handler: Callable[[R, S], S]) -> Callable[[R, S], S]:
        """``handler``, answering even when it fails (an exception would leave the caller waiting forever): the
        failure is flagged and said in the answer's ``message``."""

        def answer(request: R, response: S) -> S:
            try:
                return handler(request, response)
            except Exception as exc:  # noqa: BLE001 - said in the answer and on /safety_status
                text = f"{name} failed: {type(exc).__name__}: {exc}"
                self.set_flag("service", text, Level.WARN)
                if hasattr(response, "message"):
                    response.message = text
                return response

        return answer

    def _services(self) -> None:
        prime = _interface("prime_msgs.srv")
        if prime is None:
            self.missing.append("prime_msgs (~/switch_mode, ~/reset_faults left out)")
        else:
            self.node.create_service(prime.SwitchMode, "~/switch_mode",
                                     self._guarded("~/switch_mode", self._switch_mode), callback_group=self._group)
            self.node.create_service(prime.ResetFaults, "~/reset_faults",
                                     self._guarded("~/reset_faults", self._reset_faults), callback_group=self._group)
        cm = _interface("controller_manager_msgs.srv")
        if cm is None:
            self.missing.append("controller_manager_msgs (the controller manager's services left out)")
        else:
            self._cm_msg = importlib.import_module("controller_manager_msgs.msg")
            where = in_namespace(self.namespace, NAMESPACE)
            self.node.create_service(cm.ListControllers, f"{where}/list_controllers",
                                     self._guarded("list_controllers", self._list_controllers),
                                     callback_group=self._group)
            self.node.create_service(cm.SwitchController, f"{where}/switch_controller",
                                     self._guarded("switch_controller", self._switch_controller),
                                     callback_group=self._group)

    def _switch(self, mode: Mode, wait_s: float) -> SwitchResult:
        if not self.control:
            return SwitchResult("refused", "", f"{mode.value} refused: {NOT_CONTROLLING}")
        if self.switch is None:
            return SwitchResult("refused", "", f"{mode.value} refused: this run switches no modes")
        try:
            return self.switch(mode, wait_s if wait_s > 0 else DEFAULT_WAIT_S)
        except PrimeError as exc:
            return SwitchResult("refused", "", str(exc))

    def _switch_mode(self, request: _SwitchModeRequest, response: _SwitchModeResponse) -> _SwitchModeResponse:
        try:
            answer = self._switch(Mode.parse(request.mode), request.timeout)
        except ValueError as exc:
            answer = SwitchResult("refused", "", str(exc))
        response.success, response.outcome = answer.ok, answer.outcome
        response.active_mode, response.message = answer.active, answer.message
        self._log(f"~/switch_mode: {answer.message}", None if answer.ok else Level.WARN)
        return response

    def _reset_faults(self, request: object, response: _ResetFaultsResponse) -> _ResetFaultsResponse:
        if not self.control:
            response.success, response.message = False, NOT_CONTROLLING
            return response
        before = self.manager.resets
        faults = self.manager.request_reset()
        deadline = time.monotonic() + DEFAULT_WAIT_S
        while self.manager.resets == before and time.monotonic() < deadline:
            time.sleep(self.manager.period / 2)
        applied = self.manager.resets != before
        response.success = applied
        response.faults = list(faults)
        response.message = (f"reset applied; {len(faults)} latched fault(s) before it" if applied else
                            f"the control loop did not apply the reset within {DEFAULT_WAIT_S:g} s")
        self._log(f"~/reset_faults: {response.message}", None if applied else Level.WARN)
        return response

    def _list_controllers(self, request: object, response: _ListControllersResponse) -> _ListControllersResponse:
        states: list[object] = []
        for info in controllers(self.manager):
            state = self._cm_msg.ControllerState()
            state.name, state.state, state.type, state.update_rate = info.name, info.state, info.type, info.update_rate
            state.claimed_interfaces = list(info.claimed_interfaces)
            state.required_command_interfaces = list(info.required_command_interfaces)
            state.required_state_interfaces = list(info.required_state_interfaces)
            states.append(state)
        response.controller = states
        return response

    def _switch_controller(self, request: _SwitchControllerRequest,
                           response: _SwitchControllerResponse) -> _SwitchControllerResponse:
        strict = request.strictness == STRICT
        try:
            mode = mode_to_activate(self.manager, list(request.activate_controllers),
                                    list(request.deactivate_controllers), strict)
        except SwitchRefused as exc:
            response.ok, response.message = False, str(exc)
        else:
            if mode is None:
                response.ok, response.message = True, "nothing to switch"
            else:
                answer = self._switch(mode, _seconds(request.timeout))
                response.ok, response.message = answer.ok, answer.message
        self._log(f"switch_controller: {response.message}", None if response.ok else Level.WARN)
        return response

    # ---- the trajectory actions ------------------------------------------------------------------

    def _actions(self) -> None:
        action = _interface("control_msgs.action")
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
            points=tuple(Point(_seconds(p.time_from_start), list(p.positions), list(p.velocities))
                         for p in request.trajectory.points),
            path_tolerance=tolerances(request.path_tolerance), goal_tolerance=tolerances(request.goal_tolerance),
            goal_time_tolerance_s=_seconds(request.goal_time_tolerance),
            multi_dof=bool(request.multi_dof_trajectory.points))

    def _accept(self, request: _GoalRequest, name: str, joints: tuple[str, ...]) -> GoalResponse:
        if not self.control:
            self._log(f"{name}: goal rejected: {NOT_CONTROLLING}", Level.WARN)
            return GoalResponse.REJECT
        try:
            from humanoid_prime.dds.trajectory import plan

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

    # ---- the executor and the run's end ----------------------------------------------------------

    def _spin(self) -> None:
        while self.context.ok() and not self._closed:
            try:
                self._executor.spin_once(timeout_sec=0.1)
            except Exception as exc:  # the context shut down under it, or a callback failed: flagged, not fatal
                if self._closed or not self.context.ok():
                    return
                self.set_flag("executor", f"rclpy executor: {type(exc).__name__}: {exc}", Level.WARN)

    def joint_state_readers(self) -> int:
        """How many subscriptions of the joint states this node is matched with now."""
        return self._publishers[self.joint_states_topic].get_subscription_count()

    def pause(self) -> None:
        """Stop taking the loop's ticks (the node and everything it serves stay on the graph)."""
        self.tap.close()

    def resume(self) -> None:
        """Take the loop's ticks again after ``pause``."""
        self.tap = TickTap(self.manager, self, name="rclpy-publish", on_drop=self.on_drop, slots=self.tap.slots,
                           clock=self.clock)

    def started(self) -> str:
        """The start-up line, also logged on /rosout."""
        missing = f"; not installed: {'; '.join(self.missing)}" if self.missing else ""
        node = in_namespace(self.namespace, "/" + NODE_NAME)
        control = "control from the graph ON" if self.control else "publishing only (no --dds-control)"
        line = f"ROS 2 node {node} on rclpy ({self.rmw}), domain {self.domain}; {control}{missing}"
        self._log(line, None, outer=False)
        return line

    def summary(self) -> dict[str, object]:
        return {"domain": self.domain, "node": in_namespace(self.namespace, "/" + NODE_NAME), "rmw": self.rmw,
                "missing": list(self.missing), "trajectory_commands": self.trajectories.sent, **super().summary()}

    def close(self, timeout: float = 5.0) -> None:
        """Detach from the loop (what is queued is written first), end any goal, then leave the graph: the
        node is destroyed and the context shut down, which deletes the participant and tells the peers."""
        if self._closed:
            return
        self.tap.close(timeout)
        self.trajectories.stop()
        self._closed = True
        self._teardown()

    def _teardown(self) -> None:
        self._closed = True
        spinner = getattr(self, "_spinner", None)
        if spinner is not None:
            spinner.join(2.0)  # its spin_once returns within 0.1 s and sees _closed
        executor = getattr(self, "_executor", None)
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        node = getattr(self, "node", None)
        if node is not None:
            for server in getattr(self, "_action_servers", []):
                server.destroy()
            node.destroy_node()
        self.context.try_shutdown()


def rclpy_bridge(manager: ControllerManager, *, domain: int, namespace: str = "/", control: bool = False,
                 request_mode: Callable[[str], object] | None = None, switch: Switch | None = None,
                 epoch_offset: float = 0.0, sim_clock: bool = False, report: Report | None = None) -> RclpyBridge:
    """Put ``manager``'s run on the ROS 2 graph as rclpy node ``prime`` (module docstring); its flags join
    /safety_status."""
    gravity = None
    try:
        from humanoid_prime.calibration.gravity import GravityModel

        gravity = GravityModel(manager.robot).torques
    except Exception:  # noqa: BLE001 - without a model the trajectories go without feed-forward
        gravity = None
    bridge = RclpyBridge(manager, domain=domain, namespace=namespace, control=control,
                         request_mode=request_mode or manager.request_mode, switch=switch, epoch_offset=epoch_offset,
                         sim_clock=sim_clock, report=report, gravity=gravity)
    manager.add_flag_source(bridge)
    return bridge
