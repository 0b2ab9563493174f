"""``MujocoSystem``: the simulated Prime, one hardware component owning all 14 joints.

The MIT law ``tau = kp(q_cmd - q) + kd(qd_cmd - qd) + tau_ff``, saturated to each joint's effort limit,
is applied by MuJoCo itself at every physics step with the live q and qd: each joint has one affine
actuator whose bias terms are ``-kp*q - kd*qd`` and whose control is ``kp*q_cmd + kd*qd_cmd + tau_ff``.
``write`` sets those per tick and advances physics by one control period, so simulated time moves
exactly ``physics_rate / update_rate`` steps per tick; the seconds those steps take are the tick's plant time
(``io_s``), as the wire and the emulator are on the buses, so the tick's cost minus them is our own CPU.

The system may own a subset of the joints (``joints``); the actuators of the others stay at zero gain
and zero control, so another component (e.g. emulated motors applying their own torque) drives them.
``advance`` replaces MuJoCo's own step, once per physics step, for whoever must run alongside physics.

The model is ``data/description/prime.xml``. The robot description is authoritative: the loader checks
that the model has the description's bodies, joint origins and axes, sets every joint range from the
description's limits (hard stops), and generates the actuators with the description's effort limits.
"""

from __future__ import annotations

import math
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
import numpy.typing as npt

from humanoid_prime.config.robot import Robot
from humanoid_prime.control.hardware import HardwareComponent
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.errors import ConfigError, PrimeError
from humanoid_prime.files import bundled

MODEL_FILE = "description/prime.xml"
ACTUATOR_SUFFIX = "_mit"
_TOLERANCE = 1e-6


@dataclass(frozen=True)
class _UrdfJoint:
    name: str
    kind: str
    parent: str
    child: str
    xyz: npt.NDArray[np.float64]
    quat: npt.NDArray[np.float64]
    axis: npt.NDArray[np.float64]


def _rpy_quat(rpy: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """URDF fixed-axis roll-pitch-yaw as a MuJoCo (w, x, y, z) quaternion."""
    r, p, y = rpy / 2.0
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array([
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ])


def _vector(element: ET.Element | None, key: str, default: str) -> npt.NDArray[np.float64]:
    text = element.get(key, default) if element is not None else default
    return np.array([float(v) for v in text.split()])


def _urdf_joints(urdf: str) -> list[_UrdfJoint]:
    joints = []
    for joint in ET.fromstring(urdf).findall("joint"):
        origin = joint.find("origin")
        axis = _vector(joint.find("axis"), "xyz", "1 0 0")
        parent, child = joint.find("parent"), joint.find("child")
        assert parent is not None and child is not None  # a URDF joint has both (the xacro's own output)
        joints.append(_UrdfJoint(
            name=joint.get("name", ""),
            kind=joint.get("type", ""),
            parent=parent.get("link", ""),
            child=child.get("link", ""),
            xyz=_vector(origin, "xyz", "0 0 0"),
            quat=_rpy_quat(_vector(origin, "rpy", "0 0 0")),
            axis=axis / np.linalg.norm(axis),
        ))
    return joints


def load_model(robot: Robot, model_path: str | Path | None = None, *, physics_rate: float = 1000.0) -> mujoco.MjModel:
    """Compile the MJCF with the description's joint ranges and effort limits, after checking its tree."""
    path = Path(model_path) if model_path is not None else bundled(MODEL_FILE)
    try:
        spec = mujoco.MjSpec.from_file(str(path))
    except Exception as exc:  # MuJoCo raises plain errors with the parser's text
        raise ConfigError(path, "", f"cannot load the MuJoCo model: {str(exc).strip()}") from None

    urdf_joints = _urdf_joints(robot.description.urdf)
    described = {j.name for j in urdf_joints if j.kind != "fixed"}
    source = robot.description.source.name
    for joint in spec.joints:
        if joint.name not in described:
            raise ConfigError(path, f"joint {joint.name}", f"is not an actuated joint of {source}",
                              "remove it from the model or add it to the description")
    for spec_joint in robot.joints:
        joint = spec.joint(spec_joint.name)
        if joint is None:
            raise ConfigError(path, f"joint {spec_joint.name}", "missing from the MuJoCo model",
                              f"add a hinge joint named {spec_joint.name} as in {source}")
        joint.limited = mujoco.mjtLimited.mjLIMITED_TRUE
        joint.range = [spec_joint.lower, spec_joint.upper]

    if len(spec.actuators):
        raise ConfigError(path, f"actuator {spec.actuators[0].name}", "the model declares actuators",
                          "remove them: the MIT actuators are generated from the description's effort limits")
    for spec_joint in robot.joints:
        actuator = spec.add_actuator()
        actuator.name = spec_joint.name + ACTUATOR_SUFFIX
        actuator.target = spec_joint.name
        actuator.trntype = mujoco.mjtTrn.mjTRN_JOINT
        actuator.gaintype = mujoco.mjtGain.mjGAIN_FIXED
        actuator.gainprm[0] = 1.0
        actuator.biastype = mujoco.mjtBias.mjBIAS_AFFINE
        actuator.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        actuator.forcerange = [-spec_joint.effort_limit, spec_joint.effort_limit]
    spec.option.timestep = 1.0 / physics_rate

    try:
        model = spec.compile()
    except Exception as exc:
        raise ConfigError(path, "", f"MuJoCo cannot compile the model: {str(exc).strip()}") from None
    _check_tree(model, urdf_joints, path, source)
    return model


def _check_tree(model: mujoco.MjModel, urdf_joints: list[_UrdfJoint], path: Path, source: str) -> None:
    """Every description joint is the same parent -> child step in the model, at the same origin and axis."""
    for uj in urdf_joints:
        where = f"joint {uj.name}"
        child = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, uj.child)
        if child < 0:
            raise ConfigError(path, where, f"has no body {uj.child!r}", f"add it as in {source}")
        parent = model.body(int(model.body_parentid[child])).name
        if parent != uj.parent:
            raise ConfigError(path, where, f"body {uj.child} hangs from {parent}, the description says {uj.parent}",
                              "fix the model's body nesting")
        body = model.body(child)
        same_quat = min(np.abs(body.quat - uj.quat).max(), np.abs(body.quat + uj.quat).max()) < _TOLERANCE
        if np.abs(body.pos - uj.xyz).max() > _TOLERANCE or not same_quat:
            raise ConfigError(path, where,
                              f"body {uj.child} is at pos {body.pos.tolist()} quat {body.quat.tolist()}, "
                              f"the description says xyz {uj.xyz.tolist()} quat {uj.quat.round(6).tolist()}",
                              "make the model's body origin match the description's joint origin")
        body_joints = [model.joint(int(model.body_jntadr[child]) + k) for k in range(int(model.body_jntnum[child]))]
        if uj.kind == "fixed":
            if body_joints:
                raise ConfigError(path, where, f"is fixed in the description but body {uj.child} has a joint "
                                  f"{body_joints[0].name}", "remove the joint from the model")
            continue
        wanted = mujoco.mjtJoint.mjJNT_HINGE if uj.kind == "revolute" else mujoco.mjtJoint.mjJNT_SLIDE
        if len(body_joints) != 1 or body_joints[0].name != uj.name or int(body_joints[0].type[0]) != wanted:
            names = [j.name for j in body_joints] or "none"
            raise ConfigError(path, where, f"body {uj.child} must carry exactly this {uj.kind} joint (has {names})",
                              "fix the model's joints")
        joint = body_joints[0]
        if np.abs(joint.axis - uj.axis).max() > _TOLERANCE or np.abs(joint.pos).max() > _TOLERANCE:
            raise ConfigError(path, where, f"axis {joint.axis.tolist()} at {joint.pos.tolist()} differs from the "
                              f"description's axis {uj.axis.tolist()} at the body origin",
                              "make the model's joint axis match the description")


class MujocoSystem(HardwareComponent):
    """The joints in MuJoCo (default all 14), in canonical order; the MIT law at ``physics_rate`` with live state.

    ``joints``: the subset this component owns. ``advance(dt)``: called once per physics step instead of
    ``mujoco.mj_step``; it must step the world exactly once.
    """

    def __init__(self, robot: Robot, *, physics_rate: float = 1000.0, update_rate: float = 200.0,
                 model_path: str | Path | None = None, initial_pose: Mapping[str, float] | None = None,
                 name: str = "MujocoSystem", joints: tuple[str, ...] | None = None,
                 advance: Callable[[float], None] | None = None) -> None:
        owned = robot.names if joints is None else tuple(joints)
        unknown = [j for j in owned if j not in robot.names]
        if unknown or len(set(owned)) != len(owned) or not owned:
            raise PrimeError(f"{name}: joints must be distinct joints of the robot, got {', '.join(owned) or 'none'}"
                             f"; known joints: {', '.join(robot.names)}")
        owned = tuple(j for j in robot.names if j in owned)  # canonical order
        super().__init__(name, robot, owned)
        ratio = physics_rate / update_rate if update_rate > 0 else 0.0
        if not (physics_rate > 0 and ratio >= 1 and abs(ratio - round(ratio)) < 1e-9):
            raise PrimeError(f"simulation rates: physics_rate {physics_rate:g} Hz must be a whole multiple of the "
                             f"control rate {update_rate:g} Hz (set mujoco_simulation.update_rate and "
                             "physics_rate in prime_controllers.yaml)")
        self.robot = robot
        self.physics_rate = float(physics_rate)
        self.update_rate = float(update_rate)
        self.substeps = round(ratio)
        self.advance = advance
        self.model = load_model(robot, model_path, physics_rate=physics_rate)
        self.data = mujoco.MjData(self.model)
        self.physics_dt = float(self.model.opt.timestep)

        joint_ids = [self.model.joint(n).id for n in owned]
        self.qpos_adr = self.model.jnt_qposadr[joint_ids].astype(np.intp)
        self.dof_adr = self.model.jnt_dofadr[joint_ids].astype(np.intp)
        # Actuators are generated in canonical order, one per robot joint; these are the owned joints' ones.
        self._actuators = slice(None) if owned == robot.names else self.indices
        self._bias_kp = self.model.actuator_biasprm[:, 1]
        self._bias_kd = self.model.actuator_biasprm[:, 2]
        n = len(owned)
        self._kp = np.zeros(n)
        self._kd = np.zeros(n)
        self._u = np.zeros(n)
        self._a = np.zeros(n)
        self._b = np.zeros(n)
        # Views into MuJoCo's buffers, taken once.
        self._qpos, self._qvel, self._ctrl = self.data.qpos, self.data.qvel, self.data.ctrl
        self._force = self.data.actuator_force
        if initial_pose:
            self.set_pose(initial_pose)
        mujoco.mj_forward(self.model, self.data)

    @property
    def sim_time(self) -> float:
        """Simulated seconds since the start."""
        return float(self.data.time)

    @property
    def period(self) -> float:
        return self.substeps / self.physics_rate

    def set_pose(self, pose: Mapping[str, float]) -> None:
        """Place joints of the model (rad, joint frame, owned or not) at rest; joints left out keep their position."""
        names = self.robot.names
        for joint, value in pose.items():
            if joint not in names:
                raise PrimeError(f"initial pose: {joint!r} matches no joint; known joints: {', '.join(names)}")
            spec = self.robot.joints[self.robot.index(joint)]
            if not spec.lower <= value <= spec.upper:
                raise PrimeError(f"initial pose: {joint} = {value:g} rad is outside its limits "
                                 f"[{spec.lower:g}, {spec.upper:g}]")
            model_joint = self.model.joint(joint)
            self.data.qpos[model_joint.qposadr[0]] = value
            self.data.qvel[model_joint.dofadr[0]] = 0.0
        mujoco.mj_forward(self.model, self.data)

    def on_activate(self) -> None:
        self._limp()

    def on_deactivate(self) -> None:
        self._limp()

    def _limp(self) -> None:
        self._bias_kp[:] = 0.0
        self._bias_kd[:] = 0.0
        self._ctrl[:] = 0.0

    def read(self, now: float, state: StateArrays) -> None:
        idx = self.indices
        self._qpos.take(self.qpos_adr, out=self._a)
        state.position[idx] = self._a
        self._qvel.take(self.dof_adr, out=self._a)
        state.velocity[idx] = self._a
        self._force.take(self.indices, out=self._a)
        state.effort[idx] = self._a

    def write(self, now: float, command: CommandArrays) -> None:
        idx, actuators = self.indices, self._actuators
        u = self._u
        command.stiffness.take(idx, out=self._kp)
        command.damping.take(idx, out=self._kd)
        np.negative(self._kp, out=self._a)
        self._bias_kp[actuators] = self._a
        np.negative(self._kd, out=self._a)
        self._bias_kd[actuators] = self._a
        command.position.take(idx, out=self._a)
        np.multiply(self._kp, self._a, out=u)
        command.velocity.take(idx, out=self._a)
        np.multiply(self._kd, self._a, out=self._b)
        u += self._b
        command.effort.take(idx, out=self._a)
        u += self._a
        self._ctrl[actuators] = u
        advance = self.advance
        began = time.perf_counter()  # the physics is this component's plant time (``io_s``)
        if advance is None:
            mujoco.mj_step(self.model, self.data, nstep=self.substeps)
        else:
            dt = self.physics_dt
            for _ in range(self.substeps):
                advance(dt)
        self.io_s = time.perf_counter() - began
