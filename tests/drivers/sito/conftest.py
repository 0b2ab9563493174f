"""Fixtures of the Sito tests: rigs on private virtual CAN channels (``doubles.sito``)."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest

from doubles.sito import Rig
from humanoid_prime.config.robot import Robot


@pytest.fixture
def make_rig(robot: Robot) -> Iterator[Callable[..., Rig]]:
    rigs: list[Rig] = []

    def make(**options: object) -> Rig:
        rig = Rig(robot, **options)
        rigs.append(rig)
        return rig

    yield make
    for rig in rigs:
        rig.close()


@pytest.fixture
def rig(make_rig: Callable[..., Rig]) -> Rig:
    """An activated rig with the bundled robot, identity calibration and free inertia plants."""
    rig = make_rig()
    rig.activate()
    rig.sniffed()
    return rig
