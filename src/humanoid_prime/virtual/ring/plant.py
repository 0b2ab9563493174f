"""The mechanics the emulated drives move. A Plant takes one motor torque per drive and integrates;
the drives read its joint state. Values are the drive's own (raw: before calibration), one per ring
position; ``external`` is a torque an operator or a test load applies.

``InertiaPlant``: one independent joint per drive with inertia, viscous friction, a gravity term
``-gravity * sin(q)`` (q = 0 hanging), optional hard stops and the holding brake of a disabled drive.
``MujocoPlant``: the arms in MuJoCo, coupled, with the description's joint limits as hard stops.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import mujoco
import numpy as np

from humanoid_prime.config.calibration import Calibration, load_calibration
from humanoid_prime.config.robot import Robot, load_robot
from humanoid_prime.drivers.mujoco.system import load_model
from humanoid_prime.errors import PrimeError

STOP_STIFFNESS_NM_PER_RAD = 2000.0
STOP_DAMPING_NM_S_PER_RAD = 50.0

# Per ring position within one arm (shoulder pitch, roll, yaw, elbow pitch, wrist yaw): output-side
# inertia including the reflected rotor (kg*m^2) and the gravity torque amplitude (Nm) of a hanging arm.
ARM_INERTIA = (0.6, 0.5, 0.2, 0.15, 0.05)
ARM_GRAVITY = (10.0, 10.0, 0.0, 2.0, 0.0)
ARM_FRICTION = (0.5, 0.5, 0.3, 0.3, 0.1)


class Plant(ABC):
    """Joint state ``q`` (rad) and ``qd`` (rad/s) and the external torque, one entry per drive."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.q = np.zeros(n)
        self.qd = np.zeros(n)
        self.external = np.zeros(n)

    @abstractmethod
    def step(self, torque: np.ndarray, braked: np.ndarray, dt: float) -> None:
        """Advance by ``dt`` under the motor ``torque`` (Nm); joints where ``braked`` is True hold still."""


class InertiaPlant(Plant):
    def __init__(self, inertia: np.ndarray, *, friction: np.ndarray | None = None,
                 gravity: np.ndarray | None = None, lower: np.ndarray | None = None,
                 upper: np.ndarray | None = None) -> None:
        inertia = np.asarray(inertia, dtype=float)
        super().__init__(len(inertia))
        if np.any(inertia <= 0):
            raise ValueError("every joint inertia must be positive")
        self.inertia = inertia
        self.friction = np.zeros(self.n) if friction is None else np.asarray(friction, dtype=float)
        self.gravity = np.zeros(self.n) if gravity is None else np.asarray(gravity, dtype=float)
        self.lower = np.full(self.n, -np.inf) if lower is None else np.asarray(lower, dtype=float)
        self.upper = np.full(self.n, np.inf) if upper is None else np.asarray(upper, dtype=float)
        self._acc = np.zeros(self.n)
        self._stop = np.zeros(self.n)

    @classmethod
    def arms(cls, n: int) -> InertiaPlant:
        """Default mechanics for ``n`` drives laid out as Prime's ring (five per arm)."""
        pick = [i % len(ARM_INERTIA) for i in range(n)]
        return cls(np.array([ARM_INERTIA[i] for i in pick]), friction=np.array([ARM_FRICTION[i] for i in pick]),
                   gravity=np.array([ARM_GRAVITY[i] for i in pick]))

    def step(self, torque: np.ndarray, braked: np.ndarray, dt: float) -> None:
        acc = self._acc
        np.sin(self.q, out=acc)
        acc *= -self.gravity
        acc += torque
        acc += self.external
        acc -= self.friction * self.qd
        stop = self._stop
        stop[:] = 0.0
        below = self.q < self.lower
        above = self.q > self.upper
        if below.any() or above.any():
            damping = STOP_DAMPING_NM_S_PER_RAD * self.qd
            stop[below] = (STOP_STIFFNESS_NM_PER_RAD * (self.lower - self.q) - damping)[below]
            stop[above] = (STOP_STIFFNESS_NM_PER_RAD * (self.upper - self.q) - damping)[above]
            acc += stop
        acc /= self.inertia
        self.qd += acc * dt
        self.qd[braked] = 0.0
        self.q += self.qd * dt


class MujocoPlant(Plant):
    """Prime's arms in MuJoCo (the model ``drivers.mujoco.system.load_model`` builds). Ring position ``i`` is the
    joint ``joints.erob_slaves`` maps to ``i``; its raw angle is ``direction * q + homing_offset`` with the
    given calibration (the emulated robot's encoders). Drive torques enter as generalised forces; joints of
    braked drives and the Sito wrist joints (not on this ring) are held where they are."""

    def __init__(self, robot: Robot, calibration: Calibration, *, physics_dt_s: float = 0.001) -> None:
        by_position = {position: joint for joint, position in robot.hardware.erob_slaves.items()}
        n = len(by_position)
        if sorted(by_position) != list(range(n)):
            raise PrimeError(f"joints.erob_slaves must use ring positions 0..{n - 1}, got {sorted(by_position)}")
        super().__init__(n)
        names = [by_position[i] for i in range(n)]
        self.model = load_model(robot, physics_rate=1.0 / physics_dt_s)
        self.data = mujoco.MjData(self.model)
        self._qpos_adr = np.array([self.model.joint(j).qposadr[0] for j in names], dtype=np.intp)
        self._dof_adr = np.array([self.model.joint(j).dofadr[0] for j in names], dtype=np.intp)
        others = [j.name for j in robot.joints if j.name not in names]
        self._other_qpos = np.array([self.model.joint(j).qposadr[0] for j in others], dtype=np.intp)
        self._other_dof = np.array([self.model.joint(j).dofadr[0] for j in others], dtype=np.intp)
        self._other_hold = self.data.qpos[self._other_qpos].copy()
        self.direction = calibration.direction_array(tuple(names))
        self.offset = calibration.offset_array(tuple(names))
        self._hold = np.zeros(n)
        self._was_braked = np.zeros(n, dtype=bool)
        self._published = np.zeros(n)
        mujoco.mj_forward(self.model, self.data)
        self._publish()

    def _publish(self) -> None:
        self.q[:] = self.direction * self.data.qpos[self._qpos_adr] + self.offset
        self.qd[:] = self.direction * self.data.qvel[self._dof_adr]
        self._published[:] = self.q

    def step(self, torque: np.ndarray, braked: np.ndarray, dt: float) -> None:
        data = self.data
        moved = self.q != self._published  # set from outside (a test placing a joint)
        if moved.any():
            data.qpos[self._qpos_adr[moved]] = (self.direction * (self.q - self.offset))[moved]
            data.qvel[self._dof_adr[moved]] = 0.0
            self._hold[moved] = data.qpos[self._qpos_adr[moved]]
        engaged = braked & ~self._was_braked
        self._hold[engaged] = data.qpos[self._qpos_adr[engaged]]
        self._was_braked[:] = braked
        data.qfrc_applied[:] = 0.0
        data.qfrc_applied[self._dof_adr] = self.direction * (torque + self.external)
        for _ in range(max(1, round(dt / self.model.opt.timestep))):
            mujoco.mj_step(self.model, data)
            held = self._qpos_adr[braked]
            data.qpos[held] = self._hold[braked]
            data.qvel[self._dof_adr[braked]] = 0.0
            data.qpos[self._other_qpos] = self._other_hold
            data.qvel[self._other_dof] = 0.0
        self._publish()


def make_plant(kind: str, slaves: int, physics_dt_s: float) -> Plant:
    """The plant named by the ``plant`` option, for ``slaves`` drives."""
    if kind == "inertia":
        return InertiaPlant.arms(slaves)
    robot = load_robot()
    if slaves != len(robot.hardware.erob_slaves):
        raise PrimeError(f"the mujoco plant drives Prime's {len(robot.hardware.erob_slaves)} eRob joints; "
                         f"got {slaves} slaves (use --slaves {len(robot.hardware.erob_slaves)} or --plant inertia)")
    return MujocoPlant(robot, load_calibration(robot.hardware), physics_dt_s=physics_dt_s)
