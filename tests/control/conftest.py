"""Fixtures of the control core tests: the bundled controllers file, a settable clock, an ideal plant and a
started manager over it."""

from __future__ import annotations

import pytest

from doubles.control import Clock, Plant
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.control.manager import ControllerManager


@pytest.fixture(scope="session")
def config(robot):
    return load_controllers(robot.names)


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def plant(robot) -> Plant:
    return Plant("plant", robot.names)


@pytest.fixture
def manager(robot, config, plant, clock):
    """A started manager (ZERO_TORQUE active) on one plant owning all 14 joints."""
    m = ControllerManager(robot, [plant], config, update_rate=100.0, clock=clock, sleep=clock.sleep)
    m.start()
    yield m
    m.shutdown()
