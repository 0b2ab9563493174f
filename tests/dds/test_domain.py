"""ROS 2's discovery variables and namespaces, as Prime turns them into Cyclone DDS configuration and names, and
the type hashes Prime announces against the ones rosidl wrote into the ROS 2 wheels."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from humanoid_prime.dds import messages as msg
from humanoid_prime.dds.domain import discovery, in_namespace, node_namespace
from humanoid_prime.dds.typehash import type_hash
from humanoid_prime.errors import PrimeError

from .conftest import ROS_DISTROS

COMPATIBILITY = "<Compatibility><IgnoreTypeInformation>1.15</IgnoreTypeInformation></Compatibility>"


def test_the_default_is_the_subnet_with_multicast_and_any_static_peers():
    xml = discovery({"ROS_STATIC_PEERS": "10.0.0.7; robot.local"}).cyclone_xml()
    assert "AllowMulticast" not in xml and COMPATIBILITY in xml
    assert '<Peers><Peer address="10.0.0.7"/><Peer address="robot.local"/></Peers>' in xml


def test_localhost_turns_multicast_off_and_peers_with_this_machine():
    xml = discovery({"ROS_AUTOMATIC_DISCOVERY_RANGE": "localhost", "ROS_STATIC_PEERS": "10.0.0.7"}).cyclone_xml()
    assert "<AllowMulticast>false</AllowMulticast>" in xml
    assert '<Peers><Peer address="localhost"/><Peer address="10.0.0.7"/></Peers>' in xml


def test_the_deprecated_localhost_only_means_localhost_without_static_peers():
    settings = discovery({"ROS_LOCALHOST_ONLY": "1", "ROS_STATIC_PEERS": "10.0.0.7"})
    assert (settings.range, settings.static_peers) == ("LOCALHOST", ())


def test_off_finds_nobody_and_system_default_leaves_cyclone_alone():
    off = discovery({"ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF", "ROS_STATIC_PEERS": "10.0.0.7"}).cyclone_xml()
    assert "<ParticipantIndex>none</ParticipantIndex>" in off and "<Peer " not in off
    assert "<AllowMulticast>false</AllowMulticast>" in off
    default = discovery({"ROS_AUTOMATIC_DISCOVERY_RANGE": "SYSTEM_DEFAULT"}).cyclone_xml()
    assert "<Discovery>" not in default and "AllowMulticast" not in default and COMPATIBILITY in default


def test_an_unknown_range_is_refused():
    with pytest.raises(PrimeError, match="ROS_AUTOMATIC_DISCOVERY_RANGE='MOON' is not one of"):
        discovery({"ROS_AUTOMATIC_DISCOVERY_RANGE": "MOON"})


@pytest.mark.parametrize(("given", "namespace"), [(None, "/"), ("", "/"), ("/", "/"), ("left", "/left"),
                                                  ("/lab/left/", "/lab/left")])
def test_namespaces_are_written_as_ros2_writes_them(given, namespace):
    assert node_namespace(given) == namespace
    assert in_namespace(namespace, "/prime/joint_states") == namespace.rstrip("/") + "/prime/joint_states"


@pytest.mark.parametrize("bad", ["9left", "le-ft", "a//b"])
def test_a_namespace_that_is_no_ros2_name_is_refused(bad):
    with pytest.raises(PrimeError, match="is not a ROS 2 name"):
        node_namespace(bad)


@pytest.mark.parametrize("distro", ROS_DISTROS)
def test_every_type_hash_is_the_one_rosidl_wrote_into_the_wheels(ros_clients, distro):
    """rosidl writes each type's description and hash next to its definition (share/<pkg>/msg/<Type>.json);
    prime_msgs and tf2_msgs were built there by the same toolchain."""
    prefixes = [Path(p) for p in ros_clients[distro]["AMENT_PREFIX_PATH"].split(":")]
    for ros_type, cls in {**msg.ROS_TYPES, **msg.GRAPH_TYPES}.items():
        package, _, name = ros_type.split("/")
        (path,) = [p / "share" / package / "msg" / f"{name}.json" for p in prefixes
                   if (p / "share" / package / "msg" / f"{name}.json").is_file()]
        hashes = json.loads(path.read_text())["type_hashes"]
        assert type_hash(cls) == hashes[0]["hash_string"], ros_type
