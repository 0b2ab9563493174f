"""The control socket: mode requests and SDO from a second terminal reach the running instance."""

import subprocess
import sys

import pytest

from humanoid_prime.cli import main
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.socket import ControlServer, SocketSdoClient, send_mode_request


class RecordingSdo:
    def __init__(self):
        self.objects = {(3, 0x2382, 1): b"\x1e\x00\x00\x00"}

    def sdo_read(self, position, index, sub_index):
        try:
            return self.objects[(position, index, sub_index)]
        except KeyError:
            raise PrimeError(f"ring {position}: SDO abort 0x06020000 on 0x{index:04X}:{sub_index:02X}") from None

    def sdo_write(self, position, index, sub_index, data):
        self.objects[(position, index, sub_index)] = data


def recorder(requested: list[Mode]):
    """A switch handler that records the modes asked for and reports each as requested."""
    def switch(mode: Mode, wait: float) -> dict:
        requested.append(mode)
        return {"mode": mode.value, "outcome": "requested"}
    return switch


@pytest.fixture
def server(tmp_path):
    requested: list[Mode] = []
    sdo = RecordingSdo()
    with ControlServer(recorder(requested), tmp_path / "control.sock", sdo=sdo) as srv:
        yield srv, requested, sdo


def test_mode_request_is_handed_to_the_manager(server):
    srv, requested, _ = server
    assert send_mode_request(Mode.STANDBY, srv.path)["mode"] == "STANDBY"
    assert requested == [Mode.STANDBY]


def test_the_wait_goes_to_the_switch_handler_and_its_outcome_comes_back(tmp_path):
    asked = []

    def switch(mode, wait):
        asked.append((mode, wait))
        return {"mode": mode.value, "outcome": "fell_back", "reason": "fell back to DAMPING: standby failed"}

    with ControlServer(switch, tmp_path / "c.sock") as srv:
        answer = send_mode_request(Mode.STANDBY, srv.path, wait=3.0)
        assert main(["switch", "STANDBY", "--socket", str(srv.path), "--timeout", "2"]) == 1
    assert asked == [(Mode.STANDBY, 3.0), (Mode.STANDBY, 2.0)]
    assert answer["outcome"] == "fell_back" and "standby failed" in answer["reason"]


def test_a_wait_beyond_the_limit_is_refused(tmp_path):
    with ControlServer(recorder([]), tmp_path / "c.sock") as srv, pytest.raises(PrimeError, match="wait must be"):
        send_mode_request(Mode.STANDBY, srv.path, wait=1e9)


def test_controller_names_are_accepted(server):
    srv, requested, _ = server
    assert main(["switch", "damping_controller", "--socket", str(srv.path)]) == 0
    assert requested == [Mode.DAMPING]


def test_prime_reset_asks_the_running_instance_and_lists_the_latched_faults(tmp_path, capsys):
    asked = []

    def reset():
        asked.append(True)
        return ["left_elbow_pitch (ring 3): fault, statusword 4616 (0x1208), error 0x8500"]

    with ControlServer(path=tmp_path / "control.sock", reset=reset) as srv:
        assert main(["reset", "--socket", str(srv.path)]) == 0
    assert asked == [True]
    out = capsys.readouterr().out
    assert out.startswith("reset sent to 1 faulted drive:\n  left_elbow_pitch (ring 3): fault")


def test_prime_reset_on_an_instance_without_latching_hardware_says_so(server, capsys):
    srv, _, _ = server
    assert main(["reset", "--socket", str(srv.path)]) == 1
    assert "drives no hardware that latches faults" in capsys.readouterr().err


def test_switch_without_a_running_instance_is_one_line_error(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "humanoid_prime", "switch", "STANDBY",
                           "--socket", str(tmp_path / "none.sock")], capture_output=True, text=True)
    assert proc.returncode == 1
    assert proc.stderr.count("\n") == 1
    assert "no running prime instance" in proc.stderr


def test_unknown_mode_is_refused_before_sending(server, capsys):
    srv, requested, _ = server
    assert main(["switch", "WALK", "--socket", str(srv.path)]) == 1
    assert "unknown mode 'WALK'" in capsys.readouterr().err
    assert requested == []


def test_sdo_read_and_write_through_the_socket(server):
    srv, _, sdo = server
    client = SocketSdoClient(srv.path)
    assert client.sdo_read(3, 0x2382, 1) == b"\x1e\x00\x00\x00"
    client.sdo_write(3, 0x2383, 0, b"\x01")
    assert sdo.objects[(3, 0x2383, 0)] == b"\x01"


def test_sdo_abort_comes_back_as_one_error(server):
    srv, _, _ = server
    with pytest.raises(PrimeError, match="SDO abort 0x06020000"):
        SocketSdoClient(srv.path).sdo_read(3, 0x9999, 0)


def test_sdo_without_a_master_is_refused(tmp_path):
    with ControlServer(recorder([]), tmp_path / "c.sock") as srv, \
            pytest.raises(PrimeError, match="no EtherCAT master"):
        SocketSdoClient(srv.path).sdo_read(0, 0x2382, 1)


def test_second_server_on_a_live_socket_is_refused(server):
    srv, _, _ = server
    with pytest.raises(PrimeError, match="already listens"):
        ControlServer(None, srv.path).start()


def test_stale_socket_is_replaced(tmp_path):
    import socket

    path = tmp_path / "control.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as dead:  # a socket no process listens on any more
        dead.bind(str(path))
    requested: list[Mode] = []
    with ControlServer(recorder(requested), path):
        send_mode_request(Mode.REMOTE, path)
    assert requested == [Mode.REMOTE]
    assert not path.exists()


def test_a_file_that_is_not_a_socket_is_never_replaced(tmp_path):
    path = tmp_path / "keep.txt"
    path.write_text("the operator's notes\n")
    with pytest.raises(PrimeError, match="not a socket"):
        ControlServer(recorder([]), path).start()
    assert path.read_text() == "the operator's notes\n"


def test_a_folder_or_an_overlong_path_is_refused_before_anything_starts(tmp_path):
    with pytest.raises(PrimeError, match="is a folder"):
        ControlServer(recorder([]), tmp_path).start()
    with pytest.raises(PrimeError, match="too long"):
        ControlServer(recorder([]), tmp_path / ("x" * 120) / "c.sock").start()


def test_state_answers_the_latest_joints_mode_and_flags(tmp_path):
    import numpy as np

    from humanoid_prime.config.robot import load_robot
    from humanoid_prime.control.flags import Level
    from humanoid_prime.control.topics import (
        CONTROL_MODE,
        JOINT_STATES,
        SAFETY_STATUS,
        ControlMode,
        JointState,
        SafetyStatus,
        Snapshot,
        TopicBus,
    )
    from humanoid_prime.runtime.socket import request_state

    robot = load_robot()
    topics = TopicBus()
    snapshot = Snapshot(topics, robot.names)
    position = np.linspace(-0.5, 0.5, robot.n)
    position[3] = np.nan  # a joint not measured (the other bus of a single-bus run)
    topics.publish(JOINT_STATES, JointState(1.5, robot.names, position, np.zeros(14), np.zeros(14)))
    topics.publish(CONTROL_MODE, ControlMode("STANDBY", "standby_controller", 1.0))
    topics.publish(SAFETY_STATUS, SafetyStatus(False, {"dds/dropped": "3 dropped"}, 1.5, {"dds/dropped": Level.WARN}))
    with ControlServer(path=tmp_path / "control.sock", state=snapshot.as_dict):
        state = request_state(tmp_path / "control.sock")
    assert state["names"] == list(robot.names) and state["mode"] == "STANDBY" and state["stamp"] == 1.5
    assert state["position"][3] is None and state["position"][0] == -0.5
    assert state["flags"] == {"dds/dropped": "3 dropped"} and state["levels"] == {"dds/dropped": "WARN"}
