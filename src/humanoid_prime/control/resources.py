"""One flat list of 14 joints in canonical order, whichever hardware components own them.

The resource manager owns the global state and command arrays, checks that every joint has one owner
(each component knows its joints' canonical indices from construction), and walks the components in
order for every lifecycle step, ``read`` and ``write``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from humanoid_prime.config.robot import Robot
from humanoid_prime.control.hardware import HardwareComponent
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.errors import PrimeError


class ResourceManager:
    """``partial`` allows joints no component owns (a single-bus run); their state stays NaN (not measured)."""

    def __init__(self, robot: Robot, components: Sequence[HardwareComponent], *, partial: bool = False) -> None:
        self.robot = robot
        self.components = tuple(components)
        owner: dict[str, str] = {}
        for component in self.components:
            for joint in component.joints:
                if joint in owner:
                    raise PrimeError(f"joint {joint!r} is owned by both {owner[joint]!r} and {component.name!r}; "
                                     "each joint must belong to exactly one hardware component")
                owner[joint] = component.name
        missing = [name for name in robot.names if name not in owner]
        if missing and not partial:
            names = ", ".join(c.name for c in self.components) or "none"
            raise PrimeError(f"no hardware component owns {', '.join(missing)} (components: {names}); "
                             "every joint needs exactly one owner")
        self.state = StateArrays(robot.n)
        self.command = CommandArrays(robot.n)
        self.owned = np.zeros(robot.n, dtype=bool)
        self.owned[[robot.index(j) for j in owner]] = True
        self.state.data[:, ~self.owned] = np.nan

    def read(self, now: float) -> None:
        for component in self.components:
            component.read(now, self.state)
        self.state.stamp = now

    def write(self, now: float) -> None:
        for component in self.components:
            component.write(now, self.command)

    def latched_faults(self) -> list[str]:
        return [fault for component in self.components for fault in component.latched_faults()]

    def reset_faults(self) -> None:
        for component in self.components:
            component.reset_faults()

    def configure(self) -> None:
        for component in self.components:
            component.configure()

    def activate(self) -> None:
        for component in self.components:
            component.activate()

    def deactivate(self) -> None:
        """Deactivate every component (each leaves its devices safe), even if one of them fails."""
        self._attempt_all(HardwareComponent.deactivate, "deactivate")

    def shutdown(self) -> None:
        """Shut every component down, even if one of them fails; then report the failures."""
        self._attempt_all(HardwareComponent.shutdown, "shut down")

    def _attempt_all(self, step: Callable[[HardwareComponent], None], verb: str) -> None:
        failures = []
        for component in self.components:
            try:
                step(component)
            except Exception as exc:
                failures.append((component.name, exc))
        if failures:
            text = "; ".join(f"{name}: {exc}" for name, exc in failures)
            raise PrimeError(f"could not {verb} every hardware component: {text}") from failures[0][1]
