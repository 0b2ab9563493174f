"""Prime as real ROS 2 nodes see it: rclpy from PyPI's wheels, Jazzy (Fast DDS 2.14) and Kilted (Fast DDS 3.2),
against two simulated Primes on one domain, ``/prime`` and ``/second/prime``, discovery kept to this machine
(ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST on both sides).

Both ROS 2 nodes (``ros/probe.py``) run at once: each reads every topic of both Primes, looks at the graph,
and drives one of them (Jazzy the first, Kilted the second) with mode requests and prime_msgs/MitCommand
(built from ``prime_msgs/`` with the wheels' rosidl toolchain and cmake), following /clock with use_sim_time.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest

from doubles.process import popen, stop
from humanoid_prime.config.robot import load_robot
from humanoid_prime.dds import messages as msg
from humanoid_prime.dds.node import DdsNode, take
from humanoid_prime.dds.tf import quaternion_multiply, rotate
from humanoid_prime.drivers.mujoco.system import load_model

from .conftest import LOOPBACK, ROS_DISTROS, _domains, ros_environment, wait_for

# Two simulations at 200 Hz on the wall clock and a ROS 2 node per distribution that must keep up with both: on busy
# cores a node falls seconds behind one stream and its /tf and joint states no longer overlap.
pytestmark = pytest.mark.realtime

PRIME = [sys.executable, "-m", "humanoid_prime"]
PROBE = Path(__file__).parent / "ros" / "probe.py"
SIM_RATE_HZ = 200.0  # the bundled prime_sim controllers' update rate
JOINT_STATES = 200  # collected per instance and distribution: one simulated second
COMMAND_S = 3.0  # simulated seconds of commands
OFFSET = -0.5  # rad, the commanded move of one elbow
# Who drives which Prime with which joint.
DRIVES = {"jazzy": ("/", "left_elbow_pitch"), "kilted": ("/second", "right_elbow_pitch")}
OUT = {"/prime/joint_states": "sensor_msgs/msg/JointState", "/control_mode": "std_msgs/msg/String",
       "/safety_status": "diagnostic_msgs/msg/DiagnosticArray", "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
       "/robot_description": "std_msgs/msg/String", "/tf": "tf2_msgs/msg/TFMessage",
       "/tf_static": "tf2_msgs/msg/TFMessage", "/clock": "rosgraph_msgs/msg/Clock"}
IN = {"/prime/mode_request": "std_msgs/msg/String", "/remote_policy_controller/command": "prime_msgs/msg/MitCommand"}


def name(namespace: str, topic: str) -> str:
    return topic if namespace == "/" else namespace + topic


@pytest.fixture(scope="module")
def graph(ros_clients, tmp_path_factory):
    """Two Primes and two ROS 2 nodes on a domain of their own; what each node reported and each Prime's
    summary."""
    folder = tmp_path_factory.mktemp("graph")
    domain = next(_domains)
    env = {**os.environ, "CYCLONEDDS_URI": LOOPBACK, "ROS_DOMAIN_ID": str(domain),
           "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    sims = {}
    for namespace in ("/", "/second"):
        summary = folder / f"sim{namespace.replace('/', '_')}.json"
        extra = [] if namespace == "/" else ["--namespace", namespace.strip("/")]
        with open(folder / f"sim{namespace.replace('/', '_')}.log", "w") as log:  # a file: a pipe could fill
            socket = folder / f"sim{namespace.replace('/', '_')}.sock"  # each instance answers on its own
            sims[namespace] = (popen([*PRIME, "sim", "--dds", "--dds-control", *extra, "--mode", "STANDBY",
                                      "--duration", "600", "--summary", str(summary), "--socket", str(socket)],
                                     env=env,
                                     stdout=subprocess.DEVNULL, stderr=log), summary)
    probes = {}
    try:
        with pytest.MonkeyPatch.context() as patch:  # the ROS 2 nodes join once both Primes hold STANDBY
            for key in ("CYCLONEDDS_URI", "ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
                patch.setenv(key, env[key])
            _wait_for_standby(domain)
        for distro in ROS_DISTROS:
            control, joint = DRIVES[distro]
            spec = {"name": f"probe_{distro}", "instances": ["/", "/second"], "control": control, "joint": joint,
                    "offset": OFFSET, "joint_states": JOINT_STATES, "command_s": COMMAND_S}
            client = ros_clients[distro]
            probes[distro] = subprocess.Popen(
                [client["python"], str(PROBE), json.dumps(spec)],
                env=ros_environment(client, domain), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        reports = {}
        for distro, probe in probes.items():
            out, err = probe.communicate(timeout=400)
            assert probe.returncode == 0, f"{distro}: {out[-2000:]}{err[-3000:]}"
            reports[distro] = json.loads(out.strip().splitlines()[-1])
    finally:
        for probe in probes.values():
            if probe.poll() is None:
                probe.kill()
        for process, _ in sims.values():
            stop(process)
    summaries = {}
    for namespace, (process, path) in sims.items():
        assert process.returncode == 0, (folder / f"sim{namespace.replace('/', '_')}.log").read_text()[-3000:]
        summaries[namespace] = json.loads(path.read_text())
    for distro, report in reports.items():  # the sample counts, for `pytest -s` (the note's figures)
        counts = {namespace: {key: len(value) for key, value in seen.items() if isinstance(value, list)}
                  for namespace, seen in report["instances"].items()}
        print(f"\n{distro}: received {json.dumps(counts)}")
    for namespace, summary in summaries.items():
        print(f"prime {namespace}: dds {json.dumps(summary.get('dds', {}))[:600]}")
    return reports, summaries


def _wait_for_standby(domain: int) -> None:
    with DdsNode(domain) as node:
        readers = [node.reader(name(namespace, "/control_mode"), msg.String, latched=True, depth=1)
                   for namespace in ("/", "/second")]
        modes: list[list[str]] = [[], []]

        def poll() -> None:
            for reader, seen in zip(readers, modes, strict=True):
                seen.extend(sample.data for sample in take(reader))

        assert wait_for(lambda: all(seen and seen[-1] == "STANDBY" for seen in modes), timeout=120, poll=poll), modes


@pytest.mark.parametrize("distro", ROS_DISTROS)
def test_the_node_list_has_both_primes_with_their_topics(graph, distro):
    report = graph[0][distro]
    assert ["prime", "/"] in report["graph"]["nodes"] and ["prime", "/second"] in report["graph"]["nodes"]
    for namespace in ("/", "/second"):
        by_node = report["graph"]["by_node"][namespace]
        assert by_node["publishers"] == sorted([name(namespace, t), [ty]] for t, ty in OUT.items())
        assert by_node["subscriptions"] == sorted([name(namespace, t), [ty]] for t, ty in IN.items())


@pytest.mark.parametrize("distro", ROS_DISTROS)
def test_every_endpoint_has_the_type_hash_the_wheels_compute(graph, distro):
    report = graph[0][distro]
    compared = set()
    for topic, kinds in report["graph"]["endpoints"].items():
        namespace = "/second" if topic.startswith("/second/") else "/"
        prime = [e for kind in ("publishers", "subscriptions") for e in kinds[kind] if not e["own"]
                 and not e["node"].startswith("probe_")]
        own = {e["hash"] for kind in ("publishers", "subscriptions") for e in kinds[kind] if e["own"]}
        assert prime, topic
        for endpoint in prime:
            assert endpoint["hash"].startswith("RIHS01_") and endpoint["hash"] != "RIHS01_" + "0" * 64, topic
            if own:  # this node has an endpoint of the same type there: the wheels' hash
                assert {endpoint["hash"]} == own, topic
                compared.add(topic.removeprefix("/second"))
            if distro == "jazzy":
                # Fast DDS 3 (Kilted) takes an endpoint's participant from a field Cyclone DDS does not send in
                # endpoint discovery, so its topic info lists Prime's endpoints as _CREATED_BY_BARE_DDS_APP_;
                # its node list and node info (the test above) are right.
                assert (endpoint["node"], endpoint["namespace"]) == ("prime", namespace), topic
    assert compared == set(OUT) | set(IN)


@pytest.mark.parametrize("distro", ROS_DISTROS)
def test_joint_states_arrive_every_tick_in_canonical_order(graph, distro, sim_robot):
    for namespace, seen in graph[0][distro]["instances"].items():
        stamps = np.array([stamp for stamp, _, _ in seen["joint_states"]]) * 1e-9
        assert len(stamps) == JOINT_STATES, namespace
        assert {tuple(names) for _, names, _ in seen["joint_states"]} == {sim_robot.names}
        np.testing.assert_allclose(np.diff(stamps), 1.0 / SIM_RATE_HZ, atol=1e-6)


@pytest.mark.parametrize("distro", ROS_DISTROS)
def test_latched_mode_safety_and_diagnostics(graph, distro):
    control, _ = DRIVES[distro]
    # Latched: STANDBY was set before this node joined (the other node may have switched the other Prime since).
    assert graph[0][distro]["instances"][control]["modes"][0] == "STANDBY"
    for seen in graph[0][distro]["instances"].values():
        names = [status[0] for status in seen["safety"]]
        # one status per flag source, the bridge's last, then the run's configuration files
        assert names[-2:] == ["prime/dds", "prime/configuration"]
        assert [status[0] for status in seen["diagnostics"]] == names
        dds = [message for status, _, message in seen["safety"] if status == "prime/dds"][0]
        assert "takes mode requests and REMOTE commands from the ROS 2 graph" in dds
    assert graph[0][distro]["instances"][control]["modes"][-1] == "REMOTE"


@pytest.mark.parametrize("distro", ROS_DISTROS)
def test_robot_description_and_tf_match_forward_kinematics(graph, distro, sim_robot):
    model = load_model(sim_robot, None)
    data = mujoco.MjData(model)
    for namespace, seen in graph[0][distro]["instances"].items():
        assert seen["description"] == load_robot(use_sim=True).description.urdf
        frame = seen["frame"]
        assert "error" not in frame, frame.get("error")
        parent_of = {child: (parent, np.array(t), np.array(r))
                     for parent, child, t, r in seen["tf_static"] + frame["transforms"]}
        for link in ("left_hand_link", "right_hand_link"):
            translation, rotation, walk = np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]), link
            while walk != "base_link":
                walk, t, r = parent_of[walk]
                translation, rotation = t + rotate(r, translation), quaternion_multiply(r, rotation)
            # MuJoCo's forward kinematics of the same positions (its model, not the URDF), in base_link.
            for i, joint in enumerate(sim_robot.names):
                data.qpos[model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, joint)]] = \
                    frame["positions"][i]
            mujoco.mj_kinematics(model, data)
            base = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "base_link")
            body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, link)
            expected = data.xmat[base].reshape(3, 3).T @ (data.xpos[body] - data.xpos[base])
            np.testing.assert_allclose(translation, expected, atol=1e-9, err_msg=f"{namespace} {link}")
            inverse = np.zeros(4)
            mujoco.mju_negQuat(inverse, data.xquat[base])
            relative = np.zeros(4)
            mujoco.mju_mulQuat(relative, inverse, data.xquat[body])
            wxyz = np.array([rotation[3], *rotation[:3]])
            assert min(np.abs(wxyz - relative).max(), np.abs(wxyz + relative).max()) < 1e-9, (namespace, link)


@pytest.mark.parametrize("distro", ROS_DISTROS)
def test_a_use_sim_time_clock_follows_the_simulation(graph, distro):
    """The node's clock reads simulated time: about the joint states' stamps (the system clock would be 1.7e9 s
    off; the slack is how far this node's callbacks lag), never ahead of the simulation, and it ran the COMMAND_S
    seconds the node waited for."""
    reports, summaries = graph
    (before_clock, before_stamp), (after_clock, after_stamp) = reports[distro]["clock"]
    assert abs(before_clock - before_stamp) < 5e9 and abs(after_clock - after_stamp) < 5e9
    assert after_clock - before_clock >= COMMAND_S * 1e9
    assert after_clock <= summaries["/"]["sim_seconds"] * 1e9


def test_each_prime_follows_only_the_node_that_drives_it(graph, sim_robot):
    reports, summaries = graph
    for distro, (namespace, joint) in DRIVES.items():
        seen = reports[distro]["instances"][namespace]
        before = np.array(seen["joint_states"][-1][2])
        after = np.array(reports[distro]["instances"][namespace]["latest"][1])
        moved = sim_robot.index(joint)
        other = sim_robot.index("right_elbow_pitch" if joint.startswith("left") else "left_elbow_pitch")
        # The commanded joint moves by OFFSET less what gravity takes from a stiffness-20 hold (about 0.15 rad
        # for an elbow swinging towards horizontal); the other elbow, held where it was, barely moves.
        assert OFFSET - 0.15 < after[moved] - before[moved] < OFFSET + 0.25, distro
        assert abs(after[other] - before[other]) < 0.15, distro
        received = summaries[namespace]["dds"]["topics"]["/remote_policy_controller/command"]
        # ROS 2's default QoS keeps the last 10: a reader that lags on a busy machine may lose a few (the newest
        # command is what REMOTE follows), none is refused.
        assert 0.9 * reports[distro]["sent_commands"] <= received["received"] <= reports[distro]["sent_commands"]
        assert received["refused"] == 0
        assert summaries[namespace]["dds"]["topics"]["/prime/mode_request"]["received"] == 1
        assert summaries[namespace]["dds"]["topics"]["/prime/joint_states"]["dropped"] == 0
        assert summaries[namespace]["fallbacks"] == []
