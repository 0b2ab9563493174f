"""The virtual Prime in this process and in virtual time: its device models on its MuJoCo world, stepped in
lockstep with the controller manager, without a wire. For runs that need many robot-minutes quickly (the
hands-free calibration on many truths); the emulator behind real buses is ``python -m humanoid_prime.virtual``.

``LockstepPrime`` is the robot, not a component: the host drives it through the two components a run on the real
robot uses (``components``: ``EthercatSystem`` and ``SitoSystem``, with the calibration they apply), each on an
in-process bus, so every command takes the host's own per-tick path (the compiled ``EcTick`` and ``SitoTick``)
and nothing of the host's command mapping is restated here. The devices are the emulator's own:

- each eRob is an ``ErobDrive`` (object dictionary with its sizes and the gate, loop gains at the realised
  efficiency, following error, 0x6072, faults) behind ``LockstepRing``, an ``EthercatMaster`` whose exchange hands
  the process image to the drives' objects in Prime's PDO layout and their inputs back, and whose SDOs go to their
  object dictionaries. The ring comes up and the drives are enabled by the host's own bring-up and enabling;
- each Sito is a ``SitoMotor`` behind ``LockstepCan``, a python-can bus on which a frame the host sends reaches
  the motors as it is sent, and the motors' feedback reaches the host's receive thread before the next tick.
  A motor answers its enable with its first feedback, then streams at the intervals it was told (one firmware
  tick per control period).

``step`` runs once per control period, after every component's ``write`` (the controller manager's end of tick).
Each device's control law is a joint-space impedance (the eRob's cascaded loop with its integral at 0, the Sito's
MIT law), so MuJoCo applies it at every physics step as ``MujocoSystem`` applies the MIT law, with the device's
gains, targets and torque limit of that tick, moved into the true joint frame by the truth calibration
(``raw = direction * joint + offset``). A disabled or faulted eRob brakes: a stiff hold where the joint is. Then
the devices measure the moved world at their own resolution.

While a joint is within ``NEAR_STOP_RAD`` of a mechanical stop the world is stepped one physics step at a time;
the effort its actuator puts into the stop beyond gravity is recorded (``contact_peak``), and the speed it met the
stop at (``touch_speed``): the truths a contact-effort cap and a contact speed are checked against. Two bodies of
different classes that touch (an arm the other arm or the body) are recorded with when (``body_contacts``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import mujoco
import numpy as np

from humanoid_prime.calibration.auto import AutoCalibration
from humanoid_prime.calibration.journal import OverrideJournal
from humanoid_prime.calibration.plan import OFFSET_RANGE_RAD
from humanoid_prime.calibration.report import AutoResult
from humanoid_prime.calibration.sequence import SteppedTicks
from humanoid_prime.calibration.workflow import identity_from
from humanoid_prime.config.calibration import Calibration
from humanoid_prime.config.controllers import ControllersConfig
from humanoid_prime.config.robot import Robot
from humanoid_prime.control.hardware import HardwareComponent
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.drivers.erob.constants import COUNTS_PER_RAD
from humanoid_prime.drivers.ethercat.system import EthercatSystem
from humanoid_prime.drivers.mujoco.system import MujocoSystem
from humanoid_prime.drivers.sito.protocol import (
    FrameType,
    counts_to_position,
    counts_to_velocity,
    current_mA_to_torque,
)
from humanoid_prime.drivers.sito.system import SitoSystem
from humanoid_prime.runtime.registry import ComponentSettings
from humanoid_prime.runtime.session import assemble
from humanoid_prime.sim.demo import START_POSE
from humanoid_prime.virtual.lockstep_buses import LockstepCan, LockstepRing
from humanoid_prime.virtual.operator import WatchingOperator
from humanoid_prime.virtual.plant import Bools, Floats, Plant
from humanoid_prime.virtual.ring.drive import ErobDrive
from humanoid_prime.virtual.sito import SitoEmulator, SitoMotor

NEAR_STOP_RAD = 0.02
SETTLE_S = 1.0  # after activation, before a calibration starts: the arms sag onto their drives' factory gains
BRAKE_KP = 2000.0  # Nm/rad: a closed holding brake
BRAKE_KD = 20.0


class _RawWrists(Plant):
    """The wrists' raw state as the emulated motors measure it (moved by MuJoCo, not here)."""

    def step(self, torque: Floats, braked: Bools, dt: float) -> None:
        pass


class LockstepPrime:
    """All 14 joints on the emulator's device models and one MuJoCo world (module docstring).

    ``calibration``: what the host's components apply (raw -> joint frame). ``truth``: the virtual robot's wiring
    and factory offsets. ``update_rate``: the controller manager's rate; each ``step`` advances the world by one
    period. ``components`` are the host's, for the controller manager; ``close()`` after it has shut them down."""

    def __init__(self, robot: Robot, calibration: Calibration, truth: Calibration, *, update_rate: float,
                 physics_rate: float = 1000.0, initial_pose: Mapping[str, float] | None = None) -> None:
        self.robot = robot
        self.physics = MujocoSystem(robot, physics_rate=physics_rate, update_rate=update_rate,
                                    initial_pose=initial_pose, name="LockstepPrime/physics")
        model = self.physics.model
        model.jnt_solref[:] = (2.0 * self.physics.physics_dt, 1.0)  # metal stops: the stiffest stable limit
        self.period = 1.0 / update_rate
        names = robot.names
        self.true_direction = truth.direction_array(names)
        self.true_offset = truth.offset_array(names)
        hw = robot.hardware
        self.erob = {j: ErobDrive(serial=hw.erob_slaves[j], kt=hw.erob_kt[j], gear=hw.erob_gear[j])
                     for j in sorted(hw.erob_joints, key=lambda j: hw.erob_slaves[j])}  # ring order
        self._erob_index = [(robot.index(j), drive) for j, drive in self.erob.items()]
        self._wrists = _RawWrists(len(hw.sito_joints))
        self.sito = {j: SitoMotor(hw.mit_joints[j], self._wrists, k,
                                  torque_limit=robot.joints[robot.index(j)].effort_limit)
                     for k, j in enumerate(hw.sito_joints)}
        self._sito_index = [(robot.index(j), k, motor) for k, (j, motor) in enumerate(self.sito.items())]
        n = robot.n
        self.law = CommandArrays(n)  # the devices' laws in the true joint frame, what MuJoCo applies
        self.true_state = StateArrays(n)
        self.raw_q = np.zeros(n)
        self.raw_qd = np.zeros(n)
        self.raw_torque = np.zeros(n)
        self.limit = np.array([j.effort_limit for j in robot.joints])
        self.contact_peak = np.zeros(n)  # per joint: the most effort beyond gravity its actuator put into a stop
        self.touch_speed = np.zeros(n)  # per joint: the fastest it met a stop at (rad/s)
        self._touching = np.zeros(n, dtype=bool)
        self.body_contacts: dict[tuple[str, str], float] = {}  # two bodies of different classes touching: first time
        self._dof = self.physics.dof_adr
        self._lower, self._upper = robot.lower, robot.upper
        self.physics.configure()
        self.physics.activate()
        self.sim_time = self.physics.sim_time
        self._sense()

        self.ring = LockstepRing(tuple(self.erob.values()), update_rate=update_rate)
        self._ring_joint = np.array([i for i, _ in self._erob_index], dtype=np.intp)
        self.can = LockstepCan(self._deliver)
        self._motors = SitoEmulator(self.can.motors, self.sito.values(), rate_hz=update_rate)
        self._measure()
        self.ethercat = EthercatSystem(robot, calibration, update_rate=update_rate, master=self.ring, emulated=True)
        self.wrists = SitoSystem(robot, calibration, update_rate=update_rate, bus=self.can.host,
                                 clock=lambda: self.sim_time, emulated=True)
        self.components: tuple[HardwareComponent, ...] = (self.ethercat, self.wrists)

    def close(self) -> None:
        self.can.close()
        self.physics.shutdown()

    # ---- faults a test injects -----------------------------------------------------------------------------
    def inject_fault(self, joint: str, code: int) -> None:
        """Fault the eRob of ``joint`` with ``code`` (0x603F), as the ring emulator's fault injection does."""
        with self.ring.lock:
            self.erob[joint].fault(code)

    # ---- the wire ---------------------------------------------------------------------------------------------
    def _deliver(self) -> None:
        """The frames the host just sent reach the motors; a motor enabled by one answers with its first feedback
        (its firmware's tick 0)."""
        enables = [motor.received[FrameType.ENABLE] for motor in self.sito.values()]
        self._motors.process_pending()
        for motor, before in zip(self.sito.values(), enables, strict=True):
            if motor.enabled and motor.received[FrameType.ENABLE] != before:
                motor.stream(self.can.motors.send)

    # ---- per tick -------------------------------------------------------------------------------------------
    def step(self) -> None:
        """One control period: the devices act on what they hold, the world moves, the devices measure it."""
        raw_q, raw_qd = self.raw_q.tolist(), self.raw_qd.tolist()
        with self.ring.lock:
            for i, drive in self._erob_index:
                drive.step(raw_q[i], raw_qd[i], self.period)  # its state machine and following error
                self._erob_law(i, drive)
        for i, _, motor in self._sito_index:
            self._sito_law(i, motor)
        self._advance()
        self._watch_bodies()
        self._sense()
        self._measure()
        for motor in self.sito.values():
            motor.stream(self.can.motors.send)
        self.can.drain()

    def _erob_law(self, i: int, drive: ErobDrive) -> None:
        """The drive's loop as a joint impedance in the true frame, with its torque limit."""
        law, td, to = self.law, self.true_direction[i], self.true_offset[i]
        forcerange = self.physics.model.actuator_forcerange
        if drive.braked:
            law.position[i], law.velocity[i], law.effort[i] = self.true_state.position[i], 0.0, 0.0
            law.stiffness[i], law.damping[i] = BRAKE_KP, BRAKE_KD
            forcerange[i] = (-3.0 * self.limit[i], 3.0 * self.limit[i])
            return
        kp, kd, _ = drive.gains
        rated = drive.rated_torque_nm
        law.position[i] = td * (int(drive.target_position.value) / COUNTS_PER_RAD - to)
        law.velocity[i] = td * int(drive.velocity_offset.value) / COUNTS_PER_RAD
        law.effort[i] = td * int(drive.torque_offset.value) / 1000.0 * rated
        law.stiffness[i], law.damping[i] = kp, kd
        limit = int(drive.max_torque.value) / 1000.0 * rated
        forcerange[i] = (-limit, limit)

    def _sito_law(self, i: int, motor: SitoMotor) -> None:
        """The firmware's MIT law in the true frame."""
        law, td, to = self.law, self.true_direction[i], self.true_offset[i]
        if motor.enabled:
            law.position[i] = td * (counts_to_position(motor.position_counts) - to)
            law.velocity[i] = td * counts_to_velocity(motor.velocity_counts)
            law.effort[i] = td * current_mA_to_torque(motor.current_mA, motor.model)
            law.stiffness[i], law.damping[i] = motor.kp, motor.kd
        else:
            law.data[:, i] = 0.0
        self.physics.model.actuator_forcerange[i] = (-motor.torque_limit, motor.torque_limit)

    def _advance(self) -> None:
        """One control period of physics; one step at a time near a stop (or one it can reach within the period),
        recording the contact effort and speed."""
        q = self.true_state.position
        reach = NEAR_STOP_RAD + 2.0 * np.abs(self.true_state.velocity) * self.period
        near = (q - self._lower < reach) | (self._upper - q < reach)
        self.physics.advance = self._step_watching if near.any() else None
        self.physics.write(self.sim_time, self.law)
        self.sim_time = self.physics.sim_time

    def _step_watching(self, dt: float) -> None:
        model, data = self.physics.model, self.physics.data
        mujoco.mj_step(model, data)
        q = data.qpos[self.physics.qpos_adr]
        beyond = (self._lower - q, q - self._upper)
        touching_any = np.zeros(self.robot.n, dtype=bool)
        for side, depth in ((-1.0, beyond[0]), (1.0, beyond[1])):
            touching = depth > -1e-4
            if touching.any():
                push = side * (data.actuator_force - data.qfrc_bias[self._dof])
                np.maximum(self.contact_peak, np.where(touching, push, 0.0), out=self.contact_peak)
                touching_any |= touching
        met = touching_any & ~self._touching
        if met.any():  # the speed it came in at, the step it met the stop
            np.maximum(self.touch_speed, np.where(met, np.abs(data.qvel[self._dof]), 0.0), out=self.touch_speed)
        self._touching = touching_any

    def _watch_bodies(self) -> None:
        """Two bodies of different classes (an arm against the other arm or the body) in contact after this period:
        recorded with the first time they were (a calibration must never bring them together)."""
        model, data = self.physics.model, self.physics.data
        for k in range(data.ncon):
            contact = data.contact[k]
            a, b = int(contact.geom1), int(contact.geom2)
            if model.geom_contype[a] == model.geom_contype[b]:
                continue
            names = tuple(sorted(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.geom_bodyid[g])) or "?"
                                 for g in (a, b)))
            self.body_contacts.setdefault((names[0], names[1]), self.sim_time)

    def _sense(self) -> None:
        """The world's true state, and each joint's in its device's raw frame."""
        self.physics.read(self.sim_time, self.true_state)
        td, to = self.true_direction, self.true_offset
        true = self.true_state
        np.multiply(td, true.position, out=self.raw_q)
        self.raw_q += to
        np.multiply(td, true.velocity, out=self.raw_qd)
        np.multiply(td, true.effort, out=self.raw_torque)

    def _measure(self) -> None:
        """What each device measures of the world: the joint, and the torque it applied (none while braked)."""
        ring = self.ring
        with ring.lock:
            ring.q[:] = self.raw_q[self._ring_joint]
            ring.qd[:] = self.raw_qd[self._ring_joint]
            torque = self.raw_torque.tolist()
            for i, drive in self._erob_index:
                drive.torque_nm = 0.0 if drive.braked else torque[i]
        for i, k, motor in self._sito_index:
            self._wrists.q[k], self._wrists.qd[k] = self.raw_q[i], self.raw_qd[i]
            motor.torque = self.raw_torque[i]

    def true_positions(self) -> dict[str, float]:
        """Every joint's true angle (description frame)."""
        return {j: float(self.true_state.position[i]) for i, j in enumerate(self.robot.names)}


def calibrate_in_lockstep(robot: Robot, config: ControllersConfig, prior: Calibration, truth: Calibration,
                          joints: Sequence[str], *, physics_rate: float = 250.0,
                          initial_pose: Mapping[str, float] | None = None, assume_direction: bool = False,
                          measure: bool = False, offset_range: float = OFFSET_RANGE_RAD,
                          journal: OverrideJournal | None = None,
                          each_tick: Callable[[LockstepPrime, AutoCalibration], None] | None = None,
                          ) -> tuple[AutoResult, LockstepPrime]:
    """``prime calibrate --auto`` of ``joints`` on a ``LockstepPrime`` with the virtual robot's ``truth``, in
    virtual time: the host frame is ``prior``'s (its directions, offsets 0), the operator watches the virtual
    robot, ``each_tick`` runs after every tick (a test injecting a fault); ``measure``: the realised impedance
    too; ``journal``: where the eRob overrides are recorded. Returns the result and the rig, shut down (drives
    disabled, wrists off)."""
    host = identity_from(prior)
    rig = LockstepPrime(robot, host, truth, update_rate=config.update_rate, physics_rate=physics_rate,
                        initial_pose=START_POSE if initial_pose is None else initial_pose)
    settings = ComponentSettings(robot, host, update_rate=config.update_rate)
    manager = assemble(settings, config, rig.components, broadcaster_only=True)
    manager.add_end_of_tick(rig.step)
    try:
        manager.start(now=rig.sim_time)
        auto: AutoCalibration | None = None

        def step() -> None:
            manager.tick(now=rig.sim_time)
            if each_tick is not None and auto is not None:
                each_tick(rig, auto)

        for _ in range(round(SETTLE_S * config.update_rate)):  # the arms settle on their drives' own gains first
            manager.tick(now=rig.sim_time)
        rings = {j: (rig.ring, robot.hardware.erob_slaves[j]) for j in robot.hardware.erob_joints}
        auto = AutoCalibration(manager, prior, joints, rings=rings, ticks=SteppedTicks(step),
                               operator=WatchingOperator(robot, rig.true_positions), assume_direction=assume_direction,
                               measure=measure, offset_range=offset_range, journal=journal)
        auto.attach()
        return auto.run(), rig
    finally:
        manager.shutdown()
        rig.close()
