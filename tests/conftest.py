"""Shared fixtures: the bundled robot, loaded once, a private CAN channel name, and whole sessions on the
doubles (``doubles.session``: the EtherCAT block on the master double, the wrists on emulated motors)."""

from __future__ import annotations

import contextlib
import uuid
from collections.abc import Iterator

import pytest

from doubles.session import DoubledRobot
from humanoid_prime.config.robot import Robot, load_robot


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
