"""Every way out of a process disables every wrist: normal exit, an exception, SIGINT, SIGTERM.

The wrists are emulated in this process and the system runs in a child process; they meet on a
udp_multicast CAN bus, as an emulated robot and its controller would.
"""

from __future__ import annotations

import random
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from doubles.process import popen
from doubles.sito import SITO_IDS, wait_until
from humanoid_prime.virtual.sito import SitoEmulator

CHILD = Path(__file__).with_name("exit_child.py")
pytest.importorskip("msgpack", reason="python-can's udp_multicast interface needs msgpack")


@pytest.fixture
def emulated_robot(robot) -> Iterator[tuple[SitoEmulator, str, int]]:
    group = f"239.{random.randint(1, 254)}.{random.randint(1, 254)}.{random.randint(1, 254)}"
    port = random.randint(20000, 60000)
    bus = can.Bus(interface="udp_multicast", channel=group, port=port)
    emulator = SitoEmulator.for_robot(robot, bus)
    emulator.start()
    yield emulator, group, port
    emulator.stop()
    bus.shutdown()


def run_child(emulated_robot, how: str, send_signal: int | None = None) -> subprocess.CompletedProcess:
    emulator, group, port = emulated_robot
    child = popen([sys.executable, str(CHILD), group, str(port), how],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        if send_signal is not None:
            assert child.stdout.readline().strip() == "active"
            wait_until(lambda: all(emulator.motors[i].kp > 0 for i in SITO_IDS), "the child's gains")
            child.send_signal(send_signal)
        out, err = child.communicate(timeout=30)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    return subprocess.CompletedProcess(child.args, child.returncode, out, err)


def assert_all_disabled(emulator: SitoEmulator) -> None:
    wait_until(lambda: all(emulator.motors[i].disables >= 1 for i in SITO_IDS), "a disable for every wrist")
    time.sleep(0.05)
    assert all(not emulator.motors[i].enabled for i in SITO_IDS)


def test_normal_exit_disables_every_wrist(emulated_robot):
    result = run_child(emulated_robot, "normal")
    assert result.returncode == 0, result.stderr
    assert_all_disabled(emulated_robot[0])


def test_exit_by_exception_disables_every_wrist(emulated_robot):
    result = run_child(emulated_robot, "exception")
    assert "the control loop failed" in result.stderr
    assert_all_disabled(emulated_robot[0])


def test_sigint_disables_every_wrist(emulated_robot):
    result = run_child(emulated_robot, "signal", signal.SIGINT)
    assert "KeyboardInterrupt" in result.stderr
    assert_all_disabled(emulated_robot[0])


def test_sigterm_disables_every_wrist(emulated_robot):
    result = run_child(emulated_robot, "signal", signal.SIGTERM)
    assert result.returncode == -signal.SIGTERM
    assert_all_disabled(emulated_robot[0])
