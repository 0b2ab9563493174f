"""The ROS 2 messages Prime speaks on DDS, as Cyclone DDS types with ROS 2's DDS type names.

Each class is the field list of its ROS 2 definition, in order, with ROS 2's IDL mapping (``string[]`` ->
``sequence<string>``, ``float64`` -> ``double``, msg ``byte`` -> ``octet``). Every type is final (the default),
so it serialises as XCDR1 exactly like both ROS 2 middlewares; the tests compare the bytes with ROS 2's own
definitions (Humble and Jazzy) and ``MitCommand`` with ``prime_msgs/msg/MitCommand.msg``, field by field.
"""

# No `from __future__ import annotations`: Cyclone DDS resolves these field annotations at run time.

from dataclasses import dataclass, field

from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import byte, float64, int32, sequence, uint32


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
}


def stamp(seconds: float) -> Time:
    """A ROS 2 Time from seconds (nanoseconds rounded, never 10**9)."""
    total = round(seconds * 1e9)
    return Time(sec=total // 1_000_000_000, nanosec=total % 1_000_000_000)


def seconds(time: Time) -> float:
    return time.sec + time.nanosec * 1e-9
