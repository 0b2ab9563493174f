"""``MujocoSystem``: the simulated Prime, one hardware component owning all 14 joints.

The MIT law ``tau = kp(q_cmd - q) + kd(qd_cmd - qd) + tau_ff``, saturated to each joint's effort limit,
is applied by MuJoCo itself at every physics step with the live q and qd: each joint has one affine
actuator whose bias terms are ``-kp*q - kd*qd`` and whose control is ``kp*q_cmd + kd*qd_cmd + tau_ff``.
``write`` sets those per tick and advances physics by one control period, so simulated time moves
exactly ``physics_rate / update_rate`` steps per tick; the seconds those steps take are the tick's plant time
(``io_s``), as the wire and the emulator are on the buses, so the tick's cost minus them is our own CPU.

A joint with no command (a NaN position, the rest zero: a broadcaster-only run's passive command) is limp, as a
Sito without gains is. The system may own a subset of the joints (``joints``); the actuators of the others stay at
zero gain and zero control, so another component (e.g. emulated motors applying their own torque) drives them.
``advance`` replaces MuJoCo's own step, once per physics step, for whoever must run alongside physics.

The model is the robot's (``config.model``: ``data/description/prime.xml`` checked against the description, its
ranges and actuators generated from it); its arms collide with each other and with the body.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from pathlib import Path

import mujoco
import numpy as np

from humanoid_prime.config.model import load_model
from humanoid_prime.config.robot import Robot
from humanoid_prime.control.hardware import HardwareComponent
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.errors import PrimeError


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
        self._none = np.zeros(n, dtype=bool)
        # Owning every joint (a whole simulated robot), the tick reads into and writes from the manager's rows
        # directly: no copy through an index of every joint.
        self._all = owned == robot.names
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
        if self._all:
            self._qpos.take(self.qpos_adr, out=state.position)
            self._qvel.take(self.dof_adr, out=state.velocity)
            np.copyto(state.effort, self._force)
            return
        idx = self.indices
        self._qpos.take(self.qpos_adr, out=self._a)
        state.position[idx] = self._a
        self._qvel.take(self.dof_adr, out=self._a)
        state.velocity[idx] = self._a
        self._force.take(self.indices, out=self._a)
        state.effort[idx] = self._a

    def write(self, now: float, command: CommandArrays) -> None:
        u = self._u
        if self._all:
            kp, kd = command.stiffness, command.damping
            np.negative(kp, out=self._bias_kp)
            np.negative(kd, out=self._bias_kd)
            np.multiply(kp, command.position, out=u)
            np.multiply(kd, command.velocity, out=self._b)
            u += self._b
            u += command.effort
        else:
            idx, actuators = self.indices, self._actuators
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
        np.isnan(u, out=self._none)
        np.copyto(u, 0.0, where=self._none)  # no command: limp
        self._ctrl[self._actuators] = u
        advance = self.advance
        began = time.perf_counter()  # the physics is this component's plant time (``io_s``)
        if advance is None:
            mujoco.mj_step(self.model, self.data, nstep=self.substeps)
        else:
            dt = self.physics_dt
            for _ in range(self.substeps):
                advance(dt)
        self.io_s = time.perf_counter() - began
