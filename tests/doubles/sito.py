"""A Sito rig on a private virtual CAN channel: emulated motors, the host ``SitoSystem`` and a sniffer.

``rig`` runs in lockstep: the emulator is stepped explicitly and the system's clock is the emulator's
firmware time, so timeouts and intervals are exact and no test depends on the wall clock.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable

import can

from humanoid_prime.config.calibration import Calibration, identity_calibration
from humanoid_prime.config.robot import Robot
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.drivers.sito.system import SitoSystem
from humanoid_prime.virtual.plant import InertiaPlant, Plant
from humanoid_prime.virtual.sito import SitoEmulator

UPDATE_RATE = 50.0
PERIOD = 1.0 / UPDATE_RATE
SITO_IDS = (22, 23, 38, 39)


def wait_until(condition: Callable[[], bool], what: str, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.0002)


class HoldableBus(can.BusABC):
    """A virtual CAN bus whose receiving can be held: while held, frames wait in the channel, as they wait in the
    socket while a busy process does not run its receive thread."""

    def __init__(self, channel: str) -> None:
        self._inner = can.Bus(interface="virtual", channel=channel)
        self._released = threading.Event()
        self._released.set()
        self._receiving = threading.Lock()
        super().__init__(channel=channel)

    def hold(self) -> None:
        """From now on nothing is received until ``release``: a receive under way is finished first."""
        with self._receiving:
            self._released.clear()

    def release(self) -> None:
        self._released.set()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not self._released.wait(timeout):
            return None, False
        with self._receiving:
            if not self._released.is_set():
                return None, False
            return self._inner.recv(timeout), False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._inner.send(msg, timeout)

    def shutdown(self) -> None:
        self._inner.shutdown()
        super().shutdown()


class Rig:
    def __init__(self, robot: Robot, calibration: Calibration | None = None,
                 plant: Plant | None = None, update_rate: float = UPDATE_RATE, **system_options: object) -> None:
        self.robot = robot
        self.channel = f"sito-test-{uuid.uuid4().hex}"
        self.emulator_bus = can.Bus(interface="virtual", channel=self.channel)
        self.host_bus = HoldableBus(self.channel)
        self.sniffer = can.Bus(interface="virtual", channel=self.channel)
        self.plant = plant or InertiaPlant.wrists(len(robot.hardware.sito_joints))
        self.emulator = SitoEmulator.for_robot(robot, self.emulator_bus, self.plant)
        self.system = SitoSystem(robot, calibration or identity_calibration(robot.hardware),
                                 update_rate=update_rate, bus=self.host_bus, clock=lambda: self.emulator.time,
                                 **system_options)
        self.command = CommandArrays(robot.n)
        self.state = StateArrays(robot.n)
        self.idx = robot.indices("sito")
        self.period = 1.0 / update_rate

    def motor(self, can_id: int):
        return self.emulator.motors[can_id]

    def slot(self, joint: str) -> int:
        """The plant joint (and emulated motor) of a Sito joint: its place among the Sito joints."""
        return self.robot.hardware.sito_joints.index(joint)

    def activate(self) -> None:
        """Activate while the emulator runs, as on the robot; re-raise what activation raised."""
        if self.system.lifecycle.value == "unconfigured":
            self.system.configure()
        errors: list[BaseException] = []

        def run() -> None:
            try:
                self.system.activate()
            except BaseException as exc:
                errors.append(exc)

        worker = threading.Thread(target=run)
        worker.start()
        while worker.is_alive():
            self.emulator.step(0.001)
            # firmware time never runs ahead of what the host has received
            wait_until(lambda: self.drained() or not worker.is_alive(), "the host to drain its queue")
            time.sleep(0.0001)
        worker.join()
        if errors:
            raise errors[0]
        self.settle()

    def drained(self) -> bool:
        return self.system.frames_received >= self.emulator.frames_sent

    def settle(self) -> None:
        """Wait until the system's receive thread has taken every frame the emulator sent."""
        wait_until(self.drained, "the host to drain its queue")

    def tick(self, count: int = 1) -> None:
        """``count`` control periods: firmware time advances, then read() and write() as the loop does."""
        for _ in range(count):
            self.emulator.step(self.period)
            self.settle()
            self.system.read(self.emulator.time, self.state)
            self.system.write(self.emulator.time, self.command)

    def sniffed(self) -> list[can.Message]:
        """Every frame on the bus since the last call, in order."""
        frames = []
        while (msg := self.sniffer.recv(0.0)) is not None:
            frames.append(msg)
        return frames

    def host_frames(self) -> list[tuple[int, bytes]]:
        """(arbitration id, data) of the frames the host sent since the last call."""
        return [(m.arbitration_id, bytes(m.data)) for m in self.sniffed()
                if m.is_extended_id and not m.is_error_frame and (m.arbitration_id & 0xFF) in (0x00, 0x01, 0x09, 0x45)]

    def close(self) -> None:
        try:
            self.system.shutdown()
        finally:
            self.emulator.stop()
            for bus in (self.emulator_bus, self.host_bus, self.sniffer):
                bus.shutdown()


