"""The bridge in one process, over real DDS on loopback: what a ROS 2 node on the graph sees and sends. (Real
ROS 2 nodes, rclpy on Jazzy and Kilted, are in test_rclpy.py.)"""

from __future__ import annotations

import threading

import numpy as np
import pytest
from cyclonedds.internal import InvalidSample
from cyclonedds.qos import Policy
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from humanoid_prime.dds import messages as msg
from humanoid_prime.dds.bridge import DdsBridge, bridge_manager
from humanoid_prime.dds.graph import CONTROL_OFF, CONTROL_ON, MODE_REQUEST
from humanoid_prime.dds.node import DISCOVERY_TOPIC, DdsNode, ros_qos
from humanoid_prime.dds.tf import frames_from_urdf
from humanoid_prime.dds.typehash import type_hash
from humanoid_prime.modes import Mode

from .conftest import wait_for


@pytest.fixture
def bridged(manager, domain):
    """A bridge that takes control from the graph (--dds-control), publishing /clock as in simulation."""
    bridge = bridge_manager(manager, domain=domain, control=True, sim_clock=True)
    yield bridge
    bridge.close()


@pytest.fixture
def publishing(manager, domain):
    """A bridge that only publishes (--dds alone)."""
    bridge = bridge_manager(manager, domain=domain)
    yield bridge
    bridge.close()


@pytest.fixture
def peer(domain):
    """Another participant in the domain: a ROS 2 node stands here."""
    with DdsNode(domain) as node:
        yield node


def take(reader, into: list) -> None:
    into.extend(s for s in reader.take(N=100) if not isinstance(s, InvalidSample))


def test_joint_states_reach_a_reader_every_tick_in_canonical_order(manager, bridged, peer, sim_robot):
    reader = peer.reader("/prime/joint_states", msg.JointState, depth=100)  # keeps all 20 of the burst below
    assert wait_for(lambda: bool(reader.get_matched_publications()))
    for k in range(20):
        manager.tick(k * 0.01)
    got: list = []
    assert wait_for(lambda: len(got) >= 20, poll=lambda: take(reader, got))
    assert [list(s.name) for s in got] == [list(sim_robot.names)] * 20
    assert [round(msg.seconds(s.header.stamp), 6) for s in got] == [round(k * 0.01, 6) for k in range(20)]
    summary = bridged.summary()["topics"]["/prime/joint_states"]
    assert summary["published"] == 20 and summary["dropped"] == 0


def test_mode_and_safety_are_latched_for_a_late_joiner(manager, bridged, peer):
    manager.request_mode(Mode.DAMPING)
    manager.tick(0.0)
    assert wait_for(lambda: bridged.counts["/control_mode"].samples >= 2)
    mode = peer.reader("/control_mode", msg.String, latched=True, depth=1)  # joins after the fact
    safety = peer.reader("/safety_status", msg.DiagnosticArray, latched=True, depth=1)
    modes: list = []
    statuses: list = []
    assert wait_for(lambda: modes and statuses, poll=lambda: (take(mode, modes), take(safety, statuses)))
    assert [m.data for m in modes] == ["DAMPING"]
    names = [s.name for s in statuses[-1].status]
    assert names == [f"prime/{source}" for source in manager.flag_source_names]
    assert all(s.level == msg.DiagnosticStatus.OK for s in statuses[-1].status)
    assert [s.message for s in statuses[-1].status if s.name != "prime/dds"] == ["ok"] * (len(names) - 1)
    assert [s.message for s in statuses[-1].status if s.name == "prime/dds"] == [f"ok; {CONTROL_ON}"]


def test_a_flag_is_one_key_value_under_its_source_at_its_level(manager, bridged, peer):
    safety = peer.reader("/safety_status", msg.DiagnosticArray, latched=True, depth=1)
    manager.request_mode(Mode.REMOTE)
    manager.tick(0.0)  # REMOTE without a command: the stale warning
    statuses: list = []

    def stale():
        remote = [s for a in statuses for s in a.status if s.name == "prime/remote_policy_controller"]
        return remote and remote[-1].level == msg.DiagnosticStatus.WARN

    assert wait_for(stale, poll=lambda: take(safety, statuses))
    remote = [s for s in statuses[-1].status if s.name == "prime/remote_policy_controller"][0]
    assert [kv.key for kv in remote.values] == ["stale"]
    assert "waiting for the first command" in remote.message


def test_a_remote_command_from_the_graph_drives_remote(manager, bridged, peer, sim_robot):
    writer = peer.writer("/remote_policy_controller/command", msg.MitCommand)
    manager.request_mode(Mode.REMOTE)
    manager.tick(0.0)
    target = (sim_robot.lower + sim_robot.upper) / 2
    command = msg.MitCommand(name=list(sim_robot.names), position=target.tolist(), velocity=[0.0] * 14,
                             effort=[0.0] * 14, stiffness=[5.0] * 14, damping=[0.5] * 14)
    assert wait_for(lambda: bool(writer.get_matched_subscriptions()))
    writer.write(command)
    remote = manager.controllers["remote_policy_controller"]
    assert wait_for(lambda: remote.accepted == 1)
    manager.tick(0.01)
    plant = manager.resources.components[0]
    np.testing.assert_allclose(plant.written[-1][0], target)
    assert manager.active_mode is Mode.REMOTE


def test_a_bad_remote_command_is_refused_counted_and_flagged(manager, bridged, peer, sim_robot):
    writer = peer.writer("/remote_policy_controller/command", msg.MitCommand)
    manager.request_mode(Mode.REMOTE)
    manager.tick(0.0)
    assert wait_for(lambda: bool(writer.get_matched_subscriptions()))
    writer.write(msg.MitCommand(name=list(reversed(sim_robot.names)), position=[0.0] * 14, velocity=[0.0] * 14,
                                effort=[0.0] * 14, stiffness=[0.0] * 14, damping=[0.0] * 14))
    writer.write(msg.MitCommand(name=list(sim_robot.names), position=[float("nan")] * 14, velocity=[0.0] * 14,
                                effort=[0.0] * 14, stiffness=[0.0] * 14, damping=[0.0] * 14))
    remote = manager.controllers["remote_policy_controller"]
    assert wait_for(lambda: remote.rejected == 2)
    manager.tick(0.01)
    assert manager.active_mode is Mode.REMOTE and not manager.fallbacks
    flags = manager.topics.latest("/safety_status").flags
    assert "position of left_shoulder_pitch is nan" in flags["remote_policy_controller/rejected"]
    received = bridged.summary()["topics"]["/remote_policy_controller/command"]
    assert received["received"] == 2 and received["refused"] == 2


def test_a_mode_request_takes_the_switch_path_and_an_unknown_one_is_refused(manager, bridged, peer):
    writer = peer.writer(MODE_REQUEST, msg.String)
    assert wait_for(lambda: bool(writer.get_matched_subscriptions()))
    writer.write(msg.String(data="standby"))
    assert wait_for(lambda: bridged.counts[MODE_REQUEST].samples == 1)
    manager.tick(0.0)
    assert manager.active_mode is Mode.STANDBY
    writer.write(msg.String(data="FLY"))
    assert wait_for(lambda: bridged.counts[MODE_REQUEST].refused == 1)
    manager.tick(0.01)
    assert manager.active_mode is Mode.STANDBY
    assert "mode request 'FLY' on /prime/mode_request refused" in \
        manager.topics.latest("/safety_status").flags["dds/mode_request"]


class StuckBridge(DdsBridge):
    """A bridge whose transport never returns from writing a joint state (until released)."""

    def __init__(self, *args, **kwargs) -> None:
        self.release = threading.Event()
        self.entered = threading.Event()
        super().__init__(*args, **kwargs)

    def write(self, topic, message) -> None:
        if topic == "/prime/joint_states":
            self.entered.set()
            self.release.wait()
        super().write(topic, message)


def test_a_stuck_transport_never_holds_the_tick_it_drops_counts_and_flags(manager, domain):
    bridge = StuckBridge(DdsNode(domain, name="prime"), manager, request_mode=None, control=False)
    manager.add_flag_source(bridge)
    try:
        manager.tick(0.0)
        assert bridge.entered.wait(30)
        ticks = 3 * bridge.tap.slots
        for k in range(1, ticks):
            manager.tick(k * 0.01)  # returns: nothing here waits on the stuck writer
        counts = bridge.summary()["topics"]["/prime/joint_states"]
        assert counts["dropped"] == ticks - bridge.tap.slots  # the stuck sample holds its slot too
        assert "joint states dropped" in manager.topics.latest("/safety_status").flags["dds/dropped"]
    finally:
        bridge.release.set()
        bridge.close()


def test_closing_leaves_the_domain(manager, domain, peer):
    bridge = bridge_manager(manager, domain=domain)
    reader = peer.reader("/prime/joint_states", msg.JointState)
    assert wait_for(lambda: bool(reader.get_matched_publications()))
    bridge.close()
    assert wait_for(lambda: not reader.get_matched_publications())


def test_without_control_the_node_reads_nothing_from_the_graph_and_says_so(manager, publishing, peer):
    (node,) = publishing.node.entities_info().node_entities_info_seq
    assert node.reader_gid_seq == [] and len(node.writer_gid_seq) == 7
    safety = peer.reader("/safety_status", msg.DiagnosticArray, latched=True, depth=1)
    statuses: list = []
    assert wait_for(lambda: statuses, poll=lambda: take(safety, statuses))
    assert [s.message for s in statuses[-1].status if s.name == "prime/dds"] == [f"ok; {CONTROL_OFF}"]
    assert publishing.summary()["control"] is False and MODE_REQUEST not in publishing.summary()["topics"]


def test_the_node_is_announced_with_every_endpoint_and_its_type_hash(manager, bridged, peer):
    # ros_discovery_info is a topic of the rmw layer, outside ROS 2's names (no rt/ prefix).
    reader = DataReader(peer.participant, Topic(peer.participant, DISCOVERY_TOPIC, msg.ParticipantEntitiesInfo),
                        qos=ros_qos(latched=True, depth=1))
    infos: list = []
    assert wait_for(lambda: infos and infos[-1].node_entities_info_seq[0].reader_gid_seq,
                    poll=lambda: take(reader, infos))
    info = infos[-1]
    (node,) = info.node_entities_info_seq
    assert (node.node_namespace, node.node_name) == ("/", "prime")
    # The endpoints announced are the ones a peer matches on each of Prime's topics (their GUIDs as GIDs).
    outgoing = {"/prime/joint_states": msg.JointState, "/control_mode": msg.String,
                "/safety_status": msg.DiagnosticArray, "/diagnostics": msg.DiagnosticArray,
                "/robot_description": msg.String, "/tf_static": msg.TFMessage, "/tf": msg.TFMessage,
                "/clock": msg.Clock}
    readers = [peer.reader(topic, kind, latched=topic in ("/control_mode", "/safety_status", "/robot_description",
                                                          "/tf_static"), depth=1) for topic, kind in outgoing.items()]
    writers = [peer.writer(MODE_REQUEST, msg.String), peer.writer("/remote_policy_controller/command", msg.MitCommand)]
    assert wait_for(lambda: all(r.get_matched_publications() for r in readers)
                    and all(w.get_matched_subscriptions() for w in writers))
    matched_writers = {r.get_matched_publication_data(h).key.bytes for r in readers
                       for h in r.get_matched_publications()}
    matched_readers = {w.get_matched_subscription_data(h).key.bytes for w in writers
                       for h in w.get_matched_subscriptions()}
    assert {bytes(g.data) for g in node.writer_gid_seq} == matched_writers and len(matched_writers) == 8
    assert {bytes(g.data) for g in node.reader_gid_seq} == matched_readers and len(matched_readers) == 2
    assert bytes(info.gid.data)[:12] == next(iter(matched_writers))[:12]  # the participant's GUID prefix
    # What a peer discovers of the joint states' writer: ROS 2's type hash in its user data.
    (handle,) = readers[0].get_matched_publications()
    data = readers[0].get_matched_publication_data(handle)
    assert data.qos[Policy.Userdata].data == f"typehash={type_hash(msg.JointState)};".encode()


def test_a_best_effort_publisher_of_mode_requests_is_a_qos_mismatch_flagged_and_counted(manager, bridged, domain):
    with DdsNode(domain) as other:
        other.writer(MODE_REQUEST, msg.String, reliable=False)
        assert wait_for(lambda: bridged.summary()["qos_mismatches"] >= 1)
        manager.tick(0.0)
        flags = manager.topics.latest("/safety_status").flags
        assert flags["dds/qos/prime/mode_request"].startswith("QoS mismatch on /prime/mode_request: a publisher "
                                                             "with an incompatible reliability")
        assert bridged.summary()["topics"][MODE_REQUEST]["qos_mismatches"] >= 1


def test_a_transient_local_subscriber_of_the_joint_states_is_a_qos_mismatch(manager, bridged, peer):
    peer.reader("/prime/joint_states", msg.JointState, latched=True)  # Prime offers them volatile
    assert wait_for(lambda: bridged.summary()["topics"]["/prime/joint_states"]["qos_mismatches"] >= 1)
    manager.tick(0.0)
    flag = manager.topics.latest("/safety_status").flags["dds/qos/prime/joint_states"]
    assert flag.startswith("QoS mismatch on /prime/joint_states: a subscription with an incompatible durability")


def test_tf_clock_description_and_static_frames(manager, bridged, peer, sim_robot):
    frames = frames_from_urdf(sim_robot.description.urdf, sim_robot.names)
    tf = peer.reader("/tf", msg.TFMessage, depth=100)
    clock = peer.reader("/clock", msg.Clock, depth=100)
    assert wait_for(lambda: bool(tf.get_matched_publications()) and bool(clock.get_matched_publications()))
    for k in range(5):
        manager.tick(k * 0.01)
    tfs: list = []
    clocks: list = []
    assert wait_for(lambda: len(tfs) >= 5 and len(clocks) >= 5, poll=lambda: (take(tf, tfs), take(clock, clocks)))
    assert [round(msg.seconds(c.clock), 6) for c in clocks] == [0.0, 0.01, 0.02, 0.03, 0.04]
    latest = tfs[-1]
    measured = manager.resources.state.data[0]
    translations, rotations = frames.transforms(measured)
    assert [(t.header.frame_id, t.child_frame_id) for t in latest.transforms] == list(
        zip(frames.parents, frames.children, strict=True))
    assert {round(msg.seconds(t.header.stamp), 6) for t in latest.transforms} == {0.04}
    got = np.array([[t.transform.translation.x, t.transform.translation.y, t.transform.translation.z]
                    for t in latest.transforms])
    np.testing.assert_allclose(got, translations)
    got = np.array([[t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z, t.transform.rotation.w]
                    for t in latest.transforms])
    np.testing.assert_allclose(got, rotations)
    # Late joiners: the URDF and the fixed joints are latched.
    description = peer.reader("/robot_description", msg.String, latched=True, depth=1)
    static = peer.reader("/tf_static", msg.TFMessage, latched=True, depth=1)
    urdfs: list = []
    statics: list = []
    assert wait_for(lambda: urdfs and statics, poll=lambda: (take(description, urdfs), take(static, statics)))
    assert urdfs[-1].data == sim_robot.description.urdf
    assert [(t.header.frame_id, t.child_frame_id) for t in statics[-1].transforms] == [
        ("base_link", "waist_yaw_link"), ("waist_yaw_link", "waist_roll_link"), ("waist_roll_link", "torso_link")]


def test_diagnostics_repeat_every_second_of_loop_time(manager, bridged, peer):
    diagnostics = peer.reader("/diagnostics", msg.DiagnosticArray, depth=100)
    assert wait_for(lambda: bool(diagnostics.get_matched_publications()))
    published = bridged.counts["/prime/joint_states"]
    for k in range(251):  # 2.5 s of loop time, in bursts the publisher keeps up with (none dropped)
        manager.tick(k * 0.01)
        if k % 50 == 49:
            assert wait_for(lambda k=k: published.samples == k + 1)
    got: list = []
    assert wait_for(lambda: len(got) >= 3, poll=lambda: take(diagnostics, got))
    stamps = [round(msg.seconds(a.header.stamp), 6) for a in got]
    assert stamps[-3:] == [0.0, 1.0, 2.0]
    assert [s.name for s in got[-1].status] == [f"prime/{source}" for source in manager.flag_source_names]


def test_a_namespace_prefixes_every_topic_and_the_node(manager, domain, peer):
    bridge = bridge_manager(manager, domain=domain, namespace="/left")
    try:
        reader = peer.reader("/left/prime/joint_states", msg.JointState)
        assert wait_for(lambda: bool(reader.get_matched_publications()))
        (node,) = bridge.node.entities_info().node_entities_info_seq
        assert (node.node_namespace, node.node_name) == ("/left", "prime")
        assert bridge.summary()["node"] == "/left/prime"
    finally:
        bridge.close()
