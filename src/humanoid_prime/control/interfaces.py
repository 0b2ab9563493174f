"""Per-tick joint arrays in canonical order: 5 command and 3 state interfaces per joint.

Preallocated once; the hot path writes into them in place (no per-tick allocation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

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

    def freeze(self) -> None:
        """Make the arrays read-only from Python: a writer bound before (a compiled kernel's view) is the only one
        left (the controller manager's gate commits the command so)."""
        for array in (self.data, self.position, self.velocity, self.effort, self.stiffness, self.damping):
            array.flags.writeable = False


@dataclass(frozen=True)
class Frame:
    """Where a controller's joint positions are not the model's (a calibration's host frame, which is what it is
    finding): model = ``scale * position + shift`` per joint. ``known``: the joints whose frame is known (the body
    check leaves the bodies of the others out); ``limited``: the joints whose limits apply, moved by the frame (not
    a joint pressing a stop to find it). The controller may change the arrays in place as it learns (in its
    ``update``, on the loop's thread)."""

    scale: npt.NDArray[np.float64]
    shift: npt.NDArray[np.float64]
    known: npt.NDArray[np.uint8]
    limited: npt.NDArray[np.uint8]


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
