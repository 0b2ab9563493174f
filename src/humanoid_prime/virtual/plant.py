"""The mechanics the emulated eRob drives and Sito motors move: one ``Plant`` abstraction for both.

A plant holds joints in the raw frames of the devices that drive them, one entry per joint: position
``q`` (rad), velocity ``qd`` (rad/s) and ``external``, a torque an operator or a test load applies (Nm).
``step(torque, braked, dt)`` applies the devices' torques for ``dt``; a braked joint (a disabled eRob's
holding brake) stays where it is.

- ``InertiaPlant``: independent joints with inertia, viscous and Coulomb friction, a gravity term
  ``-gravity * sin(q)`` (q = 0 hanging) and optional hard stops; it integrates in ``step``.
- ``PrimeWorld``: Prime in MuJoCo, one world for all 14 joints. Every joint carries the robot's "true"
  calibration, a wiring direction and a factory encoder offset: ``raw = direction * q + homing_offset``
  where ``q`` is the description's joint angle (the calibration workflow has to recover exactly these
  numbers). Devices see it through ``world.plant(joints)`` views, which record their torques; the world
  advances once per physics step for everybody, driven by the view that owns the clock (the ring's) or
  by whoever calls ``step`` (the Sito emulator beside ``MujocoSystem``).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import mujoco
import numpy as np

from humanoid_prime.config.calibration import Calibration, JointCalibration, load_calibration
from humanoid_prime.config.model import load_model
from humanoid_prime.config.robot import Robot, load_robot
from humanoid_prime.errors import PrimeError

STOP_STIFFNESS_NM_PER_RAD = 2000.0
STOP_DAMPING_NM_S_PER_RAD = 50.0
HAND_GAIN_MAX = 40.0  # Nm*s/rad: a firm hand
HAND_STABILITY = 0.5  # fraction of inertia/dt: the explicit speed loop stays well inside its stability bound

# Per ring position within one arm (shoulder pitch, roll, yaw, elbow pitch, wrist yaw): output-side
# inertia including the reflected rotor (kg*m^2), gravity torque amplitude of a hanging arm (Nm), friction.
ARM_INERTIA = (0.6, 0.5, 0.2, 0.15, 0.05)
ARM_GRAVITY = (10.0, 10.0, 0.0, 2.0, 0.0)
ARM_FRICTION = (0.5, 0.5, 0.3, 0.3, 0.1)
WRIST_INERTIA = 0.005  # kg*m^2, hand plus reflected rotor
WRIST_FRICTION = 0.01  # Nm*s/rad


class Plant(ABC):
    """Joint state ``q``, ``qd`` and the external torque, one entry per joint, in the devices' raw frames."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.q = np.zeros(n)
        self.qd = np.zeros(n)
        self.external = np.zeros(n)

    @abstractmethod
    def step(self, torque: np.ndarray, braked: np.ndarray, dt: float) -> None:
        """Apply ``torque`` (Nm, one per joint) for ``dt``; joints where ``braked`` is True hold still."""


def _per_joint(value: float | Sequence[float] | np.ndarray | None, n: int, default: float) -> np.ndarray:
    return np.full(n, default) if value is None else np.broadcast_to(np.asarray(value, dtype=float), (n,)).copy()


class InertiaPlant(Plant):
    """Independent rigid links: ``I qdd = torque + external - gravity sin(q) - friction qd - coulomb sign(qd)``,
    plus hard stops, integrated semi-implicitly in ``substeps`` per step. Coulomb friction holds a link at
    rest against a net torque it exceeds, and stops a moving link rather than reverse it."""

    def __init__(self, inertia: float | Sequence[float] | np.ndarray, *,
                 friction: float | Sequence[float] | np.ndarray | None = None,
                 coulomb: float | Sequence[float] | np.ndarray | None = None,
                 gravity: float | Sequence[float] | np.ndarray | None = None,
                 lower: float | Sequence[float] | np.ndarray | None = None,
                 upper: float | Sequence[float] | np.ndarray | None = None, substeps: int = 1) -> None:
        inertia = np.atleast_1d(np.asarray(inertia, dtype=float))
        super().__init__(len(inertia))
        if np.any(inertia <= 0):
            raise ValueError("every joint inertia must be positive")
        if substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        n = self.n
        self.inertia = inertia
        self.friction = _per_joint(friction, n, 0.0)
        self.coulomb = _per_joint(coulomb, n, 0.0)
        self.gravity = _per_joint(gravity, n, 0.0)
        self.lower = _per_joint(lower, n, -np.inf)
        self.upper = _per_joint(upper, n, np.inf)
        self.substeps = substeps
        self._net = np.zeros(n)
        self._stop = np.zeros(n)

    @classmethod
    def arms(cls, n: int) -> InertiaPlant:
        """Default mechanics for ``n`` eRob drives laid out as Prime's ring (five per arm)."""
        pick = [i % len(ARM_INERTIA) for i in range(n)]
        return cls([ARM_INERTIA[i] for i in pick], friction=[ARM_FRICTION[i] for i in pick],
                   gravity=[ARM_GRAVITY[i] for i in pick])

    @classmethod
    def wrists(cls, n: int, *, gravity: float = 0.0, coulomb: float = 0.0) -> InertiaPlant:
        """``n`` Sito wrist links (hand plus reflected rotor), integrated four times per firmware tick."""
        return cls(np.full(n, WRIST_INERTIA), friction=WRIST_FRICTION, coulomb=coulomb, gravity=gravity, substeps=4)

    def step(self, torque: np.ndarray, braked: np.ndarray, dt: float) -> None:
        h = dt / self.substeps
        net, stop = self._net, self._stop
        for _ in range(self.substeps):
            np.sin(self.q, out=net)
            net *= -self.gravity
            net += torque
            net += self.external
            net -= self.friction * self.qd
            below, above = self.q < self.lower, self.q > self.upper
            if below.any() or above.any():
                stop[:] = 0.0
                damping = STOP_DAMPING_NM_S_PER_RAD * self.qd
                stop[below] = (STOP_STIFFNESS_NM_PER_RAD * (self.lower - self.q) - damping)[below]
                stop[above] = (STOP_STIFFNESS_NM_PER_RAD * (self.upper - self.q) - damping)[above]
                net += stop
            if self.coulomb.any():
                resting = self.qd == 0.0
                stuck = resting & (np.abs(net) <= self.coulomb)
                direction = np.where(resting, np.sign(net), np.sign(self.qd))
                qd = self.qd + (net - direction * self.coulomb) / self.inertia * h
                qd[stuck] = 0.0
                qd[(self.coulomb > 0) & ~resting & (qd * self.qd < 0.0)] = 0.0  # friction stops, never reverses
                self.qd[:] = qd
            else:
                self.qd += net / self.inertia * h
            self.qd[braked] = 0.0
            self.q += self.qd * h


def truth_calibration(robot: Robot, overrides: Calibration | None = None) -> Calibration:
    """The virtual robot's wiring and factory offsets: identity unless ``overrides`` says otherwise."""
    joints = {j: JointCalibration() for j in robot.names}
    if overrides is not None:
        joints.update(overrides.joints)
    return Calibration(joints)


class PrimeWorld:
    """Prime in MuJoCo as the emulated hardware sees it (module docstring).

    ``model``/``data`` default to the bundled model at ``physics_dt``; pass another component's (the
    simulation's) to put devices on that world. ``held`` joints have no device and stay where they are.
    """

    def __init__(self, robot: Robot, truth: Calibration, *, physics_dt: float = 0.001,
                 initial_pose: Mapping[str, float] | None = None, held: Sequence[str] = (),
                 model: Any = None, data: Any = None) -> None:
        self.robot = robot
        self.truth = truth
        if model is None:
            model = load_model(robot, physics_rate=1.0 / physics_dt)
            # Mechanical stops are metal: the stiffest limit constraint stable at this step (time constant 2 dt).
            model.jnt_solref[:] = (2.0 * physics_dt, 1.0)
            data = mujoco.MjData(model)
        self.model, self.data = model, data
        n = robot.n
        ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j) for j in robot.names]
        self.dof = np.array([model.jnt_dofadr[i] for i in ids], dtype=np.intp)  # canonical order
        self.qpos = np.array([model.jnt_qposadr[i] for i in ids], dtype=np.intp)
        self.direction = truth.direction_array(robot.names)
        self.offset = truth.offset_array(robot.names)
        self.torque = np.zeros(n)  # joint frame, what the devices' views recorded for the next step
        self.braked = np.zeros(n, dtype=bool)
        self.held = np.zeros(n, dtype=bool)
        self.held[[robot.index(j) for j in held]] = True
        self._hold = np.full(n, np.nan)  # where a braked or held joint is kept
        self._views: list[MujocoPlant] = []
        self._stepper: Callable[[float], None] | None = None
        for joint, value in (initial_pose or {}).items():
            data.qpos[self.qpos[robot.index(joint)]] = value
        mujoco.mj_forward(model, data)
        # An operator's hand moves a joint at a set speed with a capped force; its gain per joint is what the
        # joint's inertia allows at this step without going unstable.
        inertia = np.zeros((model.nv, model.nv))
        mujoco.mj_fullM(model, data, inertia)
        self.hand_gain = np.minimum(HAND_STABILITY * np.diag(inertia)[self.dof] / model.opt.timestep, HAND_GAIN_MAX)
        self.hand_speed = np.zeros(n)
        self.hand_force = np.zeros(n)  # 0: no hand on that joint
        self.joint_external = np.zeros(n)  # joint-frame external torque per joint (Nm), a test load
        self._hand = np.zeros(n)

    def plant(self, joints: Sequence[str], *, clock: bool = False) -> MujocoPlant:
        """The devices' view of ``joints`` (in their order); with ``clock`` its ``step`` advances the world."""
        view = MujocoPlant(self, [self.robot.index(j) for j in joints], clock=clock)
        self._views.append(view)
        return view

    def attach(self, stepper: Callable[[float], None]) -> None:
        """Let ``stepper(dt)`` advance the world instead of ``step`` (e.g. the Sito emulator's firmware tick,
        which records the wrists' torques and then calls ``step``)."""
        self._stepper = stepper

    def advance(self, dt: float) -> None:
        (self._stepper or self.step)(dt)

    def step(self, dt: float) -> None:
        """One world step of ``dt``: hands, loads and the recorded device torques, then physics and brakes."""
        model, data = self.model, self.data
        applied = data.qfrc_applied
        applied[:] = 0.0
        hand = self._hand
        np.subtract(self.hand_speed, data.qvel[self.dof], out=hand)
        hand *= self.hand_gain
        hand += data.qfrc_bias[self.dof]  # a hand carries the limb's weight while it moves it
        np.clip(hand, -self.hand_force, self.hand_force, out=hand)
        hand += self.joint_external
        hand += self.torque
        applied[self.dof] = hand
        still = self.braked | self.held
        engaged = still & np.isnan(self._hold)  # a brake closing now holds the joint where it is
        self._hold[engaged] = data.qpos[self.qpos[engaged]]
        self._hold[~still] = np.nan
        for _ in range(max(1, round(dt / model.opt.timestep))):
            mujoco.mj_step(model, data)
            if still.any():
                data.qpos[self.qpos[still]] = self._hold[still]
                data.qvel[self.dof[still]] = 0.0
        for view in self._views:
            view.refresh()

    def joint_positions(self) -> dict[str, float]:
        """True joint angles (description frame) of every joint."""
        return {j: float(self.data.qpos[self.qpos[i]]) for i, j in enumerate(self.robot.names)}

    def set_joint_external(self, joint: str, torque_nm: float) -> None:
        self.joint_external[self.robot.index(joint)] = torque_nm

    def set_hand(self, joint: str, speed_rad_s: float, force_nm: float) -> None:
        """Move ``joint`` at ``speed_rad_s`` (joint frame) pushing with at most ``force_nm``; force 0 lets go."""
        i = self.robot.index(joint)
        self.hand_speed[i] = speed_rad_s
        self.hand_force[i] = abs(force_nm)

    def set_gravity(self, enabled: bool) -> list[float]:
        self.model.opt.gravity[:] = (0.0, 0.0, -9.81) if enabled else (0.0, 0.0, 0.0)
        return list(self.model.opt.gravity)


class MujocoPlant(Plant):
    """Some joints of a ``PrimeWorld`` in the raw frames of their devices (``PrimeWorld.plant``).

    ``step`` records the torques and brakes for the world's next step (and with ``clock`` takes that step).
    Writing ``q`` places a joint there at rest at the next step (a test setting up a pose).
    """

    def __init__(self, world: PrimeWorld, indices: Sequence[int], *, clock: bool) -> None:
        super().__init__(len(indices))
        self.world = world
        self.indices = np.asarray(indices, dtype=np.intp)
        self.clock = clock
        self.direction = world.direction[self.indices]
        self.offset = world.offset[self.indices]
        self._qpos = world.qpos[self.indices]
        self._dof = world.dof[self.indices]
        self._published = np.zeros(self.n)
        self.refresh()

    def refresh(self) -> None:
        data = self.world.data
        np.multiply(self.direction, data.qpos[self._qpos], out=self.q)
        self.q += self.offset
        np.multiply(self.direction, data.qvel[self._dof], out=self.qd)
        np.copyto(self._published, self.q)

    def step(self, torque: np.ndarray, braked: np.ndarray, dt: float) -> None:
        world = self.world
        moved = self.q != self._published
        if moved.any():
            world.data.qpos[self._qpos[moved]] = (self.direction * (self.q - self.offset))[moved]
            world.data.qvel[self._dof[moved]] = 0.0
            world._hold[self.indices[moved]] = np.nan
        world.torque[self.indices] = self.direction * (torque + self.external)
        world.braked[self.indices] = braked
        if self.clock:
            world.advance(dt)


def make_ring_plant(kind: str, slaves: int, physics_dt: float) -> Plant:
    """The plant the ring's ``plant`` option names, for ``slaves`` drives in ring order: ``inertia`` (one
    independent joint per drive) or ``mujoco`` (Prime's arms with the bundled files, the wrists held)."""
    if kind == "inertia":
        return InertiaPlant.arms(slaves)
    robot = load_robot()
    hw = robot.hardware
    if slaves != len(hw.erob_slaves):
        raise PrimeError(f"the mujoco plant drives Prime's {len(hw.erob_slaves)} eRob joints; "
                         f"got {slaves} slaves (use --slaves {len(hw.erob_slaves)} or --plant inertia)")
    world = PrimeWorld(robot, load_calibration(hw), physics_dt=physics_dt, held=hw.sito_joints)
    return world.plant(ring_order(robot), clock=True)


def ring_order(robot: Robot) -> list[str]:
    """The eRob joints by ring position; the positions must be 0..n-1."""
    by_position = {position: joint for joint, position in robot.hardware.erob_slaves.items()}
    if sorted(by_position) != list(range(len(by_position))):
        raise PrimeError(f"joints.erob_slaves must use ring positions 0..{len(by_position) - 1}, "
                         f"got {sorted(by_position)}")
    return [by_position[i] for i in range(len(by_position))]
