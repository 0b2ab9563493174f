"""Mode requests from a second terminal reach the running instance, and bad ones are refused."""

import subprocess
import sys

import pytest

from humanoid_prime.cli import main
from humanoid_prime.control.operator import ModeRequestServer, send_mode_request
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode


@pytest.fixture
def server(tmp_path):
    requested: list[Mode] = []
    with ModeRequestServer(requested.append, tmp_path / "mode.sock") as srv:
        yield srv, requested


def test_request_is_handed_to_the_manager(server):
    srv, requested = server
    assert send_mode_request(Mode.STANDBY, srv.path) == "ok STANDBY"
    assert requested == [Mode.STANDBY]


def test_controller_names_are_accepted(server):
    srv, requested = server
    main(["switch", "damping_controller", "--socket", str(srv.path)])
    assert requested == [Mode.DAMPING]


def test_switch_without_a_running_instance_is_one_line_error(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "humanoid_prime.cli", "switch", "STANDBY",
                           "--socket", str(tmp_path / "none.sock")], capture_output=True, text=True)
    assert proc.returncode == 1
    assert proc.stderr.strip().count("\n") == 0
    assert "no running prime sim or bringup" in proc.stderr


def test_unknown_mode_is_refused_before_sending(server, capsys):
    srv, requested = server
    assert main(["switch", "WALK", "--socket", str(srv.path)]) == 1
    assert "unknown mode 'WALK'" in capsys.readouterr().err
    assert requested == []


def test_second_server_on_a_live_socket_is_refused(server):
    srv, _ = server
    with pytest.raises(PrimeError, match="already listens"):
        ModeRequestServer(lambda m: None, srv.path).start()


def test_stale_socket_file_is_replaced(tmp_path):
    path = tmp_path / "mode.sock"
    path.write_text("")
    requested: list[Mode] = []
    with ModeRequestServer(requested.append, path):
        send_mode_request(Mode.REMOTE, path)
    assert requested == [Mode.REMOTE]
    assert not path.exists()
