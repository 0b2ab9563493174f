"""``prime_controllers.yaml``: controller manager rates, mode controllers, per-mode gains, standby poses."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from humanoid_prime.errors import ConfigError
from humanoid_prime.files import bundled, check_keys, config_path, load_yaml
from humanoid_prime.modes import JOINT_STATE_BROADCASTER, MODE_CONTROLLERS, Mode

if TYPE_CHECKING:
    from humanoid_prime.config.robot import Robot

CONTROLLERS_FILE = "prime_controllers.yaml"
# This stack has one controller class per mode; a file naming another type means another stack's file.
CONTROLLER_TYPES = {
    JOINT_STATE_BROADCASTER: "joint_state_broadcaster/JointStateBroadcaster",
    "zero_torque_controller": "prime_controllers/ZeroTorqueController",
    "damping_controller": "prime_controllers/DampingController",
    "standby_controller": "prime_controllers/StandbyController",
    "locomotion_controller": "prime_controllers/LocomotionController",
    "remote_policy_controller": "prime_controllers/RemotePolicyController",
}
MAX_ACTION_SCALE_RAD = 1.0  # rad per unit action: beyond it every action a policy outputs saturates at a limit
MAX_UPDATE_RATE_HZ = 2000.0  # the eRob's minimum cycle is 500 us (DESIGN §2), and SYNC0 is the loop period
MAX_BRINGUP_RATE_HZ = MAX_UPDATE_RATE_HZ  # faster bring-up frames than the drives' cycle gain nothing
MAX_STANDBY_RAMP_S = 60.0
MAX_PHYSICS_RATE_HZ = 10000.0
MAX_REMOTE_TIMEOUT_S = 1.0
# The parameters each node of the file takes (ROS 2 parameter-file shape: ``node: ros__parameters: {...}``).
PARAMETERS: dict[str, tuple[str, ...]] = {
    "controller_manager": ("update_rate", "bringup_rate", *CONTROLLER_TYPES),
    "mujoco_simulation": ("update_rate", "physics_rate"),
    JOINT_STATE_BROADCASTER: ("topic",),
    "zero_torque_controller": ("mode",),
    "damping_controller": ("mode", "kd"),
    "standby_controller": ("mode", "kp", "kd", "duration", "default_pose", "poses"),
    "locomotion_controller": ("mode", "policy", "action_scale", "default_pose", "erob_kp", "erob_kd", "sito_kp",
                              "sito_kd"),
    "remote_policy_controller": ("mode", "topic", "timeout", "stale_policy", "stale_kd", "erob_kp", "erob_kd"),
    "erob_impedance_manager": ("parallel_sdo", "sdo_retries", "torque_efficiency"),  # the last refused below
}


@dataclass(frozen=True)
class StandbyParams:
    kp: float
    kd: float
    duration: float
    default_pose: str
    poses: dict[str, dict[str, float]]


@dataclass(frozen=True)
class LocomotionParams:
    policy: str
    action_scale: float
    default_pose: str
    erob_kp: float
    erob_kd: float
    sito_kp: float
    sito_kd: float


@dataclass(frozen=True)
class RemoteParams:
    topic: str
    timeout: float
    stale_policy: str
    stale_kd: float
    erob_kp: float
    erob_kd: float


@dataclass(frozen=True)
class ImpedanceParams:
    parallel_sdo: bool
    sdo_retries: int


@dataclass(frozen=True)
class ControllersConfig:
    path: Path
    update_rate: float
    bringup_rate: float
    sim_update_rate: float
    physics_rate: float
    joint_states_topic: str
    damping_kd: float
    standby: StandbyParams
    locomotion: LocomotionParams
    remote: RemoteParams
    impedance: ImpedanceParams

    def mode_gain_keys(self) -> dict[Mode, tuple[str | None, str | None]]:
        """Where each mode's eRob (kp, kd) is set in the file (None: fixed at 0 by the mode)."""
        return {
            Mode.ZERO_TORQUE: (None, None),
            Mode.DAMPING: (None, "damping_controller.ros__parameters.kd"),
            Mode.STANDBY: ("standby_controller.ros__parameters.kp", "standby_controller.ros__parameters.kd"),
            Mode.LOCOMOTION: ("locomotion_controller.ros__parameters.erob_kp",
                              "locomotion_controller.ros__parameters.erob_kd"),
            Mode.REMOTE: ("remote_policy_controller.ros__parameters.erob_kp",
                          "remote_policy_controller.ros__parameters.erob_kd"),
        }

    def mode_gains(self) -> dict[Mode, tuple[float, float]]:
        """Per-mode eRob (kp, kd), derived from the mode controllers' own parameters."""
        return {
            Mode.ZERO_TORQUE: (0.0, 0.0),
            Mode.DAMPING: (0.0, self.damping_kd),
            Mode.STANDBY: (self.standby.kp, self.standby.kd),
            Mode.LOCOMOTION: (self.locomotion.erob_kp, self.locomotion.erob_kd),
            Mode.REMOTE: (self.remote.erob_kp, self.remote.erob_kd),
        }


class _Reader:
    def __init__(self, path: Path, data: dict[object, object]) -> None:
        self.path = path
        self.data = data

    def params(self, node: str) -> dict[str, object]:
        block = self.data.get(node)
        params = block.get("ros__parameters") if isinstance(block, dict) else None
        if not isinstance(params, dict):
            raise ConfigError(self.path, f"{node}.ros__parameters", "missing or not a mapping",
                              f"add a '{node}: ros__parameters:' block")
        return params

    def number(self, node: str, key: str, *, minimum: float = 0.0, allow_equal: bool = True,
               default: float | None = None, maximum: float = math.inf, why_maximum: str = "") -> float:
        value = self.params(node).get(key, default)
        where = f"{node}.ros__parameters.{key}"
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError(self.path, where, f"expected a finite number, got {value!r}")
        if value < minimum or (value == minimum and not allow_equal):
            bound = ">=" if allow_equal else ">"
            raise ConfigError(self.path, where, f"must be {bound} {minimum}, got {value}")
        if value > maximum:
            raise ConfigError(self.path, where, f"must be <= {maximum:g}, got {value:g}", why_maximum)
        return float(value)

    def text(self, node: str, key: str, default: str | None = None) -> str:
        value = self.params(node).get(key, default)
        if not isinstance(value, str) or not value:
            raise ConfigError(self.path, f"{node}.ros__parameters.{key}", f"expected a string, got {value!r}")
        return value


def load_controllers(joints: tuple[str, ...], path: str | Path | None = None) -> ControllersConfig:
    """Load the controllers file; pose joint names are checked against ``joints``."""
    path = config_path(path) if path is not None else bundled(CONTROLLERS_FILE)
    r = _Reader(path, load_yaml(path))
    check_keys(path, "", r.data, tuple(PARAMETERS))
    for node, known in PARAMETERS.items():
        block = r.data.get(node)
        if isinstance(block, dict):
            check_keys(path, node, block, ("ros__parameters",))
            params = block.get("ros__parameters")
            if isinstance(params, dict):
                check_keys(path, f"{node}.ros__parameters", params, known)

    cm = r.params("controller_manager")
    for name, kind in CONTROLLER_TYPES.items():
        declared = cm.get(name)
        if not isinstance(declared, dict):
            raise ConfigError(path, f"controller_manager.ros__parameters.{name}", "controller not declared",
                              f"add '{name}: {{type: {kind}}}'")
        check_keys(path, f"controller_manager.ros__parameters.{name}", declared, ("type",))
        if declared.get("type", kind) != kind:
            raise ConfigError(path, f"controller_manager.ros__parameters.{name}.type",
                              f"{declared['type']!r} is not a controller of this stack", f"use {kind}")
    for mode, name in MODE_CONTROLLERS.items():
        given = r.params(name).get("mode", mode.value)
        if given != mode.value:
            raise ConfigError(path, f"{name}.ros__parameters.mode", f"{given!r}, but {name} implements {mode.value}",
                              f"set mode: {mode.value} or leave it out")

    raw_poses = r.params("standby_controller").get("poses")
    if not isinstance(raw_poses, dict) or not raw_poses:
        raise ConfigError(path, "standby_controller.ros__parameters.poses", "missing or empty",
                          "give at least one named pose")
    poses: dict[str, dict[str, float]] = {}
    for pose, values in raw_poses.items():
        key = f"standby_controller.ros__parameters.poses.{pose}"
        values = values or {}
        if not isinstance(values, dict):
            raise ConfigError(path, key, "expected a mapping joint -> rad")
        for joint, value in values.items():
            if joint not in joints:
                raise ConfigError(path, f"{key}.{joint}", f"{joint!r} matches no joint", "fix the joint name")
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ConfigError(path, f"{key}.{joint}", f"expected a finite angle in rad, got {value!r}")
        poses[str(pose)] = {j: float(v) for j, v in values.items()}

    standby = StandbyParams(
        kp=r.number("standby_controller", "kp"),
        kd=r.number("standby_controller", "kd"),
        duration=r.number("standby_controller", "duration", allow_equal=False, maximum=MAX_STANDBY_RAMP_S,
                          why_maximum="the ramp to the pose; longer is a slip of the keyboard"),
        default_pose=r.text("standby_controller", "default_pose"),
        poses=poses,
    )
    locomotion = LocomotionParams(
        policy=r.text("locomotion_controller", "policy"),
        action_scale=r.number("locomotion_controller", "action_scale", allow_equal=False,
                              maximum=MAX_ACTION_SCALE_RAD),
        default_pose=r.text("locomotion_controller", "default_pose"),
        erob_kp=r.number("locomotion_controller", "erob_kp"),
        erob_kd=r.number("locomotion_controller", "erob_kd"),
        sito_kp=r.number("locomotion_controller", "sito_kp"),
        sito_kd=r.number("locomotion_controller", "sito_kd"),
    )
    defaults = (("standby_controller", standby.default_pose), ("locomotion_controller", locomotion.default_pose))
    for node, pose in defaults:
        if pose not in poses:
            raise ConfigError(path, f"{node}.ros__parameters.default_pose", f"pose {pose!r} is not defined",
                              f"use one of {', '.join(poses)}")
    stale = r.text("remote_policy_controller", "stale_policy", "damp")
    if stale not in ("damp", "hold"):
        raise ConfigError(path, "remote_policy_controller.ros__parameters.stale_policy",
                          f"expected 'damp' or 'hold', got {stale!r}")
    remote = RemoteParams(
        topic=r.text("remote_policy_controller", "topic", "/remote_policy_controller/command"),
        timeout=r.number("remote_policy_controller", "timeout", allow_equal=False, maximum=MAX_REMOTE_TIMEOUT_S,
                         why_maximum="a REMOTE command older than this is stale; a longer timeout lets a client "
                                     "that died drive the robot with its last command"),
        stale_policy=stale,
        stale_kd=r.number("remote_policy_controller", "stale_kd"),
        erob_kp=r.number("remote_policy_controller", "erob_kp"),
        erob_kd=r.number("remote_policy_controller", "erob_kd"),
    )
    imp = r.params("erob_impedance_manager")
    if "torque_efficiency" in imp:
        raise ConfigError(path, "erob_impedance_manager.ros__parameters.torque_efficiency",
                          "is set here and in the hardware file", "set it only in prime_hardware.yaml")
    parallel = imp.get("parallel_sdo", True)
    if not isinstance(parallel, bool):
        raise ConfigError(path, "erob_impedance_manager.ros__parameters.parallel_sdo",
                          f"expected true or false, got {parallel!r}")
    retries = imp.get("sdo_retries", 3)
    if isinstance(retries, bool) or not isinstance(retries, int) or not 0 <= retries <= 20:
        raise ConfigError(path, "erob_impedance_manager.ros__parameters.sdo_retries",
                          f"expected an integer 0..20, got {retries!r}")

    sim_update_rate = r.number("mujoco_simulation", "update_rate", allow_equal=False)
    physics_rate = r.number("mujoco_simulation", "physics_rate", allow_equal=False, maximum=MAX_PHYSICS_RATE_HZ,
                            why_maximum="MuJoCo steps below 0.1 ms gain nothing and stall the simulation")
    ratio = physics_rate / sim_update_rate
    if ratio < 1 or abs(ratio - round(ratio)) > 1e-9:
        raise ConfigError(path, "mujoco_simulation.ros__parameters.physics_rate",
                          f"{physics_rate:g} Hz is not a whole multiple of the simulation update_rate "
                          f"{sim_update_rate:g} Hz", "physics steps a whole number of times per control tick")
    return ControllersConfig(
        path=path,
        update_rate=r.number("controller_manager", "update_rate", allow_equal=False, maximum=MAX_UPDATE_RATE_HZ,
                             why_maximum="SYNC0 is the loop period, and the eRob's minimum cycle is 500 us"),
        bringup_rate=r.number("controller_manager", "bringup_rate", allow_equal=False, default=1000.0,
                              maximum=MAX_BRINGUP_RATE_HZ),
        sim_update_rate=sim_update_rate,
        physics_rate=physics_rate,
        joint_states_topic=r.text("joint_state_broadcaster", "topic", "/prime/joint_states"),
        damping_kd=r.number("damping_controller", "kd"),
        standby=standby,
        locomotion=locomotion,
        remote=remote,
        impedance=ImpedanceParams(parallel_sdo=parallel, sdo_retries=retries),
    )


def check_command_limits(config: ControllersConfig, robot: Robot) -> None:
    """Every gain a mode controller commands within the hardware file's command limits of the family it drives,
    and every standby pose within its joints' limits: the bus would clamp either silently."""
    limits = robot.hardware.command_limits
    gains = (("locomotion_controller", "sito_kp", config.locomotion.sito_kp, "sito", "stiffness"),
             ("locomotion_controller", "sito_kd", config.locomotion.sito_kd, "sito", "damping"),
             ("damping_controller", "kd", config.damping_kd, "sito", "damping"),
             ("damping_controller", "kd", config.damping_kd, "erob", "damping"),
             ("remote_policy_controller", "stale_kd", config.remote.stale_kd, "sito", "damping"),
             ("remote_policy_controller", "stale_kd", config.remote.stale_kd, "erob", "damping"),
             *((node, f"{prefix}kp", kp, "erob", "stiffness") for node, prefix, kp, _ in _erob_gains(config)),
             *((node, f"{prefix}kd", kd, "erob", "damping") for node, prefix, _, kd in _erob_gains(config)))
    for node, key, value, family, limit in gains:
        most = getattr(limits[family], limit)
        if value > most:
            raise ConfigError(config.path, f"{node}.ros__parameters.{key}",
                              f"{value:g} is beyond the {family} {limit} limit {most:g} of {robot.hardware.path}",
                              "lower it, or raise command_limits in the hardware file")
    for pose, values in config.standby.poses.items():
        for joint, angle in values.items():
            j = robot.joints[robot.index(joint)]
            if not j.lower <= angle <= j.upper:
                raise ConfigError(config.path, f"standby_controller.ros__parameters.poses.{pose}.{joint}",
                                  f"{angle:g} rad is outside the joint's limits {j.lower:g}..{j.upper:g} rad",
                                  "give an angle the joint can reach")


def _erob_gains(config: ControllersConfig) -> tuple[tuple[str, str, float, float], ...]:
    return (("standby_controller", "", config.standby.kp, config.standby.kd),
            ("locomotion_controller", "erob_", config.locomotion.erob_kp, config.locomotion.erob_kd),
            ("remote_policy_controller", "erob_", config.remote.erob_kp, config.remote.erob_kd))
