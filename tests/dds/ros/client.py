"""A ROS 2 user's session with Prime (rclpy, run by a ROS 2 client environment's Python), as ``ros2 param``,
``ros2 control``, ``ros2 service call``, MoveIt's trajectory client and ``ros2 node list`` would go about it. One
JSON argument:

    {"name": node name, "backend": "rclpy" or "dds", "joint_states": topic}

It starts before Prime and waits for node /prime. With the rclpy backend it then: lists, gets and sets
parameters through rclpy's parameter client; reads /rosout; switches DAMPING -> STANDBY -> DAMPING with
~/switch_mode and again with the controller manager's switch_controller, listing the controllers after each; in
REMOTE sends one arm a FollowJointTrajectory goal of 3 points over 2 s (its joint states and feedback kept), a
goal it cancels after 1 s, and one outside the joint limits. With either backend it publishes best-effort on
/prime/mode_request (a QoS mismatch for Prime to report) and reads /safety_status. Then it prints ``ready``, and
on a line ``exited <t>`` on stdin (CLOCK_MONOTONIC seconds of Prime's exit) it watches the node list until
/prime is gone, and prints one JSON object with everything it saw.
"""

from __future__ import annotations

import json
import sys
import threading
import time

import rclpy
from builtin_interfaces.msg import Duration
from control_msgs.action import FollowJointTrajectory
from control_msgs.msg import JointTolerance
from controller_manager_msgs.srv import ListControllers, SwitchController
from diagnostic_msgs.msg import DiagnosticArray
from prime_msgs.msg import MitCommand
from prime_msgs.srv import SwitchMode
from rcl_interfaces.msg import Log
from rclpy.action import ActionClient
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from trajectory_msgs.msg import JointTrajectoryPoint

TIMEOUT_S = 120.0  # bounds a failure only
LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
ROSOUT = QoSProfile(depth=1000, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
ARM = "left_arm_controller"
STEPS = ((-0.15, 0.1), (-0.3, 0.15), (-0.2, 0.05))  # (shoulder_pitch, elbow_pitch) offsets of the 3 points, rad


def wait(node, future, timeout: float = TIMEOUT_S):
    deadline = time.monotonic() + timeout
    while not future.done() and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.02)
    if not future.done():
        raise TimeoutError("no answer")
    return future.result()


def spin_until(node, condition, timeout: float = TIMEOUT_S) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        rclpy.spin_once(node, timeout_sec=0.02)
    return condition()


class Seen:
    def __init__(self, node, joint_states: str) -> None:
        self.rosout: list[tuple[str, int, str]] = []
        self.safety: list[tuple[str, int, str]] = []
        self.joint_states: list[tuple[float, list[str], list[float], list[float]]] = []
        self.modes: list[str] = []
        node.create_subscription(Log, "/rosout", self.on_log, ROSOUT)
        node.create_subscription(DiagnosticArray, "/safety_status", self.on_safety, LATCHED)
        node.create_subscription(JointState, joint_states, self.on_joint_state, 100)
        node.create_subscription(String, "/control_mode", lambda m: self.modes.append(m.data), LATCHED)

    def on_log(self, m: Log) -> None:
        if m.name == "prime":
            self.rosout.append((m.name, int(m.level), m.msg))

    def on_safety(self, m: DiagnosticArray) -> None:
        self.safety = [(s.name, s.level[0] if isinstance(s.level, bytes) else s.level, s.message) for s in m.status]

    def on_joint_state(self, m: JointState) -> None:
        self.joint_states.append((time.monotonic(), list(m.name), list(m.position), list(m.velocity)))


def parameters(node) -> dict:
    client = AsyncParameterClient(node, "/prime")
    assert client.wait_for_services(TIMEOUT_S), "no parameter services"
    listed = wait(node, client.list_parameters()).result.names
    names = ["backend", "update_rate", "joints", "config.hardware.sha256", "modes.STANDBY.erob_kp",
             "command_limits.erob.stiffness", "remote.timeout_s", "use_sim_time"]
    values = wait(node, client.get_parameters(names)).values
    got = {name: parameter_value_to_python(value) for name, value in zip(names, values, strict=True)}
    sets = {}
    for name, value in (("remote.timeout_s", 0.2), ("remote.timeout_s", 5.0), ("update_rate", 100.0),
                        ("backend", "dds"), ("use_sim_time", True)):
        result = wait(node, client.set_parameters([Parameter(name, value=value)])).results[0]
        sets[f"{name}={value}"] = {"successful": result.successful, "reason": result.reason}
    after = wait(node, client.get_parameters(["remote.timeout_s", "use_sim_time"])).values
    return {"listed": list(listed), "got": got, "sets": sets, "timeout_after": after[0].double_value,
            "use_sim_time_after": after[1].bool_value}


def call(node, client, request):
    assert client.wait_for_service(TIMEOUT_S), client.srv_name
    return wait(node, client.call_async(request))


def switching(node, seen: Seen) -> dict:
    switch = node.create_client(SwitchMode, "/prime/switch_mode")
    listing = node.create_client(ListControllers, "/controller_manager/list_controllers")
    cm = node.create_client(SwitchController, "/controller_manager/switch_controller")

    def active() -> list[str]:
        return [c.name for c in call(node, listing, ListControllers.Request()).controller if c.state == "active"]

    steps = []
    for mode in ("DAMPING", "STANDBY", "DAMPING"):
        answer = call(node, switch, SwitchMode.Request(mode=mode, timeout=5.0))
        steps.append({"via": "switch_mode", "asked": mode, "success": answer.success, "outcome": answer.outcome,
                      "active_mode": answer.active_mode, "message": answer.message, "listed_active": active()})
    previous = "damping_controller"
    for controller in ("standby_controller", "damping_controller"):
        request = SwitchController.Request(activate_controllers=[controller], deactivate_controllers=[previous],
                                           strictness=SwitchController.Request.STRICT, timeout=Duration(sec=5))
        answer = call(node, cm, request)
        steps.append({"via": "switch_controller", "asked": controller, "success": answer.ok,
                      "message": answer.message, "listed_active": active()})
        previous = controller
    refused = call(node, cm, SwitchController.Request(activate_controllers=["nonsense_controller"],
                                                      strictness=SwitchController.Request.STRICT))
    listed = call(node, listing, ListControllers.Request()).controller
    return {"steps": steps, "refused": {"ok": refused.ok, "message": refused.message},
            "controllers": [{"name": c.name, "state": c.state, "type": c.type, "claimed": len(c.claimed_interfaces)}
                            for c in listed]}


def trajectory(node, seen: Seen) -> dict:
    switch = node.create_client(SwitchMode, "/prime/switch_mode")
    client = ActionClient(node, FollowJointTrajectory, f"/{ARM}/follow_joint_trajectory")
    assert client.wait_for_server(TIMEOUT_S), "no trajectory action"
    names = seen.joint_states[-1][1]
    arm = [n for n in names if n.startswith("left_")]
    report: dict = {"joints": arm}
    # Outside the limits: the elbow bends the wrong way (its upper limit is 0).
    goal = FollowJointTrajectory.Goal()
    goal.trajectory.joint_names = arm
    start = dict(zip(names, seen.joint_states[-1][2], strict=True))
    bad = [start[j] for j in arm]
    bad[arm.index("left_elbow_pitch")] = 0.8
    goal.trajectory.points = [JointTrajectoryPoint(positions=bad, time_from_start=Duration(sec=2))]
    call(node, switch, SwitchMode.Request(mode="STANDBY", timeout=5.0))  # the ready pose, then REMOTE from there
    spin_until(node, lambda: False, 2.5)
    switch_answer = call(node, switch, SwitchMode.Request(mode="REMOTE", timeout=5.0))
    report["remote"] = {"success": switch_answer.success, "message": switch_answer.message}
    handle = wait(node, client.send_goal_async(goal))
    report["out_of_limits_accepted"] = handle.accepted

    def run(goal, cancel_after: float | None):
        feedback: list = []
        began = len(seen.joint_states)
        handle = wait(node, client.send_goal_async(goal, feedback_callback=lambda f: feedback.append(f.feedback)))
        if not handle.accepted:
            return {"accepted": False}
        result_future = handle.get_result_async()
        cancelled_at = None
        if cancel_after is not None:
            spin_until(node, lambda: False, cancel_after)
            cancelled_at = len(seen.joint_states)
            wait(node, handle.cancel_goal_async())
        result = wait(node, result_future)
        ended = len(seen.joint_states)
        spin_until(node, lambda: len(seen.joint_states) >= ended + 150, 60)  # the arm after the end: 0.75 s of ticks
        indices = [names.index(j) for j in arm]
        during = [[s[2][i] for i in indices] for s in seen.joint_states[began:ended]]
        after = [[s[2][i] for i in indices] for s in seen.joint_states[ended:]]
        return {"accepted": True, "status": result.status, "error_code": result.result.error_code,
                "error_string": result.result.error_string,
                "feedback_errors": [list(f.error.positions) for f in feedback],
                "feedback": len(feedback), "during": during, "after": after,
                "cancelled_after_samples": None if cancelled_at is None else cancelled_at - began}

    start = dict(zip(names, seen.joint_states[-1][2], strict=True))
    points = []
    for (pitch, elbow), at in zip(STEPS, (Duration(nanosec=666_666_667), Duration(sec=1, nanosec=333_333_333),
                                          Duration(sec=2)), strict=True):
        positions = [start[j] for j in arm]
        positions[arm.index("left_shoulder_pitch")] += pitch
        positions[arm.index("left_elbow_pitch")] += elbow
        points.append(JointTrajectoryPoint(positions=positions, time_from_start=at))
    goal = FollowJointTrajectory.Goal()
    goal.trajectory.joint_names = arm
    goal.trajectory.points = points
    goal.path_tolerance = [JointTolerance(name=j, position=0.1) for j in arm]
    goal.goal_tolerance = [JointTolerance(name=j, position=0.02) for j in arm]
    goal.goal_time_tolerance = Duration(sec=1)
    report["goal"] = {"points": [list(p.positions) for p in points], "path_tolerance": 0.1, "goal_tolerance": 0.02}
    report["followed"] = run(goal, None)
    # A slow goal back, cancelled after 1 s.
    back = FollowJointTrajectory.Goal()
    back.trajectory.joint_names = arm
    back.trajectory.points = [JointTrajectoryPoint(positions=[start[j] for j in arm], time_from_start=Duration(sec=4))]
    report["cancelled"] = run(back, 1.0)
    return report


def topics_in(node, seen: Seen) -> dict:
    """A MitCommand stream (every joint held where it is) in REMOTE, then DAMPING asked for on the mode topic."""
    commands = node.create_publisher(MitCommand, "/remote_policy_controller/command", 10)
    requests = node.create_publisher(String, "/prime/mode_request", 10)
    spin_until(node, lambda: commands.get_subscription_count() > 0 and requests.get_subscription_count() > 0)
    _, names, position, _ = seen.joint_states[-1]
    for _ in range(20):
        commands.publish(MitCommand(name=names, position=position, velocity=[0.0] * len(names),
                                    effort=[0.0] * len(names), stiffness=[20.0] * len(names),
                                    damping=[2.0] * len(names)))
        spin_until(node, lambda: False, 0.02)
    requests.publish(String(data="DAMPING"))
    spin_until(node, lambda: seen.modes[-1] == "DAMPING", 30)
    return {"sent_commands": 20, "modes_after": seen.modes[-2:]}


def main() -> int:
    spec = json.loads(sys.argv[1])
    rclpy.init()
    node = rclpy.create_node(spec["name"])
    seen = Seen(node, spec["joint_states"])
    report: dict = {"rmw": rclpy.get_rmw_implementation_identifier()}

    def listed() -> bool:
        return ("prime", "/") in node.get_node_names_and_namespaces()

    if not spin_until(node, lambda: listed() and len(seen.joint_states) > 10 and seen.modes):
        print(json.dumps({"error": "node /prime did not come"}))
        return 1
    # A best-effort publisher where Prime subscribes reliably: a QoS mismatch for Prime to report.
    node.create_publisher(String, "/prime/mode_request",
                          QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
    if spec["backend"] == "rclpy":
        report["parameters"] = parameters(node)
        report["switching"] = switching(node, seen)
        report["trajectory"] = trajectory(node, seen)
        report["topics_in"] = topics_in(node, seen)
        spin_until(node, lambda: any("started" in text or "on rclpy" in text for _, _, text in seen.rosout), 10)
        report["rosout"] = seen.rosout
    spin_until(node, lambda: any("QoS mismatch" in message for _, _, message in seen.safety), 30)
    report["safety"] = seen.safety
    print("ready", flush=True)
    line = sys.stdin.readline().split()
    exited = float(line[1])
    spin_until(node, lambda: not listed(), 30)
    report["gone_after_exit_s"] = time.monotonic() - exited
    report["listed_at_end"] = listed()
    print(json.dumps(report), flush=True)
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    threading.excepthook = lambda args: None
    sys.exit(main())
