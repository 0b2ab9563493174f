"""Ctrl-C while a command starts (the command line loading, the modules a command imports for its work): exit 130
with one line saying it was interrupted; never a traceback, never a half-written file, never a command that goes
on. Child processes (a signal needs a process of its own), each sending itself the SIGINT at one moment of its
start-up, so that every case lands where it says whatever the load of the machine: a handful only."""

from __future__ import annotations

import subprocess
import sys

import pytest

from cli.bad_input.harness import TOTALS
from doubles.process import popen

COMMANDS = {
    "calibrate": ["calibrate", "--output", "{tmp}/cal.yaml"],
    "sim": ["sim", "--fast", "--summary", "{tmp}/summary.json"],
    "plot": ["plot", "{tmp}/none.mcap"],
    "bench": ["bench", "--only", "tick", "--output", "{tmp}/bench.json"],
}

# The moment, as the import the SIGINT comes with, and where Python handles it: in the importing code, or in a
# weakref callback, whose exceptions Python reports and drops (importlib runs one as every import ends).
MOMENTS = {
    "loading": ("humanoid_prime.cli", "plain"),  # the command line itself, before it watches for Ctrl-C
    "importing": ("numpy", "plain"),  # a module the command needs (plot imports it only once it runs)
    "importing-in-a-weakref-callback": ("numpy", "callback"),
}

# `prime ARGS` (the installed script's entry point, loaded as the script loads it), sending itself a SIGINT as
# MODULE is first imported, handled WHERE says
CHILD = """
import signal, sys, weakref
from importlib.metadata import entry_points

module, where = sys.argv[1:3]
sys.argv = ["prime", *sys.argv[3:]]


class Dying:
    pass


def interrupt(*_):
    signal.raise_signal(signal.SIGINT)


def at(event, args):
    global module
    if event != "import" or args[0] != module:
        return
    module = None
    if where == "plain":
        interrupt()
        return
    dying = Dying()
    ref = weakref.ref(dying, interrupt)
    del dying  # its callback runs here


sys.addaudithook(at)
(script,) = entry_points(group="console_scripts", name="prime")
sys.exit(script.load()())
"""


@pytest.mark.parametrize("moment", MOMENTS)
@pytest.mark.parametrize("command", COMMANDS)
def test_ctrl_c_while_a_command_starts_is_one_line_and_exit_130(tmp_path, command, moment):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in COMMANDS[command]]
    child = popen([sys.executable, "-c", CHILD, *MOMENTS[moment], *argv], stdout=subprocess.DEVNULL,
                  stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        _, err = child.communicate(timeout=120)
    finally:
        if child.poll() is None:
            child.kill()
    said = "prime" if moment == "loading" else f"prime {command}"  # the command is named once it is known
    assert (child.returncode, err.splitlines()) == (130, [f"{said}: interrupted"])
    assert not list(tmp_path.glob(".*.tmp")) and not (tmp_path / "cal.yaml").exists()
    TOTALS["correct refusal"] += 1
