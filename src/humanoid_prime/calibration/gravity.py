"""What gravity asks of each joint, how heavy each joint is to turn, and where its axis points, from the package's
MuJoCo model.

``torques(q)`` is the torque every joint must apply to hold the arms still at ``q`` (description joint
frame, Nm): MuJoCo's bias force at zero velocity. ``inertia(q)``: each joint's inertia about its axis at ``q``.
``axis(joint, q)`` is the joint's axis in the world (x forward, y to the robot's left, z up) at ``q``: a positive
rotation turns counter-clockwise seen from its tip.
"""

from __future__ import annotations

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
        self._moved: dict[tuple[int, ...], tuple[npt.NDArray[np.intp], ...]] = {}

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
        data = self.data
        data.qpos[self.qpos] = q
        mujoco.mj_kinematics(self.model, data)
        geoms, segment, box, radius, half_length, size, rbound = self._geoms(joints)
        axes = np.abs(data.geom_xmat[geoms].reshape(-1, 3, 3)[:, 1, :])  # each geom axis's share along y
        half = np.where(segment, axes[:, 2] * half_length + radius,
                        np.where(box, np.einsum("ij,ij->i", axes, size), rbound))
        y = data.geom_xpos[geoms, 1]
        return float(np.min(y - half)), float(np.max(y + half))

    def _geoms(self, joints: Sequence[int]) -> tuple[npt.NDArray[np.intp], ...]:
        """The colliding geoms on the bodies that ``joints`` move, and what ``lateral`` needs of their shapes."""
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
            geoms = np.array([g for g in range(model.ngeom) if int(model.geom_bodyid[g]) in moved
                              and (model.geom_contype[g] or model.geom_conaffinity[g])], dtype=np.intp)
            kind = model.geom_type[geoms]
            segment = (kind == mujoco.mjtGeom.mjGEOM_CAPSULE) | (kind == mujoco.mjtGeom.mjGEOM_CYLINDER)
            found = (geoms, segment, kind == mujoco.mjtGeom.mjGEOM_BOX, model.geom_size[geoms, 0].copy(),
                     model.geom_size[geoms, 1].copy(), model.geom_size[geoms].copy(), model.geom_rbound[geoms].copy())
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
