"""STANDBY: hold a named pose with kp 20, kd 2 (DESIGN §2), reached by a smooth trajectory that starts
at the pose measured on entry, so entering from a moving or limp arm never steps the target. The trajectory is a
straight line in joint space, planned on entry (``planned``): the gate checks it against the body once, then."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from humanoid_prime.config.robot import Robot
from humanoid_prime.control._tick import Blend
from humanoid_prime.control.controller import Controller, capture_position
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.control.topics import TopicBus
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode


def min_jerk(s: float) -> tuple[float, float]:
    """Quintic blend 0 -> 1 on s in [0, 1] and its derivative; zero velocity and acceleration at both ends."""
    if s <= 0.0:
        return 0.0, 0.0
    if s >= 1.0:
        return 1.0, 0.0
    return s * s * s * (10.0 + s * (-15.0 + 6.0 * s)), 30.0 * s * s * (1.0 - s) * (1.0 - s)


class StandbyController(Controller):
    """Poses are arrays in canonical order; ``select_pose`` picks the target of the next activation."""

    def __init__(self, poses: dict[str, npt.NDArray[np.float64]], default_pose: str, kp: float, kd: float,
                 duration: float) -> None:
        super().__init__(Mode.STANDBY.controller, Mode.STANDBY)
        self.poses = poses
        self.kp = kp
        self.kd = kd
        self.duration = duration
        self.pose = ""
        self.select_pose(default_pose)

    def select_pose(self, name: str) -> None:
        """Choose the pose to move to; it takes effect when STANDBY is (re-)entered."""
        if name not in self.poses:
            raise PrimeError(f"unknown standby pose {name!r}; known poses: {', '.join(self.poses)}")
        self.pose = name

    def on_configure(self, robot: Robot, topics: TopicBus) -> None:
        self.names = robot.names
        self.start = np.zeros(robot.n)
        self.delta = np.zeros(robot.n)
        self.t0 = 0.0
        self._blend = Blend()

    def on_activate(self, state: StateArrays, now: float) -> None:
        capture_position(self.names, state, self.start, "cannot start the trajectory: ")
        np.subtract(self.poses[self.pose], self.start, out=self.delta)
        self.t0 = now

    def planned(self) -> tuple[npt.NDArray[np.float64], float]:
        return np.stack((self.start, self.poses[self.pose])), self.kp

    def update(self, now: float, dt: float, state: StateArrays, command: CommandArrays) -> None:
        blend, rate = min_jerk((now - self.t0) / self.duration)
        self._blend.run(self.start, self.delta, blend, rate / self.duration, self.kp, self.kd, command.data)
