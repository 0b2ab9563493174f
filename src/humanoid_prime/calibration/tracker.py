"""Live per-joint min/max while the operator sweeps joints to their mechanical stops.

Positions arrive in the identity frame (direction applied, offset 0) on ``/prime/joint_states``.
The tracker keeps running min/max, and the trace itself in a growing buffer, so that it can tell which
stop each joint reached first: the operator sweeps to the lower stop first, and a joint whose trace
reaches its maximum first is wired the other way round (``order``). ``rows()`` gives a consistent
snapshot for the live readout, including how much of the described range each sweep covers.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from humanoid_prime.config.robot import Robot
from humanoid_prime.control.topics import JOINT_STATES, JointState, TopicBus

STOP_BAND_FRACTION = 0.05  # a joint within 5 % of its sweep from an extreme is at that stop
INITIAL_CAPACITY = 4096


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
    def __init__(self, robot: Robot, joints: Sequence[str], clock: Callable[[], float] = time.monotonic) -> None:
        self.robot = robot
        self.joints = tuple(joints)
        self.clock = clock
        self.index = np.array([robot.index(j) for j in self.joints], dtype=np.intp)
        self.lower = robot.lower[self.index]
        self.upper = robot.upper[self.index]
        self._lock = threading.Lock()
        n = len(self.joints)
        self._position = np.full(n, np.nan)
        self._min = np.full(n, np.inf)
        self._max = np.full(n, -np.inf)
        self._trace = np.empty((INITIAL_CAPACITY, n))
        self.samples = 0

    def update(self, position: npt.NDArray[np.float64]) -> None:
        """Take one canonical-order position vector (non-finite entries are ignored)."""
        values = position[self.index]
        with self._lock:
            if self.samples == len(self._trace):  # amortised: the buffer doubles, rarely
                self._trace = np.concatenate([self._trace, np.empty_like(self._trace)])
            self._trace[self.samples] = values
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

    def order(self) -> dict[str, str | None]:
        """Per joint, which extreme of its sweep the trace reached first: ``"min"`` or ``"max"``; None when it
        cannot tell (not swept, or it started resting within a stop band, where the order is ambiguous)."""
        with self._lock:
            trace = self._trace[:self.samples].copy()
            lo, hi = self._min.copy(), self._max.copy()
        result: dict[str, str | None] = {}
        for i, joint in enumerate(self.joints):
            column = trace[:, i]
            column = column[np.isfinite(column)]
            span = hi[i] - lo[i]
            if column.size == 0 or not span > 0:
                result[joint] = None
                continue
            band = STOP_BAND_FRACTION * span
            at_min = column <= lo[i] + band
            at_max = column >= hi[i] - band
            if at_min[0] or at_max[0]:
                result[joint] = None
                continue
            result[joint] = "min" if np.argmax(at_min) < np.argmax(at_max) else "max"
        return result
