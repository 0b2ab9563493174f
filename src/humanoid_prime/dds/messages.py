"""The ROS 2 messages Prime speaks on DDS, as Cyclone DDS types with ROS 2's DDS type names.

Each class is the field list of its ROS 2 definition, in order, with ROS 2's IDL mapping (``string[]`` ->
``sequence<string>``, ``float64`` -> ``double``, msg ``byte`` -> ``octet``). Every type is final (the default),
so it serialises as XCDR1 exactly like both ROS 2 middlewares; the tests compare the bytes with ROS 2's own
definitions (Humble and Jazzy) and ``MitCommand`` with ``prime_msgs/msg/MitCommand.msg``, field by field.

``GRAPH_TYPES`` are the graph information rmw implementations share (``rmw_dds_common``, Iron and later: a GID
is 16 bytes; Humble's were 24, so a Humble node lists Prime's topics but not the node ``prime``).
"""

# No `from __future__ import annotations`: Cyclone DDS resolves these field annotations at run time.

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import byte, float64, int32, uint8, uint32

GID_BYTES = 16  # RMW_GID_STORAGE_SIZE since Iron
NAME_BYTES = 256  # rmw_dds_common's bounded node names and namespaces

if TYPE_CHECKING:  # Cyclone's IDL annotations are type constructors run at import; the checker reads them so
    from builtins import list as sequence

    GidBytes = list[int]
    Name = str
else:
    from cyclonedds.idl.types import array, bounded_str, sequence

    GidBytes = array[uint8, GID_BYTES]
    Name = bounded_str[NAME_BYTES]


def dds_type_name(ros_type: str) -> str:
    """``sensor_msgs/msg/JointState`` -> ``sensor_msgs::msg::dds_::JointState_`` (both ROS 2 middlewares)."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


@dataclass
class Time(IdlStruct, typename=dds_type_name("builtin_interfaces/msg/Time")):
    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Header(IdlStruct, typename=dds_type_name("std_msgs/msg/Header")):
    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class String(IdlStruct, typename=dds_type_name("std_msgs/msg/String")):
    data: str = ""


@dataclass
class JointState(IdlStruct, typename=dds_type_name("sensor_msgs/msg/JointState")):
    header: Header = field(default_factory=Header)
    name: sequence[str] = field(default_factory=list)
    position: sequence[float64] = field(default_factory=list)
    velocity: sequence[float64] = field(default_factory=list)
    effort: sequence[float64] = field(default_factory=list)


@dataclass
class KeyValue(IdlStruct, typename=dds_type_name("diagnostic_msgs/msg/KeyValue")):
    key: str = ""
    value: str = ""


@dataclass
class DiagnosticStatus(IdlStruct, typename=dds_type_name("diagnostic_msgs/msg/DiagnosticStatus")):
    OK = 0  # the level constants of diagnostic_msgs/DiagnosticStatus
    WARN = 1
    ERROR = 2
    STALE = 3

    level: byte = 0
    name: str = ""
    message: str = ""
    hardware_id: str = ""
    values: sequence[KeyValue] = field(default_factory=list)


LEVEL_NAMES = {DiagnosticStatus.OK: "OK", DiagnosticStatus.WARN: "WARN", DiagnosticStatus.ERROR: "ERROR",
               DiagnosticStatus.STALE: "STALE"}


@dataclass
class DiagnosticArray(IdlStruct, typename=dds_type_name("diagnostic_msgs/msg/DiagnosticArray")):
    header: Header = field(default_factory=Header)
    status: sequence[DiagnosticStatus] = field(default_factory=list)


@dataclass
class MitCommand(IdlStruct, typename=dds_type_name("prime_msgs/msg/MitCommand")):
    """prime_msgs/msg/MitCommand (``prime_msgs/msg/MitCommand.msg`` in the repository)."""

    header: Header = field(default_factory=Header)
    name: sequence[str] = field(default_factory=list)
    position: sequence[float64] = field(default_factory=list)
    velocity: sequence[float64] = field(default_factory=list)
    effort: sequence[float64] = field(default_factory=list)
    stiffness: sequence[float64] = field(default_factory=list)
    damping: sequence[float64] = field(default_factory=list)


@dataclass
class Clock(IdlStruct, typename=dds_type_name("rosgraph_msgs/msg/Clock")):
    clock: Time = field(default_factory=Time)


@dataclass
class Vector3(IdlStruct, typename=dds_type_name("geometry_msgs/msg/Vector3")):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Quaternion(IdlStruct, typename=dds_type_name("geometry_msgs/msg/Quaternion")):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0
    w: float64 = 1.0


@dataclass
class Transform(IdlStruct, typename=dds_type_name("geometry_msgs/msg/Transform")):
    translation: Vector3 = field(default_factory=Vector3)
    rotation: Quaternion = field(default_factory=Quaternion)


@dataclass
class TransformStamped(IdlStruct, typename=dds_type_name("geometry_msgs/msg/TransformStamped")):
    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    transform: Transform = field(default_factory=Transform)


@dataclass
class TFMessage(IdlStruct, typename=dds_type_name("tf2_msgs/msg/TFMessage")):
    transforms: sequence[TransformStamped] = field(default_factory=list)


# Every type above with its ROS 2 name (the byte-compatibility tests walk this table).
ROS_TYPES: dict[str, type[IdlStruct]] = {
    "builtin_interfaces/msg/Time": Time,
    "std_msgs/msg/Header": Header,
    "std_msgs/msg/String": String,
    "sensor_msgs/msg/JointState": JointState,
    "diagnostic_msgs/msg/KeyValue": KeyValue,
    "diagnostic_msgs/msg/DiagnosticStatus": DiagnosticStatus,
    "diagnostic_msgs/msg/DiagnosticArray": DiagnosticArray,
    "prime_msgs/msg/MitCommand": MitCommand,
    "rosgraph_msgs/msg/Clock": Clock,
    "geometry_msgs/msg/Vector3": Vector3,
    "geometry_msgs/msg/Quaternion": Quaternion,
    "geometry_msgs/msg/Transform": Transform,
    "geometry_msgs/msg/TransformStamped": TransformStamped,
    "tf2_msgs/msg/TFMessage": TFMessage,
}


@dataclass
class Gid(IdlStruct, typename=dds_type_name("rmw_dds_common/msg/Gid")):
    data: GidBytes = field(default_factory=lambda: [0] * GID_BYTES)


@dataclass
class NodeEntitiesInfo(IdlStruct, typename=dds_type_name("rmw_dds_common/msg/NodeEntitiesInfo")):
    node_namespace: Name = ""
    node_name: Name = ""
    reader_gid_seq: sequence[Gid] = field(default_factory=list)
    writer_gid_seq: sequence[Gid] = field(default_factory=list)


@dataclass
class ParticipantEntitiesInfo(IdlStruct, typename=dds_type_name("rmw_dds_common/msg/ParticipantEntitiesInfo")):
    gid: Gid = field(default_factory=Gid)
    node_entities_info_seq: sequence[NodeEntitiesInfo] = field(default_factory=list)


GRAPH_TYPES: dict[str, type[IdlStruct]] = {
    "rmw_dds_common/msg/Gid": Gid,
    "rmw_dds_common/msg/NodeEntitiesInfo": NodeEntitiesInfo,
    "rmw_dds_common/msg/ParticipantEntitiesInfo": ParticipantEntitiesInfo,
}


def stamp(seconds: float) -> Time:
    """A ROS 2 Time from seconds (nanoseconds rounded, never 10**9)."""
    total = round(seconds * 1e9)
    return Time(sec=total // 1_000_000_000, nanosec=total % 1_000_000_000)


def seconds(time: Time) -> float:
    return time.sec + time.nanosec * 1e-9
