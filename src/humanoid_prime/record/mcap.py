"""``--record FILE.mcap``: every topic of a run as ROS 2 messages in one MCAP file that ``ros2 bag play``,
Foxglove, rosbags and rerun open.

The file has the ``ros2`` profile, one ``ros2msg`` schema per type (ROS 2's own definitions, from rosbags' type
store; ``prime_msgs/MitCommand`` from our interface package), CDR messages (the bytes ROS 2 puts on the wire),
zstd-compressed chunks, and per channel the ``offered_qos_profiles`` metadata rosbag2 reads (integer form,
which Humble and Jazzy both parse). Topics: ``/prime/joint_states``, ``/prime/command`` (the MIT command
written to the hardware) and ``/tf`` every tick (``/clock`` too in simulation), ``/robot_description`` and
``/tf_static`` once, ``/control_mode`` and ``/safety_status`` on change (latched QoS), ``/diagnostics`` as the
graph has it (on change and every second), and the remote command as it arrives, when there is one: what
Foxglove's 3D panel and ``ros2 bag play`` need to show the robot. ``topics`` keeps a recording to some of them.

Nothing here runs on the control thread: a ``TickTap`` hands each tick to the recorder's thread, which
serialises, compresses and writes. The file is finished (summary, index, footer) on every way out of the run;
one killed with SIGKILL still reads to its last complete chunk with a streaming reader.
"""

from __future__ import annotations

from pathlib import Path
from typing import IO, Any

from mcap.writer import CompressionType, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from humanoid_prime import __version__
from humanoid_prime.control.flags import Level, SafetyFlags
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.tap import TickSample, TickTap
from humanoid_prime.control.topics import CONTROL_MODE, SAFETY_STATUS, ControlMode, MitCommand, SafetyStatus
from humanoid_prime.dds import messages as msg
from humanoid_prime.dds.graph import (
    CLOCK,
    DIAGNOSTICS,
    DIAGNOSTICS_PERIOD_S,
    ROBOT_DESCRIPTION,
    TF,
    TF_STATIC,
    diagnostics,
    static_transforms,
)
from humanoid_prime.dds.tf import frames_from_urdf
from humanoid_prime.dds.tfmessage import TfPacker
from humanoid_prime.errors import PrimeError
from humanoid_prime.files import bundled
from humanoid_prime.record.topics import COMMAND as COMMAND_TOPIC
from humanoid_prime.record.topics import JOINT_STATES, REMOTE, TOPICS

CHUNK_BYTES = 256 * 1024  # what a killed recorder can lose, at most (about 1 s of ticks at 1 kHz)

# rosbag2's QoS of a recorded topic, integer form (history 1 keep-last, reliability 1 reliable, durability
# 1 transient-local / 2 volatile, liveliness 1 automatic; zero durations: the defaults).
_QOS = """- history: 1
  depth: {depth}
  reliability: 1
  durability: {durability}
  deadline:
    sec: 0
    nsec: 0
  lifespan:
    sec: 0
    nsec: 0
  liveliness: 1
  liveliness_lease_duration:
    sec: 0
    nsec: 0
  avoid_ros_namespace_conventions: false
"""
VOLATILE_QOS = _QOS.format(depth=10, durability=2)
LATCHED_QOS = _QOS.format(depth=1, durability=1)
TF_QOS = _QOS.format(depth=100, durability=2)
CLOCK_QOS = _QOS.format(depth=1, durability=2)


def type_store() -> Any:
    """ROS 2's message definitions (Jazzy; these types are identical in Humble) plus ``prime_msgs``."""
    store = get_typestore(Stores.ROS2_JAZZY)
    for path in sorted(bundled("prime_msgs").glob("*.msg")):
        store.register(get_types_from_msg(path.read_text(), f"prime_msgs/msg/{path.stem}"))
    return store


class Recorder(SafetyFlags):
    """Records ``manager``'s run to ``path`` (see the module docstring); a flag source (``record``) when a
    write fails. ``close`` finishes the file; ``summary`` says what went in."""

    def __init__(self, path: str | Path, manager: ControllerManager, *, epoch_offset: float = 0.0,
                 wait: bool = False, sim_clock: bool = False, topics: tuple[str, ...] | None = None) -> None:
        super().__init__("record")
        self.path = Path(path)
        self.wait = wait  # the loop waits for the writer rather than drop a tick (no real-time deadline)
        self.names = list(manager.robot.names)
        self.epoch_offset = epoch_offset
        self.counts: dict[str, int] = {}
        self.dropped = 0
        self.errors = 0
        self.last_error = ""
        self._store = type_store()
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file: IO[bytes] = open(self.path, "wb")  # noqa: SIM115 -- closed by close()
        except OSError as exc:
            raise PrimeError(f"cannot record to {self.path}: {exc.strerror}") from None
        self._writer = Writer(self._file, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        self._writer.start(profile="ros2", library=f"humanoid-prime {__version__}")
        self.joint_states_topic = manager.config.joint_states_topic
        self.remote_topic = manager.config.remote.topic
        # The topics asked for (the configured joint-state and remote topics stand for their defaults' names).
        chosen = set(TOPICS if topics is None else topics)
        self.sim_clock = sim_clock
        self.wanted = {topic for topic, default in ((self.joint_states_topic, JOINT_STATES),
                                                    (self.remote_topic, REMOTE)) if default in chosen}
        self.wanted |= chosen - {JOINT_STATES, REMOTE} - (set() if sim_clock else {CLOCK})
        for topic, ros_type, qos in (
                (self.joint_states_topic, "sensor_msgs/msg/JointState", VOLATILE_QOS),
                (COMMAND_TOPIC, "prime_msgs/msg/MitCommand", VOLATILE_QOS),
                (CONTROL_MODE, "std_msgs/msg/String", LATCHED_QOS),
                (SAFETY_STATUS, "diagnostic_msgs/msg/DiagnosticArray", LATCHED_QOS),
                (DIAGNOSTICS, "diagnostic_msgs/msg/DiagnosticArray", VOLATILE_QOS),
                (ROBOT_DESCRIPTION, "std_msgs/msg/String", LATCHED_QOS),
                (TF_STATIC, "tf2_msgs/msg/TFMessage", LATCHED_QOS),
                (TF, "tf2_msgs/msg/TFMessage", TF_QOS),
                (CLOCK, "rosgraph_msgs/msg/Clock", CLOCK_QOS)):
            if topic in self.wanted:
                self._channel(topic, ros_type, qos)
        self.frames = frames_from_urdf(manager.robot.description.urdf, manager.robot.names)
        self._tf = TfPacker(self.frames.parents, self.frames.children)
        self._diagnostics_due = -1e300
        self._last_diagnostics: msg.DiagnosticArray | None = None
        self.configuration = manager.configuration
        for kind, entry in self.configuration.items():  # which files the run used, read back by `prime plot`
            self._writer.add_metadata(f"prime_{kind}", {key: str(value) for key, value in entry.items()})
        self._last_stamp = 0.0  # the loop time of the latest tick recorded (the log time of what arrives between)
        begun = self._log_ns(manager.clock())
        self._add(ROBOT_DESCRIPTION, msg.String(data=manager.robot.description.urdf), begun)
        self._add(TF_STATIC, static_transforms(self.frames), begun)
        self._closed = False
        self.tap: TickTap | None = None
        self.attach(manager)

    def attach(self, manager: ControllerManager) -> None:
        """Record ``manager``'s ticks from now on (a calibration run attaches each phase's manager in turn)."""
        self.detach()
        self.sources = [*manager.flag_source_names, self.name]
        manager.add_flag_source(self)
        self.tap = TickTap(manager, self, name="recorder", commands=True, remote=True, on_drop=self._on_drop,
                           wait=self.wait)

    def detach(self) -> None:
        """Stop taking ticks; what is queued is recorded first."""
        tap, self.tap = self.tap, None
        if tap is not None:
            tap.close()
            self.dropped += tap.dropped
            self.errors += tap.errors
            self.last_error = tap.last_error or self.last_error

    def _channel(self, topic: str, ros_type: str, qos: str) -> int:
        if topic not in self._channels:
            if ros_type not in self._schemas:
                text, _ = self._store.generate_msgdef(ros_type, ros_version=2)
                self._schemas[ros_type] = self._writer.register_schema(ros_type, "ros2msg", text.encode())
            self._channels[topic] = self._writer.register_channel(
                topic, "cdr", self._schemas[ros_type], metadata={"offered_qos_profiles": qos})
            self.counts[topic] = 0
        return self._channels[topic]

    def _on_drop(self, dropped: int) -> None:
        self.set_flag("dropped", f"{self.dropped + dropped} ticks not recorded: the recorder fell behind the loop",
                      Level.WARN)

    def _add(self, topic: str, sample: Any, log_ns: int) -> None:
        if topic not in self._channels:  # a topic left out (--topics)
            return
        try:
            self._writer.add_message(self._channels[topic], log_time=log_ns, publish_time=log_ns,
                                     data=sample.serialize(), sequence=self.counts[topic])
        except Exception as exc:
            self.set_flag("write", f"recording to {self.path} failed: {type(exc).__name__}: {exc}")
            raise
        self.counts[topic] += 1

    def _log_ns(self, stamp: float) -> int:
        """Log times are the loop clock, like the stamps (simulated time in simulation, else the system clock),
        so every topic of a recording lines up on one time axis."""
        return max(0, round((stamp + self.epoch_offset) * 1e9))

    # ---- the recorder thread (the tap's consumer) ------------------------------------------------

    def on_tick(self, sample: TickSample) -> None:
        data = sample.data
        stamp = msg.stamp(sample.stamp + self.epoch_offset)
        header = msg.Header(stamp=stamp)
        self._last_stamp = sample.stamp
        log_ns = self._log_ns(sample.stamp)
        if self.sim_clock:
            self._add(CLOCK, msg.Clock(clock=stamp), log_ns)
        if TF in self._channels:
            self._add(TF, self._tf.fill(*self.frames.transforms(data[0]), stamp), log_ns)
        if sample.stamp >= self._diagnostics_due and self._last_diagnostics is not None:
            self._add_diagnostics(self._last_diagnostics, sample.stamp)
        self._add(self.joint_states_topic, msg.JointState(
            header=header, name=self.names, position=data[0].tolist(), velocity=data[1].tolist(),
            effort=data[2].tolist()), log_ns)
        self._add(COMMAND_TOPIC, msg.MitCommand(
            header=header, name=self.names, position=data[3].tolist(), velocity=data[4].tolist(),
            effort=data[5].tolist(), stiffness=data[6].tolist(), damping=data[7].tolist()), log_ns)

    def on_mode(self, message: ControlMode) -> None:
        self._add(CONTROL_MODE, msg.String(data=message.mode), self._log_ns(message.stamp))

    def on_safety(self, message: SafetyStatus) -> None:
        array = diagnostics(message, self.sources, self.epoch_offset, configuration=self.configuration)
        self._add(SAFETY_STATUS, array, self._log_ns(message.stamp))
        self._add_diagnostics(array, message.stamp)

    def _add_diagnostics(self, array: msg.DiagnosticArray, stamp: float) -> None:
        """/diagnostics as the graph has it: on change and every second (diagnostic_updater's period)."""
        self._last_diagnostics = array
        self._diagnostics_due = stamp + DIAGNOSTICS_PERIOD_S
        array.header.stamp = msg.stamp(stamp + self.epoch_offset)
        self._add(DIAGNOSTICS, array, self._log_ns(stamp))

    def on_remote(self, message: MitCommand) -> None:
        if self.remote_topic not in self.wanted:
            return
        self._channel(self.remote_topic, "prime_msgs/msg/MitCommand", VOLATILE_QOS)
        self._add(self.remote_topic, msg.MitCommand(
            header=msg.Header(stamp=msg.stamp(message.stamp)), name=list(message.joint_names),
            position=message.position.tolist(), velocity=message.velocity.tolist(), effort=message.effort.tolist(),
            stiffness=message.stiffness.tolist(), damping=message.damping.tolist()), self._log_ns(self._last_stamp))

    # ---- the end ---------------------------------------------------------------------------------

    def close(self) -> None:
        """Record what is queued, then finish the file (summary, index, footer) and close it."""
        if self._closed:
            return
        self._closed = True
        try:
            self.detach()
            self._writer.finish()
        finally:
            self._file.close()

    def summary(self) -> dict[str, Any]:
        return {"file": str(self.path), "messages": dict(self.counts), "dropped_ticks": self.dropped,
                "errors": self.errors, "last_error": self.last_error,
                "bytes": self.path.stat().st_size if self.path.exists() else None}
