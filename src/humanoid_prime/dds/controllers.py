"""Prime's modes as ros2_control's controller manager lists and switches them, so ``ros2 control
list_controllers`` and ``ros2 control switch_controllers`` work on Prime as on any ros2_control robot.

The controllers are the joint-state broadcaster (always active) and the five mode controllers, of which exactly
one is active and claims every joint's five command interfaces. A switch activates one mode controller (and
may name the active one to deactivate): it is a mode switch, with the same path and refusals as ``prime
switch``. Deactivating the active mode with nothing in its place is refused: Prime always has a mode.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from humanoid_prime.control.interfaces import COMMAND_NAMES
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.modes import JOINT_STATE_BROADCASTER, Mode

STATE_NAMES = ("position", "velocity", "effort")
BROADCASTER_TYPE = "joint_state_broadcaster/JointStateBroadcaster"
NAMESPACE = "/controller_manager"  # where ros2 control looks for the services (its default --controller-manager)
# The trajectory controllers a joint_trajectory_controller setup would have: name -> joints (canonical order).
ARM_CONTROLLERS = ("left_arm_controller", "right_arm_controller", "arms_controller")


@dataclass(frozen=True)
class ControllerInfo:
    """controller_manager_msgs/ControllerState's fields that Prime fills."""

    name: str
    state: str  # active or inactive
    type: str
    update_rate: int
    claimed_interfaces: tuple[str, ...]
    required_command_interfaces: tuple[str, ...]
    required_state_interfaces: tuple[str, ...]


def arm_controllers(names: tuple[str, ...]) -> dict[str, tuple[str, ...]]:
    """The joints of each trajectory controller: each arm's seven, and all fourteen."""
    return {"left_arm_controller": tuple(n for n in names if n.startswith("left_")),
            "right_arm_controller": tuple(n for n in names if n.startswith("right_")),
            "arms_controller": names}


def controllers(manager: ControllerManager) -> list[ControllerInfo]:
    """Every controller of ``manager``'s run as the controller manager lists it."""
    names = manager.robot.names
    commands = tuple(f"{joint}/{interface}" for joint in names for interface in COMMAND_NAMES)
    states = tuple(f"{joint}/{interface}" for joint in names for interface in STATE_NAMES)
    rate = round(manager.update_rate)
    listed = [ControllerInfo(JOINT_STATE_BROADCASTER, "active", BROADCASTER_TYPE, rate, (), (), states)]
    if manager.broadcaster_only:
        return listed
    active = manager.active_mode
    for mode in Mode:
        controller = manager.controllers.get(mode.controller)
        if controller is None:
            continue
        on = mode is active
        listed.append(ControllerInfo(mode.controller, "active" if on else "inactive",
                                     f"prime_controllers/{type(controller).__name__}", rate,
                                     commands if on else (), commands, states))
    return listed


@dataclass(frozen=True)
class SwitchResult:
    """What became of a mode switch asked for from the graph, as the services answer it."""

    outcome: str  # active, fell_back, superseded, gains_failed, pending or refused
    active: str  # the mode active once the request was applied ('': not applied)
    message: str  # one line for a person

    @property
    def ok(self) -> bool:
        return self.outcome == "active"


Switch = Callable[[Mode, float], SwitchResult]  # the run's switch, followed to its outcome (as `prime switch`)


class SwitchRefused(Exception):
    """A switch_controllers request Prime cannot do, and why."""


def mode_to_activate(manager: ControllerManager, activate: list[str], deactivate: list[str],
                     strict: bool) -> Mode | None:
    """The mode a switch_controllers request asks for (None: nothing to do), or SwitchRefused with the reason.
    ``strict`` (STRICT): every name must be a controller and the request must make sense as asked;
    otherwise (BEST_EFFORT, AUTO) names that are not Prime's mode controllers are skipped."""
    by_name = {mode.controller: mode for mode in Mode}
    known = {JOINT_STATE_BROADCASTER, *by_name}
    unknown = [name for name in [*activate, *deactivate] if name not in known]
    if unknown and strict:
        raise SwitchRefused(f"no controller named {', '.join(unknown)}; Prime's are {', '.join(sorted(known))}")
    if JOINT_STATE_BROADCASTER in deactivate and strict:
        raise SwitchRefused(f"{JOINT_STATE_BROADCASTER} is always active: every mode reads the joint states")
    modes = [by_name[name] for name in activate if name in by_name]
    if len(modes) > 1:
        raise SwitchRefused("one mode controller is active at a time: activate one of "
                            f"{', '.join(mode.controller for mode in modes)}")
    active = manager.active_mode
    leaving = [by_name[name] for name in deactivate if name in by_name]
    if not modes:
        if any(mode is active for mode in leaving):
            raise SwitchRefused(f"{active.controller if active else 'the active mode'} cannot be deactivated alone: "
                                "Prime always has one mode active; activate the mode controller to switch to")
        return None
    wrong = [mode for mode in leaving if mode is not active and mode is not modes[0]]
    if wrong and strict:
        raise SwitchRefused(f"{', '.join(mode.controller for mode in wrong)} is not active")
    return modes[0]
