"""Prime's topics on the ROS 2 graph: the in-process topics of a running controller manager, published and
subscribed over DDS with ROS 2's types, names and QoS.

Out: ``/prime/joint_states`` (sensor_msgs/JointState, every tick, canonical order), ``/control_mode``
(std_msgs/String, latched, on change) and ``/safety_status`` (diagnostic_msgs/DiagnosticArray, latched, on
change: one status per flag source, one key/value per flag). In: the REMOTE controller's MIT command
(prime_msgs/MitCommand) and ``/prime/mode_request`` (std_msgs/String), which takes the same path, with the same
refusals, as ``prime switch``.

The control tick never waits on DDS: the tick thread copies a joint state into a slot of a fixed ring and,
at the end of the tick (after ``write()``), hands what the tick produced to the publisher thread, which
converts and writes while the loop waits for its next period. When the ring is full (the
publisher, the transport or a reader fell behind) the sample is dropped, counted and flagged; the tick goes on.
Incoming samples are read on their own thread and enter the stack through the same paths as in-process ones.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from cyclonedds.core import GuardCondition, InstanceState, ReadCondition, SampleState, ViewState, WaitSet
from cyclonedds.internal import InvalidSample
from cyclonedds.util import duration

from humanoid_prime.config.robot import Robot
from humanoid_prime.control.flags import Level, SafetyFlags
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.topics import (
    CONTROL_MODE,
    JOINT_STATES,
    REMOTE_COMMAND,
    SAFETY_STATUS,
    ControlMode,
    SafetyStatus,
    TopicBus,
)
from humanoid_prime.control.topics import JointState as JointStateMessage
from humanoid_prime.control.topics import MitCommand as MitCommandMessage
from humanoid_prime.dds import messages as msg
from humanoid_prime.dds.node import DdsNode
from humanoid_prime.modes import Mode

MODE_REQUEST = "/prime/mode_request"
RING_SLOTS = 64  # joint states in flight to the publisher thread before one is dropped
LATENCY_WINDOW = 4096  # recent tick-to-written latencies kept for the summary
HARDWARE_ID = "prime"
READ_BATCH = 32


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


def diagnostics(status: SafetyStatus, sources: Sequence[str], epoch_offset: float) -> msg.DiagnosticArray:
    """One DiagnosticStatus per flag source (``prime/<source>``), OK when it has no flag, else its worst level,
    the flags' texts as the message and each flag as a key/value."""
    grouped: dict[str, list[tuple[str, str, Level]]] = {source: [] for source in sources}
    for key, text in status.flags.items():
        source, _, rest = key.partition("/")
        grouped.setdefault(source, []).append((rest or source, text, status.levels.get(key, Level.ERROR)))
    statuses = []
    for source, flags in grouped.items():
        level = max((int(level) for _, _, level in flags), default=msg.DiagnosticStatus.OK)
        statuses.append(msg.DiagnosticStatus(
            level=level, name=f"prime/{source}", message="; ".join(text for _, text, _ in flags) or "ok",
            hardware_id=HARDWARE_ID, values=[msg.KeyValue(key=key, value=text) for key, text, _ in flags]))
    return msg.DiagnosticArray(header=msg.Header(stamp=msg.stamp(status.stamp + epoch_offset)), status=statuses)


class DdsBridge(SafetyFlags):
    """Bridges a controller manager's topics to DDS (module docstring). A flag source of its own (``dds``):
    dropped joint states, refused mode requests.

    ``epoch_offset`` turns the loop clock into message stamps: ``time.time() - time.monotonic()`` for a run on
    the robot (stamps in the system clock, as ROS 2 nodes use), 0 in simulation (stamps in simulated time, as
    ROS 2 does with ``use_sim_time``). ``request_mode`` is the run's mode request path (None: refuse).
    """

    def __init__(self, node: DdsNode, topics: TopicBus, robot: Robot, *, period: float,
                 request_mode: Callable[[str], None] | None, sources: Sequence[str] = (),
                 epoch_offset: float = 0.0, joint_states_topic: str = JOINT_STATES,
                 remote_topic: str = REMOTE_COMMAND, remote_refusals: Callable[[], tuple[int, str]] | None = None,
                 slots: int = RING_SLOTS, clock: Callable[[], float] = time.perf_counter) -> None:
        super().__init__("dds")
        self.node = node
        self.topics = topics
        self.names = list(robot.names)
        self.period = period
        self.request_mode = request_mode
        self.sources = [*sources, self.name]
        self.epoch_offset = epoch_offset
        self.joint_states_topic = joint_states_topic
        self.remote_topic = remote_topic
        self.remote_refusals = remote_refusals
        self.clock = clock
        self.counts = {
            joint_states_topic: TopicCounts("sensor_msgs/msg/JointState", "out"),
            CONTROL_MODE: TopicCounts("std_msgs/msg/String", "out"),
            SAFETY_STATUS: TopicCounts("diagnostic_msgs/msg/DiagnosticArray", "out"),
            remote_topic: TopicCounts("prime_msgs/msg/MitCommand", "in"),
            MODE_REQUEST: TopicCounts("std_msgs/msg/String", "in"),
        }
        n = robot.n
        self._slots = slots
        self._ring = np.zeros((slots, 3, n))
        self._stamps = np.zeros(slots)
        self._queued_at = np.zeros(slots)
        self._head = 0  # written by the tick thread only
        self._tail = 0  # written by the publisher thread only
        self._latency = np.full(LATENCY_WINDOW, np.nan)
        self._latencies = 0
        self._work: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._pending: list[Any] = []  # produced by the current tick, handed over at its end
        self._stop = threading.Event()

        self._joint_states = node.writer(joint_states_topic, msg.JointState)
        self._mode = node.writer(CONTROL_MODE, msg.String, latched=True, depth=1)
        self._safety = node.writer(SAFETY_STATUS, msg.DiagnosticArray, latched=True, depth=1)
        self._commands = node.reader(remote_topic, msg.MitCommand)
        self._mode_requests = node.reader(MODE_REQUEST, msg.String)
        self._guard = GuardCondition(node.participant)
        self._waitset = WaitSet(node.participant)
        mask = SampleState.NotRead | ViewState.Any | InstanceState.Any
        self._conditions = {id(reader): ReadCondition(reader, mask)
                            for reader in (self._commands, self._mode_requests)}
        for condition in self._conditions.values():
            self._waitset.attach(condition)
        self._waitset.attach(self._guard)

        self._publisher = threading.Thread(target=self._publish_loop, name="dds-publish", daemon=True)
        self._reader = threading.Thread(target=self._read_loop, name="dds-read", daemon=True)
        self._publisher.start()
        self._reader.start()
        self.detach: Callable[[], None] | None = None  # undoes bridge_manager's attachment
        topics.subscribe(joint_states_topic, self._on_joint_states)
        topics.subscribe(CONTROL_MODE, self._on_control_mode, latched=True)
        topics.subscribe(SAFETY_STATUS, self._on_safety, latched=True)
        self._closed = False

    # ---- the tick thread: copy and hand over, never wait ----------------------------------------

    def _on_joint_states(self, message: JointStateMessage) -> None:
        head = self._head
        if head - self._tail >= self._slots:
            counts = self.counts[self.joint_states_topic]
            counts.dropped += 1
            self.set_flag("dropped", f"{counts.dropped} joint states dropped: the DDS publisher fell behind the "
                                     "loop", Level.WARN)
            return
        k = head % self._slots
        row = self._ring[k]
        row[0] = message.position
        row[1] = message.velocity
        row[2] = message.effort
        self._stamps[k] = message.stamp
        self._queued_at[k] = self.clock()
        self._head = head + 1
        self._pending.append(k)

    def _on_control_mode(self, message: ControlMode) -> None:
        self._pending.append(message)

    def _on_safety(self, message: SafetyStatus) -> None:
        self._pending.append(message)

    def end_of_tick(self) -> None:
        """Hand this tick's samples to the publisher thread (the manager calls it after ``write()``)."""
        pending = self._pending
        if pending:
            self._pending = []
            for item in pending:
                self._work.put(item)

    # ---- the publisher thread --------------------------------------------------------------------

    def _publish_loop(self) -> None:
        while True:
            item = self._work.get()
            if item is None:
                return
            try:
                self._publish(item)
            except Exception as exc:  # a transport error is a flag, never the end of publishing
                self.set_flag("publish", f"DDS write failed: {type(exc).__name__}: {exc}", Level.WARN)

    def _publish(self, item: Any) -> None:
        if isinstance(item, int):
            row = self._ring[item]
            sample = msg.JointState(
                header=msg.Header(stamp=msg.stamp(float(self._stamps[item]) + self.epoch_offset)), name=self.names,
                position=row[0].tolist(), velocity=row[1].tolist(), effort=row[2].tolist())
            queued_at = float(self._queued_at[item])
            self._tail += 1  # the slot is free again once its values are out
            self._joint_states.write(sample)
            latency = self.clock() - queued_at
            self._latency[self._latencies % LATENCY_WINDOW] = latency
            self._latencies += 1
            counts = self.counts[self.joint_states_topic]
            counts.samples += 1
            if latency > self.period:
                counts.late += 1
        elif isinstance(item, ControlMode):
            self._mode.write(msg.String(data=item.mode))
            self.counts[CONTROL_MODE].samples += 1
        elif isinstance(item, SafetyStatus):
            self._safety.write(diagnostics(item, self.sources, self.epoch_offset))
            self.counts[SAFETY_STATUS].samples += 1

    # ---- the reader thread -----------------------------------------------------------------------

    def _read_loop(self) -> None:
        while not self._stop.is_set():
            self._waitset.wait(duration(seconds=1))
            if self._stop.is_set():
                return
            try:
                for sample in self._take(self._commands):
                    self._on_command(sample)
                for sample in self._take(self._mode_requests):
                    self._on_mode_request(sample)
            except Exception as exc:
                self.set_flag("read", f"DDS read failed: {type(exc).__name__}: {exc}", Level.WARN)

    def _take(self, reader: Any) -> list[Any]:
        condition = self._conditions[id(reader)]
        return [s for s in reader.take(N=READ_BATCH, condition=condition) if not isinstance(s, InvalidSample)]

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
        if self.remote_refusals is not None:
            refused, reason = self.remote_refusals()
            topics[self.remote_topic].update(refused=refused, last_refusal=reason)
        latency = self._latency[np.isfinite(self._latency)] * 1e6
        return {
            "domain": self.node.domain,
            "topics": topics,
            "tick_to_written_us": {
                "median": float(np.median(latency)) if latency.size else None,
                "p99": float(np.percentile(latency, 99)) if latency.size else None,
            },
        }

    def close(self, timeout: float = 5.0) -> None:
        """Stop both threads (what is queued is written first), then leave the DDS domain."""
        if self._closed:
            return
        self._closed = True
        self.topics.unsubscribe(self.joint_states_topic, self._on_joint_states)
        self.topics.unsubscribe(CONTROL_MODE, self._on_control_mode)
        self.topics.unsubscribe(SAFETY_STATUS, self._on_safety)
        if self.detach is not None:
            self.detach()
        self.end_of_tick()  # what the last tick produced is still written
        self._work.put(None)
        self._stop.set()
        self._guard.set(True)
        self._publisher.join(timeout)
        self._reader.join(timeout)
        self.node.close()


def bridge_manager(manager: ControllerManager, *, domain: int | None = None,
                   request_mode: Callable[[str], None] | None = None, epoch_offset: float = 0.0) -> DdsBridge:
    """Put ``manager``'s topics on DDS (domain ``domain``, else ``ROS_DOMAIN_ID``); its flags join
    /safety_status. ``request_mode`` defaults to the manager's own (which refuses in a broadcaster-only run)."""
    remote = manager.controllers[Mode.REMOTE.controller]
    node = DdsNode(domain)
    try:
        bridge = DdsBridge(
            node, manager.topics, manager.robot, period=manager.period,
            request_mode=request_mode or manager.request_mode, sources=manager.flag_source_names,
            epoch_offset=epoch_offset, joint_states_topic=manager.config.joint_states_topic,
            remote_topic=manager.config.remote.topic,
            remote_refusals=lambda: (remote.rejected, remote.last_rejection))
    except BaseException:
        node.close()
        raise
    manager.add_flag_source(bridge)
    manager.add_end_of_tick(bridge.end_of_tick)
    bridge.detach = lambda: manager.remove_end_of_tick(bridge.end_of_tick)
    bridge.end_of_tick()  # the latched mode and status it was given on subscribing
    return bridge
