"""``prime bringup --emulate --dds`` as root: the robot lives in a private network namespace, the ROS 2 node on
this machine's graph, where a participant outside the namespace reads its joint states."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from doubles.process import popen, stop
from humanoid_prime.dds import messages as msg
from humanoid_prime.dds.node import DdsNode, take
from humanoid_prime.virtual.netns import netns_unavailable_reason

from .conftest import wait_for

pytestmark = pytest.mark.netns
PRIME = [sys.executable, "-m", "humanoid_prime"]


@pytest.mark.skipif(os.geteuid() != 0 or netns_unavailable_reason() is not None,
                    reason="the host's graph from inside the emulation's namespace needs root")
def test_an_emulated_bringup_is_a_node_on_the_hosts_graph(domain, tmp_path, sim_robot):
    summary = tmp_path / "summary.json"
    with DdsNode(domain) as peer:
        joint_states = peer.reader("/prime/joint_states", msg.JointState, depth=100)
        process = popen([*PRIME, "bringup", "--emulate", "--dds", "--no-live", "--duration", "60", "--summary",
                         str(summary), "--socket", str(tmp_path / "control.sock")], stdout=subprocess.PIPE,
                        stderr=subprocess.STDOUT, text=True)
        got: list = []
        try:
            assert wait_for(lambda: len(got) >= 50, timeout=120, poll=lambda: got.extend(take(joint_states)))
        finally:
            stop(process)
    out = process.stdout.read()
    # What the bring-up itself did (a loaded machine can starve an emulated drive's watchdog) is other tests'
    # subject; this one is where its node was.
    assert summary.is_file(), out[-3000:]
    assert {tuple(s.name) for s in got} == {sim_robot.names}
    assert "private network namespace" not in out  # the node was not left inside
    assert json.loads(summary.read_text())["dds"]["topics"]["/prime/joint_states"]["published"] >= len(got)
