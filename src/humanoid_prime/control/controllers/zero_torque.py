"""ZERO_TORQUE: no stiffness, no damping, no effort on any joint (true limp on both families).

The position target follows the measured position (within the joint limits, as every target must be) so an
eRob CSP target never drifts away from the joint while the arm is moved by hand; a joint whose measurement is
not finite keeps its last valid target.
"""

from __future__ import annotations

from humanoid_prime.config.robot import Robot
from humanoid_prime.control._tick import FollowMeasured
from humanoid_prime.control.controller import Controller
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.control.topics import TopicBus
from humanoid_prime.modes import Mode


class ZeroTorqueController(Controller):
    def __init__(self) -> None:
        super().__init__(Mode.ZERO_TORQUE.controller, Mode.ZERO_TORQUE)

    def on_configure(self, robot: Robot, topics: TopicBus) -> None:
        self._follow = FollowMeasured(robot.lower, robot.upper)

    def update(self, now: float, dt: float, state: StateArrays, command: CommandArrays) -> None:
        self._follow.run(state.position, command.data)
