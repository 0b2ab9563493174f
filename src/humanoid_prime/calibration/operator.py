"""The person at the robot during a hands-free calibration (``calibration.auto``), or the virtual robot's scripted
operator: who lets a joint move and answers the direction question the physics cannot."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np
import numpy.typing as npt


class Operator(Protocol):
    """The person (or the virtual robot's scripted operator) at the robot."""

    answered_by: str  # where an answer comes from, in the report: "the operator's answer", ...

    def begin(self, joints: Sequence[str]) -> None:
        """Before anything moves (on the robot: the e-stop reminder)."""

    def confirm(self, joint: str) -> bool:
        """May ``joint`` move now? (On the robot: Enter moves it, anything else skips it.)"""

    def watch(self, joint: str) -> None:
        """``joint`` is about to make the prompted motion."""

    def turned_counter_clockwise(self, joint: str, view: npt.NDArray[np.float64], where: str) -> bool | None:
        """Seen from ``where`` (looking along -``view``), did ``joint`` just turn counter-clockwise? None: cannot
        tell."""


class Unattended:
    """No one at the robot: every joint may move, no question can be answered."""

    answered_by = "nobody"

    def begin(self, joints: Sequence[str]) -> None:
        pass

    def confirm(self, joint: str) -> bool:
        return True

    def watch(self, joint: str) -> None:
        pass

    def turned_counter_clockwise(self, joint: str, view: npt.NDArray[np.float64], where: str) -> bool | None:
        return None
