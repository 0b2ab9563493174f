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
    "StandbyController", "ZeroTorqueController", "build_controllers", "resolve_policy",
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


def build_controllers(robot: Robot, config: ControllersConfig) -> dict[str, Controller]:
    """The broadcaster and the five mode controllers, in staged-start order."""
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
