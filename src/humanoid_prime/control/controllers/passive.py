"""The command of a run without mode controllers (a single-bus run, a calibration by hand): no command on any
joint (a NaN position, the rest zero), so each eRob holds its last target on its drive's own gains and each Sito
is limp; except the joints marked limp (``prime limp``, through the control socket), whose target follows the
joint at zero gains, so an eRob made limp in its registers builds no following error while it is swept by hand."""

from __future__ import annotations

import numpy as np

from humanoid_prime.config.robot import Robot
from humanoid_prime.control.controller import Controller
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.control.topics import TopicBus

PASSIVE_CONTROLLER = "passive_controller"


class PassiveController(Controller):
    releases = True

    def __init__(self) -> None:
        super().__init__(PASSIVE_CONTROLLER, None)

    def on_configure(self, robot: Robot, topics: TopicBus) -> None:
        self.names = robot.names
        self._lower, self._upper = robot.lower, robot.upper
        self.limp = np.zeros(robot.n, dtype=bool)
        self._follow = np.zeros(robot.n, dtype=bool)
        self._target = np.zeros(robot.n)

    def mark_limp(self, index: int, limp: bool) -> None:
        """From the next tick on (any thread), joint ``index`` follows where it is (``limp``) or has no command."""
        self.limp[index] = limp

    def update(self, now: float, dt: float, state: StateArrays, command: CommandArrays) -> None:
        command.data[1:] = 0.0
        command.position[:] = np.nan
        if self.limp.any():
            np.isfinite(state.position, out=self._follow)
            self._follow &= self.limp
            np.clip(state.position, self._lower, self._upper, out=self._target)
            np.copyto(command.position, self._target, where=self._follow)
