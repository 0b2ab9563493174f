"""What node ``prime`` is on the ROS 2 graph, whichever backend carries it (bare Cyclone DDS, ``bridge.py``, or
rclpy, ``rclpy_node.py``): its topics with their types and QoS, the messages it makes from the loop's ticks, how a
sample from the graph enters the stack, QoS mismatches, and the figures of the run's summary.

A backend gives ``write(topic, message)`` (one of ``messages.py``'s types: a Cyclone writer writes it, an rclpy
publisher publishes its CDR bytes, the same bytes) and passes what it reads to ``on_command`` and
``on_mode_request``; this class does the rest, so both backends say and count the same things.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from cyclonedds.idl import IdlStruct

from humanoid_prime.control.controllers.remote import RemotePolicyController
from humanoid_prime.control.flags import Level, SafetyFlags
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.tap import TickSample
from humanoid_prime.control.topics import CONTROL_MODE, SAFETY_STATUS, ControlMode, SafetyStatus
from humanoid_prime.control.topics import MitCommand as MitCommandMessage
from humanoid_prime.dds import messages as msg
from humanoid_prime.dds.tf import Frames, frames_from_urdf
from humanoid_prime.dds.tfmessage import TfPacker
from humanoid_prime.modes import Mode

NODE_NAME = "prime"
MODE_REQUEST = "/prime/mode_request"
DIAGNOSTICS = "/diagnostics"
ROBOT_DESCRIPTION = "/robot_description"
TF = "/tf"
TF_STATIC = "/tf_static"
CLOCK = "/clock"
DEFAULT_DEPTH = 10  # ROS 2's default QoS: reliable, volatile, keep-last 10
TF_DEPTH = 100  # tf2's listener QoS (reliable, volatile, keep-last 100)
DIAGNOSTICS_PERIOD_S = 1.0  # diagnostic_updater's default period: aggregators mark a silent status stale
LATENCY_WINDOW = 4096  # recent tick-to-written latencies kept for the summary
HARDWARE_ID = "prime"
CONTROL_ON = "takes mode requests and REMOTE commands from the ROS 2 graph (--dds-control)"
CONTROL_OFF = "publishes only: nothing on the ROS 2 graph can switch modes or command the robot"

Report = Callable[[str, Level | None], None]  # a log line of the node and its level (None: information)


@dataclass(frozen=True)
class TopicSpec:
    """One topic of the node: ROS 2 type, QoS (latched: transient-local) and which way it goes."""

    ros_type: str
    message: type[IdlStruct]
    direction: str  # "out" or "in"
    latched: bool = False
    depth: int = DEFAULT_DEPTH


def topics(manager: ControllerManager, *, sim_clock: bool, control: bool) -> dict[str, TopicSpec]:
    """Every topic of node ``prime`` for ``manager``'s run (absolute names, before the namespace)."""
    config = manager.config
    out = {
        config.joint_states_topic: TopicSpec("sensor_msgs/msg/JointState", msg.JointState, "out"),
        CONTROL_MODE: TopicSpec("std_msgs/msg/String", msg.String, "out", latched=True, depth=1),
        SAFETY_STATUS: TopicSpec("diagnostic_msgs/msg/DiagnosticArray", msg.DiagnosticArray, "out", latched=True,
                                 depth=1),
        DIAGNOSTICS: TopicSpec("diagnostic_msgs/msg/DiagnosticArray", msg.DiagnosticArray, "out"),
        ROBOT_DESCRIPTION: TopicSpec("std_msgs/msg/String", msg.String, "out", latched=True, depth=1),
        TF_STATIC: TopicSpec("tf2_msgs/msg/TFMessage", msg.TFMessage, "out", latched=True, depth=1),
        TF: TopicSpec("tf2_msgs/msg/TFMessage", msg.TFMessage, "out", depth=TF_DEPTH),
    }
    if sim_clock:
        out[CLOCK] = TopicSpec("rosgraph_msgs/msg/Clock", msg.Clock, "out", depth=1)
    if control:
        out[config.remote.topic] = TopicSpec("prime_msgs/msg/MitCommand", msg.MitCommand, "in")
        out[MODE_REQUEST] = TopicSpec("std_msgs/msg/String", msg.String, "in")
    return out


@dataclass
class TopicCounts:
    """What went through one topic: samples published (or received), dropped, late, refused, and the QoS
    mismatches seen with other endpoints."""

    ros_type: str
    direction: str
    samples: int = 0
    dropped: int = 0
    late: int = 0
    refused: int = 0
    last_refusal: str = ""
    qos_mismatches: int = 0
    qos_policies: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, object]:
        key = "published" if self.direction == "out" else "received"
        result: dict[str, object] = {"type": self.ros_type, key: self.samples}
        if self.direction == "out":
            result.update(dropped=self.dropped, late=self.late)
        else:
            result.update(refused=self.refused, last_refusal=self.last_refusal)
        result.update(qos_mismatches=self.qos_mismatches)
        return result


def diagnostics(status: SafetyStatus, sources: Sequence[str], epoch_offset: float,
                notes: dict[str, str] | None = None,
                configuration: Mapping[str, Mapping[str, object]] | None = None) -> msg.DiagnosticArray:
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
        values = [msg.KeyValue(key=f"{kind}{suffix}", value=str(entry.get(field_name, "")))
                  for kind, entry in configuration.items()
                  for suffix, field_name in (("", "path"), ("_sha256", "sha256"))]
        statuses.append(msg.DiagnosticStatus(
            level=msg.DiagnosticStatus.OK, name="prime/configuration", hardware_id=HARDWARE_ID,
            message="; ".join(f"{kind} {entry.get('path')}" for kind, entry in configuration.items()), values=values))
    return msg.DiagnosticArray(header=msg.Header(stamp=msg.stamp(status.stamp + epoch_offset)), status=statuses)


def static_transforms(frames: Frames) -> msg.TFMessage:
    """The fixed joints (stamp 0: tf2 holds a static transform for all times)."""
    return msg.TFMessage(transforms=[
        msg.TransformStamped(header=msg.Header(frame_id=parent), child_frame_id=child,
                             transform=msg.Transform(msg.Vector3(*map(float, t)), msg.Quaternion(*map(float, r))))
        for parent, child, t, r in zip(frames.static_parents, frames.static_children, frames.static_translations,
                                       frames.static_rotations, strict=True)])


class GraphBridge(SafetyFlags):
    """The node's side of the loop (module docstring); a flag source of its own (``dds``): dropped joint states,
    refused mode requests, QoS mismatches, transport errors.

    ``epoch_offset`` turns the loop clock into message stamps: ``time.time() - time.monotonic()`` for a run on
    the robot (stamps in the system clock, as ROS 2 nodes use), 0 in simulation (stamps in simulated time, as
    ROS 2 does with ``use_sim_time``, and then ``sim_clock`` publishes that time on ``/clock``).
    ``request_mode`` is the run's mode request path; with ``control`` False nothing is read from the graph.
    ``report`` takes the node's log lines (the first QoS mismatch of each topic, say).
    """

    backend = ""

    def __init__(self, manager: ControllerManager, *, request_mode: Callable[[str], object] | None,
                 control: bool, epoch_offset: float, sim_clock: bool, clock: Callable[[], float] = time.perf_counter,
                 report: Report | None = None) -> None:
        super().__init__("dds")
        self.manager = manager
        self.topics = manager.topics
        self.names = list(manager.robot.names)
        self.period = manager.period
        self.request_mode = request_mode
        self.control = control
        self.sim_clock = sim_clock
        self.sources = [*manager.flag_source_names, self.name]
        self.notes = {self.name: CONTROL_ON if control else CONTROL_OFF}
        self.epoch_offset = epoch_offset
        self.joint_states_topic = manager.config.joint_states_topic
        self.remote_topic = manager.config.remote.topic
        self.clock = clock
        self.report = report
        self.frames = frames_from_urdf(manager.robot.description.urdf, manager.robot.names)
        self.specs = topics(manager, sim_clock=sim_clock, control=control)
        self.counts = {topic: TopicCounts(spec.ros_type, spec.direction) for topic, spec in self.specs.items()}
        self._latency = np.full(LATENCY_WINDOW, np.nan)
        self._latencies = 0
        self._last_diagnostics: msg.DiagnosticArray | None = None
        self._diagnostics_due = -np.inf
        self._tf_packer = TfPacker(self.frames.parents, self.frames.children)
        self._mismatch_lock = threading.Lock()

    def write(self, topic: str, message: IdlStruct) -> None:
        """Put ``message`` on ``topic``: the backend's transport (``send`` counts and flags around it)."""
        raise NotImplementedError

    def publish_static(self) -> None:
        """The latched topics that never change: the robot description and the fixed joints."""
        self.send(ROBOT_DESCRIPTION, msg.String(data=self.manager.robot.description.urdf))
        self.send(TF_STATIC, static_transforms(self.frames))

    def send(self, topic: str, message: IdlStruct) -> None:
        """Write ``message`` on ``topic`` and count it (a topic the backend left out is skipped); a transport
        error is flagged, then raised."""
        counts = self.counts.get(topic)
        if counts is None:
            return
        try:
            self.write(topic, message)
        except Exception as exc:  # a transport error is a flag, never the end of publishing
            self.set_flag("publish", f"write on {topic} failed: {type(exc).__name__}: {exc}", Level.WARN)
            raise
        counts.samples += 1

    # ---- the publisher thread (a TickTap's consumer) ---------------------------------------------

    def on_tick(self, sample: TickSample) -> None:
        data = sample.data
        stamp = msg.stamp(sample.stamp + self.epoch_offset)
        if self.sim_clock:  # first: a use_sim_time node's clock is never behind the stamps it gets
            self.send(CLOCK, msg.Clock(clock=stamp))
        self.send(self.joint_states_topic, msg.JointState(
            header=msg.Header(stamp=stamp), name=self.names,
            position=data[0].tolist(), velocity=data[1].tolist(), effort=data[2].tolist()))
        self.send(TF, self._transforms(data[0], stamp))
        if sample.stamp >= self._diagnostics_due and self._last_diagnostics is not None:
            self._publish_diagnostics(self._last_diagnostics, sample.stamp)
        latency = self.clock() - sample.queued_at
        self._latency[self._latencies % LATENCY_WINDOW] = latency
        self._latencies += 1
        if latency > self.period:
            self.counts[self.joint_states_topic].late += 1

    def _transforms(self, positions: npt.NDArray[np.float64], stamp: msg.Time) -> msg.TFMessage:
        return self._tf_packer.fill(*self.frames.transforms(positions), stamp)

    def on_mode(self, message: ControlMode) -> None:
        self.send(CONTROL_MODE, msg.String(data=message.mode))

    def on_safety(self, message: SafetyStatus) -> None:
        array = diagnostics(message, self.sources, self.epoch_offset, self.notes, self.manager.configuration)
        self.send(SAFETY_STATUS, array)
        self._publish_diagnostics(array, message.stamp)

    def _publish_diagnostics(self, array: msg.DiagnosticArray, now: float) -> None:
        self._last_diagnostics = array
        self._diagnostics_due = now + DIAGNOSTICS_PERIOD_S
        array.header.stamp = msg.stamp(now + self.epoch_offset)
        self.send(DIAGNOSTICS, array)

    def on_remote(self, message: MitCommandMessage) -> None:  # the bridge takes no remote tap
        """Not used: the bridge is the source of remote commands, not their consumer."""

    def on_drop(self, dropped: int) -> None:
        self.counts[self.joint_states_topic].dropped = dropped
        self.set_flag("dropped", f"{dropped} joint states dropped: the ROS 2 publisher fell behind the loop",
                      Level.WARN)

    # ---- what comes from the graph ---------------------------------------------------------------

    def on_command(self, sample: msg.MitCommand) -> None:
        """A MitCommand from the graph: into the stack on the REMOTE topic, where REMOTE checks it."""
        self.counts[self.remote_topic].samples += 1
        self.topics.publish(self.remote_topic, MitCommandMessage(
            joint_names=tuple(sample.name), position=np.asarray(sample.position, dtype=np.float64),
            velocity=np.asarray(sample.velocity, dtype=np.float64), effort=np.asarray(sample.effort, dtype=np.float64),
            stiffness=np.asarray(sample.stiffness, dtype=np.float64),
            damping=np.asarray(sample.damping, dtype=np.float64), stamp=msg.seconds(sample.header.stamp)))

    def on_mode_request(self, sample: msg.String) -> None:
        """A mode name from the graph: the same path, with the same refusals, as ``prime switch``."""
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

    def qos_mismatch(self, topic: str, policy: str, peer: str) -> None:
        """Another endpoint on ``topic`` cannot match Prime's (``policy`` differs; ``peer`` says which kind of
        endpoint it is): counted, flagged on /safety_status while the run lasts, logged once per topic."""
        counts = self.counts[topic]
        with self._mismatch_lock:
            counts.qos_mismatches += 1
            first = counts.qos_mismatches == 1
            if policy not in counts.qos_policies:
                counts.qos_policies.append(policy)
        spec = self.specs[topic]
        ours = f"reliable, {'transient-local' if spec.latched else 'volatile'}, keep-last {spec.depth}"
        text = (f"QoS mismatch on {topic}: a {peer} with an incompatible {'/'.join(counts.qos_policies)} cannot "
                f"match Prime's ({ours}); {counts.qos_mismatches} seen")
        self.set_flag(f"qos{topic}", text, Level.WARN)
        if first and self.report is not None:
            self.report(text, Level.WARN)

    # ---- the run's end ---------------------------------------------------------------------------

    def summary(self) -> dict[str, object]:
        topics_seen = {topic: counts.as_dict() for topic, counts in self.counts.items()}
        remote = self.manager.controllers.get(Mode.REMOTE.controller)
        if isinstance(remote, RemotePolicyController) and self.control:  # every refusal from the graph is REMOTE's
            topics_seen[self.remote_topic].update(refused=remote.rejected, last_refusal=remote.last_rejection)
        latency = self._latency[np.isfinite(self._latency)] * 1e6
        return {
            "backend": self.backend,
            "control": self.control,
            "topics": topics_seen,
            "qos_mismatches": sum(counts.qos_mismatches for counts in self.counts.values()),
            "tick_to_written_us": {
                "median": float(np.median(latency)) if latency.size else None,
                "p99": float(np.percentile(latency, 99)) if latency.size else None,
            },
        }
