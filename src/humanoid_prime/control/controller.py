"""The controller interface: what the controller manager calls, and nothing about buses.

A controller sees the joint-frame arrays (``StateArrays`` in, ``CommandArrays`` out), the ``Robot``
model (names, family per joint, limits) and the topic bus. ``update`` runs once per tick on
preallocated arrays and must write every element of all five command rows; it raises
``ControllerError`` (or lets any exception escape) when it cannot produce a safe command, and the
manager then swaps it for its fallback within the same tick. What it writes is a proposal: the manager's gate
checks it (the bounds, the body) before anything reaches a bus.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping

import numpy as np
import numpy.typing as npt

from humanoid_prime.config.robot import Robot
from humanoid_prime.control.flags import SafetyFlags
from humanoid_prime.control.hardware import Lifecycle
from humanoid_prime.control.interfaces import CommandArrays, Frame, StateArrays
from humanoid_prime.control.topics import TopicBus
from humanoid_prime.errors import ControllerError
from humanoid_prime.modes import Mode


class Controller(SafetyFlags, ABC):
    """Base of the joint-state broadcaster and the five mode controllers.

    ``mode`` is the mode a controller implements (None for the broadcaster and the tasks of a broadcaster-only
    run); ``claims_commands`` says whether it claims every command interface while active; ``releases``, whether
    the gate lets its command leave a joint with no command (the modes command every joint). The manager drives
    ``lifecycle``.
    """

    claims_commands: bool = True
    releases: bool = False  # its command may leave a joint with no command (NaN position, the rest zero)
    frame: Frame | None = None  # its positions' frame, where it is not the model's (control/interfaces.py)

    def __init__(self, name: str, mode: Mode | None) -> None:
        super().__init__(name)
        self.mode = mode
        self.lifecycle = Lifecycle.UNCONFIGURED

    def on_configure(self, robot: Robot, topics: TopicBus) -> None:
        """Allocate buffers, load models, subscribe to topics. Runs once, before the first activation."""

    def on_activate(self, state: StateArrays, now: float) -> None:
        """Capture what the controller needs from the measured state at the switch."""

    def on_deactivate(self) -> None:
        """Stop; the command interfaces are released right after."""

    def planned(self) -> tuple[npt.NDArray[np.float64], float] | None:
        """The targets this activation plans in advance (k x n, joint frame, in order, the path between them a
        straight line) and the stiffness they are held with: the gate checks the plan once, right after
        ``on_activate``, and refuses the activation if it would bring two bodies within the margin. None: nothing
        is planned (every tick's command is checked as it comes)."""
        return None

    def on_refused(self, reason: str, held: npt.NDArray[np.bool_]) -> None:
        """The gate refused this tick's command against the body (``reason`` names the two bodies and their
        distance): the ``held`` joints (the arms it would drive) hold their last command. Called in the tick,
        before the write."""

    @abstractmethod
    def update(self, now: float, dt: float, state: StateArrays, command: CommandArrays) -> None:
        """Write the command for this tick into ``command`` (all five rows, every joint)."""


def capture_position(names: tuple[str, ...], state: StateArrays, out: npt.NDArray[np.float64], why: str) -> None:
    """Copy the measured position into ``out``; a joint that is not measured (non-finite) refuses the
    activation, with ``why`` saying what could not be done."""
    bad = np.flatnonzero(~np.isfinite(state.position))
    if bad.size:
        raise ControllerError(f"{why}measured position of {names[bad[0]]} is not finite")
    np.copyto(out, state.position)


def gain_rows(robot: Robot, erob: tuple[float, float],
              sito: tuple[float, float]) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Per-joint (stiffness, damping) rows from one (kp, kd) pair per actuator family."""
    is_erob = np.array([j.family == "erob" for j in robot.joints])
    stiffness = np.where(is_erob, erob[0], sito[0]).astype(np.float64)
    damping = np.where(is_erob, erob[1], sito[1]).astype(np.float64)
    return stiffness, damping


def pose_array(robot: Robot, pose: Mapping[str, float]) -> npt.NDArray[np.float64]:
    """A named pose (joint -> rad, joints left out are 0) as an array in canonical order."""
    values = np.zeros(robot.n)
    for joint, angle in pose.items():
        values[robot.index(joint)] = angle
    return values
