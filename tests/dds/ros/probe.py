"""A real ROS 2 node (rclpy, run by a ROS 2 client environment's Python) that looks at Prime the way ROS 2
tools and nodes do, and drives one Prime. One JSON argument:

    {"name": node name, "instances": [namespace, ...], "control": namespace it drives,
     "joint": joint it moves, "offset": rad, "joint_states": how many to collect per instance,
     "command_s": seconds of simulated time to stream commands}

It waits until every instance is in the node list and has sent each of its topics, collects ``joint_states``
joint states per instance, then streams prime_msgs/MitCommand (every joint held where it is, ``joint`` moved by
``offset``) and asks for REMOTE, for ``command_s`` of the /clock its use_sim_time clock follows. It prints one
JSON object with what it saw (see ``report``).
"""

from __future__ import annotations

import json
import sys
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from prime_msgs.msg import MitCommand
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from tf2_msgs.msg import TFMessage

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
TIMEOUT_S = 120.0  # bounds a failure only
KEPT = 2000  # the latest joint states and /tf samples kept by stamp, to pair them


def topic(namespace: str, name: str) -> str:
    return name if namespace == "/" else namespace + name


class Instance:
    """One Prime as this node sees it."""

    def __init__(self, node, namespace: str, keep: int) -> None:
        self.namespace = namespace
        self.keep = keep
        self.joint_states: list[tuple[int, list[str], list[float]]] = []  # (stamp ns, names, positions)
        self.received = {name: 0 for name in ("joint_states", "control_mode", "safety_status", "diagnostics",
                                              "robot_description", "tf", "tf_static")}
        self.modes: list[str] = []
        self.safety: list[list[tuple[str, int, str]]] = []
        self.diagnostics: list[tuple[str, int, str]] = []
        self.description = ""
        self.tf: dict[int, list] = {}  # stamp ns -> transforms
        self.tf_static: list = []
        self.positions_at: dict[int, list[float]] = {}  # stamp ns -> positions (the last few)
        # the latest /tf and joint state with one stamp (paired as they arrive: on a loaded machine /tf may trail the
        # joint states by more than the last few)
        self.matched: dict | None = None
        sub = node.create_subscription
        sub(JointState, topic(namespace, "/prime/joint_states"), self.on_joint_state, 1000)
        sub(String, topic(namespace, "/control_mode"), self.on_mode, LATCHED)
        sub(DiagnosticArray, topic(namespace, "/safety_status"), self.on_safety, LATCHED)
        sub(DiagnosticArray, topic(namespace, "/diagnostics"), self.on_diagnostics, 10)
        sub(String, topic(namespace, "/robot_description"), self.on_description, LATCHED)
        sub(TFMessage, topic(namespace, "/tf"), self.on_tf, 100)
        sub(TFMessage, topic(namespace, "/tf_static"), self.on_tf_static, LATCHED)

    def on_joint_state(self, m: JointState) -> None:
        self.received["joint_states"] += 1
        stamp = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
        if len(self.joint_states) < self.keep:
            self.joint_states.append((stamp, list(m.name), list(m.position)))
        self.latest = (stamp, list(m.position))
        self.positions_at[stamp] = list(m.position)
        self.pair(stamp)
        if len(self.positions_at) > KEPT:
            self.positions_at.pop(next(iter(self.positions_at)))

    def on_mode(self, m: String) -> None:
        self.received["control_mode"] += 1
        self.modes.append(m.data)

    def on_safety(self, m: DiagnosticArray) -> None:
        self.received["safety_status"] += 1
        self.safety.append([(s.name, s.level[0] if isinstance(s.level, bytes) else s.level, s.message)
                            for s in m.status])

    def on_diagnostics(self, m: DiagnosticArray) -> None:
        self.received["diagnostics"] += 1
        self.diagnostics = [(s.name, s.level[0] if isinstance(s.level, bytes) else s.level, s.message)
                            for s in m.status]

    def on_description(self, m: String) -> None:
        self.received["robot_description"] += 1
        self.description = m.data

    def on_tf(self, m: TFMessage) -> None:
        self.received["tf"] += 1
        stamp = m.transforms[0].header.stamp
        ns = stamp.sec * 1_000_000_000 + stamp.nanosec
        self.tf[ns] = transforms(m)
        self.pair(ns)
        if len(self.tf) > KEPT:
            self.tf.pop(next(iter(self.tf)))

    def on_tf_static(self, m: TFMessage) -> None:
        self.received["tf_static"] += 1
        self.tf_static = transforms(m)

    def complete(self) -> bool:
        return len(self.joint_states) >= self.keep and all(self.received.values())

    def pair(self, stamp: int) -> None:
        if stamp in self.tf and stamp in self.positions_at:
            self.matched = {"stamp_ns": stamp, "positions": self.positions_at[stamp], "transforms": self.tf[stamp]}

    def frame_with_joints(self) -> dict:
        """The latest /tf whose stamp has its joint state too (an error in words where none had)."""
        if self.matched is None:
            return {"error": f"none of {self.received['tf']} /tf samples carried the stamp of one of the "
                             f"{self.received['joint_states']} joint states"}
        return self.matched


def transforms(m: TFMessage) -> list:
    return [(t.header.frame_id, t.child_frame_id,
             [t.transform.translation.x, t.transform.translation.y, t.transform.translation.z],
             [t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z, t.transform.rotation.w])
            for t in m.transforms]


def spin_until(node, condition, timeout: float = TIMEOUT_S) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        rclpy.spin_once(node, timeout_sec=0.05)
    return condition()


def endpoints(node, topics: list[str], own: str) -> dict:
    """Per topic: what the graph says of its publishers and subscriptions (node, type, type hash)."""
    out = {}
    for name in topics:
        out[name] = {kind: [{"node": i.node_name, "namespace": i.node_namespace, "type": i.topic_type,
                             "hash": str(i.topic_type_hash), "own": i.node_name == own}
                            for i in lookup(name)]
                     for kind, lookup in (("publishers", node.get_publishers_info_by_topic),
                                          ("subscriptions", node.get_subscriptions_info_by_topic))}
    return out


def report(node, spec: dict, instances: dict, sent: int, clock: list) -> dict:
    graph = {"nodes": sorted(node.get_node_names_and_namespaces()), "by_node": {}, "endpoints": {}}
    for namespace in instances:
        graph["by_node"][namespace] = {
            "publishers": sorted((t, ty) for t, ty in node.get_publisher_names_and_types_by_node("prime", namespace)),
            "subscriptions": sorted((t, ty) for t, ty in
                                    node.get_subscriber_names_and_types_by_node("prime", namespace))}
        names = ["/prime/joint_states", "/control_mode", "/safety_status", "/diagnostics", "/robot_description",
                 "/tf", "/tf_static", "/clock", "/prime/mode_request", "/remote_policy_controller/command"]
        graph["endpoints"].update(endpoints(node, [topic(namespace, n) for n in names], spec["name"]))
    return {
        "rmw": rclpy.get_rmw_implementation_identifier(),
        "graph": graph,
        "sent_commands": sent,
        "clock": clock,
        "instances": {ns: {"received": i.received, "joint_states": i.joint_states, "modes": i.modes,
                           "safety": i.safety[-1] if i.safety else None, "diagnostics": i.diagnostics,
                           "description": i.description, "tf_static": i.tf_static, "frame": i.frame_with_joints(),
                           "latest": i.latest}
                      for ns, i in instances.items()},
    }


def main() -> int:
    spec = json.loads(sys.argv[1])
    rclpy.init()
    node = rclpy.create_node(spec["name"], parameter_overrides=[Parameter("use_sim_time", value=True)])
    instances = {ns: Instance(node, ns, spec["joint_states"]) for ns in spec["instances"]}
    # Publishers of every type this node compares hashes with, on the topics Prime reads.
    controlled = spec["control"]
    commands = node.create_publisher(MitCommand, topic(controlled, "/remote_policy_controller/command"), 10)
    requests = node.create_publisher(String, topic(controlled, "/prime/mode_request"), 10)
    for ns in spec["instances"]:
        if ns != controlled:
            node.create_publisher(MitCommand, topic(ns, "/remote_policy_controller/command"), 10)
    listed = lambda: all(("prime", ns) in node.get_node_names_and_namespaces() for ns in instances)  # noqa: E731
    if not spin_until(node, lambda: listed() and all(i.complete() for i in instances.values())):
        missing = {ns: [k for k, v in i.received.items() if not v] for ns, i in instances.items()}
        print(json.dumps({"error": f"incomplete after {TIMEOUT_S} s: nodes {node.get_node_names_and_namespaces()}, "
                                   f"nothing yet on {missing}"}))
        return 1
    clock = []  # (this node's clock, the latest joint-state stamp of the first instance), ns
    first = instances[spec["instances"][0]]
    clock.append((node.get_clock().now().nanoseconds, first.latest[0]))

    # Drive the controlled Prime: hold every joint where it is, move one.
    target = instances[controlled]
    names = target.joint_states[-1][1]
    position = list(target.latest[1])
    position[names.index(spec["joint"])] += spec["offset"]
    subscribers = lambda: commands.get_subscription_count() and requests.get_subscription_count()  # noqa: E731
    spin_until(node, subscribers)
    sent = 0
    start = node.get_clock().now().nanoseconds
    requested = False
    deadline = time.monotonic() + TIMEOUT_S  # a clock that does not advance fails, it does not hang
    while node.get_clock().now().nanoseconds - start < spec["command_s"] * 1e9 and time.monotonic() < deadline:
        message = MitCommand(name=names, position=position, velocity=[0.0] * len(names),
                             effort=[0.0] * len(names), stiffness=[20.0] * len(names), damping=[2.0] * len(names))
        message.header.stamp = node.get_clock().now().to_msg()
        commands.publish(message)
        sent += 1
        if not requested:  # after the first command: REMOTE starts from it, not from a stale stream
            requests.publish(String(data="REMOTE"))
            requested = True
        spin_until(node, lambda: False, timeout=0.01)
    # This node's callbacks may lag the graph (a busy machine): take in what was published up to now first.
    end = node.get_clock().now().nanoseconds
    spin_until(node, lambda: all(i.latest[0] >= end for i in instances.values()))
    clock.append((node.get_clock().now().nanoseconds, first.latest[0]))
    print(json.dumps(report(node, spec, instances, sent, clock)))
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
