"""What a command may ask of a joint, whatever its source: the one set of bounds the controller manager holds
every tick's command to and REMOTE holds every incoming message to, and the words for a refusal.

A command is refused when any value is not finite, a stiffness or damping is negative, a |velocity|, stiffness
or damping is beyond its family's maximum (``command_limits`` in the hardware file), an |effort| is beyond the
joint's effort limit, or a position target (with or without stiffness) lies beyond a joint limit by more than
``POSITION_MARGIN``; a target within the margin is clipped onto the limit. The check is compiled
(``_tick.CommandCheck``); this module builds it and words what it found.
"""

from __future__ import annotations

import numpy as np

from humanoid_prime.config.robot import Robot
from humanoid_prime.control._tick import BEYOND, NEGATIVE_GAIN, NON_FINITE, CommandCheck
from humanoid_prime.control.interfaces import COMMAND_NAMES, POSITION_MARGIN

UNITS = ("rad", "rad/s", "Nm", "Nm/rad", "Nm*s/rad")  # of each command row
FAMILY_NAMES = {"erob": "eRob", "sito": "Sito"}


class CommandBounds:
    """The bounds of ``robot``'s joints (canonical order) and their compiled check (``check``). ``release``: a joint
    may have no command (a NaN position, the other four rows zero), as the manager's gate allows a controller that
    ``releases`` (control/controller.py); REMOTE's messages give every joint a command."""

    def __init__(self, robot: Robot, *, release: bool = False) -> None:
        self.names = robot.names
        self.families = tuple(j.family for j in robot.joints)
        self.lower = np.ascontiguousarray(robot.lower, dtype=np.float64)
        self.upper = np.ascontiguousarray(robot.upper, dtype=np.float64)
        limits = robot.hardware.command_limits
        self.hardware_file = robot.hardware.path.name
        # rows 1 to 4 of a command: |velocity|, |effort|, stiffness, damping
        self.maximum = np.array([[limits[f].velocity for f in self.families], robot.effort_limit,
                                 [limits[f].stiffness for f in self.families],
                                 [limits[f].damping for f in self.families]], dtype=np.float64)
        self.check = CommandCheck(self.lower, self.upper, self.maximum, POSITION_MARGIN, release)

    def refusal(self, found: int, row: int, col: int, value: float) -> str:
        """What the check found (``found`` at ``row``, ``col``; ``value`` is what the command held there), in
        words: the interface, the joint, the value and the bound it broke."""
        interface, joint, unit = COMMAND_NAMES[row], self.names[col], UNITS[row]
        if found == NON_FINITE:
            return f"{interface} of {joint} is {value}"
        if found == NEGATIVE_GAIN:
            return f"{interface} of {joint} is negative ({value:g})"
        if found == BEYOND:
            limit = self.maximum[row - 1, col]
            beyond = f"{interface} of {joint} is {value:g} {unit}, beyond its limit of {limit:g} {unit}"
            if interface == "effort":
                return beyond
            family = self.families[col]
            return (f"{beyond} (the {FAMILY_NAMES[family]} maximum, command_limits.{family}.{interface} in "
                    f"{self.hardware_file})")
        return (f"position target of {joint} is {value:g} rad, outside its limits "
                f"[{self.lower[col]:g}, {self.upper[col]:g}]")
