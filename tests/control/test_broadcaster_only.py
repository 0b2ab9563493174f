"""Single-bus runs: only the joint-state broadcaster, unowned joints unmeasured, commands left as "none"."""

import math

import numpy as np
import pytest

from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.control.hardware import HardwareComponent
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.topics import JOINT_STATES
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import JOINT_STATE_BROADCASTER, Mode


class Wrists(HardwareComponent):
    """Owns the four Sito joints at a fixed pose and records what it was told to do."""

    def __init__(self, robot):
        super().__init__("wrists", robot, robot.hardware.sito_joints)
        self.written = []

    def read(self, now, state):
        state.position[self.indices] = 0.25

    def write(self, now, command):
        self.written.append(command.data[:, self.indices].copy())


@pytest.fixture
def manager(robot):
    wrists = Wrists(robot)
    mgr = ControllerManager(robot, [wrists], load_controllers(robot.names), broadcaster_only=True)
    mgr.start()
    yield mgr, wrists
    mgr.shutdown()


def test_only_the_broadcaster_starts(manager):
    mgr, _ = manager
    assert [name for name, _ in mgr.stages if not name.startswith("hardware")] == [JOINT_STATE_BROADCASTER,
                                                                                   "controllers activated"]
    assert mgr.active_mode is None


def test_unowned_joints_are_published_as_not_measured(manager, robot):
    mgr, _ = manager
    seen = []
    mgr.topics.subscribe(JOINT_STATES, lambda m: seen.append(m.position.copy()))
    mgr.tick()
    q = seen[-1]
    assert q[robot.index("left_wrist_roll")] == 0.25
    assert math.isnan(q[robot.index("left_elbow_pitch")])


def test_commands_are_no_command(manager):
    mgr, wrists = manager
    mgr.tick()
    command = wrists.written[-1]
    assert np.isnan(command[0]).all() and (command[1:] == 0.0).all()


def test_mode_switch_is_refused(manager):
    mgr, _ = manager
    with pytest.raises(PrimeError, match="only the joint-state broadcaster"):
        mgr.request_mode(Mode.STANDBY)


def test_partial_ownership_is_refused_for_full_runs(robot):
    with pytest.raises(PrimeError, match="no hardware component owns"):
        ControllerManager(robot, [Wrists(robot)], load_controllers(robot.names))
