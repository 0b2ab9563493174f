"""Prime and a policy sender in separate processes over DDS, both in the namespace ``lab``: ``prime sim --dds
--dds-control --namespace lab`` in one, ``prime remote --namespace lab`` in another. The arm follows the
wave; when the sender dies, REMOTE goes stale and damps."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import pytest
from cyclonedds.internal import InvalidSample

from doubles.process import popen, stop
from humanoid_prime.dds import messages as msg
from humanoid_prime.dds.node import DdsNode

from .conftest import wait_for

PRIME = [sys.executable, "-m", "humanoid_prime"]


@pytest.fixture
def sim(domain, tmp_path):
    """``prime sim --dds --dds-control`` in DAMPING until the test ends it with Ctrl-C; yields its summary's path."""
    summary = tmp_path / "sim.json"
    process = popen([*PRIME, "sim", "--dds", "--dds-control", "--namespace", "lab", "--mode", "DAMPING",
                     "--duration", "300", "--summary", str(summary)],
                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    yield process, summary
    stop(process)


def remote_status(statuses: list) -> msg.DiagnosticStatus | None:
    for array in reversed(statuses):
        for status in array.status:
            if status.name == "prime/remote_policy_controller":
                return status
    return None


def test_a_remote_process_drives_the_simulated_arm_and_its_death_makes_remote_damp(sim, domain, tmp_path):
    process, summary_path = sim
    done = subprocess.run([*PRIME, "remote", "--namespace", "lab", "--duration", "10", "--json", "--wait", "120"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    remote = json.loads(done.stdout)
    assert remote["modes_seen"][-1] == "REMOTE"
    assert remote["joint_states_received"] > 0
    tracking = remote["tracking"]
    assert tracking["samples"] > 100
    # The waving joints swing as commanded (elbows and wrist pitches, 0.3 rad at 0.5 Hz) ...
    assert 0.6 < tracking["range_ratio"] < 1.4, tracking
    # ... and, once the steady gravity sag of a stiffness-20 joint is taken out, follow the wave closely.
    assert tracking["residual_rms_rad"] < 0.1, tracking
    assert tracking["offset_rad"] < 0.25, tracking

    # A sender that is killed mid-stream: REMOTE flags the stale stream and damps.
    with DdsNode(domain) as node:
        safety = node.reader("/lab/safety_status", msg.DiagnosticArray, latched=True, depth=1)
        statuses: list = []

        def poll() -> None:
            statuses.extend(s for s in safety.take(N=10) if not isinstance(s, InvalidSample))

        sender = popen([*PRIME, "remote", "--namespace", "lab", "--amplitude", "0", "--wait", "120"],
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            assert wait_for(lambda: (s := remote_status(statuses)) is not None and s.level == 0, timeout=120,
                            poll=poll), "REMOTE never saw the second sender's commands"
            statuses.clear()
            os.kill(sender.pid, signal.SIGKILL)
            sender.wait(timeout=30)
            assert wait_for(lambda: (s := remote_status(statuses)) is not None and s.level == 1, timeout=60,
                            poll=poll)
        finally:
            if sender.poll() is None:
                sender.kill()
    stale = remote_status(statuses)
    assert [kv.key for kv in stale.values] == ["stale"]
    assert "no command on /remote_policy_controller/command for more than 100 ms; damp" in stale.message

    stop(process)
    out = process.stdout.read()  # the startup line names the node and says control from the graph is on
    assert "node /lab/prime" in out and "control from the graph ON" in out
    summary = json.loads(summary_path.read_text())
    received = summary["dds"]["topics"]["/remote_policy_controller/command"]
    assert received["received"] >= remote["commands_sent"] and received["refused"] == 0
    assert summary["dds"]["topics"]["/prime/joint_states"]["dropped"] == 0
    assert summary["fallbacks"] == []
