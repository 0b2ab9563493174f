"""DDS tests run on the loopback interface, each in a ROS 2 domain of its own, so parallel runs on one machine
(or a network the machine is on) never hear each other."""

from __future__ import annotations

import itertools
import os
import threading
import time
from collections.abc import Callable

import pytest

from humanoid_prime.config.controllers import load_controllers

# Cyclone DDS on loopback with multicast, plus a unicast peer for participants that do not multicast.
LOOPBACK = ('<CycloneDDS><Domain Id="any"><General><Interfaces><NetworkInterface name="lo" multicast="true"/>'
            '</Interfaces><AllowMulticast>true</AllowMulticast></General><Discovery><ParticipantIndex>auto'
            '</ParticipantIndex><MaxAutoParticipantIndex>60</MaxAutoParticipantIndex><Peers>'
            '<Peer address="127.0.0.1"/></Peers></Discovery></Domain></CycloneDDS>')
_domains = itertools.count(1 + os.getpid() % 150)


@pytest.fixture
def domain(monkeypatch) -> int:
    """A ROS 2 domain for this test alone (set as ROS_DOMAIN_ID for children too), on loopback."""
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK)
    number = next(_domains) % 200 + 1
    monkeypatch.setenv("ROS_DOMAIN_ID", str(number))
    return number


@pytest.fixture(scope="session")
def config(sim_robot):
    return load_controllers(sim_robot.names)


def wait_for(condition: Callable[[], bool], timeout: float = 30.0, poll: Callable[[], None] | None = None) -> bool:
    """Poll ``condition`` until it holds; the timeout only bounds a failure (nothing is timed)."""
    deadline = time.monotonic() + timeout
    event = threading.Event()
    while time.monotonic() < deadline:
        if poll is not None:
            poll()
        if condition():
            return True
        event.wait(0.01)
    return condition()
