"""Prime's node as a ROS 2 user meets it, with real rclpy from PyPI's wheels, Jazzy (Fast DDS 2.14) and Kilted
(Fast DDS 3.2), against each backend: the rclpy node (Prime run by the client environment's Python, where
``pip install '.[ros-jazzy]'`` put Prime and its extra, from this source tree) and the bare Cyclone DDS node.

One simulated Prime per distribution and backend serves every assertion of that pair: the ROS 2 user's session
(``ros/client.py``) starts first, waits for node /prime, does what a user does, and then reports how soon /prime
left its graph after Prime's process exited (Ctrl-C against Jazzy, SIGTERM against Kilted). The two distributions
run side by side, each in a domain of its own.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from doubles.process import popen, stop

from .conftest import LOOPBACK, REPO, ROS_DISTROS, _domains, ros_environment

# Four simulations at 200 Hz on the wall clock, two at a time, each followed by a ROS 2 user that times a trajectory, a
# cancel and how soon the node leaves the graph: on busy cores the arm is still moving when the cancel is checked.
pytestmark = pytest.mark.realtime

PRIME = ["-m", "humanoid_prime", "sim", "--dds", "--dds-control", "--mode", "DAMPING", "--duration", "600"]
CLIENT = Path(__file__).parent / "ros" / "client.py"
BACKENDS = ("rclpy", "dds")
GONE_WITHIN_S = 1.0


def _session(client: dict[str, str], distro: str, backend: str, folder: Path) -> tuple[dict, dict, str]:
    domain = next(_domains) % 200 + 1
    env = ros_environment(client, domain)
    spec = {"name": f"user_{distro}", "backend": backend, "joint_states": "/prime/joint_states"}
    user = subprocess.Popen([client["python"], str(CLIENT), json.dumps(spec)], env=env, stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    summary = folder / f"{distro}-{backend}.json"
    log_path = folder / f"{distro}-{backend}.log"
    if backend == "rclpy":  # Prime in the client environment, as a user of the extra runs it
        python, prime_env = client["python"], {**env, "PYTHONPATH": f"{REPO / 'src'}:{env['PYTHONPATH']}"}
    else:
        python, prime_env = sys.executable, {**os.environ, "CYCLONEDDS_URI": LOOPBACK, "ROS_DOMAIN_ID": str(domain),
                                             "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    with open(log_path, "w") as log:
        prime = popen([python, *PRIME, "--ros-backend", backend, "--summary", str(summary), "--socket",
                       str(folder / f"{distro}-{backend}.sock")], env=prime_env, stdout=log, stderr=subprocess.STDOUT)
    try:
        ready = _read_line(user, 400)
        assert ready == "ready", f"{distro}/{backend}: {ready}{user.stderr.read()[-3000:] if user.poll() else ''}"
        if distro == "kilted":  # the other way out: as a service manager stops it
            prime.send_signal(signal.SIGTERM)
            prime.wait(timeout=60)
        else:
            stop(prime)
        exited = time.monotonic()
        out, err = user.communicate(f"exited {exited}\n", timeout=60)
        assert user.returncode == 0, f"{distro}/{backend}: {out[-2000:]}{err[-3000:]}"
    finally:
        for process in (user, prime):
            if process.poll() is None:
                process.kill()
    assert prime.returncode == 0, log_path.read_text()[-3000:]
    return json.loads(out.strip().splitlines()[-1]), json.loads(summary.read_text()), log_path.read_text()


def _read_line(process: subprocess.Popen, timeout: float) -> str:
    """The next line of ``process``'s output, or what it said instead (the timeout bounds a failure only)."""
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.append(process.stdout.readline()), daemon=True)
    reader.start()
    reader.join(timeout)
    return lines[0].strip() if lines else f"nothing within {timeout} s"


@pytest.fixture(scope="module")
def sessions(ros_clients, tmp_path_factory):
    """(distro, backend) -> (the user's report, Prime's summary, Prime's output)."""
    folder = tmp_path_factory.mktemp("ros_node")
    found: dict[tuple[str, str], tuple[dict, dict, str]] = {}
    failures: list[BaseException] = []

    def distro_sessions(distro: str) -> None:
        try:
            for backend in BACKENDS:
                found[distro, backend] = _session(ros_clients[distro], distro, backend, folder)
        except BaseException as exc:  # reported by the fixture, in the test's thread
            failures.append(exc)

    threads = [threading.Thread(target=distro_sessions, args=(distro,)) for distro in ROS_DISTROS]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    if failures:
        raise failures[0]
    for (distro, backend), (report, summary, _) in found.items():  # the figures, for `pytest -s`
        line = (f"\n{distro}/{backend} ({report['rmw']}): gone {report['gone_after_exit_s']:.3f} s after exit; QoS "
                f"mismatches {summary['dds']['qos_mismatches']}")
        if backend == "rclpy":
            followed = report["trajectory"]["followed"]
            errors = [abs(e) for errors in followed["feedback_errors"] for e in errors]
            final = np.abs(np.array(followed["after"][0]) - np.array(report["trajectory"]["goal"]["points"][-1]))
            line += (f"; {len(report['parameters']['listed'])} parameters, {len(report['rosout'])} /rosout lines, "
                     f"{len(report['switching']['steps'])} switches; trajectory: {followed['feedback']} feedback, "
                     f"{len(followed['during'])} joint states, largest error {max(errors):.4f} rad, at the end "
                     f"{final.max():.4f} rad")
        print(line)
    return found


PAIRS = [(distro, backend) for distro in ROS_DISTROS for backend in BACKENDS]
RCLPY = [(distro, "rclpy") for distro in ROS_DISTROS]


@pytest.mark.parametrize(("distro", "backend"), PAIRS)
def test_the_node_leaves_the_graph_within_a_second_of_the_exit(sessions, distro, backend):
    report, _, _ = sessions[distro, backend]
    assert not report["listed_at_end"]
    assert report["gone_after_exit_s"] <= GONE_WITHIN_S


@pytest.mark.parametrize(("distro", "backend"), PAIRS)
def test_a_best_effort_publisher_on_the_mode_requests_is_reported_as_a_qos_mismatch(sessions, distro, backend):
    report, summary, output = sessions[distro, backend]
    dds = [message for name, _, message in report["safety"] if name == "prime/dds"][0]
    assert "QoS mismatch on /prime/mode_request" in dds
    assert summary["dds"]["topics"]["/prime/mode_request"]["qos_mismatches"] >= 1
    assert summary["dds"]["qos_mismatches"] >= 1
    assert output.count("QoS mismatch on /prime/mode_request") == 1  # logged once
    assert summary["dds"]["backend"] == backend


@pytest.mark.parametrize(("distro", "backend"), RCLPY)
def test_parameters_are_the_run_and_refuse_changes_with_a_reason(sessions, distro, backend, sim_robot):
    report, summary, _ = sessions[distro, backend]
    parameters = report["parameters"]
    assert {"backend", "robot", "update_rate", "joints", "config.hardware.path", "config.hardware.sha256",
            "modes.STANDBY.erob_kp", "command_limits.sito.velocity", "remote.timeout_s",
            "use_sim_time"} <= set(parameters["listed"])
    got = parameters["got"]
    assert got["backend"] == "rclpy" and got["update_rate"] == summary["update_rate"] == 200.0
    assert tuple(got["joints"]) == sim_robot.names
    assert got["config.hardware.sha256"] == summary["config"]["hardware"]["sha256"]
    assert got["modes.STANDBY.erob_kp"] == 20.0 and got["use_sim_time"] is False
    sets = parameters["sets"]
    assert sets["remote.timeout_s=0.2"] == {"successful": True, "reason": ""}
    assert parameters["timeout_after"] == 0.2
    assert sets["use_sim_time=True"]["successful"] and parameters["use_sim_time_after"] is True  # honoured
    assert not sets["remote.timeout_s=5.0"]["successful"] and sets["remote.timeout_s=5.0"]["reason"]
    for refused in ("update_rate=100.0", "backend=dds"):
        assert not sets[refused]["successful"] and "read-only" in sets[refused]["reason"], sets[refused]


@pytest.mark.parametrize(("distro", "backend"), RCLPY)
def test_rosout_has_the_start_up_line(sessions, distro, backend):
    report, _, _ = sessions[distro, backend]
    lines = [text for _, _, text in report["rosout"]]
    assert any(text.startswith("ROS 2 node /prime on rclpy (rmw_fastrtps_cpp)") for text in lines), lines[:5]
    assert any("QoS mismatch on /prime/mode_request" in text for _, level, text in report["rosout"]
               if level == 30)  # WARN


@pytest.mark.parametrize(("distro", "backend"), RCLPY)
def test_switch_mode_and_the_controller_manager_switch_and_report_it(sessions, distro, backend):
    switching = sessions[distro, backend][0]["switching"]
    for step in switching["steps"]:
        assert step["success"], step
    by_mode = [(s["asked"], s.get("active_mode"), s["listed_active"]) for s in switching["steps"][:3]]
    assert by_mode == [(mode, mode, ["joint_state_broadcaster", f"{mode.lower()}_controller"])
                       for mode in ("DAMPING", "STANDBY", "DAMPING")]
    assert [s["listed_active"][-1] for s in switching["steps"][3:]] == ["standby_controller", "damping_controller"]
    assert not switching["refused"]["ok"] and "nonsense_controller" in switching["refused"]["message"]
    listed = {c["name"]: c for c in switching["controllers"]}
    assert set(listed) == {"joint_state_broadcaster", "zero_torque_controller", "damping_controller",
                           "standby_controller", "locomotion_controller", "remote_policy_controller"}
    assert listed["damping_controller"]["claimed"] == 14 * 5


@pytest.mark.parametrize(("distro", "backend"), RCLPY)
def test_a_trajectory_goal_is_followed_within_its_tolerances(sessions, distro, backend):
    trajectory = sessions[distro, backend][0]["trajectory"]
    assert trajectory["remote"]["success"], trajectory["remote"]
    followed = trajectory["followed"]
    assert followed["accepted"] and followed["status"] == 4 and followed["error_code"] == 0, followed  # SUCCEEDED
    assert followed["feedback"] > 10
    assert max(abs(e) for errors in followed["feedback_errors"] for e in errors) <= 0.1
    final = np.array(trajectory["goal"]["points"][-1])
    assert np.all(np.abs(np.array(followed["after"][0]) - final) <= 0.02)
    # The joint states themselves stay between the points, within the path tolerance.
    points, during = np.array(trajectory["goal"]["points"]), np.array(followed["during"])
    assert len(during) > 100
    assert np.all(during >= np.minimum(points.min(axis=0), during[0]) - 0.1)
    assert np.all(during <= np.maximum(points.max(axis=0), during[0]) + 0.1)


@pytest.mark.parametrize(("distro", "backend"), RCLPY)
def test_a_cancelled_goal_stops_the_arm(sessions, distro, backend):
    cancelled = sessions[distro, backend][0]["trajectory"]["cancelled"]
    assert cancelled["accepted"] and cancelled["status"] == 5, cancelled  # CANCELED
    after = np.array(cancelled["after"])
    assert len(after) >= 150
    assert np.all(np.abs(after[-1] - after[len(after) // 4]) < 0.01)  # still


@pytest.mark.parametrize(("distro", "backend"), RCLPY)
def test_a_goal_outside_the_limits_is_rejected(sessions, distro, backend):
    assert sessions[distro, backend][0]["trajectory"]["out_of_limits_accepted"] is False


@pytest.mark.parametrize("distro", ROS_DISTROS)
def test_prime_is_installed_with_its_extra_beside_rclpy(ros_clients, distro):
    """The client environment has Prime as `pip install 'humanoid-prime[ros-<distro>]'` installs it (the sessions
    above run this source tree over it): the installed package imports beside rclpy and declares the extra."""
    client = ros_clients[distro]
    done = subprocess.run([client["python"], "-c",
                           "import importlib.metadata as m, humanoid_prime, rclpy; print(humanoid_prime.__file__); "
                           "print('\\n'.join(m.requires('humanoid-prime')))"],
                          env=ros_environment(client, 0), capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    where, *requires = done.stdout.splitlines()
    assert "/site-packages/humanoid_prime/" in where
    prefix = "ros-jazzy-" if distro == "jazzy" else "ros-"
    assert f'{prefix}rclpy[fastrtps]; extra == "ros-{distro}"' in requires


@pytest.mark.parametrize(("distro", "backend"), RCLPY)
def test_mit_commands_and_mode_requests_reach_the_rclpy_node(sessions, distro, backend):
    report, summary, _ = sessions[distro, backend]
    assert report["topics_in"]["modes_after"] == ["REMOTE", "DAMPING"]
    topics = summary["dds"]["topics"]
    assert topics["/remote_policy_controller/command"]["received"] == report["topics_in"]["sent_commands"]
    assert topics["/remote_policy_controller/command"]["refused"] == 0
    assert topics["/prime/mode_request"]["received"] == 1 and topics["/prime/mode_request"]["refused"] == 0

