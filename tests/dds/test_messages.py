"""Every message Prime puts on DDS serialises to exactly the bytes of ROS 2's own type definitions (the rosbags
type stores of Humble and Jazzy), and prime_msgs/MitCommand to the bytes of the shipped .msg file; the field
lists match the definitions one for one, so the Python types cannot drift from them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cyclonedds.idl._type_normalize import get_extended_type_hints
from cyclonedds.idl.types import sequence
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from humanoid_prime.config.robot import load_robot
from humanoid_prime.control.flags import Level
from humanoid_prime.control.topics import SafetyStatus
from humanoid_prime.dds import messages as msg
from humanoid_prime.dds.graph import diagnostics

PRIME_MSGS = Path(__file__).parents[2] / "prime_msgs"
STORES = {"humble": Stores.ROS2_HUMBLE, "jazzy": Stores.ROS2_JAZZY}


@pytest.fixture(scope="module", params=sorted(STORES))
def store(request):
    typestore = get_typestore(STORES[request.param])
    for path in sorted((PRIME_MSGS / "msg").glob("*.msg")):
        typestore.register(get_types_from_msg(path.read_text(), f"prime_msgs/msg/{path.stem}"))
    return typestore


def _ros(store, ros_type, value):
    """rosbags' message from ours, walking rosbags' own field definitions."""
    kwargs = {name: _convert(store, kind, detail, getattr(value, name))
              for name, (kind, detail) in store.fielddefs[ros_type][1]}
    return store.types[ros_type](**kwargs)


def _convert(store, kind, detail, item):
    if kind.name == "NAME":  # a nested message
        return _ros(store, detail, item)
    if kind.name == "BASE":
        return item
    (inner_kind, inner_detail), _ = detail  # an array or a sequence
    if inner_kind.name == "NAME":
        return [_ros(store, inner_detail, element) for element in item]
    if inner_detail[0] == "string":
        return list(item)
    return np.array(item, dtype=np.dtype(inner_detail[0]))


def _base(annotation) -> str:
    """The ROS 2 base type of one of our field annotations (a nested type: its ROS 2 name)."""
    for ros_type, cls in msg.ROS_TYPES.items():
        if annotation is cls:
            return ros_type
    if annotation is str:
        return "string"
    metadata = getattr(annotation, "__metadata__", ())  # cyclonedds' primitives: Annotated[int, 'int32']
    return metadata[0] if metadata else repr(annotation)


def robot():
    return load_robot(use_sim=True)


def joint_state(n: int = 14, frame: str = "") -> msg.JointState:
    rng = np.random.default_rng(n)
    names = list(robot().names[:n])
    return msg.JointState(header=msg.Header(stamp=msg.stamp(1234.56789), frame_id=frame), name=names,
                          position=rng.normal(size=n).tolist(), velocity=rng.normal(size=n).tolist(),
                          effort=[] if n % 2 else rng.normal(size=n).tolist())


def samples():
    status = SafetyStatus(ok=False, flags={"EthercatSystem/ring0/fault": "0x8500 following error",
                                           "remote_policy_controller/stale": "no command for 100 ms"},
                          levels={"EthercatSystem/ring0/fault": Level.ERROR,
                                  "remote_policy_controller/stale": Level.WARN}, stamp=12.5)
    yield "sensor_msgs/msg/JointState", joint_state()
    yield "sensor_msgs/msg/JointState", joint_state(3, frame="base")
    yield "sensor_msgs/msg/JointState", msg.JointState()
    yield "std_msgs/msg/String", msg.String(data="STANDBY")
    yield "std_msgs/msg/String", msg.String(data="")
    yield "diagnostic_msgs/msg/DiagnosticArray", diagnostics(status, ["EthercatSystem", "controller_manager"], 0.0)
    yield "diagnostic_msgs/msg/DiagnosticArray", msg.DiagnosticArray()
    yield "prime_msgs/msg/MitCommand", msg.MitCommand(
        header=msg.Header(stamp=msg.stamp(7.25), frame_id=""), name=list(robot().names),
        position=[0.1] * 14, velocity=[0.0] * 14, effort=[0.5] * 14, stiffness=[20.0] * 14, damping=[2.0] * 14)
    yield "prime_msgs/msg/MitCommand", msg.MitCommand()


SAMPLES = list(samples())


@pytest.mark.parametrize(("ros_type", "sample"), SAMPLES, ids=[f"{t.split('/')[-1]}-{i}"
                                                               for i, (t, _) in enumerate(SAMPLES)])
def test_each_message_has_the_bytes_of_ros2s_own_definition(store, ros_type, sample):
    ours = sample.serialize()
    theirs = bytes(store.serialize_cdr(_ros(store, ros_type, sample), ros_type))
    assert ours == theirs
    assert ours[:4] == b"\x00\x01\x00\x00"  # XCDR1 (plain CDR), little endian: what both ROS 2 middlewares speak
    assert type(sample).deserialize(theirs) == sample  # and we read ROS 2's bytes back


def test_every_type_has_ros2s_dds_type_name():
    for ros_type, cls in msg.ROS_TYPES.items():
        package, _, name = ros_type.split("/")
        assert cls.__idl_typename__ == f"{package}::msg::dds_::{name}_"


@pytest.mark.parametrize("ros_type", sorted(msg.ROS_TYPES))
def test_field_lists_match_the_definitions(store, ros_type):
    """Same field names, kinds and base types in the same order as ROS 2's definition (MitCommand: the shipped
    .msg file), and the same constants."""
    constants, fields = store.fielddefs[ros_type]
    hints = get_extended_type_hints(msg.ROS_TYPES[ros_type])
    assert list(hints) == [name for name, _ in fields]
    for name, (kind, detail) in fields:
        annotation = hints[name]
        if kind.name == "SEQUENCE":
            assert isinstance(annotation, sequence), name
            (inner_kind, inner_detail), bound = detail
            assert bound == 0 and annotation.max_length is None, name
            want = inner_detail if inner_kind.name == "NAME" else inner_detail[0]
            assert _base(annotation.subtype) == want, name
        elif kind.name == "NAME":
            assert _base(annotation) == detail, name
        else:
            assert _base(annotation) == detail[0], name
    for constant, _, value in constants:
        assert getattr(msg.ROS_TYPES[ros_type], constant) == value


def test_the_shipped_interface_package_is_a_ros2_package():
    package = (PRIME_MSGS / "package.xml").read_text()
    cmake = (PRIME_MSGS / "CMakeLists.txt").read_text()
    assert "<name>prime_msgs</name>" in package and "rosidl_interface_packages" in package
    for path in (PRIME_MSGS / "msg").glob("*.msg"):
        assert f'"msg/{path.name}"' in cmake


def test_stamps_round_trip_in_nanoseconds():
    assert msg.stamp(1.9999999999) == msg.Time(sec=2, nanosec=0)
    assert msg.stamp(-0.5) == msg.Time(sec=-1, nanosec=500_000_000)
    assert msg.seconds(msg.stamp(1234.5678)) == pytest.approx(1234.5678, abs=1e-9)


def test_the_packed_tf_message_has_the_bytes_of_the_built_one():
    """/tf is serialised by filling numbers into bytes laid out once; they are the bytes of the message built
    field by field, for any positions and stamps."""
    from humanoid_prime.dds.tf import frames_from_urdf
    from humanoid_prime.dds.tfmessage import TfPacker

    prime = robot()
    frames = frames_from_urdf(prime.description.urdf, prime.names)
    packer = TfPacker(frames.parents, frames.children)
    rng = np.random.default_rng(7)
    for seconds in (0.0, 12.345, 1.8e9 + 0.5, -3.25):
        translations, rotations = frames.transforms(rng.uniform(prime.lower, prime.upper))
        stamp = msg.stamp(seconds)
        built = msg.TFMessage(transforms=[
            msg.TransformStamped(header=msg.Header(stamp=stamp, frame_id=parent), child_frame_id=child,
                                 transform=msg.Transform(msg.Vector3(*map(float, t)), msg.Quaternion(*map(float, r))))
            for parent, child, t, r in zip(frames.parents, frames.children, translations, rotations, strict=True)])
        assert packer.fill(translations, rotations, stamp).serialize() == built.serialize()
