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

The control tick never waits on DDS: a ``TickTap`` hands each tick's joint state to the publisher thread at
the end of the tick, which converts and writes while the loop waits for its next period. When the publisher,
the transport or a reader falls behind, samples are dropped, counted and flagged; the tick goes on.
Incoming samples are read on their own thread and enter the stack through the same paths as in-process ones.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from cyclonedds.core import GuardCondition, InstanceState, ReadCondition, SampleState, ViewState, WaitSet
from cyclonedds.util import duration

from humanoid_prime.control.flags import Level, SafetyFlags
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.tap import SLOTS, TickSample, TickTap
from humanoid_prime.control.topics import (
    CONTROL_MODE,
    SAFETY_STATUS,
    ControlMode,
    SafetyStatus,
)
from humanoid_prime.control.topics import MitCommand as MitCommandMessage
from humanoid_prime.dds import messages as msg
from humanoid_prime.dds.domain import Discovery
from humanoid_prime.dds.node import DdsNode, take
from humanoid_prime.dds.tf import frames_from_urdf
from humanoid_prime.dds.tfmessage import TfPacker
from humanoid_prime.modes import Mode

NODE_NAME = "prime"
MODE_REQUEST = "/prime/mode_request"
DIAGNOSTICS = "/diagnostics"
ROBOT_DESCRIPTION = "/robot_description"
TF = "/tf"
TF_STATIC = "/tf_static"
CLOCK = "/clock"
TF_DEPTH = 100  # tf2's listener QoS (reliable, volatile, keep-last 100)
DIAGNOSTICS_PERIOD_S = 1.0  # diagnostic_updater's default period: aggregators mark a silent status stale
LATENCY_WINDOW = 4096  # recent tick-to-written latencies kept for the summary
HARDWARE_ID = "prime"
READ_BATCH = 32
CONTROL_ON = "takes mode requests and REMOTE commands from the ROS 2 graph (--dds-control)"
CONTROL_OFF = "publishes only: nothing on the ROS 2 graph can switch modes or command the robot"


class TopicCounts:
    """What went through one topic: samples published (or received), dropped, late, refused."""

    def __init__(self, ros_type: str, direction: str) -> None:
        self.ros_type = ros_type
        self.direction = direction
        self.samples = 0
        self.dropped = 0
        self.late = 0
        self.refused = 0
        self.last_refusal = ""

    def as_dict(self) -> dict[str, Any]:
        key = "published" if self.direction == "out" else "received"
        result: dict[str, Any] = {"type": self.ros_type, key: self.samples}
        if self.direction == "out":
            result.update(dropped=self.dropped, late=self.late)
        else:
            result.update(refused=self.refused, last_refusal=self.last_refusal)
        return result


def diagnostics(status: SafetyStatus, sources: Sequence[str], epoch_offset: float,
                notes: dict[str, str] | None = None,
                configuration: Mapping[str, Mapping[str, Any]] | None = None) -> msg.DiagnosticArray:
    """One DiagnosticStatus per flag source (``prime/<source>``), OK when it has no flag, else its worst level,
    the flags' texts as the message and each flag as a key/value. ``notes`` adds a standing remark to a
    source's message (``ok; <note>``). Then ``prime/configuration``, the run's configuration files (path and
    sha256 of each kind), when it has them."""
    grouped: dict[str, list[tuple[str, str, Level]]] = {source: [] for source in sources}
    for key, text in status.flags.items():
        source, _, rest = key.partition("/")
        grouped.setdefault(source, []).append((rest or source, text, status.levels.get(key, Level.ERROR)))
    statuses = []
    for source, flags in grouped.items():
        level = max((int(level) for _, _, level in flags), default=msg.DiagnosticStatus.OK)
        message = "; ".join(text for _, text, _ in flags) or "ok"
        if notes and source in notes:
            message = f"{message}; {notes[source]}"
        statuses.append(msg.DiagnosticStatus(
            level=level, name=f"prime/{source}", message=message,
            hardware_id=HARDWARE_ID, values=[msg.KeyValue(key=key, value=text) for key, text, _ in flags]))
    if configuration:
        values = [msg.KeyValue(key=f"{kind}{suffix}", value=str(entry.get(field, "")))
                  for kind, entry in configuration.items() for suffix, field in (("", "path"), ("_sha256", "sha256"))]
        statuses.append(msg.DiagnosticStatus(
            level=msg.DiagnosticStatus.OK, name="prime/configuration", hardware_id=HARDWARE_ID,
            message="; ".join(f"{kind} {entry.get('path')}" for kind, entry in configuration.items()), values=values))
    return msg.DiagnosticArray(header=msg.Header(stamp=msg.stamp(status.stamp + epoch_offset)), status=statuses)


class DdsBridge(SafetyFlags):
    """Bridges a controller manager's topics to DDS (module docstring). A flag source of its own (``dds``):
    dropped joint states, refused mode requests, transport errors.

    ``epoch_offset`` turns the loop clock into message stamps: ``time.time() - time.monotonic()`` for a run on
    the robot (stamps in the system clock, as ROS 2 nodes use), 0 in simulation (stamps in simulated time, as
    ROS 2 does with ``use_sim_time``, and then ``sim_clock`` publishes that time on ``/clock``).
    ``request_mode`` is the run's mode request path; with ``control`` False nothing is read from the graph.
    """

    def __init__(self, node: DdsNode, manager: ControllerManager, *, request_mode: Callable[[str], None] | None,
                 control: bool = True, epoch_offset: float = 0.0, sim_clock: bool = False, slots: int = SLOTS,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        super().__init__("dds")
        self.node = node
        self.manager = manager
        self.topics = manager.topics
        self.names = list(manager.robot.names)
        self.period = manager.period
        self.request_mode = request_mode
        self.control = control
        self.sources = [*manager.flag_source_names, self.name]
        self.notes = {self.name: CONTROL_ON if control else CONTROL_OFF}
        self.epoch_offset = epoch_offset
        self.joint_states_topic = manager.config.joint_states_topic
        self.remote_topic = manager.config.remote.topic
        self.clock = clock
        self.frames = frames_from_urdf(manager.robot.description.urdf, manager.robot.names)
        out = {self.joint_states_topic: "sensor_msgs/msg/JointState", CONTROL_MODE: "std_msgs/msg/String",
               SAFETY_STATUS: "diagnostic_msgs/msg/DiagnosticArray", DIAGNOSTICS: "diagnostic_msgs/msg/DiagnosticArray",
               ROBOT_DESCRIPTION: "std_msgs/msg/String", TF_STATIC: "tf2_msgs/msg/TFMessage",
               TF: "tf2_msgs/msg/TFMessage", **({CLOCK: "rosgraph_msgs/msg/Clock"} if sim_clock else {})}
        self.counts = {topic: TopicCounts(ros_type, "out") for topic, ros_type in out.items()}
        if control:
            self.counts[self.remote_topic] = TopicCounts("prime_msgs/msg/MitCommand", "in")
            self.counts[MODE_REQUEST] = TopicCounts("std_msgs/msg/String", "in")
        self._latency = np.full(LATENCY_WINDOW, np.nan)
        self._latencies = 0
        self._last_diagnostics: msg.DiagnosticArray | None = None
        self._diagnostics_due = -np.inf
        self._stop = threading.Event()

        self._joint_states = node.writer(self.joint_states_topic, msg.JointState)
        self._mode = node.writer(CONTROL_MODE, msg.String, latched=True, depth=1)
        self._safety = node.writer(SAFETY_STATUS, msg.DiagnosticArray, latched=True, depth=1)
        self._diagnostics = node.writer(DIAGNOSTICS, msg.DiagnosticArray)
        self._description = node.writer(ROBOT_DESCRIPTION, msg.String, latched=True, depth=1)
        self._tf_static = node.writer(TF_STATIC, msg.TFMessage, latched=True, depth=1)
        self._tf = node.writer(TF, msg.TFMessage, depth=TF_DEPTH)
        self._clock = node.writer(CLOCK, msg.Clock, depth=1) if sim_clock else None
        self._tf_packer = TfPacker(self.frames.parents, self.frames.children)
        self._write(self._description, msg.String(data=manager.robot.description.urdf), ROBOT_DESCRIPTION)
        self._write(self._tf_static, self._static_transforms(), TF_STATIC)
        self._guard = GuardCondition(node.participant)
        self._waitset = WaitSet(node.participant)
        self._waitset.attach(self._guard)
        self._conditions: dict[int, ReadCondition] = {}
        if control:
            self._commands = node.reader(self.remote_topic, msg.MitCommand)
            self._mode_requests = node.reader(MODE_REQUEST, msg.String)
            mask = SampleState.NotRead | ViewState.Any | InstanceState.Any
            self._conditions = {id(reader): ReadCondition(reader, mask)
                                for reader in (self._commands, self._mode_requests)}
            for condition in self._conditions.values():
                self._waitset.attach(condition)
        self._reader = threading.Thread(target=self._read_loop, name="dds-read", daemon=True)
        self._reader.start()
        self._closed = False
        self.tap = TickTap(manager, self, name="dds-publish", on_drop=self._on_drop, slots=slots, clock=clock)

    def _static_transforms(self) -> msg.TFMessage:
        """The fixed joints (stamp 0: tf2 holds a static transform for all times)."""
        f = self.frames
        return msg.TFMessage(transforms=[
            msg.TransformStamped(header=msg.Header(frame_id=parent), child_frame_id=child,
                                 transform=msg.Transform(msg.Vector3(*map(float, t)), msg.Quaternion(*map(float, r))))
            for parent, child, t, r in zip(f.static_parents, f.static_children, f.static_translations,
                                           f.static_rotations, strict=True)])

    def pause(self) -> None:
        """Stop taking the loop's ticks (the node, its latched topics and its readers stay on the graph)."""
        self.tap.close()

    def resume(self) -> None:
        """Take the loop's ticks again after ``pause``."""
        self.tap = TickTap(self.manager, self, name="dds-publish", on_drop=self._on_drop, slots=self.tap.slots,
                           clock=self.clock)

    def joint_state_readers(self) -> int:
        """How many DDS readers of the joint states this bridge is matched with now."""
        return len(self._joint_states.get_matched_subscriptions())

    def _on_drop(self, dropped: int) -> None:
        self.counts[self.joint_states_topic].dropped = dropped
        self.set_flag("dropped", f"{dropped} joint states dropped: the DDS publisher fell behind the loop",
                      Level.WARN)

    # ---- the publisher thread (the tap's consumer) -----------------------------------------------

    def on_tick(self, sample: TickSample) -> None:
        data = sample.data
        stamp = msg.stamp(sample.stamp + self.epoch_offset)
        if self._clock is not None:  # first: a use_sim_time node's clock is never behind the stamps it gets
            self._write(self._clock, msg.Clock(clock=stamp), CLOCK)
        self._write(self._joint_states, msg.JointState(
            header=msg.Header(stamp=stamp), name=self.names,
            position=data[0].tolist(), velocity=data[1].tolist(), effort=data[2].tolist()))
        self._write(self._tf, self._transforms(data[0], stamp), TF)
        if sample.stamp >= self._diagnostics_due and self._last_diagnostics is not None:
            self._publish_diagnostics(self._last_diagnostics, sample.stamp)
        latency = self.clock() - sample.queued_at
        self._latency[self._latencies % LATENCY_WINDOW] = latency
        self._latencies += 1
        counts = self.counts[self.joint_states_topic]
        counts.samples += 1
        if latency > self.period:
            counts.late += 1

    def _transforms(self, positions: np.ndarray, stamp: msg.Time) -> msg.TFMessage:
        return self._tf_packer.fill(*self.frames.transforms(positions), stamp)

    def on_mode(self, message: ControlMode) -> None:
        self._write(self._mode, msg.String(data=message.mode), CONTROL_MODE)

    def on_safety(self, message: SafetyStatus) -> None:
        array = diagnostics(message, self.sources, self.epoch_offset, self.notes,
                            self.manager.configuration)
        self._write(self._safety, array, SAFETY_STATUS)
        self._publish_diagnostics(array, message.stamp)

    def _publish_diagnostics(self, array: msg.DiagnosticArray, now: float) -> None:
        self._last_diagnostics = array
        self._diagnostics_due = now + DIAGNOSTICS_PERIOD_S
        array.header.stamp = msg.stamp(now + self.epoch_offset)
        self._write(self._diagnostics, array, DIAGNOSTICS)

    def on_remote(self, message: MitCommandMessage) -> None:  # the bridge takes no remote tap
        """Not used: the bridge is the source of remote commands, not their consumer."""

    def _write(self, writer: Any, sample: Any, topic: str | None = None) -> None:
        try:
            writer.write(sample)
        except Exception as exc:  # a transport error is a flag, never the end of publishing
            self.set_flag("publish", f"DDS write failed: {type(exc).__name__}: {exc}", Level.WARN)
            raise
        if topic is not None:
            self.counts[topic].samples += 1

    # ---- the reader thread -----------------------------------------------------------------------

    def _read_loop(self) -> None:
        while not self._stop.is_set():
            self._waitset.wait(duration(seconds=1))
            if self._stop.is_set():
                return
            if not self.control:
                continue
            try:
                for sample in self._take(self._commands):
                    self._on_command(sample)
                for sample in self._take(self._mode_requests):
                    self._on_mode_request(sample)
            except Exception as exc:
                self.set_flag("read", f"DDS read failed: {type(exc).__name__}: {exc}", Level.WARN)

    def _take(self, reader: Any) -> list[Any]:
        condition = self._conditions[id(reader)]
        return take(reader, READ_BATCH, condition=condition)

    def _on_command(self, sample: msg.MitCommand) -> None:
        self.counts[self.remote_topic].samples += 1
        self.topics.publish(self.remote_topic, MitCommandMessage(
            joint_names=tuple(sample.name), position=np.asarray(sample.position, dtype=np.float64),
            velocity=np.asarray(sample.velocity, dtype=np.float64), effort=np.asarray(sample.effort, dtype=np.float64),
            stiffness=np.asarray(sample.stiffness, dtype=np.float64),
            damping=np.asarray(sample.damping, dtype=np.float64), stamp=msg.seconds(sample.header.stamp)))

    def _on_mode_request(self, sample: msg.String) -> None:
        counts = self.counts[MODE_REQUEST]
        counts.samples += 1
        try:
            if self.request_mode is None:
                raise ValueError("this run takes no mode requests")
            self.request_mode(sample.data)
        except Exception as exc:
            counts.refused += 1
            counts.last_refusal = f"{sample.data!r}: {exc}"
            self.set_flag("mode_request", f"mode request {sample.data!r} on {MODE_REQUEST} refused: {exc}",
                          Level.WARN)
        else:
            self.clear_flag("mode_request")

    # ---- the run's end ---------------------------------------------------------------------------

    def summary(self) -> dict[str, Any]:
        topics = {topic: counts.as_dict() for topic, counts in self.counts.items()}
        remote = self.manager.controllers.get(Mode.REMOTE.controller)
        if remote is not None and self.control:  # every refusal of a command from the graph is REMOTE's
            topics[self.remote_topic].update(refused=remote.rejected, last_refusal=remote.last_rejection)
        latency = self._latency[np.isfinite(self._latency)] * 1e6
        return {
            "domain": self.node.domain,
            "node": self.node.topic_name("/" + NODE_NAME),
            "control": self.control,
            "discovery": self.node.settings.describe(),
            "topics": topics,
            "tick_to_written_us": {
                "median": float(np.median(latency)) if latency.size else None,
                "p99": float(np.percentile(latency, 99)) if latency.size else None,
            },
        }

    def close(self, timeout: float = 5.0) -> None:
        """Detach from the loop (what is queued is written first), stop reading, then leave the DDS domain."""
        if self._closed:
            return
        self._closed = True
        self.tap.close(timeout)
        self._stop.set()
        self._guard.set(True)
        self._reader.join(timeout)
        self.node.close()


def bridge_manager(manager: ControllerManager, *, domain: int | None = None, namespace: str = "/",
                   control: bool = False, request_mode: Callable[[str], None] | None = None,
                   epoch_offset: float = 0.0, sim_clock: bool = False,
                   settings: Discovery | None = None) -> DdsBridge:
    """Put ``manager``'s topics on DDS as node ``prime`` in ``namespace`` (domain ``domain``, else
    ``ROS_DOMAIN_ID``); its flags join /safety_status. With ``control``, mode requests and REMOTE commands are
    taken from the graph; ``request_mode`` defaults to the manager's own (which refuses in a broadcaster-only
    run)."""
    node = DdsNode(domain, name=NODE_NAME, namespace=namespace, settings=settings)
    try:
        bridge = DdsBridge(node, manager, request_mode=request_mode or manager.request_mode, control=control,
                           epoch_offset=epoch_offset, sim_clock=sim_clock)
    except BaseException:
        node.close()
        raise
    manager.add_flag_source(bridge)
    return bridge
