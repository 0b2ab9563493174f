"""Live per-joint min/max while the operator sweeps joints to their mechanical stops.

Positions arrive in the identity frame (direction applied, offset 0) on ``/prime/joint_states``.
The tracker keeps running min/max in preallocated arrays; ``rows()`` gives a consistent snapshot for
the live readout, including how much of the described range each sweep covers.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from humanoid_prime.control.topics import JOINT_STATES, JointState, TopicBus
from humanoid_prime.robot import Robot


@dataclass(frozen=True)
class SweepRow:
    joint: str
    position: float
    minimum: float
    maximum: float
    lower: float
    upper: float

    @property
    def sweep(self) -> float:
        return self.maximum - self.minimum if self.maximum >= self.minimum else 0.0

    @property
    def coverage(self) -> float:
        """Fraction of the described range the sweep spans (1.0 = stop to stop)."""
        return self.sweep / (self.upper - self.lower)


class SweepTracker:
    def __init__(self, robot: Robot, joints: Sequence[str]) -> None:
        self.robot = robot
        self.joints = tuple(joints)
        self.index = np.array([robot.index(j) for j in self.joints], dtype=np.intp)
        self.lower = robot.lower[self.index]
        self.upper = robot.upper[self.index]
        self._lock = threading.Lock()
        self._position = np.full(len(self.joints), np.nan)
        self._min = np.full(len(self.joints), np.inf)
        self._max = np.full(len(self.joints), -np.inf)
        self.samples = 0

    def update(self, position: np.ndarray) -> None:
        """Take one canonical-order position vector (ignores non-finite entries)."""
        values = position[self.index]
        with self._lock:
            finite = np.isfinite(values)
            self._position[finite] = values[finite]
            np.fmin(self._min, np.where(finite, values, np.inf), out=self._min)
            np.fmax(self._max, np.where(finite, values, -np.inf), out=self._max)
            self.samples += 1

    def _on_joint_states(self, msg: JointState) -> None:
        self.update(msg.position)

    def attach(self, topics: TopicBus) -> None:
        topics.subscribe(JOINT_STATES, self._on_joint_states)

    def detach(self, topics: TopicBus) -> None:
        topics.unsubscribe(JOINT_STATES, self._on_joint_states)

    def rows(self) -> list[SweepRow]:
        with self._lock:
            pos, lo, hi = self._position.copy(), self._min.copy(), self._max.copy()
        return [SweepRow(j, float(pos[i]), float(lo[i]), float(hi[i]), float(self.lower[i]), float(self.upper[i]))
                for i, j in enumerate(self.joints)]

    def sweeps(self) -> dict[str, tuple[float, float]]:
        """Joint -> (min, max) for every joint that has been seen at least once."""
        return {r.joint: (r.minimum, r.maximum) for r in self.rows() if r.maximum >= r.minimum}
