"""DAMPING: the compliant fail-safe. Zero stiffness, per-joint damping (default 6 Nm*s/rad),
position target held at the pose captured on entry (within the joint limits: with zero stiffness the target
exerts no torque, and every target must be within them)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from humanoid_prime.config.robot import Robot
from humanoid_prime.control._tick import Copy
from humanoid_prime.control.controller import Controller, capture_position
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.control.topics import TopicBus
from humanoid_prime.modes import Mode


class DampingController(Controller):
    def __init__(self, kd: float | Sequence[float] = 6.0) -> None:
        super().__init__(Mode.DAMPING.controller, Mode.DAMPING)
        self.kd = kd

    def on_configure(self, robot: Robot, topics: TopicBus) -> None:
        kd = np.broadcast_to(np.asarray(self.kd, dtype=np.float64), (robot.n,)).copy()
        if not np.all(np.isfinite(kd)) or np.any(kd < 0):
            raise ValueError(f"{self.name}: kd must be finite and >= 0 per joint, got {kd.tolist()}")
        self.names = robot.names
        self._lower, self._upper = robot.lower, robot.upper
        # The whole command, written at activation: the captured pose, no velocity, effort or stiffness, kd.
        self._command = np.zeros((5, robot.n))
        self._command[4] = kd
        self.captured = self._command[0]
        self._copy = Copy()

    def on_activate(self, state: StateArrays, now: float) -> None:
        capture_position(self.names, state, self.captured, "cannot capture the pose: ")
        np.clip(self.captured, self._lower, self._upper, out=self.captured)

    def update(self, now: float, dt: float, state: StateArrays, command: CommandArrays) -> None:
        self._copy.run(command.data, self._command)
