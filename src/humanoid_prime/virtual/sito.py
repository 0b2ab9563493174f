"""An emulated Sito: motors that answer on a python-can bus the way the firmware does.

Each ``SitoMotor`` parses every frame type addressed to its CAN id, runs the MIT law at the firmware
rate on a plant, and streams 0xB1/0xB2 feedback at the intervals it was told. The law uses the same
measured divisors as the host, so the emulated wrist realises exactly the stiffness and damping asked
for: ``tau = kp(q_cmd - q) + kd(qd_cmd - qd) + tau_ff``, saturated at the joint's effort limit. A
motor is limp until it is enabled with non-zero gains, and a disable (reset) makes it limp and silent.

``SitoEmulator`` owns the motors on one bus. ``step(duration)`` advances it deterministically (tests);
``start()`` runs it in a background thread at the firmware rate, paced by the wall clock (live use).
Faults: per motor drop a fraction of frames, go silent, send garbage after each feedback frame, send its feedback
late (``late_s``: each frame held that long, as a busy bus or a stalled host delivers it); for the whole bus stop
acknowledging (the host's transmit queue fills) and report bus-off.
"""

from __future__ import annotations

import queue
import random
import struct
import threading
from collections import deque
from collections.abc import Callable, Iterable
from typing import TypedDict, Unpack

import can
import numpy as np

from humanoid_prime.config.robot import Robot
from humanoid_prime.control.rate import Rate
from humanoid_prime.drivers.sito.bus import CAN_ERR_BUSOFF, CAN_ERR_CRTL
from humanoid_prime.drivers.sito.protocol import (
    COUNTS_PER_RAD,
    DATA_LENGTH,
    FEEDBACK1,
    FEEDBACK2,
    INT16_MAX,
    INT16_MIN,
    INT32_MAX,
    MODE_MIT,
    MOTOR_FRAME_TYPES,
    UNDECODED_FEEDBACK_TYPES,
    Command,
    Disable,
    Enable,
    FrameType,
    Gains,
    InvalidFrame,
    SitoModel,
    arbitration_id,
    counts_to_position,
    counts_to_velocity,
    current_mA_to_torque,
    firmware_to_kd,
    firmware_to_kp,
    parse,
    position_to_counts,
    sito_model,
    split_arbitration_id,
    torque_to_current_mA,
    velocity_to_counts,
)
from humanoid_prime.virtual.plant import InertiaPlant, Plant

FIRMWARE_RATE_HZ = 1000.0
TX_QUEUE_LENGTH = 10  # Linux default txqueuelen of a CAN interface
SUPPLY_VOLTAGE_RAW = 240  # reported as-is in 0xB1; the firmware's unit is not documented


def _saturate(value: float, low: int, high: int) -> int:
    """The pwm field's clamp (its units are not documented, so it is no protocol conversion)."""
    return min(max(round(value), low), high)


class SitoMotor:
    """One emulated Sito at ``can_id`` driving joint ``index`` of ``plant`` (its raw frame is the motor's)."""

    def __init__(self, can_id: int, plant: Plant, index: int = 0, *, model: str | SitoModel = "TA40-50",
                 torque_limit: float = 4.8, rate_hz: float = FIRMWARE_RATE_HZ, seed: int | None = None) -> None:
        self.can_id = can_id
        self.plant = plant
        self.index = index
        self.model = model if isinstance(model, SitoModel) else sito_model(model)
        self.torque_limit = torque_limit
        self.rate_hz = rate_hz
        self._rng = random.Random(can_id if seed is None else seed)
        self.ids = {t: arbitration_id(can_id, t) for t in MOTOR_FRAME_TYPES}
        # Fault injection.
        self.drop_fraction = 0.0  # of frames lost in either direction
        self.silent = False  # obeys commands but sends no feedback
        self.garbage = False  # a protocol-breaking frame after every feedback frame
        self.undocumented_feedback = False  # 0xB0 and 0xB3 frames besides 0xB1/0xB2, as a Sito may send
        self.late_s = 0.0  # each feedback frame goes out this much later than it was measured
        self.late_sent = 0
        self._held: deque[tuple[int, can.Message]] = deque()  # (firmware tick it is due, frame)
        self._ticks = 0  # firmware ticks since the motor was created (``_tick`` restarts on enable)
        # Counters a test can assert on.
        self.received: dict[FrameType, int] = {t: 0 for t in FrameType}
        self.invalid_received = 0
        self.disables = 0
        self.feedback_sent = 0
        self.undocumented_sent = 0
        self.garbage_sent = 0
        self._garbage_kind = 0
        self.reset()

    def reset(self) -> None:
        """Power-on / reset state: not enabled, no feedback, zero gains and command."""
        self.enabled = False
        self.mode = 0
        self.feedback_ms = (0, 0, 0)
        self.kp_fw = 0.0
        self.kd_fw = 0.0
        self.position_counts = 0
        self.velocity_counts = 0
        self.current_mA = 0
        self.torque = 0.0
        self._tick = 0

    @property
    def kp(self) -> float:
        """Stiffness the firmware realises now (Nm/rad)."""
        return firmware_to_kp(self.kp_fw, self.model)

    @property
    def kd(self) -> float:
        return firmware_to_kd(self.kd_fw, self.model)

    def receive(self, frame_type: int, data: bytes | bytearray) -> None:
        """Apply one frame addressed to this motor."""
        if self.drop_fraction and self._rng.random() < self.drop_fraction:
            return
        try:
            frame = parse(frame_type, data)
        except InvalidFrame:
            self.invalid_received += 1
            return
        self.received[FrameType(frame_type)] += 1
        match frame:
            case Disable():
                self.disables += 1
                self.reset()
            case Enable(mode, feedback_ms):
                self.mode = mode
                self.feedback_ms = feedback_ms
                self.enabled = mode == MODE_MIT
                self._tick = 0
                if self.enabled:
                    q = float(self.plant.q[self.index])  # hold where it is until the first command
                    self.position_counts = position_to_counts(q)
                    self.velocity_counts = 0
            case Gains(kp_fw, kd_fw):
                self.kp_fw, self.kd_fw = kp_fw, kd_fw
            case Command(current, velocity, position):
                self.current_mA, self.velocity_counts, self.position_counts = current, velocity, position

    def control(self) -> float:
        """The firmware MIT law at the current plant state (Nm); zero while not enabled."""
        if not self.enabled:
            return 0.0
        q, qd = float(self.plant.q[self.index]), float(self.plant.qd[self.index])
        torque = (self.kp * (counts_to_position(self.position_counts) - q)
                  + self.kd * (counts_to_velocity(self.velocity_counts) - qd)
                  + current_mA_to_torque(self.current_mA, self.model))
        return min(max(torque, -self.torque_limit), self.torque_limit)

    def stream(self, send: Callable[[can.Message], None]) -> None:
        """Send the feedback frames due at this tick (after the world has moved), and those held back till now."""
        self._ticks += 1
        while self._held and self._held[0][0] <= self._ticks:
            send(self._held.popleft()[1])
            self.late_sent += 1
        if not self.enabled:
            return
        for frame_type, interval_ms in ((FrameType.FEEDBACK1, self.feedback_ms[0]),
                                        (FrameType.FEEDBACK2, self.feedback_ms[1]),
                                        (FrameType.FEEDBACK3, self.feedback_ms[2])):
            if interval_ms and self._tick % max(1, round(interval_ms * self.rate_hz / 1000.0)) == 0:
                self._send_feedback(frame_type, send)
        if self.undocumented_feedback and self._tick % max(1, round(0.01 * self.rate_hz)) == 0:
            for frame_type in (FrameType.FEEDBACK0, FrameType.FEEDBACK3):  # every 10 ms, unasked
                self._send_feedback(frame_type, send)
        self._tick += 1

    def _send_feedback(self, frame_type: FrameType, send: Callable[[can.Message], None]) -> None:
        if self.silent or (self.drop_fraction and self._rng.random() < self.drop_fraction):
            return
        q, qd = float(self.plant.q[self.index]), float(self.plant.qd[self.index])
        if frame_type in UNDECODED_FEEDBACK_TYPES:  # no source documents the layout: a counter and zeros
            send(can.Message(arbitration_id=self.ids[frame_type], is_extended_id=True,
                             data=struct.pack(">I4x", self._tick & 0xFFFFFFFF)))
            self.undocumented_sent += 1
            return
        if frame_type == FrameType.FEEDBACK1:
            current, _ = torque_to_current_mA(self.torque, self.model)
            pwm = _saturate(1000.0 * self.torque / self.torque_limit, INT16_MIN, INT16_MAX)
            velocity, _ = velocity_to_counts(qd)
            data = FEEDBACK1.pack(SUPPLY_VOLTAGE_RAW, pwm, current, velocity)
        else:
            output = position_to_counts(q)
            motor = (round(q * self.model.gear * COUNTS_PER_RAD) + 2**31) % 2**32 - 2**31  # wraps on the motor
            data = FEEDBACK2.pack(motor, output)
        message = can.Message(arbitration_id=self.ids[frame_type], is_extended_id=True, data=data)
        if self.late_s > 0:
            self._held.append((self._ticks + max(1, round(self.late_s * self.rate_hz)), message))
        else:
            send(message)
        self.feedback_sent += 1
        if self.garbage:
            send(self._garbage_frame())
            self.garbage_sent += 1

    def _garbage_frame(self) -> can.Message:
        """A frame in this motor's id range that breaks the protocol, cycling through the ways it can."""
        self._garbage_kind = (self._garbage_kind + 1) % 4
        wild = FEEDBACK2.pack(INT32_MAX, INT32_MAX)
        b2 = self.ids[FrameType.FEEDBACK2]
        if self._garbage_kind == 0:  # truncated 0xB2 whose first bytes would read as a huge position
            return can.Message(arbitration_id=b2, is_extended_id=True, data=wild[:5])
        if self._garbage_kind == 1:  # unknown type
            return can.Message(arbitration_id=arbitration_id(self.can_id, 0xB7), is_extended_id=True, data=wild)
        if self._garbage_kind == 2:  # remote frame
            return can.Message(arbitration_id=b2, is_extended_id=True, is_remote_frame=True, dlc=DATA_LENGTH)
        # 0xB1 one byte short
        return can.Message(arbitration_id=self.ids[FrameType.FEEDBACK1], is_extended_id=True, data=wild[:7])


class EmulatorSettings(TypedDict, total=False):
    """``SitoEmulator``'s keyword arguments, for ``for_robot``."""

    rate_hz: float
    world_step: Callable[[float], None] | None
    log_length: int


class SitoEmulator:
    """Emulated Sito motors on one python-can bus (the caller owns the bus)."""

    def __init__(self, bus: can.BusABC, motors: Iterable[SitoMotor], *, rate_hz: float = FIRMWARE_RATE_HZ,
                 world_step: Callable[[float], None] | None = None, log_length: int = 10000) -> None:
        self.bus = bus
        self.motors: dict[int, SitoMotor] = {}
        for motor in motors:
            if motor.can_id in self.motors:
                raise ValueError(f"two emulated motors share CAN id {motor.can_id}")
            motor.rate_hz = rate_hz
            self.motors[motor.can_id] = motor
        # Each plant the motors drive is stepped once per tick with all of its motors' torques.
        self._plants = {id(m.plant): m.plant for m in self.motors.values()}
        self._torques = {key: np.zeros(plant.n) for key, plant in self._plants.items()}
        self._unbraked = {key: np.zeros(plant.n, dtype=bool) for key, plant in self._plants.items()}
        self.dt = 1.0 / rate_hz
        self.world_step = world_step
        self.time = 0.0
        self.ticks = 0
        self.frames_sent = 0
        self.frames_received = 0
        self.foreign_received = 0  # datagrams on the channel that were no CAN frame
        self.send_failures = 0
        self.log: deque[tuple[float, int, int]] = deque(maxlen=log_length)  # (time, can id, type) received
        self._acknowledge = True
        self._lock = threading.RLock()
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()  # set by stop(): wakes the paced thread at once

    @classmethod
    def for_robot(cls, robot: Robot, bus: can.BusABC, plant: Plant | None = None, *,
                  model: str = "TA40-50", **options: Unpack[EmulatorSettings]) -> SitoEmulator:
        """One motor per ``robot.hardware.mit_joints`` entry, joint ``k`` of ``plant`` driven by the ``k``-th
        Sito joint in canonical order (default: free wrist links), saturated at the joint's effort limit."""
        joints = robot.hardware.sito_joints
        plant = plant if plant is not None else InertiaPlant.wrists(len(joints))
        if plant.n != len(joints):
            raise ValueError(f"the plant has {plant.n} joints for {len(joints)} Sito motors")
        motors = [SitoMotor(robot.hardware.mit_joints[name], plant, k, model=model,
                            torque_limit=robot.joints[robot.index(name)].effort_limit)
                  for k, name in enumerate(joints)]
        return cls(bus, motors, **options)

    # --- faults ----------------------------------------------------------------------------------------

    @property
    def acknowledge(self) -> bool:
        return self._acknowledge

    @acknowledge.setter
    def acknowledge(self, value: bool) -> None:
        """With no node acknowledging, a sender's frames pile up in its transmit queue until it is full.
        On the virtual interface that queue is ours: bounded and left undrained while not acknowledging."""
        with self._lock:
            self._acknowledge = value
            rx_queue = getattr(self.bus, "queue", None)
            if isinstance(rx_queue, queue.Queue):
                with rx_queue.mutex:
                    rx_queue.maxsize = 0 if value else TX_QUEUE_LENGTH
                    rx_queue.not_full.notify_all()

    def inject_bus_off(self) -> None:
        """Report bus-off as SocketCAN does: an error frame of class CAN_ERR_BUSOFF."""
        self._send(can.Message(arbitration_id=CAN_ERR_BUSOFF | CAN_ERR_CRTL, is_extended_id=False,
                               is_error_frame=True, data=bytes(DATA_LENGTH)))

    # --- running ---------------------------------------------------------------------------------------

    def process_pending(self) -> None:
        """Apply every frame waiting on the bus (none while not acknowledging)."""
        if not self._acknowledge and isinstance(getattr(self.bus, "queue", None), queue.Queue):
            return
        while True:
            try:
                msg = self.bus.recv(0.0)
            except can.CanOperationError:  # a datagram that is no CAN frame (udp_multicast), or a socket gone:
                self.foreign_received += 1  # set aside; the frames after it wait for the next tick
                return
            if msg is None:
                return
            self.frames_received += 1
            if not self._acknowledge or msg.is_error_frame or not msg.is_extended_id:
                continue
            split = split_arbitration_id(msg.arbitration_id)
            if split is None:
                continue
            can_id, frame_type = split
            motor = self.motors.get(can_id)
            if motor is None or frame_type in MOTOR_FRAME_TYPES:
                continue  # another motor, or feedback (ours echoed back on multicast)
            self.log.append((self.time, can_id, frame_type))
            if msg.is_remote_frame:
                motor.invalid_received += 1
                continue
            motor.receive(frame_type, bytes(msg.data[:msg.dlc]))

    def step(self, duration: float) -> None:
        """Advance ``duration`` seconds of firmware time (rounded to whole firmware ticks)."""
        with self._lock:
            for _ in range(max(1, round(duration / self.dt))):
                self._tick()

    def _tick(self) -> None:
        """One firmware tick: apply the frames, run every motor's law, move the plants, stream feedback."""
        self.process_pending()
        for motor in self.motors.values():
            motor.torque = motor.control()
            self._torques[id(motor.plant)][motor.index] = motor.torque
        for key, plant in self._plants.items():
            plant.step(self._torques[key], self._unbraked[key], self.dt)
        if self.world_step is not None:
            self.world_step(self.dt)
        self.ticks += 1
        self.time = self.ticks * self.dt
        for motor in self.motors.values():
            motor.stream(self._send)

    def _send(self, msg: can.Message) -> None:
        try:
            self.bus.send(msg, timeout=0.0)
            self.frames_sent += 1
        except (can.CanError, OSError):
            self.send_failures += 1

    def start(self) -> None:
        """Run in a background thread, one firmware tick per period of the wall clock."""
        if self._thread is not None:
            return
        self._stopping.clear()
        self._thread = threading.Thread(target=self._run, name="sito-emulator", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stopping.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None

    def _run(self) -> None:
        rate = Rate(1.0 / self.dt, sleep=self._stopping.wait)
        while not self._stopping.is_set():
            rate.wait()
            with self._lock:
                self._tick()

    def __enter__(self) -> SitoEmulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

