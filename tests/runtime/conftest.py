"""A whole session without a network: the EtherCAT block on the master double, the Sito block on emulated
motors over a private virtual CAN channel (``doubles.session``)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import pytest

from doubles.session import DoubledRobot


@pytest.fixture
def doubled(robot, channel, monkeypatch) -> Iterator[DoubledRobot]:
    with contextlib.ExitStack() as stack:
        yield DoubledRobot(robot, channel, monkeypatch, stack)
