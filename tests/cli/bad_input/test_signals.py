"""Ctrl-C while a command starts (its imports, its checks): exit 130 with one line saying it was interrupted,
or, if the signal came before Python could handle it, death by SIGINT; never a traceback, never a half-written
file. Child processes (a signal needs a process of its own): a handful only."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest

from cli.bad_input.harness import TOTALS
from doubles.process import popen

COMMANDS = {
    "calibrate": ["calibrate", "--output", "{tmp}/cal.yaml"],
    "sim": ["sim", "--fast", "--summary", "{tmp}/summary.json"],
    "plot": ["plot", "{tmp}/none.mcap"],
    "bench": ["bench", "--only", "tick", "--output", "{tmp}/bench.json"],
}


@pytest.mark.parametrize("after_s", [0.15, 0.6], ids=["importing", "checking"])
@pytest.mark.parametrize("command", COMMANDS)
def test_ctrl_c_while_a_command_starts_is_one_line_and_exit_130(tmp_path, command, after_s):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in COMMANDS[command]]
    child = popen([sys.executable, "-m", "humanoid_prime", *argv], stdout=subprocess.DEVNULL,
                  stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    time.sleep(after_s)  # any moment will do: each outcome below is one the user may see
    child.send_signal(signal.SIGINT)
    try:
        _, err = child.communicate(timeout=120)
    finally:
        if child.poll() is None:
            child.kill()
    lines = err.strip().splitlines()
    if "Traceback" in err:  # only from the interpreter's own start, before any of the package's code runs
        assert "humanoid_prime" not in err and lines[-1] == "KeyboardInterrupt", err
        assert child.returncode in (1, -signal.SIGINT), (child.returncode, err)
        TOTALS["correct refusal"] += 1
        return
    # 1: refused before the signal came; 0: a simulation already running, which Ctrl-C ends as its normal stop
    assert child.returncode in (-signal.SIGINT, 1, 130) or (command, child.returncode) == ("sim", 0), \
        (child.returncode, err)
    if child.returncode == 130:
        assert lines in (["prime: interrupted"], [f"prime {command}: interrupted"]), err  # before/after argv
    elif child.returncode == 1:
        assert len(lines) == 1, err
    assert not list(tmp_path.glob(".*.tmp")) and not (tmp_path / "cal.yaml").exists()
    TOTALS["correct refusal"] += 1
