"""Shared fixtures: the bundled robot, loaded once, and a private CAN channel name."""

from __future__ import annotations

import uuid

import pytest

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
