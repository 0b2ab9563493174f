"""``prime sim`` on a terminal: the live table, mode keys, and a terminal left as it was found."""

import contextlib
import json
import os
import pty
import re
import select
import signal
import sys
import termios
import time

import pytest

ANSI = re.compile(rb"\x1b\[[0-9;?]*[A-Za-z]")


class Terminal:
    """``prime sim`` running on a pseudo-terminal."""

    def __init__(self, *args: str) -> None:
        self.pid, self.fd = pty.fork()
        if self.pid == 0:  # the child: become prime
            env = dict(os.environ, COLUMNS="160", LINES="40")
            os.execve(sys.executable, [sys.executable, "-m", "humanoid_prime.cli", "sim", *args], env)
        self.output = b""

    def screen(self) -> bytes:
        """The output without terminal control sequences."""
        return ANSI.sub(b"", self.output)

    def read_until(self, text: bytes, timeout: float = 20.0) -> None:
        deadline = time.monotonic() + timeout
        while text not in self.screen():
            assert time.monotonic() < deadline, f"{text!r} never appeared in {self.screen()[-2000:]!r}"
            ready, _, _ = select.select([self.fd], [], [], 0.1)
            if ready:
                self.output += os.read(self.fd, 65536)

    def cooked(self) -> bool:
        return bool(termios.tcgetattr(self.fd)[3] & termios.ICANON)

    def wait(self, timeout: float = 20.0) -> int:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if select.select([self.fd], [], [], 0.1)[0]:
                with contextlib.suppress(OSError):  # EIO once the child has closed the terminal
                    self.output += os.read(self.fd, 65536)
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid:
                return os.waitstatus_to_exitcode(status)
        os.kill(self.pid, signal.SIGKILL)
        pytest.fail("prime sim did not exit")

    def close(self) -> None:
        os.close(self.fd)


@pytest.fixture()
def terminal(tmp_path):
    started = []

    def start(*args: str) -> Terminal:
        term = Terminal("--socket", str(tmp_path / "control.sock"), "--summary", str(tmp_path / "summary.json"), *args)
        started.append(term)
        return term

    yield start
    for term in started:
        term.close()


def test_number_keys_switch_modes_and_q_quits_leaving_the_terminal_cooked(terminal, tmp_path):
    term = terminal("--mode", "DAMPING")
    term.read_until(b"mode DAMPING")  # the live table is up, the keys are read
    assert not term.cooked()
    os.write(term.fd, b"3")
    term.read_until(b"operator: STANDBY")
    os.write(term.fd, b"q")
    assert term.wait() == 0
    assert term.cooked()
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["modes_visited"] == ["ZERO_TORQUE", "DAMPING", "STANDBY"]
    assert summary["stopped_by"] == "operator"


def test_sigterm_stops_the_run_cleanly_and_restores_the_terminal(terminal, tmp_path):
    term = terminal("--mode", "STANDBY")
    term.read_until(b"q quit")
    assert not term.cooked()
    os.kill(term.pid, signal.SIGTERM)
    assert term.wait() == 0
    assert term.cooked()
    assert json.loads((tmp_path / "summary.json").read_text())["stopped_by"] == "interrupt"
