"""Prime on the ROS 2 graph: node ``prime`` (in the run's namespace) with the in-process topics of a running
controller manager, published and subscribed over DDS with ROS 2's types, names and QoS.

Out: ``/prime/joint_states`` (sensor_msgs/JointState, every tick, canonical order), ``/control_mode``
(std_msgs/String, latched, on change), ``/safety_status`` (diagnostic_msgs/DiagnosticArray, latched, on
change: one status per flag source, one key/value per flag) and the same statuses on ``/diagnostics`` (on
change and every second, as diagnostic_updater publishes), ``/robot_description`` (std_msgs/String, latched:
the URDF), ``/tf_static`` (the fixed joints, latched) and ``/tf`` (tf2_msgs/TFMessage: every actuated joint
from the measured positions, every tick), and in simulation ``/clock`` (rosgraph_msgs/Clock, every tick, the
simulated time the stamps are in). Every topic is under the run's namespace.

In, only when the run takes control from the graph (``--dds-control``): the REMOTE controller's MIT command
(prime_msgs/MitCommand) and ``/prime/mode_request`` (std_msgs/String), which takes the same path, with the
same refusals, as ``prime switch``. Without it nothing on the graph can move the robot, and the ``dds`` status
says which of the two a run is.

This is the bare backend: one Cyclone DDS participant that ROS 2 sees as a node (``node.py``), for hosts without
ROS 2. What the node publishes and how samples enter the stack is ``graph.py``'s, shared with the rclpy backend.

The control tick never waits on DDS: a ``TickTap`` hands each tick's joint state to the publisher thread at
the end of the tick, which converts and writes while the loop waits for its next period. When the publisher,
the transport or a reader falls behind, samples are dropped, counted and flagged; the tick goes on.
Incoming samples are read on their own thread and enter the stack through the same paths as in-process ones.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from cyclonedds.core import GuardCondition, InstanceState, Listener, ReadCondition, SampleState, ViewState, WaitSet
from cyclonedds.idl import IdlStruct
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.util import duration

from humanoid_prime.control.flags import Level
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.tap import SLOTS, TickTap
from humanoid_prime.dds import messages as msg
from humanoid_prime.dds.domain import Discovery
from humanoid_prime.dds.graph import MODE_REQUEST, NODE_NAME, GraphBridge, Report
from humanoid_prime.dds.node import DdsNode, take

READ_BATCH = 32
# Cyclone's QoS policy ids (dds_qos_policy_id_t) as ROS 2 names them in its incompatible-QoS events.
POLICY_NAMES = {2: "durability", 4: "deadline", 5: "latency budget", 6: "ownership", 8: "liveliness",
                11: "reliability", 12: "destination order", 13: "history", 23: "lifespan", 28: "data representation"}


def _policy(status: object) -> str:
    policy_id = getattr(status, "last_policy_id", -1)
    return POLICY_NAMES.get(int(policy_id), f"policy {policy_id}")


class DdsBridge(GraphBridge):
    """Node ``prime`` as one bare Cyclone DDS participant (module docstring)."""

    backend = "dds"

    def __init__(self, node: DdsNode, manager: ControllerManager, *, request_mode: Callable[[str], object] | None,
                 control: bool = True, epoch_offset: float = 0.0, sim_clock: bool = False, slots: int = SLOTS,
                 clock: Callable[[], float] = time.perf_counter, report: Report | None = None) -> None:
        super().__init__(manager, request_mode=request_mode, control=control, epoch_offset=epoch_offset,
                         sim_clock=sim_clock, clock=clock, report=report)
        self.node = node
        self._stop = threading.Event()
        self._writers: dict[str, DataWriter[IdlStruct]] = {}
        for topic, spec in self.specs.items():
            if spec.direction == "out":
                self._writers[topic] = node.writer(topic, spec.message, latched=spec.latched, depth=spec.depth,
                                                   listener=self._listener(topic))
        self._commands: DataReader[msg.MitCommand] | None = None
        self._mode_requests: DataReader[msg.String] | None = None
        if control:
            self._commands = node.reader(self.remote_topic, msg.MitCommand, listener=self._listener(self.remote_topic))
            self._mode_requests = node.reader(MODE_REQUEST, msg.String, listener=self._listener(MODE_REQUEST))
        self.publish_static()
        self._guard = GuardCondition(node.participant)
        self._waitset = WaitSet(node.participant)
        self._waitset.attach(self._guard)
        mask = SampleState.NotRead | ViewState.Any | InstanceState.Any
        self._conditions = {topic: ReadCondition(reader, mask) for topic, reader in
                            ((self.remote_topic, self._commands), (MODE_REQUEST, self._mode_requests))
                            if reader is not None}
        for condition in self._conditions.values():
            self._waitset.attach(condition)
        self._reader = threading.Thread(target=self._read_loop, name="dds-read", daemon=True)
        self._reader.start()
        self._closed = False
        self.tap = TickTap(manager, self, name="dds-publish", on_drop=self.on_drop, slots=slots, clock=clock)

    def _listener(self, topic: str) -> Listener:
        """Cyclone's incompatible-QoS statuses of ``topic``'s endpoint (called on Cyclone's own thread)."""
        return Listener(  # type: ignore[no-untyped-call]  # Cyclone's Listener takes its callbacks untyped
            on_offered_incompatible_qos=lambda _, status: self.qos_mismatch(topic, _policy(status), "subscription"),
            on_requested_incompatible_qos=lambda _, status: self.qos_mismatch(topic, _policy(status), "publisher"))

    def write(self, topic: str, message: IdlStruct) -> None:
        self._writers[topic].write(message)

    def pause(self) -> None:
        """Stop taking the loop's ticks (the node, its latched topics and its readers stay on the graph)."""
        self.tap.close()

    def resume(self) -> None:
        """Take the loop's ticks again after ``pause``."""
        self.tap = TickTap(self.manager, self, name="dds-publish", on_drop=self.on_drop, slots=self.tap.slots,
                           clock=self.clock)

    def joint_state_readers(self) -> int:
        """How many DDS readers of the joint states this bridge is matched with now."""
        return len(self._writers[self.joint_states_topic].get_matched_subscriptions())

    # ---- the reader thread -----------------------------------------------------------------------

    def _read_loop(self) -> None:
        while not self._stop.is_set():
            self._waitset.wait(duration(seconds=1))
            if self._stop.is_set():
                return
            if not self.control:
                continue
            try:
                if self._commands is not None:
                    for command in take(self._commands, READ_BATCH, self._conditions[self.remote_topic]):
                        self.on_command(command)
                if self._mode_requests is not None:
                    for request in take(self._mode_requests, READ_BATCH, self._conditions[MODE_REQUEST]):
                        self.on_mode_request(request)
            except Exception as exc:
                self.set_flag("read", f"DDS read failed: {type(exc).__name__}: {exc}", Level.WARN)

    # ---- the run's end ---------------------------------------------------------------------------

    def summary(self) -> dict[str, object]:
        return {"domain": self.node.domain, "node": self.node.topic_name("/" + NODE_NAME),
                "discovery": self.node.settings.describe(), **super().summary()}

    def close(self, timeout: float = 5.0) -> None:
        """Detach from the loop (what is queued is written first), stop reading, then leave the graph: the node
        first (ros_discovery_info without it, as rmw does when a node goes), then the participant."""
        if self._closed:
            return
        self._closed = True
        self.tap.close(timeout)
        self._stop.set()
        self._guard.set(True)
        self._reader.join(timeout)
        self.node.close()


def bridge_manager(manager: ControllerManager, *, domain: int | None = None, namespace: str = "/",
                   control: bool = False, request_mode: Callable[[str], object] | None = None,
                   epoch_offset: float = 0.0, sim_clock: bool = False,
                   settings: Discovery | None = None, report: Report | None = None) -> DdsBridge:
    """Put ``manager``'s topics on DDS as node ``prime`` in ``namespace`` (domain ``domain``, else
    ``ROS_DOMAIN_ID``); its flags join /safety_status. With ``control``, mode requests and REMOTE commands are
    taken from the graph; ``request_mode`` defaults to the manager's own (which refuses in a broadcaster-only
    run)."""
    node = DdsNode(domain, name=NODE_NAME, namespace=namespace, settings=settings)
    try:
        bridge = DdsBridge(node, manager, request_mode=request_mode or manager.request_mode, control=control,
                           epoch_offset=epoch_offset, sim_clock=sim_clock, report=report)
    except BaseException:
        node.close()
        raise
    manager.add_flag_source(bridge)
    return bridge
