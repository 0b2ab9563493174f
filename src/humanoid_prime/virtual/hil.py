"""The simulated Prime with its wrists in the loop over CAN: the real ``SitoSystem`` talks on a
python-can ``virtual`` bus to emulated Sito motors whose plants are the wrist joints of the very
MuJoCo model ``MujocoSystem`` simulates; ``MujocoSystem`` owns only the ten eRob joints.

Lockstep: every physics step of ``MujocoSystem`` is one firmware tick of the emulator (apply the
frames on the bus, run the motors' MIT law, step the world, stream feedback). The host's wrist
commands are on the bus before physics advances (components are ordered SitoSystem, MujocoSystem),
and the feedback of a control period's last physics step has reached the host's receive thread
before the next ``read``, as it would over a real 1 Mbit/s bus, where a frame takes about 130 µs.
``SitoSystem``'s clock is the emulator's firmware time, so its RX timeout counts simulated time.
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Mapping
from pathlib import Path

import can
from can.interfaces.virtual import VirtualBus

from humanoid_prime.config.calibration import Calibration, load_calibration
from humanoid_prime.config.controllers import ControllersConfig
from humanoid_prime.config.robot import Robot
from humanoid_prime.control.hardware import Lifecycle
from humanoid_prime.drivers.mujoco.system import MujocoSystem
from humanoid_prime.drivers.sito.protocol import FrameType
from humanoid_prime.drivers.sito.system import SitoSystem
from humanoid_prime.runtime.registry import ComponentSettings
from humanoid_prime.runtime.session import assemble
from humanoid_prime.virtual.plant import PrimeWorld
from humanoid_prime.virtual.sito import SitoEmulator

HOST_RECEIVE_TIMEOUT_S = 1.0  # wall time the loop waits for the host to take the feedback; then it carries on


class _HostBus(VirtualBus):
    """The host's end of the virtual bus. It counts the frames its reader has finished with: a frame is
    handled once the receive thread asks for the next one, after its listeners have stored it."""

    def __init__(self, channel: str) -> None:
        super().__init__(channel=channel)
        self.handled = 0
        self._in_hand = 0

    def recv(self, timeout: float | None = None) -> can.Message | None:
        self.handled += self._in_hand
        msg = super().recv(timeout)
        self._in_hand = 0 if msg is None else 1
        return msg


class HilSimulation:
    """``MujocoSystem`` (eRob) + ``SitoSystem`` (wrists, over CAN) + the Sito emulator, under one controller
    manager. ``start`` replaces ``manager.start``; ``close`` leaves everything shut down (use as a context
    manager)."""

    def __init__(self, robot: Robot, config: ControllersConfig, *, initial_pose: Mapping[str, float] | None = None,
                 model_path: str | Path | None = None, calibration: Calibration | None = None) -> None:
        calibration = calibration if calibration is not None else load_calibration(robot.hardware)
        self.channel = f"prime-hil-{uuid.uuid4().hex}"
        self.buses: list[can.BusABC] = []
        try:
            emulator_bus = can.Bus(interface="virtual", channel=self.channel)
            self.buses.append(emulator_bus)
            self._host_bus = _HostBus(self.channel)
            self.buses.append(self._host_bus)
            self.system = MujocoSystem(robot, physics_rate=config.physics_rate, update_rate=config.sim_update_rate,
                                       model_path=model_path, initial_pose=initial_pose,
                                       joints=robot.hardware.erob_joints, advance=self._advance)
            # The wrists of the simulated model, seen through their wiring and factory offsets (the calibration).
            world = PrimeWorld(robot, calibration, model=self.system.model, data=self.system.data)
            # The world stands still until the loop runs: start() attaches world_step.
            self.emulator = SitoEmulator.for_robot(robot, emulator_bus, world.plant(robot.hardware.sito_joints),
                                                   rate_hz=self.system.physics_rate)
            self._world_step = world.step
            self.sito = SitoSystem(robot, calibration, update_rate=config.sim_update_rate, bus=self._host_bus,
                                   clock=self._firmware_time)
            settings = ComponentSettings(robot, calibration, update_rate=config.sim_update_rate)
            self.manager = assemble(settings, config, (self.sito, self.system), clock=time.perf_counter)
        except BaseException:
            self._close_buses()
            raise

    def _firmware_time(self) -> float:
        return self.emulator.time

    def start(self) -> None:
        """The staged start while the motors' firmware runs on the wall clock (the world held still), then
        feedback aligned to the control period and the emulator handed to the physics loop."""
        emulator = self.emulator
        emulator.start()
        try:
            self.manager.start(now=self.system.sim_time)
        finally:
            emulator.stop()
        self._align_feedback()
        emulator.world_step = self._world_step

    def _align_feedback(self) -> None:
        """Tick the firmware (world still) until every motor has just streamed: from then on feedback leaves
        on the last physics step of each control period, so ``read`` sees the state ``write`` left."""
        emulator, interval_ms = self.emulator, self.sito.feedback_ms
        motors = list(emulator.motors.values())
        for _ in range(max(1, round(interval_ms * self.system.physics_rate / 1000.0))):
            before = [motor.feedback_sent for motor in motors]
            emulator.step(emulator.dt)
            if all(motor.feedback_sent > count for motor, count in zip(motors, before, strict=True)):
                break
        self._wait_for_host()

    def _advance(self, dt: float) -> None:
        """One physics step: one firmware tick, which steps the world; then the host takes the feedback."""
        emulator = self.emulator
        emulator.step(dt)
        if self._host_bus.handled < emulator.frames_sent:
            self._wait_for_host()

    def _wait_for_host(self) -> None:
        host, sito, emulator = self._host_bus, self.sito, self.emulator
        deadline = time.perf_counter() + HOST_RECEIVE_TIMEOUT_S
        while host.handled < emulator.frames_sent and sito.lifecycle is Lifecycle.ACTIVE:
            if time.perf_counter() > deadline:
                return  # the host's own RX timeout reports what it missed
            time.sleep(0)

    def frame_counts(self) -> dict[str, int]:
        """CAN frames each side sent and received, the ones that broke the protocol, the disables the motors
        took, and how many motors are enabled now (none once closed)."""
        sito, emulator = self.sito, self.emulator
        motors = emulator.motors.values()
        return {
            "host_frames_sent": sito.frames_sent,
            "host_frames_received": sito.frames_received,
            "host_send_failures": sito.send_failures,
            "host_invalid_frames": sito.invalid_frames,
            "emulator_frames_sent": emulator.frames_sent,
            "emulator_frames_received": emulator.frames_received,
            "emulator_invalid_frames": sum(motor.invalid_received for motor in motors),
            "emulator_disable_frames": sum(motor.received[FrameType.DISABLE] for motor in motors),
            "emulator_motors_enabled": sum(motor.enabled for motor in motors),
        }

    def close(self) -> None:
        """Shut the manager down (SitoSystem disables every motor), let the emulated motors take the
        disable, stop the emulator and close both buses. Safe to call more than once."""
        try:
            self.manager.shutdown()
        finally:
            try:
                self.emulator.stop()
                if self.buses:
                    self.emulator.process_pending()
            finally:
                self._close_buses()

    def _close_buses(self) -> None:
        while self.buses:
            self.buses.pop().shutdown()

    def __enter__(self) -> HilSimulation:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def build_hil_simulation(robot: Robot, config: ControllersConfig, *, initial_pose: Mapping[str, float] | None = None,
                         model_path: str | Path | None = None, calibration: Calibration | None = None
                         ) -> HilSimulation:
    """The simulated Prime with its Sito wrists behind real CAN frames (not started). ``calibration``
    defaults to the bundled prime_calibration.yaml."""
    return HilSimulation(robot, config, initial_pose=initial_pose, model_path=model_path, calibration=calibration)
