"""What gravity asks of each joint, and where each joint's axis points, from the package's MuJoCo model.

``torques(q)`` is the torque every joint must apply to hold the arms still at ``q`` (description joint
frame, Nm): MuJoCo's bias force at zero velocity. ``axis(joint, q)`` is the joint's axis in the world
(x forward, y to the robot's left, z up) at ``q``: a positive rotation turns counter-clockwise seen from its tip.
"""

from __future__ import annotations

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
