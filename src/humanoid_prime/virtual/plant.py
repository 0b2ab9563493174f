"""One MuJoCo plant for all 14 joints, seen by the emulated drives in their own raw frames.

The ring's drives take ``PrimePlant`` as their plant (one entry per ring position); the Sito motor
emulator takes ``sito_plant(joint)`` per wrist. Each physics step the ring hands over the eRob motor
torques, the Sito emulator runs one firmware tick (reading its CAN frames, applying its MIT law), and
then the world advances once for everybody.

Every joint can carry a factory encoder offset and a wiring direction (the robot's "true" calibration):
``raw = direction * q + offset`` where ``q`` is the joint angle of the description. The calibration
workflow has to recover exactly these numbers.
"""

from __future__ import annotations

from collections.abc import Mapping

import mujoco
import numpy as np

from humanoid_prime.config.calibration import Calibration, JointCalibration
from humanoid_prime.config.robot import Robot
from humanoid_prime.drivers.mujoco.system import load_model
from humanoid_prime.virtual.ring.plant import Plant
from humanoid_prime.virtual.sito import MotorSidePlant

HAND_GAIN_MAX = 40.0  # Nm*s/rad: a firm hand
HAND_STABILITY = 0.5  # fraction of inertia/dt: the explicit speed loop stays well inside its stability bound


class _WristJoint:
    """A wrist joint of the shared model, in the joint frame: its torque is applied at the next world step."""

    def __init__(self, plant: PrimePlant, joint: str) -> None:
        self.plant = plant
        self.joint = joint
        self.dof = plant.dof[joint]
        self.qpos = plant.qpos[joint]

    def state(self) -> tuple[float, float]:
        data = self.plant.data
        return float(data.qpos[self.qpos]), float(data.qvel[self.dof])

    def step(self, torque: float, dt: float) -> None:
        self.plant.wrist_torque[self.joint] = torque


class PrimePlant(Plant):
    """The ring's plant (ring order, raw frames) over a MuJoCo model of the whole robot."""

    def __init__(self, robot: Robot, truth: Calibration, *, physics_dt: float = 0.001,
                 initial_pose: Mapping[str, float] | None = None) -> None:
        hw = robot.hardware
        self.ring_joints = [j for j, _ in sorted(hw.erob_slaves.items(), key=lambda item: item[1])]
        super().__init__(len(self.ring_joints))
        self.robot = robot
        self.truth = truth
        self.model = load_model(robot, physics_rate=1.0 / physics_dt)
        # Mechanical stops are metal: the stiffest limit constraint stable at this step (time constant 2 dt).
        self.model.jnt_solref[:] = (2.0 * physics_dt, 1.0)
        self.data = mujoco.MjData(self.model)
        self.dof = {j: int(self.model.jnt_dofadr[self._joint_id(j)]) for j in robot.names}
        self.qpos = {j: int(self.model.jnt_qposadr[self._joint_id(j)]) for j in robot.names}
        self._ring_dof = np.array([self.dof[j] for j in self.ring_joints], dtype=np.intp)
        self._ring_qpos = np.array([self.qpos[j] for j in self.ring_joints], dtype=np.intp)
        self._direction = np.array([truth.joints[j].direction for j in self.ring_joints], dtype=float)
        self._offset = np.array([truth.joints[j].homing_offset for j in self.ring_joints], dtype=float)
        self._held = np.full(self.n, np.nan)
        self._torque = np.zeros(self.n)
        self._braked = np.ones(self.n, dtype=bool)
        self.wrist_torque: dict[str, float] = {j: 0.0 for j in hw.sito_joints}
        self.joint_external = np.zeros(robot.n)  # joint-frame external torque per canonical joint (Nm)
        self._canonical_dof = np.array([self.dof[j] for j in robot.names], dtype=np.intp)
        self._sito_step = None
        for joint, value in (initial_pose or {}).items():
            self.data.qpos[self.qpos[joint]] = value
        mujoco.mj_forward(self.model, self.data)
        # An operator's hand: moves a joint at a set speed with a capped force (HAND_* below). Its gain per
        # joint is what the joint's inertia allows at this step without going unstable.
        inertia = np.zeros((self.model.nv, self.model.nv))
        mujoco.mj_fullM(self.model, self.data, inertia)
        own = np.diag(inertia)[self._canonical_dof]
        self.hand_gain = np.minimum(HAND_STABILITY * own / physics_dt, HAND_GAIN_MAX)
        self.hand_speed = np.zeros(robot.n)
        self.hand_force = np.zeros(robot.n)  # 0: no hand on that joint
        self._hand = np.zeros(robot.n)
        self._refresh()

    def _joint_id(self, joint: str) -> int:
        return mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, joint)

    def attach_sito(self, step: object) -> None:
        """Tick the Sito emulator (``step(dt)``, which calls back ``world_step``) on every physics step."""
        self._sito_step = step

    def _refresh(self) -> None:
        self.q[:] = self._direction * self.data.qpos[self._ring_qpos] + self._offset
        self.qd[:] = self._direction * self.data.qvel[self._ring_dof]

    def step(self, torque: np.ndarray, braked: np.ndarray, dt: float) -> None:
        np.copyto(self._torque, torque)
        np.copyto(self._braked, braked)
        if self._sito_step is not None:
            self._sito_step(dt)  # one firmware tick; it calls world_step(dt)
        else:
            self.world_step(dt)

    def world_step(self, dt: float) -> None:
        data = self.data
        applied = data.qfrc_applied
        applied[:] = 0.0
        hand = self._hand
        np.subtract(self.hand_speed, data.qvel[self._canonical_dof], out=hand)
        hand *= self.hand_gain
        hand += data.qfrc_bias[self._canonical_dof]  # a hand carries the limb's weight while it moves it
        np.clip(hand, -self.hand_force, self.hand_force, out=hand)
        hand += self.joint_external
        applied[self._canonical_dof] = hand
        applied[self._ring_dof] += self._direction * (self._torque + self.external)
        for joint, tau in self.wrist_torque.items():
            applied[self.dof[joint]] += tau
        mujoco.mj_step(self.model, data)
        # A disabled eRob holds its brake: the joint stays where it was when the brake closed.
        held = self._held
        for i in range(self.n):
            if self._braked[i]:
                if np.isnan(held[i]):
                    held[i] = data.qpos[self._ring_qpos[i]]
                data.qpos[self._ring_qpos[i]] = held[i]
                data.qvel[self._ring_dof[i]] = 0.0
            else:
                held[i] = np.nan
        self._refresh()

    def sito_plant(self, joint: str) -> MotorSidePlant:
        """The Sito emulator's plant for a wrist: the joint seen through its wiring and factory offset."""
        cal = self.truth.joints[joint]
        return MotorSidePlant(_WristJoint(self, joint), cal.direction, cal.homing_offset)

    def joint_positions(self) -> dict[str, float]:
        """True joint angles (description frame) of every joint."""
        return {j: float(self.data.qpos[self.qpos[j]]) for j in self.robot.names}

    def set_joint_external(self, joint: str, torque_nm: float) -> None:
        self.joint_external[self.robot.index(joint)] = torque_nm

    def set_hand(self, joint: str, speed_rad_s: float, force_nm: float) -> None:
        """Move ``joint`` at ``speed_rad_s`` (joint frame) pushing with at most ``force_nm``; force 0 lets go."""
        i = self.robot.index(joint)
        self.hand_speed[i] = speed_rad_s
        self.hand_force[i] = abs(force_nm)


def truth_calibration(robot: Robot, overrides: Calibration | None = None) -> Calibration:
    """The virtual robot's wiring and factory offsets: identity unless ``overrides`` says otherwise."""
    joints = {j: JointCalibration() for j in robot.names}
    if overrides is not None:
        joints.update(overrides.joints)
    return Calibration(joints)
