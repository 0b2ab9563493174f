"""Per-tick joint arrays in canonical order: 5 command and 3 state interfaces per joint.

Preallocated once; the hot path writes into them in place (no per-tick allocation).
"""

from __future__ import annotations

import numpy as np

COMMAND_NAMES = ("position", "velocity", "effort", "stiffness", "damping")
STATE_NAMES = ("position", "velocity", "effort")
POSITION_MARGIN = 0.005  # rad beyond a joint limit that a command may reach: clipped onto the limit, not rejected


class CommandArrays:
    """MIT command per joint: tau = stiffness*(position - q) + damping*(velocity - qd) + effort."""

    __slots__ = ("data", "position", "velocity", "effort", "stiffness", "damping")

    def __init__(self, n: int) -> None:
        self.data = np.zeros((5, n), dtype=np.float64)
        self.position, self.velocity, self.effort, self.stiffness, self.damping = self.data

    @property
    def n(self) -> int:
        return self.data.shape[1]

    def copy_from(self, other: CommandArrays) -> None:
        np.copyto(self.data, other.data)


class StateArrays:
    """Measured joint state per joint, in the joint frame (calibration already applied)."""

    __slots__ = ("data", "position", "velocity", "effort", "stamp")

    def __init__(self, n: int) -> None:
        self.data = np.zeros((3, n), dtype=np.float64)
        self.position, self.velocity, self.effort = self.data
        self.stamp = 0.0

    @property
    def n(self) -> int:
        return self.data.shape[1]

    def copy_from(self, other: StateArrays) -> None:
        np.copyto(self.data, other.data)
        self.stamp = other.stamp
