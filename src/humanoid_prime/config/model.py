"""The robot's MuJoCo model: ``data/description/prime.xml`` compiled with the description's joint ranges (hard
stops) and one MIT actuator per joint at the description's effort limit, after checking that its tree, joint
origins and axes are the description's. The simulation, the gate's body check, the gravity model and the view all
compile it here, so they share one geometry.

Collision: the arm, torso and pedestal geoms collide in three classes (``contype``/``conaffinity`` bits: the left
arm, the right arm, the body), so an arm meets the other arm and the body but never itself or its own parts, and the
parent-child pairs where an arm joins the torso are excluded (``<contact><exclude>``). ``BODY_GROUPS`` names the
classes.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
import numpy.typing as npt

from humanoid_prime.config.robot import Robot
from humanoid_prime.errors import ConfigError
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
