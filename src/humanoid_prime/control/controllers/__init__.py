"""The joint-state broadcaster and the five mode controllers, built from ``prime_controllers.yaml``."""

from __future__ import annotations

from pathlib import Path

from humanoid_prime.config.controllers import ControllersConfig
from humanoid_prime.config.robot import Robot
from humanoid_prime.control.controller import Controller, pose_array
from humanoid_prime.control.controllers.broadcaster import JointStateBroadcaster
from humanoid_prime.control.controllers.damping import DampingController
from humanoid_prime.control.controllers.locomotion import LocomotionController
from humanoid_prime.control.controllers.remote import RemotePolicyController
from humanoid_prime.control.controllers.standby import StandbyController
from humanoid_prime.control.controllers.zero_torque import ZeroTorqueController
from humanoid_prime.errors import ConfigError
from humanoid_prime.files import bundled

__all__ = [
    "DampingController", "JointStateBroadcaster", "LocomotionController", "RemotePolicyController",
    "StandbyController", "ZeroTorqueController", "build_controllers", "check_gains", "resolve_policy",
]


def resolve_policy(config: ControllersConfig) -> Path:
    """A bare file name is looked up in the bundled data folder first; any other name is a path,
    relative to the controllers file's folder."""
    name = config.locomotion.policy
    candidate = Path(name).expanduser()
    if candidate.name == name and bundled(name).is_file():
        return bundled(name)
    path = candidate if candidate.is_absolute() else config.path.parent / candidate
    if not path.is_file():
        raise ConfigError(config.path, "locomotion_controller.ros__parameters.policy",
                          f"policy file {str(path)!r} not found",
                          "give a path to an .onnx file or the name of a bundled policy (standby_policy.onnx)")
    return path


def check_gains(robot: Robot, config: ControllersConfig) -> None:
    """Every gain the controllers file sets is within the hardware file's maximum for the family it reaches
    (``command_limits``), so a mode cannot be configured to command what every tick of it would be refused."""
    both = ("erob", "sito")
    params = [("damping_controller", "kd", config.damping_kd, both),
              ("standby_controller", "kp", config.standby.kp, both),
              ("standby_controller", "kd", config.standby.kd, both),
              ("locomotion_controller", "erob_kp", config.locomotion.erob_kp, ("erob",)),
              ("locomotion_controller", "erob_kd", config.locomotion.erob_kd, ("erob",)),
              ("locomotion_controller", "sito_kp", config.locomotion.sito_kp, ("sito",)),
              ("locomotion_controller", "sito_kd", config.locomotion.sito_kd, ("sito",)),
              ("remote_policy_controller", "erob_kp", config.remote.erob_kp, ("erob",)),
              ("remote_policy_controller", "erob_kd", config.remote.erob_kd, ("erob",)),
              ("remote_policy_controller", "stale_kd", config.remote.stale_kd, ("sito",))]
    present = {j.family for j in robot.joints}
    for node, name, value, families in params:
        interface = "stiffness" if name.endswith("kp") else "damping"
        for family in (f for f in families if f in present):
            limit = getattr(robot.hardware.command_limits[family], interface)
            if value > limit:
                raise ConfigError(config.path, f"{node}.ros__parameters.{name}",
                                  f"{value:g} is beyond the {family} {interface} maximum of {limit:g} "
                                  f"(command_limits.{family}.{interface} in {robot.hardware.path})",
                                  f"use at most {limit:g}, or raise the maximum in the hardware file")


def build_controllers(robot: Robot, config: ControllersConfig) -> dict[str, Controller]:
    """The broadcaster and the five mode controllers, in staged-start order."""
    check_gains(robot, config)
    poses = {}
    for name, values in config.standby.poses.items():
        key = f"standby_controller.ros__parameters.poses.{name}"
        poses[name] = pose_array(robot, values)
        for joint in robot.joints:
            angle = poses[name][joint.index]
            if not joint.lower <= angle <= joint.upper:
                given = joint.name in values
                raise ConfigError(config.path, f"{key}.{joint.name}" if given else key,
                                  f"{joint.name} at {angle} rad{'' if given else ' (left out)'} is outside its "
                                  f"limits [{joint.lower}, {joint.upper}]",
                                  f"give {joint.name} an angle within the limits")
    standby, locomotion, remote = config.standby, config.locomotion, config.remote
    controllers: list[Controller] = [
        JointStateBroadcaster(config.joint_states_topic),
        ZeroTorqueController(),
        DampingController(config.damping_kd),
        StandbyController(poses, standby.default_pose, standby.kp, standby.kd, standby.duration),
        LocomotionController(resolve_policy(config), poses[locomotion.default_pose], locomotion.action_scale,
                             locomotion.erob_kp, locomotion.erob_kd, locomotion.sito_kp, locomotion.sito_kd),
        RemotePolicyController(remote.topic, remote.timeout, remote.stale_policy, remote.stale_kd,
                               remote.erob_kp, remote.erob_kd),
    ]
    return {c.name: c for c in controllers}
