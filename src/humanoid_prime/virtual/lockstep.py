"""The virtual Prime in this process and in virtual time: its device models on its MuJoCo world, stepped in
lockstep with the controller manager, without the wire. For runs that need many robot-minutes quickly (the
hands-free calibration on many truths); the emulator behind real buses is ``python -m humanoid_prime.virtual``.

``LockstepPrime`` is one hardware component owning all 14 joints. Like the real components it applies a
calibration (the host frame) and speaks to its devices in their raw frames; the devices are the emulator's own:

- each eRob is an ``ErobDrive`` (object dictionary with its sizes and the gate, loop gains at the realised
  efficiency, following error, 0x6072, faults), enabled in CSP at activation. Per tick it takes the command as
  ``EthercatSystem`` maps it (a NaN position keeps the last target, zero stiffness follows the joint, no offsets
  unless enabled) in whole counts and per mille, and reports position, velocity and torque the same way. SDO
  goes to the object dictionaries (``sdo_read``/``sdo_write``, ring positions as on the ring);
- each Sito is a ``SitoMotor`` fed the frames ``SitoSystem`` would send (unusable or no command: limp), and
  reports output position and phase current at the wire's resolution.

Each device's control law is a joint-space impedance (the eRob's cascaded loop with its integral at 0, the
Sito's MIT law), so MuJoCo applies it at every physics step as ``MujocoSystem`` applies the MIT law, with the
device's gains, targets and torque limit of that tick, moved into the true joint frame by the truth calibration
(``raw = direction * joint + offset``). A disabled or faulted eRob brakes: a stiff hold where the joint is.

While a joint is within ``NEAR_STOP_RAD`` of a mechanical stop the world is stepped one physics step at a time;
the effort its actuator puts into the stop beyond gravity is recorded (``contact_peak``), and the speed it met the
stop at (``touch_speed``): the truths a contact-effort cap and a contact speed are checked against.
"""

from __future__ import annotations

import math
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
from humanoid_prime.drivers.erob import objects as obj
from humanoid_prime.drivers.erob.constants import COUNTS_PER_RAD, MODE_CSP
from humanoid_prime.drivers.ethercat.errors import SdoError
from humanoid_prime.drivers.mujoco.system import MujocoSystem
from humanoid_prime.drivers.sito.protocol import COUNTS_PER_RAD as SITO_COUNTS_PER_RAD
from humanoid_prime.drivers.sito.protocol import (
    Command,
    Disable,
    Enable,
    Gains,
    counts_to_position,
    counts_to_velocity,
    current_mA_to_torque,
    kd_to_firmware,
    kp_to_firmware,
    pack,
    position_to_counts,
    torque_to_current_mA,
    velocity_to_counts,
)
from humanoid_prime.runtime.registry import ComponentSettings
from humanoid_prime.runtime.session import assemble
from humanoid_prime.sim.demo import START_POSE
from humanoid_prime.virtual.operator import WatchingOperator
from humanoid_prime.virtual.plant import Bools, Floats, Plant
from humanoid_prime.virtual.ring.drive import Cia402State, ErobDrive
from humanoid_prime.virtual.ring.od import SdoAbort
from humanoid_prime.virtual.sito import SitoMotor

NEAR_STOP_RAD = 0.02
SETTLE_S = 1.0  # after activation, before a calibration starts: the arms sag onto their drives' factory gains
BRAKE_KP = 2000.0  # Nm/rad: a closed holding brake
BRAKE_KD = 20.0
_I32 = (-0x80000000, 0x7FFFFFFF)


class _RawWrists(Plant):
    """The wrists' raw state as the emulated motors read it when they are enabled (moved by MuJoCo, not here)."""

    def step(self, torque: Floats, braked: Bools, dt: float) -> None:
        pass


def _clamp(value: float, low: float, high: float) -> float:
    return low if value < low else high if value > high else value


class LockstepPrime(HardwareComponent):
    """All 14 joints on the emulator's device models and one MuJoCo world (module docstring).

    ``calibration``: what the host applies (raw -> joint frame), as a real component does. ``truth``: the
    virtual robot's wiring and factory offsets. ``update_rate``: the controller manager's rate; each ``write``
    advances the world by one period."""

    def __init__(self, robot: Robot, calibration: Calibration, truth: Calibration, *, update_rate: float,
                 physics_rate: float = 1000.0, initial_pose: Mapping[str, float] | None = None,
                 name: str = "LockstepPrime") -> None:
        super().__init__(name, robot, robot.names)
        self.robot = robot
        self.physics = MujocoSystem(robot, physics_rate=physics_rate, update_rate=update_rate,
                                    initial_pose=initial_pose, name=f"{name}/physics")
        model = self.physics.model
        model.jnt_solref[:] = (2.0 * self.physics.physics_dt, 1.0)  # metal stops: the stiffest stable limit
        self.period = 1.0 / update_rate
        names = robot.names
        self.host_direction = calibration.direction_array(names)
        self.host_offset = calibration.offset_array(names)
        self.true_direction = truth.direction_array(names)
        self.true_offset = truth.offset_array(names)
        hw = robot.hardware
        self.erob = {j: ErobDrive(serial=hw.erob_slaves[j], kt=hw.erob_kt[j], gear=hw.erob_gear[j])
                     for j in hw.erob_joints}
        self.by_position = {hw.erob_slaves[j]: drive for j, drive in self.erob.items()}
        self._erob_index = [(robot.index(j), drive) for j, drive in self.erob.items()]
        self._wrists = _RawWrists(len(hw.sito_joints))
        self.sito = {j: SitoMotor(hw.mit_joints[j], self._wrists, k,
                                  torque_limit=robot.joints[robot.index(j)].effort_limit)
                     for k, j in enumerate(hw.sito_joints)}
        self._sito_index = [(robot.index(j), k, motor) for k, (j, motor) in enumerate(self.sito.items())]
        self._sent: dict[int, tuple[tuple[float, float], Command]] = {}  # per Sito joint: the last gains and command
        self._erob = np.array([i for i, _ in self._erob_index], dtype=np.intp)
        self._sito = np.array([i for i, _, _ in self._sito_index], dtype=np.intp)
        self._joint_of = {hw.erob_slaves[j]: robot.index(j) for j in hw.erob_joints}
        self._rated = np.array([drive.rated_torque_nm for _, drive in self._erob_index])
        self._nm_per_mA = np.array([motor.model.nm_per_mA for _, _, motor in self._sito_index])
        self._braked = np.ones(len(self._erob_index), dtype=bool)
        self._enabled = np.zeros(len(self._sito_index), dtype=bool)
        n = robot.n
        self._last_command = np.full((5, n), np.nan)
        self._dirty = np.ones(n, dtype=bool)
        self.law = CommandArrays(n)  # the devices' laws in the true joint frame, what MuJoCo applies
        self.true_state = StateArrays(n)
        self.raw_q = np.zeros(n)
        self.raw_qd = np.zeros(n)
        self.raw_torque = np.zeros(n)
        self.limit = np.array([j.effort_limit for j in robot.joints])
        self.contact_peak = np.zeros(n)  # per joint: the most effort beyond gravity its actuator put into a stop
        self.touch_speed = np.zeros(n)  # per joint: the fastest it met a stop at (rad/s)
        self._touching = np.zeros(n, dtype=bool)
        self._dof = self.physics.dof_adr
        self._lower, self._upper = robot.lower, robot.upper
        self.sim_time = 0.0

    # ---- lifecycle -----------------------------------------------------------------------------------------
    def on_activate(self) -> None:
        self.physics.configure()
        self.physics.activate()
        self._sense()
        for i, drive in self._erob_index:
            drive.target_position.value = round(self.raw_q[i] * COUNTS_PER_RAD)  # enabled where it is
            drive.mode.value = MODE_CSP
            drive.mode_display.value = MODE_CSP
            drive.state = Cia402State.OPERATION_ENABLED
        for i, k, motor in self._sito_index:
            self._wrists.q[k] = self.raw_q[i]
            motor.receive(*pack(Gains(0.0, 0.0)))  # as SitoSystem activates them: limp, then enabled
            motor.receive(*pack(Enable(9, (1, 1, 0))))

    def on_deactivate(self) -> None:
        for _, drive in self._erob_index:
            drive.state = Cia402State.SWITCH_ON_DISABLED
        for _, _, motor in self._sito_index:
            motor.receive(*pack(Disable()))
        self._sent.clear()
        self._dirty[:] = True

    # ---- faults a test injects -----------------------------------------------------------------------------
    def inject_fault(self, joint: str, code: int) -> None:
        """Fault the eRob of ``joint`` with ``code`` (0x603F), as the ring emulator's fault injection does."""
        self.erob[joint].fault(code)
        self._dirty[self.robot.index(joint)] = True

    # ---- SDO ------------------------------------------------------------------------------------------------
    def sdo_read(self, position: int, index: int, sub_index: int) -> bytes:
        try:
            return self._drive(position, index, sub_index).od.upload(index, sub_index)
        except SdoAbort as exc:
            raise SdoError(position, index, sub_index, f"aborted with 0x{exc.code:08X} ({exc})", exc.code) from None

    def sdo_write(self, position: int, index: int, sub_index: int, data: bytes) -> None:
        try:
            self._drive(position, index, sub_index).od.download(index, sub_index, bytes(data))
            self._dirty[self._joint_of[position]] = True
        except SdoAbort as exc:
            raise SdoError(position, index, sub_index, f"aborted with 0x{exc.code:08X} ({exc})", exc.code) from None

    def _drive(self, position: int, index: int, sub_index: int) -> ErobDrive:
        drive = self.by_position.get(position)
        if drive is None:
            raise SdoError(position, index, sub_index, "no slave at that ring position")
        return drive

    # ---- per tick -------------------------------------------------------------------------------------------
    # A device whose command, state and settings have not changed since the last tick keeps its law; its frames
    # would carry what it already holds. Feedback is computed for all joints at once, at the wire's resolution.
    def read(self, now: float, state: StateArrays) -> None:
        d, o = self.host_direction, self.host_offset
        e, w = self._erob, self._sito
        counts = np.round(self.raw_q[e] * COUNTS_PER_RAD)  # 0x6064
        state.position[e] = d[e] * (counts / COUNTS_PER_RAD - o[e])
        state.velocity[e] = d[e] * np.round(self.raw_qd[e] * COUNTS_PER_RAD) / COUNTS_PER_RAD  # 0x606C
        per_mille = np.clip(np.round(self.raw_torque[e] / self._rated * 1000.0), -0x8000, 0x7FFF)  # 0x6077
        per_mille[self._braked] = 0.0
        state.effort[e] = d[e] * per_mille / 1000.0 * self._rated
        counts = np.round(self.raw_q[w] * SITO_COUNTS_PER_RAD)  # 0xB2 output position
        state.position[w] = d[w] * (counts / SITO_COUNTS_PER_RAD - o[w])
        speed = np.clip(np.round(self.raw_qd[w] * SITO_COUNTS_PER_RAD), -0x8000, 0x7FFF)  # 0xB1 velocity
        state.velocity[w] = d[w] * speed / SITO_COUNTS_PER_RAD
        current = np.clip(np.round(self.raw_torque[w] / self._nm_per_mA), -0x8000, 0x7FFF)  # 0xB1 phase current
        state.effort[w] = np.where(self._enabled, d[w] * current * self._nm_per_mA, 0.0)
        for i, drive in self._erob_index:
            key = f"ring{drive.serial}/fault"
            faulted = drive.state == Cia402State.FAULT
            if faulted != (key in self.flags):
                if faulted:
                    self.set_flag(key, f"{self.robot.names[i]} (ring {drive.serial}): fault, error "
                                       f"0x{int(drive.error_code.value):04X}")
                else:
                    self.clear_flag(key)

    def write(self, now: float, command: CommandArrays) -> None:
        data, last = command.data, self._last_command
        changed = (np.any((data != last) & ~(np.isnan(data) & np.isnan(last)), axis=0) | self._dirty).tolist()
        np.copyto(last, data)
        q_counts = np.round(self.raw_q * COUNTS_PER_RAD).tolist()
        raw_q, raw_qd = self.raw_q.tolist(), self.raw_qd.tolist()
        braked = self._braked
        for k, (i, drive) in enumerate(self._erob_index):
            follows = command.stiffness[i] == 0.0 and math.isfinite(command.position[i])  # moves with the joint
            if changed[i] or drive.braked != braked[k] or follows:
                self._erob_command(i, drive, command, int(q_counts[i]))
                self._erob_law(k, i, drive)
            drive.step(raw_q[i], raw_qd[i], self.period)  # its state machine and following error
            if drive.braked != braked[k]:
                self._erob_law(k, i, drive)
        for i, k, motor in self._sito_index:
            if changed[i] and self._sito_command(i, k, motor, command):
                self._sito_law(k, i, motor)
        self._dirty[:] = False
        self._step(now)
        self._sense()
        torque = self.raw_torque.tolist()
        for k, (i, drive) in enumerate(self._erob_index):
            drive.torque_nm = 0.0 if braked[k] else torque[i]

    def _erob_law(self, k: int, i: int, drive: ErobDrive) -> None:
        """The drive's loop as a joint impedance in the true frame, with its torque limit."""
        law, td, to = self.law, self.true_direction[i], self.true_offset[i]
        forcerange = self.physics.model.actuator_forcerange
        self._braked[k] = drive.braked
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

    def _sito_law(self, k: int, i: int, motor: SitoMotor) -> None:
        """The firmware's MIT law in the true frame."""
        law, td, to = self.law, self.true_direction[i], self.true_offset[i]
        self._enabled[k] = motor.enabled
        if motor.enabled:
            law.position[i] = td * (counts_to_position(motor.position_counts) - to)
            law.velocity[i] = td * counts_to_velocity(motor.velocity_counts)
            law.effort[i] = td * current_mA_to_torque(motor.current_mA, motor.model)
            law.stiffness[i], law.damping[i] = motor.kp, motor.kd
        else:
            law.data[:, i] = 0.0
        self.physics.model.actuator_forcerange[i] = (-motor.torque_limit, motor.torque_limit)

    def _erob_command(self, i: int, drive: ErobDrive, command: CommandArrays, actual: int) -> None:
        """The CSP target and offsets as ``EthercatSystem`` writes them (whole counts, per mille)."""
        d, o = self.host_direction[i], self.host_offset[i]
        position = command.position[i]
        if not drive.csp_enabled:
            drive.target_position.value = actual
            drive.velocity_offset.value = 0
            drive.torque_offset.value = 0
            return
        if math.isfinite(position):
            target = actual if command.stiffness[i] == 0.0 else round((d * position + o) * COUNTS_PER_RAD)
            drive.target_position.value = int(_clamp(target, *_I32))
        velocity, effort = command.velocity[i], command.effort[i]
        drive.velocity_offset.value = int(_clamp(round(d * velocity * COUNTS_PER_RAD), *_I32)) \
            if math.isfinite(velocity) else 0
        limit = obj.TORQUE_OFFSET_LIMIT_PER_MILLE
        drive.torque_offset.value = int(_clamp(round(d * effort / drive.rated_torque_nm * 1000.0), -limit, limit)) \
            if math.isfinite(effort) else 0

    def _sito_command(self, i: int, k: int, motor: SitoMotor, command: CommandArrays) -> bool:
        """The gains and the MIT command frames ``SitoSystem`` sends; False when they carry what the motor holds."""
        d, o = self.host_direction[i], self.host_offset[i]
        position, velocity, effort = command.position[i], command.velocity[i], command.effort[i]
        kp, kd = command.stiffness[i], command.damping[i]
        if not (math.isfinite(position) and math.isfinite(velocity) and math.isfinite(effort)
                and math.isfinite(kp) and math.isfinite(kd) and kp >= 0 and kd >= 0):
            position = velocity = effort = kp = kd = 0.0
        self._wrists.q[k] = self.raw_q[i]
        gains = (kp_to_firmware(kp, motor.model), kd_to_firmware(kd, motor.model))
        current, _ = torque_to_current_mA(d * effort, motor.model)
        speed, _ = velocity_to_counts(d * velocity)
        frame = Command(current, speed, position_to_counts(d * position + o))
        if self._sent.get(i) == (gains, frame):
            return False
        if self._sent.get(i, (None,))[0] != gains:
            motor.receive(*pack(Gains(*gains)))
        motor.receive(*pack(frame))
        self._sent[i] = (gains, frame)
        return True

    def _step(self, now: float) -> None:
        """One control period of physics; one step at a time near a stop (or one it can reach within the period),
        recording the contact effort and speed."""
        q = self.true_state.position
        reach = NEAR_STOP_RAD + 2.0 * np.abs(self.true_state.velocity) * self.period
        near = (q - self._lower < reach) | (self._upper - q < reach)
        self.physics.advance = self._step_watching if near.any() else None
        self.physics.write(now, self.law)
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

    def _sense(self) -> None:
        """The world's true state, and each joint's in its device's raw frame."""
        self.physics.read(self.sim_time, self.true_state)
        td, to = self.true_direction, self.true_offset
        true = self.true_state
        np.multiply(td, true.position, out=self.raw_q)
        self.raw_q += to
        np.multiply(td, true.velocity, out=self.raw_qd)
        np.multiply(td, true.effort, out=self.raw_torque)

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
    manager = assemble(settings, config, (rig,), broadcaster_only=True)
    manager.start(now=rig.sim_time)
    try:
        auto: AutoCalibration | None = None

        def step() -> None:
            manager.tick(now=rig.sim_time)
            if each_tick is not None and auto is not None:
                each_tick(rig, auto)

        for _ in range(round(SETTLE_S * config.update_rate)):  # the arms settle on their drives' own gains first
            manager.tick(now=rig.sim_time)
        rings = {j: (rig, robot.hardware.erob_slaves[j]) for j in robot.hardware.erob_joints}
        auto = AutoCalibration(manager, prior, joints, rings=rings, ticks=SteppedTicks(step),
                               operator=WatchingOperator(robot, rig.true_positions), assume_direction=assume_direction,
                               measure=measure, offset_range=offset_range, journal=journal)
        auto.attach()
        return auto.run(), rig
    finally:
        manager.shutdown()
