"""The run as ROS 2 parameters of node ``prime``: what ``ros2 param list /prime`` shows and ``ros2 param get``
reads. All of them describe the run and are read-only, but ``remote.timeout_s``: how long REMOTE waits for a
command before it damps, safe to change live within its bounds (at least two ticks, at most half a second; the
REMOTE controller reads it every tick). Nothing here knows ROS: the node declares what ``run_parameters`` gives.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass

from humanoid_prime.control.controllers.remote import RemotePolicyController
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.modes import Mode

Value = bool | int | float | str | list[float] | list[str]
REMOTE_TIMEOUT = "remote.timeout_s"
REMOTE_TIMEOUT_MAX_S = 0.5  # beyond this a dead stream holds a stale command too long to call REMOTE safe


@dataclass(frozen=True)
class RunParameter:
    """One parameter: its value, what it is, and for a settable one its bounds and how it is applied."""

    name: str
    value: Value
    description: str
    bounds: tuple[float, float] | None = None  # settable within these (None: read-only)
    apply: Callable[[float], None] | None = None


def robot_name(urdf: str) -> str:
    return ET.fromstring(urdf).get("name", "")


def run_parameters(manager: ControllerManager, *, backend: str, control: bool) -> list[RunParameter]:
    """The parameters of ``manager``'s run (see the module docstring)."""
    robot, config = manager.robot, manager.config
    names = list(robot.names)
    found: list[RunParameter] = [
        RunParameter("backend", backend, "how Prime is on the ROS 2 graph: rclpy (this node) or dds (bare Cyclone)"),
        RunParameter("robot", robot_name(robot.description.urdf), "the robot description's name"),
        RunParameter("robot_description_source", str(robot.description.source), "the robot description's file"),
        RunParameter("joints", names, "the joints in canonical order (the order of every array here and on the "
                                      "topics)"),
        RunParameter("update_rate", float(manager.update_rate), "the control loop's rate, Hz"),
        RunParameter("control", control, "whether the graph may switch modes and command the robot (--dds-control)"),
    ]
    for kind, entry in sorted(manager.configuration.items()):
        for key in ("path", "sha256"):
            found.append(RunParameter(f"config.{kind}.{key}", str(entry.get(key, "")),
                                      f"the {kind} configuration file's {key}"))
    for mode, (kp, kd) in config.mode_gains().items():
        found.append(RunParameter(f"modes.{mode.value}.erob_kp", float(kp), f"{mode.value}'s eRob stiffness, Nm/rad"))
        found.append(RunParameter(f"modes.{mode.value}.erob_kd", float(kd),
                                  f"{mode.value}'s eRob damping, Nm*s/rad"))
    limits = robot.hardware.command_limits
    for family, limit in sorted(limits.items()):
        for key, value, unit in (("stiffness", limit.stiffness, "Nm/rad"), ("damping", limit.damping, "Nm*s/rad"),
                                 ("velocity", limit.velocity, "rad/s")):
            found.append(RunParameter(f"command_limits.{family}.{key}", float(value),
                                      f"the most any command may give a {family} joint, {unit}"))
    found += [
        RunParameter("joint_limits.lower", [j.lower for j in robot.joints], "each joint's lower limit, rad"),
        RunParameter("joint_limits.upper", [j.upper for j in robot.joints], "each joint's upper limit, rad"),
        RunParameter("joint_limits.velocity", [j.velocity_limit for j in robot.joints], "each joint's velocity "
                                                                                       "limit, rad/s"),
        RunParameter("joint_limits.effort", [j.effort_limit for j in robot.joints], "each joint's effort limit, Nm"),
    ]
    remote = manager.controllers.get(Mode.REMOTE.controller)
    if isinstance(remote, RemotePolicyController):
        def set_timeout(value: float) -> None:
            remote.timeout = value

        found.append(RunParameter(REMOTE_TIMEOUT, float(remote.timeout),
                                  "REMOTE damps when no command came for this long, s (settable live)",
                                  bounds=(round(2.0 * manager.period, 6), REMOTE_TIMEOUT_MAX_S), apply=set_timeout))
    return found
