"""Node ``prime`` as an rclpy node, on whatever middleware the user's ROS 2 is set to: the topics of the bare
backend (``graph.py``: the same names, types, QoS and bytes) and what only a real ROS 2 node serves:

- parameters: the run, read-only, and ``remote.timeout_s`` settable within its bounds (``parameters.py``);
  ``use_sim_time`` as every rclpy node has it (off unless set, even in simulation);
- logs on ``/rosout``: the start-up line, each flag of /safety_status at its level as it appears, and QoS
  mismatches;
- services ``~/switch_mode`` and ``~/reset_faults`` (prime_msgs), and the controller manager's ``list_controllers``
  and ``switch_controller`` (``rclpy_services.py``);
- ``control_msgs/action/FollowJointTrajectory`` for each arm and both, executed through REMOTE
  (``rclpy_actions.py``).

What moves the robot (mode requests, MitCommands, the mode and reset services, switch_controller and trajectory
goals) is taken only when the run takes control from the graph (``--dds-control``); without it each is refused
with that reason. The loop never waits on rclpy: ticks reach the publisher through a tick tap, as on the bare
backend, and rclpy's executor runs on threads of its own (it waits in C, without the interpreter's lock).
Interfaces that are not installed (prime_msgs, tf2_msgs, control_msgs, controller_manager_msgs have no PyPI
wheels) leave out what needs them, and the start-up line says which.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Protocol

import numpy as np
import numpy.typing as npt
import rclpy
from cyclonedds.idl import IdlStruct
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
from humanoid_prime.dds.controllers import Switch
from humanoid_prime.dds.domain import in_namespace
from humanoid_prime.dds.graph import NODE_NAME, GraphBridge, Report
from humanoid_prime.dds.parameters import run_parameters
from humanoid_prime.dds.rclpy_actions import TrajectoryActions
from humanoid_prime.dds.rclpy_services import ModeServices, interface
from humanoid_prime.dds.trajectory import TrajectoryExecutor

Array = npt.NDArray[np.float64]

EXECUTOR_THREADS = 4  # services that wait for the loop, goals that run for seconds, and everything else


class _Publisher(Protocol):  # what Prime uses of an rclpy publisher
    def publish(self, message: bytes) -> None: ...
    def get_subscription_count(self) -> int: ...


def _qos(latched: bool, depth: int) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def _policy(event: object) -> str:
    kind = getattr(event, "last_policy_kind", None)
    return str(getattr(kind, "name", kind)).lower().replace("_", " ")


class RclpyBridge(GraphBridge, ModeServices, TrajectoryActions):
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
            module = interface(f"{package}.{kind}")
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
