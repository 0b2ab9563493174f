"""`prime limp` through the control socket: limp while waiting, restored on Enter, SIGTERM and Ctrl-C, and after
SIGKILL by the next command that reaches the drive."""

import json
import signal
import subprocess
import sys
import time

import pytest

from doubles.mailboxes import DriveMailboxes
from doubles.process import popen
from humanoid_prime.cli import main
from humanoid_prime.errors import PrimeError
from humanoid_prime.runtime.socket import ControlServer, request
from humanoid_prime.virtual.netns import EmulatedRing, netns_unavailable_reason


@pytest.fixture
def served(tmp_path):
    drives = DriveMailboxes()
    drives.limp_marks = []

    def joint_limp(position, limp):
        drives.limp_marks.append((position, limp))
        return f"ring{position}"

    with ControlServer(None, tmp_path / "control.sock", sdo=drives, joint_limp=joint_limp) as srv:
        yield srv, drives


def test_limp_for_a_scripted_time_then_restores(served, capsys):
    srv, drives = served
    before = dict(drives.values[3])
    assert main(["limp", "3", "--seconds", "0", "--socket", str(srv.path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["joint"] == "left_elbow_pitch"
    assert out["limp"]["pos_reg"] == 0 and out["limp"]["gate"] == 1
    assert out["restored"] == {key: value for key, value in before.items() if key != "window"}
    assert drives.values[3] == before
    assert drives.limp_marks == [(3, True), (3, False)]


def test_limp_is_refused_where_a_controller_commands_the_erob(tmp_path, capsys):
    drives = DriveMailboxes()
    before = dict(drives.values[3])
    with ControlServer(lambda mode: None, tmp_path / "c.sock", sdo=drives) as srv:
        assert main(["limp", "3", "--seconds", "0", "--socket", str(srv.path)]) == 1
    assert "needs a running `prime calibrate`" in capsys.readouterr().err
    assert drives.values[3] == before and drives.log == []


def test_damping_argument_sets_the_velocity_gain(served, capsys):
    srv, drives = served
    seen = []
    original = drives.sdo_write

    def spy(position, index, sub_index, data):
        original(position, index, sub_index, data)
        seen.append(dict(drives.values[position]))

    drives.sdo_write = spy
    assert main(["limp", "3", "2.0", "--seconds", "0", "--socket", str(srv.path)]) == 0
    assert any(s["pos_reg"] == 0 and s["vel_reg"] == 19 and s["gate"] == 1 for s in seen)  # 2.0 / 0.1063


def test_unknown_ring_position_is_one_line_error(served, capsys):
    srv, _ = served
    assert main(["limp", "12", "--socket", str(srv.path)]) == 1
    assert "ring position 12 is not an eRob" in capsys.readouterr().err


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signal_while_waiting_restores_the_snapshot(served, sig):
    srv, drives = served
    before = dict(drives.values[6])
    proc = popen([sys.executable, "-m", "humanoid_prime", "limp", "6", "--socket", str(srv.path)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 20
    while drives.values[6]["pos_reg"] != 0 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert drives.values[6]["pos_reg"] == 0, "the joint never went limp"
    proc.send_signal(sig)
    proc.wait(timeout=20)  # stdin stays open: the signal, not an end of input, ends the limp
    out, err = proc.communicate()
    assert proc.returncode == 130, err
    assert drives.values[6] == before
    assert "restored" in out


def test_enter_restores_the_snapshot(served):
    srv, drives = served
    before = dict(drives.values[0])
    proc = subprocess.run([sys.executable, "-m", "humanoid_prime", "limp", "0", "--socket", str(srv.path)],
                          input="\n", capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0, proc.stderr
    assert "damped-limp: read back gate=1 Kp(pos_reg)=0" in proc.stdout
    assert drives.values[0] == before


REASON = netns_unavailable_reason()
GAINS = ("gate", "pos_reg", "vel_reg", "integral")


@pytest.mark.netns
@pytest.mark.skipif(REASON is not None, reason=f"no emulated ring: {REASON}")
def test_a_drive_a_killed_limp_left_limp_is_restored_by_the_next_run_that_opens_the_ring(tmp_path):
    """`prime limp` and the single-bus run it went through both killed outright (SIGKILL: no exit path runs), so the
    drive stays limp in its own memory, as a real one does. The next run that opens the ring restores it from the
    record the limp left, before anything else writes a drive, and says so; the record is then gone."""
    socket = tmp_path / "control.sock"
    bringup = [sys.executable, "-m", "humanoid_prime", "bringup", "--backends", "ec", "--socket", str(socket),
               "--no-live"]
    with EmulatedRing(slaves=10) as ring:
        def gains() -> dict[str, int]:
            drive = ring.control.slave(3)["drive"]
            return {name: drive[name] for name in GAINS}

        before = gains()
        owner = popen([*bringup, "--interface", ring.master_interface], stdout=subprocess.DEVNULL,
                      stderr=subprocess.PIPE, text=True)
        limp = None
        try:
            deadline = time.monotonic() + 60
            while not _answers(socket):
                assert owner.poll() is None and time.monotonic() < deadline, owner.stderr.read()
                time.sleep(0.1)
            limp = popen([sys.executable, "-m", "humanoid_prime", "limp", "3", "--socket", str(socket)],
                         stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            while gains()["pos_reg"] != 0:
                assert limp.poll() is None and time.monotonic() < deadline, "the joint never went limp"
                time.sleep(0.05)
        finally:
            for process in (limp, owner):
                if process is not None:
                    process.kill()
                    process.wait(timeout=30)
        assert gains() == {**before, "gate": 1, "pos_reg": 0}  # left limp
        next_run = subprocess.run([*bringup, "--interface", ring.master_interface, "--duration", "0.5"],
                                  capture_output=True, text=True, timeout=120)
        assert next_run.returncode == 0, next_run.stderr
        assert gains() == before
        assert (f"ring 3 (left_elbow_pitch) was left limp by `prime limp 3` (pid {limp.pid}, " in next_run.stderr
                and "which ended without restoring it: restored its gains as found, "
                    + " ".join(f"{name}={value}" for name, value in before.items()) in next_run.stderr)
        again = subprocess.run([*bringup, "--interface", ring.master_interface, "--duration", "0.5"],
                               capture_output=True, text=True, timeout=120)
        assert again.returncode == 0 and "was left limp" not in again.stderr, again.stderr


def _answers(socket) -> bool:
    try:
        return bool(request(socket, {"op": "ping"}, timeout=0.5)["ready"])
    except PrimeError:
        return False
