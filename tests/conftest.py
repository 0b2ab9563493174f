"""Shared fixtures: the bundled robot, loaded once."""

from __future__ import annotations

import pytest

from humanoid_prime.config.robot import Robot, load_robot


@pytest.fixture(scope="session")
def robot() -> Robot:
    return load_robot()


@pytest.fixture(scope="session")
def sim_robot() -> Robot:
    return load_robot(use_sim=True)
