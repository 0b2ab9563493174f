"""Shared fixtures: the bundled robot, loaded once, a private CAN channel name, and whole sessions on the
doubles (``doubles.session``: the EtherCAT block on the master double, the wrists on emulated motors)."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import uuid
from collections.abc import Iterator

import pytest
from hypothesis import settings

from doubles.session import DoubledRobot
from humanoid_prime.config.robot import Robot, load_robot

# The suite's groups, its guard against a real-time test outside them, and its rules under CI (docs/development.md,
# Tests).
pytest_plugins = ["suite_rules"]

# Property tests judge values, never time: hypothesis's per-example deadline would fail them on a busy machine.
settings.register_profile("prime", deadline=None)
settings.load_profile("prime")


def pytest_configure(config) -> None:
    """Every command a test runs reads the configuration of an empty config folder of the suite's own (the
    bundled templates), never the folder of the user who runs the suite; tests that need a robot folder make
    one (``PRIME_CONFIG_DIR`` / ``XDG_CONFIG_HOME`` in their own environment)."""
    os.environ["XDG_CONFIG_HOME"] = tempfile.mkdtemp(prefix="prime-suite-config-")
    for name in ("PRIME_CONFIG_DIR", "PRIME_ROBOT"):
        os.environ.pop(name, None)


@pytest.fixture(autouse=True)
def control_socket(monkeypatch) -> Iterator[None]:
    """Each test's commands answer on a control socket of their own (their children inherit it): a `prime sim`
    refuses to start beside another instance on its socket, and this machine may run other suites at once."""
    folder = tempfile.mkdtemp(prefix="prime-sock-")  # short: a UNIX socket path holds 107 bytes
    monkeypatch.setenv("PRIME_CONTROL_SOCKET", os.path.join(folder, "control.sock"))
    yield
    shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture(scope="session")
def robot() -> Robot:
    return load_robot()


@pytest.fixture(scope="session")
def sim_robot() -> Robot:
    return load_robot(use_sim=True)


@pytest.fixture
def channel() -> str:
    """A python-can channel no other test uses."""
    return f"sito-test-{uuid.uuid4().hex}"


@pytest.fixture
def doubled(robot, channel, monkeypatch) -> Iterator[DoubledRobot]:
    with contextlib.ExitStack() as stack:
        yield DoubledRobot(robot, channel, monkeypatch, stack)
