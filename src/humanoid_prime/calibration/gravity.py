"""What gravity asks of each joint, how heavy each joint is to turn, and where its axis points, from the package's
MuJoCo model.

``torques(q)`` is the torque every joint must apply to hold the arms still at ``q`` (description joint
frame, Nm): MuJoCo's bias force at zero velocity. ``inertia(q)``: each joint's inertia about its axis at ``q``.
``axis(joint, q)`` is the joint's axis in the world (x forward, y to the robot's left, z up) at ``q``: a positive
rotation turns counter-clockwise seen from its tip.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import mujoco
import numpy as np
import numpy.typing as npt

from humanoid_prime.config.model import load_model
from humanoid_prime.config.robot import Robot


class GravityModel:
    """``model``: a compiled model of ``robot`` to share (compiling one takes a while; a running loop's keeper
    should not wait for it); default: compile the package's."""

    def __init__(self, robot: Robot, model: mujoco.MjModel | None = None) -> None:
        self.robot = robot
        self.model = model if model is not None else load_model(robot)
        self.data = mujoco.MjData(self.model)
        ids = [mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, name) for name in robot.names]
        self.joint_ids = np.array(ids, dtype=np.intp)
        self.qpos = self.model.jnt_qposadr[self.joint_ids].astype(np.intp)
        self.dof = self.model.jnt_dofadr[self.joint_ids].astype(np.intp)
        self._torques = np.zeros(robot.n)
        self._moved: dict[tuple[int, ...], list[int]] = {}

    def torques(self, q: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """Holding torque of every joint at ``q`` (canonical order); the returned array is reused."""
        data = self.data
        data.qpos[self.qpos] = q
        data.qvel[:] = 0.0
        mujoco.mj_forward(self.model, data)
        np.take(data.qfrc_bias, self.dof, out=self._torques)
        return self._torques

    def axis(self, joint: str, q: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """The world direction of ``joint``'s axis at ``q``."""
        data = self.data
        data.qpos[self.qpos] = q
        mujoco.mj_kinematics(self.model, data)
        return np.array(data.xaxis[self.joint_ids[self.robot.index(joint)]], dtype=np.float64)

    def lateral(self, q: npt.NDArray[np.float64], joints: Sequence[int]) -> tuple[float, float]:
        """The lowest and highest y (to the robot's left, m) that the collision geoms moved by ``joints`` (canonical
        indices) reach at ``q``: a capsule's or cylinder's segment and radius, a box's corners, else its bounding
        sphere."""
        model, data = self.model, self.data
        data.qpos[self.qpos] = q
        mujoco.mj_kinematics(model, data)
        low, high = math.inf, -math.inf
        for g in self._geoms(joints):
            y, axes, size = float(data.geom_xpos[g][1]), data.geom_xmat[g].reshape(3, 3)[1], model.geom_size[g]
            kind = model.geom_type[g]
            if kind in (mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_CYLINDER):
                half = abs(float(axes[2])) * float(size[1]) + float(size[0])
            elif kind == mujoco.mjtGeom.mjGEOM_BOX:
                half = float(np.abs(axes) @ size)
            else:
                half = float(model.geom_rbound[g])
            low, high = min(low, y - half), max(high, y + half)
        return low, high

    def _geoms(self, joints: Sequence[int]) -> list[int]:
        """The colliding geoms on the bodies that ``joints`` move."""
        key = tuple(joints)
        found = self._moved.get(key)
        if found is None:
            model = self.model
            bodies = {int(model.jnt_bodyid[self.joint_ids[j]]) for j in joints}
            moved = set()
            for b in range(model.nbody):
                chain = b
                while chain > 0 and chain not in bodies:
                    chain = int(model.body_parentid[chain])
                if chain in bodies:
                    moved.add(b)
            found = [g for g in range(model.ngeom) if int(model.geom_bodyid[g]) in moved
                     and (model.geom_contype[g] or model.geom_conaffinity[g])]
            self._moved[key] = found
        return found

    def inertia(self, q: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """Each joint's inertia about its own axis at ``q`` (kg m^2, the mass matrix's diagonal, armature
        included): what accelerating that joint alone asks."""
        data = self.data
        data.qpos[self.qpos] = q
        mujoco.mj_forward(self.model, data)
        full = np.zeros((self.model.nv, self.model.nv))
        mujoco.mj_fullM(self.model, data, full)
        return np.array(full[self.dof, self.dof], dtype=np.float64)
